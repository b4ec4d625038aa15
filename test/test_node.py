"""The extractor node in-process: outputs, bad input, parameters, dropped frames and a bag replay.

Every test gets its own rclpy context and namespace; every wait has a deadline.
"""

from __future__ import annotations

import gc
import itertools
import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from depth_frames import STAMP, camera_info, corner_depth, depth_image
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray

from ppe_ros.core.synthetic import plane_scan
from ppe_ros.ros.depth_image import camera_model
from ppe_ros.ros.messages import rclpy_message_types
from ppe_ros.ros.node import ExtractorNode, LatestMailbox, Turnstile
from ppe_ros.ros.pointcloud2 import pointcloud2_to_structured, structured_to_pointcloud2, xyz_to_pointcloud2

pytestmark = [pytest.mark.ros, pytest.mark.timeout(300)]

READY_TIMEOUT_S = 240.0  # the first node of a session may compile the numba kernels (cold cache)
RELIABLE = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
_counter = itertools.count()


@pytest.fixture
def ros_context():
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=int(os.environ['ROS_DOMAIN_ID']))
    try:
        yield context
    finally:
        context.try_shutdown()


@pytest.fixture
def executor(ros_context):
    executor = SingleThreadedExecutor(context=ros_context)
    try:
        yield executor
    finally:
        for node in list(executor.get_nodes()):
            executor.remove_node(node)
            node.destroy_node()  # ExtractorNode.destroy_node joins its worker first
        executor.shutdown(timeout_sec=1.0)


@pytest.fixture
def namespace():
    return f'/test_node_{os.getpid()}_{next(_counter)}'


def spin_until(executor, predicate, timeout=10.0) -> bool:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.02)
    return True


class Harness:
    """An extractor node plus a probe node that publishes clouds and records every output."""

    def __init__(self, context, executor, namespace, overrides=(), input_qos=RELIABLE):
        self.executor = executor
        params = [Parameter('min_plane_points', value=20), *overrides]
        if not any(p.name == 'input_reliability' for p in params) and input_qos is RELIABLE:
            params.append(Parameter('input_reliability', value='reliable'))
        self.node = ExtractorNode(context=context, namespace=namespace, parameter_overrides=params)
        executor.add_node(self.node)
        self.probe = rclpy.create_node('probe', context=context, namespace=namespace)
        executor.add_node(self.probe)
        self.received = {'labeled_points': [], 'markers': [], 'planes': [], 'diagnostics': []}
        self.probe.create_subscription(
            PointCloud2, 'planes/labeled_points', self.received['labeled_points'].append, RELIABLE
        )
        self.probe.create_subscription(MarkerArray, 'planes/markers', self.received['markers'].append, RELIABLE)
        self.probe.create_subscription(PointCloud2, 'planes', self.received['planes'].append, RELIABLE)
        self.probe.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)
        self.publisher = self.probe.create_publisher(PointCloud2, 'points', input_qos)
        self.status_name = f'{namespace.strip("/")}/extractor: plane extraction'
        assert spin_until(executor, self.node.ready.is_set, READY_TIMEOUT_S), 'JIT warm-up did not finish'
        assert spin_until(executor, self.connected), 'node and probe did not discover each other'

    def _on_diagnostics(self, msg):
        self.received['diagnostics'] += [s for s in msg.status if s.name == self.status_name]

    def connected(self) -> bool:
        node = self.node
        return (
            self.publisher.get_subscription_count() > 0
            and node._labeled_points_pub.get_subscription_count() > 0
            and node._markers_pub.get_subscription_count() > 0
            and node._plane_table_pub.get_subscription_count() > 0
        )

    def send(self, msg, *, wait_for: str = 'planes', timeout: float = 20.0):
        """Publish a cloud and wait until the node has counted it (and, by default, a plane table arrived)."""
        before = {k: len(v) for k, v in self.received.items()}
        counts = self.node.frame_counts()
        done_before = counts['processed'] + counts['skipped'] + counts['failed']
        self.publisher.publish(msg)

        def handled():
            now = self.node.frame_counts()
            return now['processed'] + now['skipped'] + now['failed'] > done_before

        assert spin_until(self.executor, handled, timeout), 'the node did not handle the cloud'
        if wait_for:
            assert spin_until(self.executor, lambda: len(self.received[wait_for]) > before[wait_for], timeout)

    def latest_status(self, timeout=5.0) -> DiagnosticStatus:
        count = len(self.received['diagnostics'])
        assert spin_until(self.executor, lambda: len(self.received['diagnostics']) > count, timeout)
        return self.received['diagnostics'][-1]


def make_cloud(points, frame_id='os_lidar', sec=1_700_000_000, nanosec=5):
    header = Header(frame_id=frame_id)
    header.stamp.sec, header.stamp.nanosec = sec, nanosec
    return xyz_to_pointcloud2(points, header=header, msg_class=PointCloud2, field_class=PointField)


@pytest.fixture(scope='module')
def scan_points():
    return plane_scan(3, rows=24, cols=32, radial_sigma=0.005, seed=2).points


def header_of(msg):
    return msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id


def values_of(status: DiagnosticStatus) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


# ------------------------------------------------------------------ outputs


def test_every_output_carries_the_input_header(ros_context, executor, namespace, scan_points):
    harness = Harness(ros_context, executor, namespace)
    harness.send(make_cloud(scan_points, sec=1_700_000_001, nanosec=42))
    assert spin_until(executor, lambda: harness.received['markers'] and harness.received['labeled_points'])
    expected = (1_700_000_001, 42, 'os_lidar')

    labeled = harness.received['labeled_points'][-1]
    assert header_of(labeled) == expected
    assert (labeled.height, labeled.width) == (24, 32)
    assert [f.name for f in labeled.fields] == ['x', 'y', 'z', 'label', 'rgb']
    labels = pointcloud2_to_structured(labeled)['label']
    assert set(np.unique(labels)) == {0, 1, 2, 3}

    table = harness.received['planes'][-1]
    assert header_of(table) == expected and (table.height, table.width) == (1, 3)
    rows = pointcloud2_to_structured(table)[0]
    np.testing.assert_allclose(
        np.linalg.norm(np.stack([rows['normal_x'], rows['normal_y'], rows['normal_z']]), axis=0), 1.0
    )
    assert rows['point_count'].sum() == (labels > 0).sum()

    markers = harness.received['markers'][-1].markers
    assert markers[0].action == 3
    assert len(markers) == 1 + 3 * 3
    for marker in markers:
        assert header_of(marker) == expected
        assert (marker.texture.header.frame_id, marker.texture.header.stamp.sec) == ('os_lidar', 1_700_000_001)
    assert {m.ns for m in markers[1:]} == {'plane_mesh', 'plane_outline', 'plane_normal'}
    assert sorted({m.id for m in markers[1:]}) == [1, 2, 3]

    status = harness.latest_status()
    values = values_of(status)
    assert status.level == DiagnosticStatus.OK and status.hardware_id == 'os_lidar'
    assert values['frames_processed'] == '1' and values['frames_skipped'] == '0'
    assert values['input_topic'] == f'{namespace}/points'
    assert values['depth_image_topic'] == f'{namespace}/depth/image'
    for key in ('input_rate_hz', 'processing_time_mean_ms', 'processing_time_max_ms', 'frames_dropped', 'last_error'):
        assert key in values


