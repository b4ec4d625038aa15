"""Tests of ppe_ros.core.synthetic: the deterministic SynPEB-style scan generator."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest

from ppe_ros.core.synthetic import (
    DEFAULT_MIN_REGION_PIXELS,
    DEFAULT_SENSOR_POSE,
    UNLABELLED_LABEL,
    ScanGrid,
    Scene,
    SensorPose,
    beam_offset_origins,
    box_polygons,
    cast_rays,
    generate_scan,
    icosahedron_polygons,
    label_regions,
    make_room_scene,
    plane_scan,
    plane_scene,
    prism_polygons,
    pyramid_polygons,
    room_polygons,
    shelf_polygons,
    stairs_polygons,
    table_polygons,
    wedge_polygons,
)

SMALL_GRID = ScanGrid.uniform(60, 80, azimuth_fov_deg=70.0, elevation_fov_deg=60.0)


def angles_of(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(elevation, azimuth) in degrees of direction vectors."""
    azimuth = np.degrees(np.arctan2(points[..., 1], points[..., 0]))
    elevation = np.degrees(np.arctan2(points[..., 2], np.hypot(points[..., 0], points[..., 1])))
    return elevation, azimuth


def plane_distances(scan) -> np.ndarray:
    """Per-pixel distance of each labelled point to its own face's plane (NaN elsewhere)."""
    out = np.full(scan.shape, np.nan)
    for label in scan.visible_labels():
        normal, offset = scan.plane_of_label(label)
        mask = scan.labels == label
        out[mask] = scan.points[mask] @ normal - offset
    return out


# ---------------------------------------------------------------------------------------------
# Grid
# ---------------------------------------------------------------------------------------------


def test_synpeb_grid_matches_the_formula_exactly():
    grid = ScanGrid.synpeb()
    assert grid.shape == (500, 500)
    np.testing.assert_array_equal(grid.azimuth_deg, -35.0 + 0.14 * np.arange(500))
    np.testing.assert_array_equal(grid.elevation_deg, np.linspace(30.0, -30.0, 500))
    directions = grid.directions()
    np.testing.assert_allclose(np.linalg.norm(directions, axis=-1), 1.0, atol=1e-15)
    elevation, azimuth = angles_of(directions)
    np.testing.assert_allclose(azimuth, np.broadcast_to(grid.azimuth_deg, (500, 500)), atol=1e-12)
    np.testing.assert_allclose(elevation, np.broadcast_to(grid.elevation_deg[:, None], (500, 500)), atol=1e-12)
    # Row 0 is the top (+30 deg), column 0 the sensor's right (azimuth -35 deg: y < 0).
    assert directions[0, 250, 2] > 0 > directions[499, 250, 2]
    assert directions[250, 0, 1] < 0 < directions[250, 499, 1]


def _read_ascii_pcd(path) -> np.ndarray:
    lines = path.read_bytes().decode('latin-1').splitlines()
    header = {line.split()[0]: line.split()[1:] for line in lines[:20] if line and not line.startswith('#')}
    start = next(i for i, line in enumerate(lines) if line.startswith('DATA')) + 1
    assert header['DATA'] == ['ascii']
    values = np.array([line.split() for line in lines[start:]], dtype=np.float64)
    return values.reshape(int(header['HEIGHT'][0]), int(header['WIDTH'][0]), -1)


def test_synpeb_grid_matches_the_directions_of_the_real_test_scan(shared_data):
    # test_100.pcd is rows/cols 100..199 of SynPEB's test_500 (6-decimal ASCII, ~1e-5 deg rounding).
    data = _read_ascii_pcd(shared_data / 'synpeb' / 'test_100.pcd')
    elevation, azimuth = angles_of(data[..., :3])
    grid = ScanGrid.synpeb()
    np.testing.assert_allclose(azimuth, np.broadcast_to(grid.azimuth_deg[100:200], (100, 100)), atol=2e-4)
    np.testing.assert_allclose(elevation, np.broadcast_to(grid.elevation_deg[100:200, None], (100, 100)), atol=2e-4)


