"""Public API of PPE: extract_plane_hierarchy (the action log), PlaneHierarchy (its cuts) and extract_planes."""

from __future__ import annotations

import itertools
import numbers
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from ppe_ros.core.fitting import fit_pixel_groups
from ppe_ros.core.planes import PlaneSet
from ppe_ros.core.ppe.greedy import _greedy, _replay, _run_cutoff
from ppe_ros.core.ppe.layout import (
    ACTION_DTYPE,
    KIND_CREATE,
    MAX_RAYS,
    STAT_NAMES,
    TETROMINO_OFFSETS,
)
from ppe_ros.core.ppe.options import DEFAULT_OPTIONS, GreedyOptions
from ppe_ros.core.ppe.seeds import _edge_masks, _seed_stage
from ppe_ros.core.ppe.tiles import _placed_borders, _tile_bounds, _tiled_greedy, joint_order
from ppe_ros.core.scan import RayScan, make_ray_scan
from ppe_ros.core.sensor import (
    PROFILES,
    NoiseModel,
    SensorProfile,
    check_optional_length,
    is_whole_number,
    sensor_profile,
)
from ppe_ros.core.surfaces import whole_surfaces


def _as_threshold_list(value, name: str, cast) -> list | None:
    if value is None:
        return None
    values = list(value) if isinstance(value, Sequence | np.ndarray) else [value]
    if not values:
        raise ValueError(f'{name} must not be an empty list')
    out = []
    for v in values:
        try:
            if cast is int and (isinstance(v, bool | np.bool_) or not float(v).is_integer()):
                raise ValueError('not a whole number')
            x = cast(v)
        except (TypeError, ValueError) as exc:
            raise ValueError(f'{name} must be a number or a list of numbers; got {v!r}') from exc
        if cast is float and (not np.isfinite(x) or x < 0):
            raise ValueError(f'{name} must be finite and >= 0 (m^2); got {v!r}')
        if cast is int and x < 1:
            raise ValueError(f'{name} must be >= 1; got {v!r}')
        out.append(x)
    return out


@dataclass(frozen=True)
class PlaneHierarchy:
    """The greedy action log of one PPE run; cut it at any threshold without re-running.

    Attributes:
        scan: the ray model the run used.
        log: the greedy's actions as arrays (kinds, a, b, increments): one greedy's log, or the strips'
            logs one after another (``tiles``), each in its own order.
        run_starts: ``(R + 1,)`` start of each run (one greedy or one strip) in ``log``.
        initial_plane_count: J before the first action (the number of valid rays).
        complete: True when the run went on until no action was left.
        seconds: wall time of the run (seeds + greedy), excluding JIT compilation of a first call.
        actions (property): structured array (kind, a, b, increment) with kind 0 create (a = anchor
            pixel id, b = tetromino config 0..16), 1 extend (a = plane id, b = pixel id), 2 merge
            (a = surviving id = min, b = removed id); increments in m^2. Pixel id = row * W + col.
            The strips' logs interleaved by each strip's running maximum increment (built when first
            read: a cut at e does not need it).
        plane_counts (property): J after each of ``actions``.
    """

    scan: RayScan
    log: tuple
    run_starts: np.ndarray
    initial_plane_count: int
    complete: bool
    seconds: float = 0.0
    stats: dict | None = None
    sigmas: np.ndarray | None = None

    @cached_property
    def actions(self) -> np.ndarray:
        kinds, a_ids, b_ids, increments = self.log
        if len(self.run_starts) > 2:
            order = joint_order(increments, self.run_starts)
            kinds, a_ids, b_ids, increments = kinds[order], a_ids[order], b_ids[order], increments[order]
        return _action_log(kinds, a_ids, b_ids, increments)

    @cached_property
    def plane_counts(self) -> np.ndarray:
        return self.initial_plane_count - np.cumsum(np.where(self.actions['kind'] == KIND_CREATE, 3, 1))

    def _run_steps_for_error(self, max_error_increment: float) -> np.ndarray:
        """Actions of each run before its first one whose increment exceeds e."""
        increments = self.log[3]
        steps = np.diff(self.run_starts)
        for r, (first, stop) in enumerate(itertools.pairwise(self.run_starts)):
            over = np.flatnonzero(increments[first:stop] > max_error_increment)
            if len(over):
                steps[r] = over[0]
        return steps

    def steps_for_error(self, max_error_increment: float) -> int:
        """Number of actions before the first one whose increment exceeds e (m^2): the runs' own counts
        added up (a strip's actions below its running maximum's first excess come first in ``actions``)."""
        return int(self._run_steps_for_error(max_error_increment).sum())

    def plane_ids_for_error(self, max_error_increment: float) -> np.ndarray:
        """``plane_ids(steps_for_error(e))`` from each run's own cut, without building ``actions``."""
        kinds, a_ids, b_ids, _ = self.log
        return _replay(
            kinds,
            a_ids,
            b_ids,
            np.asarray(self.run_starts, np.int64),
            self._run_steps_for_error(max_error_increment).astype(np.int64),
            self.scan.height,
            self.scan.width,
            TETROMINO_OFFSETS,
        )

    def steps_for_count(self, max_planes: int) -> int:
        """Number of actions until J <= n first holds."""
        if self.initial_plane_count <= max_planes:
            return 0
        hit = np.flatnonzero(self.plane_counts <= max_planes)
        return int(hit[0]) + 1 if len(hit) else len(self.actions)

    def plane_ids(self, steps: int) -> np.ndarray:
        """``(H*W,)`` plane id of each pixel after ``steps`` actions (-1: atomic/no return)."""
        a = self.actions
        return _replay(
            np.ascontiguousarray(a['kind']),
            np.ascontiguousarray(a['a']),
            np.ascontiguousarray(a['b']),
            np.array([0, len(a)], np.int64),
            np.array([int(steps)], np.int64),
            self.scan.height,
            self.scan.width,
            TETROMINO_OFFSETS,
        )

    def cut(
        self, *, max_error_increment: float | None = None, max_planes: int | None = None, min_plane_points: int = 4
    ) -> PlaneSet:
        """The planes of the snapshot for one threshold (exactly one of e or n)."""
        if (max_error_increment is None) == (max_planes is None):
            raise ValueError('cut needs exactly one of max_error_increment or max_planes')
        if max_error_increment is not None:
            steps = self.steps_for_error(max_error_increment)
            ids = self.plane_ids_for_error(max_error_increment)
        else:
            steps = self.steps_for_count(max_planes)
            ids = self.plane_ids(steps)
        planes, _ = fit_pixel_groups(
            self.scan,
            ids,
            min_plane_points=min_plane_points,
            residuals=False,
            sigmas=self.sigmas,
            max_error_increment=max_error_increment,
            max_planes=max_planes,
            actions=steps,
        )
        return planes


