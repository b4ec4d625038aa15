"""ppe bag on Hesai-like (height 1, ring field) and Velodyne-like (transposed) clouds: the node's outputs (issue 20)."""

from __future__ import annotations

import numpy as np
from lidar_sweeps import HDL_LIKE_ELEVATIONS, room_sweep, shuffled
from test_bag import JAZZY, OUTPUTS, POINTCLOUD2, TYPES, bag_time, header, read_bag, run_cli, serialized, write_rosbag2

from ppe_ros.ros.pointcloud2 import pointcloud2_to_structured, structured_to_pointcloud2
from ppe_ros.ros.processing import ExtractorParams, process_cloud


def ringed_cloud(index, points, rings):
    table = np.zeros(rings.shape, [('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4'), ('ring', '<u2')])
    table['x'], table['y'], table['z'] = points[..., 0], points[..., 1], points[..., 2]
    table['ring'] = rings
    return structured_to_pointcloud2(
        table,
        header=header(JAZZY, index),
        msg_class=JAZZY.types[POINTCLOUD2],
        field_class=JAZZY.types['sensor_msgs/msg/PointField'],
    )


def test_a_bag_of_hesai_and_velodyne_like_clouds_gets_the_nodes_outputs_in_the_inputs_layouts(tmp_path):
    sweep = room_sweep(HDL_LIKE_ELEVATIONS[::4], 360, sigma=0.005)
    points, rings, _ = shuffled(sweep)
    hesai = ringed_cloud(0, points, rings)
    velodyne = ringed_cloud(1, sweep.transpose(1, 0, 2), np.broadcast_to(np.arange(16), (360, 16)))
    source = write_rosbag2(
        tmp_path / 'in', [(bag_time(0), serialized(JAZZY, hesai)), (bag_time(1), serialized(JAZZY, velodyne))]
    )
    params = tmp_path / 'params.yaml'
    params.write_text('extractor:\n  ros__parameters:\n    sensor: lidar\n')
    assert run_cli([source, tmp_path / 'out', '--params', params]) == 0
    out = read_bag(tmp_path / 'out')
    labelled = [pointcloud2_to_structured(msg) for _, msg in out[OUTPUTS['labeled_points']]]
    assert labelled[0].shape == (1, len(points)) and labelled[1].shape == (360, 16)
    node_params = ExtractorParams(sensor='lidar')
    for table, msg in zip(labelled, (hesai, velodyne), strict=True):  # what the node publishes for each
        expected = process_cloud(msg, node_params, TYPES).planes.labels
        np.testing.assert_array_equal(table['label'], expected)
    assert len(np.unique(labelled[0]['label'])) > 4
