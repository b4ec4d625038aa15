"""Plane-extraction methods behind one small interface: organized points -> per-pixel plane labels, timed.

Every method is a :class:`PlaneMethod`: construct it with its parameters, call
:meth:`PlaneMethod.check_available` (raises :class:`MethodUnavailable` with the reason, e.g. an
optional peer that is not installed), then :meth:`PlaneMethod.segment` per scan. Methods: ``ppe``
(this project), ``msac`` (the paper's baseline) and the peers of :mod:`ppe_ros.benchmark.peers`.
"""

from __future__ import annotations

import hashlib
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from ppe_ros.core.msac import DEFAULT_DISTANCE, DEFAULT_MIN_REMAINING_FRACTION, extract_planes_msac

PPE_DEFAULT_MAX_NEIGHBOR_DISTANCE = 0.18
"""lmax (m) tuned by the reference on SynPEB."""

PPE_DEFAULT_MAX_ERROR_INCREMENT = 0.0484
"""e (m^2) tuned by the reference on SynPEB (sqrt(e) = 0.22 m)."""

ERROR_GRID = tuple((0.02 * i) ** 2 for i in range(1, 51))
"""The reference's e grid (m^2): ``(0.02:0.02:1)^2``."""

LEVEL_MATCH_TOLERANCE = 5e-5
"""Per-level parameters apply to scans whose radial sigma is within this many metres (0.05 mm)."""


class MethodUnavailable(RuntimeError):
    """A method cannot run here (an optional dependency is missing); the message says why and how to fix it."""


@dataclass(frozen=True)
class Segmentation:
    """The result of one method on one scan.

    Attributes:
        labels: ``(H, W)`` int64 plane labels; 0 = no plane.
        seconds: wall time of the method on this scan (s), excluding loading and scoring.
        residuals: ``(H, W)`` radial residuals (m) of each pixel w.r.t. the exact radial fit of its
            plane, when the method computes them (PPE); None: the runner fits them.
        sweep: for methods with a threshold hierarchy (PPE): e (m^2) -> ``(H, W)`` labels of that cut.
        info: method-specific details (plane count, ...).
    """

    labels: np.ndarray
    seconds: float
    residuals: np.ndarray | None = None
    sweep: dict[float, np.ndarray] | None = None
    info: dict[str, Any] = field(default_factory=dict)


class PlaneMethod:
    """Base class: a plane-extraction method with fixed parameters."""

    name: ClassVar[str] = ''
    description: ClassVar[str] = ''

    def parameters(self) -> dict[str, Any]:
        """The parameters, JSON-ready (shown in the benchmark report)."""
        raise NotImplementedError

    def check_available(self) -> None:
        """Raise :class:`MethodUnavailable` if the method cannot run here."""

    def warm_up(self) -> None:
        """Run once on a tiny scan so that compilation (numba) does not count in the timings."""
        from ppe_ros.core.synthetic import plane_scan

        self.segment(plane_scan(3, rows=12, cols=16, radial_sigma=0.005).points)

    def segment(self, points: np.ndarray, origins: np.ndarray | None = None) -> Segmentation:
        """Segment an organized ``(H, W, 3)`` scan (metres, NaN = no return) into planes."""
        raise NotImplementedError

    def for_noise(self, radial_sigma: float | None) -> PlaneMethod:
        """The method to run on scans of this radial noise (m; None = unknown): ``self`` unless per-level params."""
        return self

    def describe(self) -> str:
        """``name (key=value, ...)``."""
        params = ', '.join(f'{k}={_format_value(v)}' for k, v in self.parameters().items())
        return f'{self.name} ({params})'


def profile_digest(sensor: str) -> str:
    """12 hex digits of the SHA-256 of the named sensor profile's repr (every field, the noise model's too)."""
    from ppe_ros.core.sensor import sensor_profile

    return hashlib.sha256(repr(sensor_profile(sensor)).encode()).hexdigest()[:12]


