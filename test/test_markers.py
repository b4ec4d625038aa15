"""Marker geometry (mesh of grid cells, outline, winding) and the CDR MarkerArray encoder."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from ppe_ros.core.planes import PlaneSet
from ppe_ros.core.synthetic import polygon_room_lidar_scan
from ppe_ros.ros.markers import (
    _LARGE_BLOCK,
    ARROW,
    DELETEALL,
    LINE_LIST,
    MESH_NAMESPACE,
    NORMAL_NAMESPACE,
    OUTLINE_NAMESPACE,
    TRIANGLE_LIST,
    arrow_lengths,
    budgeted_plane_geometry,
    marker_array_cdr,
    plane_geometry,
)
from ppe_ros.ros.messages import StampedFrame, rosbags_message_types

SPACING = 0.1  # m between grid pixels in the hand-made scenes


def flat_scene(labels: np.ndarray, depth: float = 2.0) -> tuple[np.ndarray, PlaneSet]:
    """Pixels on planes z = depth (label 1) and z = depth + 1 (label 2, if present), facing the origin."""
    labels = np.asarray(labels, np.int32)
    height, width = labels.shape
    rows, cols = np.mgrid[0:height, 0:width].astype(float)
    z = np.where(labels == 2, depth + 1.0, depth)
    points = np.stack([cols * SPACING * z / depth, rows * SPACING * z / depth, z], axis=-1)
    points[labels == 0] = np.nan
    num_planes = int(labels.max())
    normals = np.tile([0.0, 0.0, -1.0], (num_planes, 1))
    offsets = -(depth + np.arange(num_planes, dtype=float))
    centroids = np.array([points[labels == j + 1].mean(axis=0) for j in range(num_planes)])
    counts = np.bincount(labels.ravel(), minlength=num_planes + 1)[1:]
    planes = PlaneSet(
        labels=labels,
        normals=normals,
        offsets=offsets,
        centroids=centroids,
        point_counts=counts,
        sse=np.zeros(num_planes),
        rmse=np.zeros(num_planes),
        covariances=np.tile(np.eye(3) * 1e-4, (num_planes, 1, 1)),
    )
    return points, planes


def polygon_room(height: int = 128, width: int = 1024, sides: int = 28, seed: int = 0):
    """A spinning-lidar scan (sensor at the origin) of a ``sides``-gon room with floor and ceiling.

    Returns points (NaN = no return, 5 %), and a PlaneSet built from the true planes (sides + 2 of them).
    """
    points, labels, normals, offsets = polygon_room_lidar_scan(
        height, width, sides=sides, no_return_fraction=0.05, seed=seed
    )
    num_planes = len(normals)
    counts = np.bincount(labels.ravel(), minlength=num_planes + 1)[1:]
    centroids = np.array([points[labels == j + 1].mean(axis=0) for j in range(num_planes)])
    planes = PlaneSet(
        labels=labels,
        normals=normals,
        offsets=offsets,
        centroids=centroids,
        point_counts=counts,
        sse=np.zeros(num_planes),
        rmse=np.zeros(num_planes),
        covariances=np.zeros((num_planes, 3, 3)),
    )
    return points, planes


def boundary_edges_brute_force(triangles: np.ndarray) -> set:
    """Edges used by exactly one triangle (vertices rounded to 1e-9 m)."""
    uses = Counter()
    for triangle in np.round(triangles, 9):
        corners = [tuple(v) for v in triangle]
        for a, b in ((0, 1), (1, 2), (2, 0)):
            uses[tuple(sorted((corners[a], corners[b])))] += 1
    return {edge for edge, count in uses.items() if count == 1}


def segment_set(segments: np.ndarray) -> set:
    return {tuple(sorted((tuple(s[0]), tuple(s[1])))) for s in np.round(segments, 9)}


def plane_slices(counts: np.ndarray) -> list[slice]:
    ends = np.concatenate([[0], np.cumsum(counts)])
    return [slice(ends[j], ends[j + 1]) for j in range(len(counts))]


def test_full_block_gives_two_triangles_per_cell_and_its_perimeter():
    labels = np.zeros((5, 6), np.int32)
    labels[1:4, 1:5] = 1  # 3 x 4 pixels = 2 x 3 cells
    points, planes = flat_scene(labels)
    geometry = plane_geometry(points, planes)
    assert geometry.triangle_counts.tolist() == [12]
    assert geometry.segment_counts.tolist() == [10]  # 2 * 3 + 2 * 2 sides, no diagonals
    assert geometry.areas[0] == pytest.approx(6 * SPACING**2)


def test_hole_is_kept_not_a_convex_hull():
    labels = np.ones((5, 5), np.int32)
    labels[2, 2] = 0  # one missing pixel in the middle: its 4 cells keep one triangle each
    points, planes = flat_scene(labels)
    geometry = plane_geometry(points, planes)
    assert geometry.triangle_counts.tolist() == [12 * 2 + 4]
    assert geometry.areas[0] == pytest.approx((16 - 4 * 0.5) * SPACING**2)
    assert geometry.segment_counts.tolist() == [16 + 4]  # outer perimeter + the diamond around the hole
    hole = points[2, 2].copy()
    hole[:] = [2 * SPACING, 2 * SPACING, 2.0]
    assert not np.any(np.all(np.isclose(geometry.triangles, hole), axis=-1))


def test_three_corner_cells_and_mixed_labels():
    labels = np.array(
        [
            [1, 1, 2],
            [1, 2, 2],
        ]
    )
    points, planes = flat_scene(labels)
    geometry = plane_geometry(points, planes)
    # cell 0 has corners 1,1,1,2 -> one triangle of plane 1; cell 1 has 1,2,2,2 -> one of plane 2
    assert geometry.triangle_counts.tolist() == [1, 1]
    assert geometry.segment_counts.tolist() == [3, 3]


def test_outline_is_exactly_the_boundary_of_the_mesh():
    rng = np.random.default_rng(3)
    labels = np.where(rng.random((30, 40)) < 0.85, 1, 0)
    labels[:, 25:] = np.where(labels[:, 25:] > 0, 2, 0)
    labels[10:14, 5:9] = 0
    points, planes = flat_scene(labels)
    geometry = plane_geometry(points, planes)
    assert geometry.triangle_counts.min() > 0
    triangle_parts = plane_slices(geometry.triangle_counts)
    segment_parts = plane_slices(geometry.segment_counts)
    for j in range(planes.num_planes):
        expected = boundary_edges_brute_force(geometry.triangles[triangle_parts[j]])
        assert segment_set(geometry.segments[segment_parts[j]]) == expected
        assert len(expected) == geometry.segment_counts[j]  # no duplicates


def test_vertices_are_ray_plane_intersections_wound_towards_the_normal():
    points, planes = polygon_room(height=16, width=64, sides=6)
    origin = np.zeros(3)
    geometry = plane_geometry(points, planes, ray_origin=origin)
    plane_of_triangle = np.repeat(np.arange(planes.num_planes), geometry.triangle_counts)
    normals = planes.normals[plane_of_triangle]
    offsets = planes.offsets[plane_of_triangle]
    for corner in range(3):
        on_plane = np.einsum('ij,ij->i', geometry.triangles[:, corner], normals) - offsets
        np.testing.assert_allclose(on_plane, 0.0, atol=1e-9)
    cross = np.cross(
        geometry.triangles[:, 1] - geometry.triangles[:, 0], geometry.triangles[:, 2] - geometry.triangles[:, 0]
    )
    assert np.all(np.einsum('ij,ij->i', cross, normals) > 0)
    # a mirrored grid (columns reversed) flips the cells' natural winding; the output must not flip
    mirrored = PlaneSet(**{**planes.__dict__, 'labels': planes.labels[:, ::-1]})
    mirrored_triangles = plane_geometry(points[:, ::-1], mirrored).triangles
    cross = np.cross(
        mirrored_triangles[:, 1] - mirrored_triangles[:, 0], mirrored_triangles[:, 2] - mirrored_triangles[:, 0]
    )
    assert np.all(np.einsum('ij,ij->i', cross, normals) > 0)
    # every vertex lies on the ray through some measured point of its plane
    valid = planes.labels > 0
    measured = points[valid]
    directions = measured / np.linalg.norm(measured, axis=1, keepdims=True)
    vertex = geometry.triangles[0, 0]
    alignment = directions @ (vertex / np.linalg.norm(vertex))
    assert alignment.max() == pytest.approx(1.0, abs=1e-12)


def test_ray_origin_moves_the_intersections():
    labels = np.ones((3, 3), np.int32)
    points, planes = flat_scene(labels)
    origin = np.array([0.0, 0.0, 1.0])  # halfway to the plane z = 2
    geometry = plane_geometry(points, planes, ray_origin=origin)
    # the measured points are on the plane already, so the intersections are the points themselves
    np.testing.assert_allclose(
        np.sort(geometry.triangles.reshape(-1, 3), axis=0)[[0, -1]], [points[0, 0], points[2, 2]], atol=1e-12
    )
    noisy = points.copy()
    noisy[..., 2] += 0.05
    noisy[..., :2] *= 2.05 / 2.0  # same rays from the origin, 5 cm beyond the plane
    from_origin = plane_geometry(noisy, planes).triangles
    np.testing.assert_allclose(from_origin[..., 2], 2.0, atol=1e-12)
    np.testing.assert_allclose(np.sort(from_origin.reshape(-1, 3)[:, 0])[-1], 2 * SPACING, atol=1e-12)


def test_grazing_ray_falls_back_to_orthogonal_projection():
    labels = np.ones((2, 2), np.int32)
    points, planes = flat_scene(labels)
    points[0, 0] = [0.5, 0.0, 0.0]  # ray from the origin parallel to the plane z = 2
    geometry = plane_geometry(points, planes)
    assert np.all(np.isfinite(geometry.triangles))
    np.testing.assert_allclose(geometry.triangles[..., 2], 2.0)


def test_stride_coarsens_the_mesh():
    points, planes = flat_scene(np.ones((9, 9), np.int32))
    assert plane_geometry(points, planes).triangle_counts.tolist() == [2 * 8 * 8]
    assert plane_geometry(points, planes, stride=2).triangle_counts.tolist() == [2 * 4 * 4]
    assert plane_geometry(points, planes, stride=2).areas[0] == pytest.approx(64 * SPACING**2)


def test_per_pixel_ray_origins_move_each_pixels_intersection():
    """Ouster beams start off the axis: a pixel's vertex is where the ray from its own start meets the plane."""
    points, planes = flat_scene(np.ones((4, 5), np.int32))
    same = np.broadcast_to([0.0, 0.0, 1.0], points.shape)
    np.testing.assert_array_equal(
        plane_geometry(points, planes, ray_origin=same).triangles,
        plane_geometry(points, planes, ray_origin=np.array([0.0, 0.0, 1.0])).triangles,
    )
    noisy = points.copy()
    noisy[..., 2] += 0.05  # 5 cm beyond the plane z = 2, straight behind each point
    origins = noisy.copy()
    origins[..., 2] = 0.0  # every ray runs along z from its own start below its point: meets z = 2 at (x, y)
    triangles = plane_geometry(noisy, planes, ray_origin=origins).triangles.reshape(-1, 3)
    np.testing.assert_allclose(triangles[:, 2], 2.0, atol=1e-12)
    expected = {tuple(np.round(p[:2], 9)) for p in points.reshape(-1, 3)}
    assert {tuple(np.round(v[:2], 9)) for v in triangles} == expected
    from_origin = plane_geometry(noisy, planes).triangles.reshape(-1, 3)  # rays from (0, 0, 0): shifted inwards
    assert not np.allclose(np.sort(from_origin[:, 0]), np.sort(triangles[:, 0]))
    with pytest.raises(ValueError, match='one per pixel'):
        plane_geometry(points, planes, ray_origin=np.zeros((3, 5, 3)))