def test_small_uniform_grid():
    grid = ScanGrid.uniform(8, 10, azimuth_fov_deg=45.0, elevation_fov_deg=21.0, azimuth_center_deg=5.0)
    assert grid.shape == (8, 10) and grid.rows == 8 and grid.cols == 10
    np.testing.assert_allclose(grid.azimuth_deg, np.linspace(-17.5, 27.5, 10), atol=1e-13)
    np.testing.assert_allclose(grid.elevation_deg, np.linspace(10.5, -10.5, 8), atol=1e-13)
    scan = plane_scan(2, rows=8, cols=10)
    assert scan.points.shape == (8, 10, 3) and scan.labels.shape == (8, 10)
    single = ScanGrid.uniform(1, 1, azimuth_fov_deg=10.0, elevation_fov_deg=10.0, elevation_center_deg=-3.0)
    assert single.elevation_deg.tolist() == [-3.0] and single.azimuth_deg.tolist() == [0.0]


def test_grid_validation():
    with pytest.raises(ValueError, match='rows and cols'):
        ScanGrid.uniform(0, 5, azimuth_fov_deg=10.0, elevation_fov_deg=10.0)
    with pytest.raises(ValueError, match='between -90 and \\+90'):
        ScanGrid(elevation_deg=np.array([90.0]), azimuth_deg=np.array([0.0]))
    with pytest.raises(ValueError, match='1-D'):
        ScanGrid(elevation_deg=np.zeros((2, 2)), azimuth_deg=np.array([0.0]))


# ---------------------------------------------------------------------------------------------
# Scans
# ---------------------------------------------------------------------------------------------


def test_same_seed_gives_identical_scans_and_other_seeds_differ():
    first = generate_scan(seed=7, grid=SMALL_GRID)
    second = generate_scan(seed=7, grid=SMALL_GRID)
    np.testing.assert_array_equal(first.points, second.points)
    np.testing.assert_array_equal(first.labels, second.labels)
    assert first.params == second.params
    other = generate_scan(seed=8, grid=SMALL_GRID)
    assert not np.array_equal(first.labels, other.labels)
    # Same scene, same seed, different noise level: the same noise pattern, scaled.
    quiet = generate_scan(first.scene, seed=7, grid=SMALL_GRID, radial_sigma=0.01)
    np.testing.assert_allclose(quiet.ranges() - quiet.true_ranges, (first.ranges() - first.true_ranges) / 2, atol=1e-12)


def test_noise_free_labelled_points_lie_on_their_faces():
    scan = generate_scan(seed=3, radial_sigma=0.0, angular_sigma_deg=0.0)
    assert scan.points.shape == (500, 500, 3) and scan.points.dtype == np.float64
    assert scan.labels.dtype == np.int64
    assert np.all(scan.face_labels >= 10)  # a closed room: every ray returns
    assert np.all((scan.labels >= 10) | (scan.labels == UNLABELLED_LABEL))
    distances = plane_distances(scan)
    assert np.all(np.isfinite(distances[scan.labels >= 10]))
    assert np.all(np.isnan(distances[scan.labels == UNLABELLED_LABEL]))
    assert np.nanmax(np.abs(distances)) < 1e-9
    # Every region lies on the face it names; label-3 pixels still lie on the face they hit.
    for label, face_label in scan.region_faces.items():
        assert np.all(scan.face_labels[scan.labels == label] == face_label)
    for face_label in np.unique(scan.face_labels[scan.labels == UNLABELLED_LABEL]):
        face = scan.scene.face(int(face_label))
        world = scan.points[scan.face_labels == face_label] @ scan.sensor_pose.rotation().T
        world += np.array(scan.sensor_pose.position)
        assert np.abs(world @ face.normal - face.offset).max() < 1e-9
    # The stored points are exactly along the nominal directions.
    np.testing.assert_allclose(scan.points / scan.ranges()[..., None], scan.grid.directions(), atol=1e-12)
    # A point is on its face, not just on its plane: inside the face's bounding box (world frame).
    world = scan.points @ scan.sensor_pose.rotation().T + np.array(scan.sensor_pose.position)
    for label in scan.visible_labels():
        vertices = scan.face_of_label(label).vertices
        inside = world[scan.labels == label]
        assert np.all(inside >= vertices.min(axis=0) - 1e-6) and np.all(inside <= vertices.max(axis=0) + 1e-6)