def _action_log(kinds: np.ndarray, a_ids: np.ndarray, b_ids: np.ndarray, increments: np.ndarray) -> np.ndarray:
    """The greedy's actions as an ACTION_DTYPE array."""
    actions = np.empty(len(kinds), ACTION_DTYPE)
    actions['kind'] = kinds
    actions['a'] = a_ids
    actions['b'] = b_ids
    actions['increment'] = increments
    return actions


def _stops(max_error_increment: float | None, max_planes: int | None) -> tuple[float, int]:
    """The greedy's stop increment and plane count (inf and -1: run the whole hierarchy)."""
    if max_error_increment is None and max_planes is None:
        return np.inf, -1
    stop_increment = -np.inf if max_error_increment is None else float(max_error_increment)
    stop_count = np.iinfo(np.int64).max if max_planes is None else min(int(max_planes), np.iinfo(np.int64).max)
    return stop_increment, stop_count


def _check_hierarchy_options(scan: RayScan, lmax: float, options) -> None:
    """extract_plane_hierarchy's checks of its scan size, lmax and options (ValueError or TypeError naming them)."""
    if not (lmax > 0):
        raise ValueError(f'max_neighbor_distance must be > 0 m (inf = no limit); got {lmax!r}')
    if scan.size >= MAX_RAYS:
        raise ValueError(f'scans of fewer than {MAX_RAYS} rays (2^26) are supported; got {scan.height} x {scan.width}')
    if options is not None and not isinstance(options, GreedyOptions):
        raise TypeError(f'options must be a GreedyOptions or None; got {type(options).__name__}')


