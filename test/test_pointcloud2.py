"""PointCloud2 <-> numpy for rclpy and rosbags messages (ppe_ros.ros.pointcloud2)."""

from __future__ import annotations

import array
import itertools
import subprocess
import sys

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from ppe_ros.ros.pointcloud2 import (
    FLOAT32,
    FLOAT64,
    UINT16,
    UINT32,
    UNLABELLED_COLOR,
    PointCloudError,
    is_organized,
    label_colors,
    pointcloud2_beams,
    pointcloud2_field,
    pointcloud2_to_structured,
    pointcloud2_to_xyz,
    structured_to_pointcloud2,
    xyz_to_pointcloud2,
)

pytestmark = pytest.mark.ros

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
BAG_CLOUD = TYPESTORE.types['sensor_msgs/msg/PointCloud2']
BAG_FIELD = TYPESTORE.types['sensor_msgs/msg/PointField']
BAG_HEADER = TYPESTORE.types['std_msgs/msg/Header']
BAG_TIME = TYPESTORE.types['builtin_interfaces/msg/Time']
CLOUD_TYPE = 'sensor_msgs/msg/PointCloud2'

FLAVOURS = ('rclpy', 'rosbags')


def _classes(flavour: str) -> tuple[type, type]:
    return (PointCloud2, PointField) if flavour == 'rclpy' else (BAG_CLOUD, BAG_FIELD)


def _header(flavour: str, frame_id: str = 'sensor', sec: int = 12, nanosec: int = 345) -> object:
    if flavour == 'rclpy':
        header = Header(frame_id=frame_id)
        header.stamp.sec = sec
        header.stamp.nanosec = nanosec
        return header
    return BAG_HEADER(stamp=BAG_TIME(sec=sec, nanosec=nanosec), frame_id=frame_id)


def _message(
    flavour: str,
    *,
    fields: list[tuple[str, int, int, int]],
    height: int,
    width: int,
    point_step: int,
    row_step: int,
    data: bytes,
    is_bigendian: bool = False,
) -> object:
    """A PointCloud2 built by hand (not through ppe_ros) from (name, offset, datatype, count)."""
    cloud_class, field_class = _classes(flavour)
    buffer = array.array('B', data) if flavour == 'rclpy' else np.frombuffer(data, np.uint8).copy()
    return cloud_class(
        header=_header(flavour),
        height=height,
        width=width,
        fields=[field_class(name=n, offset=o, datatype=d, count=c) for n, o, d, c in fields],
        is_bigendian=is_bigendian,
        point_step=point_step,
        row_step=row_step,
        data=buffer,
        is_dense=False,
    )