def test_mesh_budget_raises_the_stride_until_the_triangles_fit():
    points, planes = flat_scene(np.ones((41, 41), np.int32))
    full = plane_geometry(points, planes)
    assert len(full.triangles) == 2 * 40 * 40
    geometry, stride = budgeted_plane_geometry(points, planes, max_triangles=0)
    assert stride == 1 and np.array_equal(geometry.triangles, full.triangles)
    for budget in (3200, 3199, 800, 500, 100, 7, 1):
        geometry, stride = budgeted_plane_geometry(points, planes, max_triangles=budget)
        assert len(geometry.triangles) <= budget, (budget, stride)
        assert np.array_equal(geometry.triangles, plane_geometry(points, planes, stride=stride).triangles)
        assert stride > 1 or budget >= len(full.triangles)
    assert budgeted_plane_geometry(points, planes, max_triangles=3199)[1] == 2  # 2 * 20 * 20 = 800 triangles
    geometry, stride = budgeted_plane_geometry(points, planes, stride=4, max_triangles=10_000)
    assert stride == 4 and len(geometry.triangles) == 2 * 10 * 10  # within budget: the stride asked for
    with pytest.raises(ValueError, match='max_triangles'):
        budgeted_plane_geometry(points, planes, max_triangles=-1)


def test_the_budget_bounds_the_markers_of_a_depth_camera_sized_cloud():
    """Issue 19 item 9: 640 x 480 at the defaults gave 35.8 MB of markers per frame; the default budget bounds it."""
    from ppe_ros.ros.processing import ExtractorParams

    points, planes = flat_scene(np.ones((480, 640), np.int32), depth=2.0)
    colors = np.full(1, 0x00FF0000, np.uint32)
    stamped = StampedFrame(1, 2, 'camera_depth_optical_frame')
    unbounded = marker_array_cdr(plane_geometry(points, planes), planes, stamped, colors=colors)
    budget = ExtractorParams().marker_max_triangles
    geometry, stride = budgeted_plane_geometry(points, planes, max_triangles=budget)
    bounded = marker_array_cdr(geometry, planes, stamped, colors=colors)
    assert len(unbounded) > 40e6 and stride == 3 and len(geometry.triangles) <= budget
    assert len(bounded) < 72 * budget + 1e6, len(bounded)