def extract_plane_hierarchy(
    points: np.ndarray,
    *,
    origins: np.ndarray | None = None,
    max_neighbor_distance: float = np.inf,
    max_error_increment: float | None = None,
    max_planes: int | None = None,
    options: GreedyOptions | None = None,
    noise: NoiseModel | None = None,
    tiles: int | str = 1,
    threads: int | None = None,
) -> PlaneHierarchy:
    """Run PPE and return its action log.

    Args:
        points: organized ``(H, W, 3)`` endpoints in metres, NaN = no return; H * W < MAX_RAYS (2^26).
        origins: ray starts: None (coordinate origin), ``(3,)`` or ``(H, W, 3)``, same frame.
        max_neighbor_distance: the largest 3-D distance (m) between 4-neighbouring endpoints that
            may be joined (the paper's d, the reference's lmax); inf = no limit.
        max_error_increment: stop once the next increment exceeds this (m^2) and no plane-count
            target remains; None with max_planes None runs until no action is left.
        max_planes: continue at least until J <= max_planes.
        options: the greedy's tuning (:class:`GreedyOptions`; None: its defaults, what extract_planes
            runs): exact-fit sizes, re-linearisation, merge re-valuation, deferred merges, pool sizes.
        noise: the rays' range noise (:class:`~ppe_ros.core.sensor.NoiseModel`): the greedy minimises
            the squared residuals divided by sigma_k^2, and increments (and max_error_increment) are
            dimensionless; None: the paper's model (increments in m^2).
        tiles: 1 (the exact greedy of the whole grid), a count, or 'auto' (one per AUTO_TILE_COLUMNS
            columns of a sweep, twice that of an image, see _tile_bounds): the grid is cut into that
            many vertical strips (azimuth sectors of a sweep) that are extracted independently, no
            plane crossing a border (join the pieces afterwards, as extract_planes's consolidation
            does). Each inner border moves by up to TILE_BORDER_SLACK of a strip's width to the
            column that the fewest admissible grid edges cross. Needs max_planes
            None. The log's cut at e is the union of the strips' cuts at e.
        threads: strips extracted at once, one thread each (None: numba's thread count of the calling
            thread); the result does not depend on it.
    """
    import time

    scan = make_ray_scan(points, origins)
    sigmas = None
    if noise is not None:
        scan, sigmas = _noise_scaled(scan, noise)
    if isinstance(max_neighbor_distance, bool) or not isinstance(max_neighbor_distance, numbers.Real):
        raise ValueError(f'max_neighbor_distance must be > 0 m (inf = no limit); got {max_neighbor_distance!r}')
    lmax = float(max_neighbor_distance)
    _check_hierarchy_options(scan, lmax, options)
    options = DEFAULT_OPTIONS if options is None else options
    stop_increment, stop_count = _stops(max_error_increment, max_planes)
    tile_columns = _tile_bounds(scan.width, tiles, scan.height)
    if threads is not None and not (is_whole_number(threads) and threads >= 1):
        raise ValueError(f"threads must be a count >= 1 or None (numba's thread count); got {threads!r}")
    if tiles != 1 and max_planes is not None:
        raise ValueError('tiles > 1 needs a max_error_increment stop without max_planes (a plane count is global)')
    start = time.perf_counter()
    ok_right, ok_down = _edge_masks(scan, lmax)
    tile_columns = _placed_borders(tile_columns, ok_right, scan.height, scan.width)
    for column in tile_columns[1:-1]:  # no seed or join crosses a tile border
        ok_right[column - 1 :: scan.width] = False
    seed_sse, seed_best, seed_key = _seed_stage(
        scan,
        ok_right,
        ok_down,
        _run_cutoff(stop_increment, stop_count, scan.size),
        options.seed_shapes,
        options.fit_tolerance,
    )
    inputs = (scan.endpoints, scan.directions, scan.valid, ok_right, ok_down, seed_sse, seed_best, seed_key)
    if len(tile_columns) == 2:
        *log, stats = _greedy(inputs, scan.height, scan.width, options, stop_increment, stop_count)
        run_starts = np.array([0, len(log[0])], np.int64)
    else:
        log, run_starts, stats = _tiled_greedy(
            inputs, scan.height, scan.width, tile_columns, options, stop_increment, stop_count, threads
        )
    seconds = time.perf_counter() - start
    complete = stop_increment == np.inf and stop_count < 0
    return PlaneHierarchy(
        scan=scan,
        log=tuple(log),
        run_starts=run_starts,
        initial_plane_count=int(scan.valid.sum()),
        complete=complete,
        seconds=seconds,
        stats=dict(zip(STAT_NAMES, (int(x) for x in stats), strict=True)),
        sigmas=sigmas,
    )


def _noise_scaled(scan: RayScan, noise: NoiseModel) -> tuple[RayScan, np.ndarray]:
    """The scan with each ray's direction scaled by its sigma_k, and the sigmas (m; NaN: invalid).

    The residual (w . p - 1) / (w . v) of a plane w then is (r_k - rhat_k) / sigma_k exactly.
    """
    directions = np.empty_like(scan.directions)
    sigmas = noise.ray_sigmas(scan.ranges, scan.directions, scan.valid, scaled_directions=directions)
    return replace(scan, directions=directions), sigmas


class _ProfileDefault:
    """The default of an extract_planes argument: today's value without a sensor, else the profile's."""

    def __repr__(self) -> str:
        return 'the profile default'


