"""Contiguous runs of groups (planes) with about equal work, one per thread of a numba parallel loop.

numba's ``prange`` gives each thread an equal share of the iterations. The per-plane kernels of the
fits and of the whole-surface pass loop over planes numbered by decreasing size, so equal shares of
planes would give the first thread most of the points. They loop instead over ``group_chunks``:
one run of planes per thread, each holding about the same number of points. Each plane is still
computed by one thread in its own order, so the results do not depend on the thread count.
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
