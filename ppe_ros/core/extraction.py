"""Probabilistic Plane Extraction (PPE): greedy maximum-likelihood agglomeration of rays into planes.

Semantics (Schaefer et al., ICRA 2019, Algorithm 1, with the reference code's stopping rules and
without its quirks):

* every valid ray starts as an atomic plane; the error E of a set of planes is the sum over rays
  of squared ray-length residuals (m^2), atomic planes have error 0;
* actions: *create* a regular plane from 4 atomic rays forming one of the 17 non-I tetrominoes,
  *extend* a regular plane by one 4-neighbouring atomic ray, *merge* two regular planes that touch;
  joins happen only over grid edges whose endpoints are at most ``max_neighbor_distance`` apart
  (the paper's d / the reference's lmax), and a seed with a no-return or a too-long internal edge
  is invalid;
* each step executes the action with the least error increment (ties: create < extend < merge,
  then by ids);
* a cut for threshold e is the state before the first action whose increment exceeds e; a cut
  for a plane count n is the first state with J <= n planes (J counts atomic rays and regular planes).

Plane ids in the action log: a plane created from a seed gets the row-major pixel id of the seed's
anchor; a merge keeps the smaller id. Increments are computed exactly (Gauss-Newton to convergence)
for planes of up to ``exact_plane_size`` rays and for every merge that is executed; larger planes
use their Gauss-Newton quadratic model, re-linearised (one Gauss-Newton step on all their rays)
whenever the plane doubles in size or its parameters drift (see docs/algorithm.md for the error
bound and how it is tested).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numba as nb
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

from ppe_ros.core.fitting import (
    _fit,
    _fit4,
    _fit_rays,
    _gn_pass,
    _ray_terms,
    _solve_sym3,
    fit_pixel_groups,
)
from ppe_ros.core.planes import PlaneSet
from ppe_ros.core.scan import RayScan, make_ray_scan
from ppe_ros.core.sensor import PROFILES, NoiseModel, SensorProfile, sensor_profile
from ppe_ros.core.surfaces import whole_surfaces

KIND_CREATE = 0
KIND_EXTEND = 1
KIND_MERGE = 2

#: Offsets (drow, dcol) of the 17 fixed non-I tetrominoes containing the anchor (0, 0), in the
#: reference implementation's configuration order (1 O, 4 T, 4 S/Z, 8 L/J).
TETROMINO_OFFSETS = np.array(
    [
        [(0, 0), (1, 0), (0, 1), (1, 1)],
        [(-1, 0), (0, 0), (1, 0), (0, 1)],
        [(0, -1), (-1, 0), (0, 0), (1, 0)],
        [(0, -1), (0, 0), (1, 0), (0, 1)],
        [(0, -1), (-1, 0), (0, 0), (0, 1)],
        [(0, 0), (1, 0), (-1, 1), (0, 1)],
        [(-1, -1), (0, -1), (0, 0), (1, 0)],
        [(0, -1), (0, 0), (1, 0), (1, 1)],
        [(0, -1), (-1, 0), (0, 0), (-1, 1)],
        [(-1, 0), (0, 0), (1, 0), (-1, 1)],
        [(-1, -1), (-1, 0), (0, 0), (1, 0)],
        [(0, -1), (1, -1), (0, 0), (0, 1)],
        [(0, -1), (0, 0), (0, 1), (1, 1)],
        [(-1, -1), (0, -1), (0, 0), (0, 1)],
        [(0, -1), (0, 0), (-1, 1), (0, 1)],
        [(-1, 0), (0, 0), (1, 0), (1, 1)],
        [(1, -1), (-1, 0), (0, 0), (1, 0)],
    ],
    dtype=np.int64,
)

ACTION_DTYPE = np.dtype([('kind', np.int8), ('a', np.int64), ('b', np.int64), ('increment', np.float64)])

#: A union fit started from the two planes' merged quadratic model is kept when its increment is within this
#: relative difference of the models' increment; otherwise the union is also fitted from three other starts.
UNION_MODEL_AGREEMENT = 0.25

#: Planes of up to this many rays are evaluated with exact fits; larger ones with their model.
DEFAULT_EXACT_PLANE_SIZE = 32
#: Relative drift of predicted ranges that triggers a re-linearisation of a large plane.
RELINEARISATION_DRIFT = 1e-2
#: Model merge increments above this multiple of the stopping threshold are not queued.
MODEL_CUTOFF_FACTOR = 4.0
#: Model merge increments are queued this fraction below their value (refined exactly when popped).
MODEL_MERGE_KEY_MARGIN = 0.05
#: A merge refined at the top of the queue keeps the smaller plane's exact residuals as a quadratic
#: model around the refined union's w; while that plane is unchanged and the larger one has grown by at
#: most this fraction of its size at the refinement, the merge is re-valued from that model (0: never).
REFINED_MERGE_GROWTH = 0.125
#: After an action on a plane larger than exact_plane_size that has grown by at most this fraction
#: since its last full merge loop, only its new neighbours' merges are valued; its queued and
#: deferred merges keep their keys (0: every action re-values every merge).
MERGE_LOOP_GROWTH = 1.0 / 512.0
#: Relative slack subtracted from cached lower bounds (round-off and model error).
BOUND_SLACK = 1e-7
#: Scans must have fewer rays than this (the greedy stores ids, versions and stamps in 32 bits).
MAX_RAYS = 2**26

_FIT_ITERATIONS = 50
_FIT_TOLERANCE = 1e-13

# global heap entry kinds (sorted so that create < extend < merge on equal keys)
_G_SEED = 0
_G_EXTEND = 1
_G_MERGE_MODEL = 2
_G_MERGE_EXACT = 3

# queue state fields (far buckets of the two-level queue)
_QCUR = 0  # buckets up to this index live in the heap
_QFREE = 1  # free far-bucket chunks: a stack of this many chunk ids in fnext[:, 1]
_QUSED = 2  # far-bucket chunks ever allocated
_QCOUNT = 3  # entries in far buckets
_NQS = 4
# a far bucket is a linked list of chunks of _Q_CHUNK consecutive entries (only its head chunk
# is partly filled): loading a bucket reads its entries in order and waits on one link per
# chunk instead of one per entry
_Q_CHUNK = 8
#: Far buckets per octave of the key (4: a bucket spans keys within a factor 2^(1/4)).
_Q_FRACTION_BITS = 2
_Q_PER_OCTAVE = 1 << _Q_FRACTION_BITS
_Q_BUCKETS = (2200 + 2) * _Q_PER_OCTAVE


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _q_chunks(capacity):
    """Far-bucket chunks that hold capacity entries: full chunks plus one partly filled per bucket."""
    return (capacity + _Q_CHUNK - 1) // _Q_CHUNK + _Q_BUCKETS


# adjacency node fields
_AN_PLANE = 0  # the neighbouring plane (an id that may have been merged since: resolve with _find)
_AN_KIND = 1  # kind of the deferred merge
_AN_VA = 2  # versions of the deferred merge's planes (smaller id first)
_AN_VB = 3
_AN_KEY = 4  # key of the deferred merge, a float64 in the same row (inf: none)
_AN_FIELDS = 5
#: A plane's adjacency nodes are one segment of the pool; segment sizes are powers of two from this.
_ADJ_MIN_ROWS = 4
_ADJ_CLASSES = 40

# plane float fields
_PE = 0  # error (m^2)
_PW = 1  # w (3)
_PH = 4  # GN information (6)
_PRPARTNER = 10  # partner of the plane's kept refined merge (rcache; -1: none): next to w and the
#                  information, which the merge loop reads with it (the same two cache lines)
_PRMAX = 11  # max |p| of the plane's endpoints
_PDEFER = 12  # least key of the merges deferred on the plane's adjacency nodes (inf: none)
_PWL = 13  # w at the last exact linearisation (3)
_PCOUNTLOOP = 16  # ray count at the plane's last full merge loop
_PCOUNTLIN = 17  # ray count at the plane's last exact linearisation
_NPF = 18
# plane int fields
_PCOUNT = 0
_PMVER = 1  # merge version: the version at the plane's last full merge loop (merge entries carry it)
_PVER = 2
_PSTAMP = 3
_PHEAD = 4
_PTAIL = 5
_PROOT = 6
_PADJ = 7  # first row of the adjacency segment (-1: none)
_PADJN = 8  # adjacency nodes in use
_PALIVE = 9
_PADJC = 10  # rows of the adjacency segment
_NPI = 11
# kernel statistics (counters returned with the action log)
_ST_POPS = 0
_ST_REEVALS = 1
_ST_NEW_CANDIDATES = 2
_ST_MERGE_EVALS = 3
_ST_MERGE_REFINES = 4
_ST_REFINE_RAYS = 5
_ST_RELINS = 6
_ST_RELIN_RAYS = 7
_ST_HEAP_PEAK = 8
_ST_REFINED_REUSES = 9
_N_STATS = 10
STAT_NAMES = (
    'heap_pops',
    'candidate_reevaluations',
    'new_candidates',
    'merge_evaluations',
    'merge_refinements',
    'merge_refinement_rays',
    'relinearisations',
    'relinearisation_rays',
    'heap_capacity',
    'refined_merge_reuses',
)


@intrinsic
def _prefetch(typingctx, arr, row, col):
    """Hint the CPU to fetch arr[row, col] (arr[row] of a 1-D array) into the cache (no effect on results)."""
    if not isinstance(arr, types.Array) or arr.ndim > 2:
        return None
    sig = types.void(arr, row, col)

    def codegen(context, builder, signature, args):
        aryty, rowty, colty = signature.args
        ary = context.make_array(aryty)(context, builder, args[0])
        inds = [context.cast(builder, args[1], rowty, types.intp), context.cast(builder, args[2], colty, types.intp)]
        inds = inds[: aryty.ndim]
        ptr = cgutils.get_item_pointer2(
            context,
            builder,
            data=ary.data,
            shape=cgutils.unpack_tuple(builder, ary.shape),
            strides=cgutils.unpack_tuple(builder, ary.strides),
            layout=aryty.layout,
            inds=inds,
            wraparound=False,
        )
        i32 = ir.IntType(32)
        i8p = ir.IntType(8).as_pointer()
        fn = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]), 'llvm.prefetch.p0'
        )
        # read access, high temporal locality, data cache
        builder.call(fn, [builder.bitcast(ptr, i8p), ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def _float_bits(typingctx, x):
    """The IEEE 754 bits of a float64 as an int64 (a bit cast)."""
    if not isinstance(x, types.Float) or x.bitwidth != 64:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(x), codegen


# --------------------------------------------------------------------------------------------
# seeds
# --------------------------------------------------------------------------------------------


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _seed_rays(idx, anchor, o0, o1, o2, o3):
    """Write the ray ids of the seed at anchor with the tetromino's id offsets o0..o3 into idx[:4]."""
    idx[0] = anchor + o0
    idx[1] = anchor + o1
    idx[2] = anchor + o2
    idx[3] = anchor + o3


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
    endpoints, directions, P, V, ok_right, ok_down, height, width, offsets, out, best_config, best_key, cutoff=np.inf
):
    """SSE (m^2) of every tetromino seed (anchor pixel, config) into out; inf where the seed is invalid.

    P, V: the endpoints and directions as (3, n) arrays (_ray_columns), which the vectorised
    fits read with unit stride across anchors.

    best_config[anchor] is the anchor's first config of least SSE (-1: no valid seed), best_key
    that SSE (inf: none): the greedy's initial seeds.

    Per grid row and config, the straight-line four-ray fit runs over all anchors of each block of
    _SEED_BLOCK anchors that holds at least _SEED_BLOCK_MIN valid seeds (a vectorised loop); the
    valid seeds of the other blocks (sparse rows such as a 32-beam lidar's with a distance limit) and
    the seeds the loop did not finish are fitted by the general Gauss-Newton. The values are
    bit-identical to fitting every seed with _fit_rays, except that a seed left to the general fit
    whose SSE provably exceeds cutoff (m^2; _seed_exceeds) is not fitted and gets inf: a run
    that stops at cutoff never creates it (at lmax inf, most seeds the loop does not finish span a
    depth step or meet a surface at a grazing angle, with SSEs far above any useful e).
    """
    edges = _tetromino_edges(offsets, width)
    for i in nb.prange(height):
        row = np.empty(width)
        ok = np.empty(width, np.bool_)
        idx = np.empty(4, np.int64)
        base = i * width
        # the row's errors by config, copied into out's rows at the end (writing a column of out
        # touches a cache line per anchor)
        errors = np.full((17, width), np.inf)
        for c in range(17):
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
            f0 = edges[c, 0, 0]
            f1 = edges[c, 1, 0]
            f2 = edges[c, 2, 0]
            f3 = edges[c, 3, 0]
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
                        sse, done = _fit4(
                            P, V, np.uint64(a + o0), np.uint64(a + o1), np.uint64(a + o2), np.uint64(a + o3)
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
                    sse, _, _, _ = _fit_rays(
                        endpoints, directions, idx, 4, np.nan, np.nan, np.nan, _FIT_ITERATIONS, _FIT_TOLERANCE
                    )
                errors[c, j] = sse if np.isfinite(sse) else np.inf
        for j in range(width):
            best = -1
            least = np.inf
            for c in range(17):
                e = errors[c, j]
                out[base + j, c] = e
                if e < least:
                    best = c
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


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _sort_seed_keys(seed_key, cutoff=np.inf):
    """Anchors with a finite seed key <= cutoff, in the order of (key, anchor): a stable LSD radix sort.

    Keys are >= 0, so their IEEE bits order like the keys; 16-bit digits, and a digit that all
    keys share is skipped (the exponents of a scan's seeds span a few octaves). Returns (anchors,
    their keys). The same order as a stable argsort of the keys, in O(n) instead of O(n log n).
    """
    n = seed_key.shape[0]
    m = 0
    for k in range(n):
        if seed_key[k] < np.inf and seed_key[k] <= cutoff:
            m += 1
    order = np.empty(m, np.int64)
    bits = np.empty(m, np.uint64)
    m = 0
    for k in range(n):
        if seed_key[k] < np.inf and seed_key[k] <= cutoff:
            order[m] = k
            bits[m] = np.uint64(_float_bits(seed_key[k] + 0.0))  # + 0.0: -0.0 becomes +0.0
            m += 1
    order2 = np.empty(m, np.int64)
    bits2 = np.empty(m, np.uint64)
    count = np.empty(65537, np.int64)
    for shift in range(0, 64, 16):
        count[:] = 0
        for t in range(m):
            count[((bits[t] >> np.uint64(shift)) & np.uint64(0xFFFF)) + 1] += 1
        if m == 0 or count.max() == m:
            continue
        for d in range(65536):
            count[d + 1] += count[d]
        for t in range(m):
            d = (bits[t] >> np.uint64(shift)) & np.uint64(0xFFFF)
            pos = count[d]
            count[d] = pos + 1
            order2[pos] = order[t]
            bits2[pos] = bits[t]
        order, order2 = order2, order
        bits, bits2 = bits2, bits
    return order, seed_key[order]


# --------------------------------------------------------------------------------------------
# global 4-ary heap: key, then (kind, a, b); int payload columns kind a b va vb
# --------------------------------------------------------------------------------------------


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _g_less(gkey, gint, i, j):
    if gkey[i] != gkey[j]:
        return gkey[i] < gkey[j]
    if gint[i, 0] != gint[j, 0]:
        return gint[i, 0] < gint[j, 0]
    if gint[i, 1] != gint[j, 1]:
        return gint[i, 1] < gint[j, 1]
    return gint[i, 2] < gint[j, 2]


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _g_before(key, kind, a, b, gkey, gint, j):
    """True when the entry (key, kind, a, b) comes before heap slot j."""
    if key != gkey[j]:
        return key < gkey[j]
    if kind != gint[j, 0]:
        return kind < gint[j, 0]
    if a != gint[j, 1]:
        return a < gint[j, 1]
    return b < gint[j, 2]


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _g_move(gkey, gint, dst, src):
    gkey[dst] = gkey[src]
    for c in range(5):
        gint[dst, c] = gint[src, c]


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _g_entry(gkey, gint, i):
    """Heap slot i as (key, kind, a, b, va, vb)."""
    return gkey[i], gint[i, 0], gint[i, 1], gint[i, 2], gint[i, 3], gint[i, 4]


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _g_set(gkey, gint, i, key, kind, a, b, va, vb):
    """Write the entry (key, kind, a, b, va, vb) into slot i."""
    gkey[i] = key
    gint[i, 0] = kind
    gint[i, 1] = a
    gint[i, 2] = b
    gint[i, 3] = va
    gint[i, 4] = vb


# Helpers called from the greedy's loops that only read and write arrays they are given are
# compiled with _nrt=False: numba otherwise increments and decrements the reference count of
# every array argument on each call, with atomic instructions.


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _g_push(gkey, gint, size, key, kind, a, b, va, vb):
    """Push an entry; the caller guarantees capacity. Returns the new size."""
    i = size
    while i > 0:
        parent = (i - 1) >> 2
        if _g_before(key, kind, a, b, gkey, gint, parent):
            _g_move(gkey, gint, i, parent)
            i = parent
        else:
            break
    _g_set(gkey, gint, i, key, kind, a, b, va, vb)
    return size + 1


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _g_sift_down(gkey, gint, size, i, key, kind, a, b, va, vb):
    """Place an entry into the hole at slot i of a heap of size slots (smaller children move up)."""
    while True:
        first = 4 * i + 1
        if first >= size:
            break
        child = first
        end = min(first + 4, size)
        for other in range(first + 1, end):
            if _g_less(gkey, gint, other, child):
                child = other
        if _g_before(key, kind, a, b, gkey, gint, child):
            break
        _g_move(gkey, gint, i, child)
        i = child
    _g_set(gkey, gint, i, key, kind, a, b, va, vb)


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _g_pop(gkey, gint, size):
    """Remove the minimum (moved to index size-1, where the caller reads it). Returns the new size."""
    last = size - 1
    # the former last entry sifts down from the root through a hole
    key, kind, a, b, va, vb = _g_entry(gkey, gint, last)
    _g_move(gkey, gint, last, 0)
    if last > 0:
        _g_sift_down(gkey, gint, last, 0, key, kind, a, b, va, vb)
    return last


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _g_heapify(gkey, gint, size):
    """Arrange slots 0..size-1 into a 4-ary heap (sift-down from the last parent)."""
    for top in range((size - 2) // 4, -1, -1):
        key, kind, a, b, va, vb = _g_entry(gkey, gint, top)
        _g_sift_down(gkey, gint, size, top, key, kind, a, b, va, vb)


# --------------------------------------------------------------------------------------------
# two-level queue: the heap holds the entries whose key falls in a bucket up to qstate[_QCUR];
# later buckets (a bucket per quarter octave of the key) are unsorted linked lists, moved into
# the heap one bucket at a time when the heap runs empty. The greedy's keys grow over many
# orders of magnitude, so the heap stays small (cache-resident) and the far entries are never
# sifted; entries that went stale while waiting are dropped when their bucket is loaded.
# --------------------------------------------------------------------------------------------


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _q_bucket(key):
    """Bucket index of a key >= 0, non-decreasing in the key."""
    if not key > 0.0:
        return 0
    if not key < np.inf:
        return _Q_BUCKETS - 1
    if key < 2.2250738585072014e-308:  # subnormal
        mantissa, exponent = math.frexp(key)  # key = mantissa 2^exponent, mantissa in [0.5, 1)
        return (exponent + 1100) * _Q_PER_OCTAVE + int((mantissa - 0.5) * (2 * _Q_PER_OCTAVE))
    # the same from the bits of a normal float (no call into libm): exponent = biased exponent -
    # 1022, and (mantissa - 0.5) * 2 * _Q_PER_OCTAVE = _Q_PER_OCTAVE * fraction, whose integer part
    # is the fraction's top _Q_FRACTION_BITS bits
    bits = _float_bits(key)
    return ((bits >> 52) - 1022 + 1100) * _Q_PER_OCTAVE + ((bits >> (52 - _Q_FRACTION_BITS)) & (_Q_PER_OCTAVE - 1))


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _q_new(capacity):
    """An empty queue: heap (gkey, gint), far-bucket chunk pool (fkey, fint, fnext), bucket heads, state.

    Chunk c holds the entries c * _Q_CHUNK + [0, fnext[c, 2]) of fkey and fint; fnext[c, 0] links a
    bucket's chunks (its head chunk first); fnext[:, 1] is the stack of free chunk ids.
    """
    qstate = np.zeros(_NQS, np.int64)
    qstate[_QCUR] = -1
    chunks = _q_chunks(capacity)
    return (
        np.empty(capacity),
        np.empty((capacity, 5), np.int32),
        np.empty(chunks * _Q_CHUNK),
        np.empty((chunks * _Q_CHUNK, 5), np.int32),
        np.empty((chunks, 3), np.int32),
        np.full(_Q_BUCKETS, -1, np.int64),
        qstate,
    )


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _q_push(gkey, gint, gsize, fkey, fint, fnext, bhead, qstate, key, kind, a, b, va, vb):
    """Push an entry into the heap or its far bucket (the caller guarantees capacity). Returns the heap size."""
    bucket = _q_bucket(key)
    if bucket <= qstate[_QCUR]:
        return _g_push(gkey, gint, gsize, key, kind, a, b, va, vb)
    chunk = bhead[bucket]
    if chunk < 0 or fnext[chunk, 2] == _Q_CHUNK:
        if qstate[_QFREE] > 0:
            qstate[_QFREE] -= 1
            new = fnext[qstate[_QFREE], 1]
        else:
            new = qstate[_QUSED]
            qstate[_QUSED] += 1
        fnext[new, 0] = chunk
        fnext[new, 2] = 0
        bhead[bucket] = new
        chunk = new
    slot = chunk * _Q_CHUNK + fnext[chunk, 2]
    fnext[chunk, 2] += 1
    _g_set(fkey, fint, slot, key, kind, a, b, va, vb)  # a pool slot has a heap slot's layout
    qstate[_QCOUNT] += 1
    return gsize


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _q_load(gkey, gint, fkey, fint, fnext, bhead, qstate, pi):
    """Move the next non-empty far bucket(s) into the empty heap, dropping stale entries.

    An extension proxy is stale when its plane is gone or has a newer stamp, a merge when either
    plane is gone or changed (ids and versions never come back, so stale stays stale). Returns the
    heap size (0 only when the far buckets are exhausted).
    """
    size = 0
    while size == 0 and qstate[_QCOUNT] > 0:
        j = qstate[_QCUR] + 1
        while bhead[j] < 0:
            j += 1
        qstate[_QCUR] = j
        chunk = bhead[j]
        bhead[j] = -1
        while chunk >= 0:
            nxt = fnext[chunk, 0]
            for node in range(chunk * _Q_CHUNK, chunk * _Q_CHUNK + fnext[chunk, 2]):
                kind = fint[node, 0]
                a = fint[node, 1]
                b = fint[node, 2]
                keep = True
                if kind == _G_EXTEND:
                    keep = pi[a, _PALIVE] != 0 and fint[node, 3] == pi[a, _PSTAMP]
                elif kind != _G_SEED:
                    keep = (
                        pi[a, _PALIVE] != 0
                        and pi[b, _PALIVE] != 0
                        and fint[node, 3] == pi[a, _PMVER]
                        and fint[node, 4] == pi[b, _PMVER]
                    )
                if keep:
                    gkey[size] = fkey[node]
                    for c in range(5):
                        gint[size, c] = fint[node, c]
                    size += 1
            qstate[_QCOUNT] -= fnext[chunk, 2]
            fnext[qstate[_QFREE], 1] = chunk
            qstate[_QFREE] += 1
            chunk = nxt
    _g_heapify(gkey, gint, size)
    return size


# --------------------------------------------------------------------------------------------
# per-plane skew heaps of extension candidates (node pool)
#   hf[node] = (bound key, exact value); hi[node] = (pixel, version, left, right)
# --------------------------------------------------------------------------------------------


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _h_less(hf, hi, x, y):
    if hf[x, 0] != hf[y, 0]:
        return hf[x, 0] < hf[y, 0]
    return hi[x, 0] < hi[y, 0]


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _h_meld(hf, hi, x, y):
    """Meld two skew heaps (top-down, iterative). Returns the root."""
    if x < 0:
        return y
    if y < 0:
        return x
    if _h_less(hf, hi, y, x):
        x, y = y, x
    root = x
    while True:
        r = hi[x, 3]
        hi[x, 3] = hi[x, 2]
        if r < 0:
            hi[x, 2] = y
            break
        if _h_less(hf, hi, y, r):
            r, y = y, r
        hi[x, 2] = r
        x = r
    return root


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _h_drop_taken(hf, hi, owner, root, hfree):
    """Remove the tops of a plane's candidate heap whose ray another (or the same) plane has taken.

    Returns (root, hfree).
    """
    while root >= 0 and owner[hi[root, 0]] >= 0:
        newroot = _h_meld(hf, hi, hi[root, 2], hi[root, 3])
        hi[root, 2] = hfree
        hfree = root
        root = newroot
    return root, hfree


# --------------------------------------------------------------------------------------------
# helpers on plane state
# --------------------------------------------------------------------------------------------


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _find(parent, x):
    root = x
    while parent[root] != root:
        root = parent[root]
    while parent[x] != root:
        nxt = parent[x]
        parent[x] = root
        x = nxt
    return root


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _gather(pi, nextpix, p, buf, endpoints, directions, start=0):
    """Write plane p's pixel ids into buf from index start on; returns their count.

    Prefetch hints request each ray's endpoint and direction, which the fit that follows reads:
    the pixel list is a chain of dependent loads, the rays' rows are independent of each other, so
    requesting them during the walk overlaps their cache misses with it.
    """
    n = 0
    k = pi[p, _PHEAD]
    while k >= 0:
        _prefetch(endpoints, k, 0)
        _prefetch(directions, k, 0)
        buf[start + n] = k
        n += 1
        k = nextpix[k]
    return n


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _store_state(pf, p, sse, w0, w1, w2, information):
    """Store plane p's E, w (also as its linearisation point) and information."""
    pf[p, _PE] = sse
    pf[p, _PW] = w0
    pf[p, _PW + 1] = w1
    pf[p, _PW + 2] = w2
    pf[p, _PWL] = w0
    pf[p, _PWL + 1] = w1
    pf[p, _PWL + 2] = w2
    for i in range(6):
        pf[p, _PH + i] = information[i]


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _set_exact_state(endpoints, directions, pf, idx, count, p, w0, w1, w2):
    """Fit plane p exactly on idx[:count] from (w0, w1, w2) and store E, w, information, w_lin."""
    sse, w0, w1, w2, information = _fit(endpoints, directions, idx, count, w0, w1, w2, _FIT_ITERATIONS, _FIT_TOLERANCE)
    _store_state(pf, p, sse, w0, w1, w2, information)


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _put_fit(fits, r, value, w0, w1, w2, information):
    """Write a fit into row r of an (n, 10) fit table: value (SSE, m^2), w (3) and information (6)."""
    fits[r, 0] = value
    fits[r, 1] = w0
    fits[r, 2] = w1
    fits[r, 3] = w2
    for t in range(6):
        fits[r, 4 + t] = information[t]


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _get_fit(fits, r):
    """Row r of an (n, 10) fit table: (value, w0, w1, w2, information)."""
    return (
        fits[r, 0],
        fits[r, 1],
        fits[r, 2],
        fits[r, 3],
        (fits[r, 4], fits[r, 5], fits[r, 6], fits[r, 7], fits[r, 8], fits[r, 9]),
    )


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _candidate_increment(endpoints, directions, pf, p, small, idx, n, k, version, ecache_i, ecache_f):
    """Increment (m^2) of extending plane p (at its current version) by ray k.

    A small plane (small: it has at most exact_plane_size rays with k) is fitted exactly from its w
    on its rays idx[:n] (the caller gathers them) plus k, written to idx[n]; the least-SSE candidate
    fit of p's current version is kept in (ecache_i, ecache_f)[p] (ray, version; SSE, w,
    information), so that executing that extension needs no fit: it is the same fit (same rays in
    the same order, same start) that _set_exact_state would make. A large plane uses its model.
    """
    if not small:
        return _model_extension(endpoints, directions, pf, p, k)[0]
    idx[n] = k
    sse, w0, w1, w2, information = _fit(
        endpoints, directions, idx, n + 1, pf[p, _PW], pf[p, _PW + 1], pf[p, _PW + 2], _FIT_ITERATIONS, _FIT_TOLERANCE
    )
    if ecache_i[p, 1] != version or sse < ecache_f[p, 0]:
        ecache_i[p, 0] = k
        ecache_i[p, 1] = version
        _put_fit(ecache_f, p, sse, w0, w1, w2, information)
    return sse - pf[p, _PE]


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _relinearise(endpoints, directions, pf, idx, count, p):
    """Re-linearise large plane p on its rays idx[:count]: one Gauss-Newton step from its current w.

    The model's w is already close to the minimiser (rank-one updates), so one step brings it to
    within the Gauss-Newton rate of convergence; E becomes the SSE at the new w predicted by the
    linearisation and the information is the Gauss-Newton J^T J at the current w.
    """
    w0 = pf[p, _PW]
    w1 = pf[p, _PW + 1]
    w2 = pf[p, _PW + 2]
    sse, a00, a01, a02, a11, a12, a22, b0, b1, b2 = _gn_pass(endpoints, directions, idx, count, w0, w1, w2)
    d0, d1, d2, ok = _solve_sym3(a00, a01, a02, a11, a12, a22, b0, b1, b2)
    if not (ok and np.isfinite(sse)):
        _set_exact_state(endpoints, directions, pf, idx, count, p, w0, w1, w2)
        return
    _store_state(
        pf, p, max(sse - (d0 * b0 + d1 * b1 + d2 * b2), 0.0), w0 - d0, w1 - d1, w2 - d2, (a00, a01, a02, a11, a12, a22)
    )


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _model_extension(endpoints, directions, pf, p, k):
    """Increment of adding ray k to plane p under p's quadratic model (rank-one update).

    Returns (increment, x0, x1, x2, f, g0, g1, g2) with x = H^-1 g.
    """
    w0 = pf[p, _PW]
    w1 = pf[p, _PW + 1]
    w2 = pf[p, _PW + 2]
    f, g0, g1, g2 = _ray_terms(endpoints, directions, k, w0, w1, w2)
    x0, x1, x2, ok = _solve_sym3(
        pf[p, _PH], pf[p, _PH + 1], pf[p, _PH + 2], pf[p, _PH + 3], pf[p, _PH + 4], pf[p, _PH + 5], g0, g1, g2
    )
    if not ok or not np.isfinite(f):
        return np.inf, 0.0, 0.0, 0.0, f, g0, g1, g2
    denom = 1.0 + g0 * x0 + g1 * x1 + g2 * x2
    return f * f / denom, x0, x1, x2, f, g0, g1, g2


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _model_merge_terms(pf, a, b):
    """Ha (w_a - w_b), Hb (w_a - w_b) and S = Ha + Hb (6) of planes a, b: the merge model's system."""
    # scalar reads (no array views: a view costs reference counting in the hot loop)
    ha0, ha1, ha2, ha3, ha4, ha5 = (
        pf[a, _PH],
        pf[a, _PH + 1],
        pf[a, _PH + 2],
        pf[a, _PH + 3],
        pf[a, _PH + 4],
        pf[a, _PH + 5],
    )
    hb0, hb1, hb2, hb3, hb4, hb5 = (
        pf[b, _PH],
        pf[b, _PH + 1],
        pf[b, _PH + 2],
        pf[b, _PH + 3],
        pf[b, _PH + 4],
        pf[b, _PH + 5],
    )
    d0 = pf[a, _PW] - pf[b, _PW]
    d1 = pf[a, _PW + 1] - pf[b, _PW + 1]
    d2 = pf[a, _PW + 2] - pf[b, _PW + 2]
    # Ha d, Hb d
    ad0 = ha0 * d0 + ha1 * d1 + ha2 * d2
    ad1 = ha1 * d0 + ha3 * d1 + ha4 * d2
    ad2 = ha2 * d0 + ha4 * d1 + ha5 * d2
    bd0 = hb0 * d0 + hb1 * d1 + hb2 * d2
    bd1 = hb1 * d0 + hb3 * d1 + hb4 * d2
    bd2 = hb2 * d0 + hb4 * d1 + hb5 * d2
    return (ad0, ad1, ad2), (bd0, bd1, bd2), (ha0 + hb0, ha1 + hb1, ha2 + hb2, ha3 + hb3, ha4 + hb4, ha5 + hb5)


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _model_merge_increment_of(ad, bd, s):
    """Merge increment (ad^T S^-1 bd, at least 0; inf when S is singular) of the terms of _model_merge_terms."""
    y0, y1, y2, ok = _solve_sym3(s[0], s[1], s[2], s[3], s[4], s[5], bd[0], bd[1], bd[2])
    if not ok:
        return np.inf
    inc = ad[0] * y0 + ad[1] * y1 + ad[2] * y2
    if inc < 0.0:
        inc = 0.0
    return inc


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _model_merge_increment(pf, a, b):
    """Merge increment of planes a, b under their quadratic models (inf when the models are singular)."""
    ad, bd, s = _model_merge_terms(pf, a, b)
    return _model_merge_increment_of(ad, bd, s)


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _model_merge(pf, a, b):
    """Merge increment of planes a, b under their quadratic models and the merged w."""
    ad, bd, s = _model_merge_terms(pf, a, b)
    inc = _model_merge_increment_of(ad, bd, s)
    if not inc < np.inf:
        return np.inf, np.nan, np.nan, np.nan
    # merged w = w_b + S^-1 Ha (w_a - w_b)
    z0, z1, z2, _ = _solve_sym3(s[0], s[1], s[2], s[3], s[4], s[5], ad[0], ad[1], ad[2])
    return inc, pf[b, _PW] + z0, pf[b, _PW + 1] + z1, pf[b, _PW + 2] + z2


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _model_offset(pf, big, w0, w1, w2):
    """Plane big's information H (6), e = w - w_big (3) and H e (3): its quadratic model at w is
    E_big + e^T H e, with half gradient H e."""
    h0, h1, h2, h3, h4, h5 = (
        pf[big, _PH],
        pf[big, _PH + 1],
        pf[big, _PH + 2],
        pf[big, _PH + 3],
        pf[big, _PH + 4],
        pf[big, _PH + 5],
    )
    e0 = w0 - pf[big, _PW]
    e1 = w1 - pf[big, _PW + 1]
    e2 = w2 - pf[big, _PW + 2]
    he = (h0 * e0 + h1 * e1 + h2 * e2, h1 * e0 + h3 * e1 + h4 * e2, h2 * e0 + h4 * e1 + h5 * e2)
    return (h0, h1, h2, h3, h4, h5), (e0, e1, e2), he


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _hybrid_pass(endpoints, directions, pf, big, idx, count, w0, w1, w2):
    """model_big(w) + exact radial SSE of rays idx[:count] at w, with its Gauss-Newton system.

    Returns (value, info6, r0, r1, r2): info6 = H_big + J^T J (a tuple a00 a01 a02 a11 a12 a22) and
    r = H_big (w - w_big) + J^T f.
    """
    (h0, h1, h2, h3, h4, h5), (e0, e1, e2), (r0, r1, r2) = _model_offset(pf, big, w0, w1, w2)
    value = pf[big, _PE] + e0 * r0 + e1 * r1 + e2 * r2
    for t in range(count):
        f, g0, g1, g2 = _ray_terms(endpoints, directions, idx[t], w0, w1, w2)
        value += f * f
        h0 += g0 * g0
        h1 += g0 * g1
        h2 += g0 * g2
        h3 += g1 * g1
        h4 += g1 * g2
        h5 += g2 * g2
        r0 += g0 * f
        r1 += g1 * f
        r2 += g2 * f
    return value, (h0, h1, h2, h3, h4, h5), r0, r1, r2


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _hybrid_merge(endpoints, directions, pf, big, idx, count, w0, w1, w2):
    """min over w of model_big(w) + exact SSE of rays idx[:count] (Gauss-Newton with step halving).

    One pass over the rays per iteration (the pass at a trial point gives its value and, when
    accepted, the next system). Returns (value, w0, w1, w2, info6, r3) where info6 is the information
    matrix and r3 the half gradient H_big (w - w_big) + J^T f at the returned w.
    """
    value, info, r0, r1, r2 = _hybrid_pass(endpoints, directions, pf, big, idx, count, w0, w1, w2)
    for _ in range(_FIT_ITERATIONS):
        d0, d1, d2, ok = _solve_sym3(info[0], info[1], info[2], info[3], info[4], info[5], r0, r1, r2)
        if not ok:
            break
        if not (d0 * r0 + d1 * r1 + d2 * r2) > _FIT_TOLERANCE * value:
            break
        step = 1.0
        improved = False
        for _h in range(30):
            n0 = w0 - step * d0
            n1 = w1 - step * d1
            n2 = w2 - step * d2
            trial = _hybrid_pass(endpoints, directions, pf, big, idx, count, n0, n1, n2)
            if trial[0] <= value:
                improved = True
                break
            step *= 0.5
        if not improved:
            break
        decrease = value - trial[0]
        w0, w1, w2 = n0, n1, n2
        value, info, r0, r1, r2 = trial
        if decrease <= _FIT_TOLERANCE * value:
            break
    return value, w0, w1, w2, info, (r0, r1, r2)


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _keep_refined_merge(rcache_i, rcache_f, pf, pi, big, small, e_small, value, w0, w1, w2, info, r):
    """Keep the small plane's exact residuals of a refined hybrid merge as a quadratic model at its w.

    value, info, r: _hybrid_merge's result at w; e_small: the small plane's exact E (m^2). Stored on
    the small plane: the partner (pf's _PRPARTNER); its own version and the partner's ray count
    (rcache_i); its SSE at w minus e_small, its half gradient J^T f (3) and Gauss-Newton information
    J^T J (6) at w, and w (3) (rcache_f).
    """
    (h0, h1, h2, h3, h4, h5), (e0, e1, e2), (he0, he1, he2) = _model_offset(pf, big, w0, w1, w2)
    pf[small, _PRPARTNER] = big
    rcache_i[small, 0] = pi[small, _PVER]
    rcache_i[small, 1] = pi[big, _PCOUNT]
    rcache_f[small, 0] = value - (pf[big, _PE] + e0 * he0 + e1 * he1 + e2 * he2) - e_small
    rcache_f[small, 1] = r[0] - he0
    rcache_f[small, 2] = r[1] - he1
    rcache_f[small, 3] = r[2] - he2
    rcache_f[small, 4] = info[0] - h0
    rcache_f[small, 5] = info[1] - h1
    rcache_f[small, 6] = info[2] - h2
    rcache_f[small, 7] = info[3] - h3
    rcache_f[small, 8] = info[4] - h4
    rcache_f[small, 9] = info[5] - h5
    rcache_f[small, 10] = w0
    rcache_f[small, 11] = w1
    rcache_f[small, 12] = w2


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _refined_merge_increment(pf, big, rcache_f, small):
    """Merge increment (m^2) of big's current model plus small's residual model kept by _keep_refined_merge.

    min over w of E_big + (w - w_big)^T H_big (w - w_big) + s + 2 r^T u + u^T H_s u (u = w - w*),
    minus E_big and small's exact E: excess + e^T H_big e - c^T S^-1 c with e = w* - w_big,
    c = H_big e + r, S = H_big + H_s (the minimiser is u = -S^-1 c). Equals the refined increment
    while big is unchanged.
    """
    (h0, h1, h2, h3, h4, h5), (e0, e1, e2), (he0, he1, he2) = _model_offset(
        pf, big, rcache_f[small, 10], rcache_f[small, 11], rcache_f[small, 12]
    )
    c0 = he0 + rcache_f[small, 1]
    c1 = he1 + rcache_f[small, 2]
    c2 = he2 + rcache_f[small, 3]
    y0, y1, y2, ok = _solve_sym3(
        h0 + rcache_f[small, 4],
        h1 + rcache_f[small, 5],
        h2 + rcache_f[small, 6],
        h3 + rcache_f[small, 7],
        h4 + rcache_f[small, 8],
        h5 + rcache_f[small, 9],
        c0,
        c1,
        c2,
    )
    if not ok:
        return np.inf
    inc = rcache_f[small, 0] + e0 * he0 + e1 * he1 + e2 * he2 - (c0 * y0 + c1 * y1 + c2 * y2)
    if inc < 0.0:
        inc = 0.0
    return inc


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _union_fit(endpoints, directions, pf, idx, count, a, b):
    """Exact fit of the union of planes a and b (rays idx[:count]); both planes' states are exact fits.

    Starts from the merged w of the two planes' quadratic models. The radial SSE of rays on two
    different surfaces can have several local minima, so when the increment found there disagrees
    with the models' by more than UNION_MODEL_AGREEMENT (relative), the fit also starts from a's
    plane, b's plane and the algebraic fit and keeps the least SSE (on the SynPEB and Ouster scans
    the models agree within 5 % and all four starts reach the same minimum).
    Returns (sse, w0, w1, w2).
    """
    model_inc, m0, m1, m2 = _model_merge(pf, a, b)
    best = np.inf
    b0 = np.nan
    b1 = np.nan
    b2 = np.nan
    if model_inc < np.inf:
        best, b0, b1, b2 = _fit_rays(endpoints, directions, idx, count, m0, m1, m2, _FIT_ITERATIONS, _FIT_TOLERANCE)
        inc = best - pf[a, _PE] - pf[b, _PE]
        if best < np.inf and abs(inc - model_inc) <= UNION_MODEL_AGREEMENT * max(inc, model_inc):
            return best, b0, b1, b2
    sse, w0, w1, w2 = _fit_rays(
        endpoints, directions, idx, count, pf[a, _PW], pf[a, _PW + 1], pf[a, _PW + 2], _FIT_ITERATIONS, _FIT_TOLERANCE
    )
    if sse < best:
        best, b0, b1, b2 = sse, w0, w1, w2
    sse, w0, w1, w2 = _fit_rays(
        endpoints, directions, idx, count, pf[b, _PW], pf[b, _PW + 1], pf[b, _PW + 2], _FIT_ITERATIONS, _FIT_TOLERANCE
    )
    if sse < best:
        best, b0, b1, b2 = sse, w0, w1, w2
    sse, w0, w1, w2 = _fit_rays(
        endpoints, directions, idx, count, np.nan, np.nan, np.nan, _FIT_ITERATIONS, _FIT_TOLERANCE
    )
    if sse < best:
        best, b0, b1, b2 = sse, w0, w1, w2
    return best, b0, b1, b2


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _cache_merge(mcache_i, mcache_f, a, b, va, vb, value, w0, w1, w2, info):
    """Remember the refined merge of planes a < b at versions (va, vb): its value, merged w and information."""
    mcache_i[a, 0] = b
    mcache_i[a, 1] = va
    mcache_i[a, 2] = vb
    _put_fit(mcache_f, a, value, w0, w1, w2, info)


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _release_deferred(gkey, gint, gsize, fkey, fint, fnext, bhead, qstate, anode, akey, pf, p, first, n, proxy_key):
    """Queue the merges deferred on plane p's adjacency nodes first..first+n whose key is at most
    proxy_key (p's proxy key, m^2); store the least key left deferred in p's row. Returns the heap size."""
    least = np.inf
    for x in range(first, first + n):
        if akey[x, _AN_KEY] <= proxy_key and akey[x, _AN_KEY] < np.inf:
            q = anode[x, _AN_PLANE]
            gsize = _q_push(
                gkey,
                gint,
                gsize,
                fkey,
                fint,
                fnext,
                bhead,
                qstate,
                akey[x, _AN_KEY],
                anode[x, _AN_KIND],
                min(p, q),
                max(p, q),
                anode[x, _AN_VA],
                anode[x, _AN_VB],
            )
            akey[x, _AN_KEY] = np.inf
        elif akey[x, _AN_KEY] < least:
            least = akey[x, _AN_KEY]
    pf[p, _PDEFER] = least
    return gsize


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _queue_proxy(gkey, gint, gsize, fkey, fint, fnext, bhead, qstate, hf, hi, pf, pi, p, cutoff):
    """Queue plane p's extension proxy for the top of its candidate heap (the caller reserves room).

    Its key is the top's exact increment when that is current, else the top's lower bound; a new
    stamp makes earlier proxies of p stale. The entry is (key, _G_EXTEND, p, top's ray, stamp, top's
    node): the node only serves as a prefetch hint when the entry is next in the heap. Returns
    (gsize, proxy key; inf when none is queued).
    """
    root = pi[p, _PROOT]
    if root < 0:
        return gsize, np.inf
    if hi[root, 1] == pi[p, _PVER]:
        pkey = hf[root, 1] - pf[p, _PE]
    else:
        pkey = hf[root, 0] - pf[p, _PE]
    pi[p, _PSTAMP] += 1
    if pkey > cutoff:
        return gsize, np.inf
    return _q_push(
        gkey, gint, gsize, fkey, fint, fnext, bhead, qstate, pkey, _G_EXTEND, p, hi[root, 0], pi[p, _PSTAMP], root
    ), pkey


# --------------------------------------------------------------------------------------------
# adjacency segments: each plane's neighbour nodes are contiguous rows of one pool, so that the
# loops over a plane's neighbours read memory in order (a linked list of nodes scattered over the
# pool made them wait on a cache miss per neighbour). Segments have power-of-two sizes; freed ones
# are kept on a free list per size.
# --------------------------------------------------------------------------------------------


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _adj_class(rows):
    """Size class and size of the smallest segment of at least rows rows."""
    c = 0
    size = _ADJ_MIN_ROWS
    while size < rows:
        size *= 2
        c += 1
    return c, size


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _adj_copy(anode, dst, src, n):
    """Copy n adjacency nodes from row src on to row dst on."""
    for t in range(n):
        for f in range(_AN_FIELDS):
            anode[dst + t, f] = anode[src + t, f]


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _adj_release(anode, afree, start, rows):
    """Put the segment of rows rows at start on its size's free list (linked through its first row)."""
    c, _ = _adj_class(rows)
    anode[start, 0] = afree[c]
    afree[c] = start


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _adj_move(anode, afree, pi, x, rows, aused):
    """Move plane x's adjacency nodes to a segment of at least rows rows; returns aused (-1: the pool is full)."""
    c, size = _adj_class(rows)
    start = afree[c]
    if start >= 0:
        afree[c] = anode[start, 0]
    else:
        start = aused
        if start + size > anode.shape[0]:
            return -1
        aused = start + size
    old = pi[x, _PADJ]
    if old >= 0:
        _adj_copy(anode, start, old, pi[x, _PADJN])
        _adj_release(anode, afree, old, pi[x, _PADJC])
    pi[x, _PADJ] = start
    pi[x, _PADJC] = size
    return aused


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _adj_append(anode, akey, afree, pi, x, y, aused):
    """Add plane y to plane x's neighbours; returns aused (-1: the pool is full).

    Nothing is added when y is already x's last neighbour node (a plane growing along another
    appends itself to the other's list once per new pixel; x's merge loop keeps the first node of
    each neighbour anyway).
    """
    n = pi[x, _PADJN]
    if n > 0 and anode[pi[x, _PADJ] + n - 1, _AN_PLANE] == y:
        return aused
    if n == pi[x, _PADJC]:
        aused = _adj_move(anode, afree, pi, x, n + 1, aused)
        if aused < 0:
            return -1
    row = pi[x, _PADJ] + n
    anode[row, _AN_PLANE] = y
    akey[row, _AN_KEY] = np.inf
    pi[x, _PADJN] = n + 1
    return aused


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _adj_concat(anode, afree, pi, s, o, aused):
    """Append plane o's neighbour nodes to plane s's and free o's segment; returns aused (-1: the pool is full)."""
    ns = pi[s, _PADJN]
    no = pi[o, _PADJN]
    if ns + no > pi[s, _PADJC]:
        aused = _adj_move(anode, afree, pi, s, ns + no, aused)
        if aused < 0:
            return -1
    start = pi[s, _PADJ]
    old = pi[o, _PADJ]
    if old >= 0:
        _adj_copy(anode, start + ns, old, no)
        _adj_release(anode, afree, old, pi[o, _PADJC])
    pi[s, _PADJN] = ns + no
    pi[o, _PADJ] = -1
    pi[o, _PADJN] = 0
    pi[o, _PADJC] = 0
    return aused


# --------------------------------------------------------------------------------------------
# the greedy kernel
# --------------------------------------------------------------------------------------------


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _aligned(offset):
    """The next multiple of 8 elements (64 bytes) from offset: every work array starts on a cache line."""
    return (offset + 7) & ~7


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _work_sizes(n_pixels, gcap, hcap, acap):
    """Elements of the kernel's float64, int64 and int32 work buffers (the kernel's views, in its order)."""
    a = _aligned
    far = _q_chunks(gcap) * _Q_CHUNK
    n_f = (
        a(n_pixels * (_NPF + 10))
        + a(gcap)
        + a(far)
        + a(hcap * 2)
        + a(n_pixels * 10)
        + a(n_pixels * 13)
        + a(n_pixels + 1)
    )
    n_i = 2 * a(n_pixels) + a(_Q_BUCKETS) + a(acap * _AN_FIELDS) + 2 * a(n_pixels + 1)
    n_i32 = (
        5 * a(n_pixels)
        + a(hcap * 4)
        + a(n_pixels * _NPI)
        + a(gcap * 5)
        + a(far * 5)
        + a(far // _Q_CHUNK * 3)
        + a(n_pixels * 3)
        + 2 * a(n_pixels * 2)
        + a(n_pixels + 1)
    )
    return n_f, n_i, n_i32


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _run_cutoff(max_increment, min_count, n_pixels):
    """The largest key (m^2) a run can execute: entries above it never are (the run stops before any
    action above max_increment unless a plane-count target, min_count < n_pixels, keeps it going).
    The greedy drops such entries and the seed stage does not fit seeds provably above it."""
    return np.inf if min_count < n_pixels else max_increment


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _empty_log(stats, overflow):
    """The kernel's result when a pool ran out: an empty action log, its stats and overflow."""
    return (np.empty(0, np.int8), np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0), stats, overflow)


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _ppe_kernel(
    endpoints,
    directions,
    valid,
    ok_right,
    ok_down,
    height,
    width,
    offsets,
    seed_sse,
    seed_best,
    seed_key,
    exact_plane_size,
    exact_merge_size,
    drift_limit,
    max_increment,
    min_count,
    slack,
    model_key_factor,
    refined_growth,
    merge_loop_growth,
    defer_merges,
    gcap,
    hcap,
    acap,
    work_f,
    work_i,
    work_i32,
):
    """Run the greedy PPE agglomeration; returns the action log (kind, a, b, increment), stats and overflow.

    seed_sse, seed_best, seed_key: _seed_errors's table and each anchor's best config and key.
    refined_growth, merge_loop_growth: extract_plane_hierarchy's refined_merge_growth and
    merge_loop_growth (0: off).
    Runs while a candidate exists and (next increment <= max_increment or plane count > min_count).
    The work pools have fixed capacities (queue gcap, candidate nodes hcap, adjacency nodes acap) so
    that no array is reassigned inside the loops: numba then keeps reference counting (atomic
    instructions) out of them. When a pool would run out, the kernel stops at once and returns an
    empty log with ``overflow`` (3,) holding the capacity each pool needs (0: enough); the caller
    runs it again with larger pools (the greedy is deterministic, so the result is the same).
    Its arrays are views of the work buffers work_f (float64), work_i (int64) and work_i32 (int32)
    of at least the sizes _work_sizes gives, which the caller reuses from call to call.
    """
    n_pixels = height * width
    n_valid = 0
    for k in range(n_pixels):
        if valid[k]:
            n_valid += 1

    # work memory: views of the caller's buffers, which a thread reuses from call to call (fresh
    # memory would cost a page fault per 4 KiB page on first touch, tens of thousands per scan).
    # The slicing is written out here: views returned by a helper function made numba count
    # references inside the greedy's loops (checked in the machine code)
    n_f, n_i, n_i32 = _work_sizes(n_pixels, gcap, hcap, acap)
    if len(work_f) < n_f or len(work_i) < n_i or len(work_i32) < n_i32:
        raise ValueError('work buffers smaller than _work_sizes')
    of = 0
    oi = 0
    o32 = 0
    # pixel state. Pixel, plane and node ids, versions and stamps are 32-bit wherever they are
    # stored (each is below 2^31 for the scans extract_plane_hierarchy accepts, < MAX_RAYS): the
    # greedy waits on memory, and narrower arrays mean fewer cache misses
    owner = work_i32[o32 : o32 + n_pixels]
    o32 = _aligned(o32 + n_pixels)
    nextpix = work_i32[o32 : o32 + n_pixels]
    o32 = _aligned(o32 + n_pixels)
    parent = work_i32[o32 : o32 + n_pixels]
    o32 = _aligned(o32 + n_pixels)
    buf = work_i[oi : oi + n_pixels]
    oi = _aligned(oi + n_pixels)
    buf2 = work_i[oi : oi + n_pixels]
    oi = _aligned(oi + n_pixels)
    seen = work_i32[o32 : o32 + n_pixels]
    o32 = _aligned(o32 + n_pixels)
    # the plane (an id that may have been merged since) that last queued an extension candidate
    # for each ray: while it resolves to a live plane p, p's candidate heap holds a node for the ray
    candidate_of = work_i32[o32 : o32 + n_pixels]
    o32 = _aligned(o32 + n_pixels)
    candidate_of[:] = -1
    owner[:] = -1
    # parent, seen and the plane rows below are read only for plane ids (anchors of created
    # planes) and written when a plane is created; pixel lists are written as they grow
    seen_stamp = 0

    # plane state
    prow = work_f[of : of + n_pixels * (_NPF + 10)].reshape((n_pixels, _NPF + 10))
    of = _aligned(of + n_pixels * (_NPF + 10))
    # a plane's float state and its candidate-fit slot (ecache_f below) share a row: a plane's
    # action reads and writes both; a plane's row is written when it is created
    pf = prow[:, :_NPF]
    ecache_f = prow[:, _NPF:]
    # 32-bit fields (half the memory traffic of a plane's row): counts, versions and pixel ids are
    # below H*W, stamps below the number of pops, node indices below the pools' sizes (a few times
    # H*W), all below 2^31 for the scans extract_plane_hierarchy accepts (< MAX_RAYS)
    pi = work_i32[o32 : o32 + n_pixels * _NPI].reshape((n_pixels, _NPI))
    o32 = _aligned(o32 + n_pixels * _NPI)

    # global heap
    overflow = np.zeros(3, np.int64)
    # kind, ids and versions all < 2^31 (ids < H*W); the far-bucket pool holds the heap's
    # capacity (heap entries + far entries <= gcap) in chunks
    n_chunks = _q_chunks(gcap)
    gkey = work_f[of : of + gcap]
    of = _aligned(of + gcap)
    fkey = work_f[of : of + n_chunks * _Q_CHUNK]
    of = _aligned(of + n_chunks * _Q_CHUNK)
    gint = work_i32[o32 : o32 + gcap * 5].reshape((gcap, 5))
    o32 = _aligned(o32 + gcap * 5)
    fint = work_i32[o32 : o32 + n_chunks * _Q_CHUNK * 5].reshape((n_chunks * _Q_CHUNK, 5))
    o32 = _aligned(o32 + n_chunks * _Q_CHUNK * 5)
    fnext = work_i32[o32 : o32 + n_chunks * 3].reshape((n_chunks, 3))
    o32 = _aligned(o32 + n_chunks * 3)
    bhead = work_i[oi : oi + _Q_BUCKETS]
    oi = _aligned(oi + _Q_BUCKETS)
    bhead[:] = -1
    qstate = np.zeros(_NQS, np.int64)
    qstate[_QCUR] = -1
    gsize = 0

    # skew heap node pool
    hf = work_f[of : of + hcap * 2].reshape((hcap, 2))
    of = _aligned(of + hcap * 2)
    hi = work_i32[o32 : o32 + hcap * 4].reshape((hcap, 4))
    o32 = _aligned(o32 + hcap * 4)
    hused = 0
    hfree = -1

    # adjacency pool (a segment of neighbouring plane ids per plane), one row per node so that a
    # node is one memory access: neighbour and a merge deferred on the owner's node (its kind, the
    # two versions it was valued at, and its key (inf: none) in the float view akey)
    anode = work_i[oi : oi + acap * _AN_FIELDS].reshape((acap, _AN_FIELDS))
    oi = _aligned(oi + acap * _AN_FIELDS)
    akey = anode.view(np.float64)
    aused = 0
    afree = np.full(_ADJ_CLASSES, -1, np.int64)

    # the last merge refined per plane (keyed by its smaller id): partner, both versions; value, w, information
    mcache_i = work_i32[o32 : o32 + n_pixels * 3].reshape((n_pixels, 3))
    o32 = _aligned(o32 + n_pixels * 3)
    mcache_f = work_f[of : of + n_pixels * 10].reshape((n_pixels, 10))
    of = _aligned(of + n_pixels * 10)
    # the last hybrid merge refined per plane, on its smaller plane (_keep_refined_merge; the
    # partner is in the plane's float row): own version, partner's count; the plane's residual
    # model at the union's w
    rcache_i = work_i32[o32 : o32 + n_pixels * 2].reshape((n_pixels, 2))
    o32 = _aligned(o32 + n_pixels * 2)
    rcache_f = work_f[of : of + n_pixels * 13].reshape((n_pixels, 13))
    of = _aligned(of + n_pixels * 13)
    # the least candidate fit of each small plane's current version: ray, version (here); SSE, w,
    # information (ecache_f, in the plane's float row)
    ecache_i = work_i32[o32 : o32 + n_pixels * 2].reshape((n_pixels, 2))
    o32 = _aligned(o32 + n_pixels * 2)

    # action log
    log_kind = work_i32[o32 : o32 + n_pixels + 1]
    o32 = _aligned(o32 + n_pixels + 1)
    log_a = work_i[oi : oi + n_pixels + 1]
    oi = _aligned(oi + n_pixels + 1)
    log_b = work_i[oi : oi + n_pixels + 1]
    oi = _aligned(oi + n_pixels + 1)
    log_inc = work_f[of : of + n_pixels + 1]
    of = _aligned(of + n_pixels + 1)
    n_actions = 0

    cutoff = _run_cutoff(max_increment, min_count, n_pixels)
    model_cutoff = MODEL_CUTOFF_FACTOR * cutoff

    # initial seeds: the best valid config of every anchor (seed_best, seed_key from _seed_errors)
    # up to the cutoff, in a sorted array (next-best seeds of anchors whose best seed became
    # invalid go through the heap); ties by anchor id; the keys in that order too
    # (seed_key[seed_order[i]] would be a random access)
    seed_order, seed_sorted_key = _sort_seed_keys(seed_key, cutoff)
    seed_sorted_best = np.empty(len(seed_order), np.int32)  # read in order with the keys
    for t in range(len(seed_order)):
        seed_sorted_best[t] = seed_best[seed_order[t]]
    n_seeds = len(seed_order)
    seed_ptr = 0

    plane_count = n_valid
    version_counter = 0
    stats = np.zeros(_N_STATS, np.int64)
    cell = np.empty(4, np.int64)
    nb_pix = np.empty(4, np.int64)

    while True:
        # ---------------- capacity (the loop below pushes a bounded number of entries) -------
        # ---------------- find the next action with an exact key ----------------------------
        found = False
        key = 0.0
        kind = 0
        act_a = 0
        act_b = 0
        while gsize > 0 or qstate[_QCOUNT] > 0 or seed_ptr < n_seeds:
            if gsize + qstate[_QCOUNT] + 8 >= gcap:
                overflow[0] = 2 * gcap
            if gsize == 0 and qstate[_QCOUNT] > 0:
                gsize = _q_load(gkey, gint, fkey, fint, fnext, bhead, qstate, pi)
                if gsize == 0 and seed_ptr >= n_seeds:
                    break
            if hused + 8 >= hcap:
                overflow[1] = 2 * hcap
            if overflow[0] > 0 or overflow[1] > 0 or overflow[2] > 0:
                return _empty_log(stats, overflow)
            # the next entry: the sorted initial seeds or the heap, whichever comes first
            take_sorted = False
            if seed_ptr < n_seeds:
                sa = seed_order[seed_ptr]
                if gsize == 0:
                    take_sorted = True
                else:
                    sk = seed_sorted_key[seed_ptr]
                    if sk < gkey[0] or (
                        sk == gkey[0]
                        and (
                            gint[0, 0] > _G_SEED
                            or (
                                gint[0, 0] == _G_SEED
                                and (gint[0, 1] > sa or (gint[0, 1] == sa and gint[0, 2] > seed_sorted_best[seed_ptr]))
                            )
                        )
                    ):
                        take_sorted = True
            if take_sorted:
                key = seed_sorted_key[seed_ptr]
                kind = _G_SEED
                ea = sa
                eb = seed_sorted_best[seed_ptr]
                eva = 0
                evb = 0
                seed_ptr += 1
            else:
                gsize = _g_pop(gkey, gint, gsize)
                key, kind, ea, eb, eva, evb = _g_entry(gkey, gint, gsize)
                if gsize > 0:  # the next entry's planes load while this one is handled
                    _prefetch(pi, gint[0, 1], 0)
                    _prefetch(pf, gint[0, 1], 0)
                    if gint[0, 0] == _G_EXTEND:  # its candidate node (at the push) and ray
                        _prefetch(hi, gint[0, 4], 0)
                        _prefetch(hf, gint[0, 4], 0)
                        _prefetch(owner, gint[0, 2], 0)
                    else:
                        _prefetch(pi, gint[0, 2], 0)
            stats[_ST_POPS] += 1
            if kind == _G_SEED:
                anchor = ea
                c = eb
                ok = True
                i = anchor // width
                j = anchor % width
                for t in range(4):
                    k = (i + offsets[c, t, 0]) * width + (j + offsets[c, t, 1])
                    if owner[k] >= 0:
                        ok = False
                        break
                if ok:
                    found = True
                    act_a = anchor
                    act_b = c
                    break
                # next best valid seed of this anchor after (key, c); none when the anchor's own
                # ray is taken (every tetromino contains its anchor)
                best = -1
                for c2 in range(17 if owner[anchor] < 0 else 0):
                    e2 = seed_sse[anchor, c2]
                    if not np.isfinite(e2):
                        continue
                    if e2 < key or (e2 == key and c2 <= c):
                        continue
                    ok2 = True
                    for t in range(4):
                        k = (i + offsets[c2, t, 0]) * width + (j + offsets[c2, t, 1])
                        if owner[k] >= 0:
                            ok2 = False
                            break
                    if not ok2:
                        continue
                    if best < 0 or e2 < seed_sse[anchor, best]:
                        best = c2
                if best >= 0 and seed_sse[anchor, best] <= cutoff:
                    gsize = _q_push(
                        gkey,
                        gint,
                        gsize,
                        fkey,
                        fint,
                        fnext,
                        bhead,
                        qstate,
                        seed_sse[anchor, best],
                        _G_SEED,
                        anchor,
                        best,
                        0,
                        0,
                    )
            elif kind == _G_EXTEND:
                p = ea
                if pi[p, _PALIVE] == 0 or eva != pi[p, _PSTAMP]:
                    continue
                # candidate rays taken by another plane since: drop them
                root, hfree = _h_drop_taken(hf, hi, owner, pi[p, _PROOT], hfree)
                pi[p, _PROOT] = root
                k = hi[root, 0] if root >= 0 else -1
                if root < 0 or k != eb:
                    pass  # the proxy's candidate was dropped: re-queue the proxy for the new top
                elif hi[root, 1] == pi[p, _PVER]:
                    inc = hf[root, 1] - pf[p, _PE]
                    if key >= inc:
                        found = True
                        key = inc
                        act_a = p
                        act_b = k
                        break
                    # (the proxy key was a bound): fall through to re-push with the exact key
                else:
                    # stale bound: evaluate exactly for the current version and re-insert
                    stats[_ST_REEVALS] += 1
                    newroot = _h_meld(hf, hi, hi[root, 2], hi[root, 3])
                    small = pi[p, _PCOUNT] + 1 <= exact_plane_size
                    n = _gather(pi, nextpix, p, buf, endpoints, directions) if small else 0
                    inc = _candidate_increment(
                        endpoints, directions, pf, p, small, buf, n, k, pi[p, _PVER], ecache_i, ecache_f
                    )
                    if inc < 0.0:
                        inc = 0.0
                    value = pf[p, _PE] + inc
                    hf[root, 0] = value - slack * abs(value)
                    hf[root, 1] = value
                    hi[root, 1] = pi[p, _PVER]
                    hi[root, 2] = -1
                    hi[root, 3] = -1
                    if not np.isfinite(value):
                        hi[root, 2] = hfree
                        hfree = root
                        pi[p, _PROOT] = newroot
                        if candidate_of[k] >= 0 and _find(parent, candidate_of[k]) == p:
                            candidate_of[k] = -1  # p may hold no other node for k
                    else:
                        pi[p, _PROOT] = _h_meld(hf, hi, newroot, root)
                # push the plane's proxy with its current top, then release the merges deferred
                # behind the old proxy that the new one does not precede
                gsize, proxy_key = _queue_proxy(
                    gkey, gint, gsize, fkey, fint, fnext, bhead, qstate, hf, hi, pf, pi, p, cutoff
                )
                if gsize + qstate[_QCOUNT] + pi[p, _PADJN] + 8 >= gcap:
                    overflow[0] = 2 * (gcap + pi[p, _PADJN])
                    return _empty_log(stats, overflow)
                if pf[p, _PDEFER] <= proxy_key and pf[p, _PDEFER] < np.inf:
                    gsize = _release_deferred(
                        gkey,
                        gint,
                        gsize,
                        fkey,
                        fint,
                        fnext,
                        bhead,
                        qstate,
                        anode,
                        akey,
                        pf,
                        p,
                        pi[p, _PADJ],
                        pi[p, _PADJN],
                        proxy_key,
                    )
            else:
                a = ea
                b = eb
                if pi[a, _PALIVE] == 0 or pi[b, _PALIVE] == 0:
                    continue
                if pi[a, _PMVER] != eva or pi[b, _PMVER] != evb:
                    continue
                # an exact entry is current when neither plane changed since it was valued: the
                # planes are at their merge versions, or a refinement of them at their versions
                # is the last kept one; else a large plane grew since (no full merge loop) and the
                # merge is refined again at the planes' current state
                if kind == _G_MERGE_EXACT and (
                    (pi[a, _PVER] == pi[a, _PMVER] and pi[b, _PVER] == pi[b, _PMVER])
                    or (mcache_i[a, 0] == b and mcache_i[a, 1] == pi[a, _PVER] and mcache_i[a, 2] == pi[b, _PVER])
                ):
                    found = True
                    act_a = a
                    act_b = b
                    break
                # a model merge reached the top: refine it (exact union fit when small, else
                # the larger plane's model plus the smaller plane's exact residuals)
                stats[_ST_MERGE_REFINES] += 1
                if pi[a, _PCOUNT] + pi[b, _PCOUNT] <= exact_plane_size:
                    n1 = _gather(pi, nextpix, a, buf, endpoints, directions)
                    n2 = _gather(pi, nextpix, b, buf, endpoints, directions, n1)
                    sse, u0, u1, u2 = _union_fit(endpoints, directions, pf, buf, n1 + n2, a, b)
                    _cache_merge(
                        mcache_i,
                        mcache_f,
                        a,
                        b,
                        pi[a, _PVER],
                        pi[b, _PVER],
                        sse,
                        u0,
                        u1,
                        u2,
                        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
                    )
                    inc = sse - pf[a, _PE] - pf[b, _PE]
                    if inc < 0.0:
                        inc = 0.0
                    if inc <= cutoff:
                        gsize = _q_push(
                            gkey, gint, gsize, fkey, fint, fnext, bhead, qstate, inc, _G_MERGE_EXACT, a, b, eva, evb
                        )
                    continue
                big = a
                small = b
                if pi[b, _PCOUNT] > pi[a, _PCOUNT]:
                    big = b
                    small = a
                n = _gather(pi, nextpix, small, buf, endpoints, directions)
                stats[_ST_REFINE_RAYS] += n
                if n <= exact_plane_size:
                    e_small = pf[small, _PE]  # a small plane's E is its exact fit's
                else:
                    e_small, _, _, _ = _fit_rays(
                        endpoints,
                        directions,
                        buf,
                        n,
                        pf[small, _PW],
                        pf[small, _PW + 1],
                        pf[small, _PW + 2],
                        _FIT_ITERATIONS,
                        _FIT_TOLERANCE,
                    )
                _, m0, m1, m2 = _model_merge(pf, a, b)
                value, m0, m1, m2, info, grad = _hybrid_merge(endpoints, directions, pf, big, buf, n, m0, m1, m2)
                _cache_merge(mcache_i, mcache_f, a, b, pi[a, _PVER], pi[b, _PVER], value, m0, m1, m2, info)
                if refined_growth > 0.0:
                    _keep_refined_merge(rcache_i, rcache_f, pf, pi, big, small, e_small, value, m0, m1, m2, info, grad)
                inc = value - pf[big, _PE] - e_small
                if inc < 0.0:
                    inc = 0.0
                if inc <= cutoff:
                    gsize = _q_push(
                        gkey, gint, gsize, fkey, fint, fnext, bhead, qstate, inc, _G_MERGE_EXACT, a, b, eva, evb
                    )
        if not found:
            break
        if not (key <= max_increment or plane_count > min_count):
            break

        # ---------------- execute ----------------------------------------------------------
        if n_actions >= len(log_kind):
            break
        log_a[n_actions] = act_a
        log_b[n_actions] = act_b
        log_inc[n_actions] = key
        changed = -1
        new_pixels = 0
        adj_before = 0  # the changed plane's adjacency nodes before this action's appends
        in_buf = -1  # the changed plane's rays when the execution left them in buf (-1: not)
        if kind == _G_SEED:
            log_kind[n_actions] = KIND_CREATE
            p = act_a
            i = p // width
            j = p % width
            for t in range(4):
                cell[t] = (i + offsets[act_b, t, 0]) * width + (j + offsets[act_b, t, 1])
            # a plane id is created once (its anchor is taken for good): its rows start here
            parent[p] = p
            seen[p] = -1
            pi[p, _PSTAMP] = 0
            for t in range(3):
                mcache_i[p, t] = -1
            pf[p, _PRPARTNER] = -1.0
            ecache_i[p, 0] = -1
            ecache_i[p, 1] = -1
            pi[p, _PALIVE] = 1
            pi[p, _PROOT] = -1
            pi[p, _PADJ] = -1
            pi[p, _PADJC] = 0
            pi[p, _PADJN] = 0
            pi[p, _PHEAD] = cell[0]
            for t in range(4):
                owner[cell[t]] = p
                nextpix[cell[t]] = cell[t + 1] if t < 3 else -1
            pi[p, _PTAIL] = cell[3]
            pi[p, _PCOUNT] = 4
            pf[p, _PCOUNTLIN] = 4
            _set_exact_state(endpoints, directions, pf, cell, 4, p, np.nan, np.nan, np.nan)
            rmax = 0.0
            for t in range(4):
                k = cell[t]
                r = np.sqrt(endpoints[k, 0] ** 2 + endpoints[k, 1] ** 2 + endpoints[k, 2] ** 2)
                rmax = max(rmax, r)
            pf[p, _PRMAX] = rmax
            plane_count -= 3
            changed = p
            new_pixels = 4
            for t in range(4):
                buf2[t] = cell[t]
        elif kind == _G_EXTEND:
            log_kind[n_actions] = KIND_EXTEND
            p = act_a
            k = act_b
            count = pi[p, _PCOUNT]
            adj_before = pi[p, _PADJN]
            owner[k] = p
            nextpix[k] = -1
            nextpix[pi[p, _PTAIL]] = k
            pi[p, _PTAIL] = k
            pi[p, _PCOUNT] = count + 1
            r = np.sqrt(endpoints[k, 0] ** 2 + endpoints[k, 1] ** 2 + endpoints[k, 2] ** 2)
            pf[p, _PRMAX] = max(pf[p, _PRMAX], r)
            if count + 1 <= exact_plane_size and ecache_i[p, 0] == k and ecache_i[p, 1] == pi[p, _PVER]:
                # the candidate's own fit (the least of this version's): no fit again
                sse, w0, w1, w2, info = _get_fit(ecache_f, p)
                _store_state(pf, p, sse, w0, w1, w2, info)
                pf[p, _PCOUNTLIN] = count + 1
            elif count + 1 <= exact_plane_size:
                n = _gather(pi, nextpix, p, buf, endpoints, directions)
                _set_exact_state(endpoints, directions, pf, buf, n, p, pf[p, _PW], pf[p, _PW + 1], pf[p, _PW + 2])
                in_buf = n
                pf[p, _PCOUNTLIN] = n
            else:
                inc, x0, x1, x2, f, g0, g1, g2 = _model_extension(endpoints, directions, pf, p, k)
                denom = 1.0 + g0 * x0 + g1 * x1 + g2 * x2
                pf[p, _PW] -= x0 * f / denom
                pf[p, _PW + 1] -= x1 * f / denom
                pf[p, _PW + 2] -= x2 * f / denom
                pf[p, _PH] += g0 * g0
                pf[p, _PH + 1] += g0 * g1
                pf[p, _PH + 2] += g0 * g2
                pf[p, _PH + 3] += g1 * g1
                pf[p, _PH + 4] += g1 * g2
                pf[p, _PH + 5] += g2 * g2
                pf[p, _PE] += key
            plane_count -= 1
            changed = p
            new_pixels = 1
            buf2[0] = k
        else:
            log_kind[n_actions] = KIND_MERGE
            a = act_a
            b = act_b
            s = min(a, b)
            o = max(a, b)
            na = pi[a, _PCOUNT]
            nbn = pi[b, _PCOUNT]
            total = na + nbn
            info = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
            value = 0.0
            if mcache_i[a, 0] == b and mcache_i[a, 1] == pi[a, _PVER] and mcache_i[a, 2] == pi[b, _PVER]:
                # the refinement that queued this merge computed the same fit (same planes, versions)
                value, w0, w1, w2, info = _get_fit(mcache_f, a)
            elif total <= exact_plane_size:
                # exact merged state from the best of the union's starting points
                n1 = _gather(pi, nextpix, a, buf, endpoints, directions)
                n2 = _gather(pi, nextpix, b, buf, endpoints, directions, n1)
                _, w0, w1, w2 = _union_fit(endpoints, directions, pf, buf, n1 + n2, a, b)
            else:
                big = a if na >= nbn else b
                small = b if big == a else a
                n = _gather(pi, nextpix, small, buf, endpoints, directions)
                _, m0, m1, m2 = _model_merge(pf, a, b)
                value, w0, w1, w2, info, _ = _hybrid_merge(endpoints, directions, pf, big, buf, n, m0, m1, m2)
            # concatenate pixel lists into s
            nextpix[pi[s, _PTAIL]] = pi[o, _PHEAD]
            pi[s, _PTAIL] = pi[o, _PTAIL]
            parent[o] = s
            pi[s, _PCOUNT] = total
            pi[s, _PROOT] = _h_meld(hf, hi, pi[s, _PROOT], pi[o, _PROOT])
            # adjacency lists
            adj_before = pi[s, _PADJN]
            aused = _adj_concat(anode, afree, pi, s, o, aused)
            if aused < 0:
                overflow[2] = 2 * acap
                return _empty_log(stats, overflow)
            pf[s, _PRMAX] = max(pf[a, _PRMAX], pf[b, _PRMAX])
            lin = max(pf[a, _PCOUNTLIN], pf[b, _PCOUNTLIN])
            if total <= exact_plane_size:
                n = _gather(pi, nextpix, s, buf, endpoints, directions)
                _set_exact_state(endpoints, directions, pf, buf, n, s, w0, w1, w2)
                pf[s, _PCOUNTLIN] = n
            else:
                pf[s, _PE] = value
                pf[s, _PW] = w0
                pf[s, _PW + 1] = w1
                pf[s, _PW + 2] = w2
                for t in range(6):
                    pf[s, _PH + t] = info[t]
                pf[s, _PCOUNTLIN] = lin
            pi[o, _PALIVE] = 0
            pi[o, _PROOT] = -1
            plane_count -= 1
            changed = s
            new_pixels = 0
        n_actions += 1

        # ---------------- bookkeeping of the changed plane ---------------------------------
        p = changed
        count = pi[p, _PCOUNT]
        # a large plane grown a little since its last full merge loop values only its new
        # neighbours' merges; its queued and deferred merges stay (they carry its merge version)
        partial = (
            kind != _G_SEED and count > exact_plane_size and count <= pf[p, _PCOUNTLOOP] * (1.0 + merge_loop_growth)
        )
        if count > exact_plane_size:
            dw = np.sqrt(
                (pf[p, _PW] - pf[p, _PWL]) ** 2
                + (pf[p, _PW + 1] - pf[p, _PWL + 1]) ** 2
                + (pf[p, _PW + 2] - pf[p, _PWL + 2]) ** 2
            )
            if count >= 2 * pf[p, _PCOUNTLIN] or dw * pf[p, _PRMAX] > drift_limit:
                n = _gather(pi, nextpix, p, buf, endpoints, directions)
                stats[_ST_RELINS] += 1
                stats[_ST_RELIN_RAYS] += n
                _relinearise(endpoints, directions, pf, buf, n, p)
                pf[p, _PCOUNTLIN] = n
                partial = False
        # versions are unique across planes: the candidates a merged plane inherits from the
        # absorbed plane can never pass for current ones
        version_counter += 1
        pi[p, _PVER] = version_counter

        # capacity for the candidate nodes this step pushes (adjacency segments check their own)
        if hused + 4 * new_pixels + 8 >= hcap:
            overflow[1] = 2 * hcap
        if overflow[0] > 0 or overflow[1] > 0 or overflow[2] > 0:
            return _empty_log(stats, overflow)

        # new neighbours of the added pixels: extension candidates and adjacent planes
        n_gathered = in_buf  # p's rays are gathered into buf once, for its first exact candidate fit
        for t in range(new_pixels):
            k = buf2[t]
            i = k // width
            j = k % width
            n_nb = 0
            if j + 1 < width and ok_right[k]:
                nb_pix[n_nb] = k + 1
                n_nb += 1
            if j > 0 and ok_right[k - 1]:
                nb_pix[n_nb] = k - 1
                n_nb += 1
            if i + 1 < height and ok_down[k]:
                nb_pix[n_nb] = k + width
                n_nb += 1
            if i > 0 and ok_down[k - width]:
                nb_pix[n_nb] = k - width
                n_nb += 1
            for u in range(n_nb):  # the neighbours' rows load together (a candidate's fit reads its ray)
                _prefetch(endpoints, nb_pix[u], 0)
                _prefetch(directions, nb_pix[u], 0)
                _prefetch(owner, nb_pix[u], 0)
                _prefetch(candidate_of, nb_pix[u], 0)
            for u in range(n_nb):
                q = nb_pix[u]
                if owner[q] < 0:
                    if candidate_of[q] >= 0 and _find(parent, candidate_of[q]) == p:
                        # p already holds a node for q, valued for an earlier version: its key is a
                        # lower bound, and it is valued again when it reaches the top of p's heap
                        continue
                    # extension candidate (p, q), exact value for the current version
                    stats[_ST_NEW_CANDIDATES] += 1
                    small = count + 1 <= exact_plane_size
                    if small and n_gathered < 0:
                        n_gathered = _gather(pi, nextpix, p, buf, endpoints, directions)
                    inc = _candidate_increment(
                        endpoints, directions, pf, p, small, buf, n_gathered, q, pi[p, _PVER], ecache_i, ecache_f
                    )
                    if not np.isfinite(inc):
                        continue
                    if inc < 0.0:
                        inc = 0.0
                    value = pf[p, _PE] + inc
                    if hfree >= 0:
                        node = hfree
                        hfree = hi[node, 2]
                    else:
                        node = hused
                        hused += 1
                    hf[node, 0] = value - slack * abs(value)
                    hf[node, 1] = value
                    hi[node, 0] = q
                    hi[node, 1] = pi[p, _PVER]
                    hi[node, 2] = -1
                    hi[node, 3] = -1
                    pi[p, _PROOT] = _h_meld(hf, hi, pi[p, _PROOT], node)
                    candidate_of[q] = p
                else:
                    other = _find(parent, owner[q])
                    if other != p:
                        aused = _adj_append(anode, akey, afree, pi, p, other, aused)
                        if aused >= 0:
                            aused = _adj_append(anode, akey, afree, pi, other, p, aused)
                        if aused < 0:
                            overflow[2] = 2 * acap
                            return _empty_log(stats, overflow)

        # proxy of p's extension candidates (rays taken by now, such as the one p just took, dropped)
        root, hfree = _h_drop_taken(hf, hi, owner, pi[p, _PROOT], hfree)
        pi[p, _PROOT] = root
        if gsize + qstate[_QCOUNT] + 2 + pi[p, _PADJN] >= gcap:
            overflow[0] = 2 * (gcap + pi[p, _PADJN])
        if overflow[0] > 0 or overflow[1] > 0 or overflow[2] > 0:
            return _empty_log(stats, overflow)
        gsize, proxy_key = _queue_proxy(gkey, gint, gsize, fkey, fint, fnext, bhead, qstate, hf, hi, pf, pi, p, cutoff)

        # merges with every neighbouring plane (compacting p's adjacency list). A merge whose key
        # exceeds p's proxy key is deferred on p's node instead of queued: p's proxy comes first,
        # and p either changes (and re-evaluates every merge here) or re-queues its proxy, which
        # releases the deferred merges its new key no longer precedes
        seen_stamp += 1
        first = pi[p, _PADJ]
        end = first + pi[p, _PADJN]
        n_adj = 0
        least = np.inf
        release = False
        if partial:
            n_adj = adj_before
            least = pf[p, _PDEFER]
            release = least <= proxy_key and least < np.inf
        else:
            pi[p, _PMVER] = pi[p, _PVER]
            pf[p, _PCOUNTLOOP] = count
        for r in range(first + n_adj, end):
            if r + 1 < end:  # the next neighbour's rows load while this one is evaluated
                q = anode[r + 1, _AN_PLANE]
                _prefetch(parent, q, 0)
                _prefetch(seen, q, 0)
                _prefetch(pi, q, 0)
                _prefetch(pf, q, 0)
                _prefetch(pf, q, _PH + 5)
            q = _find(parent, anode[r, _AN_PLANE])
            if not (q == p or pi[q, _PALIVE] == 0 or seen[q] == seen_stamp):
                # kept: compacted to the front of the segment (x <= r, so no unread row is overwritten)
                x = first + n_adj
                seen[q] = seen_stamp
                anode[x, _AN_PLANE] = q
                n_adj += 1
                stats[_ST_MERGE_EVALS] += 1
                a = min(p, q)
                b = max(p, q)
                total = pi[a, _PCOUNT] + pi[b, _PCOUNT]
                if total <= exact_merge_size:
                    n1 = _gather(pi, nextpix, a, buf, endpoints, directions)
                    n2 = _gather(pi, nextpix, b, buf, endpoints, directions, n1)
                    sse, _, _, _ = _union_fit(endpoints, directions, pf, buf, n1 + n2, a, b)
                    inc = sse - pf[a, _PE] - pf[b, _PE]
                    gkind = _G_MERGE_EXACT
                elif (
                    pf[q, _PRPARTNER] == p
                    and rcache_i[q, 0] == pi[q, _PVER]
                    and pi[p, _PCOUNT] <= rcache_i[q, 1] * (1.0 + refined_growth)
                ):
                    # refined before, q unchanged since and p grown a little: q's residual model
                    # at the refined union's w stands for its exact residuals
                    inc = _refined_merge_increment(pf, p, rcache_f, q)
                    gkind = _G_MERGE_EXACT
                    stats[_ST_REFINED_REUSES] += 1
                else:
                    # queued below its model value so that it is refined (exactly) before any
                    # action it could precede even where the model overestimates the increment
                    inc = _model_merge_increment(pf, a, b) * model_key_factor
                    gkind = _G_MERGE_MODEL
                if inc < 0.0:
                    inc = 0.0
                akey[x, _AN_KEY] = np.inf
                if inc <= (cutoff if gkind == _G_MERGE_EXACT else model_cutoff):
                    if inc <= proxy_key or not defer_merges:
                        gsize = _q_push(
                            gkey,
                            gint,
                            gsize,
                            fkey,
                            fint,
                            fnext,
                            bhead,
                            qstate,
                            inc,
                            gkind,
                            a,
                            b,
                            pi[a, _PMVER],
                            pi[b, _PMVER],
                        )
                    else:
                        akey[x, _AN_KEY] = inc
                        least = min(least, inc)
                        anode[x, _AN_KIND] = gkind
                        anode[x, _AN_VA] = pi[a, _PMVER]
                        anode[x, _AN_VB] = pi[b, _PMVER]
        pi[p, _PADJN] = n_adj
        pf[p, _PDEFER] = least
        if release:  # the kept deferred merges that p's new proxy key no longer precedes
            gsize = _release_deferred(
                gkey, gint, gsize, fkey, fint, fnext, bhead, qstate, anode, akey, pf, p, first, n_adj, proxy_key
            )

    stats[_ST_HEAP_PEAK] = gcap
    return (
        log_kind[:n_actions].astype(np.int8),
        log_a[:n_actions].copy(),
        log_b[:n_actions].copy(),
        log_inc[:n_actions].copy(),
        stats,
        overflow,
    )


# --------------------------------------------------------------------------------------------
# replay of the action log
# --------------------------------------------------------------------------------------------


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _replay(kinds, a_ids, b_ids, n_steps, height, width, offsets):
    """Plane id of every pixel after the first n_steps actions (-1 = atomic or no return)."""
    n_pixels = height * width
    parent = np.arange(n_pixels)
    owner = np.full(n_pixels, -1, np.int64)
    for s in range(n_steps):
        kind = kinds[s]
        a = a_ids[s]
        b = b_ids[s]
        if kind == KIND_CREATE:
            i = a // width
            j = a % width
            for t in range(4):
                owner[(i + offsets[b, t, 0]) * width + (j + offsets[b, t, 1])] = a
        elif kind == KIND_EXTEND:
            owner[b] = a
        else:
            parent[b] = a
    out = np.full(n_pixels, -1, np.int64)
    for k in range(n_pixels):
        if owner[k] >= 0:
            out[k] = _find(parent, owner[k])
    return out


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------


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


def _as_threshold_list(value, name: str, cast) -> list | None:
    if value is None:
        return None
    values = list(value) if isinstance(value, Sequence | np.ndarray) else [value]
    if not values:
        raise ValueError(f'{name} must not be an empty list')
    out = []
    for v in values:
        try:
            if cast is int and (isinstance(v, bool | np.bool_) or not float(v).is_integer()):
                raise ValueError('not a whole number')
            x = cast(v)
        except (TypeError, ValueError) as exc:
            raise ValueError(f'{name} must be a number or a list of numbers; got {v!r}') from exc
        if cast is float and (not np.isfinite(x) or x < 0):
            raise ValueError(f'{name} must be finite and >= 0 (m^2); got {v!r}')
        if cast is int and x < 1:
            raise ValueError(f'{name} must be >= 1; got {v!r}')
        out.append(x)
    return out


@dataclass(frozen=True)
class PlaneHierarchy:
    """The greedy action log of one PPE run; cut it at any threshold without re-running.

    Attributes:
        scan: the ray model the run used.
        actions: structured array (kind, a, b, increment) with kind 0 create (a = anchor pixel id,
            b = tetromino config 0..16), 1 extend (a = plane id, b = pixel id), 2 merge
            (a = surviving id = min, b = removed id); increments in m^2. Pixel id = row * W + col.
        plane_counts: J after each action (atomic rays + regular planes).
        initial_plane_count: J before the first action (the number of valid rays).
        complete: True when the run went on until no action was left.
        seconds: wall time of the run (seeds + greedy), excluding JIT compilation of a first call.
    """

    scan: RayScan
    actions: np.ndarray
    plane_counts: np.ndarray
    initial_plane_count: int
    complete: bool
    seconds: float = 0.0
    stats: dict | None = None
    sigmas: np.ndarray | None = None

    def steps_for_error(self, max_error_increment: float) -> int:
        """Number of actions before the first one whose increment exceeds e (m^2)."""
        over = np.flatnonzero(self.actions['increment'] > max_error_increment)
        return int(over[0]) if len(over) else len(self.actions)

    def steps_for_count(self, max_planes: int) -> int:
        """Number of actions until J <= n first holds."""
        if self.initial_plane_count <= max_planes:
            return 0
        hit = np.flatnonzero(self.plane_counts <= max_planes)
        return int(hit[0]) + 1 if len(hit) else len(self.actions)

    def plane_ids(self, steps: int) -> np.ndarray:
        """``(H*W,)`` plane id of each pixel after ``steps`` actions (-1: atomic/no return)."""
        a = self.actions
        return _replay(
            np.ascontiguousarray(a['kind']),
            np.ascontiguousarray(a['a']),
            np.ascontiguousarray(a['b']),
            int(steps),
            self.scan.height,
            self.scan.width,
            TETROMINO_OFFSETS,
        )

    def cut(
        self, *, max_error_increment: float | None = None, max_planes: int | None = None, min_plane_points: int = 4
    ) -> PlaneSet:
        """The planes of the snapshot for one threshold (exactly one of e or n)."""
        if (max_error_increment is None) == (max_planes is None):
            raise ValueError('cut needs exactly one of max_error_increment or max_planes')
        if max_error_increment is not None:
            steps = self.steps_for_error(max_error_increment)
        else:
            steps = self.steps_for_count(max_planes)
        planes, _ = fit_pixel_groups(
            self.scan,
            self.plane_ids(steps),
            min_plane_points=min_plane_points,
            residuals=False,
            sigmas=self.sigmas,
            max_error_increment=max_error_increment,
            max_planes=max_planes,
            actions=steps,
        )
        return planes


_work_memory = threading.local()


def _reusable(name: str, size: int, dtype) -> np.ndarray:
    """A 1-D array of ``size`` elements from this thread's work memory (kept for the next call).

    Fresh memory costs a page fault per 4 KiB page when first touched: tens of thousands per
    500 x 500 scan, a noticeable share of a small scan's extraction. Each thread keeps its own
    buffers (calls from several threads never share one); a larger request replaces the buffer.
    """
    buffers = getattr(_work_memory, 'buffers', None)
    if buffers is None:
        buffers = _work_memory.buffers = {}
    buffer = buffers.get(name)
    if buffer is None or len(buffer) < size or buffer.dtype != dtype:
        buffer = buffers[name] = np.empty(size, dtype)
    return buffer[:size]


def release_work_memory() -> None:
    """Free the work memory the extractor keeps between calls in the calling thread.

    The extractor reuses its work buffers (about 1.2 KB per ray of the largest scan so far, of which
    the touched part stays resident) so that repeated calls, like a node's frames, do not pay for
    fresh memory; call this after a large one-off extraction to give the memory back.
    """
    _work_memory.buffers = {}


def _work_buffers(n_f: int, n_i: int, n_i32: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return (
        _reusable('float64', n_f, np.float64),
        _reusable('int64', n_i, np.int64),
        _reusable('int32', n_i32, np.int32),
    )


def _seed_stage(scan: RayScan, ok_right: np.ndarray, ok_down: np.ndarray, cutoff: float):
    """Every anchor's tetromino seed errors, its best config and key (reused work memory); seeds above
    ``cutoff`` (the greedy's, :func:`_run_cutoff`) are never created."""
    seed_sse = _reusable('seeds', scan.size * 17, np.float64).reshape(scan.size, 17)
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
        seed_sse,
        seed_best,
        seed_key,
        cutoff,
    )
    return seed_sse, seed_best, seed_key


def _action_log(kinds: np.ndarray, a_ids: np.ndarray, b_ids: np.ndarray, increments: np.ndarray) -> np.ndarray:
    """The greedy's actions as an ACTION_DTYPE array."""
    actions = np.empty(len(kinds), ACTION_DTYPE)
    actions['kind'] = kinds
    actions['a'] = a_ids
    actions['b'] = b_ids
    actions['increment'] = increments
    return actions


def _stops(max_error_increment: float | None, max_planes: int | None) -> tuple[float, int]:
    """The greedy's stop increment and plane count (inf and -1: run the whole hierarchy)."""
    if max_error_increment is None and max_planes is None:
        return np.inf, -1
    stop_increment = -np.inf if max_error_increment is None else float(max_error_increment)
    stop_count = np.iinfo(np.int64).max if max_planes is None else min(int(max_planes), np.iinfo(np.int64).max)
    return stop_increment, stop_count


def _check_hierarchy_options(
    scan: RayScan, lmax: float, pool_capacity, exact_plane_size, refined_merge_growth, merge_loop_growth
) -> None:
    """extract_plane_hierarchy's checks of its scan size and tuning options (ValueError naming the option)."""
    if not (lmax > 0):
        raise ValueError(f'max_neighbor_distance must be > 0 m (inf = no limit); got {lmax!r}')
    if scan.size >= MAX_RAYS:
        raise ValueError(f'scans of fewer than {MAX_RAYS} rays (2^26) are supported; got {scan.height} x {scan.width}')
    if pool_capacity is not None and int(pool_capacity) < 1:
        raise ValueError(f'pool_capacity must be >= 1 (None: from the scan size); got {pool_capacity!r}')
    if int(exact_plane_size) < 4:
        raise ValueError(f'exact_plane_size must be >= 4; got {exact_plane_size!r}')
    for name, value in (('refined_merge_growth', refined_merge_growth), ('merge_loop_growth', merge_loop_growth)):
        if not 0.0 <= float(value) < np.inf:
            raise ValueError(f'{name} must be a finite fraction >= 0 (0: off); got {value!r}')


def extract_plane_hierarchy(
    points: np.ndarray,
    *,
    origins: np.ndarray | None = None,
    max_neighbor_distance: float = np.inf,
    max_error_increment: float | None = None,
    max_planes: int | None = None,
    exact_plane_size: int = DEFAULT_EXACT_PLANE_SIZE,
    exact_merge_size: int = 0,
    relinearisation_drift: float = RELINEARISATION_DRIFT,
    refined_merge_growth: float = REFINED_MERGE_GROWTH,
    merge_loop_growth: float = MERGE_LOOP_GROWTH,
    defer_merges: bool = True,
    pool_capacity: int | None = None,
    noise: NoiseModel | None = None,
    tiles: int | str = 1,
    threads: int | None = None,
) -> PlaneHierarchy:
    """Run PPE and return its action log.

    Args:
        points: organized ``(H, W, 3)`` endpoints in metres, NaN = no return; H * W < MAX_RAYS (2^26).
        origins: ray starts: None (coordinate origin), ``(3,)`` or ``(H, W, 3)``, same frame.
        max_neighbor_distance: the largest 3-D distance (m) between 4-neighbouring endpoints that
            may be joined (the paper's d, the reference's lmax); inf = no limit.
        max_error_increment: stop once the next increment exceeds this (m^2) and no plane-count
            target remains; None with max_planes None runs until no action is left.
        max_planes: continue at least until J <= max_planes.
        exact_plane_size: planes up to this many rays are evaluated with exact fits (tests use a
            large value to make every evaluation exact).
        exact_merge_size: merges whose union has up to this many rays are fitted exactly as soon as
            they become candidates; larger ones enter the queue with their model increment and are
            refined when they reach the front.
        relinearisation_drift: relative change of a large plane's predicted ranges since its last
            linearisation that triggers a re-linearisation (one Gauss-Newton step on all its rays).
        refined_merge_growth: a merge of two planes larger than exact_plane_size in total, refined
            once, is re-valued from the kept refinement (the smaller plane's residuals as a quadratic
            model at the union's w) while the smaller plane is unchanged and the larger has grown by
            at most this fraction; 0 refines it again every time it reaches the front.
        merge_loop_growth: after an action on a plane larger than exact_plane_size that has grown by
            at most this fraction since its last full merge loop, only its new neighbours' merges are
            valued; 0 values every merge of the plane after every action.
        defer_merges: keep merges whose key exceeds the changed plane's proxy key off the queue until
            they are due (False queues every merge at once: the same action log, more heap work;
            for tests).
        pool_capacity: initial rows of each of the greedy's work pools (None: from the scan size).
            A pool that runs out is enlarged and the greedy run again, so the result does not
            depend on it (tests use small values to exercise that path).
        noise: the rays' range noise (:class:`~ppe_ros.core.sensor.NoiseModel`): the greedy minimises
            the squared residuals divided by sigma_k^2, and increments (and max_error_increment) are
            dimensionless; None: the paper's model (increments in m^2).
        tiles: 1 (the exact greedy of the whole grid), a count, or 'auto' (one per AUTO_TILE_COLUMNS
            columns of a sweep, twice that of an image, see _tile_bounds): the grid is cut into that
            many vertical strips (azimuth sectors of a sweep) that are extracted independently, no
            plane crossing a border (join the pieces afterwards, as extract_planes's consolidation
            does). Each inner border moves by up to TILE_BORDER_SLACK of a strip's width to the
            column that the fewest admissible grid edges cross. Needs max_planes
            None. The log's cut at e is the union of the strips' cuts at e.
        threads: strips extracted at once, one thread each (None: numba's thread count of the calling
            thread); the result does not depend on it.
    """
    import time

    scan = make_ray_scan(points, origins)
    sigmas = None
    if noise is not None:
        scan, sigmas = _noise_scaled(scan, noise)
    lmax = float(max_neighbor_distance)
    _check_hierarchy_options(scan, lmax, pool_capacity, exact_plane_size, refined_merge_growth, merge_loop_growth)
    stop_increment, stop_count = _stops(max_error_increment, max_planes)
    tile_columns = _tile_bounds(scan.width, tiles, scan.height)
    if threads is not None and (isinstance(threads, bool) or int(threads) != threads or int(threads) < 1):
        raise ValueError(f"threads must be a count >= 1 or None (numba's thread count); got {threads!r}")
    if tiles != 1 and max_planes is not None:
        raise ValueError('tiles > 1 needs a max_error_increment stop without max_planes (a plane count is global)')
    knobs = (
        int(exact_plane_size),
        int(exact_merge_size),
        float(relinearisation_drift),
        float(refined_merge_growth),
        float(merge_loop_growth),
        bool(defer_merges),
        pool_capacity,
    )
    start = time.perf_counter()
    ok_right, ok_down = _edge_masks(scan, lmax)
    tile_columns = _placed_borders(tile_columns, ok_right, scan.height, scan.width)
    for column in tile_columns[1:-1]:  # no seed or join crosses a tile border
        ok_right[column - 1 :: scan.width] = False
    seed_sse, seed_best, seed_key = _seed_stage(
        scan, ok_right, ok_down, _run_cutoff(stop_increment, stop_count, scan.size)
    )
    inputs = (scan.endpoints, scan.directions, scan.valid, ok_right, ok_down, seed_sse, seed_best, seed_key)
    if len(tile_columns) == 2:
        kinds, a_ids, b_ids, incs, stats = _greedy(inputs, scan.height, scan.width, knobs, stop_increment, stop_count)
    else:
        kinds, a_ids, b_ids, incs, stats = _tiled_greedy(
            inputs, scan.height, scan.width, tile_columns, knobs, stop_increment, stop_count, threads
        )
    seconds = time.perf_counter() - start
    actions = _action_log(kinds, a_ids, b_ids, incs)
    reduction = np.where(kinds == KIND_CREATE, 3, 1)
    n_valid = int(scan.valid.sum())
    plane_counts = n_valid - np.cumsum(reduction)
    complete = stop_increment == np.inf and stop_count < 0
    return PlaneHierarchy(
        scan=scan,
        actions=actions,
        plane_counts=plane_counts,
        initial_plane_count=n_valid,
        complete=complete,
        seconds=seconds,
        stats=dict(zip(STAT_NAMES, (int(x) for x in stats), strict=True)),
        sigmas=sigmas,
    )


def _greedy(inputs: tuple, height: int, width: int, knobs: tuple, stop_increment: float, stop_count: int) -> tuple:
    """The greedy on one grid: action log (kinds, a, b, increments) and stats, in the calling thread's work memory.

    inputs: endpoints, directions, valid, ok_right, ok_down, seed_sse, seed_best, seed_key of the grid.
    """
    endpoints, directions, valid, ok_right, ok_down, seed_sse, seed_best, seed_key = inputs
    exact_plane_size, exact_merge_size, drift, refined_growth, loop_growth, defer, pool_capacity = knobs
    n_pixels = height * width
    # pools: the queue, extension candidate nodes and adjacency nodes. Runs of the benchmark scans
    # use at most 0.9, 1.12 and 3.1 rows per ray; a pool that runs out is doubled and the greedy run
    # again (np.empty only reserves memory: rows that are never used cost no RAM)
    capacity = np.array([2, 4, 8]) * max(n_pixels, 256) if pool_capacity is None else np.full(3, int(pool_capacity))
    while True:
        work = _work_buffers(*_work_sizes(n_pixels, int(capacity[0]), int(capacity[1]), int(capacity[2])))
        kinds, a_ids, b_ids, incs, stats, overflow = _ppe_kernel(
            endpoints,
            directions,
            valid,
            ok_right,
            ok_down,
            height,
            width,
            TETROMINO_OFFSETS,
            seed_sse,
            seed_best,
            seed_key,
            exact_plane_size,
            exact_merge_size,
            drift,
            stop_increment,
            stop_count,
            BOUND_SLACK,
            1.0 - MODEL_MERGE_KEY_MARGIN,
            refined_growth,
            loop_growth,
            defer,
            int(capacity[0]),
            int(capacity[1]),
            int(capacity[2]),
            *work,
        )
        if not overflow.any():
            return kinds, a_ids, b_ids, incs, stats
        capacity = np.maximum(capacity, overflow)
        if capacity.max() >= 2**31:  # pool rows are 32-bit plane fields
            raise RuntimeError(f'the greedy needs work pools of {capacity.max()} rows (2^31 or more)')


#: Columns per tile of tiles='auto' on a sweep (a grid at least 4 times as wide as high: 45 deg sectors
#: of a 1024-column spinning lidar); images get twice as wide strips (measured: 128-column strips of
#: ICL-NUIM's 640 x 480 frames lost 6-8 points of k in the depth-camera profile's consolidation,
#: 320-column ones none).
AUTO_TILE_COLUMNS = 128


def _tile_bounds(width: int, tiles: int | str, height: int = 1) -> list[int]:
    """Column bounds [0, c1, ..., width] of ``tiles`` vertical strips of near-equal width.

    'auto': one strip per AUTO_TILE_COLUMNS columns on a grid at least 4 times as wide as high, per
    2 AUTO_TILE_COLUMNS otherwise (at least 1). Strips are at least 8 columns wide.
    """
    if isinstance(tiles, str):
        if tiles != 'auto':
            raise ValueError(f"tiles must be a count >= 1 or 'auto'; got {tiles!r}")
        columns = AUTO_TILE_COLUMNS if width >= 4 * height else 2 * AUTO_TILE_COLUMNS
        count = max(1, round(width / columns))
    else:
        if isinstance(tiles, bool) or int(tiles) != tiles or int(tiles) < 1:
            raise ValueError(f"tiles must be a count >= 1 or 'auto'; got {tiles!r}")
        count = int(tiles)
    count = max(1, min(count, width // 8))
    return [round(i * width / count) for i in range(count + 1)]


#: A tile border may move by this fraction of the strip width to where the fewest grid edges cross it.
TILE_BORDER_SLACK = 0.25


def _placed_borders(bounds: list[int], ok_right: np.ndarray, height: int, width: int) -> list[int]:
    """The inner borders moved (each within TILE_BORDER_SLACK of a strip's width) to the column between c - 1
    and c that the fewest admissible grid edges cross (ties: the nearest to the nominal border, then the
    left one): a border there cuts fewest surfaces (it falls on depth jumps, no-returns, edges of objects).
    """
    if len(bounds) <= 2:
        return bounds
    crossing = ok_right.reshape(height, width).sum(axis=0)  # crossing[c - 1]: edges between columns c - 1, c
    slack = int(TILE_BORDER_SLACK * width / (len(bounds) - 1))
    placed = [0]
    for nominal in bounds[1:-1]:
        candidates = np.arange(max(nominal - slack, placed[-1] + 8), min(nominal + slack, width - 8) + 1)
        if len(candidates) == 0:
            placed.append(nominal)
            continue
        order = np.lexsort((candidates, np.abs(candidates - nominal), crossing[candidates - 1]))
        placed.append(int(candidates[order[0]]))
    return [*placed, width]


_tile_pool_lock = threading.Lock()
_tile_pool: list = []


def _tile_executor(workers: int):
    """A process-wide pool of at least ``workers`` threads for tiles (its threads keep their work memory)."""
    from concurrent.futures import ThreadPoolExecutor

    with _tile_pool_lock:
        if not _tile_pool or _tile_pool[0]._max_workers < workers:
            # a smaller pool is replaced, not shut down: a caller may still submit to it; its idle
            # threads end when it is no longer referenced
            _tile_pool[:] = [ThreadPoolExecutor(max_workers=workers, thread_name_prefix='ppe-tile')]
        return _tile_pool[0]


def _tile_inputs(inputs: tuple, height: int, width: int, c0: int, c1: int) -> tuple:
    """The inputs of _greedy for columns c0:c1, copied (row-major, tile-local pixel ids) into work memory."""
    out = []
    for index, array in enumerate(inputs):
        trailing = array.shape[1:]
        tile = array.reshape((height, width, *trailing))[:, c0:c1]
        buffer = _reusable(f'tile{index}_{array.dtype.str}', tile.size, array.dtype).reshape(tile.shape)
        np.copyto(buffer, tile)
        out.append(buffer.reshape((-1, *trailing)))
    return tuple(out)


def _tiled_greedy(
    inputs: tuple,
    height: int,
    width: int,
    bounds: list[int],
    knobs: tuple,
    stop_increment: float,
    stop_count: int,
    threads: int | None,
) -> tuple:
    """The greedy on each column strip separately (up to ``threads`` at once), as one action log.

    The strips' grid edges across a border were cut before the seeds, so each strip is an independent
    problem; its log is translated to the whole grid's pixel ids (a tile's row-major order is the
    grid's, so "a merge keeps the smaller id" still holds). The logs are interleaved by each strip's
    running maximum increment (stable: strip order breaks ties), so that for every e the cut at e of
    the joint log is the union of every strip's own cut at e. The result does not depend on threads.
    """
    n_tiles = len(bounds) - 1

    def run(t: int) -> tuple:
        c0, c1 = bounds[t], bounds[t + 1]
        local = _tile_inputs(inputs, height, width, c0, c1)
        kinds, a_ids, b_ids, incs, stats = _greedy(local, height, c1 - c0, knobs, stop_increment, stop_count)
        tile_width = c1 - c0
        a_ids = (a_ids // tile_width) * width + c0 + a_ids % tile_width
        b_global = (b_ids // tile_width) * width + c0 + b_ids % tile_width
        b_ids = np.where(kinds == KIND_CREATE, b_ids, b_global)
        return kinds, a_ids, b_ids, incs, stats

    threads = min(nb.get_num_threads() if threads is None else int(threads), n_tiles)
    if threads == 1:
        results = [run(t) for t in range(n_tiles)]
    else:
        tickets = iter(range(n_tiles))  # next() on a range iterator is atomic under the GIL
        ticket_lock = threading.Lock()

        def drain() -> list:
            done = []
            while True:
                with ticket_lock:
                    t = next(tickets, None)
                if t is None:
                    return done
                done.append((t, run(t)))

        pool = _tile_executor(threads - 1)
        futures = [pool.submit(drain) for _ in range(threads - 1)]
        pairs = drain()
        for future in futures:
            pairs += future.result()
        results = [r for _, r in sorted(pairs, key=lambda pair: pair[0])]
    kinds = np.concatenate([r[0] for r in results])
    running_max = np.concatenate([np.maximum.accumulate(r[3]) if len(r[3]) else r[3] for r in results])
    order = np.argsort(running_max, kind='stable')
    stats = np.sum([r[4] for r in results], axis=0)
    stats[_ST_HEAP_PEAK] = max(int(r[4][_ST_HEAP_PEAK]) for r in results)
    return (
        kinds[order],
        np.concatenate([r[1] for r in results])[order],
        np.concatenate([r[2] for r in results])[order],
        np.concatenate([r[3] for r in results])[order],
        stats,
    )


def _noise_scaled(scan: RayScan, noise: NoiseModel) -> tuple[RayScan, np.ndarray]:
    """The scan with each ray's direction scaled by its sigma_k, and the sigmas (m; NaN: invalid).

    The residual (w . p - 1) / (w . v) of a plane w then is (r_k - rhat_k) / sigma_k exactly.
    """
    sigmas = np.where(scan.valid, noise.sigmas(scan.ranges, scan.directions), np.nan)
    directions = scan.directions * np.where(scan.valid, sigmas, 0.0)[:, None]
    return replace(scan, directions=directions), sigmas


class _ProfileDefault:
    """The default of an extract_planes argument: today's value without a sensor, else the profile's."""

    def __repr__(self) -> str:
        return 'the profile default'


PROFILE_DEFAULT = _ProfileDefault()
#: extract_planes's defaults without a sensor profile (sensor=None).
_NO_PROFILE_DEFAULTS = PROFILES['none']


def _final_planes(hierarchy: PlaneHierarchy, min_plane_points: int) -> PlaneSet:
    """The planes after every action of the hierarchy (no threshold given)."""
    steps = len(hierarchy.actions)
    planes, _ = fit_pixel_groups(
        hierarchy.scan,
        hierarchy.plane_ids(steps),
        sigmas=hierarchy.sigmas,
        min_plane_points=min_plane_points,
        residuals=False,
        actions=steps,
    )
    return planes


def _profile_setting(profile: SensorProfile | None, name: str, value):
    """An extract_planes argument: as given, else the profile's (sensor=None: the 'none' profile's)."""
    if value is not PROFILE_DEFAULT:
        return value
    return getattr(_NO_PROFILE_DEFAULTS if profile is None else profile, name, None)


def _extract_transposed_sweep(points, origins, **options) -> PlaneSet | list[PlaneSet]:
    """extract_planes of a transposed sweep (one column per beam, at least 4 times as tall as wide):
    its strips are azimuth sectors across the rows, so it is extracted as the sweep it is and its
    labels are transposed back (the 4-neighbourhood and the tetrominoes are symmetric: the same planes)."""

    def transposed(array):
        return np.ascontiguousarray(np.swapaxes(np.asarray(array), 0, 1))

    result = extract_planes(
        transposed(points), origins=origins if np.ndim(origins) != 3 else transposed(origins), **options
    )
    if isinstance(result, list):
        return [replace(cut, labels=np.ascontiguousarray(cut.labels.T)) for cut in result]
    return replace(result, labels=np.ascontiguousarray(result.labels.T))


def extract_planes(
    points: np.ndarray,
    *,
    origins: np.ndarray | None = None,
    sensor: str | SensorProfile | None = None,
    max_error_increment: float | Sequence[float] | None = PROFILE_DEFAULT,
    max_planes: int | Sequence[int] | None = None,
    max_neighbor_distance: float = PROFILE_DEFAULT,
    min_plane_points: int = PROFILE_DEFAULT,
    surface_tolerance: float | None = PROFILE_DEFAULT,
    connected_only: bool = PROFILE_DEFAULT,
    rings: np.ndarray | None = None,
    tiles: int | str = PROFILE_DEFAULT,
    threads: int | None = None,
) -> PlaneSet | list[PlaneSet]:
    """Extract finite planes from an organized scan with PPE.

    An unorganized ``(N, 3)`` cloud (with its ``rings``, optional) is put on a range image first and
    its labels are ``(N,)``: see :func:`ppe_ros.core.projection.extract_planes_unorganized`.

    Args:
        points: organized ``(H, W, 3)`` endpoints in metres (any frame), NaN = no return.
        origins: ray starts in the same frame: None (the frame origin), ``(3,)`` or ``(H, W, 3)``.
        sensor: None or ``'none'`` (the paper's model with the defaults e 0.01 m^2, lmax inf, 4
            points: the results of earlier versions), or a sensor profile: ``'lidar'``,
            ``'depth_camera'``, ``'paper'`` or a :class:`~ppe_ros.core.sensor.SensorProfile`. A profile sets the range
            noise model and the defaults of the arguments below; arguments given explicitly win.
        max_error_increment: the paper's e: a snapshot is the state before the first action whose
            error increment exceeds it (m^2 in the paper's model; dimensionless, in units of the
            rays' noise variance, with a noise model). One value or a list (one snapshot each).
        max_planes: the paper's J_max (atomic rays and regular planes counted), one value or a list.
        max_neighbor_distance: largest distance (m) between neighbouring endpoints that may be
            joined (the paper's d / lmax).
        min_plane_points: planes with fewer rays are reported as no plane.
        surface_tolerance: tau (m): after the greedy, pieces of one physical surface (deviating from
            their common plane by at most tau RMS) are merged (ppe_ros.core.consolidation); None:
            no consolidation.
        connected_only: consolidate only pieces that touch in the grid (not across occluders).
        tiles: vertical strips (azimuth sectors of a sweep) whose greedies run independently and in
            parallel (see extract_plane_hierarchy); the consolidation joins the pieces a border cut.
            Default: 'auto' (128-column strips of a sweep, 256 of an image) when the pieces are consolidated
            (a surface_tolerance and a single max_error_increment, no max_planes), else 1 (the exact
            greedy: sensor=None and the 'paper' profile give the results of earlier versions).
        threads: strips extracted at once (None: numba's thread count of the calling thread). The
            result does not depend on it.

    Returns:
        A PlaneSet when both thresholds are single values (or None), else a list of PlaneSets:
        one per e (in the given order), then one per n.
    """
    options = {
        'sensor': sensor,
        'max_error_increment': max_error_increment,
        'max_planes': max_planes,
        'max_neighbor_distance': max_neighbor_distance,
        'min_plane_points': min_plane_points,
        'surface_tolerance': surface_tolerance,
        'connected_only': connected_only,
        'threads': threads,
    }
    if rings is not None or (np.ndim(points) == 2 and np.shape(points)[1] == 3):  # unorganized: project first
        from ppe_ros.core.projection import extract_planes_unorganized

        return extract_planes_unorganized(points, rings, origins=origins, tiles=tiles, **options)
    profile = None if sensor is None else sensor_profile(sensor)
    if profile == _NO_PROFILE_DEFAULTS:  # 'none': the paper's model, as sensor=None
        profile = None

    max_error_increment, max_neighbor_distance, min_plane_points, surface_tolerance, connected_only = (
        _profile_setting(profile, name, options[name])
        for name in (
            'max_error_increment',
            'max_neighbor_distance',
            'min_plane_points',
            'surface_tolerance',
            'connected_only',
        )
    )
    connected_only = bool(connected_only)
    e_list = _as_threshold_list(max_error_increment, 'max_error_increment', float)
    n_list = _as_threshold_list(max_planes, 'max_planes', int)
    if int(min_plane_points) < 1:
        raise ValueError(f'min_plane_points must be >= 1; got {min_plane_points!r}')
    if surface_tolerance is not None and not (np.isfinite(float(surface_tolerance)) and surface_tolerance > 0):
        raise ValueError(f'surface_tolerance must be a length > 0 m or None; got {surface_tolerance!r}')
    noise = None if profile is None else profile.noise_for(points, origins)
    if tiles is PROFILE_DEFAULT:
        tiles = 'auto' if surface_tolerance is not None and e_list and not n_list else 1
    if tiles == 'auto' and np.ndim(points) == 3 and np.shape(points)[0] >= 4 * np.shape(points)[1]:
        return _extract_transposed_sweep(points, origins, tiles=tiles, **options)
    hierarchy = extract_plane_hierarchy(
        points,
        origins=origins,
        max_neighbor_distance=max_neighbor_distance,
        max_error_increment=max(e_list) if e_list else None,
        max_planes=min(n_list) if n_list else None,
        noise=noise,
        tiles=tiles,
        threads=threads,
    )
    cut_kwargs = [{'max_error_increment': e} for e in e_list or []] + [{'max_planes': n} for n in n_list or []]
    if surface_tolerance is None and profile is None:
        cuts = [hierarchy.cut(**kw, min_plane_points=min_plane_points) for kw in cut_kwargs]
    else:
        cuts = [
            whole_surfaces(hierarchy, kw, profile, min_plane_points, surface_tolerance, connected_only)
            for kw in cut_kwargs
        ]
    cuts = cuts or [_final_planes(hierarchy, min_plane_points)]
    scalar = not isinstance(max_error_increment, Sequence | np.ndarray) and not isinstance(
        max_planes, Sequence | np.ndarray
    )
    return cuts[0] if scalar and len(cuts) == 1 else cuts
