"""The ray model (core/scan.py) against a plain numpy formulation of the same definitions."""

from __future__ import annotations

import numpy as np
import pytest

from ppe_ros.core.ppe.seeds import _edge_masks
from ppe_ros.core.scan import make_ray_scan
from ppe_ros.core.sensor import PROFILES, NoiseModel, SensorProfile, estimate_noise_scale


def _numpy_ray_model(points, origins):
    """Rays from their definitions: r = |p - s|, valid = finite and r > 0, center = mean valid start,
    endpoints relative to the center (0 when invalid), directions (p - s) / r (0 when invalid)."""
    pts = np.asarray(points, float).reshape(-1, 3)
    if origins is None:
        starts = np.zeros_like(pts)
    else:
        starts = np.broadcast_to(np.asarray(origins, float), np.asarray(points).shape).reshape(-1, 3).copy()
    delta = pts - starts
    with np.errstate(invalid='ignore'):
        ranges = np.sqrt(np.einsum('ij,ij->i', delta, delta))
        valid = np.isfinite(ranges) & (ranges > 0.0)
    center = starts[valid].mean(axis=0) if valid.any() else np.zeros(3)
    endpoints = np.where(valid[:, None], pts - center, 0.0)
    directions = np.zeros_like(delta)
    directions[valid] = delta[valid] / ranges[valid, None]
    return endpoints, directions, np.where(valid, ranges, np.nan), valid, center


def _random_scan(rng, height, width):
    points = rng.normal(0.0, 5.0, (height, width, 3))
    points[rng.random((height, width)) < 0.1] = np.nan
    points[rng.random((height, width)) < 0.02, 1] = np.inf
    return points


@pytest.mark.parametrize(
    'origin_kind, height, width',
    [('none', 37, 53), ('point', 37, 53), ('point', 128, 1024), ('per_ray', 37, 53), ('per_ray', 128, 1024)],
)
def test_ray_model_equals_its_numpy_definition(origin_kind, height, width):
    """Also the mean start of an OS-1-128-sized grid of one start or of per-ray starts (numpy adds the valid
    rows in order, which the kernel does without copying them)."""
    rng = np.random.default_rng(3)
    points = _random_scan(rng, height, width)
    origins = {
        'none': None,
        'point': np.array([0.3, -0.1, 1.2]),
        'per_ray': rng.normal(0.0, 0.05, points.shape) + np.array([0.01, -0.02, 0.036]),
    }[origin_kind]
    if origins is not None:
        # a zero-length ray (endpoint at its start) is invalid
        start = origins if origins.ndim == 1 else origins[4, 5]
        points[4, 5] = start
    scan = make_ray_scan(points, origins)
    endpoints, directions, ranges, valid, center = _numpy_ray_model(points, origins)
    np.testing.assert_array_equal(scan.valid, valid)
    np.testing.assert_array_equal(scan.center, center)
    np.testing.assert_array_equal(scan.endpoints, endpoints)
    np.testing.assert_array_equal(scan.directions, directions)
    np.testing.assert_array_equal(scan.ranges, ranges)
    if origins is not None:
        assert not scan.valid[4 * width + 5]


_NOISE_MODELS = [
    NoiseModel(constant=0.02, proportional=0.001),  # the lidar's
    NoiseModel(constant=0.0274),
    NoiseModel(proportional=0.002, minimum=0.03),  # the floor where it is larger
    NoiseModel(constant=1e-5),
    NoiseModel(constant=0.001, depth_quadratic=1.43e-3),  # Kinect v1, optical axis z
    NoiseModel(constant=0.001, proportional=0.001, depth_quadratic=5e-3, optical_axis=(0.0, -2.0, 0.0)),
    NoiseModel(depth_quadratic=1e-3, optical_axis=(1.0, 0.0, 0.0), minimum=2e-3),
]


@pytest.mark.parametrize('noise', _NOISE_MODELS)
def test_ray_sigmas_and_scaling_equal_the_noise_model_and_numpy(noise):
    """The one-pass kernel gives NoiseModel.sigmas' values and the numpy scaling bit for bit (an optical
    axis along x, y or z: its dot product has one term), NaN sigmas and zero directions on invalid rays."""
    rng = np.random.default_rng(4)
    scan = make_ray_scan(_random_scan(rng, 37, 53), np.array([0.3, -0.1, 1.2]))
    expected = np.full(scan.size, np.nan)
    expected[scan.valid] = noise.sigmas(scan.ranges[scan.valid], scan.directions[scan.valid])
    scaled = np.empty_like(scan.directions)
    sigmas = noise.ray_sigmas(scan.ranges, scan.directions, scan.valid, scaled_directions=scaled)
    np.testing.assert_array_equal(sigmas, expected)
    np.testing.assert_array_equal(scaled, scan.directions * np.where(scan.valid, expected, 0.0)[:, None])
    np.testing.assert_array_equal(noise.ray_sigmas(scan.ranges, scan.directions, scan.valid), expected)
    assert np.isnan(sigmas[~scan.valid]).all() and not np.any(scaled[~scan.valid])


