"""``process_bag`` / ``ppe bag``: bags of clouds in, bags of planes out, read back and checked.

Input bags are written with rosbags from small generated scans (24 x 32) and, with the shared
data, from the three consecutive Ouster OS-1-128 sweeps. Outputs are read back with rosbags and
compared as messages (never as bytes) with what the node's processing function gives for the same
frame, and with ``ppe extract``.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from ppe_ros.cli import main as ppe_main
from ppe_ros.core.synthetic import plane_scan
from ppe_ros.io import load_scan
from ppe_ros.ros import bag as bag_module
from ppe_ros.ros.bag import BagOptions, main, output_topics, process_bag
from ppe_ros.ros.bag import frames as bag_frames
from ppe_ros.ros.messages import rosbags_message_types
from ppe_ros.ros.pointcloud2 import pointcloud2_to_structured, structured_to_pointcloud2, xyz_to_pointcloud2
from ppe_ros.ros.processing import ExtractorParams, process_cloud

REPO = Path(__file__).resolve().parents[1]
JAZZY = get_typestore(Stores.ROS2_JAZZY)
NOETIC = get_typestore(Stores.ROS1_NOETIC)
TYPES = rosbags_message_types(JAZZY)
POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
TOPIC = '/sensor/points'
OUTPUTS = {
    'labeled_points': '/sensor/planes/labeled_points',
    'markers': '/sensor/planes/markers',
    'plane_table': '/sensor/planes',
}
FRAME_ID = 'os_lidar'
#: Bag (receive) time = header stamp + this, so that the two are told apart.
RECEIVE_DELAY_NS = 7_000_000
OUSTER_FRAMES = [f'OS-1-128_v2.3.0_1024x10_lb_n3_frame{n}_xyz_m.npy' for n in (1795, 1796, 1797)]


# --------------------------------------------------------------------------------------------
# building and reading bags
# --------------------------------------------------------------------------------------------


def stamp_of(index: int) -> tuple[int, int]:
    return 1_700_000_000 + index, (100_000_000 * index + 123) % 1_000_000_000


def bag_time(index: int) -> int:
    sec, nanosec = stamp_of(index)
    return sec * 10**9 + nanosec + RECEIVE_DELAY_NS


def header(store, index: int, frame_id: str = FRAME_ID):
    types = store.types
    stamp = types['builtin_interfaces/msg/Time'](sec=stamp_of(index)[0], nanosec=stamp_of(index)[1])
    if 'seq' in types['std_msgs/msg/Header'].__dataclass_fields__:  # ROS 1
        return types['std_msgs/msg/Header'](seq=index, stamp=stamp, frame_id=frame_id)
    return types['std_msgs/msg/Header'](stamp=stamp, frame_id=frame_id)


def cloud(store, index: int, points: np.ndarray, *, pad_bytes: int = 0):
    """An organized cloud of ``points`` (x y z float32, plus an unused field of ``pad_bytes``)."""
    types = store.types
    if not pad_bytes:
        return xyz_to_pointcloud2(
            points,
            header=header(store, index),
            msg_class=types[POINTCLOUD2],
            field_class=types['sensor_msgs/msg/PointField'],
        )
    table = np.zeros(
        points.shape[:2], dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('padding', '<u4', (pad_bytes // 4,))]
    )
    table['x'], table['y'], table['z'] = points[..., 0], points[..., 1], points[..., 2]
    return structured_to_pointcloud2(
        table,
        header=header(store, index),
        msg_class=types[POINTCLOUD2],
        field_class=types['sensor_msgs/msg/PointField'],
    )


def serialized(store, msg) -> bytes:
    if store is NOETIC:
        return bytes(NOETIC.serialize_ros1(msg, POINTCLOUD2))
    return bytes(JAZZY.serialize_cdr(msg, POINTCLOUD2))


def write_rosbag2(
    path: Path,
    messages: list[tuple[int, bytes]],
    *,
    storage: str = 'mcap',
    topic: str = TOPIC,
    compressed: bool = False,
    chatter: bool = True,
) -> Path:
    """A rosbag2 with ``messages`` (bag time, CDR) on ``topic`` and, with ``chatter``, a String topic."""
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3)
    if compressed:
        writer.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
    writer.open()
    clouds = writer.add_connection(topic, POINTCLOUD2, typestore=JAZZY)
    strings = writer.add_connection('/chatter', 'std_msgs/msg/String', typestore=JAZZY) if chatter else None
    for timestamp, raw in messages:
        writer.write(clouds, timestamp, raw)
        if strings is not None:
            text = JAZZY.types['std_msgs/msg/String'](data=f'at {timestamp}')
            writer.write(strings, timestamp + 1, JAZZY.serialize_cdr(text, 'std_msgs/msg/String'))
    writer.close()
    return path


def write_ros1(path: Path, messages: list[tuple[int, bytes]], *, chunk_bytes: int | None = None) -> Path:
    writer = Ros1Writer(path)
    if chunk_bytes is not None:
        writer.chunk_threshold = chunk_bytes
    writer.open()
    connection = writer.add_connection(TOPIC, POINTCLOUD2, typestore=NOETIC)
    for timestamp, raw in messages:
        writer.write(connection, timestamp, raw)
    writer.close()
    return path


def read_bag(path: Path) -> dict[str, list[tuple[int, object]]]:
    """Topic -> [(bag time, deserialized message)] of a bag, in time order."""
    out: dict[str, list[tuple[int, object]]] = {}
    with AnyReader([Path(path)], default_typestore=JAZZY) as reader:
        for connection, timestamp, raw in reader.messages():
            out.setdefault(connection.topic, []).append((timestamp, reader.deserialize(raw, connection.msgtype)))
        types = {c.topic: c.msgtype for c in reader.connections}
    out['__types__'] = types  # type: ignore[assignment]
    return out


def labels_of(msg) -> np.ndarray:
    return np.array(pointcloud2_to_structured(msg)['label'])


def table_of(msg) -> np.ndarray:
    return np.array(pointcloud2_to_structured(msg, allow_empty=True))


def same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal unlabelled pixels (0) and a one-to-one correspondence of the plane labels."""
    if a.shape != b.shape or not np.array_equal(a == 0, b == 0):
        return False
    pairs = np.unique(np.stack([a[a > 0], b[b > 0]], axis=1), axis=0)
    return len(np.unique(pairs[:, 0])) == len(pairs) == len(np.unique(pairs[:, 1]))