def test_a_depth_image_with_its_camera_info_gives_the_outputs(ros_context, executor, namespace):
    """A depth camera's image and camera info (as a RealSense driver publishes them): the planes of the
    back-projected image, with the image's header and size; an image before any camera info is skipped."""
    from sensor_msgs.msg import CameraInfo, Image

    types = rclpy_message_types()
    harness = Harness(ros_context, executor, namespace, overrides=[Parameter('sensor', value='depth_camera')])
    images = harness.probe.create_publisher(Image, 'depth/image', RELIABLE)
    infos = harness.probe.create_publisher(CameraInfo, 'depth/camera_info', qos_profile_sensor_data)
    assert harness.node.depth_image_topic == f'{namespace}/depth/image'
    assert spin_until(executor, lambda: images.get_subscription_count() > 0 and infos.get_subscription_count() > 0)

    image = depth_image(types, corner_depth())
    harness.publisher = images  # Harness.send publishes on its publisher
    harness.send(image, wait_for='')
    counts = harness.node.frame_counts()
    assert counts['skipped_by_kind'] == {'no_camera_info': 1}, counts

    info = camera_info(types)
    infos.publish(info)
    assert spin_until(executor, lambda: harness.node._camera_info is not None)
    assert harness.node._camera_logged == camera_model(info)  # the model went to the log
    harness.send(image)
    labeled = harness.received['labeled_points'][-1]
    assert header_of(labeled) == (*STAMP, 'camera_depth_optical_frame')
    assert (labeled.height, labeled.width) == (60, 80)
    labels = pointcloud2_to_structured(labeled)['label']
    assert harness.received['planes'][-1].width == 2  # the wall and the floor
    assert (labels > 0).mean() > 0.9
    assert harness.node.frame_counts()['processed'] == 1


def test_compressed_depth_images_on_the_transport_topic(ros_context, executor, namespace):
    """depth_image_transport compressedDepth (set at runtime): the node subscribes to depth/image/compressedDepth,
    as image_transport names it, and extracts the RVL-compressed images."""
    from depth_frames import compressed_depth_image
    from sensor_msgs.msg import CameraInfo, CompressedImage

    types = rclpy_message_types()
    harness = Harness(ros_context, executor, namespace, overrides=[Parameter('sensor', value='depth_camera')])
    [result] = harness.node.set_parameters([Parameter('depth_image_transport', value='compressedDepth')])
    assert result.successful
    assert harness.node.depth_image_topic == f'{namespace}/depth/image/compressedDepth'
    images = harness.probe.create_publisher(CompressedImage, 'depth/image/compressedDepth', RELIABLE)
    infos = harness.probe.create_publisher(CameraInfo, 'depth/camera_info', RELIABLE)
    assert spin_until(executor, lambda: images.get_subscription_count() > 0 and infos.get_subscription_count() > 0)
    infos.publish(camera_info(types))
    assert spin_until(executor, lambda: harness.node._camera_info is not None)
    harness.publisher = images
    harness.send(compressed_depth_image(types, np.round(corner_depth() * 1000.0).astype(np.uint16)))
    labeled = harness.received['labeled_points'][-1]
    assert (labeled.height, labeled.width) == (60, 80) and harness.received['planes'][-1].width == 2
    assert harness.node.frame_counts()['processed'] == 1


def test_warm_up_freezes_the_compilers_objects_out_of_garbage_collection(ros_context, executor, namespace):
    """After the warm-up the long-lived objects (numba's compiler) are frozen, so that full garbage
    collections do not pause the node for tens of milliseconds every few hundred frames."""
    gc.unfreeze()
    assert gc.get_freeze_count() == 0
    harness = Harness(ros_context, executor, namespace)
    assert harness.node.ready.is_set()
    assert gc.get_freeze_count() > 100_000


def test_default_best_effort_input_matches_a_sensor_data_publisher(ros_context, executor, namespace, scan_points):
    harness = Harness(ros_context, executor, namespace, input_qos=qos_profile_sensor_data)
    assert harness.node.params.input_reliability == 'best_effort'
    harness.send(make_cloud(scan_points))
    assert harness.received['planes'][-1].width == 3


def test_outputs_nobody_subscribes_to_are_not_built(ros_context, executor, namespace, scan_points):
    harness = Harness(ros_context, executor, namespace)
    outputs = harness.node._wanted_outputs(harness.node.params)
    assert (outputs.labeled_points, outputs.markers, outputs.plane_table) == (True, True, True)
    harness.probe.destroy_subscription(
        next(s for s in harness.probe.subscriptions if s.topic_name.endswith('planes/markers'))
    )
    assert spin_until(executor, lambda: harness.node._markers_pub.get_subscription_count() == 0)
    assert harness.node._wanted_outputs(harness.node.params).markers is False


# ------------------------------------------------------------------ bad input


