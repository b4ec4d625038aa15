"""Metrics of the real-data benchmark (ppe_ros.benchmark.real) on small synthetic cases with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ppe_ros.benchmark.real import (
    CHI2_3_MEDIAN,
    REAL_SCANS,
    SCAN_SPLIT,
    PlaneMatch,
    RangeImageProjector,
    closest_point_jacobian,
    connected_parts,
    count_planes,
    fit_ground_plane,
    ground_cover,
    mahalanobis_squared,
    match_planes,
    motion_difference,
    plane_point_counts,
    profile_with_settings,
    registration_covariance,
    resweep,
    rigid_fit_from_planes,
    share_in_large_planes,
    smooth_surfaces,
    summarize_matches,
    surface_shape,
    touching_pairs,
    transform_planes,
    truth_mahalanobis,
)


def _rotation(axis, angle_deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = math.radians(angle_deg)
    return np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k


def _labels_with_sizes(sizes, shape=(50, 60)):
    flat = np.zeros(shape[0] * shape[1], np.int64)
    start = 0
    for label, size in enumerate(sizes, start=1):
        flat[start : start + size] = label
        start += size
    return flat.reshape(shape)


def test_plane_counts_and_large_share():
    labels = _labels_with_sizes([1200, 300, 25, 19, 5])
    assert plane_point_counts(labels).tolist() == [1200, 300, 25, 19, 5]
    assert count_planes(labels, 20) == 3
    assert count_planes(labels, 100) == 2
    valid = np.ones(labels.shape, bool)
    valid.ravel()[2000:] = False  # 2000 valid pixels, the 1200-pixel plane among them
    assert share_in_large_planes(labels, valid, 1000) == pytest.approx(1200 / 2000)
    assert share_in_large_planes(labels, valid, 1201) == 0.0
    assert math.isnan(share_in_large_planes(labels, np.zeros(labels.shape, bool)))


def _spherical_scene(origin, rows=48, cols=360, max_range=40.0, wall=6.0):
    """Ray-cast a wall x = ``wall`` and the ground z = -1.5 (world frame) from ``origin``; labels 1 = wall, 2 = ground.

    Returns points in the sensor frame (world minus origin), labels, and the beam elevations/azimuths used.
    Column j looks at azimuth -2 pi j / cols (decreasing, as a destaggered Ouster image).
    """
    elevation = np.radians(np.linspace(15.0, -25.0, rows))
    azimuth = -2 * np.pi * np.arange(cols) / cols
    el, az = np.meshgrid(elevation, azimuth, indexing='ij')
    v = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)
    o = np.asarray(origin, float)
    planes = [(np.array([1.0, 0, 0]), wall), (np.array([0, 0, 1.0]), -1.5)]
    best = np.full((rows, cols), np.inf)
    labels = np.zeros((rows, cols), np.int64)
    for label, (n, d) in enumerate(planes, start=1):
        with np.errstate(divide='ignore', invalid='ignore'):
            t = (d - n @ o) / (v @ n)
        hit = (t > 0) & (t < max_range) & (t < best)
        best[hit] = t[hit]
        labels[hit] = label
    points = np.where(np.isfinite(best)[..., None], v * best[..., None], np.nan)
    return points, labels


def test_ground_plane_recovers_the_floor_and_nothing_else():
    points, labels = _spherical_scene([0, 0, 0], wall=1.2)
    ground = fit_ground_plane(points, max_horizontal_distance=25.0, inlier_distance=0.10)
    np.testing.assert_allclose(ground.normal, [0, 0, 1], atol=1e-3)  # the wall's foot (< 10 cm) pulls a little
    assert ground.offset == pytest.approx(-1.5, abs=2e-3)
    horizontal = np.hypot(points[..., 0], points[..., 1])
    with np.errstate(invalid='ignore'):
        near_plane = np.abs(points @ ground.normal - ground.offset) <= 0.1
    assert np.array_equal(ground.mask, near_plane & (horizontal <= 25.0))
    assert np.all(ground.mask[(labels == 2) & (horizontal <= 25.0)])
    # the wall (more points than the ground within 25 m, but vertical) is never chosen
    assert np.count_nonzero(labels == 1) > ground.num_points
    assert np.count_nonzero(ground.mask & (labels == 1)) < 0.02 * ground.num_points


def test_ground_cover_counts_the_fewest_planes():
    ground = np.zeros((10, 10), bool)
    ground[:5] = True  # 50 ground pixels
    labels = np.zeros((10, 10), np.int64)
    labels[0:2] = 1  # 20 ground pixels
    labels[2, :] = 2  # 10
    labels[3, :] = 3  # 10
    labels[4, :5] = 4  # 5
    labels[5:] = 1  # plane 1 also holds 50 non-ground pixels: they do not count
    cover = ground_cover(labels, ground, 0.8)
    assert cover.ground_points == 50
    assert cover.largest_share == pytest.approx(0.4)
    assert cover.planes_for_share == 3  # 20 + 10 + 10 = 40 = 80 %
    assert cover.covered_share == pytest.approx(0.9)
    assert cover.planes_touching == 4
    assert ground_cover(labels, ground, 0.95).planes_for_share is None
    assert ground_cover(labels, ground, 0.4).planes_for_share == 1


def test_connected_parts_splits_by_4_neighbours_and_drops_small_parts():
    labels = np.zeros((8, 10), np.int64)
    labels[0:3, 0:3] = 1  # 9 pixels
    labels[5:8, 5:10] = 1  # 15 pixels, same label, not connected
    labels[3, 3] = 1  # touches the first block only diagonally: its own 1-pixel part
    labels[0:2, 6:10] = 2  # 8 pixels
    parts = connected_parts(labels, min_points=2)
    sizes = plane_point_counts(parts)
    assert sizes.tolist() == [15, 9, 8]  # numbered by decreasing size; the diagonal pixel is dropped
    assert parts[3, 3] == 0
    assert np.all(parts[5:8, 5:10] == 1) and np.all(parts[0:3, 0:3] == 2) and np.all(parts[0:2, 6:10] == 3)
    assert count_planes(connected_parts(labels, min_points=9), 1) == 2


def test_rigid_fit_from_planes_recovers_a_known_motion():
    rng = np.random.default_rng(3)
    rotation = _rotation([0.3, -0.2, 1.0], 7.0)
    translation = np.array([0.23, -0.05, 0.02])
    normals = rng.normal(size=(5, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    offsets = rng.uniform(2, 10, 5)
    normals_b, offsets_b = transform_planes(normals, offsets, rotation, translation)
    fit_r, fit_t = rigid_fit_from_planes(normals, offsets, normals_b, offsets_b)
    np.testing.assert_allclose(fit_r, rotation, atol=1e-12)
    np.testing.assert_allclose(fit_t, translation, atol=1e-12)
    angle, dist = motion_difference(rotation, translation, fit_r, fit_t)
    assert angle < 1e-6 and dist < 1e-9
    with pytest.raises(ValueError, match='span'):
        parallel = np.tile([0.0, 0.0, 1.0], (4, 1))
        rigid_fit_from_planes(parallel, offsets[:4], parallel, offsets[:4] + 1)


def test_transformed_plane_contains_the_transformed_points():
    rotation, translation = _rotation([1, 2, 3], 20.0), np.array([0.5, -1.0, 2.0])
    normal, offset = np.array([[0.0, 0.6, 0.8]]), np.array([3.0])
    point_on_plane = np.array([1.0, 0.0, 3.75])
    moved_n, moved_d = transform_planes(normal, offset, rotation, translation)
    assert moved_n[0] @ (rotation @ point_on_plane + translation) == pytest.approx(moved_d[0])


def test_closest_point_jacobian_matches_finite_differences():
    rotation, translation = _rotation([0, 1, 1], 12.0), np.array([0.3, -0.2, 0.1])

    def moved_closest_point(c):
        d = np.linalg.norm(c)
        n, off = transform_planes((c / d)[None], np.array([d]), rotation, translation)
        return off[0] * n[0]

    c = np.array([1.0, -2.0, 3.0])
    step = 1e-6
    numeric = np.stack(
        [(moved_closest_point(c + step * e) - moved_closest_point(c - step * e)) / (2 * step) for e in np.eye(3)],
        axis=1,
    )
    np.testing.assert_allclose(closest_point_jacobian(c, rotation, translation), numeric, atol=1e-7)


def test_mahalanobis_squared_is_calibrated_for_its_own_covariance():
    cov = np.array([[4e-4, 1e-4, 0], [1e-4, 2e-4, 0], [0, 0, 1e-4]])
    assert mahalanobis_squared(np.array([0, 0, 0.02]), cov) == pytest.approx(4.0)
    rng = np.random.default_rng(0)
    samples = rng.multivariate_normal(np.zeros(3), cov, size=20000)
    median = np.median([mahalanobis_squared(s, cov) for s in samples])
    assert median == pytest.approx(CHI2_3_MEDIAN, rel=0.03)
    assert np.median([mahalanobis_squared(s, cov / 25) for s in samples]) > 20 * CHI2_3_MEDIAN  # overconfident
    assert math.isnan(mahalanobis_squared(np.ones(3), -np.eye(3)))
    assert math.isnan(mahalanobis_squared(np.ones(3), np.full((3, 3), np.nan)))


def test_registration_covariance_matches_sampled_small_motions():
    normal, offset = np.array([0.0, 0.6, 0.8]), 8.0
    sigma_t, sigma_r = 0.01, math.radians(0.05)
    rng = np.random.default_rng(1)
    deltas = []
    for _ in range(4000):
        w, u = rng.normal(0, sigma_r, 3), rng.normal(0, sigma_t, 3)
        moved_n, moved_d = transform_planes(
            normal[None], np.array([offset]), _rotation(w, math.degrees(np.linalg.norm(w))), u
        )
        deltas.append(moved_d[0] * moved_n[0] - offset * normal)
    sampled = np.cov(np.array(deltas).T)
    predicted = registration_covariance(normal, offset, sigma_t, sigma_r)
    np.testing.assert_allclose(sampled, predicted, atol=0.06 * np.abs(predicted).max())
    assert predicted[0, 0] == pytest.approx((offset * sigma_r) ** 2)  # x is in the plane: rotation only


def test_range_image_projector_maps_every_point_to_its_own_pixel():
    points, _ = _spherical_scene([0, 0, 0])
    projector = RangeImageProjector(points)
    valid = np.isfinite(points).all(axis=2).ravel()
    pixels = projector.project(points.reshape(-1, 3)[valid])
    assert np.array_equal(pixels, np.flatnonzero(valid))
    # a point straight up, outside the beams' elevations, lands nowhere
    assert projector.project(np.array([[0.0, 0.0, 5.0]]))[0] == -1


def test_resweep_without_motion_gives_the_sweep_back():
    points, _ = _spherical_scene([0, 0, 0])
    again = resweep(points, None, np.eye(3), np.zeros(3))
    np.testing.assert_array_equal(again, points)  # NaN where the sweep has no return


def test_resweep_sees_the_scene_from_the_moved_sensor():
    """Every return of the resweep is a moved return of A on the same surface, in the pixel of B's grid whose beam
    is nearest to it; the nearest of the returns that share a pixel stays; B's rays see most of what the sensor at
    the new position sees."""
    motion = np.array([0.25, 0.1, 0.0])  # sensor B sits at `motion` in A's (world) frame: x_B = x_A - motion
    points_a, labels_a = _spherical_scene([0, 0, 0])
    points_b = resweep(points_a, None, np.eye(3), -motion)
    truth_b, truth_labels = _spherical_scene(motion)
    valid = np.isfinite(points_b).all(axis=2)
    on_wall = np.abs(points_b[..., 0] + motion[0] - 6.0) < 1e-9
    on_ground = np.abs(points_b[..., 2] + motion[2] + 1.5) < 1e-9
    assert np.all(on_wall[valid] | on_ground[valid])  # moved returns, still on their surfaces
    moved_a = points_a.reshape(-1, 3) - motion
    assert np.isin(points_b[valid].round(9).view('f8,f8,f8'), moved_a.round(9).view('f8,f8,f8')).all()
    projector = RangeImageProjector(points_a)
    pixels = projector.grid_pixels(points_b[valid])
    np.testing.assert_array_equal(pixels, np.flatnonzero(valid.ravel()))
    # the labels B's returns carry are the true labels of the moved sensor where both see a return
    both = valid & np.isfinite(truth_b).all(axis=2)
    label_b = np.where(on_wall, 1, 2)
    assert np.mean(label_b[both] == truth_labels[both]) > 0.99
    assert np.count_nonzero(valid) > 0.8 * np.count_nonzero(np.isfinite(truth_b).all(axis=2))
    assert np.count_nonzero(valid) < np.count_nonzero(labels_a)  # returns between the beams or hidden: dropped


def test_resweep_keeps_the_nearest_return_of_a_pixel_and_adds_range_noise():
    points = np.full((2, 8, 3), np.nan)
    azimuth = -2 * np.pi * np.arange(8) / 8
    for row, elevation in enumerate((0.1, -0.1)):
        points[row] = (
            np.stack(
                [
                    np.cos(elevation) * np.cos(azimuth),
                    np.cos(elevation) * np.sin(azimuth),
                    np.full(8, np.sin(elevation)),
                ],
                -1,
            )
            * (5.0 + np.arange(8))[:, None]
        )
    near = 0.5 * points[0, 3]  # a second return on the ray of pixel (0, 3), nearer
    points_with_near = points.copy()
    points_with_near[1, 7] = near  # it lies in another pixel of A's grid but on the beam of (0, 3)
    out = resweep(points_with_near, None, np.eye(3), np.zeros(3))
    np.testing.assert_allclose(out[0, 3], near)
    assert np.isnan(out[1, 7]).all()
    noisy = resweep(points, None, np.eye(3), np.zeros(3), range_sigma=0.01, seed=3)
    lengths = np.linalg.norm(noisy, axis=2) - np.linalg.norm(points, axis=2)
    assert 0.0 < np.abs(lengths).max() < 0.06
    np.testing.assert_allclose(np.cross(noisy.reshape(-1, 3), points.reshape(-1, 3)), 0.0, atol=1e-12)  # along rays
    np.testing.assert_array_equal(resweep(points, None, np.eye(3), np.zeros(3), range_sigma=0.01, seed=3), noisy)
    with pytest.raises(ValueError, match='organized'):
        resweep(points[0], None, np.eye(3), np.zeros(3))


def _planes_of(points, labels):
    from ppe_ros.core.fitting import fit_labeled_planes

    return fit_labeled_planes(points, labels, min_plane_points=20).planes


def test_match_planes_finds_the_same_planes_after_a_known_motion():
    motion = np.array([0.25, 0.1, 0.0])
    points_a, labels_a = _spherical_scene([0, 0, 0])
    points_b, labels_b = _spherical_scene(motion)  # sensor B sits at `motion` in A's (world) frame
    planes_a, planes_b = _planes_of(points_a, labels_a), _planes_of(points_b, labels_b)
    projector = RangeImageProjector(points_b)
    args = (
        planes_a.labels,
        points_a,
        planes_a.normals,
        planes_a.offsets,
        None,
        planes_b.labels,
        projector,
        planes_b.normals,
        planes_b.offsets,
        None,
    )
    matches = match_planes(*args, np.eye(3), -motion, min_points=100)
    assert len(matches) == 2
    for m in matches:
        assert m.found, m
        assert m.iou > 0.9
        assert m.angle_deg < 1e-6 and m.offset_diff < 1e-6
    # without the motion the wall is 25 cm off: not found again
    unmoved = match_planes(*args, np.eye(3), np.zeros(3), min_points=100)
    wall = [m for m in unmoved if m.label_b > 0 and abs(planes_b.normals[m.label_b - 1][0]) > 0.9]
    assert wall and not wall[0].found and wall[0].offset_diff == pytest.approx(0.25, abs=1e-6)
    # B split into halves: the wall is matched to one half with IoU about 0.5 and is not found again
    split = planes_b.labels.copy()
    split[:, : split.shape[1] // 2][split[:, : split.shape[1] // 2] > 0] += 10
    halves = _planes_of(points_b, split)
    matches = match_planes(
        planes_a.labels,
        points_a,
        planes_a.normals,
        planes_a.offsets,
        None,
        halves.labels,
        projector,
        halves.normals,
        halves.offsets,
        None,
        np.eye(3),
        -motion,
        min_points=100,
    )
    assert all(not m.found and 0.3 < m.iou < 0.7 for m in matches)
    assert summarize_matches(matches).found_share == 0.0
    # A split into halves, B whole: each half lies inside B's plane, but B's plane is twice as large
    halves_a = _planes_of(points_a, np.where(labels_a > 0, labels_a + 10 * (np.arange(labels_a.shape[1]) < 180), 0))
    matches = match_planes(
        halves_a.labels,
        points_a,
        halves_a.normals,
        halves_a.offsets,
        None,
        planes_b.labels,
        projector,
        planes_b.normals,
        planes_b.offsets,
        None,
        np.eye(3),
        -motion,
        min_points=100,
    )
    assert len(matches) == 4 and all(not m.found and 0.3 < m.iou < 0.7 for m in matches)


def test_match_planes_mahalanobis_uses_both_covariances():
    points, labels = _spherical_scene([0, 0, 0])
    planes = _planes_of(points, labels)
    projector = RangeImageProjector(points)
    shifted = planes.offsets + 0.01  # B's planes 1 cm further than A's
    cov = np.tile(np.eye(3) * 1e-4, (planes.num_planes, 1, 1))  # sigma 1 cm per axis in each sweep
    matches = match_planes(
        planes.labels,
        points,
        planes.normals,
        planes.offsets,
        cov,
        planes.labels,
        projector,
        planes.normals,
        shifted,
        cov,
        np.eye(3),
        np.zeros(3),
        min_points=100,
        registration_sigma=(0.01, math.radians(0.1)),
    )
    assert len(matches) == 2
    for m in matches:
        assert m.mahalanobis2 == pytest.approx(0.01**2 / 2e-4)  # delta 1 cm along n, variance 2 (1 cm)^2
        assert m.sigma_d_predicted == pytest.approx(math.sqrt(2e-4))
        # the registration adds (1 cm)^2 along n (its rotation part moves c across n only)
        assert m.mahalanobis2_with_registration == pytest.approx(0.01**2 / 3e-4)
        # A's centroid is 1 cm off B's plane; B's points (A's, unmoved) lie on A's plane
        assert m.gap_at_planes == pytest.approx(0.005)


def test_gap_at_planes_is_not_the_offset_difference_of_a_plane_turned_about_its_centroid():
    points, labels = _spherical_scene([0, 0, 0])
    planes = _planes_of(points, labels)
    projector = RangeImageProjector(points)
    turn = math.radians(1.0)
    normals_b, offsets_b = planes.normals.copy(), planes.offsets.copy()
    for j in range(planes.num_planes):
        centroid = points[planes.labels == j + 1].mean(axis=0)
        n = planes.normals[j]
        side = np.cross(n, [0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.cross(n, [1.0, 0.0, 0.0])
        side /= np.linalg.norm(side)
        normals_b[j] = math.cos(turn) * n + math.sin(turn) * side
        offsets_b[j] = normals_b[j] @ centroid  # B's plane passes through A's centroid
    matches = match_planes(
        planes.labels, points, planes.normals, planes.offsets, None,
        planes.labels, projector, normals_b, offsets_b, None,
        np.eye(3), np.zeros(3), min_points=100,
    )  # fmt: skip
    assert len(matches) == 2
    for m in matches:
        assert m.gap_at_planes < 1e-6 < m.offset_diff
        assert m.angle_deg == pytest.approx(1.0)


def test_summary_medians_count_unmatched_planes_as_iou_zero():
    def match(iou, found, label_b=1, md2=1.0):
        return PlaneMatch(1, label_b, 1000, 1000, iou, 0.1, 0.01, md2, 0.01, found)

    summary = summarize_matches(
        [match(0.9, True), match(0.8, True, md2=5.0), match(0.0, False, label_b=0, md2=math.nan)]
    )
    assert summary.planes == 3 and summary.found == 2 and summary.found_share == pytest.approx(2 / 3)
    assert summary.median_iou == pytest.approx(0.8)
    assert summary.pairs == 2 and summary.median_mahalanobis2 == pytest.approx(3.0)


def test_summary_counts_why_planes_were_not_found_again():
    def match(iou, angle, offset, label_b=1):
        found = iou >= 0.7 and angle < 2.0 and offset < 0.05
        return PlaneMatch(1, label_b, 1000, 1000, iou, angle, offset, 1.0, 0.01, found)

    summary = summarize_matches(
        [
            match(0.9, 0.1, 0.01),  # found
            match(0.6, 0.1, 0.01),  # IoU
            match(0.8, 2.5, 0.01),  # angle
            match(0.5, 3.0, 0.20),  # all three
            match(0.0, math.nan, math.nan, label_b=0),  # no match: all three
            match(0.8, 0.1, 0.05),  # offset at the limit
        ]
    )
    assert summary.found == 1
    assert (summary.missed_iou, summary.missed_angle, summary.missed_offset) == (3, 3, 3)


def test_every_real_scan_has_a_split():
    assert {scan.name for scan in REAL_SCANS} == set(SCAN_SPLIT)
    assert set(SCAN_SPLIT.values()) == {'training', 'reported'}
    assert [s.name for s in REAL_SCANS if s.split == 'training'] == [
        'OS-0-128 1491',
        'OS-2-128 1259',
        'OS-2-32 5424',
        'OS-1-32 638',
        'ICL-NUIM 0',
    ]


def _benchmark_module(name: str):
    """The script benchmarks/<name>.py as a module."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / 'benchmarks' / f'{name}.py'
    spec = importlib.util.spec_from_file_location(f'{name}_under_test', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_bench_real_ppe_settings_and_bad_arguments(capsys):
    bench = _benchmark_module('bench_real')
    kwargs, _ = bench.ppe_settings('none', False, 'lidar')
    assert kwargs == {'max_error_increment': 0.01, 'max_neighbor_distance': math.inf, 'min_plane_points': 20}
    kwargs, _ = bench.ppe_settings('none', True, 'depth_camera')
    assert kwargs == {'max_error_increment': 0.0484, 'max_neighbor_distance': 0.18, 'min_plane_points': 20}
    assert bench.ppe_settings('auto', False, 'depth_camera')[0] == {'sensor': 'depth_camera'}
    assert bench.ppe_settings('lidar', False, 'depth_camera')[0]['sensor'] == 'lidar'
    assert bench.main(['--methods', 'ppe,nosuch']) == 2
    assert 'nosuch' in capsys.readouterr().err
    assert bench.main(['--paper', '--sensor', 'lidar']) == 2
    assert bench.main(['--scans', 'no-such-scan', '--data', '/nonexistent']) == 2
    if not bench.has_sensor_argument():
        assert bench.main(['--sensor', 'auto']) == 2
        assert 'no sensor argument' in capsys.readouterr().err


def test_bench_real_set_changes_the_profile_of_each_scan_kind(capsys):
    import dataclasses

    from ppe_ros.core.sensor import PROFILES

    bench = _benchmark_module('bench_real')
    kwargs, label = bench.ppe_settings('auto', False, 'lidar', ['surface_tolerance=0.065'])
    assert kwargs == {'sensor': dataclasses.replace(PROFILES['lidar'], surface_tolerance=0.065)}
    assert label == 'PPE sensor=lidar (surface_tolerance=0.065)'
    kwargs, _ = bench.ppe_settings('auto', False, 'depth_camera', ['min_plane_points=150'])
    assert kwargs['sensor'] == dataclasses.replace(PROFILES['depth_camera'], min_plane_points=150)
    capsys.readouterr()
    for argv, message in (
        (['--set', 'surface_tolerance=0.065'], 'give --sensor auto'),  # --sensor none: no profile to change
        (['--paper', '--set', 'surface_tolerance=0.065'], 'give --sensor auto'),
        (['--sensor', 'auto', '--set', 'no_such_field=1'], 'no_such_field'),
        (['--sensor', 'lidar', '--set', 'surface_tolerance'], 'name=value'),
    ):
        assert bench.main([*argv, '--data', '/nonexistent']) == 2, argv
        assert message in capsys.readouterr().err, argv


def test_bench_real_png_names_are_short_with_a_changed_profile(tmp_path):
    bench = _benchmark_module('bench_real')
    kwargs, _ = bench.ppe_settings('auto', False, 'lidar', ['min_plane_points=20', 'surface_tolerance=0.065'])
    tag = bench.png_tag('ppe', kwargs, False, ['min_plane_points=20', 'surface_tolerance=0.065'])
    path = bench.png_path(tmp_path, 'OS-0-128 1491', tag)
    assert path.name == 'OS_0_128_1491_ppe_lidar_min_plane_points_20_surface_tolerance_0_065.png'
    assert bench.png_tag('ppe', {'sensor': 'lidar'}, False) == 'ppe_lidar'
    assert bench.png_tag('ppe', {'max_error_increment': 0.0484}, True) == 'ppe_paper'
    assert bench.png_tag('ppe', {'max_error_increment': 0.01}, False) == 'ppe_node'
    assert bench.png_tag('ransac', {}, False) == 'ransac'


def test_bench_sensor_scans_makes_one_lidar_table_per_beam_layout(capsys):
    bench = _benchmark_module('bench_sensor_scans')
    with pytest.raises(SystemExit):
        bench.main(['--lidar-models', 'no-such-lidar'])
    capsys.readouterr()
    argv = ['--kinds', 'lidar', '--lidar-models', 'vlp16', 'hdl32', '--seeds', '0', '--no-ransac', '--no-peac']
    assert bench.main(argv) == 0
    out = capsys.readouterr().out
    assert '### lidar vlp16 (1 scans)' in out and '### lidar hdl32 (1 scans)' in out
    rows = [line for line in out.splitlines() if line.startswith('| PPE sensor=lidar |')]
    assert len(rows) == 2
    for row in rows:
        f, k = (float(cell.strip().rstrip(' %')) for cell in row.split('|')[2:4])
        assert 0.0 < f <= 100.0 and 0.0 < k <= 100.0


def test_bench_resweep_bad_arguments_and_a_training_sweep(capsys):
    bench = _benchmark_module('bench_resweep')
    assert bench.main(['--scans', 'no-such-scan']) == 2
    assert 'no-such-scan' in capsys.readouterr().err
    assert bench._default_scans() == ['OS-0-128 1491', 'OS-2-128 1259', 'OS-2-32 5424', 'OS-1-32 638']
    if not bench.SHARED.is_dir():
        pytest.skip(f'the shared data folder {bench.SHARED} is not here (a fresh clone)')
    assert bench.main(['--scans', 'OS-2-32 5424']) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith('| OS-2-32 5424 |')]
    assert len(rows) == len(bench.MOTIONS)
    for row in rows:
        found, planes = (int(x) for x in row.split('|')[4].split('/'))
        assert planes > 0 and 0 <= found <= planes