def test_default_scan_looks_like_synpeb():
    scan = generate_scan(seed=0)
    counts = scan.label_counts()
    assert scan.shape == (500, 500) and scan.origins is None
    assert 20 <= len(counts) <= 70  # SynPEB: 42.6 planes per scan on average (30, 38 and 60 in ../shared/data)
    # Contiguous labels from 10, none below the minimum size (SynPEB's smallest: 65 px).
    assert sorted(counts) == list(range(10, 10 + len(counts))) == sorted(scan.region_faces)
    assert scan.params['n_regions'] == len(counts)
    assert min(counts.values()) >= DEFAULT_MIN_REGION_PIXELS
    # A few border slivers are label 3, as in SynPEB (45-136 px per scan); no label is 1, 2 or 4-9.
    unlabelled = np.count_nonzero(scan.labels == UNLABELLED_LABEL)
    assert unlabelled < 0.005 * scan.labels.size
    assert np.all((scan.labels >= 10) | (scan.labels == UNLABELLED_LABEL) | (scan.labels == 0))
    ranges = scan.ranges()
    assert 1.0 < np.nanmin(ranges) and np.nanmax(ranges) < 8.0
    assert 2.0 < np.nanmedian(ranges) < 4.5  # SynPEB pc_01 / test_500: 2.8 / 2.9 m
    assert set(range(10, 16)) <= set(make_room_scene(0).labels.tolist())
    # Radial noise only: the points still lie on the nominal rays, but off their planes by ~2 cm.
    distances = plane_distances(scan)
    assert 0.005 < np.nanstd(distances) < 0.03


def test_about_40_planes_over_several_seeds():
    visible = [len(generate_scan(seed=seed, radial_sigma=0.0).label_counts()) for seed in range(5)]
    assert 30 <= np.mean(visible) <= 55, visible


def test_radial_noise_statistics_on_a_big_face():
    sigma = 0.02
    scan = plane_scan(3, rows=100, cols=120, radial_sigma=sigma, angular_sigma_deg=0.001, seed=11)
    label = 11  # the front wall
    mask = scan.labels == label
    assert mask.sum() > 5000
    normal, offset = scan.plane_of_label(label)
    directions = scan.grid.directions()[mask]
    predicted = offset / (directions @ normal)  # range where the nominal ray meets the plane
    residual = scan.ranges()[mask] - predicted
    assert abs(residual.std() - sigma) < 0.1 * sigma
    assert abs(residual.mean()) < 4 * sigma / np.sqrt(mask.sum())


def test_angular_noise_jitters_cast_direction_but_not_stored_direction():
    exact = plane_scan(3, rows=40, cols=50)
    jittered = plane_scan(3, rows=40, cols=50, angular_sigma_deg=0.05, seed=2)
    # Stored points are along the nominal directions ...
    np.testing.assert_allclose(jittered.points / jittered.ranges()[..., None], jittered.grid.directions(), atol=1e-12)
    # ... at the range of the jittered beam, so they leave the plane (by ~ r * 0.05 deg / tan(incidence)).
    same = jittered.labels == exact.labels
    deviation = np.abs(jittered.ranges() - exact.ranges())[same]
    assert 1e-5 < np.median(deviation) < 0.05
    assert np.abs(plane_distances(exact)).max() < 1e-9


