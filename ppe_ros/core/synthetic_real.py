"""Labelled scans with the errors of real sensors: a spinning lidar in a street, a Kinect-like depth camera in rooms.

:mod:`ppe_ros.core.synthetic` makes SynPEB-like scans: perfectly flat faces and independent
Gaussian range noise. Real scans differ in ways that matter for plane extraction (see issue 16):
each lidar beam has its own constant range bias and elevation error, real surfaces are flat only to
millimetres or centimetres, noise and dropouts grow at grazing incidence, and a depth camera's noise
grows as z² and is quantised in disparity. This module models those errors (all parameters in
:class:`LidarErrorModel` and :class:`DepthErrorModel`) on scenes whose ground truth is *physical
surfaces*:

* A :class:`SurfaceScene` is a :class:`~ppe_ros.core.synthetic.Scene` whose face labels are surfaces:
  all convex faces of one planar surface (a facade around its windows, a road) share one label.
  Non-planar things (trees, bushes, people, cars, lamp posts) are built from many small facets
  under labels listed in ``clutter_labels``.
* Ground truth (:class:`SensorScan`, a :class:`~ppe_ros.core.synthetic.SyntheticScan`): ``labels``
  holds one label per visible planar surface (>= 10) *even when an occluder cuts it into pieces*;
  :data:`CLUTTER_LABEL` (2) for clutter, :data:`~ppe_ros.core.synthetic.UNLABELLED_LABEL` (3) for
  surfaces seen with fewer than ``min_surface_pixels`` pixels, 0 for no return. Labels below 10 are
  "visible, no ground-truth plane" for :func:`ppe_ros.core.evaluation.score_segmentation` (they are
  no GT region but count towards the size of an extracted plane that covers them), so a method that
  forces a tree into planes is charged for it. :meth:`SensorScan.connected_labels` gives the
  4-connected pieces instead (SynPEB's convention).

Frames: scenes are in a world frame (metres, z up). Lidar points are in the lidar's sensor frame
(x forward, y left, z up), destaggered like an Ouster image: row = beam (row 0 the top beam), column
j at azimuth ``-360 j / W`` degrees, ray starts on a circle of ``beam_origin_radius`` around the
z axis (Ouster's ``lidar_origin_to_beam_origin_mm``). Depth-camera points are in the optical frame
(x right, y down, z forward), as :func:`ppe_ros.io.depth.backproject_depth` makes them.

Determinism: the scene from ``default_rng(seed)`` (in the scene builders) and its surface
undulation from ``default_rng([seed, 3])`` (the world), the per-scan noise and dropouts from
``default_rng([noise_seed, 2])``, the per-sensor calibration errors (beam biases, Kinect distortion)
from ``default_rng([sensor_seed, 4])``; ``noise_seed`` and ``sensor_seed`` default to ``seed``. Scans
of one world by one sensor (a sequence: :func:`generate_lidar_sequence`) share ``seed`` and
``sensor_seed`` and differ in ``noise_seed`` and pose.
Standard normal draws do not depend on the sigmas, so scaling a sigma scales the same pattern.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields

import numpy as np
from numba import njit

from ppe_ros.core.synthetic import (
    _INSIDE_TOLERANCE,
    _MIN_HIT_DISTANCE,
    DEFAULT_SENSOR_POSE,
    FIRST_LABEL,
    UNLABELLED_LABEL,
    Face,
    ScanGrid,
    Scene,
    SensorPose,
    SyntheticScan,
    _check_seed,
    _face_hit,
    _newell_normal,
    _validate_polygon,
    beam_offset_origins,
    icosahedron_polygons,
    label_regions,
    make_room_scene,
    prism_polygons,
)

CLUTTER_LABEL = 2
"""Ground-truth label of pixels on non-planar clutter (trees, bushes, people, cars, lamps, plants):
visible, but no plane; below :data:`~ppe_ros.core.synthetic.FIRST_LABEL`, so never a GT region."""

OS1_128_ALTITUDES_DEG = (
    20.95,
    20.67,
    20.36,
    20.03,
    19.73,
    19.41,
    19.11,
    18.76,
    18.47,
    18.14,
    17.82,
    17.5,
    17.19,
    16.86,
    16.53,
    16.2,
    15.89,
    15.56,
    15.23,
    14.9,
    14.57,
    14.23,
    13.9,
    13.57,
    13.25,
    12.91,
    12.57,
    12.22,
    11.9,
    11.55,
    11.2,
    10.87,
    10.54,
    10.18,
    9.84,
    9.51,
    9.15,
    8.81,
    8.47,
    8.11,
    7.78,
    7.43,
    7.08,
    6.74,
    6.39,
    6.04,
    5.7,
    5.34,
    4.98,
    4.64,
    4.29,
    3.93,
    3.58,
    3.24,
    2.88,
    2.53,
    2.17,
    1.82,
    1.47,
    1.12,
    0.78,
    0.41,
    0.07,
    -0.28,
    -0.64,
    -0.99,
    -1.35,
    -1.7,
    -2.07,
    -2.4,
    -2.75,
    -3.11,
    -3.46,
    -3.81,
    -4.15,
    -4.5,
    -4.86,
    -5.22,
    -5.57,
    -5.9,
    -6.27,
    -6.61,
    -6.97,
    -7.3,
    -7.67,
    -8.01,
    -8.35,
    -8.69,
    -9.05,
    -9.38,
    -9.71,
    -10.07,
    -10.42,
    -10.76,
    -11.09,
    -11.43,
    -11.78,
    -12.12,
    -12.46,
    -12.78,
    -13.15,
    -13.46,
    -13.8,
    -14.12,
    -14.48,
    -14.79,
    -15.11,
    -15.46,
    -15.79,
    -16.12,
    -16.45,
    -16.76,
    -17.11,
    -17.44,
    -17.74,
    -18.06,
    -18.39,
    -18.72,
    -19.02,
    -19.32,
    -19.67,
    -19.99,
    -20.27,
    -20.57,
    -20.92,
    -21.22,
    -21.54,
    -21.82,
)
"""Beam elevations (degrees, top beam first) of an OS-1-128 (``beam_altitude_angles`` of the Ouster
sample metadata OS-1-128_v2.3.0_1024x10.json, ouster-sdk, BSD-3-Clause): 0.28-0.37 deg apart, not uniform."""

OS1_32_ALTITUDES_DEG = (
    12.75,
    10.03,
    7.27,
    4.47,
    3.41,
    2.35,
    2.02,
    1.65,
    1.29,
    0.93,
    0.6,
    0.23,
    -0.13,
    -0.49,
    -0.83,
    -1.17,
    -1.54,
    -1.88,
    -2.24,
    -2.6,
    -2.96,
    -3.65,
    -4.36,
    -5.06,
    -5.76,
    -7.17,
    -8.57,
    -9.95,
    -11.31,
    -12.66,
    -14.01,
    -15.32,
)
"""Beam elevations (degrees) of an OS-1-32 gradient unit (OS-1-32-G_v2.1.1_1024x10.json): dense near the
horizon (0.33-0.37 deg), 1.4-2.8 deg apart at the top and bottom."""

VLP16_ALTITUDES_DEG = tuple(float(x) for x in np.linspace(15.0, -15.0, 16))
"""Beam elevations (degrees) of a Velodyne VLP-16 (Puck), top first: 16 beams 2 deg apart from +15 to -15 deg."""

HDL32_ALTITUDES_DEG = tuple(float(x) for x in np.linspace(10.67, -30.67, 32))
"""Beam elevations (degrees) of a Velodyne HDL-32E, top first: 32 beams 1.33 deg apart from +10.67 to -30.67 deg."""

HDL64_ALTITUDES_DEG = tuple(float(x) for x in np.r_[np.linspace(2.0, -8.333, 32), np.linspace(-8.833, -24.333, 32)])
"""Beam elevations (degrees) of a Velodyne HDL-64E (KITTI's lidar), top first: an upper block of 32 beams 1/3 deg
apart from +2 to -8.33 deg and a lower block of 32 beams 1/2 deg apart from -8.83 to -24.33 deg."""

LIDAR_MODELS: dict[str, tuple[float, ...]] = {
    'os1-128': OS1_128_ALTITUDES_DEG,
    'os1-32': OS1_32_ALTITUDES_DEG,
    'vlp16': VLP16_ALTITUDES_DEG,
    'hdl32': HDL32_ALTITUDES_DEG,
    'hdl64': HDL64_ALTITUDES_DEG,
}
"""Lidar models known to :func:`lidar_grid`: name -> beam elevations in degrees (columns: ``cols``, 1024 by
default: 0.35 deg, an Ouster at 10 Hz or a Velodyne at about 20 Hz)."""

OUSTER_BEAM_ORIGIN_RADIUS = 0.015806
"""Metres from the lidar's z axis to the beam origins (``lidar_origin_to_beam_origin_mm`` of the OS-1)."""

DEFAULT_LIDAR_COLUMNS = 1024

KINECT_WIDTH = 640
KINECT_HEIGHT = 480


# --------------------------------------------------------------------------------------------
# Error models
# --------------------------------------------------------------------------------------------


def _check_non_negative(model, names: Sequence[str]) -> None:
    for name in names:
        value = getattr(model, name)
        if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0.0):
            raise ValueError(f'{type(model).__name__}.{name} must be a finite number >= 0; got {value!r}')


