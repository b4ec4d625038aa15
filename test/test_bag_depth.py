"""``process_bag`` on depth camera bags: depth images with the camera info beside them, as the node takes them."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from depth_frames import camera_info, corner_depth, depth_image, message_header
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from ppe_ros.ros.bag import BagOptions, main, process_bag
from ppe_ros.ros.depth_image import DepthFrame
from ppe_ros.ros.messages import rosbags_message_types
from ppe_ros.ros.pointcloud2 import pointcloud2_to_structured
from ppe_ros.ros.processing import ExtractorParams, process_depth_image

JAZZY = get_typestore(Stores.ROS2_JAZZY)
NOETIC = get_typestore(Stores.ROS1_NOETIC)
TYPES = rosbags_message_types(JAZZY)
IMAGE, CAMERA_INFO = 'sensor_msgs/msg/Image', 'sensor_msgs/msg/CameraInfo'
DEPTH, DEPTH_INFO = '/camera/depth/image_rect_raw', '/camera/depth/camera_info'
COLOR, COLOR_INFO = '/camera/color/image_raw', '/camera/color/camera_info'
OUTPUTS = ('/camera/depth/planes/labeled_points', '/camera/depth/planes/markers', '/camera/depth/planes')
PARAMS = ExtractorParams(sensor='depth_camera', min_plane_points=20)


def frames() -> list[np.ndarray]:
    """Four depth images (mm, 16UC1) of a wall at 1.8-2.1 m above a floor."""
    return [np.round(corner_depth(wall=1.8 + 0.1 * i) * 1000.0).astype(np.uint16) for i in range(4)]


def messages(types) -> list[tuple[int, str, object]]:
    """(bag time ns, topic, message): the first depth image before any camera info, then info + image pairs,
    and a colour image with its own camera info."""
    out = []
    info = camera_info(types)
    colour = types.Image(
        header=message_header(types, 'camera_color_optical_frame', (1, 0)),
        height=60,
        width=80,
        encoding='rgb8',
        is_bigendian=0,
        step=240,
        data=np.zeros(60 * 240, dtype=np.uint8),
    )
    for i, counts in enumerate(frames()):
        t = 1_000_000_000 * (i + 1)
        if i:
            out.append((t - 1000, DEPTH_INFO, info))
        image = depth_image(types, counts, '16UC1')
        image.header = message_header(types, 'camera_depth_optical_frame', (1_700_000_000 + i, 5))
        out += [(t, DEPTH, image), (t + 10, COLOR_INFO, info), (t + 20, COLOR, colour)]
    return out


def write_rosbag2(path: Path) -> Path:
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    types = {DEPTH: IMAGE, DEPTH_INFO: CAMERA_INFO, COLOR: IMAGE, COLOR_INFO: CAMERA_INFO}
    connections = {topic: writer.add_connection(topic, msgtype, typestore=JAZZY) for topic, msgtype in types.items()}
    for t, topic, msg in messages(TYPES):
        writer.write(connections[topic], t, JAZZY.serialize_cdr(msg, types[topic]))
    writer.close()
    return path


def ros1(msg):
    """The ROS 1 twin of a Jazzy message: field by field of the ROS 1 type (a header's seq 7; CameraInfo's
    D K R P from d k r p)."""
    cls = NOETIC.types[msg.__msgtype__]
    values = {}
    for item in dataclasses.fields(cls):
        if item.name == 'seq':
            values['seq'] = 7
        elif item.name != '__msgtype__':
            value = getattr(msg, item.name.lower())
            values[item.name] = ros1(value) if hasattr(value, '__msgtype__') else value
    return cls(**values)


def write_ros1(path: Path) -> Path:
    writer = Ros1Writer(path)
    writer.open()
    types = {DEPTH: IMAGE, DEPTH_INFO: CAMERA_INFO, COLOR: IMAGE, COLOR_INFO: CAMERA_INFO}
    connections = {topic: writer.add_connection(topic, msgtype, typestore=NOETIC) for topic, msgtype in types.items()}
    for t, topic, msg in messages(TYPES):
        writer.write(connections[topic], t, NOETIC.serialize_ros1(ros1(msg), types[topic]))
    writer.close()
    return path


def read_bag(path: Path) -> dict[str, list]:
    out: dict[str, list] = {}
    with AnyReader([path], default_typestore=JAZZY) as reader:
        for connection, timestamp, raw in reader.messages():
            out.setdefault(connection.topic, []).append((timestamp, reader.deserialize(raw, connection.msgtype)))
    return out


@pytest.fixture(scope='module')
def expected():
    """What the node's processing gives for each depth image (with the camera info)."""
    info = camera_info(TYPES)
    result = []
    for t, topic, msg in messages(TYPES):
        if topic == DEPTH:
            result.append((t, process_depth_image(DepthFrame(msg, info), PARAMS, TYPES)))
    return result


def write_params(path: Path) -> Path:
    path.write_text('extractor:\n  ros__parameters:\n    sensor: depth_camera\n    min_plane_points: 20\n')
    return path


