"""Contiguous runs of groups (planes) with about equal work, one per thread of a numba parallel loop.

numba's ``prange`` gives each thread an equal share of the iterations. The per-plane kernels of the
fits and of the whole-surface pass loop over planes numbered by decreasing size, so equal shares of
planes would give the first thread most of the points. They loop instead over ``group_chunks``:
one run of planes per thread, each holding about the same number of points. Each plane is still
computed by one thread in its own order, so the results do not depend on the thread count. A thread
finds its planes' pixels in ``plane_members`` (each plane's pixels in pixel order, one counting sort)
instead of scanning every pixel for them.
"""

from __future__ import annotations

import numba as nb
import numpy as np


def group_chunks(counts: np.ndarray, n_chunks: int | None = None) -> np.ndarray:
    """``(C + 1,)`` boundaries of C runs of consecutive groups with about equal total ``counts``.

    Args:
        counts: ``(J,)`` work of each group (its points), >= 0.
        n_chunks: runs (default: numba's thread count), at least 1.
    Run c is groups ``bounds[c]:bounds[c + 1]``; a run ends at the first group that brings its
    running total to c / C of the whole or more, so a group larger than a share is a run of its
    own and later runs share the rest.
    """
    chunks = nb.get_num_threads() if n_chunks is None else int(n_chunks)
    if chunks < 1:
        raise ValueError(f'n_chunks must be at least 1; got {n_chunks}')
    return _group_chunks_kernel(np.ascontiguousarray(counts, dtype=np.float64), chunks)


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _group_chunks_kernel(counts, n_chunks):
    total = 0.0
    for count in counts:
        total += count
    bounds = np.empty(n_chunks + 1, np.int64)
    bounds[0] = 0
    g = 0
    running = 0.0
    for c in range(1, n_chunks):
        while g < len(counts) and running < total * c / n_chunks:
            running += counts[g]
            g += 1
        bounds[c] = g
    bounds[n_chunks] = len(counts)
    return bounds


def plane_members(labels: np.ndarray, n_planes: int) -> tuple[np.ndarray, np.ndarray]:
    """The pixels of each plane, grouped by plane, in pixel order within a plane (a counting sort).

    Args:
        labels: ``(N,)`` plane labels 1..n_planes of the pixels (0: no plane).
        n_planes: number of planes J.
    Returns ``members`` (the labelled pixels' indices) and ``starts`` ``(J + 1,)``: plane j's pixels
    (label j + 1) are ``members[starts[j]:starts[j + 1]]``. The per-plane kernels loop over them, so that
    a thread visits only its own planes' pixels, in the order a loop over all pixels would.
    """
    labels = np.ascontiguousarray(labels)
    if labels.ndim != 1:
        raise ValueError(f'labels must be one-dimensional; got shape {labels.shape}')
    if len(labels) and (labels.min() < 0 or labels.max() > n_planes):
        raise ValueError(f'labels must be in 0..{n_planes}')
    return _plane_members_kernel(labels, int(n_planes))


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _plane_members_kernel(labels, n_planes):
    starts = np.zeros(n_planes + 2, np.int64)  # starts[label + 1] counts the label's pixels
    for label in labels:
        starts[label + 1] += 1
    for j in range(n_planes + 1):
        starts[j + 1] += starts[j]
    fill = starts[1:-1].copy()  # label 0 (no plane) is left out: plane j fills from starts[j + 1]
    members = np.empty(starts[-1] - starts[1], np.int64)
    first = starts[1]
    for k in range(len(labels)):
        label = labels[k]
        if label > 0:
            members[fill[label - 1] - first] = k
            fill[label - 1] += 1
    return members, starts[1:] - first