def test_bench_surface_shape_finds_the_kinect_frames_curved_surface(capsys):
    bench = _benchmark_module('bench_surface_shape')
    assert bench.main(['--scans', 'no-such-scan']) == 2
    assert 'no-such-scan' in capsys.readouterr().err
    if not bench.SHARED.is_dir():
        pytest.skip(f'the shared data folder {bench.SHARED} is not here (a fresh clone)')
    assert bench.main(['--scans', 'Kinect']) == 0
    rows = [line.split('|')[1:-1] for line in capsys.readouterr().out.splitlines() if line.startswith('| Kinect')]
    groups = [row for row in rows if '+' in row[1]]
    # the surface left of the floor is one smooth surface that the depth camera profile cuts into flat strips:
    # a cylinder of radius about 1.4 m, its strips' normals tens of degrees apart
    assert len(groups) == 1
    _, members, _, plane_rms, quadric_rms, radii, angle = groups[0]
    assert len(members.split('+')) >= 3
    assert float(plane_rms) > 4 * float(quadric_rms)
    assert 1.0 < float(radii.split(',')[0]) < 2.5
    assert float(angle) > 20.0


def test_profile_with_settings_changes_the_named_fields_only():
    import dataclasses

    from ppe_ros.core.sensor import PROFILES

    variant = profile_with_settings('lidar', ['surface_tolerance=0.065', 'flatness_length=null', 'seed_shapes="all"'])
    assert variant == dataclasses.replace(
        PROFILES['lidar'], surface_tolerance=0.065, flatness_length=None, seed_shapes='all'
    )
    assert profile_with_settings('depth_camera') == PROFILES['depth_camera']
    assert profile_with_settings('depth_camera', ['noise_scale_bounds=[0.2, 3]']).noise_scale_bounds == (0.2, 3)
    for bad, message in (
        (['no_such_field=1'], 'field of SensorProfile'),
        (['surface_tolerance'], 'name=value'),
        (['surface_tolerance=abc'], 'must be JSON'),
    ):
        with pytest.raises(ValueError, match=message):
            profile_with_settings('lidar', bad)
    with pytest.raises(ValueError, match='sensor must be one of'):
        profile_with_settings('sonar', [])