def test_no_planes_and_tiny_grids_give_empty_geometry():
    points, planes = flat_scene(np.ones((1, 5), np.int32))
    geometry = plane_geometry(points, planes)
    assert geometry.triangles.shape == (0, 3, 3) and geometry.triangle_counts.tolist() == [0]
    empty = PlaneSet.empty((4, 4))
    assert plane_geometry(np.zeros((4, 4, 3)), empty).num_planes == 0


@pytest.mark.parametrize(
    ('kwargs', 'message'),
    [
        ({'stride': 0}, 'stride'),
        ({'ray_origin': [0.0, 1.0]}, 'ray_origin'),
        ({'ray_origin': [0.0, np.nan, 0.0]}, 'ray_origin'),
    ],
)
def test_bad_arguments_are_rejected(kwargs, message):
    points, planes = flat_scene(np.ones((3, 3), np.int32))
    with pytest.raises(ValueError, match=message):
        plane_geometry(points, planes, **kwargs)


def test_mismatched_shapes_and_labels_are_rejected():
    points, planes = flat_scene(np.ones((3, 3), np.int32))
    with pytest.raises(ValueError, match=r'grid of planes\.labels'):
        plane_geometry(points[:, :2], planes)
    bad = PlaneSet(**{**planes.__dict__, 'labels': np.full((3, 3), 5, np.int32)})
    with pytest.raises(ValueError, match=r'0\.\.1'):
        plane_geometry(points, bad)


