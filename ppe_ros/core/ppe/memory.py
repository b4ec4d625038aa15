"""Work memory that a thread reuses from call to call (fresh memory costs a page fault per 4 KiB page)."""

from __future__ import annotations

import threading

import numpy as np

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
    fresh memory; call this after a large one-off extraction to give the memory back. The
    whole-surface pass's work memory (ppe_ros.core.consolidation) is freed too.
    """
    from ppe_ros.core.consolidation import release_work_memory as release_surface_memory

    _work_memory.buffers = {}
    release_surface_memory()


def _work_buffers(n_f: int, n_i: int, n_i32: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return (
        _reusable('float64', n_f, np.float64),
        _reusable('int64', n_i, np.int64),
        _reusable('int32', n_i32, np.int32),
    )
