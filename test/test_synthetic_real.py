"""Tests of ppe_ros.core.synthetic_real: lidar and depth-camera scans with real sensor errors."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from ppe_ros.core.evaluation import score_segmentation
from ppe_ros.core.synthetic import UNLABELLED_LABEL, SensorPose, cast_rays, make_room_scene
from ppe_ros.core.synthetic_real import (
    CLUTTER_LABEL,
    OS1_128_ALTITUDES_DEG,
    DepthErrorModel,
    LidarErrorModel,
    SurfaceSceneBuilder,
    cast_surface_rays,
    generate_depth_scan,
    generate_lidar_scan,
    lidar_grid,
    make_indoor_scene,
    make_street_scene,
)

ORIGIN_POSE = SensorPose(position=(0.0, 0.0, 0.0), roll_deg=0.0, pitch_deg=0.0, yaw_deg=0.0)


def wall_scene(distance: float = 10.0, *, floor: float | None = None, post: bool = False):
    """A big wall at x = distance (and optionally a floor at z = -floor and a post in front)."""
    builder = SurfaceSceneBuilder()
    wall = builder.surface('wall')
    builder.add(
        wall,
        np.array(
            [
                (distance, -3 * distance, -2 * distance),
                (distance, 3 * distance, -2 * distance),
                (distance, 3 * distance, 2 * distance),
                (distance, -3 * distance, 2 * distance),
            ]
        ),
    )
    if floor is not None:
        builder.new_group()
        ground = builder.surface('floor')
        builder.add(
            ground,
            np.array(
                [(-200.0, -200.0, -floor), (200.0, -200.0, -floor), (200.0, 200.0, -floor), (-200.0, 200.0, -floor)]
            ),
        )
    if post:
        builder.new_group()
        label = builder.surface('post', clutter=True)
        x = distance / 2
        builder.add(label, np.array([(x, -0.3, -50.0), (x, 0.3, -50.0), (x, 0.3, 50.0), (x, -0.3, 50.0)]))
    return builder.build('test wall')


@pytest.fixture(scope='module')
def street_scan():
    return generate_lidar_scan(seed=0, cols=512)


# ---------------------------------------------------------------------------------------------
# Ray casting and determinism
# ---------------------------------------------------------------------------------------------


def test_grouped_caster_matches_the_reference_cast_rays():
    scene = make_street_scene(3)
    rng = np.random.default_rng(5)
    origins = np.array([0.0, 0.0, 1.8]) + rng.uniform(-5, 5, (4000, 3)) * np.array([1, 0.2, 0.05])
    directions = rng.standard_normal((4000, 3)) * np.array([1.0, 1.0, 0.2])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    reference, reference_labels = cast_rays(scene.scene, origins, directions)
    distances, labels = cast_surface_rays(scene, origins, directions)
    np.testing.assert_array_equal(labels, reference_labels)
    np.testing.assert_allclose(distances, reference, rtol=1e-12, atol=1e-12)
    assert np.mean(labels > 0) > 0.5


def test_same_seed_gives_identical_scans_and_other_seeds_differ():
    first = generate_lidar_scan(seed=4, model='os1-32', cols=128)
    again = generate_lidar_scan(seed=4, model='os1-32', cols=128)
    other = generate_lidar_scan(seed=5, model='os1-32', cols=128)
    np.testing.assert_array_equal(first.points, again.points)
    np.testing.assert_array_equal(first.labels, again.labels)
    assert not np.array_equal(np.nan_to_num(first.points), np.nan_to_num(other.points))
    depth = generate_depth_scan(seed=2, width=80, height=60)
    np.testing.assert_array_equal(depth.points, generate_depth_scan(seed=2, width=80, height=60).points)
    assert not np.array_equal(
        np.nan_to_num(depth.points), np.nan_to_num(generate_depth_scan(seed=3, width=80, height=60).points)
    )


def test_sensor_seed_fixes_the_calibration_errors_across_scans():
    first = generate_lidar_scan(seed=1, model='os1-32', cols=64, sensor_seed=9)
    second = generate_lidar_scan(seed=2, model='os1-32', cols=64, sensor_seed=9)
    assert first.params['beam_range_bias'] == second.params['beam_range_bias']
    assert first.params['beam_elevation_error_deg'] == second.params['beam_elevation_error_deg']
    assert (
        first.params['beam_range_bias']
        != generate_lidar_scan(seed=1, model='os1-32', cols=64).params['beam_range_bias']
    )


def test_a_small_lidar_grid_is_fast():
    scene = make_street_scene(1)
    generate_lidar_scan(scene, seed=1, model='os1-32', cols=256)  # builds and keeps the packed scene
    start = time.perf_counter()
    scan = generate_lidar_scan(scene, seed=2, model='os1-32', cols=256)
    assert time.perf_counter() - start < 1.0
    assert scan.shape == (32, 256)


# ---------------------------------------------------------------------------------------------
# Lidar geometry and error statistics
# ---------------------------------------------------------------------------------------------


def test_lidar_grid_and_beam_origins_are_ouster_like():
    grid = lidar_grid('os1-128', 1024)
    np.testing.assert_array_equal(grid.elevation_deg, OS1_128_ALTITUDES_DEG)
    assert np.ptp(np.diff(grid.elevation_deg)) > 0.05  # not uniform
    np.testing.assert_allclose(grid.azimuth_deg[:3], [0.0, -360 / 1024, -720 / 1024])
    scan = generate_lidar_scan(
        wall_scene(), seed=0, model='os1-32', cols=64, sensor_pose=ORIGIN_POSE, errors=LidarErrorModel.exact()
    )
    np.testing.assert_allclose(np.linalg.norm(scan.origins[..., :2], axis=-1), 0.015806, rtol=1e-12)
    assert np.all(scan.origins[..., 2] == 0.0)
    # Exact model: every returned point lies on the wall, along the nominal beam from its origin.
    hit = np.isfinite(scan.points[..., 0])
    assert hit.sum() > 500
    np.testing.assert_allclose(scan.points[hit, 0], 10.0, atol=1e-9)
    with pytest.raises(ValueError, match='unknown lidar model'):
        lidar_grid('vlp-16')


def test_velodyne_like_models_have_their_beams():
    vlp16, hdl32 = lidar_grid('vlp16'), lidar_grid('hdl32')
    assert vlp16.shape == (16, 1024) and hdl32.shape == (32, 1024)
    np.testing.assert_allclose(np.diff(vlp16.elevation_deg), -2.0, atol=1e-12)
    np.testing.assert_allclose(vlp16.elevation_deg[[0, -1]], [15.0, -15.0])
    np.testing.assert_allclose(np.diff(hdl32.elevation_deg), -(10.67 + 30.67) / 31, atol=1e-12)  # 1.33 deg
    np.testing.assert_allclose(hdl32.elevation_deg[[0, -1]], [10.67, -30.67])
    hdl64 = lidar_grid('hdl64', cols=2048)  # KITTI's HDL-64E at 10 Hz: about 0.18 deg between columns
    assert hdl64.shape == (64, 2048)
    np.testing.assert_allclose(np.diff(hdl64.elevation_deg[:32]), -1 / 3, atol=1e-3)  # the upper block
    np.testing.assert_allclose(np.diff(hdl64.elevation_deg[32:]), -0.5, atol=1e-12)  # the lower block
    np.testing.assert_allclose(hdl64.elevation_deg[[0, 31, 32, -1]], [2.0, -8.333, -8.833, -24.333])
    scan = generate_lidar_scan(
        wall_scene(), seed=0, model='vlp16', cols=64, sensor_pose=ORIGIN_POSE, errors=LidarErrorModel.exact()
    )
    assert scan.points.shape == (16, 64, 3)
    rays = scan.points - scan.origins
    hit = np.isfinite(rays[..., 0])
    elevation = np.degrees(np.arcsin(rays[..., 2] / np.linalg.norm(rays, axis=-1)))
    np.testing.assert_allclose(elevation[hit], np.broadcast_to(vlp16.elevation_deg[:, None], hit.shape)[hit], atol=1e-9)


def test_per_beam_range_bias_is_the_mean_residual_per_beam_on_a_flat_wall():
    errors = LidarErrorModel.exact(range_sigma=0.015, beam_range_bias_sigma=0.015)
    scan = generate_lidar_scan(wall_scene(), seed=3, model='os1-32', cols=256, sensor_pose=ORIGIN_POSE, errors=errors)
    residual = scan.ranges() - scan.true_ranges
    counts = np.isfinite(residual).sum(axis=1)
    assert counts.min() > 80
    mean = np.nanmean(residual, axis=1)
    bias = np.array(scan.params['beam_range_bias'])
    assert np.std(bias) > 0.008
    assert np.max(np.abs(mean - bias)) < 4 * 0.015 / math.sqrt(counts.min())
    assert np.corrcoef(mean, bias)[0, 1] > 0.98
    # The noise about the bias has the model's sigma (near-normal incidence on this wall).
    noise = residual - bias[:, None]
    assert np.nanstd(noise) == pytest.approx(errors.sigma(np.array(0.9)).item(), rel=0.1)


def test_per_beam_elevation_error_tilts_the_true_beams():
    errors = LidarErrorModel.exact(beam_elevation_sigma_deg=0.05)
    scan = generate_lidar_scan(
        wall_scene(300.0, floor=2.0), seed=1, model='os1-128', cols=64, sensor_pose=ORIGIN_POSE, errors=errors
    )
    grid = lidar_grid('os1-128', 64)
    down = grid.elevation_deg < -2.0
    # On the floor z = -2 (ray starts at z = 0) the cast ray's elevation is asin(-2 / t).
    true_elevation = np.degrees(np.arcsin(-2.0 / scan.true_ranges[down]))
    drawn = np.array(scan.params['beam_elevation_error_deg'])[down]
    np.testing.assert_allclose(
        true_elevation - grid.elevation_deg[down, None],
        np.broadcast_to(drawn[:, None], true_elevation.shape),
        atol=1e-9,
    )
    assert np.std(drawn) > 0.02
    # The points are stored along the nominal beams, so they leave the floor by about -r cos(el) * error.
    height = scan.points[down][..., 2] + 2.0
    expected = (
        -scan.true_ranges[down] * np.radians(drawn)[:, None] * np.cos(np.radians(grid.elevation_deg[down]))[:, None]
    )
    np.testing.assert_allclose(height, expected, atol=2e-3)


def test_grazing_noise_follows_the_model_sigma():
    errors = LidarErrorModel.exact(range_sigma=0.01, grazing_sigma=0.003)
    scan = generate_lidar_scan(
        wall_scene(400.0, floor=1.8), seed=2, model='os1-128', cols=512, sensor_pose=ORIGIN_POSE, errors=errors
    )
    on_floor = scan.labels == scan.scene.faces[1].label
    direction = (scan.points - scan.origins) / scan.ranges()[..., None]
    cos_incidence = np.abs(direction[..., 2])
    residual = scan.ranges() - scan.true_ranges
    for low, high in ((0.3, 0.5), (0.1, 0.15), (0.04, 0.06)):
        band = on_floor & (cos_incidence > low) & (cos_incidence < high)
        assert band.sum() > 1000
        expected = float(np.sqrt(np.mean(errors.sigma(cos_incidence[band]) ** 2)))
        assert np.std(residual[band]) == pytest.approx(expected, rel=0.1)
    assert errors.sigma(np.array(0.05)) > 3 * errors.sigma(np.array(1.0))


def test_surface_undulation_has_the_model_amplitude_and_is_smooth():
    errors = LidarErrorModel.exact(surface_amplitude=0.008)
    scan = generate_lidar_scan(
        wall_scene(12.0), seed=4, model='os1-128', cols=1024, sensor_pose=ORIGIN_POSE, errors=errors
    )
    on_wall = np.isfinite(scan.points[..., 0])
    height = scan.points[..., 0] - 12.0  # the wall's normal is x
    rms = float(np.sqrt(np.nanmean(height[on_wall] ** 2)))
    assert rms == pytest.approx(0.008, rel=0.35)
    # Smooth at the wavelengths of 1-3 m: neighbouring columns (~7 cm apart) differ by far less than the amplitude.
    step = np.abs(np.diff(height, axis=1))
    assert np.nanmedian(step) < 0.3 * rms  # white noise of that RMS: about 0.95 rms
    assert np.nanmax(np.abs(height)) < 6 * 0.008


def test_dropouts_grow_at_grazing_incidence_and_range_is_limited():
    errors = LidarErrorModel.exact(dropout_rate=0.02, grazing_dropout_deg=88.0, grazing_dropout_width_deg=0.5)
    scan = generate_lidar_scan(
        wall_scene(400.0, floor=1.8), seed=6, model='os1-128', cols=512, sensor_pose=ORIGIN_POSE, errors=errors
    )
    floor_label = scan.scene.faces[1].label
    hits_floor = scan.face_labels == floor_label
    cos_incidence = 1.8 / scan.true_ranges
    returned = np.isfinite(scan.points[..., 0])
    in_range = hits_floor & (scan.true_ranges <= errors.max_range)
    incidence = np.degrees(np.arccos(cos_incidence[in_range]))
    grazing_probability = 1 / (1 + np.exp(-(incidence - 88.0) / 0.5))
    expected = 1 - (1 - grazing_probability) * (1 - 0.02)
    lost = ~returned[in_range]
    for band in (incidence < 80.0, (incidence > 87.0) & (incidence < 88.0), incidence > 88.5):
        assert band.sum() > 300
        p = expected[band].mean()
        assert lost[band].mean() == pytest.approx(p, abs=4 * math.sqrt(p * (1 - p) / band.sum()) + 1e-3)
    assert lost[incidence < 80.0].mean() == pytest.approx(0.02, abs=0.01)
    assert lost[incidence > 88.5].mean() > 0.7
    # Beyond max_range nothing returns (the wall at 400 m), no-returns are NaN with label 0.
    assert not returned[scan.face_labels == scan.scene.faces[0].label].any()
    assert np.all(scan.labels[~returned] == 0)
    far = generate_lidar_scan(
        wall_scene(95.0), seed=0, model='os1-32', cols=64, sensor_pose=ORIGIN_POSE, errors=LidarErrorModel.exact()
    )
    assert np.isfinite(far.points[..., 0]).any()


# ---------------------------------------------------------------------------------------------
# Ground truth
# ---------------------------------------------------------------------------------------------


def test_street_has_kerbs_recessed_windows_and_a_ramp_as_separate_labels(street_scan):
    scan = street_scan
    names = scan.surface_names
    visible = {names[int(label)] for label in np.unique(scan.labels[scan.labels >= 10])}
    assert {'road', 'kerb_left', 'kerb_right', 'pavement_left', 'pavement_right', 'ramp'} <= visible
    windows = [n for n in visible if '.window' in n and n.count('.') == 1]
    facades = [n for n in visible if n.endswith('.facade')]
    assert len(windows) >= 5 and len(facades) >= 3
    label_of = {name: label for label, name in names.items()}
    # Kerb: a vertical step of 12-15 cm between road (z = 0) and pavement.
    kerb = scan.scene.face(label_of['kerb_left']).vertices
    assert 0.12 <= np.ptp(kerb[:, 2]) <= 0.15
    pavement = scan.scene.face(label_of['pavement_left']).vertices
    assert np.all(pavement[:, 2] == kerb[:, 2].max())
    # Ramp: 5 deg against the pavement.
    ramp_normal = scan.scene.face(label_of['ramp']).normal
    assert math.degrees(math.acos(abs(ramp_normal[2]))) == pytest.approx(5.0, abs=1e-9)
    # A window: parallel to its facade, 8-12 cm behind it.
    window = windows[0]
    pane = scan.scene.face(label_of[window])
    facade = scan.scene.face(label_of[window.split('.')[0] + '.facade'])
    assert abs(pane.normal @ facade.normal) == pytest.approx(1.0, abs=1e-12)
    gap = abs((pane.vertices.mean(axis=0) - facade.vertices[0]) @ facade.normal)
    assert 0.08 <= gap <= 0.2
    # Walls meeting at 90 deg: a facade and its building's side wall.
    building = facades[0].split('.')[0]
    side = scan.scene.face(label_of[f'{building}.end0'])
    assert abs(side.normal @ scan.scene.face(label_of[facades[0]]).normal) < 1e-12


def test_clutter_is_unlabelled_and_errors_are_realistic(street_scan):
    scan = street_scan
    returned = np.isfinite(scan.points[..., 0])
    on_clutter = np.isin(scan.face_labels, list(scan.clutter_labels)) & returned
    assert on_clutter.mean() > 0.03
    assert np.all(scan.labels[on_clutter] == CLUTTER_LABEL)
    assert np.all(np.isin(scan.labels[returned & ~on_clutter], [UNLABELLED_LABEL, *range(10, scan.labels.max() + 1)]))
    assert not np.any(scan.labels[returned & ~on_clutter] == CLUTTER_LABEL)
    kinds = {
        scan.surface_names[int(label)].rstrip('0123456789').rstrip('_')
        for label in np.unique(scan.face_labels[on_clutter])
    }
    assert {'tree_left', 'tree_right'} & kinds and any(kind.startswith('car') for kind in kinds)
    assert 0.5 < returned.mean() < 0.99  # sky and dropouts
    # Labelled points are near their surface's plane (undulation, noise, biases), but not on it.
    distances = []
    for label in np.unique(scan.labels[scan.labels >= 10]):
        normal, offset = scan.plane_of_label(int(label))
        mask = scan.labels == label
        distances.append(scan.points[mask] @ normal - offset)
    distances = np.concatenate(distances)
    assert 0.005 < np.median(np.abs(distances)) < 0.05


def test_an_occluded_wall_is_one_label_in_several_connected_pieces():
    scan = generate_lidar_scan(
        wall_scene(10.0, post=True),
        seed=0,
        model='os1-32',
        cols=512,
        sensor_pose=ORIGIN_POSE,
        errors=LidarErrorModel.exact(),
    )
    wall = scan.scene.faces[0].label
    assert set(np.unique(scan.labels[scan.labels > 0])) == {wall, CLUTTER_LABEL}
    regions, region_surfaces = scan.connected_labels()
    pieces = [region for region, surface in region_surfaces.items() if surface == wall]
    assert len(pieces) == 2
    assert np.all((regions >= 10) == (scan.labels == wall))
    assert np.all(regions[scan.labels == CLUTTER_LABEL] == CLUTTER_LABEL)
    # Scoring: the surface as one plane is correct; the two pieces as two planes over-segment it.
    whole = score_segmentation(np.where(scan.labels == wall, 1, 0), scan.labels)
    assert whole.f == 1.0 and whole.k == 1.0
    split = score_segmentation(np.where(regions >= 10, regions - 9, 0), scan.labels)
    assert split.f == 0.0
    assert score_segmentation(np.where(regions >= 10, regions - 9, 0), regions).f == 1.0


def test_surfaces_seen_in_too_few_pixels_are_label_3(street_scan):
    scan = street_scan
    minimum = scan.params['min_surface_pixels']
    counts = dict(zip(*np.unique(scan.labels[scan.labels >= 10], return_counts=True), strict=True))
    assert min(counts.values()) >= minimum
    small = np.isin(
        scan.face_labels,
        [
            label
            for label in np.unique(scan.face_labels)
            if label not in counts and label not in scan.clutter_labels and label > 0
        ],
    )
    assert np.all(scan.labels[small & np.isfinite(scan.points[..., 0])] == UNLABELLED_LABEL)


def test_perfect_segmentation_of_a_street_scores_f_and_k_of_one(street_scan):
    labels = street_scan.labels
    values = np.unique(labels[labels >= 10])
    prediction = np.where(labels >= 10, np.searchsorted(values, labels) + 1, 0)
    score = score_segmentation(prediction, labels)
    assert score.f == 1.0 and score.k == 1.0 and score.n_gt == len(values) > 30


# ---------------------------------------------------------------------------------------------
# Depth camera
# ---------------------------------------------------------------------------------------------


def camera_at_wall(distance: float, errors: DepthErrorModel, *, width: int = 160, height: int = 120, seed: int = 0):
    """A camera at the origin looking along +x at a wall ``distance`` metres away."""
    return generate_depth_scan(
        wall_scene(distance), seed=seed, width=width, height=height, sensor_pose=ORIGIN_POSE, errors=errors
    )


@pytest.mark.parametrize('distance', [1.0, 4.0])
def test_depth_noise_grows_as_z_squared(distance):
    errors = DepthErrorModel.exact(disparity_step_px=0.125, axial_noise_coefficient=1.43e-3)
    scan = camera_at_wall(distance, errors)
    residual = scan.points[..., 2] - scan.true_depth
    assert np.isfinite(residual).mean() > 0.99
    assert np.nanstd(residual) == pytest.approx(1.43e-3 * distance**2, rel=0.2)
    assert np.nanmean(residual) == pytest.approx(0.0, abs=0.2 * 1.43e-3 * distance**2)


def test_disparity_is_quantised_in_eighths_of_a_pixel():
    errors = DepthErrorModel()
    scan = generate_depth_scan(seed=1, errors=errors, width=160, height=120)
    z = scan.points[..., 2]
    disparity = errors.focal_px * errors.baseline / z[np.isfinite(z)]
    eighths = disparity * 8
    np.testing.assert_allclose(eighths, np.round(eighths), atol=1e-6)
    # Visible steps: on a floor seen at full resolution the disparity changes by b / h = 0.06 px per
    # row, less than a step, so neighbouring rows often report the same depth; without quantisation never.
    scene = wall_scene(6.0, floor=1.2)
    quantised = generate_depth_scan(
        scene, sensor_pose=ORIGIN_POSE, errors=DepthErrorModel.exact(disparity_step_px=0.125)
    )
    exact = generate_depth_scan(scene, sensor_pose=ORIGIN_POSE, errors=DepthErrorModel.exact())
    floor = quantised.scene.faces[1].label

    def equal_neighbours(depth_scan) -> float:
        on_floor = (depth_scan.labels[1:] == floor) & (depth_scan.labels[:-1] == floor)
        return float(np.mean(depth_scan.points[1:, :, 2][on_floor] == depth_scan.points[:-1, :, 2][on_floor]))

    assert equal_neighbours(quantised) > 0.3
    assert equal_neighbours(exact) == 0.0


def test_depth_points_are_back_projected_through_pixel_centres_in_a_y_down_frame():
    scan = camera_at_wall(3.0, DepthErrorModel.exact(), width=64, height=48)
    fx, fy, cx, cy = scan.intrinsics
    z = scan.points[..., 2]
    np.testing.assert_allclose(z, 3.0, atol=1e-9)
    np.testing.assert_allclose(scan.points[..., 0], (np.arange(64) - cx)[None, :] / fx * z, atol=1e-12)
    np.testing.assert_allclose(scan.points[..., 1], (np.arange(48) - cy)[:, None] / fy * z, atol=1e-12)
    normal, offset = scan.plane_of_label(scan.scene.faces[0].label)
    np.testing.assert_allclose(normal, [0.0, 0.0, -1.0], atol=1e-12)
    assert offset == pytest.approx(-3.0)


def test_depth_distortion_bends_a_flat_wall_more_at_range():
    errors = DepthErrorModel.exact(distortion_coefficient=1e-3)
    near = camera_at_wall(2.0, errors, width=320, height=240)
    far = camera_at_wall(4.0, errors, width=320, height=240)
    spread_near = np.ptp(near.points[..., 2])
    spread_far = np.ptp(far.points[..., 2])
    assert 0.002 < spread_near < 0.012  # a few mm at 2 m
    assert spread_far == pytest.approx(4 * spread_near, rel=0.05)
    assert spread_far > 0.01


def test_projector_shadows_and_depth_edges_drop_out():
    builder = SurfaceSceneBuilder()
    wall = builder.surface('wall')
    builder.add(wall, np.array([(3.0, -5, -5), (3.0, 5, -5), (3.0, 5, 5), (3.0, -5, 5)]))
    builder.new_group()
    board = builder.surface('board')
    builder.add(board, np.array([(1.0, -0.1, -1), (1.0, 0.1, -1), (1.0, 0.1, 1), (1.0, -0.1, 1)]))
    scene = builder.build()
    shadow = generate_depth_scan(
        scene, width=160, height=120, sensor_pose=ORIGIN_POSE, errors=DepthErrorModel.exact(projector_offset=0.075)
    )
    plain = generate_depth_scan(scene, width=160, height=120, sensor_pose=ORIGIN_POSE, errors=DepthErrorModel.exact())
    assert np.isfinite(plain.points[..., 2]).all()
    lost = ~np.isfinite(shadow.points[..., 2])
    on_board = np.flatnonzero((plain.labels == board).any(axis=0))
    # The projector (+x, image right) sees the board shifted left against the wall: the shadow is a
    # band of wall pixels on the board's left in the image (as on a real Kinect v1).
    lost_columns = np.flatnonzero(lost[60])
    assert lost_columns.size > 3 and lost_columns.max() < on_board.min()
    assert np.all(shadow.face_labels[lost] == wall)
    edges = generate_depth_scan(
        scene,
        width=160,
        height=120,
        sensor_pose=ORIGIN_POSE,
        errors=DepthErrorModel.exact(edge_dropout_probability=1.0),
    )
    dropped = ~np.isfinite(edges.points[60, :, 2])
    assert set(np.flatnonzero(dropped)) == {on_board.min() - 1, on_board.min(), on_board.max(), on_board.max() + 1}


def test_depth_range_limits():
    assert not np.isfinite(camera_at_wall(9.0, DepthErrorModel.exact()).points).any()
    assert not np.isfinite(camera_at_wall(0.4, DepthErrorModel.exact()).points).any()


def test_indoor_scene_has_unlabelled_clutter_and_one_label_per_face():
    pose = SensorPose(position=(2.0, 2.8, 1.2), pitch_deg=10.8, yaw_deg=12.0)
    scene = make_indoor_scene(0, sensor_pose=pose)
    room = make_room_scene(0, keep_clear=pose.position[:2], view_yaw_deg=pose.yaw_deg)
    planar = scene.planar_labels()
    np.testing.assert_array_equal(planar, room.labels)
    assert len(scene.clutter_labels) >= 2
    scan = generate_depth_scan(scene, seed=0, sensor_pose=pose)
    returned = np.isfinite(scan.points[..., 2])
    on_clutter = np.isin(scan.face_labels, list(scan.clutter_labels)) & returned
    assert on_clutter.sum() > 1000 and np.all(scan.labels[on_clutter] == CLUTTER_LABEL)
    assert 0.6 < returned.mean() < 0.99


def test_error_model_validation():
    with pytest.raises(ValueError, match='range_sigma'):
        LidarErrorModel(range_sigma=-1.0)
    with pytest.raises(ValueError, match='min_cos'):
        LidarErrorModel(min_cos=0.0)
    with pytest.raises(ValueError, match='quantisation'):
        DepthErrorModel(axial_noise_coefficient=1e-4).disparity_sigma()
    with pytest.raises(ValueError, match='SurfaceScene'):
        generate_lidar_scan(make_room_scene(0))


# ---------------------------------------------------------------------------------------------
# Data sets and ppe eval
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope='module')
def lidar_dataset(tmp_path_factory):
    from ppe_ros.benchmark.dataset import make_dataset

    root = tmp_path_factory.mktemp('lidar_dataset') / 'ds'
    make_dataset(root, kind='lidar', lidar_models=['os1-32'], cols=64, n_train=1, n_test=2)
    return root


def test_lidar_dataset_files_load_with_beam_origins_and_labels(lidar_dataset):
    from ppe_ros.benchmark.dataset import SENSOR_SEED_SPLITS, read_manifest
    from ppe_ros.io import load_scan

    manifest = read_manifest(lidar_dataset)
    assert manifest['kind'] == 'lidar' and manifest['levels'][0]['name'] == 'os1-32'
    seeds = {entry['split']: [] for entry in manifest['scans']}
    for entry in manifest['scans']:
        seeds[entry['split']].append(entry['scene_seed'])
    assert seeds == {
        'train': [SENSOR_SEED_SPLITS['train'][0]],
        'test': [SENSOR_SEED_SPLITS['test'][0], SENSOR_SEED_SPLITS['test'][0] + 1],
    }
    assert SENSOR_SEED_SPLITS['train'][1] <= SENSOR_SEED_SPLITS['test'][0]
    entry = manifest['scans'][1]
    loaded = load_scan(lidar_dataset / entry['file'])
    scan = generate_lidar_scan(seed=entry['scene_seed'], model='os1-32', cols=64)
    np.testing.assert_allclose(loaded.origins, scan.origins, atol=1e-15)
    np.testing.assert_allclose(loaded.points, scan.points, atol=1e-5)  # stored as float32
    assert np.array_equal(np.isnan(loaded.points), np.isnan(scan.points))
    np.testing.assert_array_equal(loaded.labels, np.where(scan.labels >= 10, scan.labels, 0))
    assert loaded.meta['min_plane_label'] == 1
    assert entry['n_planes'] == len(np.unique(scan.labels[scan.labels >= 10])) > 5


def test_depth_dataset_and_bad_parameters(tmp_path):
    from ppe_ros.benchmark.dataset import make_dataset, sensor_scene_seed
    from ppe_ros.io import load_scan

    manifest = make_dataset(tmp_path / 'depth', kind='depth_camera', rows=48, cols=64, n_train=0, n_test=1)
    entry = manifest['scans'][0]
    loaded = load_scan(tmp_path / 'depth' / entry['file'])
    assert loaded.origins is None and loaded.points.shape == (48, 64, 3)
    assert entry['scene_seed'] == 1000 and entry['level'] == 'kinect-v1'
    with pytest.raises(ValueError, match='kind must be one of'):
        make_dataset(tmp_path / 'x', kind='radar')
    with pytest.raises(ValueError, match='rows from the lidar model'):
        make_dataset(tmp_path / 'x', kind='lidar', rows=32)
    with pytest.raises(ValueError, match='leaves the range'):
        make_dataset(tmp_path / 'x', kind='lidar', seed=999, n_train=2, n_test=0)
    with pytest.raises(ValueError, match='lidar models'):
        make_dataset(tmp_path / 'x', kind='lidar', lidar_models=['hdl-64'])
    assert sensor_scene_seed('test', 5, seed=2) == 1007


def test_dataset_command_and_eval_on_a_lidar_dataset(tmp_path, capsys, lidar_dataset):
    from ppe_ros.cli import main

    out = tmp_path / 'made'
    assert (
        main(
            [
                'dataset',
                'make',
                str(out),
                '--kind',
                'depth_camera',
                '--rows',
                '24',
                '--cols',
                '32',
                '--train',
                '0',
                '--test',
                '1',
                '--quiet',
            ]
        )
        == 0
    )
    assert 'depth_camera scans' in capsys.readouterr().out
    assert main(['dataset', 'make', str(tmp_path / 'bad'), '--kind', 'lidar', '--noise', '20', '--quiet']) == 2
    assert '--noise' in capsys.readouterr().err
    report = tmp_path / 'eval.md'
    assert (
        main(['eval', str(lidar_dataset), '--methods', 'ppe', 'msac', '--no-sweep', '--quiet', '--out', str(report)])
        == 0
    )
    printed = capsys.readouterr().out
    assert 'os1-32 (2 scans)' in printed
    text = report.read_text()
    assert '--kind lidar' in text and 'clutter unlabelled' in text


def test_eval_runs_the_sensor_profile_of_a_lidar_dataset_first(tmp_path, capsys, lidar_dataset):
    from ppe_ros import extract_planes
    from ppe_ros.benchmark.dataset import iter_scans
    from ppe_ros.benchmark.methods import make_method
    from ppe_ros.cli import main
    from ppe_ros.commands.eval import DEFAULT_METHODS, default_methods
    from ppe_ros.io import load_scan

    assert default_methods('lidar') == ('ppe-lidar', *DEFAULT_METHODS)
    assert default_methods('depth_camera') == ('ppe-depth-camera', *DEFAULT_METHODS)
    assert default_methods('synpeb') == DEFAULT_METHODS
    entry = next(iter(iter_scans(lidar_dataset, split='test')))
    scan = load_scan(entry.path)
    method = make_method('ppe-lidar')
    assert method.parameters()['sensor'] == 'lidar'
    labels = method.segment(scan.points, scan.origins).labels
    np.testing.assert_array_equal(labels, extract_planes(scan.points, origins=scan.origins, sensor='lidar').labels)
    report = tmp_path / 'eval.md'
    argv = ['eval', str(lidar_dataset), '--no-sweep', '--quiet', '--out', str(report), '--max-scans', '1']
    assert main([*argv, '--methods', 'ppe-lidar', 'ppe']) == 0
    text = report.read_text()
    assert '| ppe-lidar |' in text and '| ppe |' in text and '--methods ppe-lidar ppe' in text
    capsys.readouterr()
    assert main(argv) == 0  # without --methods: the lidar profile first, then the usual ones
    text = report.read_text()
    assert '--methods ppe-lidar ppe msac' in text and '| ppe-lidar |' in text and '| msac |' in text


def test_eval_reuses_a_profile_result_only_while_the_profile_is_unchanged(tmp_path, capsys, monkeypatch, lidar_dataset):
    import dataclasses

    from ppe_ros.cli import main
    from ppe_ros.core import sensor

    raw = tmp_path / 'raw.json'
    argv = ['eval', str(lidar_dataset), '--no-sweep', '--quiet', '--max-scans', '1', '--methods', 'ppe-lidar']
    assert main([*argv, '--out', str(tmp_path / 'a.md'), '--raw', str(raw)]) == 0
    assert main([*argv, '--out', str(tmp_path / 'b.md'), '--reuse', str(raw)]) == 0
    assert 'Results of ppe-lidar were taken from the earlier run' in (tmp_path / 'b.md').read_text()
    changed = dataclasses.replace(sensor.PROFILES['lidar'], surface_tolerance=0.04)  # a default changed since
    monkeypatch.setitem(sensor.PROFILES, 'lidar', changed)
    assert main([*argv, '--out', str(tmp_path / 'c.md'), '--reuse', str(raw)]) == 0
    assert 'taken from the earlier run' not in (tmp_path / 'c.md').read_text()
    capsys.readouterr()


def test_builder_fast_path_accepts_and_rejects_like_validate_polygon():
    from ppe_ros.core.synthetic import _validate_polygon

    rng = np.random.default_rng(0)
    square = np.array([(0.0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
    candidates = [
        square,
        square[::-1],
        square[[0, 2, 1, 3]],
        square + [0, 0, 1e-6] * np.array([[0], [0], [1], [0]]),
        np.array([(0.0, 0, 0), (1, 0, 0), (2, 0, 0)]),
        np.array([(0.0, 0, 0), (1, 0, 0), (np.nan, 1, 0)]),
        np.array([(0.0, 0, 0), (2, 0, 0), (0.5, 0.5, 0), (0, 2, 0)]),
    ]
    candidates += [rng.normal(size=(int(rng.integers(3, 5)), 3)) for _ in range(40)]
    for vertices in candidates:
        try:
            _validate_polygon(vertices, 'x')
            valid = True
        except ValueError:
            valid = False
        builder = SurfaceSceneBuilder()
        label = builder.surface('x')
        if valid:
            builder.add(label, vertices)
        else:
            with pytest.raises(ValueError):
                builder.add(label, vertices)


def test_a_sequence_is_one_world_and_one_sensor_seen_with_new_noise_from_moving_poses():
    from ppe_ros.core.synthetic_real import generate_lidar_sequence

    sweeps = generate_lidar_sequence(2, 3, step=0.25, model='os1-32', cols=128)
    positions = np.array([scan.sensor_pose.position for scan in sweeps])
    np.testing.assert_allclose(np.linalg.norm(np.diff(positions, axis=0), axis=1), 0.25, atol=1e-12)
    assert all(scan.params['beam_range_bias'] == sweeps[0].params['beam_range_bias'] for scan in sweeps)
    assert len({scan.params['noise_seed'] for scan in sweeps}) == 3
    # Same world (scene and surface undulation), new noise: from one pose the undulated ranges agree exactly.
    again = generate_lidar_scan(
        make_street_scene(2), seed=2, model='os1-32', cols=128, sensor_pose=sweeps[1].sensor_pose, noise_seed=77
    )
    np.testing.assert_array_equal(again.undulated_ranges, sweeps[1].undulated_ranges)
    returned = np.isfinite(again.points[..., 0]) & np.isfinite(sweeps[1].points[..., 0])
    assert np.any(again.points[returned] != sweeps[1].points[returned])
    np.testing.assert_array_equal(
        generate_lidar_scan(seed=2, model='os1-32', cols=128).points,
        generate_lidar_sequence(2, 1, model='os1-32', cols=128)[0].points,
    )


def test_cast_surface_rays_validates_its_input():
    scene = wall_scene()
    with pytest.raises(ValueError, match=r'\(N, 3\)'):
        cast_surface_rays(scene, np.zeros((2, 3)), np.ones((3, 3)))
    with pytest.raises(ValueError, match='finite'):
        cast_surface_rays(scene, np.zeros((1, 3)), np.array([[np.nan, 0.0, 1.0]]))
    with pytest.raises(ValueError, match='SurfaceScene'):
        cast_surface_rays(scene.scene, np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0]]))
    distances, labels = cast_surface_rays(scene, np.zeros((2, 3)), np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(distances[0], 10.0)
    assert labels[0] == scene.scene.faces[0].label and np.isnan(distances[1]) and labels[1] == 0


def test_dataset_make_help_names_every_lidar_model(capsys):
    from ppe_ros.cli import main
    from ppe_ros.core.synthetic_real import LIDAR_MODELS

    with pytest.raises(SystemExit) as exit_info:
        main(['dataset', 'make', '--help'])
    assert exit_info.value.code == 0
    text = ' '.join(capsys.readouterr().out.split())  # argparse wraps the help
    listed = text.split('one level per lidar model (')[1].split(';')[0]
    assert [name.strip() for name in listed.split(',')] == list(LIDAR_MODELS)
