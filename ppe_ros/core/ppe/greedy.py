"""The greedy PPE kernel: its phases (next action, execute create / extend / merge, bookkeeping, merge loop), the
driver kernel that runs them, the Python driver that sizes its pools, and the replay of an action log."""

from __future__ import annotations

from collections import namedtuple

import numba as nb
import numpy as np

from ppe_ros.core.fitting import fit_rays
from ppe_ros.core.ppe.adjacency import _adj_append, _adj_concat, _release_deferred
from ppe_ros.core.ppe.intrinsics import _prefetch

# --------------------------------------------------------------------------------------------
from ppe_ros.core.ppe.layout import (
    _ADJ_CLASSES,
    _AN_FIELDS,
    _AN_KEY,
    _AN_KIND,
    _AN_PLANE,
    _AN_VA,
    _AN_VB,
    _EC_RAY,
    _EC_VER,
    _FIT_ITERATIONS,
    _G_EXTEND,
    _G_MERGE_EXACT,
    _G_MERGE_MODEL,
    _G_SEED,
    _GI_A,
    _GI_B,
    _GI_KIND,
    _GI_VB,
    _HF_BOUND,
    _HF_VALUE,
    _HI_LEFT,
    _HI_RAY,
    _HI_RIGHT,
    _HI_VER,
    _MC_PARTNER,
    _MC_VA,
    _MC_VB,
    _N_STATS,
    _NEC,
    _NFIT,
    _NFN,
    _NGI,
    _NHF,
    _NHI,
    _NMC,
    _NPF,
    _NPI,
    _NQS,
    _NRCF,
    _NRCI,
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
    _RC_COUNT,
    _RC_VER,
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
from ppe_ros.core.ppe.seeds import BLOCK_SIDE, SEED_SHAPES, _block_seeds, _sort_seed_keys
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
        a(n_pixels * (_NPF + _NFIT))
        + a(gcap)
        + a(far)
        + a(hcap * _NHF)
        + a(n_pixels * _NFIT)
        + a(n_pixels * _NRCF)
        + a(n_pixels + 1)
    )
    n_i = 2 * a(n_pixels) + a(_Q_BUCKETS) + a(acap * _AN_FIELDS) + 2 * a(n_pixels + 1)
    n_i32 = (
        5 * a(n_pixels)
        + a(hcap * _NHI)
        + a(n_pixels * _NPI)
        + a(gcap * _NGI)
        + a(far * _NGI)
        + a(far // _Q_CHUNK * _NFN)
        + a(n_pixels * _NMC)
        + a(n_pixels * _NRCI)
        + a(n_pixels * _NEC)
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


# --------------------------------------------------------------------------------------------
# the greedy's state, bundled by concern (named tuples of arrays: numba passes them as structs)
# --------------------------------------------------------------------------------------------

#: The scan's grid: rays, admissible edges right/down of each pixel, tetromino offsets, grid size.
Grid = namedtuple('Grid', ['endpoints', 'directions', 'ok_right', 'ok_down', 'offsets', 'height', 'width'])
#: The run's settings (GreedyOptions, stops and the cutoffs derived from them) and the pools' capacities.
Knobs = namedtuple(
    'Knobs',
    [
        'exact_plane_size',
        'exact_merge_size',
        'drift_limit',
        'max_increment',
        'min_count',
        'slack',
        'model_key_factor',
        'refined_growth',
        'merge_loop_growth',
        'defer_merges',
        'one_step_candidates',
        'fit_tolerance',
        'cutoff',
        'model_cutoff',
        'gcap',
        'hcap',
        'acap',
    ],
)
#: Per-pixel state (owner plane, pixel lists, union-find parents, merge-loop stamps, candidate owners)
#: and scratch (ray-id buffers, a seed's cells, a pixel's neighbours).
Pixels = namedtuple('Pixels', ['owner', 'nextpix', 'parent', 'seen', 'candidate_of', 'buf', 'buf2', 'cell', 'nb_pix'])
#: Per-plane rows: float and int state (layout _P*), the caches of candidate fits, refined merges and
#: refined hybrid merges (layouts _EC*, _MC*, _RC*).
Planes = namedtuple('Planes', ['pf', 'pi', 'ecache_f', 'ecache_i', 'mcache_f', 'mcache_i', 'rcache_f', 'rcache_i'])
#: The two-level global queue (queue.py): heap keys and entries, far-bucket pool, bucket heads, state.
Queue = namedtuple('Queue', ['gkey', 'gint', 'fkey', 'fint', 'fnext', 'bhead', 'qstate'])
#: Node pools: the candidate heaps' nodes (hf, hi) and the adjacency segments (anode, its float view
#: akey, free lists afree).
Pools = namedtuple('Pools', ['hf', 'hi', 'anode', 'akey', 'afree'])
#: The initial seeds in (key, anchor) order: the seed table (a column per seeding config), the configs
#: (tetromino ids) of its columns, anchors, keys, best configs.
Seeds = namedtuple('Seeds', ['sse', 'configs', 'order', 'key', 'best'])
#: The action log (kind, a, b, increment per action), statistics and the pools' overflow.
Log = namedtuple('Log', ['kind', 'a', 'b', 'inc', 'stats', 'overflow'])

#: Outcomes of _next_action.
_NO_ACTION = 0
_FOUND = 1
_OVERFLOW = 2


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _push(q, gsize, key, kind, a, b, va, vb):
    """_q_push of an entry into the queue q; returns the heap size."""
    return _q_push(q.gkey, q.gint, gsize, q.fkey, q.fint, q.fnext, q.bhead, q.qstate, key, kind, a, b, va, vb)


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _proxy(q, pools, pl, p, gsize, cutoff):
    """_queue_proxy of plane p's extension candidates into the queue q; returns (heap size, proxy key)."""
    return _queue_proxy(
        q.gkey, q.gint, gsize, q.fkey, q.fint, q.fnext, q.bhead, q.qstate, pools.hf, pools.hi, pl.pf, pl.pi, p, cutoff
    )


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _full(log):
    """True when a pool ran out (the run stops and is repeated with the capacities in log.overflow)."""
    return log.overflow[0] > 0 or log.overflow[1] > 0 or log.overflow[2] > 0


# The phases are inlined into the driver loop (numba's inline='always'): as calls, each would pass the
# bundles' arrays (dozens of them) by value on every pop and action.

# --------------------------------------------------------------------------------------------
# phase 1: the next action with an exact key
# --------------------------------------------------------------------------------------------


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _pop_entry(q, sd, pl, pools, px, gsize, seed_ptr):
    """The next entry: the sorted initial seeds' or the heap's, whichever comes first.

    Returns (key, kind, a, b, va, vb, gsize, seed_ptr).
    """
    gkey, gint = q.gkey, q.gint
    if seed_ptr < len(sd.order):
        sa = sd.order[seed_ptr]
        sk = sd.key[seed_ptr]
        sb = sd.best[seed_ptr]
        if gsize == 0 or (
            sk < gkey[0]
            or (
                sk == gkey[0]
                and (
                    gint[0, _GI_KIND] > _G_SEED
                    or (
                        gint[0, _GI_KIND] == _G_SEED
                        and (gint[0, _GI_A] > sa or (gint[0, _GI_A] == sa and gint[0, _GI_B] > sb))
                    )
                )
            )
        ):
            return sk, _G_SEED, sa, sb, 0, 0, gsize, seed_ptr + 1
    gsize = _g_pop(gkey, gint, gsize)
    key, kind, ea, eb, eva, evb = _g_entry(gkey, gint, gsize)
    if gsize > 0:  # the next entry's planes load while this one is handled
        _prefetch(pl.pi, gint[0, _GI_A], 0)
        _prefetch(pl.pf, gint[0, _GI_A], 0)
        if gint[0, _GI_KIND] == _G_EXTEND:  # its candidate node (at the push) and ray
            _prefetch(pools.hi, gint[0, _GI_VB], 0)
            _prefetch(pools.hf, gint[0, _GI_VB], 0)
            _prefetch(px.owner, gint[0, _GI_B], 0)
        else:
            _prefetch(pl.pi, gint[0, _GI_B], 0)
    return key, kind, ea, eb, eva, evb, gsize, seed_ptr


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _seed_entry(g, kn, px, q, sd, key, anchor, c, gsize):
    """A popped seed (anchor, config c): True when its cells are all free; else its anchor's next best
    valid seed after (key, c) is queued. Returns (found, gsize)."""
    owner, offsets, width, seed_sse, configs = px.owner, g.offsets, g.width, sd.sse, sd.configs
    i = anchor // width
    j = anchor % width
    ok = True
    for t in range(4):
        if owner[(i + offsets[c, t, 0]) * width + (j + offsets[c, t, 1])] >= 0:
            ok = False
            break
    if ok:
        return True, gsize
    # none when the anchor's own ray is taken (every tetromino contains its anchor)
    best = -1  # the table's column of the next best seed (configs increase with the column)
    for column in range(len(configs) if owner[anchor] < 0 else 0):
        c2 = configs[column]
        e2 = seed_sse[anchor, column]
        if not np.isfinite(e2):
            continue
        if e2 < key or (e2 == key and c2 <= c):
            continue
        ok2 = True
        for t in range(4):
            if owner[(i + offsets[c2, t, 0]) * width + (j + offsets[c2, t, 1])] >= 0:
                ok2 = False
                break
        if not ok2:
            continue
        if best < 0 or e2 < seed_sse[anchor, best]:
            best = column
    if best >= 0 and seed_sse[anchor, best] <= kn.cutoff:
        gsize = _push(q, gsize, seed_sse[anchor, best], _G_SEED, anchor, configs[best], 0, 0)
    return False, gsize


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _revalue_candidate(g, kn, px, pl, pools, p, root, hfree):
    """Value the top candidate node root of plane p (a stale bound) exactly for p's current version and
    put it back into p's heap (a candidate of infinite value is freed instead). Returns hfree."""
    hf, hi, pf, pi = pools.hf, pools.hi, pl.pf, pl.pi
    k = hi[root, _HI_RAY]
    newroot = _h_meld(hf, hi, hi[root, _HI_LEFT], hi[root, _HI_RIGHT])
    small = pi[p, _PCOUNT] + 1 <= kn.exact_plane_size
    n = _gather(pi, px.nextpix, p, px.buf, g.endpoints, g.directions) if small else 0
    inc = _candidate_increment(
        g.endpoints,
        g.directions,
        pf,
        p,
        small,
        px.buf,
        n,
        k,
        pi[p, _PVER],
        pl.ecache_i,
        pl.ecache_f,
        kn.one_step_candidates,
        kn.fit_tolerance,
    )
    if inc < 0.0:
        inc = 0.0
    value = pf[p, _PE] + inc
    hf[root, _HF_BOUND] = value - kn.slack * abs(value)
    hf[root, _HF_VALUE] = value
    hi[root, _HI_VER] = pi[p, _PVER]
    hi[root, _HI_LEFT] = -1
    hi[root, _HI_RIGHT] = -1
    if not np.isfinite(value):
        hi[root, _HI_LEFT] = hfree  # the free list is linked through the left child
        hfree = root
        pi[p, _PROOT] = newroot
        if px.candidate_of[k] >= 0 and _find(px.parent, px.candidate_of[k]) == p:
            px.candidate_of[k] = -1  # p may hold no other node for k
    else:
        pi[p, _PROOT] = _h_meld(hf, hi, newroot, root)
    return hfree


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _extend_entry(g, kn, px, pl, q, pools, log, key, p, ray, stamp, gsize, hfree):
    """A popped extension proxy of plane p for its top candidate ray (at proxy stamp).

    The action when the top is that ray, valued for p's version, and the proxy key is not below its
    increment; else the top is re-valued if stale, p's proxy re-queued for its new top and the merges
    deferred behind the old proxy that the new one no longer precedes released.
    Returns (outcome, increment, ray, gsize, hfree); outcome _OVERFLOW when the queue ran out.
    """
    pf, pi, hf, hi = pl.pf, pl.pi, pools.hf, pools.hi
    if pi[p, _PALIVE] == 0 or stamp != pi[p, _PSTAMP]:
        return _NO_ACTION, key, ray, gsize, hfree
    # candidate rays taken by another plane since: drop them
    root, hfree = _h_drop_taken(hf, hi, px.owner, pi[p, _PROOT], hfree)
    pi[p, _PROOT] = root
    if root >= 0 and hi[root, _HI_RAY] == ray:  # else the proxy's candidate was dropped: re-queue
        if hi[root, _HI_VER] == pi[p, _PVER]:
            inc = hf[root, _HF_VALUE] - pf[p, _PE]
            if key >= inc:
                return _FOUND, inc, ray, gsize, hfree
            # (the proxy key was a bound): re-push with the exact key
        else:
            log.stats[_ST_REEVALS] += 1
            hfree = _revalue_candidate(g, kn, px, pl, pools, p, root, hfree)
    gsize, proxy_key = _proxy(q, pools, pl, p, gsize, kn.cutoff)
    if gsize + q.qstate[_QCOUNT] + pi[p, _PADJN] + 8 >= kn.gcap:
        log.overflow[0] = 2 * (kn.gcap + pi[p, _PADJN])
        return _OVERFLOW, key, ray, gsize, hfree
    if pf[p, _PDEFER] <= proxy_key and pf[p, _PDEFER] < np.inf:
        gsize = _release_deferred(
            q.gkey,
            q.gint,
            gsize,
            q.fkey,
            q.fint,
            q.fnext,
            q.bhead,
            q.qstate,
            pools.anode,
            pools.akey,
            pf,
            p,
            pi[p, _PADJ],
            pi[p, _PADJN],
            proxy_key,
        )
    return _NO_ACTION, key, ray, gsize, hfree


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _merge_is_current(pl, kind, a, b):
    """An exact merge entry is current when neither plane changed since it was valued: the planes are at
    their merge versions, or a refinement of them at their versions is the last kept one (else a large
    plane grew since, without a full merge loop, and the merge is refined again at the current state)."""
    pi, mcache_i = pl.pi, pl.mcache_i
    return kind == _G_MERGE_EXACT and (
        (pi[a, _PVER] == pi[a, _PMVER] and pi[b, _PVER] == pi[b, _PMVER])
        or (
            mcache_i[a, _MC_PARTNER] == b
            and mcache_i[a, _MC_VA] == pi[a, _PVER]
            and mcache_i[a, _MC_VB] == pi[b, _PVER]
        )
    )


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _refined_increment(g, kn, px, pl, log, a, b):
    """Refine the merge of planes a < b: an exact union fit when small, else the larger plane's model plus
    the smaller plane's exact residuals; the refinement is cached (mcache, rcache). Returns the increment."""
    endpoints, directions, pf, pi, buf = g.endpoints, g.directions, pl.pf, pl.pi, px.buf
    log.stats[_ST_MERGE_REFINES] += 1
    if pi[a, _PCOUNT] + pi[b, _PCOUNT] <= kn.exact_plane_size:
        n1 = _gather(pi, px.nextpix, a, buf, endpoints, directions)
        n2 = _gather(pi, px.nextpix, b, buf, endpoints, directions, n1)
        sse, u0, u1, u2 = _union_fit(endpoints, directions, pf, buf, n1 + n2, a, b, kn.fit_tolerance)
        zero = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        _cache_merge(pl.mcache_i, pl.mcache_f, a, b, pi[a, _PVER], pi[b, _PVER], sse, u0, u1, u2, zero)
        return sse - pf[a, _PE] - pf[b, _PE]
    big = a
    small = b
    if pi[b, _PCOUNT] > pi[a, _PCOUNT]:
        big = b
        small = a
    n = _gather(pi, px.nextpix, small, buf, endpoints, directions)
    log.stats[_ST_REFINE_RAYS] += n
    if n <= kn.exact_plane_size:
        e_small = pf[small, _PE]  # a small plane's E is its exact fit's
    else:
        w0, w1, w2 = pf[small, _PW], pf[small, _PW + 1], pf[small, _PW + 2]
        e_small, _, _, _ = fit_rays(endpoints, directions, buf, n, w0, w1, w2, _FIT_ITERATIONS, kn.fit_tolerance)
    _, m0, m1, m2 = _model_merge(pf, a, b)
    value, m0, m1, m2, info, grad = _hybrid_merge(endpoints, directions, pf, big, buf, n, m0, m1, m2, kn.fit_tolerance)
    _cache_merge(pl.mcache_i, pl.mcache_f, a, b, pi[a, _PVER], pi[b, _PVER], value, m0, m1, m2, info)
    if kn.refined_growth > 0.0:
        _keep_refined_merge(pl.rcache_i, pl.rcache_f, pf, pi, big, small, e_small, value, m0, m1, m2, info, grad)
    return value - pf[big, _PE] - e_small


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _merge_entry(g, kn, px, pl, q, log, kind, a, b, va, vb, gsize):
    """A popped merge of planes a < b valued at their merge versions (va, vb): True when it is current and
    exact; a model merge (or an exact one of a grown plane) is refined and queued again with its exact
    key. Returns (found, gsize)."""
    pi = pl.pi
    if pi[a, _PALIVE] == 0 or pi[b, _PALIVE] == 0:
        return False, gsize
    if pi[a, _PMVER] != va or pi[b, _PMVER] != vb:
        return False, gsize
    if _merge_is_current(pl, kind, a, b):
        return True, gsize
    inc = _refined_increment(g, kn, px, pl, log, a, b)
    if inc < 0.0:
        inc = 0.0
    if inc <= kn.cutoff:
        gsize = _push(q, gsize, inc, _G_MERGE_EXACT, a, b, va, vb)
    return False, gsize


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _next_action(g, kn, px, pl, q, pools, sd, log, gsize, hused, hfree, seed_ptr):
    """Pop entries until one is an action with an exact key (stale entries are dropped, bounds and model
    merges valued again and re-queued). Returns (outcome, key, kind, a, b, gsize, hfree, seed_ptr);
    outcome _NO_ACTION when the queue ran empty, _OVERFLOW when a pool ran out."""
    qstate = q.qstate
    while gsize > 0 or qstate[_QCOUNT] > 0 or seed_ptr < len(sd.order):
        if gsize + qstate[_QCOUNT] + 8 >= kn.gcap:
            log.overflow[0] = 2 * kn.gcap
        if gsize == 0 and qstate[_QCOUNT] > 0:
            gsize = _q_load(q.gkey, q.gint, q.fkey, q.fint, q.fnext, q.bhead, qstate, pl.pi)
            if gsize == 0 and seed_ptr >= len(sd.order):
                break
        if hused + 8 >= kn.hcap:
            log.overflow[1] = 2 * kn.hcap
        if _full(log):
            return _OVERFLOW, 0.0, 0, 0, 0, gsize, hfree, seed_ptr
        key, kind, ea, eb, eva, evb, gsize, seed_ptr = _pop_entry(q, sd, pl, pools, px, gsize, seed_ptr)
        log.stats[_ST_POPS] += 1
        if kind == _G_SEED:
            found, gsize = _seed_entry(g, kn, px, q, sd, key, ea, eb, gsize)
        elif kind == _G_EXTEND:
            outcome, key, eb, gsize, hfree = _extend_entry(g, kn, px, pl, q, pools, log, key, ea, eb, eva, gsize, hfree)
            if outcome == _OVERFLOW:
                return _OVERFLOW, 0.0, 0, 0, 0, gsize, hfree, seed_ptr
            found = outcome == _FOUND
        else:
            found, gsize = _merge_entry(g, kn, px, pl, q, log, kind, ea, eb, eva, evb, gsize)
        if found:
            return _FOUND, key, kind, ea, eb, gsize, hfree, seed_ptr
    return _NO_ACTION, 0.0, 0, 0, 0, gsize, hfree, seed_ptr


# --------------------------------------------------------------------------------------------
# phase 2: execute the action (create, extend, merge)
# --------------------------------------------------------------------------------------------


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _create(g, kn, px, pl, p, c):
    """Create plane p (its anchor's id) from the tetromino of config c at p; its cells go into px.buf2."""
    pf, pi, cell, endpoints = pl.pf, pl.pi, px.cell, g.endpoints
    i = p // g.width
    j = p % g.width
    for t in range(4):
        cell[t] = (i + g.offsets[c, t, 0]) * g.width + (j + g.offsets[c, t, 1])
    # a plane id is created once (its anchor is taken for good): its rows start here
    px.parent[p] = p
    px.seen[p] = -1
    pi[p, _PSTAMP] = 0
    for t in range(3):
        pl.mcache_i[p, t] = -1
    pf[p, _PRPARTNER] = -1.0
    pl.ecache_i[p, _EC_RAY] = -1
    pl.ecache_i[p, _EC_VER] = -1
    pi[p, _PALIVE] = 1
    pi[p, _PROOT] = -1
    pi[p, _PADJ] = -1
    pi[p, _PADJC] = 0
    pi[p, _PADJN] = 0
    pi[p, _PHEAD] = cell[0]
    for t in range(4):
        px.owner[cell[t]] = p
        px.nextpix[cell[t]] = cell[t + 1] if t < 3 else -1
    pi[p, _PTAIL] = cell[3]
    pi[p, _PCOUNT] = 4
    pf[p, _PCOUNTLIN] = 4
    _set_exact_state(endpoints, g.directions, pf, cell, 4, p, np.nan, np.nan, np.nan, kn.fit_tolerance)
    rmax = 0.0
    for t in range(4):
        k = cell[t]
        r = np.sqrt(endpoints[k, 0] ** 2 + endpoints[k, 1] ** 2 + endpoints[k, 2] ** 2)
        rmax = max(rmax, r)
    pf[p, _PRMAX] = rmax
    for t in range(4):
        px.buf2[t] = cell[t]


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _extend(g, kn, px, pl, p, k, key):
    """Extend plane p by ray k (increment key); ray k goes into px.buf2. Returns the count of p's rays left
    gathered in px.buf (-1: none)."""
    pf, pi, endpoints = pl.pf, pl.pi, g.endpoints
    count = pi[p, _PCOUNT]
    px.owner[k] = p
    px.nextpix[k] = -1
    px.nextpix[pi[p, _PTAIL]] = k
    pi[p, _PTAIL] = k
    pi[p, _PCOUNT] = count + 1
    r = np.sqrt(endpoints[k, 0] ** 2 + endpoints[k, 1] ** 2 + endpoints[k, 2] ** 2)
    pf[p, _PRMAX] = max(pf[p, _PRMAX], r)
    px.buf2[0] = k
    if count + 1 <= kn.exact_plane_size:
        w0, w1, w2 = pf[p, _PW], pf[p, _PW + 1], pf[p, _PW + 2]
        if pl.ecache_i[p, _EC_RAY] == k and pl.ecache_i[p, _EC_VER] == pi[p, _PVER]:
            # the candidate's own fit (the least of this version's)
            sse, c0, c1, c2, info = _get_fit(pl.ecache_f, p)
            if not kn.one_step_candidates or np.isfinite(info[0]):
                # exact: no fit again
                _store_state(pf, p, sse, c0, c1, c2, info)
                pf[p, _PCOUNTLIN] = count + 1
                return -1
            w0, w1, w2 = c0, c1, c2  # one step: the exact fit starts from its w
        n = _gather(pi, px.nextpix, p, px.buf, endpoints, g.directions)
        _set_exact_state(endpoints, g.directions, pf, px.buf, n, p, w0, w1, w2, kn.fit_tolerance)
        pf[p, _PCOUNTLIN] = n
        return n
    # a large plane: rank-one update of its model
    _, x0, x1, x2, f, g0, g1, g2 = _model_extension(endpoints, g.directions, pf, p, k)
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
    return -1


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _merged_fit(g, kn, px, pl, a, b):
    """The merged plane's (value, w0, w1, w2, information) of planes a and b (value and information only
    meaningful for a union larger than exact_plane_size, whose state is not refitted)."""
    endpoints, directions, pf, pi, buf = g.endpoints, g.directions, pl.pf, pl.pi, px.buf
    na = pi[a, _PCOUNT]
    nbn = pi[b, _PCOUNT]
    mcache_i = pl.mcache_i
    if mcache_i[a, _MC_PARTNER] == b and mcache_i[a, _MC_VA] == pi[a, _PVER] and mcache_i[a, _MC_VB] == pi[b, _PVER]:
        # the refinement that queued this merge computed the same fit (same planes, versions)
        return _get_fit(pl.mcache_f, a)
    info = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    if na + nbn <= kn.exact_plane_size:
        # exact merged state from the best of the union's starting points
        n1 = _gather(pi, px.nextpix, a, buf, endpoints, directions)
        n2 = _gather(pi, px.nextpix, b, buf, endpoints, directions, n1)
        _, w0, w1, w2 = _union_fit(endpoints, directions, pf, buf, n1 + n2, a, b, kn.fit_tolerance)
        return 0.0, w0, w1, w2, info
    big = a if na >= nbn else b
    small = b if big == a else a
    n = _gather(pi, px.nextpix, small, buf, endpoints, directions)
    _, m0, m1, m2 = _model_merge(pf, a, b)
    value, w0, w1, w2, info, _ = _hybrid_merge(endpoints, directions, pf, big, buf, n, m0, m1, m2, kn.fit_tolerance)
    return value, w0, w1, w2, info


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _merge(g, kn, px, pl, pools, a, b, aused):
    """Merge planes a and b into the smaller id s. Returns (s, s's adjacency nodes before the merge, aused);
    aused -1 when the adjacency pool ran out."""
    pf, pi = pl.pf, pl.pi
    s = min(a, b)
    o = max(a, b)
    total = pi[a, _PCOUNT] + pi[b, _PCOUNT]
    value, w0, w1, w2, info = _merged_fit(g, kn, px, pl, a, b)
    # concatenate pixel lists into s
    px.nextpix[pi[s, _PTAIL]] = pi[o, _PHEAD]
    pi[s, _PTAIL] = pi[o, _PTAIL]
    px.parent[o] = s
    pi[s, _PCOUNT] = total
    pi[s, _PROOT] = _h_meld(pools.hf, pools.hi, pi[s, _PROOT], pi[o, _PROOT])
    adj_before = pi[s, _PADJN]
    aused = _adj_concat(pools.anode, pools.afree, pi, s, o, aused)
    if aused < 0:
        return s, adj_before, -1
    pf[s, _PRMAX] = max(pf[a, _PRMAX], pf[b, _PRMAX])
    lin = max(pf[a, _PCOUNTLIN], pf[b, _PCOUNTLIN])
    if total <= kn.exact_plane_size:
        n = _gather(pi, px.nextpix, s, px.buf, g.endpoints, g.directions)
        _set_exact_state(g.endpoints, g.directions, pf, px.buf, n, s, w0, w1, w2, kn.fit_tolerance)
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
    return s, adj_before, aused


# --------------------------------------------------------------------------------------------
# phase 3: bookkeeping of the changed plane, its new neighbours, its merges
# --------------------------------------------------------------------------------------------


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _refresh(g, kn, px, pl, log, p, created, version):
    """After an action on plane p: re-linearise a large plane that doubled or drifted, and give p the new
    version. Returns partial: p is large and grew by at most merge_loop_growth since its last full merge
    loop (it values only its new neighbours' merges; its queued and deferred ones carry its merge version)."""
    pf, pi = pl.pf, pl.pi
    count = pi[p, _PCOUNT]
    partial = not created and count > kn.exact_plane_size and count <= pf[p, _PCOUNTLOOP] * (1.0 + kn.merge_loop_growth)
    if count > kn.exact_plane_size:
        dw = np.sqrt(
            (pf[p, _PW] - pf[p, _PWL]) ** 2
            + (pf[p, _PW + 1] - pf[p, _PWL + 1]) ** 2
            + (pf[p, _PW + 2] - pf[p, _PWL + 2]) ** 2
        )
        if count >= 2 * pf[p, _PCOUNTLIN] or dw * pf[p, _PRMAX] > kn.drift_limit:
            n = _gather(pi, px.nextpix, p, px.buf, g.endpoints, g.directions)
            log.stats[_ST_RELINS] += 1
            log.stats[_ST_RELIN_RAYS] += n
            _relinearise(g.endpoints, g.directions, pf, px.buf, n, p)
            pf[p, _PCOUNTLIN] = n
            partial = False
    # versions are unique across planes: the candidates a merged plane inherits from the absorbed
    # plane can never pass for current ones
    pi[p, _PVER] = version
    return partial


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _neighbours(g, k, nb_pix):
    """The pixels joined to pixel k by admissible edges into nb_pix; returns their count."""
    i = k // g.width
    j = k % g.width
    n = 0
    if j + 1 < g.width and g.ok_right[k]:
        nb_pix[n] = k + 1
        n += 1
    if j > 0 and g.ok_right[k - 1]:
        nb_pix[n] = k - 1
        n += 1
    if i + 1 < g.height and g.ok_down[k]:
        nb_pix[n] = k + g.width
        n += 1
    if i > 0 and g.ok_down[k - g.width]:
        nb_pix[n] = k - g.width
        n += 1
    return n


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _add_candidate(g, kn, px, pl, pools, log, p, q, n_gathered, hused, hfree):
    """Queue ray q as an extension candidate of plane p, valued exactly for p's current version (unless p
    already holds a node for q). Returns (n_gathered, hused, hfree): p's rays are gathered into px.buf
    once, for its first exact candidate fit."""
    pf, pi, hf, hi = pl.pf, pl.pi, pools.hf, pools.hi
    if px.candidate_of[q] >= 0 and _find(px.parent, px.candidate_of[q]) == p:
        # p's node for q was valued for an earlier version: its key is a lower bound, and it is valued
        # again when it reaches the top of p's heap
        return n_gathered, hused, hfree
    log.stats[_ST_NEW_CANDIDATES] += 1
    small = pi[p, _PCOUNT] + 1 <= kn.exact_plane_size
    if small and n_gathered < 0:
        n_gathered = _gather(pi, px.nextpix, p, px.buf, g.endpoints, g.directions)
    inc = _candidate_increment(
        g.endpoints,
        g.directions,
        pf,
        p,
        small,
        px.buf,
        n_gathered,
        q,
        pi[p, _PVER],
        pl.ecache_i,
        pl.ecache_f,
        kn.one_step_candidates,
        kn.fit_tolerance,
    )
    if not np.isfinite(inc):
        return n_gathered, hused, hfree
    if inc < 0.0:
        inc = 0.0
    value = pf[p, _PE] + inc
    if hfree >= 0:
        node = hfree
        hfree = hi[node, _HI_LEFT]
    else:
        node = hused
        hused += 1
    hf[node, _HF_BOUND] = value - kn.slack * abs(value)
    hf[node, _HF_VALUE] = value
    hi[node, _HI_RAY] = q
    hi[node, _HI_VER] = pi[p, _PVER]
    hi[node, _HI_LEFT] = -1
    hi[node, _HI_RIGHT] = -1
    pi[p, _PROOT] = _h_meld(hf, hi, pi[p, _PROOT], node)
    px.candidate_of[q] = p
    return n_gathered, hused, hfree


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _frontier(g, kn, px, pl, pools, log, p, new_pixels, in_buf, hused, hfree, aused):
    """The new neighbours of plane p's added pixels px.buf2[:new_pixels]: free rays become extension
    candidates, other planes neighbours (both adjacency lists). Returns (hused, hfree, aused); aused -1
    when the adjacency pool ran out."""
    n_gathered = in_buf
    nb_pix = px.nb_pix
    for t in range(new_pixels):
        n_nb = _neighbours(g, px.buf2[t], nb_pix)
        for u in range(n_nb):  # the neighbours' rows load together (a candidate's fit reads its ray)
            _prefetch(g.endpoints, nb_pix[u], 0)
            _prefetch(g.directions, nb_pix[u], 0)
            _prefetch(px.owner, nb_pix[u], 0)
            _prefetch(px.candidate_of, nb_pix[u], 0)
        for u in range(n_nb):
            q = nb_pix[u]
            if px.owner[q] < 0:
                n_gathered, hused, hfree = _add_candidate(g, kn, px, pl, pools, log, p, q, n_gathered, hused, hfree)
                continue
            other = _find(px.parent, px.owner[q])
            if other != p:
                aused = _adj_append(pools.anode, pools.akey, pools.afree, pl.pi, p, other, aused)
                if aused >= 0:
                    aused = _adj_append(pools.anode, pools.akey, pools.afree, pl.pi, other, p, aused)
                if aused < 0:
                    return hused, hfree, -1
    return hused, hfree, aused


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _merge_key(g, kn, px, pl, p, q):
    """Key, entry kind and reuse flag of the merge of planes p and q: an exact union fit for small unions, the kept
    refinement's residual model while it stands, else the planes' models (queued below their value)."""
    pf, pi = pl.pf, pl.pi
    a = min(p, q)
    b = max(p, q)
    if pi[a, _PCOUNT] + pi[b, _PCOUNT] <= kn.exact_merge_size:
        n1 = _gather(pi, px.nextpix, a, px.buf, g.endpoints, g.directions)
        n2 = _gather(pi, px.nextpix, b, px.buf, g.endpoints, g.directions, n1)
        sse, _, _, _ = _union_fit(g.endpoints, g.directions, pf, px.buf, n1 + n2, a, b, kn.fit_tolerance)
        return sse - pf[a, _PE] - pf[b, _PE], _G_MERGE_EXACT, False
    if (
        pf[q, _PRPARTNER] == p
        and pl.rcache_i[q, _RC_VER] == pi[q, _PVER]
        and pi[p, _PCOUNT] <= pl.rcache_i[q, _RC_COUNT] * (1.0 + kn.refined_growth)
    ):
        # refined before, q unchanged since and p grown a little: q's residual model at the refined
        # union's w stands for its exact residuals
        return _refined_merge_increment(pf, p, pl.rcache_f, q), _G_MERGE_EXACT, True
    # queued below its model value so that it is refined (exactly) before any action it could precede
    # even where the model overestimates the increment
    return _model_merge_increment(pf, a, b) * kn.model_key_factor, _G_MERGE_MODEL, False


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _merge_loop(g, kn, px, pl, q, pools, log, p, partial, adj_before, proxy_key, gsize, seen_stamp):
    """Value the merges of plane p with its neighbouring planes (compacting p's adjacency segment; a
    partial loop values only the nodes appended by this action). A merge whose key exceeds p's proxy key
    is deferred on p's node instead of queued: p's proxy comes first, and p either changes (and values
    its merges again) or re-queues its proxy, which releases the deferred merges its new key no longer
    precedes. Returns gsize."""
    pf, pi, anode, akey = pl.pf, pl.pi, pools.anode, pools.akey
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
        pf[p, _PCOUNTLOOP] = pi[p, _PCOUNT]
    for r in range(first + n_adj, end):
        if r + 1 < end:  # the next neighbour's rows load while this one is evaluated
            nxt = anode[r + 1, _AN_PLANE]
            _prefetch(px.parent, nxt, 0)
            _prefetch(px.seen, nxt, 0)
            _prefetch(pi, nxt, 0)
            _prefetch(pf, nxt, 0)
            _prefetch(pf, nxt, _PH + 5)
        other = _find(px.parent, anode[r, _AN_PLANE])
        if other == p or pi[other, _PALIVE] == 0 or px.seen[other] == seen_stamp:
            continue
        # kept: compacted to the front of the segment (x <= r, so no unread row is overwritten)
        x = first + n_adj
        px.seen[other] = seen_stamp
        anode[x, _AN_PLANE] = other
        n_adj += 1
        log.stats[_ST_MERGE_EVALS] += 1
        inc, gkind, reused = _merge_key(g, kn, px, pl, p, other)
        if reused:
            log.stats[_ST_REFINED_REUSES] += 1
        if inc < 0.0:
            inc = 0.0
        akey[x, _AN_KEY] = np.inf
        if not inc <= (kn.cutoff if gkind == _G_MERGE_EXACT else kn.model_cutoff):
            continue  # (also NaN)
        a = min(p, other)
        b = max(p, other)
        if inc <= proxy_key or not kn.defer_merges:
            gsize = _push(q, gsize, inc, gkind, a, b, pi[a, _PMVER], pi[b, _PMVER])
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
            q.gkey,
            q.gint,
            gsize,
            q.fkey,
            q.fint,
            q.fnext,
            q.bhead,
            q.qstate,
            anode,
            akey,
            pf,
            p,
            first,
            n_adj,
            proxy_key,
        )
    return gsize


# --------------------------------------------------------------------------------------------
# the driver
# --------------------------------------------------------------------------------------------


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _create_block(g, kn, px, pl, log, p, n_actions):
    """The block seed at anchor p (GreedyOptions.block_seeds): the create of its top-left 2 x 2 square, then
    the extensions by its other rays in row order (each joined to an earlier one by an admissible
    edge), logged with their exact increments. Returns the number of actions logged so far."""
    pf = pl.pf
    _create(g, kn, px, pl, p, 0)  # config 0: the 2 x 2 square at its anchor
    log.kind[n_actions] = KIND_CREATE
    log.a[n_actions] = p
    log.b[n_actions] = 0
    log.inc[n_actions] = pf[p, _PE]
    n_actions += 1
    for t in range(BLOCK_SIDE * BLOCK_SIDE):
        di = t // BLOCK_SIDE
        dj = t % BLOCK_SIDE
        if di < 2 and dj < 2:
            continue  # the square
        k = p + di * g.width + dj
        before = pf[p, _PE]
        _extend(g, kn, px, pl, p, k, 0.0)  # (the key is read only for planes above exact_plane_size)
        log.kind[n_actions] = KIND_EXTEND
        log.a[n_actions] = p
        log.b[n_actions] = k
        log.inc[n_actions] = max(pf[p, _PE] - before, 0.0)
        n_actions += 1
    return n_actions


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _after_action(g, kn, px, pl, q, pools, log, p, new_pixels, in_buf, partial, adj_before, state, seen_stamp):
    """The bookkeeping of plane p after an action (or a block seed) added px.buf2[:new_pixels]: its new
    extension candidates and neighbours, its proxy, its merges (partial: only its new neighbours').
    state = (gsize, hused, hfree, aused); returns it, aused -1 when a pool ran out."""
    gsize, hused, hfree, aused = state
    # capacity for the candidate nodes this step pushes (adjacency segments check their own)
    if hused + 4 * new_pixels + 8 >= kn.hcap:
        log.overflow[1] = 2 * kn.hcap
        return gsize, hused, hfree, -1
    hused, hfree, aused = _frontier(g, kn, px, pl, pools, log, p, new_pixels, in_buf, hused, hfree, aused)
    if aused < 0:
        log.overflow[2] = 2 * kn.acap
        return gsize, hused, hfree, -1
    # proxy of p's extension candidates (rays taken by now, such as the one p just took, dropped)
    root, hfree = _h_drop_taken(pools.hf, pools.hi, px.owner, pl.pi[p, _PROOT], hfree)
    pl.pi[p, _PROOT] = root
    if gsize + q.qstate[_QCOUNT] + 2 + pl.pi[p, _PADJN] >= kn.gcap:
        log.overflow[0] = 2 * (kn.gcap + pl.pi[p, _PADJN])
        return gsize, hused, hfree, -1
    gsize, proxy_key = _proxy(q, pools, pl, p, gsize, kn.cutoff)
    gsize = _merge_loop(g, kn, px, pl, q, pools, log, p, partial, adj_before, proxy_key, gsize, seen_stamp)
    return gsize, hused, hfree, aused


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _place_blocks(g, kn, px, pl, q, pools, log, blocks):
    """Place the block seeds (anchors, in their order) before the greedy's first action: block t gets version
    and merge stamp t + 1. Every block is placed before any bookkeeping, so that no block's rays become
    another's candidates, and each gets its version (and merge version) before any merge loop queues a
    merge with it. Returns (n_actions, gsize, hused, hfree, aused); aused -1 when a pool ran out."""
    n_actions = gsize = hused = aused = 0
    hfree = -1  # the free list of candidate nodes: empty
    for t in range(len(blocks)):
        n_actions = _create_block(g, kn, px, pl, log, blocks[t], n_actions)
    for t in range(len(blocks)):
        _refresh(g, kn, px, pl, log, blocks[t], True, t + 1)
        pl.pi[blocks[t], _PMVER] = t + 1
    state = (gsize, hused, hfree, aused)
    for t in range(len(blocks)):
        p = blocks[t]
        for u in range(BLOCK_SIDE * BLOCK_SIDE):
            px.buf2[u] = p + (u // BLOCK_SIDE) * g.width + u % BLOCK_SIDE
        state = _after_action(g, kn, px, pl, q, pools, log, p, BLOCK_SIDE * BLOCK_SIDE, -1, False, 0, state, t + 1)
        if state[3] < 0:
            break
    return n_actions, state[0], state[1], state[2], state[3]


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _greedy_loop(g, kn, px, pl, q, pools, sd, log, n_valid, blocks):
    """The greedy: the block seeds (anchors, in their order), then until no action is left or the stop is
    reached, the next action, its execution and the bookkeeping of the changed plane. Returns the number of
    actions (-1: a pool ran out)."""
    seed_ptr = 0
    n_actions, gsize, hused, hfree, aused = _place_blocks(g, kn, px, pl, q, pools, log, blocks)
    if aused < 0:
        return -1
    version = seen_stamp = len(blocks)
    plane_count = n_valid - (BLOCK_SIDE * BLOCK_SIDE - 1) * len(blocks)
    while True:
        outcome, key, kind, a, b, gsize, hfree, seed_ptr = _next_action(
            g, kn, px, pl, q, pools, sd, log, gsize, hused, hfree, seed_ptr
        )
        if outcome == _OVERFLOW:
            return -1
        if outcome == _NO_ACTION or not (key <= kn.max_increment or plane_count > kn.min_count):
            return n_actions
        if n_actions >= len(log.kind):
            return n_actions
        log.a[n_actions] = a
        log.b[n_actions] = b
        log.inc[n_actions] = key
        adj_before = 0  # the changed plane's adjacency nodes before this action's appends
        in_buf = -1  # the changed plane's rays when the execution left them in buf (-1: not)
        if kind == _G_SEED:
            log.kind[n_actions] = KIND_CREATE
            _create(g, kn, px, pl, a, b)
            p, new_pixels, plane_count = a, 4, plane_count - 3
        elif kind == _G_EXTEND:
            log.kind[n_actions] = KIND_EXTEND
            adj_before = pl.pi[a, _PADJN]
            in_buf = _extend(g, kn, px, pl, a, b, key)
            p, new_pixels, plane_count = a, 1, plane_count - 1
        else:
            log.kind[n_actions] = KIND_MERGE
            p, adj_before, aused = _merge(g, kn, px, pl, pools, a, b, aused)
            if aused < 0:
                log.overflow[2] = 2 * kn.acap
                return -1
            new_pixels, plane_count = 0, plane_count - 1
        n_actions += 1
        version += 1
        partial = _refresh(g, kn, px, pl, log, p, kind == _G_SEED, version)
        seen_stamp += 1
        state = (gsize, hused, hfree, aused)
        state = _after_action(
            g, kn, px, pl, q, pools, log, p, new_pixels, in_buf, partial, adj_before, state, seen_stamp
        )
        gsize, hused, hfree, aused = state
        if aused < 0:
            return -1


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _pixel_and_plane_views(work_f, work_i, work_i32, n_pixels):
    """The first views of the work buffers: per-pixel state and scratch, the planes' rows.

    Returns (Pixels, pf, ecache_f, pi, of, oi, o32) with the buffers' next free offsets. Pixel, plane
    and node ids, versions and stamps are 32-bit wherever they are stored (each is below 2^31 for the
    scans extract_plane_hierarchy accepts, < MAX_RAYS): the greedy waits on memory, and narrower arrays
    mean fewer cache misses.
    """
    o32 = 0
    oi = 0
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
    # parent, seen and the plane rows are read only for plane ids (anchors of created planes) and
    # written when a plane is created; pixel lists are written as they grow
    px = Pixels(owner, nextpix, parent, seen, candidate_of, buf, buf2, np.empty(4, np.int64), np.empty(4, np.int64))
    # a plane's float state and its candidate-fit slot (ecache_f) share a row: a plane's action reads
    # and writes both
    prow = work_f[0 : n_pixels * (_NPF + _NFIT)].reshape((n_pixels, _NPF + _NFIT))
    of = _aligned(n_pixels * (_NPF + _NFIT))
    # 32-bit fields (half the memory traffic of a plane's row): counts, versions and pixel ids are
    # below H*W, stamps below the number of pops, node indices below the pools' sizes
    pi = work_i32[o32 : o32 + n_pixels * _NPI].reshape((n_pixels, _NPI))
    o32 = _aligned(o32 + n_pixels * _NPI)
    return px, prow[:, :_NPF], prow[:, _NPF:], pi, of, oi, o32


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _queue_and_pool_views(work_f, work_i, work_i32, gcap, hcap, acap, of, oi, o32):
    """The global queue (heap of gcap entries, far-bucket chunks for as many), the candidate node pool
    (hcap nodes) and the adjacency pool (acap nodes) on the work buffers from the offsets on.

    Returns (Queue, Pools, of, oi, o32). Queue entries' kind, ids and versions are all < 2^31. An
    adjacency node is one row (one memory access): the neighbour and a merge deferred on the owner's
    node (its kind, the two versions it was valued at, its key (inf: none) in the float view akey).
    """
    n_chunks = _q_chunks(gcap)
    gkey = work_f[of : of + gcap]
    of = _aligned(of + gcap)
    fkey = work_f[of : of + n_chunks * _Q_CHUNK]
    of = _aligned(of + n_chunks * _Q_CHUNK)
    gint = work_i32[o32 : o32 + gcap * _NGI].reshape((gcap, _NGI))
    o32 = _aligned(o32 + gcap * _NGI)
    fint = work_i32[o32 : o32 + n_chunks * _Q_CHUNK * _NGI].reshape((n_chunks * _Q_CHUNK, _NGI))
    o32 = _aligned(o32 + n_chunks * _Q_CHUNK * _NGI)
    fnext = work_i32[o32 : o32 + n_chunks * _NFN].reshape((n_chunks, _NFN))
    o32 = _aligned(o32 + n_chunks * _NFN)
    bhead = work_i[oi : oi + _Q_BUCKETS]
    oi = _aligned(oi + _Q_BUCKETS)
    bhead[:] = -1
    qstate = np.zeros(_NQS, np.int64)
    qstate[_QCUR] = -1
    hf = work_f[of : of + hcap * _NHF].reshape((hcap, _NHF))
    of = _aligned(of + hcap * _NHF)
    hi = work_i32[o32 : o32 + hcap * _NHI].reshape((hcap, _NHI))
    o32 = _aligned(o32 + hcap * _NHI)
    anode = work_i[oi : oi + acap * _AN_FIELDS].reshape((acap, _AN_FIELDS))
    oi = _aligned(oi + acap * _AN_FIELDS)
    pools = Pools(hf, hi, anode, anode.view(np.float64), np.full(_ADJ_CLASSES, -1, np.int64))
    return Queue(gkey, gint, fkey, fint, fnext, bhead, qstate), pools, of, oi, o32


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _cache_and_log_views(work_f, work_i, work_i32, n_pixels, of, oi, o32):
    """The planes' caches and the action log on the work buffers from the offsets on.

    Returns (mcache_f, mcache_i, rcache_f, rcache_i, ecache_i, Log): the last merge refined per plane
    (keyed by its smaller id: partner, both versions; value, w, information), the last hybrid merge
    refined per plane on its smaller plane (_keep_refined_merge: own version, partner's count; the
    plane's residual model at the union's w), the least candidate fit of each small plane's current
    version (ray, version; its fit is ecache_f, in the plane's float row), the log of up to n_pixels + 1
    actions with zeroed stats and overflow.
    """
    mcache_i = work_i32[o32 : o32 + n_pixels * _NMC].reshape((n_pixels, _NMC))
    o32 = _aligned(o32 + n_pixels * _NMC)
    mcache_f = work_f[of : of + n_pixels * _NFIT].reshape((n_pixels, _NFIT))
    of = _aligned(of + n_pixels * _NFIT)
    rcache_i = work_i32[o32 : o32 + n_pixels * _NRCI].reshape((n_pixels, _NRCI))
    o32 = _aligned(o32 + n_pixels * _NRCI)
    rcache_f = work_f[of : of + n_pixels * _NRCF].reshape((n_pixels, _NRCF))
    of = _aligned(of + n_pixels * _NRCF)
    ecache_i = work_i32[o32 : o32 + n_pixels * _NEC].reshape((n_pixels, _NEC))
    o32 = _aligned(o32 + n_pixels * _NEC)
    log_kind = work_i32[o32 : o32 + n_pixels + 1]
    log_a = work_i[oi : oi + n_pixels + 1]
    oi = _aligned(oi + n_pixels + 1)
    log_b = work_i[oi : oi + n_pixels + 1]
    log_inc = work_f[of : of + n_pixels + 1]
    log = Log(log_kind, log_a, log_b, log_inc, np.zeros(_N_STATS, np.int64), np.zeros(3, np.int64))
    return mcache_f, mcache_i, rcache_f, rcache_i, ecache_i, log


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _initial_seeds(seed_sse, seed_configs, seed_best, seed_key, cutoff):
    """The best valid config of every anchor (seed_best, seed_key from _seed_errors) up to the cutoff, in
    (key, anchor) order (next-best seeds of anchors whose best seed became invalid go through the queue);
    the keys and configs in that order too (seed_key[order[i]] would be a random access)."""
    order, keys = _sort_seed_keys(seed_key, cutoff)
    best = np.empty(len(order), np.int32)
    for t in range(len(order)):
        best[t] = seed_best[order[t]]
    return Seeds(seed_sse, seed_configs, order, keys, best)


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
    seed_configs,
    seed_best,
    seed_key,
    blocks,
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
    one_step_candidates,
    fit_tolerance,
    gcap,
    hcap,
    acap,
    work_f,
    work_i,
    work_i32,
):
    """Run the greedy PPE agglomeration; returns the action log (kind, a, b, increment), stats and overflow.

    seed_sse, seed_configs, seed_best, seed_key: _seed_errors's table (a column per config of seed_configs,
    the seeding tetromino ids) and each anchor's best config and key. blocks: the anchors of the block
    seeds (_block_seeds; empty without GreedyOptions.block_seeds), placed first in their order.
    refined_growth, merge_loop_growth: GreedyOptions's refined_merge_growth and merge_loop_growth (0: off);
    one_step_candidates: its candidate_fits is 'one_step'; fit_tolerance: its fit_tolerance.
    Runs while a candidate exists and (next increment <= max_increment or plane count > min_count).
    The work pools have fixed capacities (queue gcap, candidate nodes hcap, adjacency nodes acap) so
    that no array is reassigned inside the loops: numba then keeps reference counting (atomic
    instructions) out of them. When a pool would run out, the kernel stops at once and returns an
    empty log with ``overflow`` (3,) holding the capacity each pool needs (0: enough); the caller
    runs it again with larger pools (the greedy is deterministic, so the result is the same).
    Its arrays are views of the work buffers work_f (float64), work_i (int64) and work_i32 (int32)
    of at least the sizes _work_sizes gives, which the caller reuses from call to call (fresh memory
    would cost a page fault per 4 KiB page on first touch, tens of thousands per scan).
    """
    n_pixels = height * width
    n_f, n_i, n_i32 = _work_sizes(n_pixels, gcap, hcap, acap)
    if len(work_f) < n_f or len(work_i) < n_i or len(work_i32) < n_i32:
        raise ValueError('work buffers smaller than _work_sizes')
    px, pf, ecache_f, pi, of, oi, o32 = _pixel_and_plane_views(work_f, work_i, work_i32, n_pixels)
    q, pools, of, oi, o32 = _queue_and_pool_views(work_f, work_i, work_i32, gcap, hcap, acap, of, oi, o32)
    mcache_f, mcache_i, rcache_f, rcache_i, ecache_i, log = _cache_and_log_views(
        work_f, work_i, work_i32, n_pixels, of, oi, o32
    )
    pl = Planes(pf, pi, ecache_f, ecache_i, mcache_f, mcache_i, rcache_f, rcache_i)
    cutoff = _run_cutoff(max_increment, min_count, n_pixels)
    kn = Knobs(
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
        one_step_candidates,
        fit_tolerance,
        cutoff,
        MODEL_CUTOFF_FACTOR * cutoff,
        gcap,
        hcap,
        acap,
    )
    g = Grid(endpoints, directions, ok_right, ok_down, offsets, height, width)
    seeds = _initial_seeds(seed_sse, seed_configs, seed_best, seed_key, cutoff)
    n = _greedy_loop(g, kn, px, pl, q, pools, seeds, log, np.count_nonzero(valid), blocks)
    if n < 0:
        return _empty_log(log.stats, log.overflow)
    log.stats[_ST_HEAP_PEAK] = gcap
    return log.kind[:n].astype(np.int8), log.a[:n].copy(), log.b[:n].copy(), log.inc[:n].copy(), log.stats, log.overflow


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _replay(kinds, a_ids, b_ids, run_starts, run_steps, height, width, offsets):
    """Plane id of every pixel (-1 = atomic or no return) after the first run_steps[r] actions of each
    run r of the log (actions run_starts[r]:run_starts[r + 1]: one greedy's log, or the logs of strips
    whose pixels are disjoint, which the runs' cuts replay as the joint log's cut does)."""
    n_pixels = height * width
    parent = np.arange(n_pixels)
    owner = np.full(n_pixels, -1, np.int64)
    for r in range(len(run_steps)):
        for s in range(run_starts[r], run_starts[r] + run_steps[r]):
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
    seed_configs = SEED_SHAPES[options.seed_shapes]
    if seed_sse.shape[1:] != (len(seed_configs),):
        shapes = options.seed_shapes
        raise ValueError(
            f'seed table of shape {seed_sse.shape}: seed_shapes {shapes!r} needs {len(seed_configs)} columns'
        )
    pool_capacity = options.pool_capacity
    n_pixels = height * width
    blocks = np.empty(0, np.int64)
    if options.block_seeds and np.isfinite(stop_increment) and stop_increment >= 0.0:
        square_sse = np.ascontiguousarray(seed_sse[:, 0])  # config 0, the square, is every set's first column
        blocks = _block_seeds(
            endpoints, directions, ok_right, ok_down, square_sse, height, width, stop_increment, options.fit_tolerance
        )
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
            seed_configs,
            seed_best,
            seed_key,
            blocks,
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
            options.candidate_fits == 'one_step',
            options.fit_tolerance,
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
