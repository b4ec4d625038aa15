"""The boundary round: large surfaces that meet along a shared boundary become one surface.

Pure numpy/numba; no ROS import. Frames: the scan's internal frame; lengths in metres.

The consolidation (ppe_ros.core.consolidation) merges pieces two at a time, cheapest first, and its step
test compares two pieces' planes at the pieces' means. Far from where two large pieces meet, a plane
also carries the pieces' tilt: the two halves of a cambered road, each 1-2 % to its side, are 5-6 cm
apart at the other half's mean although they meet at the crown. Whether such a road ends up whole then
depends on the order in which its small pieces merged, which changes from one sweep to the next.

This round decides between the *final* large surfaces, where each plane is well known. Two surfaces A
and B, each of at least ``min_points`` rays, are compared when they share a boundary: at least
MIN_BOUNDARY_PAIRS pixel pairs (a, b) of A and B that are neighbours along a grid row or column, or
that have at most ``max_gap`` rays without a surface between them (along the rows across the seam of
a full revolution when ``wrap_columns``). They are one surface when

* each is within t of their union's orthogonal least-squares plane U (the consolidation's deviation
  test: ``mean_P dist_U^2 - s_P^2 <= t^2`` for P = A, B, with its t),
* their planes meet at the boundary: the boundary points of A lie no farther from B's plane than
  from A's own, and those of B no farther from A's plane than from B's own, by a mean square of at
  most ``(kappa t)^2`` on each side, ``max(excess_A, excess_B) <= kappa^2 t^2`` with
  ``excess_A = max(mean_{a} dist_B(a)^2 - mean_{a} dist_A(a)^2, 0)`` (each side on its own: where
  rays of the road joined the pavement's surface next to a kerb, the pavement's side of the boundary
  lies on the road's plane, but the road's side still lies a kerb's height off the pavement's), and
* their normals are at most ``max_bend_deg`` (MAX_BEND_DEG, 4 deg) apart.

A crease (two planes that intersect where the surfaces meet) has no excess; a kerb beside the road
(parallel planes 12-15 cm apart) and a window recessed into its facade have the step at the boundary
itself, so they stay apart; a ramp beside the road (5 deg) and two walls at 90 deg bend too much.
Admissible pairs merge cheapest first (cost: the larger ratio of the two tests to their tolerance, ties
by the smaller ids); a merged surface's boundaries are the union of its parts' (moments add), and its
pairs are valued again. Every valuation
is O(1) from moments. ``test/reference_consolidation.py`` (``boundary_join_reference``) is the
brute-force definition the kernel is tested against.
"""

from __future__ import annotations

import math
import numbers
import threading
from pathlib import Path

import numba as nb
import numpy as np

from ppe_ros.core.consolidation import (
    _add_pair,
    _add_ray,
    _find,
    _mean_square_distance,
    _piece_moments,
    _plane_of,
    _plane_rows,
    _scatter,
    _union_deviation,
    checked_tolerances,
    in_row_blocks,
)
from ppe_ros.core.scan import RayScan
from ppe_ros.core.sensor import check_boundary_join_points, check_step_factor


def _cache_probe():
    """A function of this module's directory: numba's cache locators place its kernels' files by it."""


_cache_guarded = []
_cache_guard_lock = threading.Lock()


def _guard_cache() -> None:
    """Once per process, before this module's first kernel is loaded: numba keys a cached kernel on its own
    file, and the kernels here inline consolidation.py's helpers, so their cache is dropped when
    consolidation.py changed (ppe_ros.core.ppe.cache_guard.guard_module_cache). Threads that call at once
    wait for the first one's guard."""
    if _cache_guarded:
        return
    from ppe_ros.core.ppe.cache_guard import cache_directory, guard_module_cache  # not at import: a cycle

    with _cache_guard_lock:
        if not _cache_guarded:
            here = Path(__file__).resolve()
            guard_module_cache(here, [here.with_name('consolidation.py')], cache_directory(_cache_probe))
            _cache_guarded.append(True)


