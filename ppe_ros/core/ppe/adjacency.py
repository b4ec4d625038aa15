"""Each plane's neighbours: a contiguous segment of adjacency nodes per plane in one pool, and the merges
deferred on those nodes."""

from __future__ import annotations

import numba as nb
import numpy as np

# --------------------------------------------------------------------------------------------
# adjacency segments: each plane's neighbour nodes are contiguous rows of one pool, so that the
# loops over a plane's neighbours read memory in order (a linked list of nodes scattered over the
# pool made them wait on a cache miss per neighbour). Segments have power-of-two sizes; freed ones
# are kept on a free list per size.
# --------------------------------------------------------------------------------------------
from ppe_ros.core.ppe.layout import (
    _ADJ_MIN_ROWS,
    _AN_FIELDS,
    _AN_FREE_LINK,
    _AN_KEY,
    _AN_KIND,
    _AN_PLANE,
    _AN_VA,
    _AN_VB,
    _PADJ,
    _PADJC,
    _PADJN,
    _PDEFER,
)
from ppe_ros.core.ppe.queue import _q_push


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
    anode[start, _AN_FREE_LINK] = afree[c]
    afree[c] = start


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _adj_move(anode, afree, pi, x, rows, aused):
    """Move plane x's adjacency nodes to a segment of at least rows rows; returns aused (-1: the pool is full)."""
    c, size = _adj_class(rows)
    start = afree[c]
    if start >= 0:
        afree[c] = anode[start, _AN_FREE_LINK]
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