def test_truth_mahalanobis_against_known_planes():
    """Plane 1 lies on surface 10 with its closest point 2 sigma off along the normal: Mahalanobis² 4; plane 2
    is exact (0); plane 3 is too small, plane 4 straddles two surfaces half and half: both skipped."""
    labels = np.zeros((40, 100), np.int64)
    truth = np.zeros((40, 100), np.int64)
    labels[:20, :60], truth[:20, :] = 1, 10  # 1200 points, all on surface 10
    labels[20:40, :60], truth[20:40, :] = 2, 11
    labels[:5, 60:70] = 3  # 50 points
    labels[10:30, 60:100] = 4  # 800 points, half on surface 10 and half on 11
    true = {10: (np.array([0.0, 0.0, 1.0]), -2.0), 11: (np.array([1.0, 0.0, 0.0]), -5.0)}
    sigma = 0.01
    normals = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    offsets = np.array([-2.0 + 2 * sigma, -5.0, -1.0, -1.0])
    covariances = np.repeat((sigma**2 * np.eye(3))[None], 4, axis=0)
    values = truth_mahalanobis(labels, offsets, normals, covariances, truth, true.__getitem__, min_points=500)
    np.testing.assert_allclose(values, [4.0, 0.0], atol=1e-9)
    # the sign of a plane's (normal, offset) does not matter: d n is the same point
    flipped = truth_mahalanobis(labels, -offsets, -normals, covariances, truth, true.__getitem__, min_points=500)
    np.testing.assert_allclose(flipped, values, atol=1e-9)
    with pytest.raises(ValueError, match='one shape'):
        truth_mahalanobis(labels[:10], offsets, normals, covariances, truth, true.__getitem__)