# ------------------------------------------------------------------ CDR MarkerArray


@pytest.fixture(scope='module')
def two_plane_markers():
    labels = np.ones((6, 8), np.int32)
    labels[:, 5:] = 2
    labels[2, 2] = 0
    points, planes = flat_scene(labels)
    geometry = plane_geometry(points, planes)
    colors = np.array([0xFF0000, 0x00FF80], np.uint32)
    stamped = StampedFrame(sec=1700000000, nanosec=123456789, frame_id='os_lidar')
    cdr = marker_array_cdr(geometry, planes, stamped, colors=colors, mesh_alpha=0.25)
    return geometry, planes, colors, stamped, cdr


def test_marker_array_layout_headers_and_colours(two_plane_markers):
    geometry, planes, _colors, _stamped, cdr = two_plane_markers
    types = rosbags_message_types()
    markers = types.decode_markers(cdr).markers
    assert [(m.ns, m.id, m.type, m.action) for m in markers] == [
        ('', 0, ARROW, DELETEALL),
        (MESH_NAMESPACE, 1, TRIANGLE_LIST, 0),
        (OUTLINE_NAMESPACE, 1, LINE_LIST, 0),
        (NORMAL_NAMESPACE, 1, ARROW, 0),
        (MESH_NAMESPACE, 2, TRIANGLE_LIST, 0),
        (OUTLINE_NAMESPACE, 2, LINE_LIST, 0),
        (NORMAL_NAMESPACE, 2, ARROW, 0),
    ]
    for marker in markers:
        for header in (marker.header, marker.texture.header):
            assert (header.stamp.sec, header.stamp.nanosec, header.frame_id) == (1700000000, 123456789, 'os_lidar')
        assert marker.pose.orientation.w == 1.0
    mesh_1, outline_1, arrow_1 = markers[1:4]
    assert len(mesh_1.points) == 3 * geometry.triangle_counts[0]
    assert len(outline_1.points) == 2 * geometry.segment_counts[0]
    first = mesh_1.points[0]
    np.testing.assert_allclose([first.x, first.y, first.z], geometry.triangles[0, 0])
    assert (mesh_1.color.r, mesh_1.color.g, mesh_1.color.b, mesh_1.color.a) == (1.0, 0.0, 0.0, 0.25)
    assert outline_1.color.a == 1.0 and outline_1.scale.x > 0
    mesh_2 = markers[4]
    assert (mesh_2.color.r, mesh_2.color.g) == (0.0, 1.0) and mesh_2.color.b == pytest.approx(128 / 255)
    start, end = arrow_1.points
    np.testing.assert_allclose([start.x, start.y, start.z], planes.centroids[0])
    length = arrow_lengths(geometry.areas)[0]
    np.testing.assert_allclose([end.x - start.x, end.y - start.y, end.z - start.z], length * planes.normals[0])


