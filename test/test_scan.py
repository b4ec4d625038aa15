"""The ray model (core/scan.py) against a plain numpy formulation of the same definitions."""

from __future__ import annotations

import numpy as np
import pytest

from ppe_ros.core.ppe.seeds import _edge_masks
from ppe_ros.core.scan import make_ray_scan, range_noise_scaled
from ppe_ros.core.sensor import NoiseModel


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


@pytest.mark.parametrize(
    'constant, proportional, minimum', [(0.02, 0.001, 1e-4), (0.0274, 0.0, 1e-4), (0.0, 0.002, 0.03), (1e-5, 0.0, 1e-4)]
)
def test_range_noise_scaling_equals_the_noise_model_and_numpy(constant, proportional, minimum):
    """The one-pass kernel of a range-only noise model gives NoiseModel.sigmas' values and the numpy scaling bit
    for bit (NaN sigmas and zero directions on invalid rays; the floor where it is larger)."""
    rng = np.random.default_rng(4)
    scan = make_ray_scan(_random_scan(rng, 37, 53), np.array([0.3, -0.1, 1.2]))
    noise = NoiseModel(constant=constant, proportional=proportional, minimum=minimum)
    expected = np.where(scan.valid, noise.sigmas(scan.ranges, scan.directions), np.nan)
    scaled, sigmas = range_noise_scaled(scan, noise.constant, noise.proportional, noise.minimum)
    np.testing.assert_array_equal(sigmas, expected)
    np.testing.assert_array_equal(scaled.directions, scan.directions * np.where(scan.valid, expected, 0.0)[:, None])
    assert scaled.endpoints is scan.endpoints and np.isnan(sigmas[~scan.valid]).all()


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