@dataclass(frozen=True)
class LidarErrorModel:
    """Errors of a spinning lidar (Ouster OS-1 class; defaults from datasheets and the shared sweeps).

    Per ray k of beam i hitting a surface at incidence angle ``inc`` (between ray and surface normal)::

        measured range = true range to the undulating surface along the beam's true direction
                         + bias_i + sigma(inc) * N(0, 1)
        sigma(inc)     = sqrt(range_sigma² + (grazing_sigma * (1 / max(cos inc, min_cos) - 1))²)

    and the point is stored along the beam's *nominal* direction, so the elevation error shows up as
    a geometric error that is constant per beam. Calibration errors (bias_i, the elevation errors)
    are per sensor: drawn from ``sensor_seed``.

    Attributes:
        range_sigma: range noise standard deviation at normal incidence, metres (OS-1: 1-3 cm).
        grazing_sigma: growth of the range sigma at grazing incidence, metres per unit of
            ``1 / cos(inc) - 1`` (the footprint spreads over a range interval).
        min_cos: ``cos inc`` is clamped to at least this in the grazing term.
        beam_range_bias_sigma: standard deviation of each beam's constant range bias, metres.
        beam_elevation_sigma_deg: standard deviation of each beam's constant elevation error, degrees.
        surface_amplitude: RMS height of each planar surface's smooth random undulation, metres
            (real walls and roads are flat to mm-cm; 0 = perfect planes).
        surface_wavelength_min, surface_wavelength_max: its wavelengths are uniform in this range, metres.
        surface_waves: number of plane waves summed per surface (random directions in the surface).
        grazing_dropout_deg: incidence angle (degrees) at which half of the returns are lost.
        grazing_dropout_width_deg: width of the logistic dropout ramp around it, degrees.
        dropout_rate: probability that any ray returns nothing.
        max_range: hits beyond this (metres) are no-returns; min_range: measured ranges below it too.
        beam_origin_radius: ray starts on a circle of this radius (metres) around the z axis.
    """

    range_sigma: float = 0.02
    grazing_sigma: float = 0.0015
    min_cos: float = 0.02
    beam_range_bias_sigma: float = 0.01
    beam_elevation_sigma_deg: float = 0.03
    surface_amplitude: float = 0.007
    surface_wavelength_min: float = 1.0
    surface_wavelength_max: float = 3.0
    surface_waves: int = 4
    grazing_dropout_deg: float = 88.0
    grazing_dropout_width_deg: float = 0.7
    dropout_rate: float = 0.005
    max_range: float = 100.0
    min_range: float = 0.3
    beam_origin_radius: float = OUSTER_BEAM_ORIGIN_RADIUS

    def __post_init__(self) -> None:
        _check_non_negative(self, [f.name for f in fields(self) if f.name != 'surface_waves'])
        if not (0.0 < self.min_cos <= 1.0):
            raise ValueError(f'LidarErrorModel.min_cos must be in (0, 1]; got {self.min_cos}')
        if not (0.0 < self.surface_wavelength_min <= self.surface_wavelength_max):
            raise ValueError('LidarErrorModel surface wavelengths must satisfy 0 < min <= max')
        if (
            isinstance(self.surface_waves, bool)
            or int(self.surface_waves) != self.surface_waves
            or self.surface_waves < 1
        ):
            raise ValueError(f'LidarErrorModel.surface_waves must be an integer >= 1; got {self.surface_waves!r}')
        if not (self.dropout_rate < 1.0 and self.max_range > self.min_range):
            raise ValueError('LidarErrorModel needs dropout_rate < 1 and max_range > min_range')

    @classmethod
    def exact(cls, **changes) -> LidarErrorModel:
        """No noise, no biases, no undulation, no dropouts (range limits and beam offsets kept)."""
        zero = {
            'range_sigma': 0.0,
            'grazing_sigma': 0.0,
            'beam_range_bias_sigma': 0.0,
            'beam_elevation_sigma_deg': 0.0,
            'surface_amplitude': 0.0,
            'grazing_dropout_deg': 90.0,
            'grazing_dropout_width_deg': 0.0,
            'dropout_rate': 0.0,
        }
        return cls(**{**zero, **changes})

    def sigma(self, cos_incidence: np.ndarray) -> np.ndarray:
        """Range noise standard deviation (metres) at the given ``cos(incidence)``."""
        grazing = self.grazing_sigma * (1.0 / np.maximum(np.abs(cos_incidence), self.min_cos) - 1.0)
        return np.sqrt(self.range_sigma**2 + grazing**2)

    def to_dict(self) -> dict:
        """Plain-Python form (for JSON)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(frozen=True)
class DepthErrorModel:
    """Errors of a structured-light depth camera (Kinect v1 class; Khoshelham and Elberink 2012).

    Per pixel, with ``z`` the true depth of the (laterally jittered) ray's hit on the undulating
    surface::

        z_distorted = z + distortion_coefficient * z² * P(u, v)
        d           = focal_px * baseline / z_distorted                  (disparity, pixels)
        d_measured  = round((d + sigma_d N(0, 1)) / step) * step         (step = disparity_step_px)
        z_measured  = focal_px * baseline / d_measured

    ``sigma_d`` is chosen so that the total axial standard deviation (Gaussian plus quantisation,
    ``step² / 12``) is ``axial_noise_coefficient * z²`` (to first order in the noise). ``P`` is a fixed
    low-frequency pattern per sensor: ``radial_weight (rho² - 1/2) + band_weight cos(2 pi u /
    band_period_px + phase)`` with ``rho`` the distance from the principal point over the corner's.
    The point is back-projected through the pixel centre: ``(u - cx) z / fx, (v - cy) z / fy, z``.

    Attributes:
        baseline: projector-camera baseline, metres (Kinect v1: 7.5 cm).
        focal_px: focal length (pixels) of the disparity measurement (Kinect v1: 575 px); it sets
            the disparity scale whatever size and intrinsics the output image has.
        disparity_step_px: disparity quantisation, pixels (Kinect v1: 1/8).
        axial_noise_coefficient: ``c`` in ``sigma_z = c z²``, 1/m (Kinect v1: 1.43e-3).
        lateral_sigma_px: standard deviation of the ray's position in the image, pixels (the lateral
            error is ``lateral_sigma_px z / f`` metres).
        distortion_coefficient: scale of the depth distortion, 1/m (1e-3: a few mm at 2 m, ~1.5 cm at 4 m).
        radial_weight, band_weight, band_period_px: shape of the distortion pattern P.
        surface_amplitude, surface_wavelength_min, surface_wavelength_max, surface_waves: smooth random
            undulation of each planar surface (RMS metres; as in :class:`LidarErrorModel`).
        projector_offset: the projector sits this far along the camera's +x axis (metres); points it
            cannot see (shadows beside foreground objects) are no-returns. 0 = no shadows.
        edge_dropout_probability: probability of a no-return at a pixel next to a depth jump larger
            than ``edge_jump_fraction * z``.
        dropout_rate: probability that any pixel returns nothing.
        min_depth, max_depth: depths (metres) outside this range are no-returns (Kinect v1: 0.5-8 m).
    """

    baseline: float = 0.075
    focal_px: float = 575.0
    disparity_step_px: float = 0.125
    axial_noise_coefficient: float = 1.43e-3
    lateral_sigma_px: float = 0.5
    distortion_coefficient: float = 1.0e-3
    radial_weight: float = 1.0
    band_weight: float = 0.5
    band_period_px: float = 160.0
    surface_amplitude: float = 0.002
    surface_wavelength_min: float = 1.0
    surface_wavelength_max: float = 3.0
    surface_waves: int = 4
    projector_offset: float = 0.075
    edge_dropout_probability: float = 0.5
    edge_jump_fraction: float = 0.05
    dropout_rate: float = 0.002
    min_depth: float = 0.5
    max_depth: float = 8.0

    def __post_init__(self) -> None:
        _check_non_negative(self, [f.name for f in fields(self) if f.name not in ('surface_waves',)])
        if not (
            self.baseline > 0.0
            and self.focal_px > 0.0
            and self.band_period_px > 0.0
            and self.max_depth > self.min_depth
        ):
            raise ValueError(
                'DepthErrorModel needs baseline > 0, focal_px > 0, band_period_px > 0 and max_depth > min_depth'
            )
        if not (0.0 < self.surface_wavelength_min <= self.surface_wavelength_max):
            raise ValueError('DepthErrorModel surface wavelengths must satisfy 0 < min <= max')
        if self.edge_dropout_probability > 1.0 or self.dropout_rate >= 1.0:
            raise ValueError('DepthErrorModel probabilities must be at most 1 (dropout_rate below 1)')
        if (
            isinstance(self.surface_waves, bool)
            or int(self.surface_waves) != self.surface_waves
            or self.surface_waves < 1
        ):
            raise ValueError(f'DepthErrorModel.surface_waves must be an integer >= 1; got {self.surface_waves!r}')

    @classmethod
    def exact(cls, **changes) -> DepthErrorModel:
        """No noise, quantisation, distortion, undulation or dropouts (the depth range kept)."""
        zero = {
            'disparity_step_px': 0.0,
            'axial_noise_coefficient': 0.0,
            'lateral_sigma_px': 0.0,
            'distortion_coefficient': 0.0,
            'surface_amplitude': 0.0,
            'projector_offset': 0.0,
            'edge_dropout_probability': 0.0,
            'dropout_rate': 0.0,
        }
        return cls(**{**zero, **changes})

    def disparity_sigma(self) -> float:
        """Standard deviation (pixels) of the Gaussian disparity noise before quantisation.

        Raises:
            ValueError: the quantisation alone is noisier than ``axial_noise_coefficient`` allows.
        """
        focal_px = self.focal_px
        total = self.axial_noise_coefficient * focal_px * self.baseline
        quantisation = self.disparity_step_px**2 / 12.0
        if total**2 < quantisation:
            raise ValueError(
                f'disparity quantisation ({self.disparity_step_px} px) alone exceeds the axial noise '
                f'c = {self.axial_noise_coefficient} 1/m at f = {focal_px} px'
            )
        return math.sqrt(total**2 - quantisation)

    def to_dict(self) -> dict:
        """Plain-Python form (for JSON)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


# --------------------------------------------------------------------------------------------
# Surface scenes
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SurfaceScene:
    """A scene whose face labels are physical surfaces, with clutter and large-scale surface shape.

    Attributes:
        scene: the faces (world frame, metres); all faces of one surface share its label.
        clutter_labels: labels of non-planar objects (no ground-truth plane).
        names: label -> what the surface or object is (``'building3.facade'``, ``'tree2'``).
        shape_waves: label -> ``(K, 5)`` rows ``(kx, ky, kz, phase, amplitude)``: the surface is
            displaced along its normal by ``sum amplitude cos(k . x + phase)`` (world frame, k in rad/m,
            amplitude in metres): the road's camber and slow undulation. Part of the scene, not an error.
        description: one line.
        groups: per face, the object it belongs to (faces of one group are consecutive; the ray
            caster skips a group whose bounding sphere a ray misses); empty: consecutive faces of one label.
    """

    scene: Scene
    clutter_labels: frozenset[int] = frozenset()
    names: dict[int, str] = field(default_factory=dict)
    shape_waves: dict[int, np.ndarray] = field(default_factory=dict)
    description: str = ''
    groups: tuple[int, ...] = ()

    def planar_labels(self) -> np.ndarray:
        """Sorted labels of the planar surfaces (not clutter)."""
        labels = {face.label for face in self.scene.faces} - set(self.clutter_labels)
        return np.array(sorted(labels), dtype=np.int64)

    def label_of(self, name: str) -> int:
        """The label of the surface or object called ``name``.

        Raises:
            KeyError: no such name.
        """
        for label, known in self.names.items():
            if known == name:
                return label
        raise KeyError(f'no surface called {name!r} in the scene')


class SurfaceSceneBuilder:
    """Collects faces surface by surface; :meth:`build` makes the :class:`SurfaceScene`.

    Faces of one object are kept together (one bounding-sphere group in the ray caster).
    """

    def __init__(self, first_label: int = FIRST_LABEL) -> None:
        self._next = int(first_label)
        self._faces: list[Face] = []
        self._groups: list[int] = []
        self._group = 0
        self._clutter: set[int] = set()
        self._names: dict[int, str] = {}
        self._waves: dict[int, np.ndarray] = {}

    def surface(self, name: str, *, clutter: bool = False) -> int:
        """A new label for a surface (or a clutter object) called ``name``."""
        label = self._next
        self._next += 1
        self._names[label] = name
        if clutter:
            self._clutter.add(label)
        return label

    def reserve(self, label: int, name: str) -> None:
        """Use an existing ``label`` (e.g. a face of another scene) for surface ``name``; later
        :meth:`surface` labels come after it."""
        self._next = max(self._next, int(label) + 1)
        self._names.setdefault(int(label), name)

    def new_group(self) -> None:
        """Start a new ray-casting group (one object)."""
        self._group += 1

    def add(self, label: int, vertices: np.ndarray, name: str = '') -> None:
        """Add a convex planar polygon ``(K, 3)`` (world frame, metres) to surface ``label``."""
        array = np.asarray(vertices, dtype=np.float64)
        if array.shape in ((3, 3), (4, 3)) and _is_planar_convex(array.tolist()):  # fast path, same rules
            checked = array.copy()
            checked.setflags(write=False)
        else:
            checked = _validate_polygon(array, f'face {len(self._faces)} ({name or self._names.get(label, "")!r})')
        self._faces.append(Face(vertices=checked, label=int(label), name=name or self._names.get(label, '')))
        self._groups.append(self._group)

    def add_triangles(self, label: int, triangles: np.ndarray, name: str = '') -> None:
        """Add ``(N, 3, 3)`` triangles (world frame, metres) to surface ``label``.

        Raises:
            ValueError: a triangle is not finite or has zero area.
        """
        array = np.array(triangles, dtype=np.float64).reshape(-1, 3, 3)
        area2 = np.linalg.norm(np.cross(array[:, 1] - array[:, 0], array[:, 2] - array[:, 0]), axis=1)
        if not (np.all(np.isfinite(array)) and np.all(area2 > 0.0)):
            raise ValueError(f'triangles of {self._names.get(label, label)!r} must be finite with non-zero area')
        array.setflags(write=False)
        name = name or self._names.get(label, '')
        self._faces.extend(Face(vertices=triangle, label=int(label), name=name) for triangle in array)
        self._groups.extend([self._group] * len(array))

    def add_polygons(self, label: int, polygons: Sequence[tuple[str, np.ndarray]]) -> None:
        """Add ``(name, vertices)`` polygons all to surface ``label``."""
        for name, vertices in polygons:
            self.add(label, vertices, name)

    def add_shape_wave(self, label: int, wave_vector: Sequence[float], phase: float, amplitude: float) -> None:
        """Displace surface ``label`` along its normal by ``amplitude cos(k . x + phase)`` (metres, rad/m)."""
        row = np.array([[*map(float, wave_vector), float(phase), float(amplitude)]])
        self._waves[label] = np.vstack([self._waves[label], row]) if label in self._waves else row

    def build(self, description: str = '') -> SurfaceScene:
        """The scene, faces ordered by group (groups in order of creation)."""
        order = sorted(range(len(self._faces)), key=lambda i: self._groups[i])
        scene = Scene(faces=tuple(self._faces[i] for i in order), description=description)
        groups = tuple(self._groups[i] for i in order)
        return SurfaceScene(
            scene=scene,
            clutter_labels=frozenset(self._clutter),
            names=dict(self._names),
            shape_waves=dict(self._waves),
            description=description,
            groups=groups,
        )