def _points(height: int = 3, width: int = 5) -> np.ndarray:
    rows, cols = np.mgrid[0:height, 0:width]
    points = np.stack([1.0 + cols, 0.5 * rows - 1.0, 0.25 + 0.125 * (rows * width + cols)], axis=-1)
    points[height // 2, width - 1] = np.nan
    return points


def _packed(
    points: np.ndarray,
    layout: dict[str, tuple[int, str]],
    point_step: int,
    row_pad: int = 0,
    extra: dict[str, np.ndarray] | None = None,
) -> bytes:
    """Bytes of an organized cloud with fields at given offsets, 0xEE filler in the padding."""
    height, width, _ = points.shape
    names = list(layout)
    dtype = np.dtype(
        {
            'names': names,
            'formats': [layout[n][1] for n in names],
            'offsets': [layout[n][0] for n in names],
            'itemsize': point_step,
        }
    )
    table = np.zeros((height, width), dtype=dtype)
    raw = table.view(np.uint8).reshape(height, width * point_step)
    raw[:] = 0xEE
    for index, axis in enumerate('xyz'):
        table[axis] = points[..., index]
    for name, values in (extra or {}).items():
        table[name] = values
    rows = np.full((height, width * point_step + row_pad), 0xAB, dtype=np.uint8)
    rows[:, : width * point_step] = table.view(np.uint8).reshape(height, -1)
    return rows.tobytes()


# --------------------------------------------------------------------------------------------
# round trips between flavours
# --------------------------------------------------------------------------------------------


def test_rclpy_message_to_numpy_to_rosbags_message() -> None:
    points = _points()
    labels = np.arange(15, dtype=np.int64).reshape(3, 5)
    colours = label_colors(labels)
    sent = xyz_to_pointcloud2(
        points, header=_header('rclpy'), msg_class=PointCloud2, field_class=PointField, labels=labels, rgb=colours
    )
    assert isinstance(sent.data, array.array)
    assert (sent.height, sent.width, sent.point_step, sent.row_step) == (3, 5, 20, 100)
    assert [(f.name, f.offset, f.datatype, f.count) for f in sent.fields] == [
        ('x', 0, FLOAT32, 1),
        ('y', 4, FLOAT32, 1),
        ('z', 8, FLOAT32, 1),
        ('label', 12, UINT32, 1),
        ('rgb', 16, FLOAT32, 1),
    ]
    assert sent.is_dense is False  # one NaN point
    np.testing.assert_array_equal(pointcloud2_to_xyz(sent), points.astype(np.float32))

    received = TYPESTORE.deserialize_cdr(serialize_message(sent), CLOUD_TYPE)
    assert isinstance(received.data, np.ndarray)
    xyz = pointcloud2_to_xyz(received)
    np.testing.assert_array_equal(xyz, points.astype(np.float32))
    table = pointcloud2_to_structured(received)
    assert np.array_equal(table['label'], labels)
    assert np.array_equal(table['rgb'].view(np.uint32), colours)

    # the same content built directly as a rosbags message equals what came through CDR
    rebuilt = xyz_to_pointcloud2(
        xyz,
        header=_header('rosbags'),
        msg_class=BAG_CLOUD,
        field_class=BAG_FIELD,
        labels=table['label'],
        rgb=table['rgb'].view(np.uint32),
    )
    assert rebuilt.header == received.header
    assert rebuilt.fields == received.fields
    for attribute in ('height', 'width', 'is_bigendian', 'point_step', 'row_step', 'is_dense'):
        assert getattr(rebuilt, attribute) == getattr(received, attribute), attribute
    assert np.array_equal(rebuilt.data, received.data)


def test_rosbags_message_to_numpy_to_rclpy_message() -> None:
    points = _points(4, 2)
    labels = np.array([[1, 2], [3, 4], [0, 0], [7, 8]], dtype=np.uint32)
    sent = xyz_to_pointcloud2(
        points, header=_header('rosbags'), msg_class=BAG_CLOUD, field_class=BAG_FIELD, labels=labels
    )
    assert isinstance(sent.data, np.ndarray) and sent.data.dtype == np.uint8
    received = deserialize_message(bytes(TYPESTORE.serialize_cdr(sent, CLOUD_TYPE)), PointCloud2)
    xyz = pointcloud2_to_xyz(received)
    np.testing.assert_array_equal(xyz, points.astype(np.float32))
    rebuilt = xyz_to_pointcloud2(
        xyz,
        header=_header('rclpy'),
        msg_class=PointCloud2,
        field_class=PointField,
        labels=pointcloud2_to_structured(received)['label'],
    )
    assert rebuilt == received


def test_structured_table_one_point_per_plane() -> None:
    table = np.zeros(
        3,
        dtype=[
            ('x', '<f4'),
            ('y', '<f4'),
            ('z', '<f4'),
            ('normal_x', '<f4'),
            ('normal_y', '<f4'),
            ('normal_z', '<f4'),
            ('point_count', '<u4'),
        ],
    )
    table['x'] = [1, 2, 3]
    table['normal_z'] = 1.0
    table['point_count'] = [100, 2000, 30000]
    for flavour in FLAVOURS:
        cloud_class, field_class = _classes(flavour)
        message = structured_to_pointcloud2(
            table, header=_header(flavour), msg_class=cloud_class, field_class=field_class
        )
        assert (message.height, message.width, message.is_dense) == (1, 3, True)
        assert not is_organized(message)
        assert [f.name for f in message.fields][-1] == 'point_count' and message.fields[-1].datatype == UINT32
        back = pointcloud2_to_structured(message)
        assert back.shape == (1, 3) and np.array_equal(back[0], table)
        # a frame without planes: an empty table is published and can be read back
        empty = structured_to_pointcloud2(
            table[:0], header=_header(flavour), msg_class=cloud_class, field_class=field_class
        )
        assert (empty.height, empty.width, len(empty.data)) == (1, 0, 0)
        assert pointcloud2_to_structured(empty, allow_empty=True).shape == (1, 0)
        with pytest.raises(PointCloudError, match='empty cloud: height 1, width 0'):
            pointcloud2_to_structured(empty)


def test_structured_to_pointcloud2_keeps_big_endian_values_and_counts() -> None:
    table = np.zeros((2, 2), dtype=[('x', '>f8'), ('y', '>f8'), ('z', '>f8'), ('ring', '>u2'), ('vec', '<f4', (3,))])
    table['x'] = [[1.5, 2.5], [3.5, 4.5]]
    table['ring'] = [[1, 2], [3, 4]]
    table['vec'] = 7.0
    message = structured_to_pointcloud2(table, header=_header('rclpy'), msg_class=PointCloud2, field_class=PointField)
    assert message.is_bigendian is False
    assert [(f.name, f.datatype, f.count) for f in message.fields][-2:] == [('ring', UINT16, 1), ('vec', FLOAT32, 3)]
    back = pointcloud2_to_structured(message)
    assert np.array_equal(back['x'], table['x']) and np.array_equal(back['ring'], table['ring'])
    assert np.array_equal(back['vec'], table['vec'])
    assert pointcloud2_to_xyz(message)[1, 1, 0] == 4.5
    with pytest.raises(ValueError, match='not a PointField datatype'):
        structured_to_pointcloud2(
            table, header=_header('rclpy'), msg_class=PointCloud2, field_class=PointField, datatypes={'ring': 12}
        )
    with pytest.raises(ValueError, match='cannot carry'):
        structured_to_pointcloud2(
            np.zeros(2, dtype=[('x', 'i8')]), header=_header('rclpy'), msg_class=PointCloud2, field_class=PointField
        )


def test_large_organized_cloud_round_trips() -> None:
    points = np.random.default_rng(0).normal(size=(480, 640, 3))
    labels = np.arange(480 * 640).reshape(480, 640) % 40
    message = xyz_to_pointcloud2(
        points,
        header=_header('rclpy'),
        msg_class=PointCloud2,
        field_class=PointField,
        labels=labels,
        rgb=label_colors(labels),
    )
    xyz = pointcloud2_to_xyz(message)
    assert (message.height, message.width) == (480, 640)
    np.testing.assert_array_equal(xyz, points.astype(np.float32))


# --------------------------------------------------------------------------------------------
# reading arbitrary layouts
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize('flavour', FLAVOURS)
@pytest.mark.parametrize('order', list(itertools.permutations(['x', 'y', 'z', 'intensity'])))
def test_field_order_permutations(flavour: str, order: tuple[str, ...]) -> None:
    points = _points()
    layout = {name: (4 * index, '<f4') for index, name in enumerate(order)}
    intensity = np.full((3, 5), 0.5, dtype=np.float32)
    data = _packed(points, layout, 16, extra={'intensity': intensity})
    fields = [(name, 4 * index, FLOAT32, 1) for index, name in enumerate(order)]
    message = _message(flavour, fields=fields, height=3, width=5, point_step=16, row_step=80, data=data)
    np.testing.assert_array_equal(pointcloud2_to_xyz(message), points.astype(np.float32))
    assert np.array_equal(pointcloud2_to_structured(message)['intensity'], intensity)


@pytest.mark.parametrize('flavour', FLAVOURS)
@pytest.mark.parametrize('big_endian', [False, True])
def test_float64_xyz_with_point_and_row_padding(flavour: str, big_endian: bool) -> None:
    points = _points(4, 3)
    points[0, 0, 0] = 1.0 + 1e-12  # float64 precision survives
    order = '>' if big_endian else '<'
    layout = {'z': (0, order + 'f8'), 'x': (16, order + 'f8'), 'y': (24, order + 'f8')}
    data = _packed(points, layout, point_step=40, row_pad=7)
    fields = [('z', 0, FLOAT64, 1), ('x', 16, FLOAT64, 1), ('y', 24, FLOAT64, 1)]
    message = _message(
        flavour, fields=fields, height=4, width=3, point_step=40, row_step=127, data=data, is_bigendian=big_endian
    )
    xyz = pointcloud2_to_xyz(message)
    assert xyz.shape == (4, 3, 3)  # height rows, width columns
    np.testing.assert_array_equal(xyz, points)


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_ouster_like_mixed_fields(flavour: str) -> None:
    # ouster-ros layout: x y z (float32, 4 bytes padding), intensity f32, t u32, reflectivity u16,
    # ring u16, ambient u16, (2 bytes), range u32, padded to 48 bytes
    height, width = 4, 6
    points = _points(height, width)
    points[2, 1] = [np.inf, 1.0, 1.0]
    layout = {
        'x': (0, '<f4'),
        'y': (4, '<f4'),
        'z': (8, '<f4'),
        'intensity': (16, '<f4'),
        't': (20, '<u4'),
        'reflectivity': (24, '<u2'),
        'ring': (26, '<u2'),
        'ambient': (28, '<u2'),
        'range': (32, '<u4'),
    }
    ring = np.repeat(np.arange(height, dtype=np.uint16)[:, None], width, axis=1)
    t_ns = np.tile(np.arange(width, dtype=np.uint32) * 48828, (height, 1))
    data = _packed(points, layout, 48, extra={'ring': ring, 't': t_ns, 'range': np.full((height, width), 4321)})
    fields = [
        ('x', 0, 7, 1),
        ('y', 4, 7, 1),
        ('z', 8, 7, 1),
        ('intensity', 16, 7, 1),
        ('t', 20, 6, 1),
        ('reflectivity', 24, 4, 1),
        ('ring', 26, 4, 1),
        ('ambient', 28, 4, 1),
        ('range', 32, 6, 1),
    ]
    message = _message(
        flavour, fields=fields, height=height, width=width, point_step=48, row_step=48 * width, data=data
    )
    xyz = pointcloud2_to_xyz(message, require_organized=True)
    expected = points.astype(np.float32).astype(np.float64)
    expected[2, 1] = np.nan  # a non-finite coordinate makes the whole point "no return"
    np.testing.assert_array_equal(xyz, expected)
    table = pointcloud2_to_structured(message)
    assert np.array_equal(table['ring'], ring) and np.array_equal(table['t'], t_ns)
    assert np.all(table['range'] == 4321) and table.dtype['reflectivity'] == np.dtype('<u2')


@pytest.mark.parametrize('flavour', FLAVOURS)
@pytest.mark.parametrize('big_endian', [False, True], ids=['little', 'big'])
def test_beam_fields_are_read_ring_first_then_line(flavour: str, big_endian: bool) -> None:
    order = '>' if big_endian else '<'
    points = _points(1, 6)
    ring = np.array([[3, 1, 4, 1, 5, 9]], dtype=np.uint16)
    line = np.array([[0, 1, 2, 3, 0, 1]], dtype=np.uint8)
    layout = {
        'x': (0, order + 'f4'),
        'y': (4, order + 'f4'),
        'z': (8, order + 'f4'),
        'line': (12, 'u1'),
        'ring': (14, order + 'u2'),
    }
    data = _packed(points, layout, 16, extra={'ring': ring, 'line': line})
    fields = [
        ('x', 0, FLOAT32, 1),
        ('y', 4, FLOAT32, 1),
        ('z', 8, FLOAT32, 1),
        ('line', 12, 2, 1),
        ('ring', 14, UINT16, 1),
    ]
    message = _message(
        flavour, fields=fields, height=1, width=6, point_step=16, row_step=96, data=data, is_bigendian=big_endian
    )
    values, name = pointcloud2_beams(message)
    assert name == 'ring' and values.dtype == np.uint16 and values.dtype.isnative
    np.testing.assert_array_equal(values, ring)
    np.testing.assert_array_equal(pointcloud2_field(message, 'line'), line)
    assert pointcloud2_field(message, 'intensity') is None
    livox = _message(
        flavour, fields=fields[:4], height=1, width=6, point_step=16, row_step=96, data=data, is_bigendian=big_endian
    )
    values, name = pointcloud2_beams(livox)
    assert name == 'line'
    np.testing.assert_array_equal(values, line)
    plain = _message(
        flavour, fields=fields[:3], height=1, width=6, point_step=16, row_step=96, data=data, is_bigendian=big_endian
    )
    assert pointcloud2_beams(plain) == (None, None)


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_unorganized_cloud_is_read_but_can_be_required_organized(flavour: str) -> None:
    points = _points(1, 6)
    data = _packed(points, {'x': (0, '<f4'), 'y': (4, '<f4'), 'z': (8, '<f4')}, 12)
    fields = [('x', 0, 7, 1), ('y', 4, 7, 1), ('z', 8, 7, 1)]
    message = _message(flavour, fields=fields, height=1, width=6, point_step=12, row_step=72, data=data)
    assert pointcloud2_to_xyz(message).shape == (1, 6, 3)
    assert not is_organized(message)
    with pytest.raises(PointCloudError, match=r'not organized \(height 1, width 6\)'):
        pointcloud2_to_xyz(message, require_organized=True)


# --------------------------------------------------------------------------------------------
# malformed messages
# --------------------------------------------------------------------------------------------

_XYZ = [('x', 0, FLOAT32, 1), ('y', 4, FLOAT32, 1), ('z', 8, FLOAT32, 1)]

MALFORMED = {
    'missing y': (dict(fields=[('x', 0, 7, 1), ('z', 8, 7, 1)]), r'no y field \(fields: x, z\)'),
    'unsupported datatype': (dict(fields=[*_XYZ[:2], ('z', 8, 9, 1)]), "field 'z' has unsupported datatype 9"),
    'mixed xyz types': (
        dict(fields=[('x', 0, 7, 1), ('y', 4, 7, 1), ('z', 8, 8, 1)], point_step=16, row_step=32, data=bytes(64)),
        'x, y, z must have the same datatype; found x 7, y 7, z 8',
    ),
    'field beyond point_step': (
        dict(fields=[*_XYZ, ('intensity', 10, 7, 1)]),
        r"field 'intensity' \(offset 10, 1 x 4 bytes\) extends to byte 14, beyond point_step 12",
    ),
    'point_step zero': (dict(point_step=0), 'point_step is 0'),
    'row_step too small': (dict(row_step=20), r'row_step 20 is smaller than width × point_step = 2 × 12 = 24'),
    'data too short': (dict(data=bytes(47)), r'data has 47 bytes, expected row_step × height = 24 × 2 = 48'),
    'data too long': (dict(data=bytes(50)), r'data has 50 bytes, expected row_step × height = 24 × 2 = 48'),
    'empty width': (dict(width=0, row_step=0, data=b''), r'empty cloud: height 2, width 0'),
    'empty height': (dict(height=0, data=b''), r'empty cloud: height 0, width 2'),
    'point_step beyond numpy': (
        dict(point_step=2**31, row_step=2**32 - 1),
        r'point_step is 2147483648; at most 2147483647 bytes per point',
    ),
}


@pytest.mark.parametrize('flavour', FLAVOURS)
@pytest.mark.parametrize('case', sorted(MALFORMED))
def test_malformed_cloud_raises_specific_error(flavour: str, case: str) -> None:
    changes, message = MALFORMED[case]
    arguments = dict(fields=_XYZ, height=2, width=2, point_step=12, row_step=24, data=bytes(48))
    arguments.update(changes)
    cloud = _message(flavour, **arguments)
    with pytest.raises(PointCloudError, match=message):
        pointcloud2_to_xyz(cloud)
    assert issubclass(PointCloudError, ValueError)


def test_writer_rejects_bad_arrays() -> None:
    points = _points()
    kwargs = dict(header=_header('rclpy'), msg_class=PointCloud2, field_class=PointField)
    with pytest.raises(ValueError, match=r'\(H, W, 3\) or \(N, 3\)'):
        xyz_to_pointcloud2(points[..., :2], **kwargs)
    with pytest.raises(ValueError, match='labels must lie in 0'):
        xyz_to_pointcloud2(points, labels=np.full((3, 5), -1), **kwargs)
    with pytest.raises(ValueError, match='labels must have shape'):
        xyz_to_pointcloud2(points, labels=np.zeros((5, 3), dtype=int), **kwargs)
    with pytest.raises(ValueError, match='rgb must be'):
        xyz_to_pointcloud2(points, rgb=np.zeros((3, 5), dtype=np.float32), **kwargs)
    rgb = np.zeros((3, 5, 3), dtype=np.uint8)
    rgb[..., 0] = 255
    message = xyz_to_pointcloud2(points, rgb=rgb, **kwargs)
    assert np.all(pointcloud2_to_structured(message)['rgb'].view(np.uint32) == 0xFF0000)
    dense = xyz_to_pointcloud2(np.ones((2, 2, 3)), **kwargs)
    assert dense.is_dense is True


# --------------------------------------------------------------------------------------------
# colours and import hygiene
# --------------------------------------------------------------------------------------------


def test_label_colors_stable_distinct_and_grey_for_unlabelled() -> None:
    ids = np.arange(1, 257)
    colours = label_colors(ids)
    assert colours.dtype == np.uint32 and colours.shape == (256,)
    assert np.all(colours <= 0xFFFFFF)
    assert len(np.unique(colours)) == 256 and UNLABELLED_COLOR not in colours
    assert np.all(label_colors(np.array([0, -1, -5])) == UNLABELLED_COLOR)
    # the colour of an id does not depend on the other ids in the array
    assert np.array_equal(
        label_colors(np.array([[7, 200], [3, 0]])), [[colours[6], colours[199]], [colours[2], UNLABELLED_COLOR]]
    )
    assert label_colors(np.array([10**9]))[0] == label_colors(np.array([10**9, 1]))[0]
    rgb = np.stack([(colours[:32] >> shift) & 0xFF for shift in (16, 8, 0)], axis=-1).astype(float)
    neighbours = np.abs(np.diff(rgb, axis=0)).sum(axis=1)
    assert neighbours.min() > 60  # consecutive ids are visibly different
    with pytest.raises(ValueError, match='integers'):
        label_colors(np.array([1.5]))


def test_modules_do_not_import_rclpy_or_rosbags() -> None:
    code = (
        'import sys, ppe_ros.ros.pointcloud2, ppe_ros.io; '
        'print(sorted(m for m in ("rclpy", "rosbags", "sensor_msgs") if m in sys.modules))'
    )
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True, timeout=60)
    assert result.stdout.strip() == '[]'


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_zero_points_become_nan_only_when_asked(flavour):
    points = np.array([[[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]], [[1.0, 0.0, 0.0], [-0.0, 0.0, 0.0]]])
    cloud_class, field_class = _classes(flavour)
    msg = xyz_to_pointcloud2(points, header=_header(flavour), msg_class=cloud_class, field_class=field_class)
    np.testing.assert_array_equal(pointcloud2_to_xyz(msg), points)  # a general converter keeps them
    read = pointcloud2_to_xyz(msg, zero_is_no_return=True)
    assert np.isnan(read[0, 0]).all() and np.isnan(read[1, 1]).all()  # -0.0 == 0.0
    np.testing.assert_array_equal(read[0, 1], points[0, 1])
    np.testing.assert_array_equal(read[1, 0], points[1, 0])


def test_negative_sizes_are_named() -> None:
    """rosbags messages take any integer (a corrupted bag): a negative height is not an "empty" cloud."""
    cloud = _message('rosbags', fields=_XYZ, height=-2, width=2, point_step=12, row_step=24, data=bytes(48))
    with pytest.raises(PointCloudError, match='negative size: height -2, width 2'):
        pointcloud2_to_xyz(cloud)


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_a_count_zero_field_does_not_shadow_a_real_one(flavour: str) -> None:
    """count 0 declares no bytes: a later count-0 'x' of another datatype must not hide the real x."""
    points = np.arange(12, dtype='<f4').reshape(2, 2, 3)
    cloud = _message(
        flavour,
        fields=[*_XYZ, ('x', 0, FLOAT64, 0)],
        height=2,
        width=2,
        point_step=12,
        row_step=24,
        data=points.tobytes(),
    )
    np.testing.assert_array_equal(pointcloud2_to_xyz(cloud), points)
