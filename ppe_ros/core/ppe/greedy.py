"""The greedy PPE kernel: its phases (next action, execute create / extend / merge, bookkeeping, merge loop), the
driver kernel that runs them, the Python driver that sizes its pools, and the replay of an action log."""

from __future__ import annotations

import numba as nb
import numpy as np

from ppe_ros.core.fitting import fit_rays
from ppe_ros.core.ppe.adjacency import _adj_append, _adj_concat, _release_deferred
from ppe_ros.core.ppe.intrinsics import _prefetch
from ppe_ros.core.ppe.layout import (
    _ADJ_CLASSES,
    _AN_FIELDS,
    _AN_KEY,
    _AN_KIND,
    _AN_PLANE,
    _AN_VA,
    _AN_VB,
    _FIT_ITERATIONS,
    _FIT_TOLERANCE,
    _G_EXTEND,
    _G_MERGE_EXACT,
    _G_MERGE_MODEL,
    _G_SEED,
    _N_STATS,
    _NPF,
    _NPI,
    _NQS,
    _PADJ,
    _PADJC,
    _PADJN,
    _PALIVE,
    _PCOUNT,
    _PCOUNTLIN,
    _PCOUNTLOOP,
    _PDEFER,
    _PE,
    _PH,
    _PHEAD,
    _PMVER,
    _PRMAX,
    _PROOT,
    _PRPARTNER,
    _PSTAMP,
    _PTAIL,
    _PVER,
    _PW,
    _PWL,
    _Q_BUCKETS,
    _Q_CHUNK,
    _QCOUNT,
    _QCUR,
    _ST_HEAP_PEAK,
    _ST_MERGE_EVALS,
    _ST_MERGE_REFINES,
    _ST_NEW_CANDIDATES,
    _ST_POPS,
    _ST_REEVALS,
    _ST_REFINE_RAYS,
    _ST_REFINED_REUSES,
    _ST_RELIN_RAYS,
    _ST_RELINS,
    BOUND_SLACK,
    KIND_CREATE,
    KIND_EXTEND,
    KIND_MERGE,
    MODEL_CUTOFF_FACTOR,
    MODEL_MERGE_KEY_MARGIN,
    TETROMINO_OFFSETS,
)
from ppe_ros.core.ppe.memory import _work_buffers
from ppe_ros.core.ppe.queue import _g_entry, _g_pop, _h_drop_taken, _h_meld, _q_chunks, _q_load, _q_push, _queue_proxy
from ppe_ros.core.ppe.seeds import _sort_seed_keys
from ppe_ros.core.ppe.state import (
    _cache_merge,
    _candidate_increment,
    _find,
    _gather,
    _get_fit,
    _hybrid_merge,
    _keep_refined_merge,
    _model_extension,
    _model_merge,
    _model_merge_increment,
    _refined_merge_increment,
    _relinearise,
    _set_exact_state,
    _store_state,
    _union_fit,
)

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
                    e_small, _, _, _ = fit_rays(
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


def _greedy(inputs: tuple, height: int, width: int, options, stop_increment: float, stop_count: int) -> tuple:
    """The greedy on one grid: action log (kinds, a, b, increments) and stats, in the calling thread's work memory.

    inputs: endpoints, directions, valid, ok_right, ok_down, seed_sse, seed_best, seed_key of the grid;
    options: the GreedyOptions.
    """
    endpoints, directions, valid, ok_right, ok_down, seed_sse, seed_best, seed_key = inputs
    pool_capacity = options.pool_capacity
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
            options.exact_plane_size,
            options.exact_merge_size,
            options.relinearisation_drift,
            stop_increment,
            stop_count,
            BOUND_SLACK,
            1.0 - MODEL_MERGE_KEY_MARGIN,
            options.refined_merge_growth,
            options.merge_loop_growth,
            options.defer_merges,
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