def _format_value(value: Any) -> str:
    if isinstance(value, float):
        return f'{value:.6g}'
    if isinstance(value, list | tuple):
        return '[' + ', '.join(_format_value(v) for v in value) + ']'
    if isinstance(value, dict):
        return '{' + ', '.join(f'{k}={_format_value(v)}' for k, v in value.items()) + '}'
    return str(value)


def _check_positive(value: float, what: str, *, allow_inf: bool = False) -> float:
    value = float(value)
    if not (value > 0.0) or (math.isinf(value) and not allow_inf) or math.isnan(value):
        raise ValueError(f'{what} must be a positive{"" if allow_inf else " finite"} number; got {value!r}')
    return value


class PpeMethod(PlaneMethod):
    """Probabilistic Plane Extraction (this project).

    Args:
        max_neighbor_distance: lmax (m).
        max_error_increment: e (m^2) of the reported segmentation.
        min_plane_points: smaller planes are reported as no plane.
        sweep_errors: also return the labels of these e values (m^2) from the same run (for the
            f-over-sqrt(e) curve and tuning); the run then continues up to the largest of them,
            and ``seconds`` includes that.
        level_params: per radial noise level: ``{sigma (m): (lmax (m), e (m^2))}`` used instead of
            the two above on scans of that noise (matched within :data:`LEVEL_MATCH_TOLERANCE`),
            e.g. parameters tuned on each level's train split. Scans of other or unknown noise use
            the two above.
    """

    name = 'ppe'
    description = 'Probabilistic Plane Extraction (this project)'

    def __init__(
        self,
        max_neighbor_distance: float = PPE_DEFAULT_MAX_NEIGHBOR_DISTANCE,
        max_error_increment: float = PPE_DEFAULT_MAX_ERROR_INCREMENT,
        *,
        min_plane_points: int = 4,
        sweep_errors: Sequence[float] | None = None,
        level_params: Mapping[float, tuple[float, float]] | None = None,
    ) -> None:
        self.max_neighbor_distance = _check_positive(
            max_neighbor_distance, 'max_neighbor_distance (lmax, m)', allow_inf=True
        )
        self.max_error_increment = float(max_error_increment)
        if not (math.isfinite(self.max_error_increment) and self.max_error_increment >= 0.0):
            raise ValueError(f'max_error_increment (e, m^2) must be finite and >= 0; got {max_error_increment!r}')
        if int(min_plane_points) != min_plane_points or min_plane_points < 1:
            raise ValueError(f'min_plane_points must be a positive integer; got {min_plane_points!r}')
        self.min_plane_points = int(min_plane_points)
        self.sweep_errors = None if sweep_errors is None else tuple(float(e) for e in sweep_errors)
        if self.sweep_errors is not None and any(not (math.isfinite(e) and e >= 0) for e in self.sweep_errors):
            raise ValueError(f'sweep_errors must be finite values >= 0 (m^2); got {sweep_errors}')
        self._levels: dict[float, PpeMethod] = {}
        for sigma, (lmax, error) in sorted((level_params or {}).items()):
            if not (math.isfinite(sigma) and sigma >= 0.0):
                raise ValueError(f'level_params: radial sigma must be finite and >= 0 (m); got {sigma!r}')
            if any(abs(sigma - known) <= LEVEL_MATCH_TOLERANCE for known in self._levels):
                raise ValueError(f'level_params: two entries for radial sigma {sigma * 1000:g} mm')
            self._levels[float(sigma)] = PpeMethod(
                lmax, error, min_plane_points=self.min_plane_points, sweep_errors=self.sweep_errors
            )

    def parameters(self) -> dict[str, Any]:
        params: dict[str, Any] = {
            'lmax': self.max_neighbor_distance,
            'e': self.max_error_increment,
            'sqrt_e': math.sqrt(self.max_error_increment),
        }
        for sigma, method in self._levels.items():
            params[f'at {sigma * 1000:g} mm'] = method.parameters()
        return params

    def for_noise(self, radial_sigma: float | None) -> PpeMethod:
        if radial_sigma is not None:
            for sigma, method in self._levels.items():
                if abs(radial_sigma - sigma) <= LEVEL_MATCH_TOLERANCE:
                    return method
        return self

    def segment(self, points: np.ndarray, origins: np.ndarray | None = None) -> Segmentation:
        from ppe_ros.core.extraction import extract_plane_hierarchy
        from ppe_ros.core.fitting import fit_pixel_groups

        stop = max([self.max_error_increment, *(self.sweep_errors or ())])
        start = time.perf_counter()
        hierarchy = extract_plane_hierarchy(
            points, origins=origins, max_neighbor_distance=self.max_neighbor_distance, max_error_increment=stop
        )
        steps = hierarchy.steps_for_error(self.max_error_increment)
        planes, residuals = fit_pixel_groups(
            hierarchy.scan, hierarchy.plane_ids(steps), min_plane_points=self.min_plane_points
        )
        seconds = time.perf_counter() - start
        sweep = None
        if self.sweep_errors is not None:
            by_steps: dict[int, np.ndarray] = {}  # equal cuts share one array (the runner scores each once)
            sweep = {}
            for e in self.sweep_errors:
                cut = hierarchy.steps_for_error(e)
                if cut not in by_steps:
                    by_steps[cut] = hierarchy_labels(hierarchy, e, self.min_plane_points)
                sweep[e] = by_steps[cut]
        return Segmentation(
            labels=planes.labels.astype(np.int64),
            seconds=seconds,
            residuals=residuals,
            sweep=sweep,
            info={'planes': planes.num_planes, 'actions': steps, 'extraction_seconds': hierarchy.seconds},
        )