PROFILE_DEFAULT = _ProfileDefault()
#: extract_planes's defaults without a sensor profile (sensor=None).
_NO_PROFILE_DEFAULTS = PROFILES['none']


def _final_planes(hierarchy: PlaneHierarchy, min_plane_points: int) -> PlaneSet:
    """The planes after every action of the hierarchy (no threshold given)."""
    steps = len(hierarchy.log[0])
    planes, _ = fit_pixel_groups(
        hierarchy.scan,
        hierarchy.plane_ids_for_error(np.inf),
        sigmas=hierarchy.sigmas,
        min_plane_points=min_plane_points,
        residuals=False,
        actions=steps,
    )
    return planes


def _profile_setting(profile: SensorProfile | None, name: str, value):
    """An extract_planes argument: as given, else the profile's (sensor=None: the 'none' profile's)."""
    if value is not PROFILE_DEFAULT:
        return value
    return getattr(_NO_PROFILE_DEFAULTS if profile is None else profile, name, None)


def _extract_transposed_sweep(points, origins, **options) -> PlaneSet | list[PlaneSet]:
    """extract_planes of a transposed sweep (one column per beam, at least 4 times as tall as wide):
    its strips are azimuth sectors across the rows, so it is extracted as the sweep it is and its
    labels are transposed back (the 4-neighbourhood and the tetrominoes are symmetric: the same planes)."""

    def transposed(array):
        return np.ascontiguousarray(np.swapaxes(np.asarray(array), 0, 1))

    result = extract_planes(
        transposed(points), origins=origins if np.ndim(origins) != 3 else transposed(origins), **options
    )
    if isinstance(result, list):
        return [replace(cut, labels=np.ascontiguousarray(cut.labels.T)) for cut in result]
    return replace(result, labels=np.ascontiguousarray(result.labels.T))


def _profile_greedy_options(profile: SensorProfile) -> GreedyOptions:
    """The GreedyOptions of a sensor profile: its seed shapes, block seeds and candidate fits, the rest the
    defaults."""
    fits = {} if profile.fit_tolerance is None else {'fit_tolerance': profile.fit_tolerance}
    return GreedyOptions(
        seed_shapes=profile.seed_shapes,
        candidate_fits=profile.candidate_fits,
        block_seeds=bool(profile.block_seeds),
        **fits,
    )


def _checked_settings(connected_only, min_plane_points, surface_tolerance) -> bool:
    """extract_planes's checks of these settings (a ValueError naming the setting); connected_only as a bool."""
    if not isinstance(connected_only, bool | np.bool_) and connected_only not in (0, 1):
        raise ValueError(f'connected_only must be True or False; got {connected_only!r}')
    if not (is_whole_number(min_plane_points) and min_plane_points >= 1):
        raise ValueError(f'min_plane_points must be a whole number of rays >= 1; got {min_plane_points!r}')
    check_optional_length('surface_tolerance', surface_tolerance, 'a length')
    return bool(connected_only)