def _is_planar_convex(corners: list[list[float]]) -> bool:
    """Whether a triangle or quad (lists of 3 coordinates) passes :func:`ppe_ros.core.synthetic._validate_polygon`'s
    tests (finite, non-zero area, coplanar within 1e-9 of the scale, convex), in plain float arithmetic."""
    if not all(math.isfinite(v) for corner in corners for v in corner):
        return False
    count = len(corners)
    normal = [0.0, 0.0, 0.0]
    for i in range(count):  # Newell's method
        (x0, y0, z0), (x1, y1, z1) = corners[i], corners[(i + 1) % count]
        normal[0] += (y0 - y1) * (z0 + z1)
        normal[1] += (z0 - z1) * (x0 + x1)
        normal[2] += (x0 - x1) * (y0 + y1)
    length = math.sqrt(sum(v * v for v in normal))
    if not length > 0.0:
        return False
    normal = [v / length for v in normal]
    scale = max(1.0, max(abs(v) for corner in corners for v in corner))
    mean = [sum(corner[k] for corner in corners) / count for k in range(3)]
    if max(abs(sum((corner[k] - mean[k]) * normal[k] for k in range(3))) for corner in corners) > 1e-9 * scale:
        return False
    for i in range(count):
        a, b, c = corners[i], corners[(i + 1) % count], corners[(i + 2) % count]
        e1 = [b[k] - a[k] for k in range(3)]
        e2 = [c[k] - b[k] for k in range(3)]
        turn = (
            (e1[1] * e2[2] - e1[2] * e2[1]) * normal[0]
            + (e1[2] * e2[0] - e1[0] * e2[2]) * normal[1]
            + (e1[0] * e2[1] - e1[1] * e2[0]) * normal[2]
        )
        if turn < -1e-12 * scale**2:
            return False
    return True


def _face_groups(surface_scene: SurfaceScene) -> np.ndarray:
    """``(F,)`` group index per face: the builder's groups, else consecutive faces of one label."""
    groups = surface_scene.groups
    if len(groups) == len(surface_scene.scene.faces) and len(groups):
        return np.asarray(groups, dtype=np.int64)
    labels = surface_scene.scene.labels
    return np.concatenate([[0], np.cumsum(labels[1:] != labels[:-1])]).astype(np.int64) if labels.size else labels


def _quad(a, b, c, d) -> np.ndarray:
    return np.array([a, b, c, d], dtype=np.float64)


def _rectangles_minus_holes(
    width: float, height: float, holes: Sequence[tuple[float, float, float, float]]
) -> list[tuple[float, float, float, float]]:
    """Cover ``[0, width] x [0, height]`` minus rectangular holes ``(s0, s1, z0, z1)`` with rectangles.

    Horizontal bands between the holes' z edges, each split at the holes it crosses; vertically
    adjacent pieces with the same s interval are merged.
    """
    edges = sorted({0.0, float(height), *(z for h in holes for z in h[2:])})
    rectangles: list[list[float]] = []
    open_pieces: dict[tuple[float, float], list[float]] = {}
    for z_low, z_high in itertools.pairwise(edges):
        if z_high - z_low <= 1e-9:
            continue
        crossing = sorted((h[0], h[1]) for h in holes if h[2] <= z_low + 1e-9 and h[3] >= z_high - 1e-9)
        pieces, start = [], 0.0
        for s0, s1 in crossing:
            if s0 > start + 1e-9:
                pieces.append((start, s0))
            start = max(start, s1)
        if width > start + 1e-9:
            pieces.append((start, float(width)))
        still_open = {}
        for piece in pieces:
            if piece in open_pieces:
                open_pieces[piece][3] = z_high
                still_open[piece] = open_pieces[piece]
            else:
                rectangle = [piece[0], piece[1], z_low, z_high]
                rectangles.append(rectangle)
                still_open[piece] = rectangle
        open_pieces = still_open
    return [tuple(r) for r in rectangles]  # type: ignore[misc]


def _add_facade(
    builder: SurfaceSceneBuilder,
    name: str,
    origin: np.ndarray,
    along: np.ndarray,
    outward: np.ndarray,
    width: float,
    height: float,
    openings: Sequence[tuple[str, float, float, float, float, float]],
) -> None:
    """A vertical wall ``width`` x ``height`` (origin = bottom corner, ``along`` its horizontal unit
    direction, ``outward`` its unit normal towards the viewer) with recessed openings
    ``(kind, s0, s1, z0, z1, depth)``: each opening is its own pane surface set ``depth`` metres back,
    with its reveals (the recess's sides) as further surfaces."""
    up = np.array([0.0, 0.0, 1.0])

    def at(s: float, z: float, back: float = 0.0) -> np.ndarray:
        return origin + s * along + z * up - back * outward

    wall = builder.surface(f'{name}.facade')
    for s0, s1, z0, z1 in _rectangles_minus_holes(width, height, [o[1:5] for o in openings]):
        builder.add(wall, _quad(at(s0, z0), at(s1, z0), at(s1, z1), at(s0, z1)))
    for index, (kind, s0, s1, z0, z1, depth) in enumerate(openings):
        pane = builder.surface(f'{name}.{kind}{index}')
        builder.add(pane, _quad(at(s0, z0, depth), at(s1, z0, depth), at(s1, z1, depth), at(s0, z1, depth)))
        reveals = {
            'left': _quad(at(s0, z0), at(s0, z0, depth), at(s0, z1, depth), at(s0, z1)),
            'right': _quad(at(s1, z0), at(s1, z1), at(s1, z1, depth), at(s1, z0, depth)),
            'top': _quad(at(s0, z1), at(s0, z1, depth), at(s1, z1, depth), at(s1, z1)),
        }
        if z0 > 1e-9:
            reveals['sill'] = _quad(at(s0, z0), at(s1, z0), at(s1, z0, depth), at(s0, z0, depth))
        for side, vertices in reveals.items():
            builder.add(builder.surface(f'{name}.{kind}{index}.{side}'), vertices)


def _add_wall(builder: SurfaceSceneBuilder, name: str, corners: Sequence[Sequence[float]]) -> int:
    label = builder.surface(name)
    builder.add(label, np.array(corners, dtype=np.float64))
    return label


def _subdivided_sphere(level: int) -> np.ndarray:
    """``(20 * 4**level, 3, 3)`` triangles of a unit sphere from a subdivided icosahedron."""
    triangles = np.array([vertices for _, vertices in icosahedron_polygons((0.0, 0.0, 0.0), 1.0)])
    for _ in range(level):
        a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
        ab, bc, ca = ((p + q) / np.linalg.norm(p + q, axis=1, keepdims=True) for p, q in ((a, b), (b, c), (c, a)))
        triangles = np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return triangles


_SPHERE_1 = _subdivided_sphere(1)


def _add_foliage(
    builder: SurfaceSceneBuilder,
    label: int,
    rng: np.random.Generator,
    center: Sequence[float],
    radii: Sequence[float],
    n_leaves: int,
    leaf_size: float,
) -> None:
    """A porous, non-planar blob: a lumpy closed core (80 jittered facets at 60 % of the size) and
    ``n_leaves`` random small triangles (``leaf_size`` metres) scattered in the ellipsoid ``radii``."""
    center = np.asarray(center, dtype=np.float64)
    radii = np.asarray(radii, dtype=np.float64)
    core = _SPHERE_1 * (0.6 * radii)
    vertices, inverse = np.unique(np.round(core.reshape(-1, 3), 9), axis=0, return_inverse=True)
    jitter = rng.uniform(0.8, 1.2, len(vertices))[:, None]
    core = (vertices * jitter)[inverse.reshape(-1)].reshape(-1, 3, 3) + center
    builder.add_triangles(label, core)
    directions = rng.standard_normal((n_leaves, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    positions = center + directions * radii * rng.uniform(0.55, 1.0, (n_leaves, 1)) ** 0.5
    corners = rng.standard_normal((n_leaves, 3, 3))
    corners *= leaf_size / np.maximum(np.linalg.norm(corners, axis=2, keepdims=True), 1e-9)
    leaves = positions[:, None, :] + corners
    area2 = np.linalg.norm(np.cross(leaves[:, 1] - leaves[:, 0], leaves[:, 2] - leaves[:, 0]), axis=1)
    builder.add_triangles(label, leaves[area2 > 0.2 * leaf_size**2])


def _add_car(
    builder: SurfaceSceneBuilder,
    label: int,
    rng: np.random.Generator,
    position: Sequence[float],
    yaw_deg: float,
    z_ground: float,
) -> None:
    """A car body of many small triangles: rounded superelliptic cross-sections lofted along the
    length, a bonnet and boot lower than the cabin, and closed ends."""
    length, width = rng.uniform(3.9, 4.9), rng.uniform(1.7, 1.9)
    body, cabin = rng.uniform(0.65, 0.8), rng.uniform(1.35, 1.55)
    clearance = 0.22
    n_along, n_around = 14, 16
    s = np.linspace(-0.5, 0.5, n_along)
    # Height profile along the car: low at the ends, cabin in the middle (smooth).
    roof = body + (cabin - body) * np.exp(-(((s - 0.05) / 0.22) ** 4))
    ends = 1.0 - 0.35 * np.abs(2 * s) ** 6  # the ends taper
    theta = np.linspace(0.0, 2 * np.pi, n_around, endpoint=False)
    exponent = 2.0 / 4.0
    cy, cz = np.cos(theta), np.sin(theta)
    sy = np.sign(cy) * np.abs(cy) ** exponent
    sz = np.sign(cz) * np.abs(cz) ** exponent
    rings = np.zeros((n_along, n_around, 3))
    for i in range(n_along):
        half_height = (roof[i] - clearance) / 2 * ends[i] ** 0.3
        rings[i, :, 0] = s[i] * length
        rings[i, :, 1] = sy * width / 2 * ends[i]
        rings[i, :, 2] = clearance + half_height + sz * half_height
    yaw = math.radians(yaw_deg)
    rotation = np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0, 0, 1.0]])
    world = rings @ rotation.T + np.array([position[0], position[1], z_ground])
    here, ahead = world[:-1], world[1:]
    here_next, ahead_next = np.roll(here, -1, axis=1), np.roll(ahead, -1, axis=1)
    triangles = [
        np.stack([here, ahead, ahead_next], axis=2).reshape(-1, 3, 3),
        np.stack([here, ahead_next, here_next], axis=2).reshape(-1, 3, 3),
    ]
    for i in (0, n_along - 1):
        centre = np.broadcast_to(world[i].mean(axis=0), (n_around, 3))
        triangles.append(np.stack([centre, world[i], np.roll(world[i], -1, axis=0)], axis=1))
    triangles = np.concatenate(triangles)
    area2 = np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1)
    builder.add_triangles(label, triangles[area2 > 1e-8])


def _add_person(
    builder: SurfaceSceneBuilder, label: int, rng: np.random.Generator, x: float, y: float, z_ground: float
) -> None:
    height = rng.uniform(1.55, 1.9)
    radius = rng.uniform(0.17, 0.24)
    yaw = float(rng.uniform(0, 360))
    builder.add_polygons(
        label, prism_polygons((x, y, z_ground), (2 * radius, 1.4 * radius, height - 0.25), n_sides=12, yaw_deg=yaw)
    )
    builder.add_triangles(label, _SPHERE_1 * np.array([0.1, 0.1, 0.12]) + np.array([x, y, z_ground + height - 0.12]))


def _add_tree(
    builder: SurfaceSceneBuilder, label: int, rng: np.random.Generator, x: float, y: float, z_ground: float
) -> None:
    trunk_height = rng.uniform(2.0, 3.2)
    trunk_radius = rng.uniform(0.1, 0.2)
    builder.add_polygons(
        label,
        prism_polygons(
            (x, y, z_ground),
            (2 * trunk_radius, 2 * trunk_radius, trunk_height),
            n_sides=10,
            yaw_deg=float(rng.uniform(0, 36)),
        ),
    )
    radius = rng.uniform(1.3, 2.4)
    crown = (x, y, z_ground + trunk_height + 0.7 * radius)
    _add_foliage(
        builder,
        label,
        rng,
        crown,
        (radius, radius, radius * rng.uniform(0.8, 1.1)),
        n_leaves=int(140 * radius**2),
        leaf_size=0.22,
    )


