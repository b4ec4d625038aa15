"""One frame, one code path: PointCloud2 in, planes and three output messages out.

Used by the live node (:mod:`ppe_ros.ros.node`) and the offline bag tool alike. Nothing here
imports rclpy: the message classes come in through :class:`ppe_ros.ros.messages.MessageTypes`
(rclpy's generated classes or a rosbags typestore's).

Outputs, each with the input header (stamp and frame_id; all coordinates in that frame, metres):

* labelled cloud (``planes/labeled_points``): the input's ``height x width``, fields ``x y z``
  (float32), ``label`` (uint32, 0 = no plane, planes 1..J) and ``rgb`` (float32-packed
  ``0x00RRGGBB``, a stable colour per label);
* markers (``planes/markers``): CDR bytes of a ``visualization_msgs/MarkerArray``
  (see :mod:`ppe_ros.ros.markers`);
* plane table (``planes``): a PointCloud2 with height 1 and one point per plane, fields
  :data:`PLANE_TABLE_FIELDS`.
"""

from __future__ import annotations

import dataclasses
import math
import re
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ppe_ros.core.planes import PlaneSet
from ppe_ros.ros.depth_image import DepthFrame, DepthImageError, depth_image_points, depth_image_size
from ppe_ros.ros.markers import budgeted_plane_geometry, marker_array_cdr
from ppe_ros.ros.messages import MessageTypes, StampedFrame
from ppe_ros.ros.pointcloud2 import (
    FLOAT32,
    PointCloudError,
    label_colors,
    pointcloud2_beams,
    pointcloud2_to_xyz,
    structured_to_pointcloud2,
    xyz_to_pointcloud2,
)

# --------------------------------------------------------------------------------------------
# parameters
# --------------------------------------------------------------------------------------------

RELIABILITY_CHOICES = ('best_effort', 'reliable')
#: Values of the sensor parameter ('none': no profile).
SENSOR_CHOICES = ('none', 'lidar', 'depth_camera', 'paper')

#: Values of the layout parameter: how an organized cloud's grid holds the beams.
LAYOUT_CHOICES = ('auto', 'rows_are_beams', 'columns_are_beams')
#: Values of the unorganized_rows parameter (ppe_ros.core.projection.ROW_METHODS).
UNORGANIZED_ROWS_CHOICES = ('auto', 'rings', 'elevation', 'angular_grid')

#: ROS parameters every node has or that configure QoS; a params file may contain them.
ROS_BUILTIN_PARAMETERS = ('use_sim_time', 'start_type_description_service')


@dataclass(frozen=True)
class ParamSpec:
    """A node parameter: its ROS type, default, description and allowed values.

    ``kind`` is one of ``'double'``, ``'integer'``, ``'bool'``, ``'string'``, ``'double_array'``.
    ``low``/``high`` bound numbers (inclusive; ``low_exclusive`` makes the lower bound strict);
    ``choices`` lists the allowed strings; ``length`` fixes an array's length.
    """

    name: str
    kind: str
    default: Any
    description: str
    low: float | None = None
    high: float | None = None
    low_exclusive: bool = False
    choices: tuple[str, ...] = ()
    length: int | None = None
    read_only: bool = False

    def constraints(self) -> str:
        """Human-readable allowed values (for the descriptor and error messages)."""
        if self.choices:
            return 'one of ' + ', '.join(repr(c) for c in self.choices)
        if self.length is not None:
            return f'{self.length} finite numbers'
        if self.low is not None and self.high is not None:
            left = '(' if self.low_exclusive else '['
            return f'in {left}{self.low}, {self.high}]'
        return ''

    def validate(self, value: Any) -> Any:
        """Return ``value`` normalized (tuple for arrays), or raise ValueError saying what is wrong."""
        name = self.name
        if self.kind == 'bool':
            if not isinstance(value, bool | np.bool_):
                raise ValueError(f'{name} must be true or false; got {value!r}')
            return bool(value)
        if self.kind == 'string':
            if not isinstance(value, str) or (self.choices and value not in self.choices):
                raise ValueError(f'{name} must be {self.constraints()}; got {value!r}')
            return value
        if self.kind == 'double_array':
            if isinstance(value, str | bytes) or not hasattr(value, '__len__'):
                raise ValueError(f'{name} must be a list of {self.constraints()}; got {value!r}')
            items = list(value)
            if (
                len(items) != self.length
                or any(isinstance(v, bool) for v in items)
                or not all(isinstance(v, int | float | np.number) and math.isfinite(v) for v in items)
            ):
                raise ValueError(f'{name} must be a list of {self.constraints()} (x y z, m); got {value!r}')
            return tuple(float(v) for v in items)
        if self.kind == 'integer':
            if isinstance(value, bool) or not isinstance(value, int | np.integer):
                raise ValueError(f'{name} must be an integer; got {value!r}')
            number = int(value)
        else:  # double (integers are accepted and converted, as the node does)
            if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
                raise ValueError(f'{name} must be a number; got {value!r}')
            number = float(value)
            if math.isnan(number):
                raise ValueError(f'{name} must be a number; got nan')
        too_low = self.low is not None and (number <= self.low if self.low_exclusive else number < self.low)
        too_high = self.high is not None and number > self.high
        if too_low or too_high:
            raise ValueError(f'{name} must be {self.constraints()}; got {value!r}')
        return number