def test_peac_driver_protocol(tmp_path, monkeypatch):
    """The PEAC adapter writes the grid as documented, reads the driver's labels and its reported time, and
    names why PEAC is skipped without a usable PEAC_BIN."""
    import sys

    bench = _benchmark_module('bench_real')
    monkeypatch.delenv('PEAC_BIN', raising=False)
    assert bench.peac_binary()[0] is None and 'set PEAC_BIN' in bench.peac_binary()[1]
    not_executable = tmp_path / 'plain.txt'
    not_executable.write_text('')
    monkeypatch.setenv('PEAC_BIN', str(not_executable))
    assert bench.peac_binary()[0] is None and 'not an executable file' in bench.peac_binary()[1]
    # a fake driver: label 1 where z > 1 m, 2 elsewhere, 0 without a point
    driver = tmp_path / 'driver.py'
    driver.write_text(
        f'#!{sys.executable}\n'
        'import sys, numpy as np\n'
        'head = np.fromfile(sys.argv[1], "<i4", count=2)\n'
        'xyz = np.fromfile(sys.argv[1], "<f8", offset=8).reshape(head[0], head[1], 3)\n'
        'labels = np.where(xyz[..., 2] > 1.0, 1, 2).astype("<i4")\n'
        'labels[np.isnan(xyz).any(axis=2)] = 0\n'
        'labels.tofile(sys.argv[2])\n'
        'print("seconds 0.125")\n'
    )
    driver.chmod(0o755)
    monkeypatch.setenv('PEAC_BIN', str(driver))
    binary, note = bench.peac_binary()
    assert binary == str(driver) and note == ''
    points = np.ones((3, 4, 3))
    points[0, :, 2] = 2.0
    points[2, 3] = np.nan
    labels, seconds = bench.run_peac(binary, points, {'minSupport': 100, 'depthAlpha': 0.004})
    expected = np.full((3, 4), 2)
    expected[0] = 1
    expected[2, 3] = 0
    np.testing.assert_array_equal(labels, expected)
    assert seconds == 0.125
    failing = tmp_path / 'failing.py'
    failing.write_text(f'#!{sys.executable}\nimport sys\nsys.exit("no luck")\n')
    failing.chmod(0o755)
    with pytest.raises(RuntimeError, match='no luck'):
        bench.run_peac(str(failing), points, {})


