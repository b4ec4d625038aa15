"""The greedy's tuning options (:class:`GreedyOptions`): speed/accuracy trade-offs of the evaluation, not the
extraction's parameters (those are extract_plane_hierarchy's own arguments)."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from ppe_ros.core.ppe.layout import (
    _FIT_TOLERANCE,
    DEFAULT_EXACT_PLANE_SIZE,
    MERGE_LOOP_GROWTH,
    REFINED_MERGE_GROWTH,
    RELINEARISATION_DRIFT,
)
from ppe_ros.core.sensor import check_candidate_fits, check_fit_tolerance, check_seed_shapes


@dataclass(frozen=True)
class GreedyOptions:
    """How the greedy evaluates its actions; the defaults are what extract_planes runs.

    Attributes:
        exact_plane_size: planes up to this many rays (>= 4) are evaluated with exact fits (tests use a
            large value to make every evaluation exact).
        exact_merge_size: merges whose union has up to this many rays are fitted exactly as soon as
            they become candidates; larger ones enter the queue with their model increment and are
            refined when they reach the front.
        relinearisation_drift: relative change of a large plane's predicted ranges since its last
            linearisation that triggers a re-linearisation (one Gauss-Newton step on all its rays).
        refined_merge_growth: a merge of two planes larger than exact_plane_size in total, refined
            once, is re-valued from the kept refinement (the smaller plane's residuals as a quadratic
            model at the union's w) while the smaller plane is unchanged and the larger has grown by
            at most this fraction; 0 refines it again every time it reaches the front.
        merge_loop_growth: after an action on a plane larger than exact_plane_size that has grown by
            at most this fraction since its last full merge loop, only its new neighbours' merges are
            valued; 0 values every merge of the plane after every action.
        defer_merges: keep merges whose key exceeds the changed plane's proxy key off the queue until
            they are due (False queues every merge at once: the same action log, more heap work;
            for tests).
        candidate_fits: how an extension candidate of a plane of up to exact_plane_size rays is valued:
            'exact' its exact fit (the paper's increment); 'one_step' one Gauss-Newton step from the
            plane's fit with the candidate's ray added (the rank-one model of a large plane) and the
            exact SSE at that step: an upper bound of the exact increment, within 1.4e-4 of it
            (relative) on an OS-1-128 sweep, at under a third of the cost. The extension that is
            executed is then fitted exactly, so plane states stay exact; the action order may differ
            from the exact greedy's where increments are that close (the lidar profile's choice).
        fit_tolerance: relative convergence tolerance of the greedy's exact fits (the tetromino seeds,
            small planes' states and exact candidates, union fits, merge refinements): a fit stops when the
            Gauss-Newton predicted decrease is at most this fraction of its SSE (the default, 1e-13, is the
            exact greedy's; the lidar profile uses 1e-6, far below its increments' resolution, the depth
            camera profile 1e-9).
        seed_shapes: the tetrominoes that seed a plane (create actions): 'all' the paper's 17 (every
            tetromino but the straight I), 'square' the 2 x 2 square alone (a 17th of the seed fits and of
            the seeds the greedy re-queues; the sensor profiles' choice for spinning lidars).
        block_seeds: before the greedy, every 4 x 4 block of the grid (aligned to its first row and column)
            whose 16 rays are joined by admissible edges and whose exact fit has an SSE of at most the
            run's stop (max_error_increment) becomes a plane at once, blocks of least SSE first, each as
            the create of its top-left 2 x 2 square and the extensions by its other 12 rays in row order
            (so the action log and its replay stay those of the paper's actions, with the exact
            increments, each at most the stop); the greedy goes on from there. Faster where much of
            the scan is in such blocks (their one-ray-at-a-time growth is most of the greedy's work),
            but the blocks' fixed grid makes the result depend more on small changes of the grid
            (docs/algorithm.md); off in the built-in profiles. Needs a finite max_error_increment
            stop (a run without one has no blocks).
        pool_capacity: initial rows (>= 1) of each of the greedy's work pools (None: from the scan size).
            A pool that runs out is enlarged and the greedy run again, so the result does not
            depend on it (tests use small values to exercise that path).

    Construction checks every field (ValueError naming it) and stores it as int, float or bool.
    """

    exact_plane_size: int = DEFAULT_EXACT_PLANE_SIZE
    exact_merge_size: int = 0
    relinearisation_drift: float = RELINEARISATION_DRIFT
    refined_merge_growth: float = REFINED_MERGE_GROWTH
    merge_loop_growth: float = MERGE_LOOP_GROWTH
    defer_merges: bool = True
    candidate_fits: str = 'exact'
    fit_tolerance: float = _FIT_TOLERANCE
    seed_shapes: str = 'all'
    block_seeds: bool = False
    pool_capacity: int | None = None

    def __post_init__(self) -> None:
        for name in ('exact_plane_size', 'exact_merge_size'):
            value = getattr(self, name)
            if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Real) or value != int(value):
                raise ValueError(f'{name} must be a whole number of rays; got {value!r}')
        if int(self.exact_plane_size) < 4:
            raise ValueError(f'exact_plane_size must be >= 4; got {self.exact_plane_size!r}')
        if self.pool_capacity is not None and (
            isinstance(self.pool_capacity, bool | np.bool_)
            or not isinstance(self.pool_capacity, numbers.Real)
            or int(self.pool_capacity) != self.pool_capacity
        ):
            raise ValueError(f'pool_capacity must be a whole number >= 1 or None; got {self.pool_capacity!r}')
        if self.pool_capacity is not None and int(self.pool_capacity) < 1:
            raise ValueError(f'pool_capacity must be >= 1 (None: from the scan size); got {self.pool_capacity!r}')
        check_seed_shapes(self.seed_shapes)
        check_candidate_fits(self.candidate_fits)
        check_fit_tolerance(self.fit_tolerance)
        if not float(self.relinearisation_drift) >= 0.0:
            drift = self.relinearisation_drift
            raise ValueError(f'relinearisation_drift must be >= 0 (inf: only on doubling); got {drift!r}')
        for name in ('refined_merge_growth', 'merge_loop_growth'):
            value = float(getattr(self, name))
            if not (0.0 <= value and math.isfinite(value)):
                raise ValueError(f'{name} must be a finite fraction >= 0 (0: off); got {getattr(self, name)!r}')
        normalised = {
            'exact_plane_size': int(self.exact_plane_size),
            'exact_merge_size': int(self.exact_merge_size),
            'relinearisation_drift': float(self.relinearisation_drift),
            'refined_merge_growth': float(self.refined_merge_growth),
            'merge_loop_growth': float(self.merge_loop_growth),
            'defer_merges': bool(self.defer_merges),
            'candidate_fits': str(self.candidate_fits),
            'fit_tolerance': float(self.fit_tolerance),
            'seed_shapes': str(self.seed_shapes),
            'block_seeds': bool(self.block_seeds),
            'pool_capacity': None if self.pool_capacity is None else int(self.pool_capacity),
        }
        for name, value in normalised.items():
            object.__setattr__(self, name, value)


#: The defaults (what extract_plane_hierarchy runs with options=None).
DEFAULT_OPTIONS = GreedyOptions()