# --------------------------------------------------------------------------------------------
# The street scene
# --------------------------------------------------------------------------------------------

STREET_HALF_LENGTH = 70.0
"""The street runs along the world x axis from -70 to +70 m."""


def make_street_scene(seed: int = 0, *, clutter: bool = True) -> SurfaceScene:
    """A random street (world frame: x along the street, y to its left, z up; the road at z = 0).

    Planar surfaces (each one label): the road (``road``; a camber crown of 2-5 cm and a slow
    undulation of 1-2 cm over 20-40 m, as ``shape_waves``), a kerb step of 12-15 cm on each side
    (``kerb_left``/``kerb_right``), the pavements (``pavement_left``/``_right``, 2-3.5 m wide, also
    the ground between and behind the buildings), buildings on both sides (6-16 m tall, 8-20 m long,
    their facades on the pavement's back edge) whose facades have windows recessed 8-12 cm and doors
    recessed 10-20 cm (each pane and each reveal its own surface) and whose side walls meet the facade
    at 90 deg in the gaps, and in one 6-8 m wide gap on the left a 5 deg ramp (``ramp``) rising 4 m
    back from the pavement to a platform (``ramp.top``) with side faces and a back wall.

    Clutter (``clutter=True``; labels in ``clutter_labels``, no ground-truth plane): trees on both
    pavements (trunk prism and a porous crown of many random facets), bushes in front of some
    facades, people on the pavements, lamp posts at the kerb and cars parked along both kerbs and
    driving in the lanes (curved bodies of ~450 small facets), kept 3.5 m clear of the street's
    centre at x in [-12, 12] where :func:`street_sensor_pose` puts the sensor.

    Deterministic in ``seed``.
    """
    seed = _check_seed(seed)
    rng = np.random.default_rng(seed)
    builder = SurfaceSceneBuilder()
    half_width = float(rng.uniform(3.0, 4.5))
    pavement = float(rng.uniform(2.0, 3.5))
    kerb = float(rng.uniform(0.12, 0.15))
    back = 16.0
    length = STREET_HALF_LENGTH
    facade_y = half_width + pavement

    road = _add_wall(
        builder,
        'road',
        [
            (-length, -half_width, 0.0),
            (length, -half_width, 0.0),
            (length, half_width, 0.0),
            (-length, half_width, 0.0),
        ],
    )
    builder.add_shape_wave(road, (0.0, math.pi / (2 * half_width), 0.0), 0.0, float(rng.uniform(0.02, 0.05)))
    wavelength = float(rng.uniform(20.0, 40.0))
    heading = float(rng.uniform(-0.3, 0.3))
    builder.add_shape_wave(
        road,
        (2 * math.pi / wavelength * math.cos(heading), 2 * math.pi / wavelength * math.sin(heading), 0.0),
        float(rng.uniform(0, 2 * math.pi)),
        float(rng.uniform(0.01, 0.02)),
    )
    for side, sign in (('left', 1.0), ('right', -1.0)):
        y_kerb = sign * half_width
        _add_wall(
            builder,
            f'kerb_{side}',
            [(-length, y_kerb, 0.0), (length, y_kerb, 0.0), (length, y_kerb, kerb), (-length, y_kerb, kerb)],
        )
        label = _add_wall(
            builder,
            f'pavement_{side}',
            [
                (-length, y_kerb, kerb),
                (length, y_kerb, kerb),
                (length, sign * (facade_y + back), kerb),
                (-length, sign * (facade_y + back), kerb),
            ],
        )
        wavelength = float(rng.uniform(10.0, 25.0))
        builder.add_shape_wave(
            label,
            (2 * math.pi / wavelength, 0.0, 0.0),
            float(rng.uniform(0, 2 * math.pi)),
            float(rng.uniform(0.003, 0.008)),
        )

    # Buildings along each side, with gaps; a wide gap with the ramp on the left near the sensor.
    ramp_gap = (float(rng.uniform(-8.0, 4.0)), 0.0)
    ramp_gap = (ramp_gap[0], ramp_gap[0] + float(rng.uniform(6.0, 8.0)))
    for side, sign in (('left', 1.0), ('right', -1.0)):
        x = -length + float(rng.uniform(0.0, 5.0))
        index = 0
        while x < length - 8.0:
            if side == 'left' and x < ramp_gap[1] and x + 8.0 > ramp_gap[0]:
                x = ramp_gap[1]
                continue
            building_length = float(rng.uniform(8.0, 20.0))
            end = min(x + building_length, length)
            if side == 'left' and x < ramp_gap[0] < end:
                end = ramp_gap[0]
            if end - x >= 6.0:
                _add_building(builder, rng, f'building_{side}{index}', x, end, sign, facade_y, kerb)
                index += 1
            x = end + (float(rng.uniform(1.5, 6.0)) if rng.random() < 0.6 else 0.0)
            if rng.random() >= 0.6 and x == end:
                x = end + 1.5  # adjacent buildings would be coplanar: keep a narrow gap
    _add_ramp(builder, rng, ramp_gap, facade_y, kerb)

    if clutter:
        _add_street_clutter(builder, rng, half_width, pavement, facade_y, kerb, ramp_gap)
    return builder.build(
        f'street (road half-width {half_width:.2f} m, pavement {pavement:.2f} m, kerb {kerb * 100:.1f} cm), seed {seed}'
    )