#: Every parameter of the extractor node, in the order of config/extractor.yaml.
PARAM_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec(
        'max_error_increment',
        'double',
        0.0,
        "PPE's threshold e: stop before the first action whose error increment exceeds it (m^2 with sensor "
        "none, else in units of the profile's noise variance); 0 = the sensor profile's",
        low=0.0,
        high=1.0e6,
    ),
    ParamSpec(
        'max_planes',
        'integer',
        0,
        'stop once at most this many planes (atomic rays included) remain; 0 = no limit',
        low=0,
        high=2**31 - 1,
    ),
    ParamSpec(
        'max_neighbor_distance',
        'double',
        0.0,
        'largest distance (m) between neighbouring points that may join one plane; .inf = no limit; '
        "0 = the sensor profile's",
        low=0.0,
        high=math.inf,
    ),
    ParamSpec(
        'min_plane_points',
        'integer',
        0,
        "planes with fewer points are reported as no plane (label 0); 0 = the sensor profile's",
        low=0,
        high=2**31 - 1,
    ),
    ParamSpec(
        'sensor',
        'string',
        'none',
        "sensor profile: none (the paper's model with the parameters above), lidar or depth_camera (a noise "
        "model and whole surfaces; e and lmax are then the profile's, see docs/algorithm.md), or paper",
        choices=SENSOR_CHOICES,
    ),
    ParamSpec(
        'surface_tolerance',
        'double',
        0.0,
        "with a sensor profile: RMS deviation (m) one physical surface may show from its plane; 0 = the profile's",
        low=0.0,
        high=10.0,
    ),
    ParamSpec(
        'range_noise',
        'double',
        0.0,
        "with a sensor profile: its noise model's range noise (m) at short range, the model's constant term "
        "(lidar 0.02, depth_camera 0.001: its floor); 0 = the profile's",
        low=0.0,
        high=1.0,
    ),
    ParamSpec(
        'ray_origin',
        'double_array',
        (0.0, 0.0, 0.0),
        'start point x y z (m) of every ray, in the frame of the input cloud',
        length=3,
    ),
    ParamSpec(
        'max_points',
        'integer',
        2_000_000,
        'clouds with more points (height x width) are skipped with a warning',
        low=1,
        high=2**31 - 1,
    ),
    ParamSpec(
        'input_reliability',
        'string',
        'best_effort',
        'QoS reliability of the input subscription (best_effort matches every publisher)',
        choices=RELIABILITY_CHOICES,
    ),
    ParamSpec('publish_labeled_points', 'bool', True, 'publish planes/labeled_points'),
    ParamSpec('publish_markers', 'bool', True, 'publish planes/markers'),
    ParamSpec('publish_plane_table', 'bool', True, 'publish planes (the per-plane table)'),
    ParamSpec(
        'marker_alpha',
        'double',
        0.5,
        'opacity of the plane meshes in RViz (0 = invisible, 1 = opaque)',
        low=0.0,
        high=1.0,
    ),
    ParamSpec(
        'marker_mesh_stride',
        'integer',
        1,
        'mesh every n-th row and column (n^2 fewer triangles for big clouds)',
        low=1,
        high=64,
    ),
    ParamSpec(
        'marker_max_triangles',
        'integer',
        150_000,
        'mesh budget per frame: the mesh stride grows (2, 3, ...) until all meshes together have at most '
        'this many triangles (72 bytes each); 0 = no limit',
        low=0,
        high=2**31 - 1,
    ),
    ParamSpec(
        'numba_threads',
        'integer',
        0,
        'threads of the extraction kernels per worker; 0 = the cores numba sees, shared out among the workers',
        low=0,
        high=1024,
    ),
    ParamSpec(
        'workers',
        'integer',
        1,
        'frames extracted at once, each in its own thread, outputs published in arrival order: more frames '
        'per second on a multi-core machine, no frame faster (the node only; ppe bag has --jobs)',
        low=1,
        high=64,
    ),
    ParamSpec(
        'process_without_subscribers',
        'bool',
        False,
        'extract frames even when no output has a subscriber (else the node idles: frames are counted, not extracted)',
    ),
    ParamSpec(
        'min_output_rate_fraction',
        'double',
        0.5,
        'diagnostics say WARN when the output rate falls below this fraction of the input rate; 0 = never',
        low=0.0,
        high=1.0,
    ),
    ParamSpec(
        'layout',
        'string',
        'auto',
        'organized clouds: rows_are_beams (Ouster), columns_are_beams (Velodyne and RoboSense organized: '
        'width = lasers), or auto (columns_are_beams when the ring field changes along the width)',
        choices=LAYOUT_CHOICES,
    ),
    ParamSpec(
        'unorganized_rows',
        'string',
        'auto',
        'clouds of height 1 are put on a range image with one row per: rings (the ring field), elevation '
        '(beams found in the elevation angles), angular_grid (a fixed grid, Livox); auto = rings with a ring '
        'field, angular_grid with a line field, else elevation',
        choices=UNORGANIZED_ROWS_CHOICES,
    ),
    ParamSpec(
        'azimuth_bins',
        'integer',
        0,
        'unorganized clouds: azimuth bins (columns) per revolution; 0 = estimated from the points',
        low=0,
        high=1_000_000,
    ),
    ParamSpec(
        'azimuth_start',
        'double',
        180.0,
        'unorganized clouds covering the full circle: azimuth (deg, counter-clockwise from x) where the range '
        'image starts (planes are cut there); 180 = behind the sensor',
        low=-360.0,
        high=360.0,
    ),
    ParamSpec(
        'angular_resolution',
        'double',
        0.8,
        'unorganized_rows angular_grid: cell size (deg) of the fixed grid',
        low=0.01,
        high=10.0,
    ),
    ParamSpec(
        'depth_image_transport',
        'string',
        'raw',
        "depth images: raw (sensor_msgs/Image on depth/image) or compressedDepth (image_transport's "
        'sensor_msgs/CompressedImage on depth/image/compressedDepth, png or rvl)',
        choices=('raw', 'compressedDepth'),
    ),
    ParamSpec(
        'depth_image_rectified',
        'bool',
        True,
        'depth images: true = rectified (pixels back-projected with the camera info P, its D ignored, as '
        'depth_image_proc does); false = raw, distorted (K and D: plumb_bob or rational_polynomial)',
    ),
    ParamSpec(
        'lost_point_tolerance',
        'double',
        0.0,
        "unorganized clouds: a point that lost its range-image cell to a nearer return gets the cell's plane "
        "within this distance (m) of it; 0 = the profile's surface_tolerance, or 0.05 m",
        low=0.0,
        high=10.0,
    ),
)
PARAM_SPEC_BY_NAME: dict[str, ParamSpec] = {spec.name: spec for spec in PARAM_SPECS}


