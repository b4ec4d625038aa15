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

This module is the stable import path of the public API; the implementation is the package
:mod:`ppe_ros.core.ppe` (one module per concern, see its docstring).
"""

from ppe_ros.core.ppe import (
    DEFAULT_OPTIONS,
    PROFILE_DEFAULT,
    GreedyOptions,
    PlaneHierarchy,
    extract_plane_hierarchy,
    extract_planes,
    release_work_memory,
)
from ppe_ros.core.ppe.layout import (
    ACTION_DTYPE,
    BOUND_SLACK,
    DEFAULT_EXACT_PLANE_SIZE,
    KIND_CREATE,
    KIND_EXTEND,
    KIND_MERGE,
    MAX_RAYS,
    MERGE_LOOP_GROWTH,
    MODEL_CUTOFF_FACTOR,
    MODEL_MERGE_KEY_MARGIN,
    REFINED_MERGE_GROWTH,
    RELINEARISATION_DRIFT,
    STAT_NAMES,
    TETROMINO_OFFSETS,
    UNION_MODEL_AGREEMENT,
)
from ppe_ros.core.ppe.tiles import AUTO_TILE_COLUMNS, TILE_BORDER_SLACK

__all__ = [
    'ACTION_DTYPE',
    'AUTO_TILE_COLUMNS',
    'BOUND_SLACK',
    'DEFAULT_EXACT_PLANE_SIZE',
    'DEFAULT_OPTIONS',
    'KIND_CREATE',
    'KIND_EXTEND',
    'KIND_MERGE',
    'MAX_RAYS',
    'MERGE_LOOP_GROWTH',
    'MODEL_CUTOFF_FACTOR',
    'MODEL_MERGE_KEY_MARGIN',
    'PROFILE_DEFAULT',
    'REFINED_MERGE_GROWTH',
    'RELINEARISATION_DRIFT',
    'STAT_NAMES',
    'TETROMINO_OFFSETS',
    'TILE_BORDER_SLACK',
    'UNION_MODEL_AGREEMENT',
    'GreedyOptions',
    'PlaneHierarchy',
    'extract_plane_hierarchy',
    'extract_planes',
    'release_work_memory',
]