def extract_planes(
    points: np.ndarray,
    *,
    origins: np.ndarray | None = None,
    sensor: str | SensorProfile | None = None,
    max_error_increment: float | Sequence[float] | None = PROFILE_DEFAULT,
    max_planes: int | Sequence[int] | None = None,
    max_neighbor_distance: float = PROFILE_DEFAULT,
    min_plane_points: int = PROFILE_DEFAULT,
    surface_tolerance: float | None = PROFILE_DEFAULT,
    connected_only: bool = PROFILE_DEFAULT,
    rings: np.ndarray | None = None,
    tiles: int | str = PROFILE_DEFAULT,
    threads: int | None = None,
) -> PlaneSet | list[PlaneSet]:
    """Extract finite planes from an organized scan with PPE.

    An unorganized ``(N, 3)`` cloud (with its ``rings``, optional) is put on a range image first and
    its labels are ``(N,)``: see :func:`ppe_ros.core.projection.extract_planes_unorganized`.

    Args:
        points: organized ``(H, W, 3)`` endpoints in metres (any frame), NaN = no return.
        origins: ray starts in the same frame: None (the frame origin), ``(3,)`` or ``(H, W, 3)``.
        sensor: None or ``'none'`` (the paper's model with the defaults e 0.01 m^2, lmax inf, 4
            points: the results of earlier versions), or a sensor profile: ``'lidar'``,
            ``'depth_camera'``, ``'paper'`` or a :class:`~ppe_ros.core.sensor.SensorProfile`. A profile sets the range
            noise model and the defaults of the arguments below; arguments given explicitly win.
        max_error_increment: the paper's e: a snapshot is the state before the first action whose
            error increment exceeds it (m^2 in the paper's model; dimensionless, in units of the
            rays' noise variance, with a noise model). One value or a list (one snapshot each).
        max_planes: the paper's J_max (atomic rays and regular planes counted), one value or a list.
        max_neighbor_distance: largest distance (m) between neighbouring endpoints that may be
            joined (the paper's d / lmax).
        min_plane_points: planes with fewer rays are reported as no plane (a profile's default: as many rays
            as cover the solid angle of its min_plane_points at its reference spacing, on a coarser grid
            fewer: :meth:`~ppe_ros.core.sensor.SensorProfile.min_plane_points_for`).
        surface_tolerance: tau (m): after the greedy, pieces of one physical surface (deviating from
            their common plane by at most tau RMS) are merged (ppe_ros.core.consolidation); None:
            no consolidation.
        connected_only: consolidate only pieces that touch in the grid (not across occluders).
        tiles: vertical strips (azimuth sectors of a sweep) whose greedies run independently and in
            parallel (see extract_plane_hierarchy); the consolidation joins the pieces a border cut.
            Default: 'auto' (128-column strips of a sweep, 256 of an image) when the pieces are consolidated
            (a surface_tolerance and a single max_error_increment, no max_planes), else 1 (the exact
            greedy: sensor=None and the 'paper' profile give the results of earlier versions).
        threads: strips extracted at once (None: numba's thread count of the calling thread). The
            result does not depend on it.

    Returns:
        A PlaneSet when both thresholds are single values (or None), else a list of PlaneSets:
        one per e (in the given order), then one per n.
    """
    options = {
        'sensor': sensor,
        'max_error_increment': max_error_increment,
        'max_planes': max_planes,
        'max_neighbor_distance': max_neighbor_distance,
        'min_plane_points': min_plane_points,
        'surface_tolerance': surface_tolerance,
        'connected_only': connected_only,
        'threads': threads,
    }
    if rings is not None or (np.ndim(points) == 2 and np.shape(points)[1] == 3):  # unorganized: project first
        from ppe_ros.core.projection import extract_planes_unorganized

        return extract_planes_unorganized(points, rings, origins=origins, tiles=tiles, **options)
    profile = None if sensor is None else sensor_profile(sensor)
    if profile == _NO_PROFILE_DEFAULTS:  # 'none': the paper's model, as sensor=None
        profile = None

    max_error_increment, max_neighbor_distance, min_plane_points, surface_tolerance, connected_only = (
        _profile_setting(profile, name, options[name])
        for name in (
            'max_error_increment',
            'max_neighbor_distance',
            'min_plane_points',
            'surface_tolerance',
            'connected_only',
        )
    )
    if options['min_plane_points'] is PROFILE_DEFAULT and profile is not None:
        min_plane_points = profile.min_plane_points_for(points, origins)  # a coarser grid: fewer rays
    connected_only = _checked_settings(connected_only, min_plane_points, surface_tolerance)
    e_list = _as_threshold_list(max_error_increment, 'max_error_increment', float)
    n_list = _as_threshold_list(max_planes, 'max_planes', int)
    noise = None if profile is None else profile.noise_for(points, origins)
    if tiles is PROFILE_DEFAULT:
        tiles = 'auto' if surface_tolerance is not None and e_list and not n_list else 1
    if tiles == 'auto' and np.ndim(points) == 3 and np.shape(points)[0] >= 4 * np.shape(points)[1]:
        return _extract_transposed_sweep(points, origins, tiles=tiles, **options)
    hierarchy = extract_plane_hierarchy(
        points,
        origins=origins,
        max_neighbor_distance=max_neighbor_distance,
        max_error_increment=max(e_list) if e_list else None,
        max_planes=min(n_list) if n_list else None,
        noise=noise,
        tiles=tiles,
        threads=threads,
        options=None if profile is None else _profile_greedy_options(profile),
    )
    cut_kwargs = [{'max_error_increment': e} for e in e_list or []] + [{'max_planes': n} for n in n_list or []]
    if surface_tolerance is None and profile is None:
        cuts = [hierarchy.cut(**kw, min_plane_points=min_plane_points) for kw in cut_kwargs]
    else:
        cuts = [
            whole_surfaces(hierarchy, kw, profile, min_plane_points, surface_tolerance, connected_only)
            for kw in cut_kwargs
        ]
    cuts = cuts or [_final_planes(hierarchy, min_plane_points)]
    scalar = not isinstance(max_error_increment, Sequence | np.ndarray) and not isinstance(
        max_planes, Sequence | np.ndarray
    )
    return cuts[0] if scalar and len(cuts) == 1 else cuts
