"""The greedy's priority queues: the global two-level queue (a 4-ary heap plus far key buckets) and the per-plane
skew heaps of extension candidates, and the extension proxy that links the two."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ppe_ros.core.ppe.intrinsics import _float_bits
from ppe_ros.core.ppe.layout import (
    _FN_COUNT,
    _FN_NEXT,
    _G_EXTEND,
    _G_SEED,
    _GI_A,
    _GI_B,
    _GI_KIND,
    _GI_VA,
    _GI_VB,
    _HF_BOUND,
    _HF_VALUE,
    _HI_LEFT,
    _HI_RAY,
    _HI_RIGHT,
    _HI_VER,
    _NFN,
    _NGI,
    _NQS,
    _PALIVE,
    _PE,
    _PMVER,
    _PROOT,
    _PSTAMP,
    _PVER,
    _Q_BUCKETS,
    _Q_CHUNK,
    _Q_FRACTION_BITS,
    _Q_PER_OCTAVE,
    _QCOUNT,
    _QCUR,
    _QFREE,
    _QUSED,
)


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _q_chunks(capacity):
    """Far-bucket chunks that hold capacity entries: full chunks plus one partly filled per bucket."""
    return (capacity + _Q_CHUNK - 1) // _Q_CHUNK + _Q_BUCKETS


# --------------------------------------------------------------------------------------------
# global 4-ary heap: key, then (kind, a, b); int payload columns kind a b va vb
# --------------------------------------------------------------------------------------------


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _g_less(gkey, gint, i, j):
    if gkey[i] != gkey[j]:
        return gkey[i] < gkey[j]
    if gint[i, _GI_KIND] != gint[j, _GI_KIND]:
        return gint[i, _GI_KIND] < gint[j, _GI_KIND]
    if gint[i, _GI_A] != gint[j, _GI_A]:
        return gint[i, _GI_A] < gint[j, _GI_A]
    return gint[i, _GI_B] < gint[j, _GI_B]


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _g_before(key, kind, a, b, gkey, gint, j):
    """True when the entry (key, kind, a, b) comes before heap slot j."""
    if key != gkey[j]:
        return key < gkey[j]
    if kind != gint[j, _GI_KIND]:
        return kind < gint[j, _GI_KIND]
    if a != gint[j, _GI_A]:
        return a < gint[j, _GI_A]
    return b < gint[j, _GI_B]


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _g_move(gkey, gint, dst, src):
    gkey[dst] = gkey[src]
    for c in range(_NGI):
        gint[dst, c] = gint[src, c]


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _g_entry(gkey, gint, i):
    """Heap slot i as (key, kind, a, b, va, vb)."""
    return gkey[i], gint[i, _GI_KIND], gint[i, _GI_A], gint[i, _GI_B], gint[i, _GI_VA], gint[i, _GI_VB]


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _g_set(gkey, gint, i, key, kind, a, b, va, vb):
    """Write the entry (key, kind, a, b, va, vb) into slot i."""
    gkey[i] = key
    gint[i, _GI_KIND] = kind
    gint[i, _GI_A] = a
    gint[i, _GI_B] = b
    gint[i, _GI_VA] = va
    gint[i, _GI_VB] = vb


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

    Chunk c holds the entries c * _Q_CHUNK + [0, fnext[c, _FN_COUNT]) of fkey and fint; fnext[c, _FN_NEXT] links a
    bucket's chunks (its head chunk first); fnext[:, _FN_FREE] is the stack of free chunk ids.
    """
    qstate = np.zeros(_NQS, np.int64)
    qstate[_QCUR] = -1
    chunks = _q_chunks(capacity)
    return (
        np.empty(capacity),
        np.empty((capacity, _NGI), np.int32),
        np.empty(chunks * _Q_CHUNK),
        np.empty((chunks * _Q_CHUNK, _NGI), np.int32),
        np.empty((chunks, _NFN), np.int32),
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
    if chunk < 0 or fnext[chunk, _FN_COUNT] == _Q_CHUNK:
        if qstate[_QFREE] > 0:
            qstate[_QFREE] -= 1
            new = fnext[qstate[_QFREE], 1]
        else:
            new = qstate[_QUSED]
            qstate[_QUSED] += 1
        fnext[new, _FN_NEXT] = chunk
        fnext[new, _FN_COUNT] = 0
        bhead[bucket] = new
        chunk = new
    slot = chunk * _Q_CHUNK + fnext[chunk, _FN_COUNT]
    fnext[chunk, _FN_COUNT] += 1
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
            nxt = fnext[chunk, _FN_NEXT]
            for node in range(chunk * _Q_CHUNK, chunk * _Q_CHUNK + fnext[chunk, _FN_COUNT]):
                kind = fint[node, _GI_KIND]
                a = fint[node, _GI_A]
                b = fint[node, _GI_B]
                keep = True
                if kind == _G_EXTEND:
                    keep = pi[a, _PALIVE] != 0 and fint[node, _GI_VA] == pi[a, _PSTAMP]
                elif kind != _G_SEED:
                    keep = (
                        pi[a, _PALIVE] != 0
                        and pi[b, _PALIVE] != 0
                        and fint[node, _GI_VA] == pi[a, _PMVER]
                        and fint[node, _GI_VB] == pi[b, _PMVER]
                    )
                if keep:
                    gkey[size] = fkey[node]
                    for c in range(_NGI):
                        gint[size, c] = fint[node, c]
                    size += 1
            qstate[_QCOUNT] -= fnext[chunk, _FN_COUNT]
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
    if hf[x, _HF_BOUND] != hf[y, _HF_BOUND]:
        return hf[x, _HF_BOUND] < hf[y, _HF_BOUND]
    return hi[x, _HI_RAY] < hi[y, _HI_RAY]


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
        r = hi[x, _HI_RIGHT]
        hi[x, _HI_RIGHT] = hi[x, _HI_LEFT]
        if r < 0:
            hi[x, _HI_LEFT] = y
            break
        if _h_less(hf, hi, y, r):
            r, y = y, r
        hi[x, _HI_LEFT] = r
        x = r
    return root


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _h_drop_taken(hf, hi, owner, root, hfree):
    """Remove the tops of a plane's candidate heap whose ray another (or the same) plane has taken.

    Returns (root, hfree).
    """
    while root >= 0 and owner[hi[root, _HI_RAY]] >= 0:
        newroot = _h_meld(hf, hi, hi[root, _HI_LEFT], hi[root, _HI_RIGHT])
        hi[root, _HI_LEFT] = hfree
        hfree = root
        root = newroot
    return root, hfree


# --------------------------------------------------------------------------------------------
# helpers on plane state


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
    if hi[root, _HI_VER] == pi[p, _PVER]:
        pkey = hf[root, _HF_VALUE] - pf[p, _PE]
    else:
        pkey = hf[root, _HF_BOUND] - pf[p, _PE]
    pi[p, _PSTAMP] += 1
    if pkey > cutoff:
        return gsize, np.inf
    return _q_push(
        gkey, gint, gsize, fkey, fint, fnext, bhead, qstate, pkey, _G_EXTEND, p, hi[root, _HI_RAY], pi[p, _PSTAMP], root
    ), pkey
