"""Work memory that a thread reuses from call to call (fresh memory costs a page fault per 4 KiB page)."""

from __future__ import annotations

import numpy as np

from ppe_ros.core.work_memory import WorkMemory

#: The greedy's work memory (seeds, tiles, the kernel's pools).
_work_memory = WorkMemory()
_reusable = _work_memory.array


def release_work_memory() -> None:
    """Free the work memory the extractor keeps between calls in the calling thread.

    The extractor reuses its work buffers (about 1.2 KB per ray of the largest scan so far, of which
    the touched part stays resident) so that repeated calls, like a node's frames, do not pay for
    fresh memory; call this after a large one-off extraction to give the memory back. The
    whole-surface pass's work memory (ppe_ros.core.consolidation) is freed too.
    """
    from ppe_ros.core.consolidation import release_work_memory as release_surface_memory

    _work_memory.release()
    release_surface_memory()


def _work_buffers(n_f: int, n_i: int, n_i32: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return (
        _reusable('float64', n_f, np.float64),
        _reusable('int64', n_i, np.int64),
        _reusable('int32', n_i32, np.int32),
    )