def header_key(msg_header) -> tuple[int, int, str]:
    """A header as values (messages read from two bags have different classes)."""
    return msg_header.stamp.sec, msg_header.stamp.nanosec, msg_header.frame_id


def assert_header(msg_header, index: int) -> None:
    assert (msg_header.stamp.sec, msg_header.stamp.nanosec) == stamp_of(index)
    assert msg_header.frame_id == FRAME_ID


def run_cli(argv: list[str]) -> int:
    return main([str(a) for a in argv] + ['--no-progress'])


# --------------------------------------------------------------------------------------------
# fixtures
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope='module')
def scans() -> list[np.ndarray]:
    """Three noisy 24 x 32 scans of a floor and two walls."""
    return [plane_scan(3, rows=24, cols=32, radial_sigma=0.005, seed=seed).points for seed in (1, 2, 3)]


@pytest.fixture(scope='module')
def ros2_messages(scans) -> list[tuple[int, bytes]]:
    return [(bag_time(i), serialized(JAZZY, cloud(JAZZY, i, points))) for i, points in enumerate(scans)]


@pytest.fixture(scope='module')
def expected(scans):
    """What the node's processing gives for each frame with the default parameters."""
    return [process_cloud(cloud(JAZZY, i, points), ExtractorParams(), TYPES) for i, points in enumerate(scans)]


@pytest.fixture(scope='module')
def mcap_bag(tmp_path_factory, ros2_messages) -> Path:
    return write_rosbag2(tmp_path_factory.mktemp('in') / 'scans', ros2_messages)


def check_outputs(out: dict, expected, indices: list[int]) -> None:
    """The three outputs of frames ``indices``: times, headers, labels, plane table, markers."""
    for kind, topic in OUTPUTS.items():
        assert [t for t, _ in out[topic]] == [bag_time(i) for i in indices], kind
    for (_, labeled), (_, table), (_, markers), i in zip(
        out[OUTPUTS['labeled_points']], out[OUTPUTS['plane_table']], out[OUTPUTS['markers']], indices, strict=True
    ):
        frame = expected[i]
        assert_header(labeled.header, i)
        assert_header(table.header, i)
        assert (labeled.height, labeled.width) == frame.points.shape[:2]
        np.testing.assert_array_equal(labels_of(labeled), frame.planes.labels)
        np.testing.assert_array_equal(table_of(table), table_of(frame.plane_table))
        want = TYPES.decode_markers(frame.markers)
        assert len(markers.markers) == len(want.markers) > 1
        for got_marker, want_marker in zip(markers.markers, want.markers, strict=True):
            assert (got_marker.ns, got_marker.id, got_marker.type) == (want_marker.ns, want_marker.id, want_marker.type)
            assert len(got_marker.points) == len(want_marker.points)
            if got_marker.ns:  # the first marker is DELETEALL
                assert_header(got_marker.header, i)


# --------------------------------------------------------------------------------------------
# output topic names
# --------------------------------------------------------------------------------------------


def test_output_topics_replace_the_last_name_like_the_node():
    names = output_topics(['/ouster/points', '/points'])
    assert names['/ouster/points'] == {
        'labeled_points': '/ouster/planes/labeled_points',
        'markers': '/ouster/planes/markers',
        'plane_table': '/ouster/planes',
    }
    assert names['/points'] == {
        'labeled_points': '/planes/labeled_points',
        'markers': '/planes/markers',
        'plane_table': '/planes',
    }


def test_output_topics_fall_back_under_the_input_when_they_would_collide():
    names = output_topics(['/a/front', '/a/back', '/b/points'], kinds=['plane_table'])
    assert names == {
        '/a/front': {'plane_table': '/a/front/planes'},
        '/a/back': {'plane_table': '/a/back/planes'},
        '/b/points': {'plane_table': '/b/planes'},
    }
    # an output equal to a copied input topic moves as well
    assert output_topics(['/x/planes'], kinds=['plane_table'], reserved=['/x/planes']) == {
        '/x/planes': {'plane_table': '/x/planes/planes'}
    }


# --------------------------------------------------------------------------------------------
# rosbag2 and ROS 1 in, rosbag2 out
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ('input_storage', 'compressed', 'output_storage'),
    [
        ('mcap', False, 'sqlite3'),
        ('sqlite3', False, 'mcap'),
        ('mcap', True, 'mcap'),
    ],
)
def test_outputs_are_the_nodes_at_the_input_times(
    tmp_path, ros2_messages, expected, input_storage, compressed, output_storage
):
    source = write_rosbag2(tmp_path / 'in', ros2_messages, storage=input_storage, compressed=compressed)
    report = process_bag(BagOptions(source, tmp_path / 'out', storage=output_storage, progress=False))
    assert report.exit_code == 0
    assert (report.frames_read, report.frames_processed, report.frames_skipped) == (3, 3, 0)
    out = read_bag(tmp_path / 'out')
    assert out['__types__'] == {
        OUTPUTS['labeled_points']: POINTCLOUD2,
        OUTPUTS['plane_table']: POINTCLOUD2,
        OUTPUTS['markers']: 'visualization_msgs/msg/MarkerArray',
    }
    check_outputs(out, expected, [0, 1, 2])
    metadata = (tmp_path / 'out' / 'metadata.yaml').read_text()
    assert f'storage_identifier: {output_storage}' in metadata
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith('.')] == []  # no staging left


def test_cli_names_the_topics_and_prints_the_summary(tmp_path, mcap_bag, capsys):
    assert run_cli([mcap_bag, tmp_path / 'out']) == 0
    stdout = capsys.readouterr().out
    assert f'processing every {POINTCLOUD2} topic' in stdout
    assert f'{TOPIC} (3 messages) -> {", ".join(OUTPUTS.values())}' in stdout
    assert f'| {TOPIC} | 3 | 3 | 0 |' in stdout
    assert re.search(r'wrote \S*out \(mcap\): 9 messages; 3 frames in', stdout)


def test_ppe_bag_runs_the_same_command(tmp_path, mcap_bag, expected, capsys):
    assert (
        ppe_main(
            [
                'bag',
                str(mcap_bag),
                str(tmp_path / 'out'),
                '--topic',
                'sensor/points',
                '--storage',
                'sqlite3',
                '--no-progress',
            ]
        )
        == 0
    )
    check_outputs(read_bag(tmp_path / 'out'), expected, [0, 1, 2])
    assert ppe_main(['bag', str(mcap_bag), str(tmp_path / 'out'), '--no-progress']) == 2
    assert 'ppe bag: error:' in capsys.readouterr().err