@dataclass(frozen=True)
class ExtractorParams:
    """Validated settings of the extractor (node parameters of the same names; see :data:`PARAM_SPECS`).

    Construction validates every field and raises ValueError naming the parameter and the allowed
    values. Use :meth:`replace` for a changed copy and :meth:`from_yaml` for a ROS params file.
    """

    max_error_increment: float = 0.0
    max_planes: int = 0
    max_neighbor_distance: float = 0.0
    min_plane_points: int = 0
    sensor: str = 'none'
    surface_tolerance: float = 0.0
    range_noise: float = 0.0
    ray_origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    max_points: int = 2_000_000
    input_reliability: str = 'best_effort'
    publish_labeled_points: bool = True
    publish_markers: bool = True
    publish_plane_table: bool = True
    marker_alpha: float = 0.5
    marker_mesh_stride: int = 1
    marker_max_triangles: int = 150_000
    numba_threads: int = 0
    workers: int = 1
    process_without_subscribers: bool = False
    min_output_rate_fraction: float = 0.5
    layout: str = 'auto'
    unorganized_rows: str = 'auto'
    azimuth_bins: int = 0
    azimuth_start: float = 180.0
    angular_resolution: float = 0.8
    depth_image_transport: str = 'raw'
    depth_image_rectified: bool = True
    lost_point_tolerance: float = 0.0

    def __post_init__(self) -> None:
        for spec in PARAM_SPECS:
            object.__setattr__(self, spec.name, spec.validate(getattr(self, spec.name)))
        if self.range_noise > 0.0:
            from ppe_ros.core.sensor import sensor_profile

            if sensor_profile(self.sensor).noise is None:
                raise ValueError(
                    f'range_noise needs a sensor profile with a noise model (sensor lidar or depth_camera); sensor '
                    f'is {self.sensor}, whose model has none (set range_noise 0)'
                )

    def replace(self, **changes: Any) -> ExtractorParams:
        """A validated copy with some values changed."""
        unknown = sorted(set(changes) - set(PARAM_SPEC_BY_NAME))
        if unknown:
            raise ValueError(f'unknown extractor parameter(s) {unknown}; known: {sorted(PARAM_SPEC_BY_NAME)}')
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict[str, Any]:
        """Parameter name -> value (arrays as lists), the layout of ``ros__parameters``."""
        return {spec.name: list(v) if isinstance(v := getattr(self, spec.name), tuple) else v for spec in PARAM_SPECS}

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], *, source: str = 'parameters') -> ExtractorParams:
        """Validated params from a ``ros__parameters`` mapping; missing names keep their defaults."""
        if not isinstance(values, Mapping):
            raise ValueError(f'{source}: ros__parameters must be a mapping; got {type(values).__name__}')
        unknown = sorted(
            name
            for name in values
            if name not in PARAM_SPEC_BY_NAME
            and name not in ROS_BUILTIN_PARAMETERS
            and not str(name).startswith('qos_overrides')
        )
        if unknown:
            raise ValueError(f'{source}: unknown extractor parameter(s) {unknown}; known: {sorted(PARAM_SPEC_BY_NAME)}')
        try:
            return cls(**{name: value for name, value in values.items() if name in PARAM_SPEC_BY_NAME})
        except ValueError as exc:
            raise ValueError(f'{source}: {exc}') from None

    @classmethod
    def from_yaml(cls, path: str | Path, node_name: str = 'extractor') -> ExtractorParams:
        """Params from a ROS 2 params file (the file ``--ros-args --params-file`` takes).

        The file maps node names to ``ros__parameters``. Sections that apply, merged in this order
        (later wins, like ROS): ``/**``, then ``node_name``, ``/node_name`` or any ``/ns/node_name``.
        """
        import yaml

        path = Path(path)
        try:
            document = yaml.safe_load(path.read_text())
        except OSError as exc:
            raise ValueError(f'cannot read params file {path}: {exc.strerror or exc}') from None
        except yaml.YAMLError as exc:
            raise ValueError(f'params file {path} is not valid YAML: {exc}') from None
        if not isinstance(document, Mapping):
            raise ValueError(f'params file {path} must map node names to ros__parameters')
        bare = node_name.strip('/').split('/')[-1]
        sections = [key for key in document if key == '/**']
        sections += [key for key in document if key != '/**' and str(key).strip('/').split('/')[-1] == bare]
        if not sections:
            raise ValueError(
                f'params file {path} has no section for node {bare!r}: expected a top-level "{bare}:" '
                f'or "/**:" key with "ros__parameters:" under it; found {sorted(map(str, document))}'
            )
        merged: dict[str, Any] = {}
        for key in sections:
            section = document[key]
            if not isinstance(section, Mapping) or 'ros__parameters' not in section:
                raise ValueError(f'params file {path}: section {key!r} must contain "ros__parameters:"')
            parameters = section['ros__parameters'] or {}
            if not isinstance(parameters, Mapping):
                raise ValueError(f'params file {path}: {key}.ros__parameters must be a mapping')
            merged.update(parameters)
        return cls.from_mapping(merged, source=f'params file {path}')