#: Rays without a surface that a boundary between two surfaces may cross along a row or column.
BOUNDARY_GAP = 3
#: Fewest boundary pixel pairs for which two surfaces are compared.
MIN_BOUNDARY_PAIRS = 10
#: Largest angle (deg) between two surfaces' normals that the round joins: a road's camber (its halves
#: 2-4 deg apart) bends less, a ramp beside the road (5 deg and more) is another surface.
MAX_BEND_DEG = 4.0


def join_at_boundaries(
    scan: RayScan,
    surface_ids: np.ndarray,
    sigmas: np.ndarray,
    surface_tolerance: float,
    min_points: int,
    *,
    noise_factor: float = 0.0,
    step_factor: float = 1.0,
    wrap_columns: bool = False,
    max_gap: int = BOUNDARY_GAP,
    max_bend_deg: float = MAX_BEND_DEG,
) -> np.ndarray:
    """The surfaces ``surface_ids`` (``(H*W,)``, -1: none) after the boundary round (module docstring).

    Args:
        scan: the ray scan (endpoints in its internal frame, m).
        surface_ids: each ray's surface (any non-negative ids; -1: none).
        sigmas: each ray's range noise (m; NaN: none), for the tolerance's noise term.
        surface_tolerance: tau (m). noise_factor: lambda. step_factor: kappa >= 1.
        min_points: surfaces with fewer rays take no part.
        wrap_columns: the last column is next to the first (a full revolution).
        max_gap: rays without a surface a boundary may cross (0: touching pixels only).
        max_bend_deg: the largest angle between two surfaces' normals that joins (deg, 0-90).

    Returns:
        ``(H*W,)`` int64: each ray's surface, the ids of joined surfaces replaced by the smallest of them.
    """
    tau, factor = checked_tolerances(surface_tolerance, noise_factor)
    _guard_cache()
    points = check_boundary_join_points(min_points)
    step2 = check_step_factor(step_factor) ** 2
    if isinstance(max_gap, bool) or not isinstance(max_gap, numbers.Integral) or max_gap < 0:
        raise ValueError(f'max_gap must be an integer >= 0; got {max_gap!r}')
    if isinstance(max_bend_deg, bool) or not isinstance(max_bend_deg, numbers.Real) or not 0 <= max_bend_deg <= 90:
        raise ValueError(f'max_bend_deg must be an angle in [0, 90] deg; got {max_bend_deg!r}')
    bend = float(max_bend_deg)
    given = np.ascontiguousarray(surface_ids, dtype=np.int64)
    if given.shape != (scan.size,):
        raise ValueError(f'surface_ids must have one entry per pixel ({scan.size}); got shape {given.shape}')
    if np.shape(sigmas) != (scan.size,):
        raise ValueError(f'sigmas must have one entry per pixel ({scan.size}); got shape {np.shape(sigmas)}')
    if given.size == 0 or given.max() < 0:
        return given.copy()
    ids, labels = given, None
    if given.max() >= given.size:  # sparse ids: numbered 0..S-1 here (in order), given back at the end
        labels, dense = np.unique(given[given >= 0], return_inverse=True)
        ids = np.full_like(given, -1)
        ids[given >= 0] = dense
    n = int(ids.max()) + 1
    ray_sigmas = np.where(np.isfinite(sigmas), np.asarray(sigmas, dtype=np.float64), 0.0)
    moments = _piece_moments(ids, scan.endpoints, ray_sigmas, n)
    large = moments[:, 0] >= points
    pixel_pairs = _parallel_boundary_pixel_pairs(ids, large, scan.height, scan.width, bool(wrap_columns), int(max_gap))
    # (no early return without pairs: every kernel runs on each call, so that a JIT warm-up on a small
    # cloud compiles them all)
    keys = ids[pixel_pairs[:, 0]] * n + ids[pixel_pairs[:, 1]]
    unique, index = np.unique(keys, return_inverse=True)  # the pairs of surfaces
    side = _side_moments(scan.endpoints, ray_sigmas, pixel_pairs, index.astype(np.int64), len(unique))
    pairs = np.stack([unique // n, unique % n], axis=1).astype(np.int64)
    plane = np.empty((n, 13))
    _plane_rows(moments, plane, 0, n)
    roots = _boundary_merge_kernel(
        moments, plane, pairs, side, tau * tau, factor * factor, step2, math.cos(math.radians(bend))
    )
    out = ids.copy()
    valid = out >= 0
    out[valid] = roots[out[valid]] if labels is None else labels[roots[out[valid]]]
    return out


#: Pixels per thread below which the boundary pixel pairs are found in the calling thread alone (a pass
#: cheaper per pixel than the candidate pairs': a 32 x 1024 sweep's is faster on one thread).
PARALLEL_PAIRS_MIN_PIXELS = 32768


def _parallel_boundary_pixel_pairs(ids, large, height: int, width: int, wrap: bool, max_gap: int) -> np.ndarray:
    """:func:`_boundary_pixel_pairs` of all pixels in row blocks (consolidation.in_row_blocks): the pairs and
    their order of one call over all pixels."""

    def block(first: int, last: int) -> np.ndarray:
        return _boundary_pixel_pairs(ids, large, height, width, wrap, max_gap, first, last)

    return in_row_blocks(block, height, width, PARALLEL_PAIRS_MIN_PIXELS)


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _boundary_pixel_pairs(ids, large, height, width, wrap, max_gap, first, last):
    """(m, 2) pixel pairs (k, l) on the boundary of two large surfaces, the smaller surface id's pixel
    first: l is the first pixel with a surface after k to its right (across the seam when wrap) or
    below it, with at most max_gap pixels without one between them, and its surface is another; for the
    pixels k in first..last-1, in the order of k."""
    out = np.empty((64, 2), np.int64)
    n_out = 0
    for k in range(first, last):
        a = ids[k]
        if a < 0 or not large[a]:
            continue
        i = k // width
        j = k - i * width
        for direction in range(2):
            for step in range(1, max_gap + 2):
                if direction == 0:
                    jj = j + step
                    if jj >= width:
                        jj -= width
                        if not wrap or jj >= j:
                            break
                    other = i * width + jj
                else:
                    if i + step >= height:
                        break
                    other = k + step * width
                b = ids[other]
                if b < 0:
                    continue
                if b != a and large[b]:
                    first, second = (k, other) if a < b else (other, k)
                    out, n_out = _add_pair(out, n_out, 0, 0)  # room for one more row, filled here
                    out[n_out - 1, 0] = first
                    out[n_out - 1, 1] = second
                break
    return out[:n_out]


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _side_moments(endpoints, sigmas, pixel_pairs, pair_index, n_pairs):
    """(2 n_pairs, 11) moments of each surface pair's boundary points: row 2p the smaller id's side,
    row 2p + 1 the larger id's (a pixel counts once per pixel pair it is in)."""
    side = np.zeros((2 * n_pairs, 11))
    for e in range(len(pixel_pairs)):
        p = pair_index[e]
        _add_ray(side, 2 * p, endpoints, pixel_pairs[e, 0], sigmas[pixel_pairs[e, 0]])
        _add_ray(side, 2 * p + 1, endpoints, pixel_pairs[e, 1], sigmas[pixel_pairs[e, 1]])
    return side


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _side_square_distance(m, plane_row):
    """Mean squared distance (m^2) of points with moments m (count, sums, sums of products) from the
    plane of a _plane_of row (through its mean, along its normal)."""
    mean, sc = _scatter(m)
    return _mean_square_distance(
        mean[0], mean[1], mean[2], sc[0], sc[1], sc[2], sc[3], sc[4], sc[5],
        plane_row[10], plane_row[11], plane_row[12], plane_row[0], plane_row[1], plane_row[2],
    )  # fmt: skip


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _boundary_cost(mom, plane, side, p, a, b, tau2, noise_factor2, step_factor2, min_cos_bend):
    """Cost of joining surfaces a < b of pair p (admissible: <= 1): the larger of the deviation test's
    max dev(P, U)^2 / t^2 and the boundary test's larger excess / (kappa t)^2 (module docstring); inf
    for a boundary of fewer than MIN_BOUNDARY_PAIRS pixel pairs (which may grow as surfaces join)."""
    if side[2 * p, 0] < MIN_BOUNDARY_PAIRS:
        return np.inf
    plane_a, plane_b = plane[a], plane[b]
    if abs(plane_a[10] * plane_b[10] + plane_a[11] * plane_b[11] + plane_a[12] * plane_b[12]) < min_cos_bend:
        return np.inf
    deviation, allowed, _, _, _ = _union_deviation(mom, plane, a, b, tau2, noise_factor2)
    side_a, side_b = side[2 * p], side[2 * p + 1]
    excess_a = max(_side_square_distance(side_a, plane_b) - _side_square_distance(side_a, plane_a), 0.0)
    excess_b = max(_side_square_distance(side_b, plane_a) - _side_square_distance(side_b, plane_b), 0.0)
    return max(deviation, max(excess_a, excess_b) / step_factor2) / allowed


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _cheapest(cost, low, high, active):
    """The active pair of least cost <= 1 (ties: smaller low, then smaller high id); -1 if none."""
    best = -1
    for p in range(len(cost)):
        if not active[p] or not cost[p] <= 1.0:
            continue
        if (
            best < 0
            or cost[p] < cost[best]
            or (cost[p] == cost[best] and (low[p] < low[best] or (low[p] == low[best] and high[p] < high[best])))
        ):
            best = p
    return best


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _fold_pairs(a, b, low, high, side, active):
    """After surface b joined a: every active pair of b becomes a pair of a (its boundary moments added
    to a's existing pair with the same surface, if there is one)."""
    for p in range(len(low)):
        if not active[p] or (low[p] != b and high[p] != b):
            continue
        x = high[p] if low[p] == b else low[p]
        row_b, row_x = (2 * p, 2 * p + 1) if low[p] == b else (2 * p + 1, 2 * p)
        side_b, side_x = side[row_b].copy(), side[row_x].copy()
        target = p
        for q in range(len(low)):
            if q != p and active[q] and ((low[q] == a and high[q] == x) or (low[q] == x and high[q] == a)):
                target = q
                break
        if target != p:
            active[p] = False
        else:
            side[2 * p] = 0.0
            side[2 * p + 1] = 0.0
        low[target], high[target] = min(a, x), max(a, x)
        row_a, row_x = (2 * target, 2 * target + 1) if a < x else (2 * target + 1, 2 * target)
        side[row_a] += side_b
        side[row_x] += side_x


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _boundary_merge_kernel(moments, plane_rows, pairs, side_rows, tau2, noise_factor2, step_factor2, min_cos_bend):
    """Root of each surface after the boundary round's merges (cheapest admissible pair first) of
    surfaces (moments (K, 11), their _plane_of rows) along their boundary pairs (m, 2), low < high,
    with the boundary moments side_rows (2m, 11)."""
    mom = moments.copy()
    plane = plane_rows.copy()
    side = side_rows.copy()
    low = pairs[:, 0].copy()
    high = pairs[:, 1].copy()
    m = len(low)
    active = np.ones(m, np.bool_)
    cost = np.empty(m)
    for p in range(m):
        cost[p] = _boundary_cost(mom, plane, side, p, low[p], high[p], tau2, noise_factor2, step_factor2, min_cos_bend)
    parent = np.arange(len(mom))
    while True:
        best = _cheapest(cost, low, high, active)
        if best < 0:
            break
        a, b = low[best], high[best]
        active[best] = False
        parent[b] = a
        mom[a] += mom[b]
        _plane_of(mom[a], plane[a])
        _fold_pairs(a, b, low, high, side, active)
        for p in range(m):
            if active[p] and (low[p] == a or high[p] == a):
                cost[p] = _boundary_cost(
                    mom, plane, side, p, low[p], high[p], tau2, noise_factor2, step_factor2, min_cos_bend
                )
    roots = np.empty(len(mom), np.int64)
    for x in range(len(mom)):
        roots[x] = _find(parent, x)
    return roots