def test_marker_bytes_equal_the_reference_serializers(two_plane_markers):
    cdr = two_plane_markers[-1]
    types = rosbags_message_types()
    decoded = types.decode_markers(cdr)
    assert bytes(types.typestore.serialize_cdr(decoded, 'visualization_msgs/msg/MarkerArray')) == cdr
    from rclpy.serialization import deserialize_message, serialize_message
    from visualization_msgs.msg import MarkerArray

    rclpy_message = deserialize_message(cdr, MarkerArray)
    again = deserialize_message(serialize_message(rclpy_message), MarkerArray)
    assert again == rclpy_message
    assert len(rclpy_message.markers) == 7 and rclpy_message.markers[1].header.frame_id == 'os_lidar'


@pytest.mark.parametrize('frame_id', ['', 'a', 'ab', 'abc', 'abcd', 'abcde', 'abcdef', 'abcdefg', 'base_link'])
def test_marker_bytes_are_exact_for_every_alignment(frame_id):
    """frame_id lengths shift every later field through all 8-byte alignment phases."""
    labels = np.ones((3, 4), np.int32)
    labels[:, 2:] = 2
    points, planes = flat_scene(labels)
    geometry = plane_geometry(points, planes)
    cdr = marker_array_cdr(geometry, planes, StampedFrame(-5, 999, frame_id), colors=np.array([7, 8]))
    types = rosbags_message_types()
    decoded = types.decode_markers(cdr)
    assert bytes(types.typestore.serialize_cdr(decoded, 'visualization_msgs/msg/MarkerArray')) == cdr
    assert {m.header.frame_id for m in decoded.markers} == {frame_id}
    assert {m.header.stamp.sec for m in decoded.markers} == {-5}