# --------------------------------------------------------------------------------------------
# skipped frames
# --------------------------------------------------------------------------------------------


class FrameSkipped(ValueError):
    """An input frame the extractor cannot use; the node counts it, warns (throttled) and goes on.

    Attributes:
        kind: short machine-readable cause: ``'empty'``, ``'unorganized'`` (a cloud of height 1 that
            cannot be put on a range image: bad ring values, no ring field for
            ``unorganized_rows: rings``), ``'too_large'``,
            ``'invalid_cloud'`` (missing x/y/z, unsupported datatype, inconsistent sizes),
            ``'no_valid_points'``, and for depth images ``'no_camera_info'``, ``'invalid_image'``,
            ``'invalid_camera_info'``, ``'camera_info_mismatch'`` (:mod:`ppe_ros.ros.depth_image`).
        reason: the full message.
    """

    def __init__(self, kind: str, reason: str) -> None:
        super().__init__(reason)
        self.kind = kind
        self.reason = reason


def frame_label(msg: Any) -> str:
    """``stamp <sec>.<nanosec> s, frame_id '<id>'`` of a cloud, for log lines (never raises)."""
    try:
        stamped = StampedFrame.of(msg.header)
    except Exception:  # a message without a readable header: say so instead of failing again
        return 'a frame without a readable header'
    return f'stamp {stamped.sec}.{stamped.nanosec:09d} s, frame_id {stamped.frame_id!r}'


_KERNEL_NAME = re.compile(r'CPUDispatcher\(<function (\w+)')


def failure_reason(exc: BaseException) -> str:
    """One line saying why a frame failed: ``<exception type>: <message>``.

    An exception raised inside a compiled (numba) kernel surfaces as ``SystemError:
    CPUDispatcher(<function ...>) returned a result with an exception set``; the reason is then the
    original exception, with the kernel's name.
    """
    cause = exc.__cause__ or exc.__context__
    if isinstance(exc, SystemError) and cause is not None:
        kernel = _KERNEL_NAME.search(str(exc))
        where = f' (in the compiled kernel {kernel.group(1)})' if kernel else ''
        exc = cause
    else:
        where = ''
    return f'{type(exc).__name__}: {str(exc) or "(no message)"}{where}'.replace('\n', ' ')


# --------------------------------------------------------------------------------------------
# output messages
# --------------------------------------------------------------------------------------------

#: Fields of the labelled cloud: ``x y z`` float32 (m), ``label`` uint32, ``rgb`` float32-packed.
LABELED_POINTS_FIELDS: tuple[str, ...] = ('x', 'y', 'z', 'label', 'rgb')

#: Fields of the plane table, one point per plane (144 bytes per plane), all in the cloud frame:
#: ``x y z`` float32 centroid of the plane's points (m), what RViz draws (its XYZ transformer
#: reads float32 only; float32 keeps 8 significant digits: 8 um at 100 m); ``rgb`` the plane's
#: colour in the labelled cloud and the markers (float32-packed ``0x00RRGGBB``, RViz's RGB8);
#: ``centroid_x centroid_y centroid_z`` the same centroid in float64; ``normal_x normal_y
#: normal_z`` unit normal (facing the sensor); ``d`` offset (m) with ``normal . p = d`` on the
#: plane; ``rmse`` (m) and ``sse`` (m^2) of the radial residuals; ``cov_xx ... cov_zz`` the upper
#: triangle of the 3x3 covariance (m^2) of the closest-point vector ``d * normal``;
#: ``point_count`` points of the plane; ``label`` its id in the labelled cloud. Everything but
#: ``x y z rgb`` is float64 or uint32: the plane itself (normal, d, covariance) at full precision.
PLANE_TABLE_DTYPE = np.dtype(
    [
        ('x', '<f4'),
        ('y', '<f4'),
        ('z', '<f4'),
        ('rgb', '<u4'),
        ('centroid_x', '<f8'),
        ('centroid_y', '<f8'),
        ('centroid_z', '<f8'),
        ('normal_x', '<f8'),
        ('normal_y', '<f8'),
        ('normal_z', '<f8'),
        ('d', '<f8'),
        ('rmse', '<f8'),
        ('sse', '<f8'),
        ('cov_xx', '<f8'),
        ('cov_xy', '<f8'),
        ('cov_xz', '<f8'),
        ('cov_yy', '<f8'),
        ('cov_yz', '<f8'),
        ('cov_zz', '<f8'),
        ('point_count', '<u4'),
        ('label', '<u4'),
    ]
)
PLANE_TABLE_FIELDS: tuple[str, ...] = PLANE_TABLE_DTYPE.names