def test_ray_sigmas_with_an_oblique_optical_axis_and_grazing_rays():
    """An oblique axis (three terms in the dot product: the order may differ from numpy's matmul by an
    ulp) and rays at 90 deg to the axis (the range's noise as depth) match NoiseModel.sigmas."""
    noise = NoiseModel(constant=0.001, depth_quadratic=1.43e-3, optical_axis=(0.3, -0.4, 0.8))
    rng = np.random.default_rng(5)
    directions = rng.normal(size=(500, 3))
    axis = np.asarray(noise.optical_axis) / np.linalg.norm(noise.optical_axis)
    directions[:100] -= np.outer(directions[:100] @ axis, axis)  # perpendicular to the axis
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    ranges = rng.uniform(0.2, 9.0, 500)
    valid = np.ones(500, bool)
    np.testing.assert_allclose(
        noise.ray_sigmas(ranges, directions, valid), noise.sigmas(ranges, directions), rtol=1e-14
    )
    with pytest.raises(ValueError, match='directions'):
        noise.ray_sigmas(ranges, directions[:, :2], valid)


def _reference_noise_scale(noise, points, origins):
    """The noise scale of SensorProfile.noise_for from its numpy definition: ranges |p - s|, directions, the
    model's sigmas of the valid rays (finite, length > 0), estimate_noise_scale."""
    rays = points - (np.zeros(3) if origins is None else origins)
    with np.errstate(invalid='ignore', divide='ignore'):
        ranges = np.linalg.norm(rays, axis=-1)
        directions = rays / np.where(ranges > 0, ranges, np.nan)[..., None]
    flat_r, flat_v = ranges.reshape(-1), directions.reshape(-1, 3)
    sigmas = np.full(flat_r.shape, np.nan)
    valid = np.isfinite(flat_r) & (flat_r > 0) & np.all(np.isfinite(flat_v), axis=1)
    sigmas[valid] = noise.sigmas(flat_r[valid], flat_v[valid])
    return estimate_noise_scale(ranges, sigmas.reshape(ranges.shape))


@pytest.mark.parametrize('origin_kind', ['none', 'point', 'per_ray'])
@pytest.mark.parametrize('noise_scale', [0.05, 1.0, 30.0])
def test_noise_for_scales_the_model_as_its_numpy_definition(origin_kind, noise_scale):
    """noise_for's one-pass ratios give the numpy definition's scale bit for bit (and so the same clamped
    model): rays at the origin, NaN and infinite points, per-ray starts."""
    rng = np.random.default_rng(6)
    height, width = 40, 61
    rows, columns = np.mgrid[0:height, 0:width]
    directions = np.stack([(columns - 30) / 60.0, (rows - 20) / 60.0, np.ones((height, width))], axis=-1)
    depth = 2.0 + 0.02 * columns + 0.01 * rows + rng.normal(0.0, 0.002 * noise_scale, (height, width))
    points = directions * depth[..., None]
    points[rng.random((height, width)) < 0.05] = np.nan
    points[3, 7, 2] = np.inf
    origins = {'none': None, 'point': np.array([0.01, -0.02, 0.0]), 'per_ray': rng.normal(0.0, 0.01, points.shape)}
    origins = origins[origin_kind]
    if origins is not None:
        points[5, 9] = origins[5, 9] if origins.ndim == 3 else origins  # a ray of length 0
    profile = PROFILES['depth_camera']
    scale = _reference_noise_scale(profile.noise, points, origins)
    assert np.isfinite(scale)
    low, high = profile.noise_scale_bounds
    assert profile.noise_for(points, origins) == profile.noise.scaled(min(max(scale, low), high))
    wide = SensorProfile(name='wide', noise=profile.noise, noise_scale_bounds=(1e-9, 1e9))
    assert wide.noise_for(points, origins) == profile.noise.scaled(scale)
    # too few valid triples: the model as it is
    few_origins = origins[:2, :40] if origin_kind == 'per_ray' else origins
    assert wide.noise_for(points[:2, :40], few_origins) == profile.noise


def test_ray_model_of_a_scan_without_returns_is_all_invalid():
    scan = make_ray_scan(np.full((3, 4, 3), np.nan))
    assert not scan.valid.any()
    np.testing.assert_array_equal(scan.center, np.zeros(3))
    np.testing.assert_array_equal(scan.endpoints, 0.0)
    np.testing.assert_array_equal(scan.directions, 0.0)


@pytest.mark.parametrize('max_distance', [0.5, 3.0, np.inf])
def test_edge_masks_equal_their_numpy_definition(max_distance):
    rng = np.random.default_rng(4)
    points = np.cumsum(rng.normal(0.0, 0.4, (29, 41, 3)), axis=1)
    points[rng.random((29, 41)) < 0.1] = np.nan
    scan = make_ray_scan(points)
    ok_right, ok_down = _edge_masks(scan, max_distance)
    p = scan.endpoints.reshape(29, 41, 3)
    v = scan.valid.reshape(29, 41)
    right = np.zeros((29, 41), bool)
    down = np.zeros((29, 41), bool)
    right[:, :-1] = v[:, 1:] & v[:, :-1] & (np.linalg.norm(p[:, 1:] - p[:, :-1], axis=2) <= max_distance)
    down[:-1] = v[1:] & v[:-1] & (np.linalg.norm(p[1:] - p[:-1], axis=2) <= max_distance)
    np.testing.assert_array_equal(ok_right, right.ravel())
    np.testing.assert_array_equal(ok_down, down.ravel())
    assert 0 < ok_right.sum() < right.size