@pytest.mark.parametrize('frame_id', ['a', 'abcd', 'base_link'])
def test_large_vertex_blocks_left_in_place_give_the_same_bytes(frame_id):
    """A plane whose mesh and outline take _LARGE_BLOCK bytes or more (its vertices stay a chunk of their own)
    beside small ones: the bytes re-serialize unchanged and the large mesh holds the geometry's triangles."""
    labels = np.ones((40, 48), np.int32)  # plane 1: about 3600 triangles, a mesh of 260 kB
    labels[:6, 44:] = 2  # plane 2: a few cells
    labels[6:, 44:] = 0
    labels[3, 46] = 0
    points, planes = flat_scene(labels)
    geometry = plane_geometry(points, planes)
    assert 72 * geometry.triangle_counts[0] >= _LARGE_BLOCK and 48 * geometry.segment_counts[0] >= _LARGE_BLOCK
    assert 72 * geometry.triangle_counts[1] < _LARGE_BLOCK
    cdr = marker_array_cdr(geometry, planes, StampedFrame(3, 4, frame_id), colors=np.array([5, 6]))
    types = rosbags_message_types()
    decoded = types.decode_markers(cdr)
    assert bytes(types.typestore.serialize_cdr(decoded, 'visualization_msgs/msg/MarkerArray')) == cdr
    mesh = decoded.markers[1]
    assert (mesh.ns, mesh.id, len(mesh.points)) == (MESH_NAMESPACE, 1, 3 * geometry.triangle_counts[0])
    last = mesh.points[-1]
    np.testing.assert_array_equal([last.x, last.y, last.z], geometry.triangles[geometry.triangle_counts[0] - 1, 2])
    assert [m.id for m in decoded.markers] == [0, 1, 1, 1, 2, 2, 2]


def test_plane_without_triangles_gets_only_its_arrow():
    labels = np.zeros((4, 4), np.int32)
    labels[0, :] = 1  # a single row: no 2x2 cell
    labels[2:, 2:] = 2
    points, planes = flat_scene(labels)
    geometry = plane_geometry(points, planes)
    cdr = marker_array_cdr(geometry, planes, StampedFrame(0, 0, 'f'), colors=np.array([1, 2]))
    markers = rosbags_message_types().decode_markers(cdr).markers
    assert [(m.ns, m.id) for m in markers] == [
        ('', 0),
        (NORMAL_NAMESPACE, 1),
        (MESH_NAMESPACE, 2),
        (OUTLINE_NAMESPACE, 2),
        (NORMAL_NAMESPACE, 2),
    ]
    assert all(len(m.points) > 0 for m in markers[1:])  # RViz rejects empty triangle lists


def test_marker_arguments_are_checked(two_plane_markers):
    geometry, planes, colors, stamped, _ = two_plane_markers
    with pytest.raises(ValueError, match='same planes'):
        marker_array_cdr(geometry, planes, stamped, colors=colors[:1])
    with pytest.raises(ValueError, match='mesh_alpha'):
        marker_array_cdr(geometry, planes, stamped, colors=colors, mesh_alpha=1.5)


def test_lidar_sized_cloud_with_30_planes():
    points, planes = polygon_room()
    assert planes.num_planes == 30
    plane_geometry(points[:4, :8], PlaneSet.empty((4, 8)))  # compiled or loaded from cache
    stamped = StampedFrame(1, 2, 'lidar')
    colors = np.arange(30, dtype=np.uint32) * 4099
    geometry = plane_geometry(points, planes)
    cdr = marker_array_cdr(geometry, planes, stamped, colors=colors)
    assert geometry.triangle_counts.sum() > 200_000
    assert len(cdr) > 24 * 3 * geometry.triangle_counts.sum()