def label_palette(num_planes: int) -> np.ndarray:
    """``(J + 1,)`` uint32 ``0x00RRGGBB`` colours of labels 0..J (labelled cloud and markers)."""
    return np.asarray(label_colors(np.arange(num_planes + 1, dtype=np.int64)), dtype=np.uint32)


def labeled_points_message(points: np.ndarray, planes: PlaneSet, header: Any, types: MessageTypes) -> Any:
    """The labelled cloud: the input grid with fields :data:`LABELED_POINTS_FIELDS`."""
    labels = planes.labels
    return xyz_to_pointcloud2(
        points,
        header=header,
        msg_class=types.PointCloud2,
        field_class=types.PointField,
        labels=labels,
        rgb=label_palette(planes.num_planes)[labels],
    )


def plane_table_message(planes: PlaneSet, header: Any, types: MessageTypes) -> Any:
    """The plane table: height 1, one point per plane, fields :data:`PLANE_TABLE_FIELDS`."""
    return structured_to_pointcloud2(
        plane_table_records(planes),
        header=header,
        msg_class=types.PointCloud2,
        field_class=types.PointField,
        is_dense=True,
        datatypes={'rgb': FLOAT32},
    )


def plane_table_records(planes: PlaneSet) -> np.ndarray:
    """``(J,)`` records of :data:`PLANE_TABLE_DTYPE`, row j = plane j + 1."""
    table = np.zeros(planes.num_planes, PLANE_TABLE_DTYPE)
    if planes.num_planes == 0:
        return table
    table['x'], table['y'], table['z'] = planes.centroids.astype(np.float32).T
    table['rgb'] = label_palette(planes.num_planes)[1:]
    table['centroid_x'], table['centroid_y'], table['centroid_z'] = planes.centroids.T
    table['normal_x'], table['normal_y'], table['normal_z'] = planes.normals.T
    table['d'] = planes.offsets
    table['rmse'] = planes.rmse
    table['sse'] = planes.sse
    cov = planes.covariances
    for name, (i, j) in zip(
        ('cov_xx', 'cov_xy', 'cov_xz', 'cov_yy', 'cov_yz', 'cov_zz'),
        ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)),
        strict=True,
    ):
        table[name] = cov[:, i, j]
    table['point_count'] = planes.point_counts
    table['label'] = np.arange(1, planes.num_planes + 1)
    return table


# --------------------------------------------------------------------------------------------
# one frame
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class OutputSelection:
    """Which outputs :func:`process_cloud` builds."""

    labeled_points: bool = True
    markers: bool = True
    plane_table: bool = True

    @classmethod
    def from_params(cls, params: ExtractorParams) -> OutputSelection:
        return cls(params.publish_labeled_points, params.publish_markers, params.publish_plane_table)


@dataclass
class ProcessedFrame:
    """The result of one frame.

    Attributes:
        header: the input header object (every output carries it).
        stamped: its stamp and frame_id.
        points: ``(H, W, 3)`` float64 input points (m, cloud frame), NaN = no return.
        planes: the extracted planes.
        labeled_points: PointCloud2 of the labelled cloud, or None if not built.
        markers: CDR bytes of the MarkerArray (publish as is with rclpy; write as is with rosbags;
            decode with ``types.decode_markers``), or None if not built.
        plane_table: PointCloud2 of the plane table, or None if not built.
        timings: seconds spent in ``convert``, ``extract``, ``labeled_points``, ``markers``,
            ``plane_table`` (and ``projection``, the range image and the labels back, for an
            unorganized cloud).
        layout: ``'rows_are_beams'``, ``'columns_are_beams'`` (the grid was transposed for the
            extraction and the labels back) or ``'unorganized'`` (``points`` is ``(1, N, 3)`` and
            ``planes.labels`` ``(1, N)``, in the input's order).
        grid_points, grid_planes: the range image ``(rows, columns, 3)`` of an unorganized cloud and
            its planes (``labels`` on that grid): the markers' meshes are built on it; None otherwise.
        ray_origins: ``(3,)`` or ``(H, W, 3)`` ray starts the planes were extracted with (m, cloud frame).
        marker_stride: mesh stride of the markers (``marker_mesh_stride``, or larger to stay within
            ``marker_max_triangles``); 0 if no markers were built.
    """

    header: Any
    stamped: StampedFrame
    points: np.ndarray
    planes: PlaneSet
    labeled_points: Any = None
    markers: bytes | None = None
    plane_table: Any = None
    timings: dict[str, float] = field(default_factory=dict)
    ray_origins: np.ndarray | None = None
    marker_stride: int = 0
    layout: str = 'rows_are_beams'
    grid_points: np.ndarray | None = None
    grid_planes: PlaneSet | None = None

    @property
    def overhead_s(self) -> float:
        """Seconds spent outside extraction (conversion in and building outputs)."""
        return sum(t for name, t in self.timings.items() if name != 'extract')


