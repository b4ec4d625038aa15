"""Tests of ppe_ros.core.synthetic: the deterministic SynPEB-style scan generator."""

from __future__ import annotations

import time

import numpy as np
import pytest

from ppe_ros.core.synthetic import (
    DEFAULT_SENSOR_POSE,
    ScanGrid,
    Scene,
    SensorPose,
    beam_offset_origins,
    box_polygons,
    cast_rays,
    generate_scan,
    make_room_scene,
    plane_scan,
    plane_scene,
    room_polygons,
    shelf_polygons,
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
    assert np.all(scan.labels >= 10)  # a closed room: every ray returns
    distances = plane_distances(scan)
    assert np.all(np.isfinite(distances))
    assert np.abs(distances).max() < 1e-9
    # The stored points are exactly along the nominal directions.
    np.testing.assert_allclose(scan.points / scan.ranges()[..., None], scan.grid.directions(), atol=1e-12)
    # A point is on its face, not just on its plane: inside the face's bounding box (world frame).
    world = scan.points @ scan.sensor_pose.rotation().T + np.array(scan.sensor_pose.position)
    for label in scan.visible_labels():
        vertices = scan.scene.face(label).vertices
        inside = world[scan.labels == label]
        assert np.all(inside >= vertices.min(axis=0) - 1e-6) and np.all(inside <= vertices.max(axis=0) + 1e-6)


def test_default_scan_looks_like_synpeb():
    scan = generate_scan(seed=0)
    counts = scan.label_counts()
    assert scan.shape == (500, 500) and scan.origins is None
    assert 30 <= len(counts) <= 60  # SynPEB: 42.6 planes per scan on average
    ranges = scan.ranges()
    assert 1.0 < np.nanmin(ranges) and np.nanmax(ranges) < 8.0
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


def test_500_by_500_scan_is_fast():
    generate_scan(seed=1, grid=ScanGrid.uniform(4, 4, azimuth_fov_deg=10.0, elevation_fov_deg=10.0))  # JIT
    start = time.perf_counter()
    generate_scan(seed=1)
    elapsed = time.perf_counter() - start
    assert elapsed < 1.0, f'a 500x500 scan took {elapsed:.2f} s'


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
    )
    scene = Scene.from_polygons(polygons)  # validates planarity and convexity
    assert len(scene.faces) == 6 + 6 + 5 + (10 + 3 * 4) + (6 + 16)
    # A closed box: ray from inside hits exactly one face in every direction at the right distance.
    box = Scene.from_polygons(box_polygons((0.0, 0.0, -1.0), (2.0, 2.0, 2.0), bottom=True))
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(500, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    distances, labels = cast_rays(box, np.zeros((500, 3)), directions)
    np.testing.assert_allclose(distances, 1.0 / np.abs(directions).max(axis=1), rtol=1e-12)
    assert np.all(labels >= 10)


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
