"""Admissible grid edges and the tetromino seeds: their four-ray fits, the bound that skips hopeless seeds, their
sorted order."""

from __future__ import annotations

import numba as nb
import numpy as np

from ppe_ros.core.fitting import fit4, fit_rays
from ppe_ros.core.ppe.intrinsics import _float_bits
from ppe_ros.core.ppe.layout import _FIT_ITERATIONS, _FIT_TOLERANCE, TETROMINO_OFFSETS
from ppe_ros.core.ppe.memory import _reusable
from ppe_ros.core.scan import RayScan
from ppe_ros.core.sensor import SEED_SHAPE_NAMES

# seeds
# --------------------------------------------------------------------------------------------


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _seed_rays(idx, anchor, o0, o1, o2, o3):
    """Write the ray ids of the seed at anchor with the tetromino's id offsets o0..o3 into idx[:4]."""
    idx[0] = anchor + o0
    idx[1] = anchor + o1
    idx[2] = anchor + o2
    idx[3] = anchor + o3


#: The tetromino configs (rows of TETROMINO_OFFSETS) that seed planes, by GreedyOptions.seed_shapes: 'all'
#: the paper's 17 (every tetromino but the straight I), 'square' the O alone (config 0).
SEED_SHAPES = dict(zip(SEED_SHAPE_NAMES, (np.arange(17, dtype=np.int64), np.zeros(1, dtype=np.int64)), strict=True))

#: Anchors per block of the vectorised seed loop, and the valid seeds a block needs for it (the
#: vectorised fit of 16 anchors costs about as much as two general fits).
_SEED_BLOCK = 16
_SEED_BLOCK_MIN = 3


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _tetromino_edges(offsets, width):
    """Internal edges of each tetromino as (id offset of the edge's first cell, 0 right / 1 down), (17, 4, 2).

    The O has four internal edges, the others three (their fourth entry repeats the first).
    """
    edges = np.empty((len(offsets), 4, 2), np.int64)
    for c in range(len(offsets)):
        n = 0
        for t in range(4):
            for u in range(4):
                dr = offsets[c, u, 0] - offsets[c, t, 0]
                dc = offsets[c, u, 1] - offsets[c, t, 1]
                if (dr == 0 and dc == 1) or (dr == 1 and dc == 0):  # u right of / below t
                    edges[c, n, 0] = offsets[c, t, 0] * width + offsets[c, t, 1]
                    edges[c, n, 1] = 0 if dc == 1 else 1
                    n += 1
        for m in range(n, 4):
            edges[c, m, 0] = edges[c, 0, 0]
            edges[c, m, 1] = edges[c, 0, 1]
    return edges


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _positive_definite(a00, a01, a02, a11, a12, a22):
    """True if the symmetric 3x3 matrix is positive definite (its Cholesky factorisation has positive pivots)."""
    if not a00 > 0.0:
        return False
    l10 = a01 / a00
    l20 = a02 / a00
    b11 = a11 - l10 * a01
    if not b11 > 0.0:
        return False
    b12 = a12 - l20 * a01
    return a22 - l20 * a02 - b12 * b12 / b11 > 0.0