@pytest.mark.parametrize(('kind', 'jobs'), [('rosbag2', 1), ('ros1', 1), ('rosbag2', 2)])
def test_depth_images_give_the_nodes_outputs_and_wait_for_their_camera_info(tmp_path, capsys, expected, kind, jobs):
    source = write_rosbag2(tmp_path / 'in') if kind == 'rosbag2' else write_ros1(tmp_path / 'in.bag')
    argv = [source, tmp_path / 'out', '--params', write_params(tmp_path / 'p.yaml'), '--jobs', jobs, '--no-progress']
    assert main([str(a) for a in argv]) == 0
    captured = capsys.readouterr()
    assert f'{DEPTH} (4 messages with {DEPTH_INFO}) -> {", ".join(OUTPUTS)}' in captured.out
    assert COLOR not in captured.out  # a colour image is no depth image
    assert 'no_camera_info' in captured.err and f'none received on {DEPTH_INFO} yet' in captured.err
    out = read_bag(tmp_path / 'out')
    assert sorted(out) == sorted(OUTPUTS)
    labeled = out[OUTPUTS[0]]
    assert [t for t, _ in labeled] == [t for t, _ in expected[1:]]  # the first image had no camera info yet
    for (_, msg), (_, frame) in zip(labeled, expected[1:], strict=True):
        assert (msg.header.stamp.sec, msg.header.frame_id) == (frame.stamped.sec, 'camera_depth_optical_frame')
        assert (msg.height, msg.width) == (60, 80)
        np.testing.assert_array_equal(np.array(pointcloud2_to_structured(msg)['label']), frame.planes.labels)
        assert frame.planes.num_planes == 2
    assert [msg.width for _, msg in out[OUTPUTS[2]]] == [2, 2, 2]


def test_a_requested_image_needs_its_camera_info_and_copy_input_copies_it(tmp_path, capsys):
    source = write_rosbag2(tmp_path / 'in')
    report = process_bag(
        BagOptions(source, tmp_path / 'out', topics=[COLOR], copy_input=True, progress=False, params=PARAMS)
    )
    assert report.frames_read == 4 and report.frames_skipped == 4  # rgb8: not a depth encoding
    assert "image encoding 'rgb8' is not a depth encoding" in report.topics[COLOR].reasons['invalid_image']
    out = read_bag(tmp_path / 'out')
    assert [msg.encoding for _, msg in out[COLOR]] == ['rgb8'] * 4
    # the image's camera info is copied along, at its own times
    assert [t for t, _ in out[COLOR_INFO]] == [t for t, topic, _ in messages(TYPES) if topic == COLOR_INFO]
    assert sorted(out) == sorted([COLOR, COLOR_INFO])  # every colour frame skipped: no outputs
    writer = Writer(tmp_path / 'lonely', version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    connection = writer.add_connection(DEPTH, IMAGE, typestore=JAZZY)
    writer.write(connection, 1, JAZZY.serialize_cdr(depth_image(TYPES, frames()[0], '16UC1'), IMAGE))
    writer.close()
    assert main([str(tmp_path / 'lonely'), str(tmp_path / 'out2'), '--topic', DEPTH, '--no-progress']) == 2
    err = capsys.readouterr().err
    assert f'topic {DEPTH} is an image without its camera info' in err and DEPTH_INFO in err
    assert main([str(tmp_path / 'lonely'), str(tmp_path / 'out3'), '--no-progress']) == 2
    assert 'no depth image topic' in capsys.readouterr().err


def test_compressed_depth_topics_go_beside_their_image_and_the_raw_image_is_preferred(tmp_path, capsys, expected):
    """A bag of image_transport's compressedDepth (RVL) images: the same outputs as the raw images, beside the
    image topic; a bag with both the raw image and its compressedDepth topic processes the raw one."""
    from depth_frames import compressed_depth_image

    compressed_topic = f'{DEPTH}/compressedDepth'
    compressed_type = 'sensor_msgs/msg/CompressedImage'
    for both in (False, True):
        path = tmp_path / f'in_{both}'
        writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.open()
        types = {DEPTH_INFO: CAMERA_INFO, compressed_topic: compressed_type, **({DEPTH: IMAGE} if both else {})}
        connections = {topic: writer.add_connection(topic, t, typestore=JAZZY) for topic, t in types.items()}
        for t, topic, msg in messages(TYPES):
            if topic == DEPTH_INFO:
                writer.write(connections[topic], t, JAZZY.serialize_cdr(msg, CAMERA_INFO))
            elif topic == DEPTH:
                counts = np.frombuffer(bytes(msg.data), '<u2').reshape(msg.height, msg.width)
                packed = compressed_depth_image(TYPES, counts, msg.header)
                writer.write(connections[compressed_topic], t + 1, JAZZY.serialize_cdr(packed, compressed_type))
                if both:
                    writer.write(connections[DEPTH], t, JAZZY.serialize_cdr(msg, IMAGE))
        writer.close()
        out = tmp_path / f'out_{both}'
        argv = [path, out, '--params', write_params(tmp_path / 'p.yaml'), '--no-progress']
        assert main([str(a) for a in argv]) == 0
        stdout = capsys.readouterr().out
        taken = DEPTH if both else compressed_topic
        assert f'{taken} (4 messages with {DEPTH_INFO}) -> {", ".join(OUTPUTS)}' in stdout
        assert both == (compressed_topic not in stdout)
        labeled = read_bag(out)[OUTPUTS[0]]
        assert len(labeled) == 3  # the first image had no camera info yet
        for (_, msg), (_, frame) in zip(labeled, expected[1:], strict=True):
            np.testing.assert_array_equal(np.array(pointcloud2_to_structured(msg)['label']), frame.planes.labels)


def test_copy_input_of_a_ros1_bag_converts_the_camera_info_too(tmp_path):
    source = write_ros1(tmp_path / 'in.bag')
    report = process_bag(BagOptions(source, tmp_path / 'out', copy_input=True, progress=False, params=PARAMS))
    assert report.frames_processed == 3
    out = read_bag(tmp_path / 'out')
    infos = [msg for _, msg in out[DEPTH_INFO]]
    assert len(infos) == 3 and all(msg.__msgtype__ == CAMERA_INFO for msg in infos)
    np.testing.assert_array_equal(infos[0].k, camera_info(TYPES).k)  # ROS 1's K is ROS 2's k
    assert [msg.encoding for _, msg in out[DEPTH]] == ['16UC1'] * 4
