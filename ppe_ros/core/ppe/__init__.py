"""PPE, the greedy plane extraction, as modules by concern (the public API is in :mod:`.api`).

* :mod:`.layout`: constants, the field layout of the greedy's plane rows, queue entries and pools;
* :mod:`.intrinsics`: the prefetch hint and a float's bits (LLVM intrinsics);
* :mod:`.seeds`: admissible grid edges and the tetromino seeds (their fits, bounds and order);
* :mod:`.queue`: the two-level global queue (4-ary heap and far key buckets) and the candidate heaps;
* :mod:`.state`: plane state, exact and model fits, merges' models and refinements;
* :mod:`.adjacency`: each plane's segment of neighbour nodes and the merges deferred on them;
* :mod:`.greedy`: the greedy's phases (next action, execute, bookkeeping, merge loop) and its driver;
* :mod:`.tiles`: the greedy of vertical strips run independently (and in parallel);
* :mod:`.memory`: the work memory reused from call to call;
* :mod:`.options`: :class:`GreedyOptions`, the greedy's tuning;
* :mod:`.api`: ``extract_plane_hierarchy``, ``extract_planes``, ``PlaneHierarchy``.

The cache guard runs first: numba's cache does not notice a change in another module of a kernel's callees.
"""

from ppe_ros.core.ppe.cache_guard import guard_kernel_cache

guard_kernel_cache()

from ppe_ros.core.ppe.api import (  # noqa: E402 (after the cache guard)
    PROFILE_DEFAULT,
    PlaneHierarchy,
    extract_plane_hierarchy,
    extract_planes,
)
from ppe_ros.core.ppe.memory import release_work_memory  # noqa: E402
from ppe_ros.core.ppe.options import DEFAULT_OPTIONS, GreedyOptions  # noqa: E402

__all__ = [
    'DEFAULT_OPTIONS',
    'PROFILE_DEFAULT',
    'GreedyOptions',
    'PlaneHierarchy',
    'extract_plane_hierarchy',
    'extract_planes',
    'release_work_memory',
]