#: Values of t = |n . mean direction| at which _seed_exceeds tests its bound (see there).
_SEED_BOUND_T = (1.0, 0.3, 0.1, 0.03, 0.01)


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _seed_exceeds(endpoints, directions, idx, cutoff):
    """True if every plane leaves the 4 rays idx[:4] a radial SSE (m^2) above cutoff (False: may not).

    A plane n . x = d (unit n) leaves ray k the radial residual (n . p_k - d) / (n . v_k). With
    the endpoints' scatter matrix S about their mean, the mean direction u and
    delta = max_k |v_k - u|: |n . v_k| <= t + delta with t = |n . u|, so the radial SSE is at
    least n'Sn / (t + delta)^2. Young's inequality, (t + delta)^2 <= (1 + eps) t^2 + (1 + 1/eps) delta^2
    for every eps > 0, turns "n'Sn > c (t + delta)^2 for every n" into a sufficient test: the matrix
    S - c (1 + eps) u u' - c (1 + 1/eps) delta^2 I is positive definite. It is tried at
    eps = delta / t for the t of _SEED_BOUND_T (the tightest where the best plane has |n . u| = t:
    grazing rays have small t), and at eps = inf in the form S - c max|v_k|^2 I (|n . v_k| <= |v_k|: 1 for
    unit directions; directions scaled by a sensor model's sigma_k are longer or shorter). The rays of a
    seed are neighbours, so delta is about the grid's angular step and the test is nearly as tight
    as the radial fit for seeds whose SSE is far above c. c exceeds cutoff by 1e-9 of itself and
    1e-12 of S's trace, far more than the rounding of S and of the factorisation.
    """
    m0 = 0.25 * (endpoints[idx[0], 0] + endpoints[idx[1], 0] + endpoints[idx[2], 0] + endpoints[idx[3], 0])
    m1 = 0.25 * (endpoints[idx[0], 1] + endpoints[idx[1], 1] + endpoints[idx[2], 1] + endpoints[idx[3], 1])
    m2 = 0.25 * (endpoints[idx[0], 2] + endpoints[idx[1], 2] + endpoints[idx[2], 2] + endpoints[idx[3], 2])
    u0 = 0.25 * (directions[idx[0], 0] + directions[idx[1], 0] + directions[idx[2], 0] + directions[idx[3], 0])
    u1 = 0.25 * (directions[idx[0], 1] + directions[idx[1], 1] + directions[idx[2], 1] + directions[idx[3], 1])
    u2 = 0.25 * (directions[idx[0], 2] + directions[idx[1], 2] + directions[idx[2], 2] + directions[idx[3], 2])
    s00 = s01 = s02 = s11 = s12 = s22 = 0.0
    delta2 = 0.0
    vmax2 = 0.0  # |n . v_k| <= |v_k|: unit directions, or scaled by the rays' noise (sensor models)
    for t in range(4):
        vmax2 = max(vmax2, directions[idx[t], 0] ** 2 + directions[idx[t], 1] ** 2 + directions[idx[t], 2] ** 2)
        x = endpoints[idx[t], 0] - m0
        y = endpoints[idx[t], 1] - m1
        z = endpoints[idx[t], 2] - m2
        s00 += x * x
        s01 += x * y
        s02 += x * z
        s11 += y * y
        s12 += y * z
        s22 += z * z
        dx = directions[idx[t], 0] - u0
        dy = directions[idx[t], 1] - u1
        dz = directions[idx[t], 2] - u2
        delta2 = max(delta2, dx * dx + dy * dy + dz * dz)
    c = cutoff * (1.0 + 1e-9) + 1e-12 * (s00 + s11 + s22)
    cv = c if abs(vmax2 - 1.0) <= 1e-12 else c * vmax2
    if _positive_definite(s00 - cv, s01, s02, s11 - cv, s12, s22 - cv):
        return True
    delta = np.sqrt(delta2) * (1.0 + 1e-12) + 1e-15  # rounded up: the bound holds for any delta above the true one
    for t in _SEED_BOUND_T:
        eps = delta / t
        cu = c * (1.0 + eps)
        ci = c * (1.0 + 1.0 / eps) * delta * delta
        if _positive_definite(
            s00 - cu * u0 * u0 - ci,
            s01 - cu * u0 * u1,
            s02 - cu * u0 * u2,
            s11 - cu * u1 * u1 - ci,
            s12 - cu * u1 * u2,
            s22 - cu * u2 * u2 - ci,
        ):
            return True
    return False


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _seed_errors(
    endpoints,
    directions,
    P,
    V,
    ok_right,
    ok_down,
    height,
    width,
    offsets,
    configs,
    out,
    best_config,
    best_key,
    cutoff=np.inf,
    tolerance=_FIT_TOLERANCE,
):
    """SSE (m^2) of every tetromino seed (anchor pixel, config) into out; inf where the seed is invalid.

    configs: the tetromino ids (0..16, increasing) that seed planes (SEED_SHAPES[GreedyOptions.seed_shapes]);
    out: ``(H*W, len(configs))``, column t the seeds of config configs[t] (one column for square seeds:
    the table the greedy and the tiles read is no wider than the shapes it holds).

    P, V: the endpoints and directions as (3, n) arrays (_ray_columns), which the vectorised
    fits read with unit stride across anchors.

    best_config[anchor] is the anchor's first config (tetromino id) of least SSE (-1: no valid seed), best_key
    that SSE (inf: none): the greedy's initial seeds.

    Per grid row and config, the straight-line four-ray fit runs over all anchors of each block of
    _SEED_BLOCK anchors that holds at least _SEED_BLOCK_MIN valid seeds (a vectorised loop); the
    valid seeds of the other blocks (sparse rows such as a 32-beam lidar's with a distance limit) and
    the seeds the loop did not finish are fitted by the general Gauss-Newton. The values are
    bit-identical to fitting every seed with fit_rays at the relative tolerance ``tolerance`` (the
    greedy's fit_tolerance: a relaxed one lets most seeds stop within the loop's three iterations),
    except that a seed left to the general fit whose SSE provably exceeds cutoff (m^2; _seed_exceeds)
    is not fitted and gets inf: a run that stops at cutoff never creates it (at lmax inf, most seeds
    the loop does not finish span a depth step or meet a surface at a grazing angle, with SSEs far
    above any useful e).
    """
    edges = _tetromino_edges(offsets, width)
    for i in nb.prange(height):
        row = np.empty(width)
        ok = np.empty(width, np.bool_)
        idx = np.empty(4, np.int64)
        base = i * width
        # the row's errors by config, copied into out's rows at the end (writing a column of out
        # touches a cache line per anchor)
        errors = np.full((len(configs), width), np.inf)
        for column, c in enumerate(configs):
            di_min = min(offsets[c, 0, 0], offsets[c, 1, 0], offsets[c, 2, 0], offsets[c, 3, 0])
            di_max = max(offsets[c, 0, 0], offsets[c, 1, 0], offsets[c, 2, 0], offsets[c, 3, 0])
            if i + di_min < 0 or i + di_max >= height:
                continue
            # anchors whose tetromino lies inside the grid
            j_lo = -min(offsets[c, 0, 1], offsets[c, 1, 1], offsets[c, 2, 1], offsets[c, 3, 1])
            j_hi = width - max(offsets[c, 0, 1], offsets[c, 1, 1], offsets[c, 2, 1], offsets[c, 3, 1])
            o0 = offsets[c, 0, 0] * width + offsets[c, 0, 1]
            o1 = offsets[c, 1, 0] * width + offsets[c, 1, 1]
            o2 = offsets[c, 2, 0] * width + offsets[c, 2, 1]
            o3 = offsets[c, 3, 0] * width + offsets[c, 3, 1]
            # valid seeds: all internal 4-adjacent pairs are admissible edges (which implies returns:
            # every cell of a tetromino is on one), as one straight-line loop over the row's anchors
            e0 = ok_right if edges[c, 0, 1] == 0 else ok_down
            e1 = ok_right if edges[c, 1, 1] == 0 else ok_down
            e2 = ok_right if edges[c, 2, 1] == 0 else ok_down
            e3 = ok_right if edges[c, 3, 1] == 0 else ok_down
            f0, f1, f2, f3 = edges[c, 0, 0], edges[c, 1, 0], edges[c, 2, 0], edges[c, 3, 0]
            for j in range(j_lo, j_hi):
                a = base + j
                ok[j] = e0[a + f0] & e1[a + f1] & e2[a + f2] & e3[a + f3]
                row[j] = np.nan
            # in blocks of _SEED_BLOCK anchors; a block with fewer than _SEED_BLOCK_MIN valid seeds
            # is left to the general fit below (a lidar's invalid seeds come in runs: no returns,
            # far ranges beyond the distance limit)
            for block in range(j_lo, j_hi, _SEED_BLOCK):
                block_end = min(block + _SEED_BLOCK, j_hi)
                n_ok = 0
                for j in range(block, block_end):
                    n_ok += ok[j]
                if n_ok >= _SEED_BLOCK_MIN:
                    for j in range(block, block_end):
                        # unsigned ids: no negative-index wraparound test, which would stop vectorisation
                        a = base + j
                        sse, done = fit4(
                            P, V, np.uint64(a + o0), np.uint64(a + o1), np.uint64(a + o2), np.uint64(a + o3), tolerance
                        )
                        row[j] = sse if done else np.nan
            for j in range(j_lo, j_hi):
                if not ok[j]:
                    continue
                sse = row[j]
                if np.isnan(sse):
                    _seed_rays(idx, base + j, o0, o1, o2, o3)
                    if cutoff < np.inf and _seed_exceeds(endpoints, directions, idx, cutoff):
                        continue  # errors[c, j] stays inf: never a create in this run
                    sse, _, _, _ = fit_rays(
                        endpoints, directions, idx, 4, np.nan, np.nan, np.nan, _FIT_ITERATIONS, tolerance
                    )
                errors[column, j] = sse if np.isfinite(sse) else np.inf
        _store_row(errors, configs, base, width, out, best_config, best_key)


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _store_row(errors, configs, base, width, out, best_config, best_key):
    """Copy one grid row's (len(configs), width) seed errors into out's rows base..base+width-1, and each
    anchor's first config (tetromino id) of least SSE (-1: none valid) and that SSE into best_config and
    best_key."""
    for j in range(width):
        best = -1
        least = np.inf
        for column in range(len(configs)):
            e = errors[column, j]
            out[base + j, column] = e
            if e < least:
                best = configs[column]
                least = e
        best_config[base + j] = best
        best_key[base + j] = least


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _ray_columns(endpoints, directions, P, V):
    """Copy (n, 3) endpoints and directions into (3, n) arrays P and V."""
    n = endpoints.shape[0]
    for block in nb.prange((n + 4095) // 4096):
        for k in range(block * 4096, min(n, block * 4096 + 4096)):
            for c in range(3):
                P[c, k] = endpoints[k, c]
                V[c, k] = directions[k, c]


#: Bits per digit of the seed keys' radix sort: 2048 buckets (a tile's few thousand keys would pay more for
#: clearing and summing 65536 buckets than for the extra pass), 6 passes over 64 bits.
_RADIX_BITS = 11


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _sort_seed_keys(seed_key, cutoff=np.inf):
    """Anchors with a finite seed key <= cutoff, in the order of (key, anchor): a stable LSD radix sort.

    Keys are >= 0, so their IEEE bits order like the keys; _RADIX_BITS-bit digits, all counted in one
    pass, and a digit that all keys share is skipped (the exponents of a scan's seeds span a few
    octaves). Returns (anchors, their keys). The same order as a stable argsort of the keys, in O(n)
    instead of O(n log n).
    """
    n = seed_key.shape[0]
    m = 0
    for k in range(n):
        if seed_key[k] < np.inf and seed_key[k] <= cutoff:
            m += 1
    order = np.empty(m, np.int64)
    bits = np.empty(m, np.uint64)
    buckets = 1 << _RADIX_BITS
    passes = (64 + _RADIX_BITS - 1) // _RADIX_BITS
    mask = np.uint64(buckets - 1)
    count = np.zeros((passes, buckets + 1), np.int64)
    m = 0
    for k in range(n):
        if seed_key[k] < np.inf and seed_key[k] <= cutoff:
            order[m] = k
            b = np.uint64(_float_bits(seed_key[k] + 0.0))  # + 0.0: -0.0 becomes +0.0
            bits[m] = b
            for digit in range(passes):
                count[digit, ((b >> np.uint64(digit * _RADIX_BITS)) & mask) + 1] += 1
            m += 1
    order2 = np.empty(m, np.int64)
    bits2 = np.empty(m, np.uint64)
    for digit in range(passes):
        shift = np.uint64(digit * _RADIX_BITS)
        if m == 0 or count[digit, ((bits[0] >> shift) & mask) + 1] == m:
            continue  # every key has this digit: the pass would not move anything
        start = count[digit]
        for d in range(buckets):
            start[d + 1] += start[d]
        for t in range(m):
            d = (bits[t] >> shift) & mask
            pos = start[d]
            start[d] = pos + 1
            order2[pos] = order[t]
            bits2[pos] = bits[t]
        order, order2 = order2, order
        bits, bits2 = bits2, bits
    return order, seed_key[order]


#: Side (rays) of a block seed (GreedyOptions.block_seeds).
BLOCK_SIDE = 4


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _block_seeds(endpoints, directions, ok_right, ok_down, square_sse, height, width, max_sse, tolerance):
    """Anchors (top-left pixels) of the BLOCK_SIDE x BLOCK_SIDE blocks at rows and columns 0, 4, 8, ... whose
    internal 4-neighbour pairs are all admissible edges and whose exact fit (fit_rays at ``tolerance``
    from the algebraic start, rays in row order) has an SSE of at most max_sse, in (SSE, anchor) order.

    square_sse: each anchor's 2 x 2 square seed SSE (inf: invalid or above the run's cutoff), fitted at
    ``tolerance`` too (so above its least SSE by about ``tolerance`` of itself at most). The four squares
    of a block are disjoint, so the sum of their least SSEs is a lower bound of the block's SSE: a block
    whose sum, lowered by twice ``tolerance``, exceeds max_sse (by more than rounding) is not fitted.
    """
    side = BLOCK_SIDE
    rows = height // side
    columns = width // side
    anchors = np.empty(rows * columns, np.int64)
    values = np.empty(rows * columns)
    idx = np.empty(side * side, np.int64)
    m = 0
    for bi in range(rows):
        for bj in range(columns):
            a = bi * side * width + bj * side
            joined = True
            for di in range(side):
                for dj in range(side):
                    k = a + di * width + dj
                    if (dj + 1 < side and not ok_right[k]) or (di + 1 < side and not ok_down[k]):
                        joined = False
            if not joined:
                continue
            lower = square_sse[a] + square_sse[a + 2] + square_sse[a + 2 * width] + square_sse[a + 2 * width + 2]
            if not lower * (1.0 - 2.0 * tolerance) <= max_sse * (1.0 + 1e-9):
                continue
            for t in range(side * side):
                idx[t] = a + (t // side) * width + t % side
            sse, _, _, _ = fit_rays(
                endpoints, directions, idx, side * side, np.nan, np.nan, np.nan, _FIT_ITERATIONS, tolerance
            )
            if sse <= max_sse:
                anchors[m] = a
                values[m] = sse
                m += 1
    order = np.argsort(values[:m], kind='mergesort')  # stable: ties in anchor order
    return anchors[:m][order]


def _edge_masks(scan: RayScan, max_neighbor_distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Admissible grid edges: right (k, k+1) and down (k, k+W) with both rays valid and close enough."""
    ok_right = np.empty(scan.size, np.bool_)
    ok_down = np.empty(scan.size, np.bool_)
    _edge_mask_kernel(
        scan.endpoints, scan.valid, scan.height, scan.width, float(max_neighbor_distance), ok_right, ok_down
    )
    return ok_right, ok_down


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _edge_mask_kernel(endpoints, valid, height, width, max_distance, ok_right, ok_down):
    """ok_right[k]: rays k and k+1 (same row) valid and at most max_distance (m) apart; ok_down[k]: k and k+W."""
    for i in nb.prange(height):
        for j in range(width):
            k = i * width + j
            ok_right[k] = j + 1 < width and valid[k] and valid[k + 1] and _distance(endpoints, k, k + 1) <= max_distance
            ok_down[k] = (
                i + 1 < height and valid[k] and valid[k + width] and _distance(endpoints, k, k + width) <= max_distance
            )


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _distance(endpoints, a, b):
    """Distance (m) between endpoints a and b (summed in the order of np.linalg.norm)."""
    d0 = endpoints[a, 0] - endpoints[b, 0]
    d1 = endpoints[a, 1] - endpoints[b, 1]
    d2 = endpoints[a, 2] - endpoints[b, 2]
    return np.sqrt((d0 * d0 + d1 * d1) + d2 * d2)


def _seed_stage(
    scan: RayScan,
    ok_right: np.ndarray,
    ok_down: np.ndarray,
    cutoff: float,
    seed_shapes: str = 'all',
    fit_tolerance: float = _FIT_TOLERANCE,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every anchor's tetromino seed errors, its best config and key (reused work memory); seeds above
    ``cutoff`` (the greedy's, :func:`_run_cutoff`) are never created. Only the configs of ``seed_shapes``
    (SEED_SHAPES) are evaluated: the table has a column per config of that set, in its order. The seeds are
    fitted to the relative tolerance ``fit_tolerance`` (GreedyOptions.fit_tolerance)."""
    configs = SEED_SHAPES[seed_shapes]
    seed_sse = _reusable('seeds', scan.size * len(configs), np.float64).reshape(scan.size, len(configs))
    seed_best = _reusable('seed_best', scan.size, np.int32)
    seed_key = _reusable('seed_key', scan.size, np.float64)
    columns = _reusable('ray_columns', scan.size * 6, np.float64).reshape(6, scan.size)
    _ray_columns(scan.endpoints, scan.directions, columns[:3], columns[3:])
    _seed_errors(
        scan.endpoints,
        scan.directions,
        columns[:3],
        columns[3:],
        ok_right,
        ok_down,
        scan.height,
        scan.width,
        TETROMINO_OFFSETS,
        configs,
        seed_sse,
        seed_best,
        seed_key,
        cutoff,
        fit_tolerance,
    )
    return seed_sse, seed_best, seed_key