def _add_building(
    builder: SurfaceSceneBuilder,
    rng: np.random.Generator,
    name: str,
    x0: float,
    x1: float,
    sign: float,
    facade_y: float,
    kerb: float,
) -> None:
    builder.new_group()
    height = float(rng.uniform(6.0, 16.0))
    depth = float(rng.uniform(8.0, 12.0))
    storey = float(rng.uniform(2.8, 3.4))
    n_storeys = max(1, int(height // storey))
    window_width, window_height = float(rng.uniform(0.9, 1.6)), float(rng.uniform(1.2, 1.7))
    window_depth = float(rng.uniform(0.08, 0.12))
    bay = window_width + float(rng.uniform(0.8, 2.0))
    width = x1 - x0
    n_bays = max(1, int((width - 1.0) // bay))
    margin = (width - n_bays * bay) / 2
    door_bay = int(rng.integers(n_bays))
    openings = []
    for storey_index in range(n_storeys):
        for bay_index in range(n_bays):
            s0 = margin + bay_index * bay + (bay - window_width) / 2
            if storey_index == 0 and bay_index == door_bay:
                door_width = float(rng.uniform(1.0, 1.4))
                s0 = margin + bay_index * bay + (bay - door_width) / 2
                openings.append(('door', s0, s0 + door_width, 0.0, 2.1, float(rng.uniform(0.1, 0.2))))
                continue
            z0 = storey_index * storey + 0.9
            if z0 + window_height > height - 0.3:
                continue
            openings.append(('window', s0, s0 + window_width, z0, z0 + window_height, window_depth))
    # The facade faces the street: outward normal -sign * y; its origin is the corner at x0 (left side)
    # so that "along" is +x.
    origin = np.array([x0, sign * facade_y, kerb])
    _add_facade(builder, name, origin, np.array([1.0, 0.0, 0.0]), np.array([0.0, -sign, 0.0]), width, height, openings)
    y_front, y_back = sign * facade_y, sign * (facade_y + depth)
    for end, x in (('end0', x0), ('end1', x1)):
        _add_wall(
            builder,
            f'{name}.{end}',
            [(x, y_front, kerb), (x, y_back, kerb), (x, y_back, kerb + height), (x, y_front, kerb + height)],
        )
    _add_wall(
        builder,
        f'{name}.back',
        [(x0, y_back, kerb), (x1, y_back, kerb), (x1, y_back, kerb + height), (x0, y_back, kerb + height)],
    )


RAMP_SLOPE_DEG = 5.0
"""Slope of the ramp of :func:`make_street_scene`."""


def _add_ramp(
    builder: SurfaceSceneBuilder, rng: np.random.Generator, gap: tuple[float, float], facade_y: float, kerb: float
) -> None:
    builder.new_group()
    x0, x1 = gap[0] + 0.8, gap[1] - 0.8
    run, top_length = 4.0, float(rng.uniform(2.5, 4.0))
    rise = run * math.tan(math.radians(RAMP_SLOPE_DEG))
    y0, y1, y2 = facade_y + 0.3, facade_y + 0.3 + run, facade_y + 0.3 + run + top_length
    z0, z1 = kerb, kerb + rise
    _add_wall(builder, 'ramp', [(x0, y0, z0), (x1, y0, z0), (x1, y1, z1), (x0, y1, z1)])
    _add_wall(builder, 'ramp.top', [(x0, y1, z1), (x1, y1, z1), (x1, y2, z1), (x0, y2, z1)])
    for side, x in (('side0', x0), ('side1', x1)):
        _add_wall(builder, f'ramp.{side}', [(x, y0, z0), (x, y1, z1), (x, y2, z1), (x, y2, z0)])
    _add_wall(
        builder,
        'ramp.back_wall',
        [(x0 - 0.8, y2, z0), (x1 + 0.8, y2, z0), (x1 + 0.8, y2, z1 + 3.0), (x0 - 0.8, y2, z1 + 3.0)],
    )


def _add_street_clutter(
    builder: SurfaceSceneBuilder,
    rng: np.random.Generator,
    half_width: float,
    pavement: float,
    facade_y: float,
    kerb: float,
    ramp_gap: tuple[float, float],
) -> None:
    length = STREET_HALF_LENGTH - 5.0
    parked: list[tuple[float, float]] = []  # (side sign, x) of the parked cars
    for side, sign in (('left', 1.0), ('right', -1.0)):
        x = -length + float(rng.uniform(0.0, 10.0))
        index = 0
        while x < length:
            if rng.random() < 0.75:
                builder.new_group()
                _add_tree(
                    builder,
                    builder.surface(f'tree_{side}{index}', clutter=True),
                    rng,
                    x,
                    sign * (half_width + min(0.9, pavement / 3)),
                    kerb,
                )
            x += float(rng.uniform(8.0, 16.0))
            index += 1
        for index in range(int(rng.integers(3, 7))):
            builder.new_group()
            px = float(rng.uniform(-30.0, 30.0))
            py = sign * (half_width + float(rng.uniform(0.5, pavement - 0.3)))
            _add_person(builder, builder.surface(f'person_{side}{index}', clutter=True), rng, px, py, kerb)
        for index in range(int(rng.integers(2, 5))):
            builder.new_group()
            bx = float(rng.uniform(-40.0, 40.0))
            if ramp_gap[0] - 2.0 < bx < ramp_gap[1] + 2.0:
                continue
            r = float(rng.uniform(0.4, 0.8))
            _add_foliage(
                builder,
                builder.surface(f'bush_{side}{index}', clutter=True),
                rng,
                (bx, sign * (facade_y - r - 0.05), kerb + 0.6 * r),
                (1.6 * r, r, 0.8 * r),
                n_leaves=int(120 * r),
                leaf_size=0.12,
            )
        x = -length + float(rng.uniform(0.0, 15.0))
        index = 0
        while x < length:
            builder.new_group()
            builder.add_polygons(
                builder.surface(f'lamp_{side}{index}', clutter=True),
                prism_polygons((x, sign * (half_width + 0.35), kerb), (0.14, 0.14, 5.5), n_sides=8),
            )
            x += float(rng.uniform(18.0, 30.0))
            index += 1
        # Parked cars along the kerb, moving cars in the lane.
        x = -length + float(rng.uniform(0.0, 8.0))
        index = 0
        while x < length:
            if rng.random() < 0.45 and not abs(x) < 12.0:
                builder.new_group()
                _add_car(
                    builder,
                    builder.surface(f'car_parked_{side}{index}', clutter=True),
                    rng,
                    (x, sign * (half_width - 1.1), 0.0),
                    float(rng.uniform(-3, 3)),
                    0.0,
                )
                parked.append((sign, x))
            x += float(rng.uniform(5.5, 9.0))
            index += 1
    for index in range(int(rng.integers(1, 4))):
        for _ in range(20):  # not beside a parked car of the same side (they would overlap on narrow roads)
            x = float(rng.uniform(14.0, 50.0)) * (1 if rng.random() < 0.5 else -1)
            sign = 1.0 if rng.random() < 0.5 else -1.0
            if all(abs(x - px) > 5.5 for ps, px in parked if ps == sign):
                builder.new_group()
                _add_car(
                    builder,
                    builder.surface(f'car_moving{index}', clutter=True),
                    rng,
                    (x, sign * half_width / 2, 0.0),
                    float(rng.uniform(-4, 4)),
                    0.0,
                )
                break


def street_sensor_pose(seed: int = 0) -> SensorPose:
    """A lidar pose in :func:`make_street_scene`: on a car roof in the street (x -10..10 m, y
    -1.2..1.2 m, 1.7-2.0 m high), looking along it (yaw -15..15 deg or turned round), pitch and roll
    within 1.5 deg. Deterministic in ``seed``."""
    rng = np.random.default_rng([_check_seed(seed), 8])
    yaw = float(rng.uniform(-15.0, 15.0)) + (180.0 if rng.random() < 0.3 else 0.0)
    return SensorPose(
        position=(float(rng.uniform(-10, 10)), float(rng.uniform(-1.2, 1.2)), float(rng.uniform(1.7, 2.0))),
        roll_deg=float(rng.uniform(-1.5, 1.5)),
        pitch_deg=float(rng.uniform(-1.5, 1.5)),
        yaw_deg=yaw,
    )


# --------------------------------------------------------------------------------------------
# Indoor scenes for the depth camera
# --------------------------------------------------------------------------------------------


def make_indoor_scene(
    seed: int = 0, *, sensor_pose: SensorPose | None = None, n_objects: int = 8, clutter: bool = True
) -> SurfaceScene:
    """A room of :func:`ppe_ros.core.synthetic.make_room_scene` (walls, floor, ceiling, furniture;
    every face its own planar surface) with non-planar clutter in view of ``sensor_pose``: a potted
    plant (a 12-sided pot and a porous foliage blob) and a floor lamp (a thin pole and a 16-sided
    shade) in front of the walls, so that walls are cut into several pieces. Deterministic in ``seed``.
    """
    seed = _check_seed(seed)
    pose = DEFAULT_SENSOR_POSE if sensor_pose is None else sensor_pose
    room = make_room_scene(seed, n_objects=n_objects, keep_clear=pose.position[:2], view_yaw_deg=pose.yaw_deg)
    builder = SurfaceSceneBuilder(first_label=FIRST_LABEL)
    for face in room.faces:
        builder.new_group()
        builder.reserve(face.label, face.name)
        builder.add(face.label, face.vertices, face.name)
    if clutter:
        rng = np.random.default_rng([seed, 9])
        size = room.room_size or (7.0, 6.0, 3.0)
        occupied = _footprints(room)
        for kind in ('plant', 'lamp', 'plant'):
            for _ in range(100):
                bearing = math.radians(pose.yaw_deg + rng.uniform(-25.0, 25.0))
                distance = float(rng.uniform(2.5, 4.5))
                x = pose.position[0] + distance * math.cos(bearing)
                y = pose.position[1] + distance * math.sin(bearing)
                radius = 0.35
                if not (radius < x < size[0] - radius and radius < y < size[1] - radius):
                    continue
                if any(x0 - radius < x < x1 + radius and y0 - radius < y < y1 + radius for x0, x1, y0, y1 in occupied):
                    continue
                occupied.append((x - radius, x + radius, y - radius, y + radius))
                builder.new_group()
                label = builder.surface(f'{kind}{len(occupied)}', clutter=True)
                if kind == 'plant':
                    pot = float(rng.uniform(0.25, 0.4))
                    builder.add_polygons(label, prism_polygons((x, y, 0.0), (0.3, 0.3, pot), n_sides=12))
                    leaves = float(rng.uniform(0.3, 0.5))
                    _add_foliage(
                        builder,
                        label,
                        rng,
                        (x, y, pot + leaves),
                        (leaves, leaves, 1.2 * leaves),
                        n_leaves=int(500 * leaves),
                        leaf_size=0.06,
                    )
                else:
                    height = float(rng.uniform(1.5, 1.8))
                    builder.add_polygons(label, prism_polygons((x, y, 0.0), (0.04, 0.04, height), n_sides=8))
                    builder.add_polygons(
                        label, prism_polygons((x, y, height), (0.4, 0.4, 0.3), n_sides=16, bottom=True)
                    )
                break
    return builder.build(f'{room.description}; clutter {clutter}')


def _footprints(scene: Scene) -> list[tuple[float, float, float, float]]:
    """xy bounding boxes (x0, x1, y0, y1) of the objects (faces grouped by name prefix) of a room."""
    boxes: dict[str, list[float]] = {}
    for face in scene.faces:
        owner = face.name.split('.')[0]
        if owner == 'room':
            continue
        low, high = face.vertices[:, :2].min(axis=0), face.vertices[:, :2].max(axis=0)
        box = boxes.setdefault(owner, [low[0], high[0], low[1], high[1]])
        box[:] = [min(box[0], low[0]), max(box[1], high[0]), min(box[2], low[1]), max(box[3], high[1])]
    return [tuple(b) for b in boxes.values()]  # type: ignore[misc]


# --------------------------------------------------------------------------------------------
# Ray casting with object groups
# --------------------------------------------------------------------------------------------


@njit(cache=True, nogil=True)
def _cast_grouped_kernel(
    origins,
    directions,
    normals,
    offsets,
    edge_normals,
    edge_offsets,
    edge_counts,
    centers,
    radii,
    object_bounds,
    chunk_bounds,
    sphere_centers,
    sphere_radii,
    inside_tolerance,
    min_distance,
):
    """Nearest face per ray (distance or NaN, face index or -1) through a two-level hierarchy of
    bounding spheres: objects (``object_bounds`` into the chunks) and chunks of a few faces
    (``chunk_bounds`` into the faces); spheres the ray misses or that lie beyond the best hit are
    skipped. ``sphere_centers``/``sphere_radii`` hold the objects' spheres then the chunks'. The hit
    test is that of :func:`ppe_ros.core.synthetic._cast_rays_kernel`."""
    n_rays = directions.shape[0]
    n_objects = object_bounds.shape[0] - 1
    distances = np.full(n_rays, np.nan)
    hit_faces = np.full(n_rays, -1, dtype=np.int64)
    for k in range(n_rays):
        ox, oy, oz = origins[k, 0], origins[k, 1], origins[k, 2]
        dx, dy, dz = directions[k, 0], directions[k, 1], directions[k, 2]
        best = np.inf
        best_face = -1
        for g in range(n_objects):
            gx = sphere_centers[g, 0] - ox
            gy = sphere_centers[g, 1] - oy
            gz = sphere_centers[g, 2] - oz
            along = gx * dx + gy * dy + gz * dz
            radius = sphere_radii[g]
            if along + radius < 0.0 or along - radius > best:
                continue
            if gx * gx + gy * gy + gz * gz - along * along > radius * radius:
                continue
            for c in range(object_bounds[g], object_bounds[g + 1]):
                s = n_objects + c
                gx = sphere_centers[s, 0] - ox
                gy = sphere_centers[s, 1] - oy
                gz = sphere_centers[s, 2] - oz
                along = gx * dx + gy * dy + gz * dz
                radius = sphere_radii[s]
                if along + radius < 0.0 or along - radius > best:
                    continue
                if gx * gx + gy * gy + gz * gz - along * along > radius * radius:
                    continue
                for f in range(chunk_bounds[c], chunk_bounds[c + 1]):
                    t = _face_hit(
                        f,
                        ox,
                        oy,
                        oz,
                        dx,
                        dy,
                        dz,
                        best,
                        normals,
                        offsets,
                        edge_normals,
                        edge_offsets,
                        edge_counts,
                        centers,
                        radii,
                        inside_tolerance,
                        min_distance,
                    )
                    if t < best:
                        best = t
                        best_face = f
        if best_face >= 0:
            distances[k] = best
            hit_faces[k] = best_face
    return distances, hit_faces


_CHUNK_FACES = 8  # faces per leaf chunk of the caster's hierarchy


@dataclass(frozen=True)
class _PackedPolygons:
    """Faces packed for the kernel (as :func:`ppe_ros.core.synthetic._pack_faces`, vectorised)."""

    normals: np.ndarray  # (F, 3)
    offsets: np.ndarray  # (F,)
    edge_normals: np.ndarray  # (F, E, 3) in-plane inward edge normals
    edge_offsets: np.ndarray  # (F, E)
    edge_counts: np.ndarray  # (F,)
    centers: np.ndarray  # (F, 3) bounding-sphere centres (vertex means)
    radii: np.ndarray  # (F,)


def _pack_polygons(polygons: Sequence[np.ndarray]) -> _PackedPolygons:
    counts = np.array([len(v) for v in polygons], dtype=np.int64)
    n_edges = int(counts.max())
    padded = np.zeros((len(polygons), n_edges, 3))
    valid = np.arange(n_edges)[None, :] < counts[:, None]
    for index, vertices in enumerate(polygons):
        padded[index, : len(vertices)] = vertices
    following = np.where(valid[..., None], padded, 0.0)
    centroid = following.sum(axis=1) / counts[:, None]
    following_index = np.where(valid, (np.arange(n_edges)[None, :] + 1) % counts[:, None], 0)
    nxt = np.take_along_axis(padded, following_index[..., None], axis=1)  # next vertex, cyclic per polygon
    nxt = np.where(valid[..., None], nxt, 0.0)
    # Newell's normal over the real edges.
    normal = np.stack(
        [
            np.sum((following[..., 1] - nxt[..., 1]) * (following[..., 2] + nxt[..., 2]), axis=1),
            np.sum((following[..., 2] - nxt[..., 2]) * (following[..., 0] + nxt[..., 0]), axis=1),
            np.sum((following[..., 0] - nxt[..., 0]) * (following[..., 1] + nxt[..., 1]), axis=1),
        ],
        axis=1,
    )
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    inward = np.cross(normal[:, None, :], nxt - following)
    length = np.linalg.norm(inward, axis=2, keepdims=True)
    inward = np.where(length > 0, inward / np.where(length > 0, length, 1.0), 0.0)
    flip = np.einsum('fek,fek->fe', inward, centroid[:, None, :] - following) < 0
    inward[flip] = -inward[flip]
    edge_offsets = np.einsum('fek,fek->fe', inward, following)
    inward[~valid] = 0.0
    edge_offsets[~valid] = 0.0
    distances = np.where(valid, np.linalg.norm(padded - centroid[:, None, :], axis=2), 0.0)
    return _PackedPolygons(
        normals=normal,
        offsets=np.einsum('fk,fk->f', normal, centroid),
        edge_normals=np.ascontiguousarray(inward),
        edge_offsets=np.ascontiguousarray(edge_offsets),
        edge_counts=counts,
        centers=centroid,
        radii=distances.max(axis=1) * (1 + 1e-12) + 1e-9,
    )


def _bounding_sphere(centers: np.ndarray, radii: np.ndarray) -> tuple[np.ndarray, float]:
    low = (centers - radii[:, None]).min(axis=0)
    high = (centers + radii[:, None]).max(axis=0)
    middle = (low + high) / 2
    return middle, float((np.linalg.norm(centers - middle, axis=1) + radii).max() * (1 + 1e-12) + 1e-9)


def _chunk_spheres(centers: np.ndarray, radii: np.ndarray, bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounding spheres (as :func:`_bounding_sphere`) of the consecutive chunks ``bounds[c]:bounds[c + 1]``."""
    starts = bounds[:-1]
    low = np.minimum.reduceat(centers - radii[:, None], starts, axis=0)
    high = np.maximum.reduceat(centers + radii[:, None], starts, axis=0)
    middle = (low + high) / 2
    owner = np.repeat(np.arange(len(starts)), np.diff(bounds))
    reach = np.linalg.norm(centers - middle[owner], axis=1) + radii
    return middle, np.maximum.reduceat(reach, starts) * (1 + 1e-12) + 1e-9


def _split_chunks(indices: np.ndarray, centers: np.ndarray) -> list[np.ndarray]:
    """Split face indices into spatially compact chunks of at most ``_CHUNK_FACES`` (median cuts
    along the longest extent of the face centres)."""
    if len(indices) <= _CHUNK_FACES:
        return [indices]
    points = centers[indices]
    axis = int(np.argmax(points.max(axis=0) - points.min(axis=0)))
    order = indices[np.argsort(points[:, axis], kind='stable')]
    half = len(order) // 2
    return _split_chunks(order[:half], centers) + _split_chunks(order[half:], centers)


@dataclass(frozen=True)
class _Caster:
    """A scene packed for :func:`_cast_grouped_kernel`; ``order[i]`` is the scene face of packed face i."""

    packed: _PackedPolygons
    order: np.ndarray
    object_bounds: np.ndarray
    chunk_bounds: np.ndarray
    sphere_centers: np.ndarray
    sphere_radii: np.ndarray

    @classmethod
    def of(cls, surface_scene: SurfaceScene) -> _Caster:
        """The packed scene (built once per scene object and kept on it)."""
        cached = surface_scene.__dict__.get('_caster')
        if cached is None:
            cached = cls._build(surface_scene)
            object.__setattr__(surface_scene, '_caster', cached)
        return cached

    @classmethod
    def _build(cls, surface_scene: SurfaceScene) -> _Caster:
        faces = surface_scene.scene.faces
        if not faces:
            raise ValueError('the scene has no faces')
        scene_packed = _pack_polygons([face.vertices for face in faces])
        groups = _face_groups(surface_scene)
        if np.any(np.diff(groups) < 0):
            raise ValueError('faces of one group must be consecutive')
        starts = np.flatnonzero(np.concatenate([[True], groups[1:] != groups[:-1]]))
        ends = np.append(starts[1:], len(faces))
        chunks: list[np.ndarray] = []
        object_bounds = [0]
        object_spheres = []
        for start, end in zip(starts, ends, strict=True):
            members = np.arange(start, end)
            chunks += _split_chunks(members, scene_packed.centers)
            object_bounds.append(len(chunks))
            object_spheres.append(_bounding_sphere(scene_packed.centers[members], scene_packed.radii[members]))
        order = np.concatenate(chunks)
        chunk_bounds = np.concatenate([[0], np.cumsum([len(c) for c in chunks])]).astype(np.int64)
        chunk_centers, chunk_radii = _chunk_spheres(
            scene_packed.centers[order], scene_packed.radii[order], chunk_bounds
        )
        spheres = object_spheres + list(zip(chunk_centers, chunk_radii, strict=True))
        packed = _PackedPolygons(
            **{f.name: np.ascontiguousarray(getattr(scene_packed, f.name)[order]) for f in fields(_PackedPolygons)}
        )
        return cls(
            packed=packed,
            order=order,
            object_bounds=np.array(object_bounds, dtype=np.int64),
            chunk_bounds=chunk_bounds,
            sphere_centers=np.array([c for c, _ in spheres]),
            sphere_radii=np.array([r for _, r in spheres]),
        )

    @property
    def normals(self) -> np.ndarray:
        """``(F, 3)`` unit normals of the scene's faces, in scene order."""
        out = np.empty_like(self.packed.normals)
        out[self.order] = self.packed.normals
        return out

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(N,)`` distances (NaN: no hit) and scene face indices (-1) of ``(N, 3)`` world-frame rays."""
        p = self.packed
        distances, hits = _cast_grouped_kernel(
            np.ascontiguousarray(origins, dtype=np.float64),
            np.ascontiguousarray(directions, dtype=np.float64),
            p.normals,
            p.offsets,
            p.edge_normals,
            p.edge_offsets,
            p.edge_counts,
            p.centers,
            p.radii,
            self.object_bounds,
            self.chunk_bounds,
            self.sphere_centers,
            self.sphere_radii,
            _INSIDE_TOLERANCE,
            _MIN_HIT_DISTANCE,
        )
        return distances, np.where(hits >= 0, self.order[np.maximum(hits, 0)], -1)


def cast_surface_rays(
    surface_scene: SurfaceScene, origins: np.ndarray, directions: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Cast ``(N, 3)`` world-frame rays (unit directions) against a surface scene.

    Returns:
        ``(distances (N,), labels (N,))`` as :func:`ppe_ros.core.synthetic.cast_rays` (NaN / 0 = no hit).
    """
    origins = np.ascontiguousarray(origins, dtype=np.float64)
    directions = np.ascontiguousarray(directions, dtype=np.float64)
    if origins.ndim != 2 or origins.shape[1] != 3 or directions.shape != origins.shape:
        raise ValueError(f'origins and directions must both be (N, 3); got {origins.shape} and {directions.shape}')
    if not (np.all(np.isfinite(origins)) and np.all(np.isfinite(directions))):
        raise ValueError('ray origins and directions must be finite')
    if not isinstance(surface_scene, SurfaceScene):
        raise ValueError(f'surface_scene must be a SurfaceScene; got {type(surface_scene).__name__}')
    distances, faces = _Caster.of(surface_scene).cast(origins, directions)
    labels = np.where(faces >= 0, surface_scene.scene.labels[np.maximum(faces, 0)], 0)
    return distances, labels


# --------------------------------------------------------------------------------------------
# Surface undulation
# --------------------------------------------------------------------------------------------


def _undulation_waves(
    surface_scene: SurfaceScene,
    normals: np.ndarray,
    amplitude: float,
    wavelengths: tuple[float, float],
    count: int,
    seed: int,
) -> dict[int, np.ndarray]:
    """Per planar surface ``(K, 5)`` waves (k vector in the surface's plane, phase, amplitude) with
    RMS height ``amplitude`` (metres), plus the scene's own ``shape_waves``. ``normals`` are the
    ``(F, 3)`` face normals in scene order."""
    rng = np.random.default_rng([seed, 3])
    labels = surface_scene.planar_labels()
    scene_labels = surface_scene.scene.labels
    first_face = {}
    for index, label in enumerate(scene_labels.tolist()):
        first_face.setdefault(label, index)
    surface_normals = normals[[first_face[int(label)] for label in labels]].reshape(-1, 3)
    helper = np.where((np.abs(surface_normals[:, 0]) < 0.9)[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    first = np.cross(surface_normals, helper)
    first /= np.linalg.norm(first, axis=1, keepdims=True)
    second = np.cross(surface_normals, first)
    angles = rng.uniform(0.0, 2 * np.pi, (len(labels), count))
    lengths = rng.uniform(wavelengths[0], wavelengths[1], (len(labels), count))
    phases = rng.uniform(0.0, 2 * np.pi, (len(labels), count))
    vectors = (2 * np.pi / lengths)[..., None] * (
        np.cos(angles)[..., None] * first[:, None, :] + np.sin(angles)[..., None] * second[:, None, :]
    )
    rows = np.concatenate(
        [vectors, phases[..., None], np.full((len(labels), count, 1), amplitude * math.sqrt(2.0 / count))], axis=2
    )
    waves: dict[int, np.ndarray] = {}
    for index, label in enumerate(labels.tolist()):
        if amplitude > 0.0:
            waves[label] = rows[index]
        if label in surface_scene.shape_waves:
            shape = np.asarray(surface_scene.shape_waves[label], dtype=np.float64)
            waves[label] = np.vstack([waves[label], shape]) if label in waves else shape
    return waves


def _surface_heights(points: np.ndarray, labels: np.ndarray, waves: dict[int, np.ndarray]) -> np.ndarray:
    """Height (metres, along the surface normal) of the undulation at world ``points`` ``(N, 3)``."""
    if not waves or not len(points):
        return np.zeros(len(points))
    keys = np.array(sorted(waves), dtype=np.int64)
    count = max(len(rows) for rows in waves.values())
    table = np.zeros((len(keys) + 1, count, 5))  # the last row: no waves
    for row, key in enumerate(keys):
        table[row, : len(waves[int(key)])] = waves[int(key)]
    position = np.searchsorted(keys, labels)
    known = (position < len(keys)) & (keys[np.minimum(position, len(keys) - 1)] == labels)
    rows = table[np.where(known, position, len(keys))]
    phase = np.einsum('nk,nwk->nw', points, rows[..., :3]) + rows[..., 3]
    return np.einsum('nw,nw->n', np.cos(phase), rows[..., 4])


def _displace_hits(
    origins: np.ndarray,
    directions: np.ndarray,
    distances: np.ndarray,
    labels: np.ndarray,
    normals: np.ndarray,
    waves: dict[int, np.ndarray],
    max_factor: float = 50.0,
) -> np.ndarray:
    """Distances to the undulating surfaces: the flat surface moved by ``h(x)`` along its normal
    towards the ray start, solved by three fixed-point steps ``t = t0 - h(x(t)) / |cos inc|``."""
    if not waves:
        return distances.copy()
    cos_inc = np.maximum(np.abs(np.einsum('ij,ij->i', normals, directions)), 1.0 / max_factor)
    towards = -np.sign(np.einsum('ij,ij->i', normals, directions))
    towards[towards == 0.0] = 1.0
    result = distances.copy()
    for _ in range(3):
        points = origins + directions * result[:, None]
        result = distances - towards * _surface_heights(points, labels, waves) / cos_inc
    return result


# --------------------------------------------------------------------------------------------
# Scans
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SensorScan(SyntheticScan):
    """A generated scan with realistic sensor errors and per-surface ground truth.

    As :class:`~ppe_ros.core.synthetic.SyntheticScan`, except:

    * ``labels``: one label (>= 10) per visible planar *surface*, even when an occluder cuts it into
      pieces; :data:`CLUTTER_LABEL` on clutter, ``UNLABELLED_LABEL`` (3) on surfaces with fewer than
      ``min_surface_pixels`` pixels, 0 = no return. ``region_faces`` is empty (labels are the scene's).
    * ``face_labels``: the scene label hit by each ray, clutter included (0 = nothing hit). Rays
      that hit something but were dropped (dropouts, range limits) keep their face label here.
    * ``true_ranges``: distance from the ray start along the cast (true) ray to the *flat* surface;
      ``undulated_ranges`` to the undulating one (before noise and biases); for a depth camera
      ``true_depth`` is the flat surface's depth (optical z) of the cast ray, metres.
    * ``points`` are in ``frame`` (``'sensor'``: x forward, y left, z up; ``'camera'``: x right, y
      down, z forward); ``sensor_from_frame`` rotates them into the sensor frame of ``sensor_pose``.
    """

    clutter_labels: frozenset[int] = frozenset()
    surface_names: dict[int, str] = field(default_factory=dict)
    frame: str = 'sensor'
    sensor_from_frame: np.ndarray = field(default_factory=lambda: np.eye(3))
    undulated_ranges: np.ndarray | None = None
    true_depth: np.ndarray | None = None
    intrinsics: tuple[float, float, float, float] | None = None

    def connected_labels(self, min_piece_pixels: int = 1) -> tuple[np.ndarray, dict[int, int]]:
        """Ground truth by 4-connected pieces (SynPEB's convention) instead of surfaces.

        Returns:
            ``(regions, region_surfaces)``: an ``(H, W)`` label image whose labels >= 10 are the
            4-connected pieces of the planar surfaces (numbered as
            :func:`ppe_ros.core.synthetic.label_regions` does), pieces smaller than
            ``min_piece_pixels`` and all other visible pixels ``< 10`` (clutter stays
            :data:`CLUTTER_LABEL`), and region label -> surface label.
        """
        planar = np.where(self.labels >= FIRST_LABEL, self.labels, 0)
        regions, region_surfaces = label_regions(planar, min_region_pixels=int(min_piece_pixels))
        regions = np.where(planar > 0, regions, self.labels)
        return regions, region_surfaces

    def plane_of_label(self, label: int) -> tuple[np.ndarray, float]:
        """``(normal, offset)`` of a surface's plane in the frame of ``points``: ``normal . x = offset``,
        the normal facing the sensor (``offset <= 0``)."""
        face = self.face_of_label(label)
        vertices = self.sensor_pose.world_to_sensor(face.vertices) @ self.sensor_from_frame
        normal = _newell_normal(vertices)
        offset = float(normal @ vertices.mean(axis=0))
        if offset > 0.0:
            normal, offset = -normal, -offset
        return normal, offset


def _ground_truth(
    face_labels: np.ndarray, returned: np.ndarray, clutter: frozenset[int], min_surface_pixels: int
) -> np.ndarray:
    labels = np.where(returned, face_labels, 0).astype(np.int64)
    if clutter:
        labels[np.isin(labels, np.fromiter(clutter, dtype=np.int64))] = CLUTTER_LABEL
    values, counts = np.unique(labels[labels >= FIRST_LABEL], return_counts=True)
    small = values[counts < min_surface_pixels]
    if small.size:
        labels[np.isin(labels, small)] = UNLABELLED_LABEL
    return labels


def _check_count(value, name: str, lowest: int = 1) -> int:
    if isinstance(value, bool) or int(value) != value or value < lowest:
        raise ValueError(f'{name} must be an integer >= {lowest}; got {value!r}')
    return int(value)


def lidar_grid(model: str = 'os1-128', cols: int = DEFAULT_LIDAR_COLUMNS) -> ScanGrid:
    """The destaggered grid of a spinning lidar: rows = the model's beam elevations (top first),
    column j at azimuth ``-360 j / cols`` degrees (Ouster's column order).

    Raises:
        ValueError: unknown model (see :data:`LIDAR_MODELS`) or cols < 2.
    """
    if model not in LIDAR_MODELS:
        raise ValueError(f'unknown lidar model {model!r}; known: {", ".join(LIDAR_MODELS)}')
    cols = _check_count(cols, 'cols', 2)
    return ScanGrid(elevation_deg=np.array(LIDAR_MODELS[model]), azimuth_deg=-360.0 * np.arange(cols) / cols)


def default_min_surface_pixels(rows: int, cols: int, *, reference_pixels: int = 128 * 1024) -> int:
    """Smallest visible surface (pixels) that is a ground-truth plane: 50 on a 128 x 1024 lidar
    image (or 50 per ``reference_pixels``), scaled with the pixel count, at least 10."""
    return max(10, round(50 * rows * cols / reference_pixels))


def _cast_undulated(scene, world_starts, world_directions, errors, seed):
    """Cast rays (world frame) and displace each hit along its face's normal by the face's undulation.

    Returns (distances to the flat faces (NaN: no hit), hit mask, scene label of each hit (0: none),
    the hit faces' normals, distances to the undulating surfaces (NaN: no hit)).
    """
    caster = _Caster.of(scene)
    distances, faces = caster.cast(world_starts, world_directions)
    hit = faces >= 0
    face_labels = np.where(hit, scene.scene.labels[np.maximum(faces, 0)], 0)
    normals = caster.normals[np.maximum(faces, 0)]
    waves = _undulation_waves(
        scene,
        caster.normals,
        errors.surface_amplitude,
        (errors.surface_wavelength_min, errors.surface_wavelength_max),
        int(errors.surface_waves),
        seed,
    )
    undulated = np.full(distances.shape, np.nan)
    undulated[hit] = _displace_hits(
        world_starts[hit], world_directions[hit], distances[hit], face_labels[hit], normals[hit], waves
    )
    return distances, hit, face_labels, normals, undulated


def _lidar_scan_inputs(scene, seed, model, cols, grid, sensor_pose, errors):
    """The checked ``(errors, grid, scene, pose)`` of :func:`generate_lidar_scan`, defaults filled in."""
    errors = LidarErrorModel() if errors is None else errors
    if not isinstance(errors, LidarErrorModel):
        raise ValueError(f'errors must be a LidarErrorModel; got {type(errors).__name__}')
    grid = lidar_grid(model, cols) if grid is None else grid
    if not isinstance(grid, ScanGrid):
        raise ValueError(f'grid must be a ScanGrid; got {type(grid).__name__}')
    if scene is None:
        scene = make_street_scene(seed)
    elif not isinstance(scene, SurfaceScene):
        raise ValueError(f'scene must be a SurfaceScene or None; got {type(scene).__name__}')
    pose = street_sensor_pose(seed) if sensor_pose is None else sensor_pose
    if not isinstance(pose, SensorPose):
        raise ValueError(f'sensor_pose must be a SensorPose; got {type(pose).__name__}')
    return errors, grid, scene, pose


def _lidar_returns(errors, cos_inc, dropout_draw, hit, true_ranges, measured):
    """Which beams return: hit within range, and not dropped (at random, more at grazing incidence).

    ``cos_inc``, ``dropout_draw``, ``true_ranges`` and ``measured`` are ``(H, W)``; ``hit`` is flat.
    """
    incidence_deg = np.degrees(np.arccos(np.clip(cos_inc, 0.0, 1.0)))
    if errors.grazing_dropout_width_deg > 0.0:
        z = (incidence_deg - errors.grazing_dropout_deg) / errors.grazing_dropout_width_deg
        grazing_probability = 1.0 / (1.0 + np.exp(-np.clip(z, -50.0, 50.0)))
    else:
        grazing_probability = (incidence_deg > errors.grazing_dropout_deg).astype(np.float64)
    drop_probability = 1.0 - (1.0 - grazing_probability) * (1.0 - errors.dropout_rate)
    return (
        hit.reshape(true_ranges.shape)
        & (dropout_draw >= drop_probability)
        & (true_ranges <= errors.max_range)
        & (measured >= errors.min_range)
    )


def generate_lidar_scan(
    scene: SurfaceScene | None = None,
    *,
    seed: int = 0,
    model: str = 'os1-128',
    cols: int = DEFAULT_LIDAR_COLUMNS,
    grid: ScanGrid | None = None,
    sensor_pose: SensorPose | None = None,
    errors: LidarErrorModel | None = None,
    sensor_seed: int | None = None,
    noise_seed: int | None = None,
    min_surface_pixels: int | None = None,
) -> SensorScan:
    """A spinning-lidar sweep (Ouster OS-1 like) of ``scene`` (default ``make_street_scene(seed)``).

    Args:
        scene: the surfaces (world frame); None builds :func:`make_street_scene` from ``seed``.
        seed: non-negative integer; the scene (if built), pose (if not given) and noise are deterministic in it.
        model: beam layout of :data:`LIDAR_MODELS` (``'os1-128'``, ``'os1-32'``, ``'vlp16'``, ``'hdl32'``,
            ``'hdl64'``), with ``cols`` columns; ignored when ``grid`` is given.
        grid: any spherical grid instead (rows = beams).
        sensor_pose: pose in the world frame; default :func:`street_sensor_pose` (``seed``).
        errors: the error model; default :class:`LidarErrorModel` (realistic); ``LidarErrorModel.exact()``
            for exact geometry.
        sensor_seed: seed of the per-beam calibration errors (default ``seed``).
        noise_seed: seed of the per-scan noise and dropouts (default ``seed``).
        min_surface_pixels: surfaces with fewer visible pixels get label 3 (default
            :func:`default_min_surface_pixels`).

    Returns:
        A :class:`SensorScan`: ``points`` ``(H, W, 3)`` in the sensor frame (NaN = no return),
        ``origins`` the beam starts, ``params`` with the drawn ``beam_range_bias`` (m) and
        ``beam_elevation_error_deg`` per row.
    """
    seed = _check_seed(seed)
    sensor_seed = seed if sensor_seed is None else _check_seed(sensor_seed)
    noise_seed = seed if noise_seed is None else _check_seed(noise_seed)
    custom_grid = grid
    errors, grid, scene, pose = _lidar_scan_inputs(scene, seed, model, cols, grid, sensor_pose, errors)
    height, width = grid.shape
    min_pixels = (
        default_min_surface_pixels(height, width)
        if min_surface_pixels is None
        else _check_count(min_surface_pixels, 'min_surface_pixels')
    )

    calibration = np.random.default_rng([sensor_seed, 4])
    beam_bias = errors.beam_range_bias_sigma * calibration.standard_normal(height)
    beam_elevation_error = errors.beam_elevation_sigma_deg * calibration.standard_normal(height)
    rng = np.random.default_rng([noise_seed, 2])
    range_noise = rng.standard_normal((height, width))
    dropout_draw = rng.random((height, width))

    starts = beam_offset_origins(grid, errors.beam_origin_radius)
    nominal = grid.directions()
    true_grid = ScanGrid(elevation_deg=grid.elevation_deg + beam_elevation_error, azimuth_deg=grid.azimuth_deg)
    cast = true_grid.directions()
    rotation = pose.rotation()
    world_starts = starts.reshape(-1, 3) @ rotation.T + np.asarray(pose.position)
    world_directions = cast.reshape(-1, 3) @ rotation.T
    distances, hit, face_labels, normals, undulated = _cast_undulated(
        scene, world_starts, world_directions, errors, seed
    )
    cos_inc = np.abs(np.einsum('ij,ij->i', normals, world_directions))
    sigma = errors.sigma(cos_inc).reshape(height, width)
    measured = undulated.reshape(height, width) + beam_bias[:, None] + sigma * range_noise
    true_ranges = distances.reshape(height, width)
    returned = _lidar_returns(errors, cos_inc.reshape(height, width), dropout_draw, hit, true_ranges, measured)
    measured = np.where(returned, measured, np.nan)
    points = starts + nominal * measured[..., None]
    face_image = face_labels.reshape(height, width).astype(np.int64)
    labels = _ground_truth(face_image, returned, scene.clutter_labels, min_pixels)
    params = {
        'generator': 'lidar',
        'seed': seed,
        'sensor_seed': sensor_seed,
        'noise_seed': noise_seed,
        'model': model if custom_grid is None else 'custom grid',
        'rows': height,
        'cols': width,
        'errors': errors.to_dict(),
        'beam_range_bias': beam_bias.tolist(),
        'beam_elevation_error_deg': beam_elevation_error.tolist(),
        'sensor_pose': pose.to_dict(),
        'min_surface_pixels': min_pixels,
        'n_faces': len(scene.scene.faces),
        'n_surfaces': len(np.unique(labels[labels >= FIRST_LABEL])),
        'scene': scene.description,
    }
    return SensorScan(
        points=points,
        labels=labels,
        origins=starts,
        scene=scene.scene,
        grid=grid,
        params=params,
        sensor_pose=pose,
        true_ranges=true_ranges,
        face_labels=face_image,
        region_faces={},
        clutter_labels=scene.clutter_labels,
        surface_names=dict(scene.names),
        frame='sensor',
        undulated_ranges=undulated.reshape(height, width),
    )


def generate_lidar_sequence(
    seed: int = 0,
    n_sweeps: int = 3,
    *,
    step: float = 0.23,
    model: str = 'os1-128',
    cols: int = DEFAULT_LIDAR_COLUMNS,
    errors: LidarErrorModel | None = None,
    first_pose: SensorPose | None = None,
) -> list[SensorScan]:
    """Consecutive sweeps of one lidar driving through one street (like the shared OS-1-128 sweeps
    1795-1797, 0.23 m apart): the scene, its undulation and the sensor's calibration errors are
    those of ``seed``; sweep k is taken ``k * step`` metres further along the first pose's heading
    with its own noise (``noise_seed = seed + 10**7 k``: sweep 0 is ``generate_lidar_scan(seed=seed)``).
    ``scan.sensor_pose`` holds each pose, so the true motion between sweeps is known.
    """
    seed = _check_seed(seed)
    n_sweeps = _check_count(n_sweeps, 'n_sweeps')
    if not math.isfinite(step):
        raise ValueError(f'step must be finite (metres); got {step}')
    scene = make_street_scene(seed)
    pose = street_sensor_pose(seed) if first_pose is None else first_pose
    heading = np.array([math.cos(math.radians(pose.yaw_deg)), math.sin(math.radians(pose.yaw_deg)), 0.0])
    sweeps = []
    for k in range(n_sweeps):
        moved = SensorPose(
            position=tuple(np.asarray(pose.position) + k * step * heading),
            roll_deg=pose.roll_deg,
            pitch_deg=pose.pitch_deg,
            yaw_deg=pose.yaw_deg,
        )
        sweeps.append(
            generate_lidar_scan(
                scene,
                seed=seed,
                model=model,
                cols=cols,
                sensor_pose=moved,
                errors=errors,
                sensor_seed=seed,
                noise_seed=seed + 10**7 * k,
            )
        )
    return sweeps


KINECT_INTRINSICS = (575.0, 575.0, 319.5, 239.5)
"""``(fx, fy, cx, cy)`` in pixels of a Kinect v1 depth camera at 640 x 480 (f about 575 px)."""

# Optical frame (x right, y down, z forward) -> sensor frame (x forward, y left, z up).
_SENSOR_FROM_CAMERA = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _check_depth_setup(
    scene, seed, width, height, intrinsics, sensor_pose, errors, sensor_seed, noise_seed, min_surface_pixels
):
    """Validated set-up of :func:`generate_depth_scan` with the defaults filled in.

    Returns ``(scene, (seed, sensor_seed, noise_seed), errors, (width, height), (fx, fy, cx, cy) in
    pixels, pose, min_pixels)``; builds the indoor scene (world frame) when ``scene`` is None.
    """
    seed = _check_seed(seed)
    sensor_seed = seed if sensor_seed is None else _check_seed(sensor_seed)
    noise_seed = seed if noise_seed is None else _check_seed(noise_seed)
    errors = DepthErrorModel() if errors is None else errors
    if not isinstance(errors, DepthErrorModel):
        raise ValueError(f'errors must be a DepthErrorModel; got {type(errors).__name__}')
    width, height = _check_count(width, 'width', 2), _check_count(height, 'height', 2)
    if intrinsics is None:
        scale = width / KINECT_WIDTH
        fx, fy = KINECT_INTRINSICS[0] * scale, KINECT_INTRINSICS[1] * scale
        cx, cy = (width - 1) / 2, (height - 1) / 2
    else:
        fx, fy, cx, cy = (float(v) for v in intrinsics)
        if not (fx > 0 and fy > 0 and all(math.isfinite(v) for v in (cx, cy))):
            raise ValueError(f'intrinsics must be (fx > 0, fy > 0, cx, cy) in pixels; got {intrinsics}')
    pose = DEFAULT_SENSOR_POSE if sensor_pose is None else sensor_pose
    if not isinstance(pose, SensorPose):
        raise ValueError(f'sensor_pose must be a SensorPose; got {type(pose).__name__}')
    if scene is None:
        scene = make_indoor_scene(seed, sensor_pose=pose)
    elif not isinstance(scene, SurfaceScene):
        raise ValueError(f'scene must be a SurfaceScene or None; got {type(scene).__name__}')
    min_pixels = (
        default_min_surface_pixels(height, width, reference_pixels=500 * 500)
        if min_surface_pixels is None
        else _check_count(min_surface_pixels, 'min_surface_pixels')
    )
    return scene, (seed, sensor_seed, noise_seed), errors, (width, height), (fx, fy, cx, cy), pose, min_pixels


def _pixel_rays(
    intrinsics: tuple[float, float, float, float], lateral: np.ndarray, lateral_sigma_px: float
) -> np.ndarray:
    """``(H, W, 3)`` unit ray directions in the optical frame through the pixels, each pixel position
    jittered by ``lateral_sigma_px`` times the standard normal draws ``lateral`` ``(H, W, 2)`` (u, v)."""
    fx, fy, cx, cy = intrinsics
    height, width = lateral.shape[:2]
    u = np.arange(width, dtype=np.float64)[None, :] + lateral_sigma_px * lateral[..., 0]
    v = np.arange(height, dtype=np.float64)[:, None] + lateral_sigma_px * lateral[..., 1]
    rays = np.stack(np.broadcast_arrays((u - cx) / fx, (v - cy) / fy, np.ones((height, width))), axis=-1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    return rays


def _projector_shadow(
    scene: SurfaceScene,
    projector_offset: float,
    position: np.ndarray,
    rotation: np.ndarray,
    world_starts: np.ndarray,
    world_directions: np.ndarray,
    distances: np.ndarray,
    hit: np.ndarray,
) -> np.ndarray:
    """Flat bool mask of the hits the projector (``projector_offset`` metres along the camera's
    optical x axis) does not see: the ray from the projector to the hit point is blocked first."""
    shadowed = np.zeros(hit.shape, dtype=bool)
    if projector_offset > 0.0 and hit.any():
        projector = position + rotation @ np.array([projector_offset, 0.0, 0.0])
        targets = world_starts[hit] + world_directions[hit] * distances[hit, None]
        towards = targets - projector
        length = np.linalg.norm(towards, axis=1)
        blocked, _ = _Caster.of(scene).cast(np.broadcast_to(projector, towards.shape), towards / length[:, None])
        shadowed[np.flatnonzero(hit)] = blocked < length - np.maximum(1e-3, 1e-4 * length)
    return shadowed


def _disparity_depth(
    depth: np.ndarray,
    errors: DepthErrorModel,
    principal_point: tuple[float, float],
    band_phase: float,
    sigma_d: float,
    disparity_noise: np.ndarray,
) -> np.ndarray:
    """``(H, W)`` measured depth (metres; non-finite where the disparity is not usable) from the
    depth of the undulated surfaces: low-frequency distortion (fixed per sensor), then disparity
    noise (``sigma_d`` px times the standard normal draws) and quantisation."""
    cx, cy = principal_point
    height, width = depth.shape
    uu = np.arange(width, dtype=np.float64)[None, :]
    vv = np.arange(height, dtype=np.float64)[:, None]
    rho2 = ((uu - cx) ** 2 + (vv - cy) ** 2) / (cx**2 + cy**2)
    pattern = errors.radial_weight * (rho2 - 0.5) + errors.band_weight * np.cos(
        2 * np.pi * uu / errors.band_period_px + band_phase
    )
    distorted = depth + errors.distortion_coefficient * depth**2 * pattern
    focal_baseline = errors.focal_px * errors.baseline
    with np.errstate(divide='ignore', invalid='ignore'):
        disparity = focal_baseline / distorted + sigma_d * disparity_noise
        if errors.disparity_step_px > 0.0:
            disparity = np.round(disparity / errors.disparity_step_px) * errors.disparity_step_px
        measured = focal_baseline / disparity
    return measured


def _depth_edges(true_depth: np.ndarray, edge_draw: np.ndarray, errors: DepthErrorModel) -> np.ndarray:
    """``(H, W)`` bool mask of the depth-edge dropouts: pixels next to a jump of the true depth by more
    than ``edge_jump_fraction`` of the nearer depth, each dropped with ``edge_dropout_probability``
    (``edge_draw``: uniform draws in [0, 1))."""
    edge = np.zeros(true_depth.shape, dtype=bool)
    if errors.edge_dropout_probability > 0.0:
        filled = np.where(np.isfinite(true_depth), true_depth, np.inf)
        for axis in (0, 1):
            jump = np.abs(np.diff(filled, axis=axis))
            limit = errors.edge_jump_fraction * np.minimum(
                np.take(filled, range(filled.shape[axis] - 1), axis=axis),
                np.take(filled, range(1, filled.shape[axis]), axis=axis),
            )
            big = ~(jump <= limit)
            if axis == 0:
                edge[:-1] |= big
                edge[1:] |= big
            else:
                edge[:, :-1] |= big
                edge[:, 1:] |= big
        edge &= edge_draw < errors.edge_dropout_probability
    return edge


def _camera_points(measured: np.ndarray, intrinsics: tuple[float, float, float, float]) -> np.ndarray:
    """``(H, W, 3)`` points in the optical frame (metres) of the measured depth along the nominal pixel rays."""
    fx, fy, cx, cy = intrinsics
    height, width = measured.shape
    cols_ray = (np.arange(width, dtype=np.float64) - cx) / fx
    rows_ray = (np.arange(height, dtype=np.float64) - cy) / fy
    return np.stack(np.broadcast_arrays(measured * cols_ray[None, :], measured * rows_ray[:, None], measured), -1)


def generate_depth_scan(
    scene: SurfaceScene | None = None,
    *,
    seed: int = 0,
    width: int = KINECT_WIDTH,
    height: int = KINECT_HEIGHT,
    intrinsics: tuple[float, float, float, float] | None = None,
    sensor_pose: SensorPose | None = None,
    errors: DepthErrorModel | None = None,
    sensor_seed: int | None = None,
    noise_seed: int | None = None,
    min_surface_pixels: int | None = None,
) -> SensorScan:
    """A Kinect-v1-like depth frame (pinhole, 640 x 480, f 575 px) of ``scene`` (default: :func:`make_indoor_scene`).

    Args:
        scene: the surfaces (world frame); None builds :func:`make_indoor_scene` from ``seed`` for the pose.
        seed: non-negative integer; scene (if built) and noise are deterministic in it.
        width, height: image size in pixels; intrinsics ``(fx, fy, cx, cy)`` in pixels (default
            :data:`KINECT_INTRINSICS` scaled to the size).
        sensor_pose: camera pose: the camera looks along the pose's x axis (optical z = sensor x,
            optical x = -sensor y, optical y = -sensor z); default :data:`~ppe_ros.core.synthetic.DEFAULT_SENSOR_POSE`.
        errors: default :class:`DepthErrorModel` (Kinect v1); ``DepthErrorModel.exact()`` for exact depth.
        sensor_seed: seed of the camera's fixed distortion pattern (default ``seed``).
        noise_seed: seed of the per-frame noise and dropouts (default ``seed``).
        min_surface_pixels: surfaces with fewer visible pixels get label 3 (default: 50 per 500 x 500 pixels).

    Returns:
        A :class:`SensorScan` with ``points`` in the optical frame (``frame='camera'``), ``origins``
        None (every ray starts at the camera centre), ``intrinsics`` and ``true_depth`` set.
    """
    scene, (seed, sensor_seed, noise_seed), errors, (width, height), (fx, fy, cx, cy), pose, min_pixels = (
        _check_depth_setup(
            scene, seed, width, height, intrinsics, sensor_pose, errors, sensor_seed, noise_seed, min_surface_pixels
        )
    )
    sigma_d = errors.disparity_sigma() if errors.axial_noise_coefficient > 0 else 0.0

    rng = np.random.default_rng([noise_seed, 2])
    lateral = rng.standard_normal((height, width, 2))
    disparity_noise = rng.standard_normal((height, width))
    dropout_draw = rng.random((height, width))
    edge_draw = rng.random((height, width))
    calibration = np.random.default_rng([sensor_seed, 4])
    band_phase = float(calibration.uniform(0.0, 2 * np.pi))

    rays = _pixel_rays((fx, fy, cx, cy), lateral, errors.lateral_sigma_px)
    rotation = pose.rotation() @ _SENSOR_FROM_CAMERA  # camera -> world
    position = np.asarray(pose.position)
    world_directions = rays.reshape(-1, 3) @ rotation.T
    world_starts = np.broadcast_to(position, world_directions.shape)
    distances, hit, face_labels, _, undulated = _cast_undulated(scene, world_starts, world_directions, errors, seed)
    ray_z = rays[..., 2]
    true_depth = distances.reshape(height, width) * ray_z
    depth = undulated.reshape(height, width) * ray_z

    # The error model: projector shadow, distorted and noisy disparity, then the dropouts (next to
    # a jump of the true depth, at random) and the range limits.
    shadowed = _projector_shadow(
        scene, errors.projector_offset, position, rotation, world_starts, world_directions, distances, hit
    ).reshape(height, width)
    measured = _disparity_depth(depth, errors, (cx, cy), band_phase, sigma_d, disparity_noise)
    edge = _depth_edges(true_depth, edge_draw, errors)
    returned = (
        hit.reshape(height, width)
        & ~shadowed
        & ~edge
        & (dropout_draw >= errors.dropout_rate)
        & np.isfinite(measured)
        & (measured >= errors.min_depth)
        & (measured <= errors.max_depth)
        & (true_depth <= errors.max_depth)
    )
    measured = np.where(returned, measured, np.nan)
    points = _camera_points(measured, (fx, fy, cx, cy))
    face_image = face_labels.reshape(height, width).astype(np.int64)
    labels = _ground_truth(face_image, returned, scene.clutter_labels, min_pixels)
    params = {
        'generator': 'depth_camera',
        'seed': seed,
        'sensor_seed': sensor_seed,
        'noise_seed': noise_seed,
        'rows': height,
        'cols': width,
        'intrinsics': [fx, fy, cx, cy],
        'errors': errors.to_dict(),
        'disparity_sigma_px': sigma_d,
        'distortion_band_phase': band_phase,
        'sensor_pose': pose.to_dict(),
        'min_surface_pixels': min_pixels,
        'n_faces': len(scene.scene.faces),
        'n_surfaces': len(np.unique(labels[labels >= FIRST_LABEL])),
        'scene': scene.description,
    }
    scan = SensorScan(
        points=points,
        labels=labels,
        origins=None,
        scene=scene.scene,
        grid=None,
        params=params,
        sensor_pose=pose,
        true_ranges=distances.reshape(height, width),
        face_labels=face_image,
        region_faces={},
        clutter_labels=scene.clutter_labels,
        surface_names=dict(scene.names),
        frame='camera',
        sensor_from_frame=_SENSOR_FROM_CAMERA.copy(),
        undulated_ranges=undulated.reshape(height, width),
        true_depth=true_depth,
        intrinsics=(fx, fy, cx, cy),
    )
    return scan