# ------------------------------------------------------------------------------------------ surface shape


def _cylinder_wall_and_floor(radius=1.4, arc_deg=40.0, rows=60, cols=90, noise=0.0, seed=0):
    """An organized grid: the left 2/3 of the columns a vertical cylinder arc (axis z, 1.2 m tall) labelled
    1, 2, 3 in three bands of columns; the right 1/3 a flat floor patch (z = 0) labelled 4 that touches
    band 3 along one column."""
    rng = np.random.default_rng(seed)
    points = np.zeros((rows, cols, 3))
    labels = np.zeros((rows, cols), np.int32)
    wall = 2 * cols // 3
    angles = np.radians(np.linspace(-arc_deg / 2, arc_deg / 2, wall))
    heights = np.linspace(0.05, 1.25, rows)
    for j, a in enumerate(angles):
        points[:, j] = np.stack([radius * np.cos(a) * np.ones(rows), radius * np.sin(a) * np.ones(rows), heights], 1)
        labels[:, j] = 1 + 3 * j // wall
    x = np.linspace(radius - 1.2, radius - 0.05, rows)
    y = np.linspace(points[0, wall - 1, 1], points[0, wall - 1, 1] + 1.0, cols - wall)
    points[:, wall:] = np.stack([*np.meshgrid(x, y, indexing='ij'), np.zeros((rows, cols - wall))], -1)
    labels[:, wall:] = 4
    points += rng.normal(0.0, noise, points.shape)
    return points, labels