def test_ros1_bag_gives_the_same_outputs_and_is_copied_as_ros2(tmp_path, scans, expected):
    ros1 = [(bag_time(i), serialized(NOETIC, cloud(NOETIC, i, points))) for i, points in enumerate(scans)]
    source = write_ros1(tmp_path / 'in.bag', ros1)
    assert run_cli([source, tmp_path / 'out', '--copy-input']) == 0
    out = read_bag(tmp_path / 'out')
    check_outputs(out, expected, [0, 1, 2])
    copied = out[TOPIC]
    assert [t for t, _ in copied] == [bag_time(i) for i in range(3)]
    assert out['__types__'][TOPIC] == POINTCLOUD2
    for i, (_, msg) in enumerate(copied):
        assert_header(msg.header, i)
        assert not hasattr(msg.header, 'seq')  # a ROS 2 header
        points = np.stack([pointcloud2_to_structured(msg)[axis] for axis in 'xyz'], axis=-1)
        np.testing.assert_array_equal(points, scans[i].astype(np.float32))


def test_copy_input_copies_rosbag2_messages(tmp_path, mcap_bag, ros2_messages):
    assert run_cli([mcap_bag, tmp_path / 'out', '--copy-input']) == 0
    out = read_bag(tmp_path / 'out')
    assert '/chatter' not in out
    originals = [JAZZY.deserialize_cdr(raw, POINTCLOUD2) for _, raw in ros2_messages]
    assert [t for t, _ in out[TOPIC]] == [t for t, _ in ros2_messages]
    for (_, copy), original in zip(out[TOPIC], originals, strict=True):
        assert (copy.height, copy.width, copy.point_step, copy.header.frame_id) == (
            original.height,
            original.width,
            original.point_step,
            original.header.frame_id,
        )
        np.testing.assert_array_equal(copy.data, original.data)


def test_params_file_is_the_nodes(tmp_path, mcap_bag, scans):
    params_file = tmp_path / 'params.yaml'
    params_file.write_text(
        'extractor:\n  ros__parameters:\n    max_error_increment: 0.001\n'
        '    min_plane_points: 5\n    publish_markers: false\n'
    )
    assert run_cli([mcap_bag, tmp_path / 'out', '--params', params_file]) == 0
    out = read_bag(tmp_path / 'out')
    assert OUTPUTS['markers'] not in out['__types__']
    params = ExtractorParams(max_error_increment=0.001, min_plane_points=5, publish_markers=False)
    for i, (_, labeled) in enumerate(out[OUTPUTS['labeled_points']]):
        frame = process_cloud(cloud(JAZZY, i, scans[i]), params, TYPES)
        np.testing.assert_array_equal(labels_of(labeled), frame.planes.labels)
    with AnyReader([tmp_path / 'out'], default_typestore=JAZZY):
        pass
    custom = (tmp_path / 'out' / 'metadata.yaml').read_text()
    assert 'ppe_ros.process_bag' in custom and 'max_error_increment' in custom


def test_jobs_2_writes_the_same_bag_as_jobs_1(tmp_path, scans):
    messages = [(bag_time(i), serialized(JAZZY, cloud(JAZZY, i, scans[i % 3]))) for i in range(7)]
    source = write_rosbag2(tmp_path / 'in', messages)
    assert run_cli([source, tmp_path / 'one', '--jobs', '1']) == 0
    assert run_cli([source, tmp_path / 'two', '--jobs', '2']) == 0
    one, two = read_bag(tmp_path / 'one'), read_bag(tmp_path / 'two')
    assert one['__types__'] == two['__types__']
    for topic in OUTPUTS.values():
        assert [t for t, _ in one[topic]] == [t for t, _ in two[topic]] == [t for t, _ in messages]
    for (_, a), (_, b) in zip(one[OUTPUTS['labeled_points']], two[OUTPUTS['labeled_points']], strict=True):
        np.testing.assert_array_equal(labels_of(a), labels_of(b))
        assert header_key(a.header) == header_key(b.header)
    for (_, a), (_, b) in zip(one[OUTPUTS['plane_table']], two[OUTPUTS['plane_table']], strict=True):
        np.testing.assert_array_equal(table_of(a), table_of(b))
    for (_, a), (_, b) in zip(one[OUTPUTS['markers']], two[OUTPUTS['markers']], strict=True):
        assert len(a.markers) == len(b.markers)
        for ma, mb in zip(a.markers, b.markers, strict=True):
            assert (ma.ns, ma.id, header_key(ma.header)) == (mb.ns, mb.id, header_key(mb.header))
            np.testing.assert_array_equal([(p.x, p.y, p.z) for p in ma.points], [(p.x, p.y, p.z) for p in mb.points])


# --------------------------------------------------------------------------------------------
# bad frames are skipped and counted
# --------------------------------------------------------------------------------------------