def _check_frame_size(height: int, width: int, params: ExtractorParams, what: str, unit: str) -> tuple[int, int]:
    """``(height, width)`` of a cloud or image; FrameSkipped when it is empty or over ``params.max_points``."""
    if height == 0 or width == 0:
        raise FrameSkipped('empty', f'empty {what} (height {height}, width {width}): nothing to extract')
    if height * width > params.max_points:
        raise FrameSkipped(
            'too_large',
            f'{what} of {height} x {width} = {height * width} {unit} exceeds max_points = {params.max_points}',
        )
    return height, width


def cloud_points(msg: Any, params: ExtractorParams) -> np.ndarray:
    """Validate an input cloud and return its ``(H, W, 3)`` float64 points (NaN = no return); an
    unorganized cloud gives ``(1, N, 3)``.

    No return: a point with a non-finite coordinate, or exactly at (0, 0, 0) (what many drivers
    publish for a pixel without a return; the file loaders of :mod:`ppe_ros.io` read it so too).

    Raises:
        FrameSkipped: empty, larger than ``params.max_points``, malformed, or no finite point.
    """
    height, width = _check_frame_size(int(msg.height), int(msg.width), params, 'cloud', 'points')
    try:
        points = pointcloud2_to_xyz(msg, zero_is_no_return=True)
    except PointCloudError as exc:
        raise FrameSkipped('invalid_cloud', f'invalid PointCloud2: {exc}') from None
    # pointcloud2_to_xyz makes a point without a return all NaN: x alone tells
    if np.isnan(points[..., 0]).all():
        raise FrameSkipped(
            'no_valid_points',
            f'cloud of {height} x {width} points has no finite point other than (0, 0, 0) '
            '(every point NaN, infinite or exactly 0, 0, 0: no return)',
        )
    return points


@dataclass(frozen=True)
class DecodedCloud:
    """An input cloud's points and how its beams lie.

    Attributes:
        points: ``(H, W, 3)`` float64 (m, cloud frame), NaN = no return; ``(1, N, 3)`` if unorganized.
        layout: ``'rows_are_beams'``, ``'columns_are_beams'`` or ``'unorganized'``.
        beams: ``(H, W)`` values of the cloud's beam field (``ring`` or ``line``), or None.
        beam_field: that field's name, or None.
    """

    points: np.ndarray
    layout: str
    beams: np.ndarray | None = None
    beam_field: str | None = None


def decode_cloud(msg: Any, params: ExtractorParams) -> DecodedCloud:
    """:func:`cloud_points` plus the beam field and the layout (``params.layout``; ``auto``: a cloud of
    height 1 is unorganized; an organized cloud is ``columns_are_beams`` when neighbours along a row
    share their ring less often than neighbours along a column, as in Velodyne's and RoboSense's
    organized clouds, else ``rows_are_beams``).

    Raises:
        FrameSkipped: see :func:`cloud_points`.
    """
    points = cloud_points(msg, params)
    try:
        beams, beam_field = pointcloud2_beams(msg)
    except PointCloudError as exc:  # pragma: no cover - cloud_points read the same layout
        raise FrameSkipped('invalid_cloud', f'invalid PointCloud2: {exc}') from None
    if points.shape[0] == 1:
        return DecodedCloud(points, 'unorganized', beams, beam_field)
    layout = params.layout
    if layout == 'auto':
        layout = 'rows_are_beams'
        if beam_field == 'ring':
            valid = ~np.isnan(points[..., 0])
            along_row = valid[:, 1:] & valid[:, :-1]
            along_column = valid[1:] & valid[:-1]
            with np.errstate(invalid='ignore'):
                same_in_row = np.mean((beams[:, 1:] == beams[:, :-1])[along_row]) if along_row.any() else 1.0
                same_in_column = np.mean((beams[1:] == beams[:-1])[along_column]) if along_column.any() else 0.0
            if same_in_row < same_in_column:
                layout = 'columns_are_beams'
    return DecodedCloud(points, layout, beams, beam_field)


def _extraction_settings(params: ExtractorParams) -> dict[str, Any]:
    """extract_planes's keyword arguments from the node parameters: 0 (e, lmax, min_plane_points,
    surface_tolerance) leaves a setting to the sensor profile (sensor none: extract_planes's own)."""
    from ppe_ros.core.extraction import PROFILE_DEFAULT

    settings = {
        name: getattr(params, name) or PROFILE_DEFAULT
        for name in ('max_error_increment', 'max_neighbor_distance', 'min_plane_points')
    }
    if params.sensor != 'none':
        settings.update(sensor=_profile(params), surface_tolerance=params.surface_tolerance or PROFILE_DEFAULT)
    return {
        **settings,
        'origins': np.asarray(params.ray_origin, dtype=np.float64),
        'max_planes': params.max_planes or None,
    }