def test_no_returns_are_nan_with_label_zero():
    # One wall only: rays below its bottom edge or beside it hit nothing.
    scan = plane_scan(1, rows=24, cols=32)
    missing = np.isnan(scan.points).any(axis=-1)
    assert 0 < missing.sum() < missing.size
    np.testing.assert_array_equal(missing, scan.labels == 0)
    assert np.all(np.isnan(scan.points[missing]))
    assert np.all(np.isfinite(scan.points[~missing]))
    # A maximum range turns far hits into no-returns.
    full = plane_scan(3, rows=24, cols=32)
    assert not np.isnan(full.points).any()
    limited = generate_scan(
        plane_scene(3),
        grid=full.grid,
        sensor_pose=full.sensor_pose,
        max_range=3.0,
        radial_sigma=0.0,
        angular_sigma_deg=0.0,
    )
    far = full.ranges() > 3.0
    assert 0 < far.sum() < far.size
    np.testing.assert_array_equal(limited.labels == 0, far)
    assert np.all(np.isnan(limited.points[far]))


def test_plane_scan_shows_floor_and_two_walls():
    scan = plane_scan(3)
    assert scan.shape == (24, 32)
    counts = scan.label_counts()
    assert sorted(counts) == [10, 11, 12] and min(counts.values()) > 50
    assert not np.isnan(scan.points).any()
    # Planes in the world frame: floor z = 0, front wall x = 4, left wall y = 3 (faces of plane_scene).
    scene = plane_scene(3)
    np.testing.assert_allclose(np.abs(scene.face(10).normal), [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(np.abs(scene.face(11).normal), [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(np.abs(scene.face(12).normal), [0, 1, 0], atol=1e-15)
    # In the sensor frame the normals face the sensor: offset < 0; floor 1.2 m below the sensor.
    normal, offset = scan.plane_of_label(10)
    assert offset == pytest.approx(-1.2, abs=1e-12)
    assert normal @ scan.sensor_pose.rotation().T @ [0, 0, 1] == pytest.approx(1.0, abs=1e-12)
    assert np.abs(plane_distances(scan)).max() < 1e-9
    # The sensor is pitched, so the plane through the sensor and the vertical wall-wall crease
    # (x = 4, y = 3) is no scan-column plane (those contain the sensor z axis): the two columns
    # straddling the crease are not coplanar, which would make the crease invisible to PPE.
    crease_point = scan.sensor_pose.world_to_sensor(np.array([4.0, 3.0, 0.0]))
    crease_direction = np.array([0.0, 0.0, 1.0]) @ scan.sensor_pose.rotation()
    through_crease = np.cross(crease_point, crease_direction)
    assert abs(through_crease[2]) / np.linalg.norm(through_crease) > 0.1
    two = plane_scan(2)
    assert sorted(two.label_counts()) == [10, 11]


def test_ray_origins_offset():
    grid = ScanGrid.uniform(8, 10, azimuth_fov_deg=40.0, elevation_fov_deg=20.0, azimuth_center_deg=20.0)
    offset = np.array([0.05, -0.02, 0.01])
    scan = generate_scan(
        plane_scene(3),
        grid=grid,
        sensor_pose=SensorPose(position=(0.5, 0.0, 1.2), pitch_deg=5.0),
        ray_origins=offset,
        radial_sigma=0.0,
        angular_sigma_deg=0.0,
        min_region_pixels=1,
    )
    assert scan.origins is not None and scan.origins.shape == (8, 10, 3)
    np.testing.assert_array_equal(scan.origins, np.broadcast_to(offset, (8, 10, 3)))
    rays = scan.points - scan.origins
    np.testing.assert_allclose(rays / np.linalg.norm(rays, axis=-1, keepdims=True), grid.directions(), atol=1e-12)
    assert np.abs(plane_distances(scan)).max() < 1e-9
    # Zero origins: no origins array.
    zero = generate_scan(plane_scene(3), grid=grid, ray_origins=np.zeros((8, 10, 3)), radial_sigma=0.0)
    assert zero.origins is None
    # Per-ray origins on a 15 mm ring (spinning-lidar style).
    ring = beam_offset_origins(grid, 0.015)
    np.testing.assert_allclose(np.linalg.norm(ring[..., :2], axis=-1), 0.015, atol=1e-15)
    ringed = plane_scan(3, rows=8, cols=10, ray_origins=ring)
    np.testing.assert_array_equal(ringed.origins, ring)
    assert np.abs(plane_distances(ringed)).max() < 1e-9
    with pytest.raises(ValueError, match='ray_origins'):
        generate_scan(plane_scene(3), grid=grid, ray_origins=np.zeros((3, 3)))


def test_default_scan_has_the_synpeb_grid_and_many_labelled_faces():
    scan = generate_scan(seed=1)
    assert scan.points.shape == (500, 500, 3)
    assert len(np.unique(scan.labels[scan.labels >= 10])) >= 20


# ---------------------------------------------------------------------------------------------
# Ground-truth regions
# ---------------------------------------------------------------------------------------------


def reference_components(values: np.ndarray) -> np.ndarray:
    """Plain BFS: ``(H, W)`` component number (1, 2, ... in row-major order of first pixel) of the
    4-connected regions of equal positive values; 0 where the value is <= 0."""
    height, width = values.shape
    components = np.zeros(values.shape, dtype=np.int64)
    count = 0
    for row in range(height):
        for col in range(width):
            if values[row, col] <= 0 or components[row, col]:
                continue
            count += 1
            components[row, col] = count
            queue = deque([(row, col)])
            while queue:
                r, c = queue.popleft()
                for rr, cc in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)):
                    if 0 <= rr < height and 0 <= cc < width and not components[rr, cc]:
                        if values[rr, cc] == values[r, c]:
                            components[rr, cc] = count
                            queue.append((rr, cc))
    return components


def test_label_regions_splits_faces_into_4_connected_pieces():
    faces = np.array(
        [
            [10, 10, 11, 10, 0],
            [10, 10, 11, 10, 0],
            [12, 0, 11, 10, 10],
            [0, 12, 12, 12, 0],
        ]
    )
    regions, region_faces = label_regions(faces, min_region_pixels=2)
    expected = np.array(
        [
            [10, 10, 12, 11, 0],
            [10, 10, 12, 11, 0],
            [3, 0, 12, 11, 11],  # (2, 0) touches face 12 only diagonally: a 1-pixel piece, too small
            [0, 13, 13, 13, 0],
        ]
    )
    np.testing.assert_array_equal(regions, expected)
    assert regions.dtype == np.int64
    assert region_faces == {10: 10, 11: 10, 12: 11, 13: 12}
    # Without a size limit the single pixel is a region too, numbered by (face, first pixel).
    regions, region_faces = label_regions(faces, min_region_pixels=1)
    assert regions[2, 0] == 13 and regions[3, 1] == 14 and region_faces[13] == region_faces[14] == 12
    # A U-shaped face whose arms only join in the last row is one region.
    u_shape = np.array([[5, 0, 5], [5, 0, 5], [5, 5, 5]])
    regions, region_faces = label_regions(u_shape, min_region_pixels=1)
    np.testing.assert_array_equal(regions, np.where(u_shape > 0, 10, 0))
    assert region_faces == {10: 5}
    empty, none = label_regions(np.zeros((3, 4), dtype=np.int32))
    assert not empty.any() and none == {}


def test_label_regions_matches_a_plain_flood_fill():
    rng = np.random.default_rng(5)
    faces = rng.integers(0, 4, size=(60, 70)) * 10  # 0 (no face), 10, 20, 30: many small, winding pieces
    faces[20:40, 10:60] = 20
    regions, region_faces = label_regions(faces, min_region_pixels=3)
    components = reference_components(faces)
    sizes = np.bincount(components.ravel())
    # Same partition: a region label <-> a reference component, except the pooled label-3 pixels.
    big = (components > 0) & (sizes[components] >= 3)
    assert np.all(regions[big] >= 10) and np.all(regions[(components > 0) & ~big] == 3)
    assert np.all(regions[components == 0] == 0)
    pairs = np.unique(np.stack([components[big], regions[big]]), axis=1)
    assert len(np.unique(pairs[0])) == len(np.unique(pairs[1])) == pairs.shape[1] == len(region_faces)
    for label, face in region_faces.items():
        assert np.all(faces[regions == label] == face)


def test_label_regions_validation():
    with pytest.raises(ValueError, match='2-D integer'):
        label_regions(np.zeros((2, 2, 2), dtype=np.int64))
    with pytest.raises(ValueError, match='2-D integer'):
        label_regions(np.zeros((2, 2)))
    with pytest.raises(ValueError, match='min_region_pixels'):
        label_regions(np.zeros((2, 2), dtype=np.int64), min_region_pixels=0)
    with pytest.raises(ValueError, match='first_label'):
        label_regions(np.zeros((2, 2), dtype=np.int64), first_label=3)
    with pytest.raises(ValueError, match='min_region_pixels'):
        generate_scan(seed=0, min_region_pixels=-5)


WALL_POSE = SensorPose(position=(0.5, 0.0, 1.5), pitch_deg=0.0, yaw_deg=0.0)
WALL_GRID = ScanGrid.uniform(40, 60, azimuth_fov_deg=60.0, elevation_fov_deg=40.0)


def wall_scan(extra_polygons, **kwargs):
    """The front wall of plane_scene(1) (face 10, x = 4 m) seen head-on, with extra faces in front."""
    polygons = [(face.name, face.vertices) for face in plane_scene(1).faces] + list(extra_polygons)
    scene = Scene.from_polygons(polygons)
    return generate_scan(scene, grid=WALL_GRID, sensor_pose=WALL_POSE, radial_sigma=0.0, **kwargs)


def test_a_face_split_by_an_occluder_gets_two_labels():
    alone = wall_scan([])
    assert not np.any(alone.labels == 0) and alone.region_faces == {10: 10}
    # A full-height post 1 m in front of the wall cuts the wall into a left and a right piece.
    scan = wall_scan(box_polygons((3.0, 0.0, 0.0), (0.1, 0.3, 4.0), name='post'))
    wall_regions = sorted(label for label, face in scan.region_faces.items() if face == 10)
    assert wall_regions == [10, 11]
    # Numbered in order of first pixel: row 0, column 0 (azimuth -30 deg, the sensor's right) is in 10.
    assert scan.labels[0, 0] == 10 and scan.labels[0, -1] == 11
    assert min(scan.label_counts()[10], scan.label_counts()[11]) > 500
    post_front = scan.scene.faces[[face.name for face in scan.scene.faces].index('post.-x')].label
    assert post_front in scan.region_faces.values()
    # The pieces are separated by the post in every row, and share the wall's plane.
    for row in range(scan.shape[0]):
        cols_10, cols_11 = np.flatnonzero(scan.labels[row] == 10), np.flatnonzero(scan.labels[row] == 11)
        assert cols_10.max() < cols_11.min() - 1
    np.testing.assert_allclose(scan.plane_of_label(10)[0], scan.plane_of_label(11)[0], atol=1e-12)
    assert scan.face_of_label(10) is scan.face_of_label(11) is scan.scene.face(10)
    with pytest.raises(KeyError, match='no ground-truth region'):
        scan.face_of_label(99)


def test_pieces_below_the_minimum_size_are_label_3():
    # A 10 cm square 2.5 m away covers about 2 x 2 pixels of the 1-degree grid.
    tiny = ('tiny', np.array([[3.0, 0.45, 1.45], [3.0, 0.55, 1.45], [3.0, 0.55, 1.55], [3.0, 0.45, 1.55]]))
    scan = wall_scan([tiny])
    tiny_pixels = scan.face_labels == 11
    assert 1 <= tiny_pixels.sum() < DEFAULT_MIN_REGION_PIXELS
    assert np.all(scan.labels[tiny_pixels] == UNLABELLED_LABEL)
    assert scan.region_faces == {10: 10}  # the wall around it is still one region
    assert scan.params['min_region_pixels'] == DEFAULT_MIN_REGION_PIXELS and scan.params['n_regions'] == 1
    kept = wall_scan([tiny], min_region_pixels=1)
    assert kept.region_faces == {10: 10, 11: 11}
    np.testing.assert_array_equal(kept.labels[tiny_pixels], 11)
    np.testing.assert_array_equal(kept.face_labels, scan.face_labels)


def test_room_scan_regions_are_maximal_4_connected_pieces_of_faces():
    grid = ScanGrid.uniform(100, 100, azimuth_fov_deg=70.0, elevation_fov_deg=60.0)
    for seed in (0, 2):
        scan = generate_scan(seed=seed, grid=grid, min_region_pixels=8)
        components = reference_components(scan.face_labels)
        sizes = np.bincount(components.ravel())
        for label, face in scan.region_faces.items():
            mask = scan.labels == label
            pieces = np.unique(components[mask])
            assert len(pieces) == 1 and np.array_equal(mask, components == pieces[0])  # one whole piece
            assert mask.sum() >= 8 and np.all(scan.face_labels[mask] == face)
        small = (components > 0) & (sizes[components] < 8)
        np.testing.assert_array_equal(scan.labels == UNLABELLED_LABEL, small)
        # Some face of the room is seen in more than one piece (what the old labels merged).
        assert len(scan.region_faces) > len(set(scan.region_faces.values()))


# ---------------------------------------------------------------------------------------------
# Scene model
# ---------------------------------------------------------------------------------------------


def test_room_scene_labels_and_layout():
    scene = make_room_scene(4)
    labels = scene.labels
    np.testing.assert_array_equal(labels, np.arange(10, 10 + len(labels)))  # every face its own label
    assert [face.name for face in scene.faces[:6]] == [
        'room.floor',
        'room.ceiling',
        'room.wall_x0',
        'room.wall_x1',
        'room.wall_y0',
        'room.wall_y1',
    ]
    # Every object face lies inside the room and away from the default sensor position.
    size = np.array(scene.room_size)
    sensor_xy = np.array(DEFAULT_SENSOR_POSE.position[:2])
    for face in scene.faces[6:]:
        assert np.all(face.vertices >= -1e-12) and np.all(face.vertices <= size + 1e-12)
        assert np.all(np.linalg.norm(face.vertices[:, :2] - sensor_xy, axis=1) > 1.0 - 1e-9)
    assert make_room_scene(4).description == scene.description
    empty = make_room_scene(4, n_objects=0)
    assert len(empty.faces) == 6


def test_primitives_have_planar_convex_faces():
    polygons = (
        room_polygons()
        + box_polygons((1.0, 1.0, 0.0), (0.5, 0.4, 0.3), yaw_deg=30.0, bottom=True)
        + wedge_polygons((2.0, 1.0, 0.0), (0.8, 0.5, 0.4), yaw_deg=-20.0, bottom=True)
        + shelf_polygons((3.0, 2.0, 0.0), (1.0, 0.3, 1.5), yaw_deg=45.0, n_boards=3)
        + table_polygons((4.0, 3.0, 0.0), (1.2, 0.8, 0.75), yaw_deg=10.0)
        + prism_polygons((1.0, 4.0, 0.0), (0.8, 0.8, 1.5), n_sides=7, yaw_deg=5.0, bottom=True)
        + pyramid_polygons((2.5, 4.0, 0.0), (1.0, 1.0, 1.2), n_sides=5, yaw_deg=-12.0, bottom=True)
        + icosahedron_polygons((5.0, 1.0, 1.5), 0.5, yaw_deg=33.0, tilt_deg=71.0)
        + stairs_polygons((5.0, 4.0, 0.0), (1.2, 1.0, 0.8), n_steps=4, yaw_deg=90.0)
    )
    scene = Scene.from_polygons(polygons)  # validates planarity and convexity
    assert len(scene.faces) == 6 + 6 + 5 + (10 + 3 * 4) + (6 + 16) + (1 + 7 + 1) + (5 + 1) + 20 + (4 * 4 + 1)
    # No part of the furniture is thinner than 4 cm (8 cm table legs): faces several pixels wide.
    for face in table_polygons((0.0, 0.0, 0.0), (1.2, 0.8, 0.75)) + shelf_polygons((0.0, 0.0, 0.0), (1.0, 0.3, 1.5)):
        extent = np.ptp(face[1], axis=0)
        assert np.sort(extent)[1] >= 0.04 - 1e-12, face[0]
        if '.leg' in face[0]:
            assert np.sort(extent)[1] >= 0.08 - 1e-12
    # A closed box: ray from inside hits exactly one face in every direction at the right distance.
    box = Scene.from_polygons(box_polygons((0.0, 0.0, -1.0), (2.0, 2.0, 2.0), bottom=True))
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(500, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    distances, labels = cast_rays(box, np.zeros((500, 3)), directions)
    np.testing.assert_allclose(distances, 1.0 / np.abs(directions).max(axis=1), rtol=1e-12)
    assert np.all(labels >= 10)
    # The icosahedron is closed too: every ray from its centre leaves through a face between the
    # inradius (0.7558 R) and the circumradius, and all 20 faces get hit.
    icosahedron = Scene.from_polygons(icosahedron_polygons((0.0, 0.0, 0.0), 2.0, yaw_deg=10.0, tilt_deg=20.0))
    distances, labels = cast_rays(icosahedron, np.zeros((500, 3)), directions)
    assert np.all(distances > 0.7557 * 2.0) and np.all(distances < 2.0 + 1e-12)
    assert set(labels.tolist()) == set(range(10, 30))


def test_scene_validation():
    with pytest.raises(ValueError, match='coplanar'):
        Scene.from_polygons([('bent', np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.1]]))])
    with pytest.raises(ValueError, match='convex'):
        Scene.from_polygons([('dart', np.array([[0, 0, 0], [2, 0, 0], [0.5, 0.5, 0], [0, 2, 0]]))])
    with pytest.raises(ValueError, match='K >= 3'):
        Scene.from_polygons([('line', np.array([[0, 0, 0], [1, 0, 0]]))])
    with pytest.raises(ValueError, match='seed'):
        generate_scan(seed=-1)
    with pytest.raises(ValueError, match='radial_sigma'):
        generate_scan(seed=0, radial_sigma=-0.1)
    with pytest.raises(ValueError, match='n_planes'):
        plane_scene(4)
    with pytest.raises(KeyError):
        plane_scene(2).face(99)


def test_polygon_room_lidar_scan_points_lie_on_their_faces():
    from ppe_ros.core.synthetic import polygon_room_lidar_scan

    points, labels, normals, offsets = polygon_room_lidar_scan(16, 64, sides=6, noise=0.0, no_return_fraction=0.1)
    assert points.shape == (16, 64, 3) and labels.shape == (16, 64) and normals.shape == (8, 3)
    valid = labels > 0
    assert np.array_equal(valid, np.isfinite(points).all(axis=2)) and 0.8 < valid.mean() < 0.97
    distance = np.einsum('ij,ij->i', points[valid], normals[labels[valid] - 1]) - offsets[labels[valid] - 1]
    assert np.abs(distance).max() < 1e-9
    # normals face the sensor at the origin (offsets < 0 with n . x = d and the origin inside)
    assert np.all(offsets < 0)
    with pytest.raises(ValueError, match='sides'):
        polygon_room_lidar_scan(sides=2)