def test_bad_frames_are_skipped_with_the_reason_and_counted(tmp_path, scans, expected, capsys):
    types = JAZZY.types
    flat = scans[1].reshape(-1, 3)  # height 1 with a ring field of no beam numbers: no range image
    ringed = np.zeros(len(flat), [('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('ring', '<i4')])
    ringed['x'], ringed['y'], ringed['z'], ringed['ring'] = *flat.T, -5
    unorganized = structured_to_pointcloud2(
        ringed, header=header(JAZZY, 1), msg_class=types[POINTCLOUD2], field_class=types['sensor_msgs/msg/PointField']
    )
    all_nan = cloud(JAZZY, 2, np.full_like(scans[2], np.nan))
    messages = [
        (bag_time(0), serialized(JAZZY, cloud(JAZZY, 0, scans[0]))),
        (bag_time(1), serialized(JAZZY, unorganized)),
        (bag_time(2), serialized(JAZZY, all_nan)),
        (bag_time(3), b'\x00\x01\x00\x00not a point cloud'),
        (bag_time(4), bytes(JAZZY.serialize_cdr(types['std_msgs/msg/String'](data='x' * 40), 'std_msgs/msg/String'))),
        (bag_time(5), serialized(JAZZY, cloud(JAZZY, 2, scans[2]))),
    ]
    source = write_rosbag2(tmp_path / 'in', messages, chatter=False)
    assert run_cli([source, tmp_path / 'out']) == 0
    captured = capsys.readouterr()
    assert f'| {TOPIC} | 6 | 2 | 4 |' in captured.out
    assert 'unorganized cloud (height 1' in captured.err
    assert 'has no finite point' in captured.err
    assert captured.err.count('(undecodable): the message does not decode as sensor_msgs/msg/PointCloud2') == 2
    assert 'skipped on /sensor/points: 2 x undecodable' in captured.out
    out = read_bag(tmp_path / 'out')
    for topic in OUTPUTS.values():
        assert [t for t, _ in out[topic]] == [bag_time(0), bag_time(5)]
    np.testing.assert_array_equal(labels_of(out[OUTPUTS['labeled_points']][1][1]), expected[2].planes.labels)


# --------------------------------------------------------------------------------------------
# clear errors, nothing written
# --------------------------------------------------------------------------------------------


def _bag_of_strings(tmp_path: Path) -> Path:
    writer = Writer(tmp_path / 'strings', version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    connection = writer.add_connection('/chatter', 'std_msgs/msg/String', typestore=JAZZY)
    writer.write(
        connection, 1, JAZZY.serialize_cdr(JAZZY.types['std_msgs/msg/String'](data='hi'), 'std_msgs/msg/String')
    )
    writer.close()
    return tmp_path / 'strings'


@pytest.mark.parametrize(
    ('case', 'message'),
    [
        ('missing', 'no such file or directory'),
        ('text file', 'is not a bag'),
        ('empty directory', 'is a directory but not a rosbag2 bag'),
        ('misnamed mcap', 'rename it to end in .mcap'),
        ('no pointcloud2', f'has no {POINTCLOUD2} topic and no depth image topic'),
        ('unknown topic', "topic '/lidar' is not in"),
        ('not a pointcloud2 topic', f'topic /chatter has type std_msgs/msg/String, not {POINTCLOUD2} or '),
        ('missing params', 'cannot read params file'),
        ('invalid params', 'max_error_increment must be'),
    ],
)
def test_clear_errors_and_no_output(tmp_path, mcap_bag, capsys, case, message):
    argv: list = [mcap_bag, tmp_path / 'out']
    if case == 'missing':
        argv[0] = tmp_path / 'nothing_here'
    elif case == 'text file':
        argv[0] = tmp_path / 'notes.bag'
        argv[0].write_text('hello\n')
    elif case == 'empty directory':
        argv[0] = tmp_path / 'empty'
        argv[0].mkdir()
    elif case == 'misnamed mcap':
        argv[0] = tmp_path / 'scans.bin'
        argv[0].write_bytes(next(mcap_bag.glob('*.mcap')).read_bytes())
    elif case == 'no pointcloud2':
        argv[0] = _bag_of_strings(tmp_path)
    elif case == 'unknown topic':
        argv += ['--topic', '/lidar']
    elif case == 'not a pointcloud2 topic':
        argv += ['--topic', '/chatter']
    elif case == 'missing params':
        argv += ['--params', tmp_path / 'missing.yaml']
    elif case == 'invalid params':
        (tmp_path / 'bad.yaml').write_text('extractor:\n  ros__parameters:\n    max_error_increment: -1.0\n')
        argv += ['--params', tmp_path / 'bad.yaml']
    assert run_cli(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith('process_bag: error: ')
    assert message in err
    assert not (tmp_path / 'out').exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith('.out')]


def test_existing_output_is_replaced_only_with_force(tmp_path, mcap_bag, capsys):
    old = tmp_path / 'out'
    old.mkdir()
    (old / 'keep.txt').write_text('mine')
    assert run_cli([mcap_bag, old]) == 2
    assert 'exists; use --force to replace it' in capsys.readouterr().err
    assert (old / 'keep.txt').read_text() == 'mine'
    assert run_cli([mcap_bag, old, '--force']) == 0
    assert not (old / 'keep.txt').exists()
    assert len(read_bag(old)[OUTPUTS['markers']]) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ['out']


@pytest.mark.parametrize('where', ['input itself', 'inside the input', 'parent of the input'])
def test_the_input_is_never_overwritten(tmp_path, ros2_messages, capsys, where):
    source = write_rosbag2(tmp_path / 'bags' / 'in', ros2_messages)
    before = sorted((p.name, p.stat().st_size) for p in source.iterdir())
    target = {'input itself': source, 'inside the input': source / 'out', 'parent of the input': source.parent}[where]
    assert run_cli([source, target, '--force']) == 2
    assert 'refusing to write' in capsys.readouterr().err
    assert sorted((p.name, p.stat().st_size) for p in source.iterdir()) == before
    assert len(read_bag(source)[TOPIC]) == 3


# --------------------------------------------------------------------------------------------
# damaged input and Ctrl-C: a valid output with every frame before
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope='module')
def big_frames(scans) -> list[tuple[int, bytes]]:
    """Six frames of 1.1 MB each (a padding field): one MCAP chunk each, like real lidar clouds."""
    return [(bag_time(i), serialized(JAZZY, cloud(JAZZY, i, scans[i % 3], pad_bytes=1424))) for i in range(6)]


@pytest.fixture(scope='module')
def big_expected(scans):
    return [process_cloud(cloud(JAZZY, i, scans[i % 3]), ExtractorParams(), TYPES) for i in range(6)]


def _check_partial(out_dir: Path, expected_frames, at_least: int, fewer_than: int) -> int:
    out = read_bag(out_dir)
    count = len(out[OUTPUTS['labeled_points']])
    assert at_least <= count < fewer_than
    check_outputs(out, expected_frames, list(range(count)))
    return count


def test_truncated_mcap_keeps_the_frames_before_the_damage(tmp_path, big_frames, big_expected, capsys):
    source = write_rosbag2(tmp_path / 'in', big_frames, chatter=False)
    storage = next(source.glob('*.mcap'))
    with storage.open('r+b') as handle:  # a recorder killed in the middle of frame 4
        handle.truncate(int(storage.stat().st_size * 0.6))
    assert run_cli([source, tmp_path / 'out']) == 1
    err = capsys.readouterr().err
    assert 'has no usable MCAP footer or summary' in err
    assert re.search(r'error: \S+ is damaged', err)
    assert 'out is a complete, valid bag of the 3 frames processed before that' in err
    assert _check_partial(tmp_path / 'out', big_expected, 3, 4) == 3


@pytest.mark.parametrize(
    ('metadata', 'note'),
    [(None, 'has no metadata.yaml'), ('rosbag2_bagfile_information: [', 'reading its storage files')],
)
def test_rosbag2_without_usable_metadata_is_read_from_its_storage_file(
    tmp_path, ros2_messages, expected, capsys, metadata, note
):
    source = write_rosbag2(tmp_path / 'in', ros2_messages, storage='sqlite3')
    if metadata is None:
        (source / 'metadata.yaml').unlink()
    else:
        (source / 'metadata.yaml').write_text(metadata)
    assert run_cli([source, tmp_path / 'out']) == 0
    assert note in capsys.readouterr().err
    check_outputs(read_bag(tmp_path / 'out'), expected, [0, 1, 2])


def test_corrupt_sqlite3_keeps_the_frames_before_the_damage(tmp_path, scans, capsys):
    messages = [(bag_time(i), serialized(JAZZY, cloud(JAZZY, i, scans[i % 3]))) for i in range(10)]
    frames = [process_cloud(cloud(JAZZY, i, scans[i % 3]), ExtractorParams(), TYPES) for i in range(10)]
    source = write_rosbag2(tmp_path / 'in', messages, storage='sqlite3', chatter=False)
    database = next(source.glob('*.db3'))
    content = database.read_bytes()
    # points at byte 5000 of a message lie in its first overflow page (4 KiB pages); frames 2, 5 and 8
    # hold the same points, stored in this order
    needle = messages[5][1][5000:5064]
    offsets = [match.start() for match in re.finditer(re.escape(needle), content)]
    assert len(offsets) == 3
    offset = offsets[1]
    with database.open('r+b') as handle:  # that page overwritten: its link to the next one is lost
        handle.seek(offset // 4096 * 4096)
        handle.write(b'\xff' * 4096)
    assert run_cli([source, tmp_path / 'out']) == 1
    err = capsys.readouterr().err
    assert 'is damaged after 5 frames: CorruptError: database disk image is malformed' in err
    assert _check_partial(tmp_path / 'out', frames, 5, 6) == 5


def test_truncated_ros1_bag_keeps_the_frames_before_the_damage(tmp_path, scans, capsys):
    messages = [(bag_time(i), serialized(NOETIC, cloud(NOETIC, i, scans[i % 3]))) for i in range(6)]
    frames = [process_cloud(cloud(JAZZY, i, scans[i % 3]), ExtractorParams(), TYPES) for i in range(6)]
    source = write_ros1(tmp_path / 'in.bag', messages, chunk_bytes=10_000)  # one chunk per frame
    with source.open('r+b') as handle:
        handle.truncate(int(source.stat().st_size * 0.6))
    assert run_cli([source, tmp_path / 'out']) == 1
    err = capsys.readouterr().err
    assert 'the ROS 1 bag has no usable index' in err
    assert _check_partial(tmp_path / 'out', frames, 3, 4) == 3


def test_ctrl_c_closes_a_valid_bag_with_the_frames_done(tmp_path, scans, monkeypatch, capsys):
    messages = [(bag_time(i), serialized(JAZZY, cloud(JAZZY, i, scans[i % 3]))) for i in range(6)]
    frames = [process_cloud(cloud(JAZZY, i, scans[i % 3]), ExtractorParams(), TYPES) for i in range(6)]
    source = write_rosbag2(tmp_path / 'in', messages, storage='sqlite3')
    original = bag_module.FrameProcessor.process
    calls = []

    def process_then_interrupt(self, raw, encoding, convert_copy=False):
        result = original(self, raw, encoding, convert_copy)
        calls.append(1)
        if len(calls) == 2:
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C while frame 2 is processed
        return result

    monkeypatch.setattr(bag_module.FrameProcessor, 'process', process_then_interrupt)
    previous = signal.getsignal(signal.SIGINT)
    assert run_cli([source, tmp_path / 'out']) == 130
    assert signal.getsignal(signal.SIGINT) is previous
    err = capsys.readouterr().err
    assert 'interrupted: closing' in err
    assert 'stopped: interrupted (SIGINT) after 2 frames' in err
    assert _check_partial(tmp_path / 'out', frames, 2, 3) == 2


def test_a_second_ctrl_c_drops_the_frame_in_progress(tmp_path, scans, monkeypatch, capsys):
    messages = [(bag_time(i), serialized(JAZZY, cloud(JAZZY, i, scans[i % 3]))) for i in range(6)]
    frames = [process_cloud(cloud(JAZZY, i, scans[i % 3]), ExtractorParams(), TYPES) for i in range(6)]
    source = write_rosbag2(tmp_path / 'in', messages)
    original = bag_module.FrameProcessor.process
    calls = []

    def process_interrupted_twice(self, raw, encoding, convert_copy=False):
        calls.append(1)
        if len(calls) == 2:
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)  # raises KeyboardInterrupt here: frame 2 is dropped
        return original(self, raw, encoding, convert_copy)

    monkeypatch.setattr(bag_module.FrameProcessor, 'process', process_interrupted_twice)
    assert run_cli([source, tmp_path / 'out']) == 130
    assert 'interrupted (SIGINT) after 2 frames; 1 frame in flight dropped' in capsys.readouterr().err
    assert _check_partial(tmp_path / 'out', frames, 1, 2) == 1


def test_a_frame_that_fails_is_skipped_and_the_run_goes_on(tmp_path, mcap_bag, expected, monkeypatch, capsys):
    original = bag_frames.process_cloud

    def fail_on_the_second_frame(msg, params, types, *, outputs=None):
        if msg.header.stamp.sec == stamp_of(1)[0]:
            raise RuntimeError('kernel exploded')
        return original(msg, params, types, outputs=outputs)

    monkeypatch.setattr(bag_frames, 'process_cloud', fail_on_the_second_frame)
    assert run_cli([mcap_bag, tmp_path / 'out']) == 0
    captured = capsys.readouterr()
    assert '(failed): processing failed: RuntimeError: kernel exploded' in captured.err
    assert f'| {TOPIC} | 3 | 2 | 1 |' in captured.out
    out = read_bag(tmp_path / 'out')
    assert [t for t, _ in out[OUTPUTS['plane_table']]] == [bag_time(0), bag_time(2)]


def test_ctrl_c_with_worker_processes(tmp_path, scans):
    """The real thing: SIGINT to ``process_bag --jobs 2`` in the middle of a run."""
    count = 300
    messages = [(bag_time(i), serialized(JAZZY, cloud(JAZZY, i, scans[i % 3]))) for i in range(count)]
    source = write_rosbag2(tmp_path / 'in', messages, chatter=False)
    script = 'import sys; from ppe_ros.ros.bag import main; sys.exit(main())'
    process = subprocess.Popen(
        [sys.executable, '-c', script, str(source), str(tmp_path / 'out'), '--jobs', '2', '--progress'],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=REPO,
    )
    seen = bytearray()

    def read_stderr():
        while chunk := process.stderr.read1(4096):
            seen.extend(chunk)

    reader = threading.Thread(target=read_stderr)
    reader.start()
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and process.poll() is None:
        done = [int(n) for n in re.findall(rb'(\d+)/%d' % count, bytes(seen))]
        if done and max(done) >= 3:
            process.send_signal(signal.SIGINT)
            break
        time.sleep(0.05)
    try:
        returncode = process.wait(timeout=120)
    finally:
        process.kill()
        reader.join()
    stdout = process.stdout.read().decode()
    assert returncode == 130, (stdout, seen.decode(errors='replace')[-2000:])
    assert 'interrupted' in seen.decode(errors='replace')
    out = read_bag(tmp_path / 'out')
    written = [t for t, _ in out[OUTPUTS['labeled_points']]]
    assert 3 <= len(written) < count
    assert written == [bag_time(i) for i in range(len(written))]  # in input order, no gap
    for topic in OUTPUTS.values():
        assert len(out[topic]) == len(written)


# --------------------------------------------------------------------------------------------
# real Ouster sweeps
# --------------------------------------------------------------------------------------------


@pytest.mark.shared_data
def test_three_ouster_sweeps_match_ppe_extract(tmp_path, shared_data):
    folder = shared_data / 'ouster'
    points = [load_scan(folder / name).points for name in OUSTER_FRAMES]
    messages = [(bag_time(i), serialized(JAZZY, cloud(JAZZY, i, p))) for i, p in enumerate(points)]
    source = write_rosbag2(tmp_path / 'in', messages)
    params_file = tmp_path / 'params.yaml'
    params_file.write_text(
        '/**:\n  ros__parameters:\n    max_error_increment: 0.0484\n'
        '    max_neighbor_distance: 0.18\n    min_plane_points: 4\n'
    )
    assert run_cli([source, tmp_path / 'out', '--params', params_file, '--topic', TOPIC]) == 0
    out = read_bag(tmp_path / 'out')
    for topic in OUTPUTS.values():
        assert [t for t, _ in out[topic]] == [bag_time(i) for i in range(3)]
    labeled = [msg for _, msg in out[OUTPUTS['labeled_points']]]
    tables = [msg for _, msg in out[OUTPUTS['plane_table']]]
    for i, (cloud_msg, table) in enumerate(zip(labeled, tables, strict=True)):
        assert_header(cloud_msg.header, i)
        assert_header(table.header, i)
        assert (cloud_msg.height, cloud_msg.width) == (128, 1024)
        labels = labels_of(cloud_msg)
        assert table.width == labels.max() > 20
        np.testing.assert_array_equal(np.bincount(labels.ravel())[1:], table_of(table)['point_count'][0])
    # ppe extract on the same frame (its points as the bag holds them, rays from the origin)
    npy = tmp_path / 'frame1795.npy'
    np.save(npy, points[0].astype(np.float32))
    assert (
        ppe_main(
            [
                'extract',
                str(npy),
                '-o',
                str(tmp_path / 'planes.npz'),
                '-e',
                '0.0484',
                '--lmax',
                '0.18',
                '--min-plane-points',
                '4',
            ]
        )
        == 0
    )
    with np.load(tmp_path / 'planes.npz') as planes:
        assert same_partition(labels_of(labeled[0]), planes['labels'])
        assert json.loads(str(planes['meta']))['max_neighbor_distance'] == 0.18


# --------------------------------------------------------------------------------------------
# issue 17: hard links, cut and compressed bags, sqlite3 recovery, messages
# --------------------------------------------------------------------------------------------


def _one_line_error(err: str, code: int) -> str:
    """The error of a run that wrote nothing (2) or stopped at damage (1): no traceback, one line."""
    assert 'Traceback' not in err
    lines = [line for line in err.splitlines() if line.startswith('process_bag: error: ')]
    assert len(lines) == 1, err
    return lines[0]


@pytest.fixture(scope='module')
def distinct_frames():
    """Twenty frames of different scans (compress poorly, like real clouds) and what the node gives."""
    scans = [plane_scan(3, rows=24, cols=32, radial_sigma=0.005, seed=100 + i).points for i in range(20)]
    messages = [(bag_time(i), serialized(JAZZY, cloud(JAZZY, i, p))) for i, p in enumerate(scans)]
    frames = [process_cloud(cloud(JAZZY, i, p), ExtractorParams(), TYPES) for i, p in enumerate(scans)]
    return messages, frames


def _cut(file: Path, size: int) -> None:
    with file.open('r+b') as handle:
        handle.truncate(size)


@pytest.mark.parametrize('layout', ['bare file', 'file in a directory bag'])
def test_a_hard_link_to_the_input_is_not_replaced(tmp_path, ros2_messages, capsys, layout):
    source = write_rosbag2(tmp_path / 'bags' / 'in', ros2_messages)
    storage = next(source.glob('*.mcap'))
    if layout == 'bare file':
        source = tmp_path / 'scans.mcap'
        os.link(storage, source)
        storage = source
    link = tmp_path / 'link.mcap'
    os.link(storage, link)
    before = storage.read_bytes()
    assert run_cli([source, link, '--force']) == 2
    assert 'refusing to write' in capsys.readouterr().err
    assert link.is_file() and os.path.samefile(link, storage)
    assert storage.read_bytes() == before


@pytest.mark.parametrize('size', [0, 5, 8, 12])
def test_an_mcap_cut_to_its_magic_is_damaged_not_a_traceback(tmp_path, mcap_bag, capsys, size):
    source = tmp_path / 'cut.mcap'
    source.write_bytes(next(mcap_bag.glob('*.mcap')).read_bytes()[:size])
    assert run_cli([source, tmp_path / 'out']) == 2
    line = _one_line_error(capsys.readouterr().err, 2)
    assert ('is empty' if size == 0 else 'is damaged') in line
    assert not (tmp_path / 'out').exists()


def _file_compressed_bag(path: Path, messages) -> Path:
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.FILE, CompressionFormat.ZSTD)
    writer.open()
    connection = writer.add_connection(TOPIC, POINTCLOUD2, typestore=JAZZY)
    for timestamp, raw in messages:
        writer.write(connection, timestamp, raw)
    writer.close()
    return path


@pytest.mark.parametrize('fraction', [0.0, 0.2, 0.5, 0.9, 0.999])
def test_a_cut_zstd_compressed_bag_keeps_what_decompresses(tmp_path, distinct_frames, capsys, fraction):
    messages, frames = distinct_frames
    source = _file_compressed_bag(tmp_path / 'in', messages)
    storage = next(source.glob('*.mcap.zstd'))
    _cut(storage, int(storage.stat().st_size * fraction))
    code = run_cli([source, tmp_path / 'out'])
    line = _one_line_error(capsys.readouterr().err, code)
    assert 'zstd stream is cut short' in line
    if code == 2:
        assert fraction < 0.9 and 'nothing' in line
        assert not (tmp_path / 'out').exists()
    else:
        assert code == 1 and fraction >= 0.9
        assert _check_partial(tmp_path / 'out', frames, 1, len(frames)) >= 1


@pytest.mark.parametrize('where', [0.0, 0.00003, 0.9999])
def test_a_corrupt_zstd_compressed_bag_is_one_line(tmp_path, distinct_frames, capsys, where):
    """A flipped byte the zstd decoder notices (frame header, last block): damaged, never a traceback."""
    messages, frames = distinct_frames
    source = _file_compressed_bag(tmp_path / 'in', messages)
    storage = next(source.glob('*.mcap.zstd'))
    content = bytearray(storage.read_bytes())
    content[int(len(content) * where)] ^= 0x5A
    storage.write_bytes(bytes(content))
    code = run_cli([source, tmp_path / 'out'])
    line = _one_line_error(capsys.readouterr().err, code)
    assert 'its zstd stream is corrupt' in line
    if where < 0.5:
        assert code == 2 and not (tmp_path / 'out').exists()
    else:  # the blocks before the damaged one are kept
        assert code == 1
        assert _check_partial(tmp_path / 'out', frames, 1, len(frames)) >= 1


@pytest.mark.parametrize('fraction', [0.35, 0.5, 0.8, 0.95])
def test_a_cut_sqlite3_bag_keeps_its_complete_messages(tmp_path, distinct_frames, capsys, fraction):
    messages, frames = distinct_frames
    source = write_rosbag2(tmp_path / 'in', messages, storage='sqlite3', chatter=False)
    database = next(source.glob('*.db3'))
    _cut(database, int(database.stat().st_size * fraction))
    assert run_cli([source, tmp_path / 'out']) == 1
    line = _one_line_error(capsys.readouterr().err, 1)
    recovered = int(re.search(r'read page by page: (\d+) complete messages? recovered', line).group(1))
    # the cut loses at most the messages of the last leaf page and those the cut goes through
    assert int(len(frames) * fraction) - 5 <= recovered < len(frames)
    assert _check_partial(tmp_path / 'out', frames, recovered, recovered + 1) == recovered


@pytest.mark.parametrize('fraction', [0.01, 0.05])
def test_a_sqlite3_bag_cut_before_its_topics_is_damaged(tmp_path, distinct_frames, capsys, fraction):
    source = write_rosbag2(tmp_path / 'in', distinct_frames[0], storage='sqlite3', chatter=False)
    database = next(source.glob('*.db3'))
    _cut(database, int(database.stat().st_size * fraction))
    assert run_cli([source, tmp_path / 'out']) == 2
    assert 'nothing' in _one_line_error(capsys.readouterr().err, 2)
    assert not (tmp_path / 'out').exists()


@pytest.mark.parametrize('kind', ['mcap', 'ros1'])
def test_a_bag_cut_before_its_first_frame_is_damaged(tmp_path, distinct_frames, capsys, kind):
    messages = distinct_frames[0]
    if kind == 'mcap':
        source = write_rosbag2(tmp_path / 'in', messages, chatter=False)
        storage = next(source.glob('*.mcap'))
        first = len(messages[0][1])
    else:
        ros1 = [
            (
                t,
                serialized(
                    NOETIC, cloud(NOETIC, i, plane_scan(3, rows=24, cols=32, radial_sigma=0.005, seed=100 + i).points)
                ),
            )
            for i, (t, _) in enumerate(messages[:4])
        ]
        source = storage = write_ros1(tmp_path / 'in.bag', ros1, chunk_bytes=10_000)
        first = len(ros1[0][1])
    _cut(storage, first // 2)
    assert run_cli([source, tmp_path / 'out']) == 2
    line = _one_line_error(capsys.readouterr().err, 2)
    assert 'is damaged before its first complete' in line
    assert 'its topics: none' not in line
    assert not (tmp_path / 'out').exists()


def test_a_ros1_bag_cut_to_8_bytes_is_damaged_not_not_a_bag(tmp_path, scans, capsys):
    messages = [(bag_time(i), serialized(NOETIC, cloud(NOETIC, i, scans[i]))) for i in range(3)]
    source = write_ros1(tmp_path / 'in.bag', messages)
    _cut(source, 8)
    assert run_cli([source, tmp_path / 'out']) == 2
    line = _one_line_error(capsys.readouterr().err, 2)
    assert 'is damaged: it is cut to 8 bytes, inside the file signature of a ROS 1 bag' in line
    assert 'not a bag' not in line


@pytest.mark.parametrize('kind', ['mcap', 'ros1'])
def test_a_chunk_cut_short_gives_its_complete_frames(tmp_path, distinct_frames, capsys, kind):
    """Small clouds share one chunk (MCAP: 1 MiB; ROS 1: here 30 kB): a cut keeps the frames before it."""
    messages, frames = distinct_frames
    if kind == 'mcap':
        source = write_rosbag2(tmp_path / 'in', messages, chatter=False)
        storage = next(source.glob('*.mcap'))
    else:
        ros1 = [
            (
                t,
                serialized(
                    NOETIC, cloud(NOETIC, i, plane_scan(3, rows=24, cols=32, radial_sigma=0.005, seed=100 + i).points)
                ),
            )
            for i, (t, _) in enumerate(messages)
        ]
        source = storage = write_ros1(tmp_path / 'in.bag', ros1, chunk_bytes=30_000)
    _cut(storage, int(storage.stat().st_size * 0.5))
    assert run_cli([source, tmp_path / 'out']) == 1
    _one_line_error(capsys.readouterr().err, 1)
    assert _check_partial(tmp_path / 'out', frames, len(frames) // 2 - 3, len(frames) // 2 + 1) > 0


@pytest.mark.parametrize(('signum', 'code'), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_second_signal_inside_a_numba_kernel_drops_the_frame(tmp_path, scans, monkeypatch, capsys, signum, code):
    """The second signal's KeyboardInterrupt raised where numba returns to Python comes out as
    ``SystemError: CPUDispatcher(...) returned a result with an exception set`` (its cause the
    KeyboardInterrupt): the frame is dropped, not counted as failed."""
    messages = [(bag_time(i), serialized(JAZZY, cloud(JAZZY, i, scans[i % 3]))) for i in range(6)]
    frames = [process_cloud(cloud(JAZZY, i, scans[i % 3]), ExtractorParams(), TYPES) for i in range(6)]
    source = write_rosbag2(tmp_path / 'in', messages)
    original = bag_frames.process_cloud
    calls = []

    def interrupted_in_the_kernel(msg, params, types, *, outputs=None):
        calls.append(1)
        if len(calls) == 2:
            os.kill(os.getpid(), signum)
            try:
                os.kill(os.getpid(), signum)  # the handler raises here, as where numba boxes a result
            except KeyboardInterrupt as exc:
                raise SystemError(
                    'CPUDispatcher(<function _seed_errors>) returned a result with an exception set'
                ) from exc
        return original(msg, params, types, outputs=outputs)

    monkeypatch.setattr(bag_frames, 'process_cloud', interrupted_in_the_kernel)
    assert run_cli([source, tmp_path / 'out']) == code
    err = capsys.readouterr().err
    assert 'SystemError' not in err and '(failed)' not in err
    assert f'interrupted ({signal.Signals(signum).name}) after 2 frames; 1 frame in flight dropped' in err
    assert _check_partial(tmp_path / 'out', frames, 1, 2) == 1


@pytest.mark.parametrize('entry', ['process_bag', 'ppe bag'])
@pytest.mark.parametrize('signum', [signal.SIGINT, signal.SIGTERM])
def test_signals_after_the_command_line_run_are_ignored_until_exit(tmp_path, monkeypatch, signum, entry):
    """main() of the process's own command line (argv None) ignores a late signal (one that would otherwise
    kill the exiting process and replace its exit code) with SIG_IGN, which the interpreter's shutdown keeps
    (it puts SIG_DFL back only for Python handlers); main(argv) restores what it found."""
    source = write_rosbag2(
        tmp_path / 'in',
        [
            (
                bag_time(0),
                serialized(JAZZY, cloud(JAZZY, 0, plane_scan(3, rows=16, cols=32, radial_sigma=0.005, seed=0).points)),
            )
        ],
    )
    before = signal.getsignal(signum)
    try:
        command = ['process_bag'] if entry == 'process_bag' else ['ppe', 'bag']
        monkeypatch.setattr(sys, 'argv', [*command, str(source), str(tmp_path / 'out'), '--no-progress'])
        assert (main if entry == 'process_bag' else ppe_main)() == 0
        assert signal.getsignal(signum) is signal.SIG_IGN
        os.kill(os.getpid(), signum)  # ignored: no KeyboardInterrupt, no kill
        assert run_cli([source, tmp_path / 'again']) == 0
        assert signal.getsignal(signum) is signal.SIG_IGN  # main(argv) restored what it found
    finally:
        signal.signal(signum, before)


@pytest.mark.parametrize('signum', [signal.SIGINT, signal.SIGTERM])
def test_repeated_signals_during_inline_frames(tmp_path, signum):
    """The real thing: signals every 20 ms into ``process_bag --jobs 1`` on 64 x 512 clouds (each frame
    runs several numba kernels, so a second signal lands between two of them)."""
    clouds = [plane_scan(3, rows=64, cols=512, radial_sigma=0.005, seed=i).points for i in range(6)]
    messages = [(bag_time(i), serialized(JAZZY, cloud(JAZZY, i, p))) for i, p in enumerate(clouds)]
    source = write_rosbag2(tmp_path / 'in', messages, chatter=False)
    script = 'import sys; from ppe_ros.ros.bag import main; sys.exit(main())'
    process = subprocess.Popen(
        [sys.executable, '-c', script, str(source), str(tmp_path / 'out'), '--progress'],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=REPO,
    )
    seen = bytearray()

    def read_stderr():
        while chunk := process.stderr.read1(4096):
            seen.extend(chunk)

    reader = threading.Thread(target=read_stderr)
    reader.start()
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and process.poll() is None and not re.search(rb'[1-9]/6', bytes(seen)):
        time.sleep(0.01)
    stop_at = time.monotonic() + 0.6
    while time.monotonic() < stop_at and process.poll() is None and b'stopped:' not in seen:
        process.send_signal(signum)
        time.sleep(0.02)
    try:
        returncode = process.wait(timeout=120)
    finally:
        process.kill()
        reader.join()
    err = seen.decode(errors='replace')
    assert returncode == 128 + signum, err[-2000:]
    assert 'SystemError' not in err and '(failed)' not in err and 'Traceback' not in err, err[-2000:]
    out = read_bag(tmp_path / 'out')
    written = [t for t, _ in out[OUTPUTS['labeled_points']]]
    assert 1 <= len(written) < 6
    assert written == [bag_time(i) for i in range(len(written))]


def test_an_unknown_key_in_the_params_file_is_a_warning_like_the_node(tmp_path, mcap_bag, scans, capsys):
    params_file = tmp_path / 'params.yaml'
    params_file.write_text(
        'extractor:\n  ros__parameters:\n    min_plane_points: 40\n    max_eror_increment: 0.1\n'
        '    use_sim_time: false\n'
    )
    assert run_cli([mcap_bag, tmp_path / 'out', '--params', params_file]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if 'unknown' in line]
    assert len(warnings) == 1
    assert f"warning: params file {params_file}: ignoring unknown parameter(s) ['max_eror_increment']" in warnings[0]
    params = ExtractorParams(min_plane_points=40)
    frames = [process_cloud(cloud(JAZZY, i, points), params, TYPES) for i, points in enumerate(scans)]
    check_outputs(read_bag(tmp_path / 'out'), frames, [0, 1, 2])
    metadata = (tmp_path / 'out' / 'metadata.yaml').read_text()
    assert 'max_eror_increment' not in metadata and 'min_plane_points' in metadata