def _profile(params: ExtractorParams):
    """The sensor profile of the params: its name, or with range_noise the profile with that constant term."""
    if not params.range_noise:
        return params.sensor
    from ppe_ros.core.sensor import sensor_profile

    return sensor_profile(params.sensor).with_range_noise(params.range_noise)


def _extract_grid(points: np.ndarray, settings: dict[str, Any]) -> PlaneSet:
    from ppe_ros.core.extraction import extract_planes

    planes = extract_planes(points, **settings)
    if isinstance(planes, list):  # both thresholds set: one cut each; stop at whichever comes first
        planes = min(planes, key=lambda cut: cut.actions)
    return planes


def lost_point_tolerance(params: ExtractorParams) -> float:
    """The distance (m) within which a point that lost its range-image cell joins the cell's plane."""
    from ppe_ros.core.projection import DEFAULT_LOST_POINT_TOLERANCE
    from ppe_ros.core.sensor import sensor_profile

    if params.lost_point_tolerance > 0:
        return params.lost_point_tolerance
    if params.sensor != 'none':
        tolerance = params.surface_tolerance or sensor_profile(params.sensor).surface_tolerance
        if tolerance:
            return float(tolerance)
    return DEFAULT_LOST_POINT_TOLERANCE


def _unorganized_method(cloud: DecodedCloud, params: ExtractorParams) -> str:
    method = params.unorganized_rows
    if method == 'auto':
        return {'ring': 'rings', 'line': 'angular_grid'}.get(cloud.beam_field, 'elevation')
    if method == 'rings' and cloud.beam_field != 'ring':
        raise FrameSkipped(
            'unorganized',
            f'unorganized cloud (height 1, width {cloud.points.shape[1]}) without a '
            'ring field, and unorganized_rows is rings (use auto or elevation)',
        )
    return method


def _extract_unorganized(
    cloud: DecodedCloud, params: ExtractorParams, settings: dict[str, Any], timings: dict[str, float]
) -> tuple[PlaneSet, np.ndarray, PlaneSet]:
    """Planes of an unorganized cloud: its range image, PPE on it, labels back ``(1, N)``."""
    from ppe_ros.core.projection import image_or_empty, planes_for_points, project_points

    start = time.perf_counter()
    points = cloud.points.reshape(-1, 3)
    method = _unorganized_method(cloud, params)
    rings = cloud.beams.reshape(-1) if method == 'rings' else None
    try:
        projection = project_points(
            points,
            rings,
            origins=settings['origins'],
            rows=method,
            azimuth_bins=params.azimuth_bins or None,
            angular_resolution=params.angular_resolution,
            azimuth_start=params.azimuth_start,
        )
    except ValueError as exc:
        raise FrameSkipped(
            'unorganized',
            f'unorganized cloud (height 1, width {len(points)}) cannot be put on a range image ({method}): {exc}',
        ) from None
    image = image_or_empty(projection, points)
    timings['projection'] = time.perf_counter() - start
    grid_planes = _extract_grid(image, settings)
    mark = time.perf_counter()
    planes = planes_for_points(projection, grid_planes, points, lost_point_tolerance(params))
    planes = dataclasses.replace(planes, labels=planes.labels.reshape(1, -1))
    timings['projection'] += time.perf_counter() - mark
    return planes, image, grid_planes


def process_cloud(
    msg: Any,
    params: ExtractorParams,
    types: MessageTypes,
    *,
    outputs: OutputSelection | None = None,
    ray_origins: np.ndarray | None = None,
) -> ProcessedFrame:
    """Convert, validate, extract planes and build the selected outputs of one PointCloud2.

    Organized clouds with the beams in columns are transposed for the extraction and their labels
    transposed back; unorganized clouds (height 1) are put on a range image
    (:mod:`ppe_ros.core.projection`) and get a label per point. Every output keeps the input's
    ``height x width`` and point order.

    Args:
        msg: ``sensor_msgs/PointCloud2`` of either flavour.
        params: extraction and output settings.
        types: message classes of the flavour to build.
        outputs: which outputs to build (default: the ``publish_*`` flags of ``params``).
        ray_origins: ``(H, W, 3)`` ray starts (m, cloud frame) to use instead of ``params.ray_origin``
            (the node's from the Ouster driver's metadata).

    Raises:
        FrameSkipped: the cloud cannot be used (see :func:`cloud_points` and :func:`decode_cloud`).
    """
    start = time.perf_counter()
    cloud = decode_cloud(msg, params)
    return _process_decoded(msg.header, cloud, params, types, outputs, ray_origins, start)