def test_surface_shape_of_a_noisy_plane_is_flat():
    rng = np.random.default_rng(3)
    u, v = rng.uniform(-2, 2, (2, 5000))
    normal = np.array([0.2, -0.3, 0.93]) / np.linalg.norm([0.2, -0.3, 0.93])
    e1 = np.cross(normal, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    points = np.outer(u, e1) + np.outer(v, e2) + np.outer(rng.normal(0, 0.004, 5000), normal) + [1, 2, 3]
    shape = surface_shape(points)
    assert shape.points == 5000
    assert shape.plane_rms == pytest.approx(0.004, rel=0.05)
    assert shape.quadric_rms == pytest.approx(shape.plane_rms, rel=0.01)
    assert min(shape.radii) > 100.0


def test_surface_shape_finds_the_radius_of_a_cylinder():
    points, labels = _cylinder_wall_and_floor(radius=1.4)
    wall = points[labels < 4]
    shape = surface_shape(wall)
    assert shape.radii[0] == pytest.approx(1.4, rel=0.05)
    assert shape.radii[1] > 1000.0
    # a 40 deg arc of radius 1.4 m: sagitta 8.4 cm, far from flat; the quadric follows it within a millimetre
    assert shape.plane_rms > 0.02
    assert shape.quadric_rms < 0.001


def test_surface_shape_refuses_too_few_points():
    with pytest.raises(ValueError, match='at least 6 points'):
        surface_shape(np.zeros((5, 3)))


def test_touching_pairs_counts_four_neighbour_pixel_pairs():
    labels = np.array([[1, 1, 2], [1, 0, 2], [3, 3, 2]])
    assert touching_pairs(labels) == {(1, 2): 1, (1, 3): 1, (2, 3): 1}
    assert touching_pairs(np.array([[1, 2], [2, 2]])) == {(1, 2): 2}
    assert touching_pairs(np.array([[1, 2], [2, 2]]), min_pairs=3) == {}


def test_smooth_surfaces_joins_the_strips_of_a_cylinder_but_not_the_floor():
    points, labels = _cylinder_wall_and_floor(noise=0.002)
    groups = smooth_surfaces(points, labels, min_points=100, max_quadric_rms=0.01, min_touching=10)
    assert [members for members, _ in groups] == [[1, 2, 3], [4]]
    wall = groups[0][1]
    assert wall.plane_rms > 0.02 and wall.quadric_rms < 0.003
    assert wall.radii[0] == pytest.approx(1.4, rel=0.1)


def test_smooth_surfaces_keeps_strips_apart_below_the_noise_or_without_contact():
    points, labels = _cylinder_wall_and_floor(noise=0.002)
    groups = smooth_surfaces(points, labels, min_points=100, max_quadric_rms=0.001, min_touching=10)
    assert sorted(members for members, _ in groups) == [[1], [2], [3], [4]]
    # strips 1 and 3 do not touch: without strip 2 (too small to count) nothing joins
    groups = smooth_surfaces(points, np.where(labels == 2, 0, labels), min_points=100, min_touching=10)
    assert sorted(members for members, _ in groups) == [[1], [3], [4]]