def hierarchy_labels(hierarchy, max_error_increment: float, min_plane_points: int = 4) -> np.ndarray:
    """``(H, W)`` int64 labels of a PPE hierarchy cut at e (m^2), without fitting the planes.

    Labels are arbitrary positive ids (plane id + 1); planes with fewer than ``min_plane_points``
    pixels become 0.
    """
    ids = hierarchy.plane_ids(hierarchy.steps_for_error(max_error_increment)).astype(np.int64)
    labels = np.where(ids >= 0, ids + 1, 0)
    if min_plane_points > 1:
        values, counts = np.unique(labels[labels > 0], return_counts=True)
        small = values[counts < min_plane_points]
        if len(small):
            labels[np.isin(labels, small)] = 0
    return labels.reshape(hierarchy.scan.height, hierarchy.scan.width)


class PpePaperMethod(PpeMethod):
    """PPE with the reference's parameters tuned on SynPEB (lmax 0.18 m, e 0.0484 m^2), one extraction, no sweep.

    Shown beside the tuned ``ppe`` row: the paper's setting on this data without any tuning.
    """

    name = 'ppe-paper'
    description = "PPE with the paper's SynPEB parameters (lmax 0.18 m, e 0.0484 m^2)"

    def __init__(self, *, min_plane_points: int = 4) -> None:
        super().__init__(
            PPE_DEFAULT_MAX_NEIGHBOR_DISTANCE, PPE_DEFAULT_MAX_ERROR_INCREMENT, min_plane_points=min_plane_points
        )


