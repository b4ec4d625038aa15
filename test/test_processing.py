"""One frame through process_cloud: parameters, outputs for rclpy and rosbags, and every bad input."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from depth_frames import message_header
from lidar_sweeps import HDL_LIKE_ELEVATIONS, room_sweep, shuffled

from ppe_ros.core.projection import matched_label_agreement
from ppe_ros.core.synthetic import plane_scan
from ppe_ros.ros.markers import MESH_NAMESPACE, NORMAL_NAMESPACE, OUTLINE_NAMESPACE
from ppe_ros.ros.messages import rclpy_message_types, rosbags_message_types
from ppe_ros.ros.pointcloud2 import (
    FLOAT32,
    FLOAT64,
    label_colors,
    pointcloud2_to_structured,
    structured_to_pointcloud2,
    xyz_to_pointcloud2,
)
from ppe_ros.ros.processing import (
    PARAM_SPECS,
    PLANE_TABLE_FIELDS,
    ExtractorParams,
    FrameSkipped,
    OutputSelection,
    cloud_points,
    failure_reason,
    frame_label,
    process_cloud,
)

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / 'config' / 'extractor.yaml'
STAMP = (1_700_000_123, 456_000_000)


@pytest.fixture(scope='module', params=['rclpy', 'rosbags'])
def types(request):
    return rclpy_message_types() if request.param == 'rclpy' else rosbags_message_types()


def make_header(types, frame_id='os_lidar', stamp=STAMP):
    return message_header(types, frame_id, stamp)


@pytest.fixture(scope='module')
def scan():
    """Floor and two walls, 24 x 32, 5 mm range noise, one no-return."""
    result = plane_scan(3, rows=24, cols=32, radial_sigma=0.005, seed=1)
    points = result.points.copy()
    points[3, 4] = np.nan
    return points


def cloud(types, points, **kwargs):
    return xyz_to_pointcloud2(
        points, header=make_header(types, **kwargs), msg_class=types.PointCloud2, field_class=types.PointField
    )


# ------------------------------------------------------------------ parameters


def test_defaults_are_valid_and_match_the_specs():
    params = ExtractorParams()
    for spec in PARAM_SPECS:
        assert getattr(params, spec.name) == spec.validate(spec.default), spec.name


def test_config_yaml_holds_every_parameter_with_the_code_defaults():
    import yaml

    section = yaml.safe_load(CONFIG.read_text())['extractor']['ros__parameters']
    assert sorted(section) == sorted(spec.name for spec in PARAM_SPECS)
    assert ExtractorParams.from_yaml(CONFIG) == ExtractorParams()
    commented = [line for line in CONFIG.read_text().splitlines() if line.startswith('    ') and ':' in line]
    assert len(commented) == len(PARAM_SPECS) and all('#' in line for line in commented)


@pytest.mark.parametrize(
    ('name', 'value', 'message'),
    [
        ('max_error_increment', -0.5, r'max_error_increment must be in \[0.0'),
        ('max_error_increment', math.nan, 'must be a number'),
        ('max_neighbor_distance', -1.0, 'max_neighbor_distance'),
        ('min_plane_points', -1, 'min_plane_points must be in'),
        ('min_plane_points', 2.5, 'min_plane_points must be an integer'),
        ('ray_origin', [0.0, 0.0], 'ray_origin must be a list of 3 finite numbers'),
        ('ray_origin', [0.0, math.inf, 0.0], 'ray_origin'),
        ('input_reliability', 'sometimes', "one of 'best_effort', 'reliable'"),
        ('layout', 'transposed', "layout must be one of 'auto', 'rows_are_beams', 'columns_are_beams'"),
        ('unorganized_rows', 'ring', "unorganized_rows must be one of 'auto', 'rings', 'elevation'"),
        ('azimuth_bins', -1, 'azimuth_bins must be in'),
        ('azimuth_start', math.inf, 'azimuth_start must be in'),
        ('angular_resolution', 0.0, 'angular_resolution must be in'),
        ('lost_point_tolerance', -0.1, 'lost_point_tolerance must be in'),
        ('publish_markers', 'yes', 'publish_markers must be true or false'),
        ('marker_alpha', 1.5, r'marker_alpha must be in \[0.0, 1.0\]'),
        ('marker_mesh_stride', 0, 'marker_mesh_stride'),
        ('max_points', 0, 'max_points'),
        ('numba_threads', -1, 'numba_threads'),
        ('workers', 0, 'workers'),
    ],
)
def test_invalid_values_are_rejected_with_the_reason(name, value, message):
    with pytest.raises(ValueError, match=message):
        ExtractorParams(**{name: value})
    with pytest.raises(ValueError, match=message):
        ExtractorParams().replace(**{name: value})


def test_values_are_normalized():
    params = ExtractorParams(ray_origin=[0, 1, 2], max_error_increment=1, max_neighbor_distance=math.inf)
    assert params.ray_origin == (0.0, 1.0, 2.0) and isinstance(params.max_error_increment, float)
    assert params.replace(marker_alpha=0.25).marker_alpha == 0.25
    with pytest.raises(ValueError, match='unknown extractor parameter'):
        params.replace(marker_opacity=0.3)


def test_from_yaml_merges_wildcard_and_node_sections(tmp_path):
    path = tmp_path / 'params.yaml'
    path.write_text(
        '/**:\n  ros__parameters:\n    use_sim_time: true\n    marker_alpha: 0.2\n    max_points: 5\n'
        '/robot/extractor:\n  ros__parameters:\n    max_points: 7\n    ray_origin: [0.0, 0.0, 0.1]\n'
        'other_node:\n  ros__parameters:\n    max_points: 9\n'
    )
    params = ExtractorParams.from_yaml(path)
    assert (params.marker_alpha, params.max_points, params.ray_origin) == (0.2, 7, (0.0, 0.0, 0.1))


@pytest.mark.parametrize(
    ('text', 'message'),
    [
        ('other:\n  ros__parameters:\n    max_points: 5\n', 'no section for node'),
        ('extractor:\n  max_points: 5\n', 'must contain "ros__parameters:"'),
        ('extractor:\n  ros__parameters:\n    max_point: 5\n', r"unknown extractor parameter\(s\) \['max_point'\]"),
        ('extractor:\n  ros__parameters:\n    marker_alpha: 3.0\n', 'marker_alpha must be in'),
        ('extractor: [\n', 'not valid YAML'),
        ('- 1\n', 'must map node names'),
    ],
)
def test_from_yaml_reports_bad_files(tmp_path, text, message):
    path = tmp_path / 'params.yaml'
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        ExtractorParams.from_yaml(path)


def test_from_yaml_missing_file(tmp_path):
    with pytest.raises(ValueError, match='cannot read params file'):
        ExtractorParams.from_yaml(tmp_path / 'absent.yaml')


# ------------------------------------------------------------------ outputs


@pytest.fixture(scope='module')
def frame(types, scan):
    return process_cloud(cloud(types, scan), ExtractorParams(min_plane_points=20), types)


def test_extracts_the_three_planes(frame):
    planes = frame.planes
    assert planes.num_planes == 3
    assert planes.labels[3, 4] == 0  # the no-return
    assert set(frame.timings) == {'convert', 'extract', 'labeled_points', 'markers', 'plane_table'}
    assert frame.overhead_s == pytest.approx(sum(frame.timings.values()) - frame.timings['extract'])


def header_tuple(header):
    return header.stamp.sec, header.stamp.nanosec, header.frame_id


def test_labeled_points_keep_grid_points_and_colour_each_label(frame, scan):
    msg = frame.labeled_points
    assert header_tuple(msg.header) == (*STAMP, 'os_lidar')
    assert (msg.height, msg.width) == scan.shape[:2] and msg.is_dense is False
    assert [(f.name, f.datatype) for f in msg.fields] == [
        ('x', FLOAT32),
        ('y', FLOAT32),
        ('z', FLOAT32),
        ('label', 6),
        ('rgb', FLOAT32),
    ]
    records = pointcloud2_to_structured(msg)
    np.testing.assert_array_equal(records['label'], frame.planes.labels)
    np.testing.assert_allclose(records['x'], scan[..., 0].astype(np.float32))
    colours = records['rgb'].view(np.uint32)
    np.testing.assert_array_equal(colours, label_colors(frame.planes.labels))
    for label in range(frame.planes.num_planes + 1):
        assert len(np.unique(colours[frame.planes.labels == label])) == 1


def test_plane_table_has_one_documented_point_per_plane(frame):
    msg = frame.plane_table
    planes = frame.planes
    assert header_tuple(msg.header) == (*STAMP, 'os_lidar')
    assert (msg.height, msg.width) == (1, planes.num_planes)
    assert tuple(f.name for f in msg.fields) == PLANE_TABLE_FIELDS
    # x y z float32 (what RViz draws) and rgb; the rest float64 but the two counts
    assert all(
        f.datatype == FLOAT64 for f in msg.fields if f.name not in ('x', 'y', 'z', 'rgb', 'point_count', 'label')
    )
    assert [(f.name, f.offset, f.datatype) for f in msg.fields[:4]] == [
        ('x', 0, 7),
        ('y', 4, 7),
        ('z', 8, 7),
        ('rgb', 12, 7),
    ]
    table = pointcloud2_to_structured(msg)[0]
    np.testing.assert_array_equal(np.stack([table['x'], table['y'], table['z']], 1), planes.centroids.astype('<f4'))
    np.testing.assert_array_equal(
        np.stack([table['centroid_x'], table['centroid_y'], table['centroid_z']], 1), planes.centroids
    )
    labeled = pointcloud2_to_structured(frame.labeled_points)  # a plane's centroid has its colour in the cloud
    for row in table:
        assert set(labeled['rgb'][labeled['label'] == row['label']].view(np.uint32)) == {row['rgb'].view(np.uint32)}
    np.testing.assert_array_equal(
        np.stack([table['normal_x'], table['normal_y'], table['normal_z']], 1), planes.normals
    )
    np.testing.assert_array_equal(table['d'], planes.offsets)
    np.testing.assert_array_equal(table['point_count'], planes.point_counts)
    np.testing.assert_array_equal(table['label'], [1, 2, 3])
    np.testing.assert_array_equal(table['rmse'], planes.rmse)
    np.testing.assert_array_equal(table['sse'], planes.sse)
    np.testing.assert_array_equal(table['cov_xy'], planes.covariances[:, 0, 1])
    np.testing.assert_array_equal(table['cov_yz'], planes.covariances[:, 1, 2])
    np.testing.assert_array_equal(table['cov_zz'], planes.covariances[:, 2, 2])


def test_markers_decode_with_the_input_header(types, frame):
    markers = types.decode_markers(frame.markers).markers
    assert markers[0].action == 3  # DELETEALL
    assert [(m.ns, m.id) for m in markers[1:4]] == [(MESH_NAMESPACE, 1), (OUTLINE_NAMESPACE, 1), (NORMAL_NAMESPACE, 1)]
    assert len(markers) == 1 + 3 * frame.planes.num_planes
    for marker in markers:
        assert header_tuple(marker.header) == (*STAMP, 'os_lidar')
        assert header_tuple(marker.texture.header) == (*STAMP, 'os_lidar')
    mesh = markers[1]
    colour = label_colors([1])[0]
    assert mesh.color.r == pytest.approx(((colour >> 16) & 255) / 255)
    assert mesh.color.a == pytest.approx(0.5)


def test_rosbags_outputs_serialize(scan):
    types = rosbags_message_types()
    frame = process_cloud(cloud(types, scan), ExtractorParams(min_plane_points=20), types)
    store = types.typestore
    for msg in (frame.labeled_points, frame.plane_table):
        raw = store.serialize_cdr(msg, 'sensor_msgs/msg/PointCloud2')
        back = store.deserialize_cdr(raw, 'sensor_msgs/msg/PointCloud2')
        assert bytes(back.data) == bytes(msg.data)


def test_output_selection_and_parameters_reach_the_outputs(types, scan):
    params = ExtractorParams(min_plane_points=20, marker_alpha=0.25, marker_mesh_stride=2)
    frame = process_cloud(
        cloud(types, scan),
        params,
        types,
        outputs=OutputSelection(labeled_points=False, markers=True, plane_table=False),
    )
    assert frame.labeled_points is None and frame.plane_table is None
    mesh = types.decode_markers(frame.markers).markers[1]
    assert mesh.color.a == 0.25
    full = process_cloud(
        cloud(types, scan), params.replace(marker_mesh_stride=1), types, outputs=OutputSelection(False, True, False)
    )
    assert len(types.decode_markers(full.markers).markers[1].points) > 3 * len(mesh.points)
    only_table = process_cloud(
        cloud(types, scan), params.replace(publish_markers=False, publish_labeled_points=False), types
    )
    assert only_table.markers is None and only_table.labeled_points is None
    assert only_table.plane_table is not None


def test_ray_origin_and_thresholds_go_to_the_extractor(types, scan):
    params = ExtractorParams(min_plane_points=500)
    assert process_cloud(cloud(types, scan), params, types).planes.num_planes == 0
    from ppe_ros.core.extraction import extract_planes

    # max_planes counts atomic rays too; with both thresholds the earlier stop wins
    sent = scan.astype(np.float32).astype(np.float64)  # what the float32 cloud carries
    by_error = extract_planes(sent, max_error_increment=0.01, min_plane_points=20)
    by_count = extract_planes(sent, max_error_increment=None, max_planes=600, min_plane_points=20)
    assert by_count.actions < by_error.actions
    frame = process_cloud(cloud(types, scan), ExtractorParams(min_plane_points=20, max_planes=600), types)
    assert frame.planes.actions == by_count.actions
    np.testing.assert_array_equal(frame.planes.labels, by_count.labels)
    shifted = ExtractorParams(min_plane_points=20, ray_origin=(0.0, 0.0, 0.5))
    frame = process_cloud(cloud(types, scan), shifted, types)
    assert frame.planes.num_planes == 3


def test_no_plane_frame_still_builds_every_output(types):
    rng = np.random.default_rng(0)
    points = rng.normal(0.0, 1.0, (8, 10, 3)) + np.array([5.0, 0.0, 0.0])  # noise: no plane of 500 points
    frame = process_cloud(cloud(types, points), ExtractorParams(min_plane_points=500), types)
    assert frame.planes.num_planes == 0
    assert frame.plane_table.width == 0
    assert [m.action for m in types.decode_markers(frame.markers).markers] == [3]
    assert not pointcloud2_to_structured(frame.labeled_points)['label'].any()


def test_float64_input_and_extra_fields_are_read(types, scan):
    table = np.zeros(scan.shape[:2], [('intensity', '<f4'), ('x', '<f8'), ('y', '<f8'), ('z', '<f8'), ('ring', '<u2')])
    table['x'], table['y'], table['z'] = scan[..., 0], scan[..., 1], scan[..., 2]
    msg = structured_to_pointcloud2(
        table, header=make_header(types), msg_class=types.PointCloud2, field_class=types.PointField
    )
    frame = process_cloud(msg, ExtractorParams(min_plane_points=20), types)
    assert frame.planes.num_planes == 3


# ------------------------------------------------------------------ bad input


def expect_skip(types, msg, kind, message, params=None):
    with pytest.raises(FrameSkipped, match=message) as caught:
        process_cloud(msg, params or ExtractorParams(), types)
    assert caught.value.kind == kind
    return caught.value


def test_a_cloud_of_height_1_without_a_ring_field_is_extracted_on_elevation_bins(types, scan):
    """The little 24 x 32 scan, flattened: its rows are found again in the elevation angles."""
    msg = cloud(types, scan.reshape(-1, 3))
    assert msg.height == 1
    frame = process_cloud(msg, ExtractorParams(min_plane_points=20), types)
    assert frame.layout == 'unorganized' and frame.planes.labels.shape == (1, 768)
    assert frame.grid_points.shape == (24, 32, 3) and frame.grid_planes.labels.shape == (24, 32)
    assert frame.planes.num_planes == 3
    organized = process_cloud(cloud(types, scan), ExtractorParams(min_plane_points=20), types).planes
    assert matched_label_agreement(organized.labels, frame.planes.labels) >= 0.99
    assert 'projection' in frame.timings


def hesai_like_cloud(types, points, rings, *, field='ring'):
    """Height 1, fields x y z intensity <field> timestamp (HesaiLidar_ROS_2.0's layout)."""
    table = np.zeros(
        len(points),
        [('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4'), (field, '<u2'), ('timestamp', '<f8')],
    )
    table['x'], table['y'], table['z'] = points.T
    table[field] = rings
    return structured_to_pointcloud2(
        table, header=make_header(types), msg_class=types.PointCloud2, field_class=types.PointField
    )


@pytest.fixture(scope='module')
def sweep():
    sweep = room_sweep(HDL_LIKE_ELEVATIONS[::2], 720, sigma=0.005)
    sweep[np.random.default_rng(8).random(sweep.shape[:2]) < 0.1] = np.nan
    return sweep


def test_a_hesai_like_cloud_gets_the_planes_of_the_organized_sweep_per_point(types, sweep):
    params = ExtractorParams(sensor='lidar')
    organized = process_cloud(cloud(types, sweep), params, types)
    points, rings, index = shuffled(sweep)
    frame = process_cloud(hesai_like_cloud(types, points, rings), params, types)
    assert frame.layout == 'unorganized' and frame.grid_points.shape == (32, 720, 3)
    assert frame.planes.meta['projection'].method == 'rings'
    labels = frame.planes.labels.reshape(-1)
    assert matched_label_agreement(organized.planes.labels.reshape(-1)[index], labels) >= 0.999
    # the labelled cloud keeps the input's height 1, its points and their order
    labeled = pointcloud2_to_structured(frame.labeled_points)
    assert labeled.shape == (1, len(points))
    np.testing.assert_array_equal(labeled['label'][0], labels)
    np.testing.assert_array_equal(labeled['x'][0], points[:, 0].astype(np.float32))
    markers = types.decode_markers(frame.markers).markers
    assert len(markers) > frame.planes.num_planes  # DELETEALL, then meshes (on the range image) and more


def test_a_livox_like_line_field_selects_the_angular_grid(types, sweep):
    points, rings, _ = shuffled(sweep)
    frame = process_cloud(
        hesai_like_cloud(types, points, rings % 4, field='line'), ExtractorParams(sensor='lidar'), types
    )
    assert frame.planes.meta['projection'].method == 'angular_grid'
    assert frame.planes.num_planes >= 4


def test_unorganized_rows_rings_without_a_ring_field_is_skipped(types, sweep):
    points, _, _ = shuffled(sweep)
    expect_skip(
        types,
        cloud(types, points),
        'unorganized',
        'without a ring field, and unorganized_rows is rings',
        ExtractorParams(unorganized_rows='rings'),
    )


def test_bad_ring_values_are_skipped_with_the_reason(types, sweep):
    points, rings, _ = shuffled(sweep)
    table = np.zeros(len(points), [('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('ring', '<i4')])
    table['x'], table['y'], table['z'] = points.T
    table['ring'] = rings - 5
    msg = structured_to_pointcloud2(
        table, header=make_header(types), msg_class=types.PointCloud2, field_class=types.PointField
    )
    expect_skip(types, msg, 'unorganized', r'cannot be put on a range image \(rings\): rings must lie in 0')


def velodyne_like_cloud(types, sweep, *, with_ring=True):
    """Velodyne's organized layout: one row per firing, the lasers across (width = lasers), a ring field."""
    firings = sweep.transpose(1, 0, 2)
    fields = [('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4')] + ([('ring', '<u2')] if with_ring else [])
    table = np.zeros(firings.shape[:2], fields)
    table['x'], table['y'], table['z'] = firings[..., 0], firings[..., 1], firings[..., 2]
    if with_ring:
        table['ring'] = np.arange(firings.shape[1])[None, :]
    return structured_to_pointcloud2(
        table, header=make_header(types), msg_class=types.PointCloud2, field_class=types.PointField
    )


@pytest.mark.parametrize('with_ring', [True, False], ids=['ring_field', 'layout_parameter'])
def test_a_velodyne_like_transposed_cloud_gets_the_planes_of_the_organized_sweep(types, sweep, with_ring):
    params = ExtractorParams(sensor='lidar')
    organized = process_cloud(cloud(types, sweep), params, types).planes
    msg = velodyne_like_cloud(types, sweep, with_ring=with_ring)
    frame = process_cloud(msg, params if with_ring else params.replace(layout='columns_are_beams'), types)
    assert frame.layout == 'columns_are_beams'
    assert frame.planes.labels.shape == (720, 32)  # the input's height x width
    np.testing.assert_array_equal(frame.planes.labels, organized.labels.T)
    labeled = pointcloud2_to_structured(frame.labeled_points)
    assert labeled.shape == (720, 32)
    np.testing.assert_array_equal(labeled['label'], organized.labels.T)
    # processed as it comes (rows_are_beams: the transposed grid itself) it gives the same planes too
    as_is = process_cloud(msg, params.replace(layout='rows_are_beams'), types).planes
    assert matched_label_agreement(as_is.labels, organized.labels.T) >= 0.999


def test_empty_cloud_is_skipped(types):
    msg = cloud(types, np.zeros((0, 5, 3)))
    expect_skip(types, msg, 'empty', r'empty cloud \(height 0, width 5\)')


def test_all_nan_cloud_is_skipped(types):
    expect_skip(types, cloud(types, np.full((4, 6, 3), np.nan)), 'no_valid_points', 'no finite point')


def test_cloud_over_max_points_is_skipped(types, scan):
    expect_skip(
        types,
        cloud(types, scan),
        'too_large',
        r'24 x 32 = 768 points exceeds max_points = 700',
        ExtractorParams(max_points=700),
    )


def test_missing_z_is_skipped(types):
    table = np.zeros((4, 5), [('x', '<f4'), ('y', '<f4'), ('intensity', '<f4')])
    msg = structured_to_pointcloud2(
        table, header=make_header(types), msg_class=types.PointCloud2, field_class=types.PointField
    )
    skipped = expect_skip(types, msg, 'invalid_cloud', 'no z field')
    assert str(skipped).startswith('invalid PointCloud2:')


def test_unsupported_datatype_is_skipped(types, scan):
    msg = cloud(types, scan)
    msg.fields[2].datatype = 13
    expect_skip(types, msg, 'invalid_cloud', 'unsupported datatype 13')


def test_inconsistent_sizes_are_skipped(types, scan):
    short_rows = cloud(types, scan)
    short_rows.row_step = short_rows.point_step * short_rows.width - 4
    expect_skip(types, short_rows, 'invalid_cloud', 'row_step')
    truncated = cloud(types, scan)
    truncated.data = truncated.data[:-12]
    expect_skip(types, truncated, 'invalid_cloud', 'data has')
    bad_step = cloud(types, scan)
    bad_step.point_step = 8
    expect_skip(types, bad_step, 'invalid_cloud', 'point_step')


def test_zero_points_are_no_return(types, scan):
    """Many drivers publish (0, 0, 0) for a pixel without a return: the frame path reads it as NaN, like ppe_ros.io."""
    points = scan.copy()
    points[:, 5] = 0.0  # a column of no-returns
    points[7, 9] = (0.0, 0.0, 1.5)  # a zero coordinate alone is a point
    frame = process_cloud(cloud(types, points), ExtractorParams(min_plane_points=20), types)
    assert np.isnan(frame.points[:, 5]).all()
    assert np.isfinite(frame.points[7, 9]).all()
    assert not frame.planes.labels[:, 5].any()
    labeled = pointcloud2_to_structured(frame.labeled_points)
    assert np.isnan(labeled['x'][:, 5]).all() and not labeled['label'][:, 5].any()
    with_nan = points.copy()
    with_nan[:, 5] = np.nan
    same = process_cloud(cloud(types, with_nan), ExtractorParams(min_plane_points=20), types)
    np.testing.assert_array_equal(frame.planes.labels, same.planes.labels)


def test_all_zero_cloud_is_skipped_as_without_valid_points(types):
    skipped = expect_skip(types, cloud(types, np.zeros((4, 6, 3))), 'no_valid_points', 'no finite point')
    assert '(0, 0, 0)' in skipped.reason


def test_byte_swapped_float_cloud_never_warns_or_raises_in_the_conversion(types, scan):
    """A little-endian cloud labelled big-endian reads as garbage (signalling NaNs, 1e-38 .. 1e38): no numpy
    warning and no exception in the conversion (the extractor decides about the values)."""
    msg = cloud(types, scan)
    msg.is_bigendian = True
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter('error')
        points = cloud_points(msg, ExtractorParams())
    assert points.shape == scan.shape


def test_failure_reason_names_the_exception_inside_a_compiled_kernel():
    try:
        try:
            raise ZeroDivisionError('division by zero')
        except ZeroDivisionError as cause:
            raise SystemError(
                'CPUDispatcher(<function _seed_errors at 0x7f>) returned a result with an exception set'
            ) from cause
    except SystemError as exc:
        assert failure_reason(exc) == 'ZeroDivisionError: division by zero (in the compiled kernel _seed_errors)'
    assert failure_reason(RuntimeError('kernel exploded')) == 'RuntimeError: kernel exploded'
    assert failure_reason(MemoryError()) == 'MemoryError: (no message)'
    assert failure_reason(ValueError('two\nlines')) == 'ValueError: two lines'


def test_frame_label_names_stamp_and_frame_id(types):
    assert frame_label(cloud(types, np.zeros((2, 2, 3)))) == "stamp 1700000123.456000000 s, frame_id 'os_lidar'"
    assert frame_label(object()) == 'a frame without a readable header'


def test_the_sensor_parameter_selects_the_profile(types, scan):
    from ppe_ros.core.extraction import extract_planes

    params = ExtractorParams(min_plane_points=20, sensor='lidar', surface_tolerance=0.04)
    frame = process_cloud(cloud(types, scan), params, types)
    expected = extract_planes(frame.points, sensor='lidar', surface_tolerance=0.04, min_plane_points=20)
    np.testing.assert_array_equal(frame.planes.labels, expected.labels)
    with pytest.raises(ValueError, match='sensor must be one of'):
        ExtractorParams(sensor='sonar')


def test_range_noise_sets_the_profiles_noise_and_needs_a_noise_model(types, scan):
    import dataclasses

    from ppe_ros.core.extraction import extract_planes
    from ppe_ros.core.sensor import PROFILES

    params = ExtractorParams(sensor='lidar', range_noise=0.04)
    frame = process_cloud(cloud(types, scan), params, types)
    lidar = PROFILES['lidar']
    noisier = dataclasses.replace(lidar, noise=dataclasses.replace(lidar.noise, constant=0.04))
    assert lidar.with_range_noise(0.04) == noisier
    with pytest.raises(ValueError, match="'paper' has no noise model"):
        PROFILES['paper'].with_range_noise(0.04)
    expected = extract_planes(frame.points, sensor=noisier)
    np.testing.assert_array_equal(frame.planes.labels, expected.labels)
    np.testing.assert_allclose(frame.planes.covariances, expected.covariances)
    default = process_cloud(cloud(types, scan), ExtractorParams(sensor='lidar'), types)
    assert not np.array_equal(default.planes.covariances, frame.planes.covariances)  # the noise reached the fit
    for sensor in ('none', 'paper'):
        with pytest.raises(ValueError, match='range_noise needs a sensor profile with a noise model'):
            ExtractorParams(sensor=sensor, range_noise=0.03)
    with pytest.raises(ValueError, match='range_noise must be in'):
        ExtractorParams(sensor='lidar', range_noise=-0.01)
    assert ExtractorParams(sensor='none', range_noise=0.0).range_noise == 0.0
