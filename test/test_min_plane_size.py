"""The smallest plane of a sensor profile on grids of other ray spacings (SensorProfile.min_plane_points_for)
and the ray spacing it is measured from (ppe_ros.core.scan.ray_spacing_deg)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ppe_ros import extract_planes
from ppe_ros.core.scan import MIN_SPACING_PAIRS, ray_spacing_deg
from ppe_ros.core.sensor import MIN_PLANE_POINTS_FLOOR, OS1_128_RAY_SPACING_DEG, PROFILES


def spherical_grid(rows: int, columns: int, azimuth_step: float, elevation_step: float):
    """Unit ray directions (rows, columns, 3) of a sweep whose beams are elevation_step degrees apart around
    the horizon and whose columns are azimuth_step degrees apart."""
    elevation = np.radians((np.arange(rows) - (rows - 1) / 2) * -elevation_step)[:, None]
    azimuth = np.radians(-azimuth_step * np.arange(columns))[None, :]
    x, y, z = np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def slow_spacing(points: np.ndarray, origins: np.ndarray, step: int) -> tuple[float, float]:
    """ray_spacing_deg by its definition: over the pixels at every step-th row and column, the median of the
    angles (arccos of the normalised dot product) to the right and lower neighbours whose rays are valid."""
    height, width = points.shape[:2]
    rays = points - origins
    angles = ([], [])
    for i in range(0, height - 1, step):
        for j in range(0, width - 1, step):
            for direction, (di, dj) in enumerate(((0, 1), (1, 0))):
                a, b = rays[i, j], rays[i + di, j + dj]
                valid = np.all(np.isfinite(a)) and np.all(np.isfinite(b))
                if valid and np.linalg.norm(a) > 0 and np.linalg.norm(b) > 0:
                    cosine = a @ b / (np.linalg.norm(a) * np.linalg.norm(b))
                    angles[direction].append(math.degrees(math.acos(min(1.0, max(-1.0, cosine)))))
    return float(np.median(angles[0])), float(np.median(angles[1]))


def test_ray_spacing_equals_a_slow_reference_with_gaps_and_per_ray_starts():
    rng = np.random.default_rng(3)
    directions = spherical_grid(40, 300, 0.7, 1.3)
    origins = rng.normal(0.0, 0.02, directions.shape)
    points = origins + rng.uniform(2.0, 30.0, directions.shape[:2])[..., None] * directions
    points[rng.random(directions.shape[:2]) < 0.25] = np.nan
    step = max(1, math.ceil(math.sqrt(points.shape[0] * points.shape[1] / 8192)))
    np.testing.assert_allclose(ray_spacing_deg(points, origins), slow_spacing(points, origins, step), rtol=1e-6)
    # one start for every ray: the same as that start repeated
    start = np.array([0.1, -0.2, 0.3])
    np.testing.assert_allclose(
        ray_spacing_deg(points, start), ray_spacing_deg(points, np.broadcast_to(start, points.shape)), rtol=1e-12
    )


def test_ray_spacing_of_a_sweep_is_its_azimuth_step_and_beam_spacing():
    points = 10.0 * spherical_grid(16, 720, 0.5, 2.0)
    along_rows, along_columns = ray_spacing_deg(points)
    # along a row, rays 0.5 deg apart in azimuth are 0.5 cos(elevation) deg apart: the beams at +-15 deg
    # make it up to 3.4 % shorter, the median beam about 1 %
    assert 0.5 * math.cos(math.radians(15.0)) < along_rows < 0.5
    assert along_columns == pytest.approx(2.0, rel=1e-9)
    # a transposed sweep (one column per beam) swaps them
    assert ray_spacing_deg(np.ascontiguousarray(points.transpose(1, 0, 2)))[::-1] == pytest.approx(
        (along_rows, along_columns), rel=1e-12
    )


def test_ray_spacing_is_nan_without_enough_valid_neighbours_and_checks_its_input():
    points = 5.0 * spherical_grid(8, 64, 1.0, 1.0)
    points[:, ::2] = np.nan  # no two valid neighbours along a row; the columns keep 31 x 7 pairs
    along_rows, along_columns = ray_spacing_deg(points)
    assert math.isnan(along_rows)
    assert along_columns == pytest.approx(1.0, rel=1e-9)
    assert MIN_SPACING_PAIRS > 1
    assert all(math.isnan(x) for x in ray_spacing_deg(np.full((4, 4, 3), np.nan)))
    with pytest.raises(ValueError, match='organized'):
        ray_spacing_deg(np.zeros((10, 3)))
    with pytest.raises(ValueError, match='origins'):
        ray_spacing_deg(points, np.zeros(2))


@pytest.mark.parametrize(
    ('azimuth_step', 'elevation_step', 'expected'),
    [
        (0.3456, 0.34, 40),  # the reference spacing: the profile's own count
        (0.3456, 0.68, 20),  # a 32-beam sensor with the same field of view: half the rays on a surface
        (0.6912, 0.68, 10),  # a quarter
        (1.4, 2.0, MIN_PLANE_POINTS_FLOOR),  # coarser still: never fewer than the floor
        (0.1, 0.1, 40),  # a finer grid keeps the count
    ],
)
def test_the_lidar_profiles_smallest_plane_covers_a_fixed_solid_angle(azimuth_step, elevation_step, expected):
    profile = PROFILES['lidar']
    assert profile.min_plane_points == 40 and profile.reference_ray_spacing_deg == OS1_128_RAY_SPACING_DEG
    points = 8.0 * spherical_grid(16, 400, azimuth_step, elevation_step)
    assert profile.min_plane_points_for(points, np.zeros(3)) == expected
    assert dataclasses.replace(profile, reference_ray_spacing_deg=None).min_plane_points_for(points) == 40
    small = dataclasses.replace(profile, min_plane_points=4)  # a count below the floor is never raised
    assert small.min_plane_points_for(points) == 4


def test_a_scan_without_a_measurable_spacing_keeps_the_profiles_count():
    profile = PROFILES['lidar']
    assert profile.min_plane_points_for(np.full((30, 40, 3), np.nan)) == profile.min_plane_points
    assert profile.min_plane_points_for(np.zeros((100, 3))) == profile.min_plane_points  # not organized
    coarse = 8.0 * spherical_grid(16, 400, 1.4, 2.0)
    assert profile.min_plane_points_for(coarse, np.zeros((2, 3))) == profile.min_plane_points  # bad origins
    # the depth camera profile keeps its count on every image (docs/algorithm.md)
    depth = PROFILES['depth_camera']
    assert depth.reference_ray_spacing_deg is None
    assert depth.min_plane_points_for(coarse) == depth.min_plane_points == 100
    with pytest.raises(ValueError, match='reference_ray_spacing_deg'):
        dataclasses.replace(profile, reference_ray_spacing_deg=(0.1, 0.0))
    with pytest.raises(ValueError, match='reference_ray_spacing_deg'):
        dataclasses.replace(profile, reference_ray_spacing_deg=(0.1,))


def test_extract_planes_asks_a_coarser_sweep_for_fewer_rays_unless_told_otherwise():
    from ppe_ros.core.synthetic_real import generate_lidar_scan

    sweep = generate_lidar_scan(seed=2, model='os1-32')  # 32 beams, 1024 columns: twice the beam spacing
    profile = PROFILES['lidar']
    count = profile.min_plane_points_for(sweep.points, sweep.origins)
    assert MIN_PLANE_POINTS_FLOOR < count < profile.min_plane_points
    default = extract_planes(sweep.points, origins=sweep.origins, sensor='lidar')
    given = extract_planes(sweep.points, origins=sweep.origins, sensor='lidar', min_plane_points=count)
    np.testing.assert_array_equal(default.labels, given.labels)
    assert default.point_counts.min() >= count
    assert np.any(default.point_counts < profile.min_plane_points)  # surfaces the count of the finer grid lost
    explicit = extract_planes(sweep.points, origins=sweep.origins, sensor='lidar', min_plane_points=40)
    assert explicit.point_counts.min() >= 40
    assert explicit.num_planes < default.num_planes