def depth_frame_points(frame: DepthFrame, params: ExtractorParams) -> np.ndarray:
    """Validate a depth image and its camera info and return the ``(H, W, 3)`` float64 points (m, the
    image's optical frame, NaN = no return); :func:`cloud_points` for a depth image.

    Raises:
        FrameSkipped: no camera info yet (``no_camera_info``), an empty or too large image, an image or
            camera info that cannot be used (``invalid_image``, ``invalid_camera_info``,
            ``camera_info_mismatch``), no valid depth.
    """
    try:
        size = depth_image_size(frame.image)  # a compressed image's from its header, before it is decoded
    except DepthImageError as exc:
        raise FrameSkipped(exc.kind, f'depth image: {exc.reason}') from None
    height, width = _check_frame_size(*size, params, 'depth image', 'pixels')
    if frame.camera_info is None:
        raise FrameSkipped(
            'no_camera_info', f'depth image without camera info: none received on {frame.camera_info_topic} yet'
        )
    try:
        points = depth_image_points(frame.image, frame.camera_info, rectified=params.depth_image_rectified)
    except DepthImageError as exc:
        raise FrameSkipped(exc.kind, f'depth image: {exc.reason}') from None
    if np.isnan(points[..., 2]).all():
        raise FrameSkipped(
            'no_valid_points',
            f'depth image of {height} x {width} pixels has no valid depth (every pixel 0, NaN or infinite)',
        )
    return points


def process_depth_image(
    frame: DepthFrame, params: ExtractorParams, types: MessageTypes, *, outputs: OutputSelection | None = None
) -> ProcessedFrame:
    """:func:`process_cloud` for a depth image and its camera info (:mod:`ppe_ros.ros.depth_image`).

    The image is back-projected into its optical frame (rays from ``params.ray_origin``, default the
    camera centre) and extracted as an organized cloud of the image's ``height x width``; the outputs
    carry the image's header.

    Raises:
        FrameSkipped: see :func:`depth_frame_points`.
    """
    start = time.perf_counter()
    cloud = DecodedCloud(depth_frame_points(frame, params), 'rows_are_beams')
    return _process_decoded(frame.image.header, cloud, params, types, outputs, None, start)


def _process_decoded(
    header: Any,
    cloud: DecodedCloud,
    params: ExtractorParams,
    types: MessageTypes,
    outputs: OutputSelection | None,
    ray_origins: np.ndarray | None,
    start: float,
) -> ProcessedFrame:
    """Extract ``cloud`` (converted since ``start``, perf_counter s) and build the selected outputs."""
    timings = {'convert': (mark := time.perf_counter()) - start}
    settings = _extraction_settings(params)
    grid_points = grid_planes = None
    if cloud.layout == 'unorganized':  # per-pixel ray starts belong to an organized grid: params' apply
        planes, grid_points, grid_planes = _extract_unorganized(cloud, params, settings, timings)
        timings['extract'] = time.perf_counter() - mark - timings['projection']
    else:
        if ray_origins is not None:
            settings['origins'] = np.asarray(ray_origins, dtype=np.float64)
        if cloud.layout == 'columns_are_beams':  # PPE's grid is symmetric under transposition: same planes
            grid = dict(settings)
            if grid['origins'].ndim == 3:
                grid['origins'] = np.ascontiguousarray(grid['origins'].transpose(1, 0, 2))
            planes = _extract_grid(np.ascontiguousarray(cloud.points.transpose(1, 0, 2)), grid)
            planes = dataclasses.replace(planes, labels=np.ascontiguousarray(planes.labels.T))
        else:
            planes = _extract_grid(cloud.points, settings)
        timings['extract'] = time.perf_counter() - mark
    frame = ProcessedFrame(
        header=header,
        stamped=StampedFrame.of(header),
        points=cloud.points,
        planes=planes,
        timings=timings,
        ray_origins=settings['origins'],
        layout=cloud.layout,
        grid_points=grid_points,
        grid_planes=grid_planes,
    )
    build_outputs(frame, params, types, OutputSelection.from_params(params) if outputs is None else outputs)
    return frame


def build_outputs(
    frame: ProcessedFrame, params: ExtractorParams, types: MessageTypes, selection: OutputSelection
) -> None:
    """Build the selected output messages of ``frame`` in place (and their ``timings``)."""
    points, planes, header, timings = frame.points, frame.planes, frame.header, frame.timings
    mark = time.perf_counter()
    if selection.labeled_points:
        frame.labeled_points = labeled_points_message(points, planes, header, types)
        timings['labeled_points'] = (now := time.perf_counter()) - mark
        mark = now
    if selection.markers:  # meshes on the grid the planes were extracted on
        if frame.grid_points is None:
            mesh_points, mesh_planes = points, planes
            origins = np.asarray(params.ray_origin) if frame.ray_origins is None else frame.ray_origins
        else:
            mesh_points, mesh_planes, origins = frame.grid_points, frame.grid_planes, np.asarray(params.ray_origin)
        geometry, frame.marker_stride = budgeted_plane_geometry(
            mesh_points,
            mesh_planes,
            ray_origin=origins,
            stride=params.marker_mesh_stride,
            max_triangles=params.marker_max_triangles,
        )
        colors = label_palette(planes.num_planes)[1:]
        frame.markers = marker_array_cdr(geometry, planes, frame.stamped, colors=colors, mesh_alpha=params.marker_alpha)
        timings['markers'] = (now := time.perf_counter()) - mark
        mark = now
    if selection.plane_table:
        frame.plane_table = plane_table_message(planes, header, types)
        timings['plane_table'] = time.perf_counter() - mark