class PpeSensorMethod(PlaneMethod):
    """PPE with a sensor profile (``extract_planes(points, origins=..., sensor=...)``): its noise model, whole
    surfaces, planarity test and defaults, as the node and ``ppe extract --sensor`` run it; no threshold sweep
    (the profile's e is in units of its noise variance, not the paper's m^2)."""

    profile: ClassVar[str] = ''

    def parameters(self) -> dict[str, Any]:
        """The profile's name and a digest of all its settings (:func:`profile_digest`): ``ppe eval --reuse``
        keys an earlier result by these, so a profile whose defaults changed since then runs again."""
        return {'sensor': self.profile, 'profile_digest': profile_digest(self.profile)}

    def warm_up(self) -> None:
        from ppe_ros.core.synthetic import plane_scan

        self.segment(plane_scan(3, rows=24, cols=48, radial_sigma=0.005).points)

    def segment(self, points: np.ndarray, origins: np.ndarray | None = None) -> Segmentation:
        from ppe_ros.core.extraction import extract_planes

        start = time.perf_counter()
        planes = extract_planes(points, origins=origins, sensor=self.profile)
        return Segmentation(
            labels=planes.labels.astype(np.int64),
            seconds=time.perf_counter() - start,
            info={'planes': planes.num_planes, 'actions': planes.actions},
        )


class PpeLidarMethod(PpeSensorMethod):
    """PPE with the lidar profile."""

    name = 'ppe-lidar'
    description = "PPE with the lidar profile (sensor='lidar')"
    profile = 'lidar'


class PpeDepthCameraMethod(PpeSensorMethod):
    """PPE with the depth camera profile."""

    name = 'ppe-depth-camera'
    description = "PPE with the depth camera profile (sensor='depth_camera')"
    profile = 'depth_camera'


#: The methods of PPE with a sensor profile, by name.
SENSOR_METHODS: dict[str, type[PpeSensorMethod]] = {
    PpeLidarMethod.name: PpeLidarMethod,
    PpeDepthCameraMethod.name: PpeDepthCameraMethod,
}


class MsacMethod(PlaneMethod):
    """The paper's baseline: sequential MSAC (:func:`ppe_ros.core.msac.extract_planes_msac`).

    Args:
        distance: inlier distance (m). fraction: stop when this fraction of the pixels is left.
        seed: random seed. max_trials: hypotheses per plane.
    """

    name = 'msac'
    description = "sequential MSAC, the paper's baseline (own numpy/numba implementation)"

    def __init__(
        self,
        distance: float = DEFAULT_DISTANCE,
        fraction: float = DEFAULT_MIN_REMAINING_FRACTION,
        *,
        seed: int = 0,
        max_trials: int = 1000,
    ) -> None:
        self.distance = _check_positive(distance, 'distance (m)')
        self.fraction = float(fraction)
        if not 0.0 <= self.fraction < 1.0:
            raise ValueError(f'fraction must be in [0, 1); got {fraction!r}')
        self.seed = int(seed)
        self.max_trials = int(max_trials)

    def parameters(self) -> dict[str, Any]:
        return {'distance': self.distance, 'fraction': self.fraction, 'seed': self.seed}

    def segment(self, points: np.ndarray, origins: np.ndarray | None = None) -> Segmentation:
        start = time.perf_counter()
        result = extract_planes_msac(
            points,
            distance=self.distance,
            min_remaining_fraction=self.fraction,
            max_trials=self.max_trials,
            seed=self.seed,
        )
        seconds = time.perf_counter() - start
        return Segmentation(labels=result.labels.astype(np.int64), seconds=seconds, info={'planes': result.num_planes})


def method_names() -> tuple[str, ...]:
    """Every known method name (available or not)."""
    from ppe_ros.benchmark.peers import PEERS

    return ('ppe', 'ppe-paper', *SENSOR_METHODS, 'msac', *PEERS)


def make_method(name: str, **params) -> PlaneMethod:
    """A method by name with its parameters (keyword arguments of its class).

    Raises:
        ValueError: unknown name or bad parameters.
    """
    from ppe_ros.benchmark.peers import PEERS

    classes: dict[str, type[PlaneMethod]] = {
        'ppe': PpeMethod,
        'ppe-paper': PpePaperMethod,
        **SENSOR_METHODS,
        'msac': MsacMethod,
        **PEERS,
    }
    if name not in classes:
        raise ValueError(f'unknown method {name!r}; known: {", ".join(classes)}')
    return classes[name](**params)