def unprojectable_cloud(points, header):
    """A cloud of height 1 whose ring field holds no beam numbers: it cannot be put on a range image."""
    flat = points.reshape(-1, 3)
    table = np.zeros(len(flat), [('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('ring', '<i4')])
    table['x'], table['y'], table['z'] = flat.T
    table['ring'] = -5
    return structured_to_pointcloud2(table, header=header, msg_class=PointCloud2, field_class=PointField)


def bad_clouds(points):
    """(kind, message) for every kind of unusable cloud."""
    good = make_cloud(points)
    unorganized = unprojectable_cloud(points, good.header)
    table = np.zeros((4, 5), [('x', '<f4'), ('y', '<f4'), ('intensity', '<f4')])
    no_z = structured_to_pointcloud2(table, header=good.header, msg_class=PointCloud2, field_class=PointField)
    unsupported = make_cloud(points)
    unsupported.fields[1].datatype = 11
    bad_row_step = make_cloud(points)
    bad_row_step.row_step -= 4
    short_data = make_cloud(points)
    short_data.data = short_data.data[:-16]
    empty = make_cloud(np.zeros((0, 4, 3)))
    all_nan = make_cloud(np.full((6, 8, 3), np.nan))
    too_large = make_cloud(np.ones((60, 40, 3)))
    return [
        ('unorganized', unorganized),
        ('invalid_cloud', no_z),
        ('invalid_cloud', unsupported),
        ('invalid_cloud', bad_row_step),
        ('invalid_cloud', short_data),
        ('empty', empty),
        ('no_valid_points', all_nan),
        ('too_large', too_large),
    ]


def test_bad_clouds_are_skipped_counted_and_the_node_keeps_running(ros_context, executor, namespace, scan_points):
    harness = Harness(ros_context, executor, namespace, overrides=[Parameter('max_points', value=2000)])
    cases = bad_clouds(scan_points)
    for number, (kind, msg) in enumerate(cases, start=1):
        harness.send(msg, wait_for='')
        counts = harness.node.frame_counts()
        assert counts['skipped'] == number, kind
        assert kind in counts['last_error'], counts['last_error']
    counts = harness.node.frame_counts()
    assert counts['skipped_by_kind'] == {
        'unorganized': 1,
        'invalid_cloud': 4,
        'empty': 1,
        'no_valid_points': 1,
        'too_large': 1,
    }
    assert counts['processed'] == 0 and counts['failed'] == 0
    assert harness.received['planes'] == []
    harness.send(make_cloud(scan_points))  # still alive and extracting
    assert harness.node.frame_counts()['processed'] == 1
    values = values_of(harness.latest_status())
    assert values['frames_skipped'] == str(len(cases))
    assert 'too_large' in values['last_error'] and 'max_points = 2000' in values['last_error']


def test_skipped_frames_turn_diagnostics_to_warn(ros_context, executor, namespace, scan_points):
    harness = Harness(ros_context, executor, namespace)
    harness.latest_status()  # the window before the bad frame
    harness.send(unprojectable_cloud(scan_points, make_cloud(scan_points).header), wait_for='')
    status = harness.latest_status()
    assert status.level == DiagnosticStatus.WARN
    assert 'skipped' in status.message and 'unorganized' in status.message


# ------------------------------------------------------------------ parameters


def test_runtime_parameter_changes_are_validated_and_applied(ros_context, executor, namespace, scan_points):
    harness = Harness(ros_context, executor, namespace)
    node = harness.node
    rejected = {
        'marker_alpha': (2.0, 'out of range'),
        'max_error_increment': (-1.0, 'max_error_increment out of range'),
        'input_reliability': ('sometimes', "one of 'best_effort', 'reliable'"),
        'ray_origin': ([0.0, 0.0], 'ray_origin must be a list of 3'),
        'min_plane_points': (1.5, 'Wrong parameter type'),
    }
    for name, (value, reason) in rejected.items():
        [result] = node.set_parameters([Parameter(name, value=value)])
        assert not result.successful and reason in result.reason, (name, result.reason)
    assert node.params.marker_alpha == 0.5

    [result] = node.set_parameters([Parameter('marker_alpha', value=0.25)])
    assert result.successful and node.params.marker_alpha == 0.25
    [result] = node.set_parameters([Parameter('max_error_increment', value=1)])  # integer for a double
    assert result.successful and node.params.max_error_increment == 1.0
    node.set_parameters([Parameter('max_error_increment', value=0.01)])
    harness.send(make_cloud(scan_points))
    assert spin_until(executor, lambda: harness.received['markers'])
    assert harness.received['markers'][-1].markers[1].color.a == 0.25

    counts = pointcloud2_to_structured(harness.received['planes'][-1])['point_count'][0]
    assert counts.min() < 300 <= counts.max()
    node.set_parameters([Parameter('publish_markers', value=False), Parameter('min_plane_points', value=300)])
    markers_before = len(harness.received['markers'])
    harness.send(make_cloud(scan_points, sec=7))
    assert harness.received['planes'][-1].header.stamp.sec == 7
    assert harness.received['planes'][-1].width == (counts >= 300).sum()  # only the big planes remain
    spin_until(executor, lambda: False, timeout=0.3)
    assert len(harness.received['markers']) == markers_before


def test_input_reliability_change_resubscribes(ros_context, executor, namespace, scan_points):
    harness = Harness(ros_context, executor, namespace)  # reliable in, reliable publisher
    [result] = harness.node.set_parameters([Parameter('input_reliability', value='best_effort')])
    assert result.successful
    assert spin_until(executor, lambda: harness.publisher.get_subscription_count() == 1)
    harness.send(make_cloud(scan_points, sec=11))  # a reliable writer matches a best-effort reader
    assert harness.received['planes'][-1].header.stamp.sec == 11


def test_numba_threads_parameter(ros_context, executor, namespace, scan_points):
    import numba

    harness = Harness(ros_context, executor, namespace)
    [result] = harness.node.set_parameters([Parameter('numba_threads', value=1)])
    assert result.successful
    harness.send(make_cloud(scan_points))
    assert harness.node._numba_threads_applied == [1]
    too_many = numba.config.NUMBA_NUM_THREADS + 1
    [result] = harness.node.set_parameters([Parameter('numba_threads', value=too_many)])
    assert not result.successful and 'NUMBA_NUM_THREADS' in result.reason


def test_invalid_start_parameters_raise_a_clear_error(ros_context):
    with pytest.raises(ValueError, match=r"invalid parameter 'marker_alpha'.*out of range"):
        ExtractorNode(context=ros_context, parameter_overrides=[Parameter('marker_alpha', value=3.0)])
    with pytest.raises(ValueError, match=r"invalid parameter 'max_error_increment'.*out of range"):
        ExtractorNode(context=ros_context, parameter_overrides=[Parameter('max_error_increment', value=-1.0)])


def test_params_file_is_loaded(tmp_path):
    """The layout of config/extractor.yaml; a key 'extractor' applies to the node in the root namespace."""
    path = tmp_path / 'params.yaml'
    path.write_text(
        'extractor:\n  ros__parameters:\n    marker_alpha: 0.75\n    max_points: 12\n    max_neighbor_distance: 2\n'
    )
    context = rclpy.context.Context()
    rclpy.init(
        context=context, domain_id=int(os.environ['ROS_DOMAIN_ID']), args=['--ros-args', '--params-file', str(path)]
    )
    node = None
    try:
        node = ExtractorNode(context=context)
        assert (node.params.marker_alpha, node.params.max_points, node.params.max_neighbor_distance) == (0.75, 12, 2.0)
        assert node.ready.wait(READY_TIMEOUT_S)
        assert node.frame_counts()['failed'] == 0  # the warm-up ignores max_points
    finally:
        if node is not None:
            node.destroy_node()
        context.try_shutdown()


# ------------------------------------------------------------------ mailbox and dropped frames


def test_mailbox_keeps_the_newest_item():
    mailbox = LatestMailbox()
    assert mailbox.take(timeout=0.01) is None
    assert mailbox.put('a') is False
    assert mailbox.put('b') is True  # replaced 'a': a dropped frame
    assert mailbox.take(timeout=0.01) == 'b'
    assert mailbox.take(timeout=0.01) is None
    mailbox.close()
    start = time.monotonic()
    assert mailbox.take(timeout=5.0) is None and time.monotonic() - start < 1.0


def test_mailbox_numbers_items_in_the_order_they_are_taken():
    mailbox = LatestMailbox()
    assert mailbox.take_numbered(timeout=0.01) is None and not mailbox.pending()
    mailbox.put('a')
    assert mailbox.pending()
    assert mailbox.take_numbered(timeout=0.01) == (0, 'a')
    mailbox.put('b')
    mailbox.put('c')  # replaces b, which never gets a number
    assert mailbox.take(timeout=0.01) == 'c'  # number 1
    mailbox.put('d')
    assert mailbox.take_numbered(timeout=0.01) == (2, 'd')


def test_turnstile_lets_numbers_through_in_order():
    """Holders that finish out of order pass in number order; released numbers (skipped frames) never block."""
    turns = Turnstile()
    passed = []
    lock = threading.Lock()

    def holder(number, delay):
        time.sleep(delay)
        assert turns.wait_turn(number, timeout=10.0)
        with lock:
            passed.append(number)
        turns.release(number)

    delays = {0: 0.2, 1: 0.0, 3: 0.05, 4: 0.0}  # 2 is a skipped frame: released without waiting
    threads = [threading.Thread(target=holder, args=item) for item in delays.items()]
    for thread in threads:
        thread.start()
    time.sleep(0.1)
    assert passed == []  # 1 and 4 are done but wait for 0
    turns.release(2)
    for thread in threads:
        thread.join(10.0)
    assert passed == [0, 1, 3, 4]
    assert not turns.wait_turn(7, timeout=0.01)  # 5 and 6 not released
    turns.close()
    assert not turns.wait_turn(5, timeout=5.0)  # closed: no waiting


def test_two_workers_extract_at_once_and_publish_in_arrival_order(ros_context, executor, namespace, scan_points):
    """A slow frame and a fast one behind it: both extracted at once, published slow first."""
    harness = Harness(ros_context, executor, namespace, overrides=[Parameter('workers', value=2)])
    node = harness.node
    assert spin_until(executor, lambda: sum(w.is_alive() for w in node._workers) == 2)
    slow = plane_scan(3, rows=200, cols=600, radial_sigma=0.005, seed=4).points
    harness.publisher.publish(make_cloud(slow, sec=1))
    assert spin_until(executor, lambda: node._stats.busy == 1 and not node._mailbox.pending())
    harness.publisher.publish(make_cloud(scan_points, sec=2))
    assert spin_until(executor, lambda: len(harness.received['planes']) == 2, timeout=60.0)
    assert [m.header.stamp.sec for m in harness.received['planes']] == [1, 2]
    assert [m.header.stamp.sec for m in harness.received['labeled_points']] == [1, 2]
    values = values_of(node.diagnostics_status())
    assert values['workers'] == '2' and values['frames_in_progress_peak'] == '2'
    counts = node.frame_counts()
    assert (counts['processed'], counts['dropped'], counts['failed']) == (2, 0, 0)
    # one worker again: the second parks, frames still flow; two again: no new thread needed
    [result] = node.set_parameters([Parameter('workers', value=1)])
    assert result.successful
    harness.send(make_cloud(scan_points, sec=3))
    assert harness.received['planes'][-1].header.stamp.sec == 3
    [result] = node.set_parameters([Parameter('workers', value=3)])
    assert result.successful
    assert spin_until(executor, lambda: sum(w.is_alive() for w in node._workers) == 3)
    harness.send(make_cloud(scan_points, sec=4))
    assert harness.received['planes'][-1].header.stamp.sec == 4
    [result] = node.set_parameters([Parameter('workers', value=0)])
    assert not result.successful and 'workers' in result.reason


def test_workers_fall_back_to_one_under_the_workqueue_threading_layer(
    ros_context, executor, namespace, scan_points, monkeypatch
):
    """numba's workqueue layer aborts on concurrent parallel launches: the node runs one worker instead."""
    import numba

    monkeypatch.setattr(numba, 'threading_layer', lambda: 'workqueue')
    harness = Harness(ros_context, executor, namespace, overrides=[Parameter('workers', value=2)])
    node = harness.node
    assert not node._active(1) and node._active(0)
    assert values_of(node.diagnostics_status())['workers'] == '1'
    harness.send(make_cloud(scan_points, sec=5))
    assert harness.received['planes'][-1].header.stamp.sec == 5


def test_frames_arriving_while_busy_are_dropped_and_counted(ros_context, executor, namespace, scan_points):
    harness = Harness(ros_context, executor, namespace)
    node = harness.node
    assert node.stop(timeout=10.0)  # no worker: every cloud waits in the mailbox
    for sec in (1, 2, 3):
        node._on_cloud(make_cloud(scan_points, sec=sec))
    counts = node.frame_counts()
    assert (counts['received'], counts['dropped']) == (3, 2)
    assert node._mailbox.take(timeout=0.1).header.stamp.sec == 3  # the newest one waits
    values = values_of(node.diagnostics_status())
    assert values['frames_dropped'] == '2' and values['frames_received'] == '3'


# ------------------------------------------------------------------ replay of a bag


def write_bag(path: Path, clouds: list[PointCloud2], period_ns: int) -> None:
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_JAZZY)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/lidar/points', 'sensor_msgs/msg/PointCloud2', typestore=typestore)
        for index, msg in enumerate(clouds):
            writer.write(connection, 1_000_000_000 + index * period_ns, serialize_message(msg))


def test_bag_replay_at_recorded_timestamps(ros_context, executor, namespace, scan_points, tmp_path):
    from rclpy.serialization import deserialize_message
    from rosbags.highlevel import AnyReader

    clouds = [
        make_cloud(scan_points + 0.001 * k, frame_id=f'lidar_{k % 2}', sec=1_700_000_100 + k, nanosec=1000 * k)
        for k in range(5)
    ]
    bag = tmp_path / 'clouds'
    write_bag(bag, clouds, period_ns=300_000_000)
    harness = Harness(ros_context, executor, namespace)

    sent = []
    with AnyReader([bag]) as reader:
        connections = [c for c in reader.connections if c.topic == '/lidar/points']
        start_wall = time.monotonic()
        first_ns = None
        for _, timestamp, raw in reader.messages(connections=connections):
            first_ns = timestamp if first_ns is None else first_ns
            due = start_wall + (timestamp - first_ns) * 1e-9
            spin_until(executor, lambda due=due: time.monotonic() >= due, timeout=5.0)
            msg = deserialize_message(bytes(raw), PointCloud2)
            harness.publisher.publish(msg)
            sent.append(header_of(msg))
    assert sent == [header_of(c) for c in clouds]

    def all_outputs():
        return all(len(harness.received[k]) >= len(sent) for k in ('labeled_points', 'markers', 'planes'))

    assert spin_until(executor, all_outputs, timeout=30.0), {k: len(v) for k, v in harness.received.items()}
    assert [header_of(m) for m in harness.received['labeled_points']] == sent
    assert [header_of(m) for m in harness.received['planes']] == sent
    for array, expected in zip(harness.received['markers'], sent, strict=True):
        assert {header_of(m) for m in array.markers} == {expected}
        assert {(m.texture.header.frame_id, m.texture.header.stamp.sec) for m in array.markers} == {
            (expected[2], expected[0])
        }
    assert harness.node.frame_counts()['dropped'] == 0


def test_unknown_parameter_names_and_non_ros_arguments():
    from ppe_ros.ros.node import _non_ros_arguments, unknown_parameter_names

    assert unknown_parameter_names(
        ['max_error_increment', 'use_sim_time', 'qos_overrides./points.reliability', 'min_plane_point', 'zzz']
    ) == ['min_plane_point', 'zzz']
    argv = ['extractor', '--help', '--ros-args', '-p', 'a:=1', '--params-file', 'f.yaml', '--', 'x']
    assert _non_ros_arguments(argv) == ['--help', 'x']
    assert _non_ros_arguments(['extractor', '--ros-args', '-r', 'points:=/lidar']) == []


# ------------------------------------------------------------------ a bad frame never stops the worker


def byte_swapped_cloud(points, sec):
    """The issue's failing frame: little-endian floats in a cloud that says is_bigendian (extreme values)."""
    msg = make_cloud(points, frame_id='swapped', sec=sec)
    msg.is_bigendian = True
    return msg


@pytest.mark.parametrize('order', ['skip_first', 'failure_first'])
def test_a_skipped_and_a_failed_frame_in_either_order_leave_the_worker_serving(
    ros_context, executor, namespace, scan_points, order, monkeypatch
):
    """Issue 17 item 1: a warning and an error from the throttled logger killed the worker thread."""
    import ppe_ros.core.extraction as extraction

    real_extract = extraction.extract_planes

    def extract_or_fail(points, **kwargs):  # the failing frame, whatever the core does with swapped bytes
        if not np.isfinite(points).all(axis=2).any() or np.nanmax(np.abs(points)) > 1e6:
            raise SystemError(
                'CPUDispatcher(<function _seed_errors at 0x1>) returned a result with an exception set'
            ) from ZeroDivisionError('division by zero')
        return real_extract(points, **kwargs)

    monkeypatch.setattr(extraction, 'extract_planes', extract_or_fail)
    harness = Harness(ros_context, executor, namespace)
    unorganized = unprojectable_cloud(scan_points, make_cloud(scan_points, sec=10).header)
    swapped = byte_swapped_cloud(scan_points, sec=11)
    for msg in [unorganized, swapped] if order == 'skip_first' else [swapped, unorganized]:
        harness.send(msg, wait_for='')
        if msg is swapped:  # one line naming the frame and the reason inside the kernel
            assert harness.node.frame_counts()['last_error'] == (
                "frame failed (stamp 11.000000005 s, frame_id 'swapped'): ZeroDivisionError: division by zero "
                '(in the compiled kernel _seed_errors)'
            )
    counts = harness.node.frame_counts()
    assert (counts['skipped'], counts['failed']) == (1, 1), counts
    for sec in (20, 21, 22):  # every good cloud after them gets its outputs
        harness.send(make_cloud(scan_points, sec=sec))
        assert harness.received['planes'][-1].header.stamp.sec == sec
    assert all(worker.is_alive() for worker in harness.node._workers)
    assert harness.node.frame_counts()['processed'] == 3


def test_the_issues_repro_with_the_real_extractor(ros_context, executor, namespace, scan_points):
    """Height-1 cloud (one that cannot be put on a range image), then a byte-swapped one (whatever the
    extractor makes of it), then good clouds."""
    harness = Harness(ros_context, executor, namespace)
    harness.send(unprojectable_cloud(scan_points, make_cloud(scan_points, sec=1).header), wait_for='')
    harness.send(byte_swapped_cloud(scan_points, sec=2), wait_for='')
    harness.send(unprojectable_cloud(scan_points, make_cloud(scan_points, sec=3).header), wait_for='')
    for sec in (4, 5, 6):
        harness.send(make_cloud(scan_points, sec=sec))
        assert harness.received['planes'][-1].header.stamp.sec == sec
    counts = harness.node.frame_counts()
    assert counts['skipped'] == 2 and counts['processed'] + counts['failed'] == 4, counts


def test_an_unexpected_exception_in_the_worker_is_a_failed_frame(
    ros_context, executor, namespace, scan_points, monkeypatch
):
    harness = Harness(ros_context, executor, namespace)
    node = harness.node
    real_process = node._process
    calls = []

    def process_once_broken(index, msg, number):
        calls.append(number)
        if len(calls) == 1:
            raise RuntimeError('a defect in the node')
        real_process(index, msg, number)

    monkeypatch.setattr(node, '_process', process_once_broken)
    harness.send(make_cloud(scan_points, frame_id='broken', sec=30), wait_for='')
    counts = node.frame_counts()
    assert counts['failed'] == 1
    assert counts['last_error'] == (
        "frame failed (stamp 30.000000005 s, frame_id 'broken'): internal error: RuntimeError: a defect in the node"
    )
    status = harness.latest_status()
    assert status.level == DiagnosticStatus.ERROR and 'a defect in the node' in status.message
    harness.send(make_cloud(scan_points, sec=31))
    assert harness.received['planes'][-1].header.stamp.sec == 31


@pytest.mark.filterwarnings('ignore::pytest.PytestUnhandledThreadExceptionWarning')  # the thread it ends
def test_diagnostics_say_error_when_a_worker_thread_is_not_running(
    ros_context, executor, namespace, scan_points, monkeypatch
):
    harness = Harness(ros_context, executor, namespace)
    node = harness.node
    assert values_of(node.diagnostics_status())['worker_threads_alive'] == '1'

    def exit_thread(index, msg, number):
        raise SystemExit  # not an Exception: ends the thread, as nothing in the node should

    monkeypatch.setattr(node, '_process', exit_thread)
    harness.publisher.publish(make_cloud(scan_points))
    assert spin_until(executor, lambda: not node._workers[0].is_alive())
    status = node.diagnostics_status()
    assert status.level == DiagnosticStatus.ERROR
    assert 'worker thread(s) ' in status.message and 'not running' in status.message
    assert values_of(status)['worker_threads_alive'] == '0'


def test_throttled_warnings_and_errors_from_one_key_and_both_severities(ros_context, executor, namespace):
    """The throttled logger logs a warning and an error in turn without rclpy's 'severity cannot be changed'."""
    harness = Harness(ros_context, executor, namespace)
    node = harness.node
    for index in range(4):
        node._warn_throttled(f'kind{index}', f'message {index}', error=bool(index % 2))
    assert set(node._warned_at) == {'kind0', 'kind1', 'kind2', 'kind3'}


# ------------------------------------------------------------------ parameters from the parameter service


def test_an_integer_array_for_ray_origin_is_accepted_at_runtime(ros_context, executor, namespace):
    """`ros2 param set /extractor ray_origin "[0, 0, 1]"` sends an INTEGER_ARRAY, read as array('q')."""
    harness = Harness(ros_context, executor, namespace)
    from_service = Parameter.from_parameter_msg(Parameter('ray_origin', value=[0, 0, 1]).to_parameter_msg())
    assert from_service.type_ == Parameter.Type.INTEGER_ARRAY
    [result] = harness.node.set_parameters([from_service])
    assert result.successful, result.reason
    assert harness.node.params.ray_origin == (0.0, 0.0, 1.0)
    assert harness.node.get_parameter('ray_origin').type_ == Parameter.Type.DOUBLE_ARRAY


def test_setting_an_unknown_parameter_names_it(ros_context, executor, namespace):
    from rclpy.exceptions import ParameterNotDeclaredException

    harness = Harness(ros_context, executor, namespace)
    with pytest.raises(ParameterNotDeclaredException) as caught:
        harness.node.set_parameters([Parameter('max_error_incremnt', value=0.1)])
    message = str(caught.value)
    assert "['max_error_incremnt']: the extractor has no such parameter; known: [" in message, message
    assert 'max_error_increment' in message and ': []' not in message
    [result] = harness.node.set_parameters([Parameter('use_sim_time', value=False)])  # ROS's own ones still work
    assert result.successful


# ------------------------------------------------------------------ a stop during the start-up


def _shut_down_before(original):
    def hook(self, *args, **kwargs):
        rclpy.get_default_context().try_shutdown()  # what rclpy's SIGINT/SIGTERM handler does
        return original(self, *args, **kwargs)

    return hook


def _sigint_before(original):
    def hook(self, *args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        return original(self, *args, **kwargs)

    return hook


@pytest.mark.parametrize(
    'point',
    [
        'declare_parameter',
        'create_publisher',
        'create_subscription',
        'create_timer',
        '_start_workers',
        'sigint_in_create_publisher',
        'sigint_in_rclpy_init',
    ],
)
@pytest.mark.filterwarnings('error::pytest.PytestUnraisableExceptionWarning')
def test_main_exits_0_quietly_when_stopped_during_start_up(monkeypatch, capfd, point, namespace):
    """Issue 17 item 10: a signal during ExtractorNode.__init__ made create_publisher raise RCLError (exit 1).
    Nor may an executor built on the shut-down context print a traceback when it is collected (its
    __del__ fails on the attribute its failed __init__ never set): an unraisable exception fails."""
    from ppe_ros.ros import node as node_module

    if point == 'sigint_in_rclpy_init':

        def interrupted_init(*args, **kwargs):
            raise KeyboardInterrupt

        monkeypatch.setattr(node_module.rclpy, 'init', interrupted_init)
    elif point.startswith('sigint_in_'):
        name = point.removeprefix('sigint_in_')
        monkeypatch.setattr(ExtractorNode, name, _sigint_before(getattr(ExtractorNode, name)))
    else:
        monkeypatch.setattr(ExtractorNode, point, _shut_down_before(getattr(ExtractorNode, point)))
    argv = ['extractor', '--ros-args', '-r', f'__ns:={namespace}']
    assert node_module.main(argv) == 0
    assert not rclpy.get_default_context().ok()
    err = capfd.readouterr().err
    assert 'Traceback' not in err and 'error' not in err.lower(), err


def test_main_still_exits_2_on_an_invalid_parameter(capfd, namespace):
    from ppe_ros.ros import node as node_module

    argv = ['extractor', '--ros-args', '-r', f'__ns:={namespace}', '-p', 'marker_alpha:=4.0']
    assert node_module.main(argv) == 2
    err = capfd.readouterr().err
    assert "extractor: error: invalid parameter 'marker_alpha'" in err and 'Traceback' not in err


def test_main_returns_without_leaving_the_shutdown_watchdog_armed(tmp_path):
    """main() arms a watchdog (faulthandler, exit code 1) for its shutdown; a caller that goes on after main()
    returned (tests do) must not be killed by it later (it killed pytest 15 s after test_main_... above)."""
    script = (
        'import time\n'
        'from ppe_ros.ros import node\n'
        'node.STOP_TIMEOUT_S, node.SHUTDOWN_GRACE_S = 0.2, 0.3\n'
        "code = node.main(['extractor', '--ros-args', '-p', 'marker_alpha:=4.0'])\n"
        'time.sleep(2.0)\n'
        "print('still running after main returned', code)\n"
    )
    env = {**os.environ, 'ROS_DOMAIN_ID': str(1 + os.getpid() % 99), 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    done = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0, done.stdout + done.stderr
    assert 'still running after main returned 2' in done.stdout, done.stdout + done.stderr


# ------------------------------------------------------------------ idling, output rate, QoS overrides (issue 19)


def wait_counted(executor, node, key: str, count: int, timeout: float = 20.0) -> bool:
    return spin_until(executor, lambda: node.frame_counts()[key] >= count, timeout)


def bare_node(context, executor, namespace, overrides=()):
    """An extractor with no subscriber on its outputs, and a probe that only publishes clouds."""
    node = ExtractorNode(
        context=context,
        namespace=namespace,
        parameter_overrides=[Parameter('input_reliability', value='reliable'), *overrides],
    )
    executor.add_node(node)
    probe = rclpy.create_node('probe', context=context, namespace=namespace)
    executor.add_node(probe)
    publisher = probe.create_publisher(PointCloud2, 'points', RELIABLE)
    assert spin_until(executor, node.ready.is_set, READY_TIMEOUT_S)
    assert spin_until(executor, lambda: publisher.get_subscription_count() > 0)
    return node, probe, publisher


def test_without_subscribers_the_node_idles_and_says_so(ros_context, executor, namespace, scan_points):
    """Issue 19 item 5: nobody listening, no extraction (counted as idle, reported in diagnostics)."""
    node, probe, publisher = bare_node(ros_context, executor, namespace)
    node.diagnostics_status()  # starts a new report window
    for sec in range(3):
        publisher.publish(make_cloud(scan_points, sec=sec))
        assert wait_counted(executor, node, 'idle', sec + 1)
    counts = node.frame_counts()
    assert (counts['processed'], counts['idle'], counts['received']) == (0, 3, 3)
    status = node.diagnostics_status()
    values = values_of(status)
    assert status.level == DiagnosticStatus.OK and status.message.startswith('idle: no subscriber on any output')
    assert (values['idle'], values['frames_idle'], values['frames_processed']) == ('true', '3', '0')
    assert values['time_since_last_output_s'] == 'nan' and values['output_rate_hz'] == '0.00'
    tables = []
    probe.create_subscription(PointCloud2, 'planes', tables.append, RELIABLE)
    assert spin_until(executor, lambda: node._plane_table_pub.get_subscription_count() > 0)
    publisher.publish(make_cloud(scan_points, sec=10))
    assert spin_until(executor, lambda: bool(tables), 20.0)
    assert node.frame_counts()['processed'] == 1 and values_of(node.diagnostics_status())['idle'] == 'false'


def test_process_without_subscribers_extracts_anyway(ros_context, executor, namespace, scan_points):
    node, _, publisher = bare_node(
        ros_context, executor, namespace, [Parameter('process_without_subscribers', value=True)]
    )
    publisher.publish(make_cloud(scan_points))
    assert wait_counted(executor, node, 'processed', 1)
    assert node.frame_counts()['idle'] == 0
    values = values_of(node.diagnostics_status())
    assert values['idle'] == 'false' and float(values['time_since_last_output_s']) < 20.0


def test_diagnostics_warn_when_the_output_rate_falls_below_the_set_fraction(
    ros_context, executor, namespace, scan_points, monkeypatch
):
    """Issue 19 item 6: output rate and time since the last output; WARN below min_output_rate_fraction."""
    from ppe_ros.ros import node as node_module

    harness = Harness(ros_context, executor, namespace)
    node = harness.node
    real_process_cloud = node_module.process_cloud

    def slow(*args, **kwargs):
        time.sleep(0.25)  # at most 4 frames/s out while 20 frames/s come in
        return real_process_cloud(*args, **kwargs)

    monkeypatch.setattr(node_module, 'process_cloud', slow)
    node.diagnostics_status()
    for sec in range(30):
        node._on_cloud(make_cloud(scan_points, sec=sec))
        spin_until(executor, lambda: False, 0.05)
    status = node.diagnostics_status()
    values = values_of(status)
    assert status.level == DiagnosticStatus.WARN, status.message
    assert status.message.startswith('output rate') and 'below 0.5 x the input rate' in status.message
    assert 0.0 < float(values['output_rate_hz']) < 0.5 * float(values['input_rate_hz'])
    assert float(values['time_since_last_output_s']) < 5.0
    [result] = node.set_parameters([Parameter('min_output_rate_fraction', value=0.0)])  # 0: never
    assert result.successful
    assert not node.diagnostics_status().message.startswith('output rate')


def test_output_rate_check_needs_enough_frames_and_leaves_idle_frames_out():
    from ppe_ros.ros.diagnostics import ReportWindow

    def window(received, published, idle=0, span_s=5.0):
        return ReportWindow(
            received=received,
            skipped=0,
            failed=0,
            dropped=0,
            times_ms=np.zeros(0),
            input_rate_hz=received / span_s,
            output_rate_hz=published / span_s,
            to_extract_in_rate_window=received - idle,
            idle_in_rate_window=idle,
            totals={},
            skipped_by_kind={},
            last_error='',
            last_error_age_s=math.nan,
            since_last_output_s=math.nan,
            last_planes=0,
            last_frame_id='',
            busy=0,
            busy_peak=0,
        )

    assert window(50, 24).output_rate_too_low(0.5) and not window(50, 25).output_rate_too_low(0.5)
    assert not window(2, 0).output_rate_too_low(0.5)  # too few frames to tell
    assert not window(50, 0).output_rate_too_low(0.0)
    assert not window(50, 10, idle=40).output_rate_too_low(0.5)  # 10 of the 10 frames to extract came out
    assert window(50, 4, idle=40).output_rate_too_low(0.5)


def test_qos_overrides_set_the_input_and_output_qos(ros_context, executor, namespace, capfd):
    """Issue 19 item 4: rclpy's QoS override parameters, for the (resolved) input and output topics."""
    from rclpy.qos import ReliabilityPolicy as Reliability

    overrides = [
        Parameter(f'qos_overrides.{namespace}/points.subscription.reliability', value='reliable'),
        Parameter(f'qos_overrides.{namespace}/points.subscription.depth', value=3),
        Parameter(f'qos_overrides.{namespace}/planes.publisher.reliability', value='best_effort'),
        Parameter(f'qos_overrides.{namespace}/planes/markers.publisher.depth', value=4),
        Parameter('qos_overrides./elsewhere/points.subscription.reliability', value='reliable'),
    ]
    node = ExtractorNode(context=ros_context, namespace=namespace, parameter_overrides=overrides)
    executor.add_node(node)
    assert node.params.input_reliability == 'best_effort'  # the override wins over it
    assert (node._subscription.qos_profile.reliability, node._subscription.qos_profile.depth) == (
        Reliability.RELIABLE,
        3,
    )
    assert node._plane_table_pub.qos_profile.reliability == Reliability.BEST_EFFORT
    assert node._markers_pub.qos_profile.depth == 4
    assert node._labeled_points_pub.qos_profile.reliability == Reliability.RELIABLE  # not overridden
    err = capfd.readouterr().err
    assert "ignoring QoS override(s) ['qos_overrides./elsewhere/points.subscription.reliability']" in err, err
    [result] = node.set_parameters([Parameter('input_reliability', value='reliable')])
    assert result.successful and node._subscription.qos_profile.depth == 3


def test_input_reliability_change_keeps_the_depth_override(ros_context, executor, namespace):
    from rclpy.qos import ReliabilityPolicy as Reliability

    node = ExtractorNode(
        context=ros_context,
        namespace=namespace,
        parameter_overrides=[
            Parameter(f'qos_overrides.{namespace}/points.subscription.depth', value=2),
            Parameter(f'qos_overrides.{namespace}/depth/image.subscription.depth', value=4),
        ],
    )
    executor.add_node(node)
    assert node._subscription.qos_profile.reliability == Reliability.BEST_EFFORT
    assert (node._depth_subscription.qos_profile.reliability, node._depth_subscription.qos_profile.depth) == (
        Reliability.BEST_EFFORT,
        4,
    )
    [result] = node.set_parameters([Parameter('input_reliability', value='reliable')])
    assert result.successful
    assert (node._subscription.qos_profile.reliability, node._subscription.qos_profile.depth) == (
        Reliability.RELIABLE,
        2,
    )
    # the depth image input follows input_reliability too, keeping its own override
    assert (node._depth_subscription.qos_profile.reliability, node._depth_subscription.qos_profile.depth) == (
        Reliability.RELIABLE,
        4,
    )
    assert node.depth_image_topic == f'{namespace}/depth/image'


# ------------------------------------------------------------------ ray origins from the Ouster metadata


def ouster_metadata(rows: int, columns: int, nested: bool = False) -> dict:
    legacy = {
        'lidar_origin_to_beam_origin_mm': 15.8,
        'lidar_to_sensor_transform': [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 36.18, 0, 0, 0, 1],
        'data_format': {
            'pixels_per_column': rows,
            'columns_per_frame': columns,
            'column_window': [0, columns - 1],
            'pixel_shift_by_row': [(3 * i) % columns for i in range(rows)],
        },
    }
    if not nested:
        return legacy
    return {
        'beam_intrinsics': {'lidar_origin_to_beam_origin_mm': legacy['lidar_origin_to_beam_origin_mm']},
        'lidar_intrinsics': {'lidar_to_sensor_transform': legacy['lidar_to_sensor_transform']},
        'lidar_data_format': legacy['data_format'],
    }


def test_ouster_metadata_of_either_layout_gives_the_file_loaders_ray_starts():
    import json

    from ppe_ros.io.ouster import ouster_ray_origins
    from ppe_ros.ros.sensor_metadata import OusterRayOrigins

    expected = ouster_ray_origins(ouster_metadata(4, 8), 4, 8)
    for nested in (False, True):
        origins = OusterRayOrigins(json.dumps(ouster_metadata(4, 8, nested)))
        assert origins.shape == (4, 8) and origins.beam_origin_mm == 15.8
        np.testing.assert_array_equal(origins.for_cloud(4, 8, 'os_sensor'), expected)
        lidar = origins.for_cloud(4, 8, 'os_lidar')  # the lidar frame: starts on a 15.8 mm circle at z = 0
        np.testing.assert_allclose(np.linalg.norm(lidar[..., :2], axis=-1), 0.0158, atol=1e-15)
        np.testing.assert_allclose(lidar[..., 2], 0.0, atol=1e-15)
        assert origins.for_cloud(4, 9, 'os_sensor') is None


@pytest.mark.parametrize(
    ('text', 'message'),
    [
        ('{', 'not JSON'),
        ('[1, 2]', 'expected an object'),
        ('{"data_format": {}}', 'missing lidar_origin_to_beam_origin_mm, lidar_to_sensor_transform'),
        (
            '{"lidar_origin_to_beam_origin_mm": "x", "lidar_to_sensor_transform": [], "data_format": '
            '{"pixels_per_column": 4, "columns_per_frame": 8}}',
            'must be',
        ),
    ],
)
def test_bad_ouster_metadata_is_a_clear_error(text, message):
    from ppe_ros.io.errors import ScanFileError
    from ppe_ros.ros.sensor_metadata import OusterRayOrigins

    with pytest.raises(ScanFileError, match=message):
        OusterRayOrigins(text)


def test_the_node_uses_the_metadata_ray_starts_unless_ray_origin_is_set(
    ros_context, executor, namespace, scan_points, monkeypatch
):
    """Issue 19 item 8: the driver's latched metadata (std_msgs/String JSON) on `metadata`."""
    import json

    from rclpy.qos import DurabilityPolicy
    from std_msgs.msg import String

    from ppe_ros.ros import node as node_module

    seen = []
    real_process_cloud = node_module.process_cloud

    def spy(*args, ray_origins=None, **kwargs):
        seen.append(ray_origins)
        return real_process_cloud(*args, ray_origins=ray_origins, **kwargs)

    monkeypatch.setattr(node_module, 'process_cloud', spy)
    harness = Harness(ros_context, executor, namespace)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    metadata_pub = harness.probe.create_publisher(String, 'metadata', latched)
    rows, columns = scan_points.shape[:2]
    assert spin_until(executor, lambda: metadata_pub.get_subscription_count() > 0)
    metadata_pub.publish(String(data='not json'))  # warned about and ignored
    assert spin_until(executor, lambda: 'metadata' in harness.node._warned_at)
    metadata_pub.publish(String(data=json.dumps(ouster_metadata(rows, columns))))
    assert spin_until(executor, lambda: harness.node._ray_starts.ouster is not None)
    harness.send(make_cloud(scan_points, frame_id='os_lidar'))
    expected = harness.node._ray_starts.ouster.for_cloud(rows, columns, 'os_lidar')
    assert seen[-1] is expected and np.allclose(np.linalg.norm(expected[..., :2], axis=-1), 0.0158)
    harness.send(make_cloud(scan_points[:, :-1], frame_id='os_lidar'))  # another size: ray_origin
    assert seen[-1] is None
    [result] = harness.node.set_parameters([Parameter('ray_origin', value=[0.0, 0.0, 0.5])])
    assert result.successful
    harness.send(make_cloud(scan_points, frame_id='os_lidar'))  # set by hand: it wins
    assert seen[-1] is None
    assert set(harness.node._warned_at) >= {'metadata', 'metadata_size'}


# ------------------------------------------------------------------ the JIT warm-up (issue 19 item 7)


def test_warm_up_lines_stay_off_rosout_and_the_ready_line_goes_there(ros_context, executor, namespace):
    """The warm-up's lines go to the console only: a SIGINT during the start-up shuts the context down from
    rclpy's signal thread, and a line then on its way to /rosout made rcl print "Failed to publish log message
    to rosout" (test_node_process's SIGINT timings). The ready line still reaches /rosout."""
    from rcl_interfaces.msg import Log
    from rclpy.qos import DurabilityPolicy, HistoryPolicy

    listener = rclpy.create_node('rosout_listener', context=ros_context, namespace=namespace)
    executor.add_node(listener)
    lines = []
    rosout_qos = QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=1000,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    listener.create_subscription(Log, '/rosout', lambda msg: lines.append((msg.name, msg.msg)), rosout_qos)
    harness = Harness(ros_context, executor, namespace)
    name = harness.node.get_logger().name
    assert spin_until(executor, lambda: any(n == name and m.startswith('ready: ') for n, m in lines), 20.0), lines
    ours = [m for n, m in lines if n.startswith(name)]
    assert not [m for m in ours if 'JIT warm-up' in m], ours


def test_warm_up_runs_each_profile_with_both_kinds_of_ray_starts_and_logs_progress(monkeypatch):
    from ppe_ros.ros import warmup as warmup_module
    from ppe_ros.ros.messages import rosbags_message_types

    calls, lines = [], []
    real_process_cloud = warmup_module.process_cloud

    def recording(cloud, params, types, *, outputs, ray_origins=None):
        calls.append((params.sensor, None if ray_origins is None else ray_origins.shape))
        time.sleep(0.05)  # long enough for the ticker
        return real_process_cloud(cloud, params, types, outputs=outputs, ray_origins=ray_origins)

    monkeypatch.setattr(warmup_module, 'process_cloud', recording)
    steps = warmup_module.warm_up(rosbags_message_types(), sensors=('none', 'lidar'), log=lines.append, tick_s=0.02)
    assert [step.sensor for step in steps] == ['none', 'lidar'] and all(step.planes >= 1 for step in steps)
    assert calls == [('none', None), ('none', (12, 16, 3)), ('lidar', None), ('lidar', (12, 16, 3))]
    assert 'JIT warm-up step 1/2: sensor none ...' in lines and 'JIT warm-up step 2/2: sensor lidar ...' in lines
    assert any(line.startswith('JIT warm-up: still compiling (step') for line in lines), lines


def test_ppe_warmup_prints_its_steps():
    import subprocess
    import sys

    result = subprocess.run(
        [sys.executable, '-m', 'ppe_ros.cli', 'warmup', '--sensor', 'none'], capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith('| step | seconds |\n|---|---|\n| sensor none | ')
    assert '| sensor none |' in result.stdout and '| PCD files (LZF) |' in result.stdout
    assert '| compressedDepth images (RVL) |' in result.stdout
    assert 'ppe warmup: JIT warm-up step 1/1: sensor none ...' in result.stderr


# ------------------------------------------------------------------ parameter changes under a stream


#: Valid values of the parameters a user may change while clouds arrive (each change is one of these).
_STREAM_CHANGES = {
    'workers': (1, 2, 3),
    'numba_threads': (0, 1, 2),
    'sensor': ('none', 'lidar', 'depth_camera', 'paper'),
    'max_error_increment': (0.0, 0.001, 1.0),
    'max_planes': (0, 1, 50),
    'max_neighbor_distance': (0.0, 0.05, math.inf),
    'min_plane_points': (0, 1, 20, 1000),
    'surface_tolerance': (0.0, 0.001, 1.0),
    'ray_origin': ([0.0, 0.0, 0.0], [0.1, 0.0, 0.03], [-5.0, 0.0, 0.0]),
    'publish_labeled_points': (True, False),
    'publish_markers': (True, False),
    'publish_plane_table': (True, True, False),
    'marker_mesh_stride': (1, 2, 64),
    'marker_max_triangles': (0, 10, 150_000),
    'layout': ('auto', 'rows_are_beams', 'columns_are_beams'),
    'unorganized_rows': ('auto', 'elevation', 'angular_grid'),
    'azimuth_bins': (0, 16, 4096),
    'input_reliability': ('reliable', 'best_effort'),
}


def test_the_node_keeps_working_while_its_parameters_change_under_a_stream(ros_context, executor, namespace):
    """Clouds at 20 Hz (organized, transposed, unorganized) while 1-3 random valid parameters change every
    0.05-0.4 s for 12 s (workers up and down, the profile, outputs on and off, ...): no frame fails, and
    with the outputs back on the node still answers (a seeded fuzz, 8 x 60 s, found nothing either)."""
    rng = np.random.default_rng(17)
    points = plane_scan(3, rows=24, cols=64, radial_sigma=0.005, seed=5).points
    clouds = [
        points,
        np.ascontiguousarray(points.transpose(1, 0, 2)),
        points.reshape(1, -1, 3)[:, np.isfinite(points.reshape(-1, 3)).all(1)],
        points[:, :16] * 10.0,
    ]
    harness = Harness(ros_context, executor, namespace)
    node = harness.node
    names = sorted(_STREAM_CHANGES)
    deadline, next_change, sec, rejected = time.monotonic() + 12.0, 0.0, 1, []
    while time.monotonic() < deadline:
        harness.publisher.publish(make_cloud(clouds[sec % len(clouds)], sec=sec))
        sec += 1
        if time.monotonic() >= next_change:
            chosen = rng.choice(names, size=int(rng.integers(1, 4)), replace=False)
            changes = [
                Parameter(str(n), value=_STREAM_CHANGES[n][int(rng.integers(len(_STREAM_CHANGES[n])))]) for n in chosen
            ]
            rejected += [r.reason for r in node.set_parameters(changes) if not r.successful]
            next_change = time.monotonic() + float(rng.uniform(0.05, 0.4))
        spin_until(executor, lambda: False, 0.05)
    assert not rejected, rejected
    node.set_parameters(
        [Parameter(n, value=True) for n in ('publish_labeled_points', 'publish_markers', 'publish_plane_table')]
        + [Parameter('input_reliability', value='reliable'), Parameter('layout', value='auto')]
    )
    counts = node.frame_counts()
    assert counts['failed'] == 0, counts
    assert counts['processed'] > 20, counts
    harness.send(make_cloud(points, sec=sec), timeout=60.0)
