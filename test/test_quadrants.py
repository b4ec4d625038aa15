"""The quadrant jackknife (ppe_ros.core.quadrants) against a slow, obviously correct reference."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ppe_ros.core.quadrants import MIN_QUADRANT_POINTS, quadrant_jackknife


def reference_jackknife(points: np.ndarray, centroid: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Delete-one-quadrant jackknife of the least-squares (a, b, c) of w = a + b u + c v, with numpy's lstsq."""
    u, v, w = ((points - centroid) @ axes.T).T
    quadrant = np.zeros(len(points), dtype=int)
    high_u = u > np.median(u)
    for half in (False, True):
        members = high_u == half
        quadrant[members] = 2 * half + (v[members] > np.median(v[members]))
    if np.bincount(quadrant, minlength=4).min() < MIN_QUADRANT_POINTS:
        return np.zeros((3, 3))
    thetas = []
    for q in range(4):
        keep = quadrant != q
        design = np.stack([np.ones(keep.sum()), u[keep], v[keep]], axis=1)
        thetas.append(np.linalg.lstsq(design, w[keep], rcond=None)[0])
    thetas = np.array(thetas)
    spread = thetas - thetas.mean(axis=0)
    return 3.0 / 4.0 * spread.T @ spread


def _random_axes(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q


def _bumpy_plane(rng, n, axes, centroid, bump):
    u, v = rng.uniform(-3, 2, n), rng.uniform(-1, 1.5, n)
    w = bump * (u**2 - 1.0) + 0.3 * bump * np.sin(2 * v) + rng.normal(0, 0.003, n)
    return centroid + np.stack([u, v, w], axis=1) @ axes


def test_kernel_matches_the_reference_on_random_planes():
    rng = np.random.default_rng(11)
    sizes = [12, 40, 500, 3, 7, 2000]
    centroids = rng.normal(0, 10, (len(sizes), 3))
    axes = np.stack([_random_axes(rng) for _ in sizes])
    clouds = [_bumpy_plane(rng, n, axes[j], centroids[j], 0.02 * j) for j, n in enumerate(sizes)]
    points = np.concatenate(clouds)
    index = np.concatenate([np.full(n, j) for j, n in enumerate(sizes)])
    shuffle = rng.permutation(len(points))
    got = quadrant_jackknife(points[shuffle], index[shuffle], centroids, axes)
    assert got.shape == (len(sizes), 3, 3)
    for j, cloud in enumerate(clouds):
        want = reference_jackknife(cloud, centroids[j], axes[j])
        np.testing.assert_allclose(got[j], want, rtol=1e-9, atol=1e-18)
    assert np.all(got[3] == 0) and np.all(got[4] == 0)  # too few points per quadrant
    assert np.trace(got[5]) > 0


def test_a_flat_plane_has_no_spread_and_a_bent_one_has():
    rng = np.random.default_rng(2)
    axes, centroid = np.eye(3), np.zeros(3)
    flat = _bumpy_plane(rng, 4000, axes, centroid, 0.0)
    bent = _bumpy_plane(rng, 4000, axes, centroid, 0.05)
    index = np.zeros(4000, dtype=int)
    spread_flat = quadrant_jackknife(flat, index, centroid[None], axes[None])[0]
    spread_bent = quadrant_jackknife(bent, index, centroid[None], axes[None])[0]
    assert spread_flat[0, 0] < 1e-8  # the 3 mm noise alone: the offset moves by about 0.1 mm
    assert spread_bent[0, 0] > 100 * spread_flat[0, 0]  # a bend in u moves the offset and the tilt about v
    assert spread_bent[1, 1] > 100 * spread_flat[1, 1]


def test_the_jackknife_is_deterministic_and_order_independent():
    rng = np.random.default_rng(5)
    points = _bumpy_plane(rng, 1000, np.eye(3), np.zeros(3), 0.03)
    index = np.zeros(1000, dtype=int)
    first = quadrant_jackknife(points, index, np.zeros((1, 3)), np.eye(3)[None])
    again = quadrant_jackknife(points[::-1].copy(), index, np.zeros((1, 3)), np.eye(3)[None])
    np.testing.assert_allclose(first, again, rtol=1e-9)
    np.testing.assert_array_equal(first, quadrant_jackknife(points, index, np.zeros((1, 3)), np.eye(3)[None]))


def test_bad_input_is_a_clear_error():
    with pytest.raises(ValueError, match='points must be'):
        quadrant_jackknife(np.zeros((4, 2)), np.zeros(4, int), np.zeros((1, 3)), np.eye(3)[None])
    with pytest.raises(ValueError, match='plane_index must be in'):
        quadrant_jackknife(np.zeros((4, 3)), np.full(4, 2), np.zeros((1, 3)), np.eye(3)[None])
    with pytest.raises(ValueError, match='axes'):
        quadrant_jackknife(np.zeros((4, 3)), np.zeros(4, int), np.zeros((1, 3)), np.eye(3))


def test_profile_covariance_counts_the_spread_of_a_bent_surface():
    """A wall bowed by 5 cm over its width: with the quadrant jackknife a lidar profile's covariance is much
    wider (the fitted tilt depends on which part of the bow is seen) than the independent-patch model's
    alone, and the same labels come out. (The lidar profile's own choice is the row jackknife, whose beams
    each see the whole bow: test_row_jackknife.)"""
    from ppe_ros import extract_planes
    from ppe_ros.core.sensor import PROFILES

    rows, cols = np.indices((48, 160))
    azimuth = np.radians(-40 + 80 * cols / 159)
    elevation = np.radians(-12 + 24 * rows / 47)
    directions = np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], -1
    )
    y = 6 * np.tan(azimuth)
    depth = 6.0 + 0.05 * (y / 5.0) ** 2  # a wall 6 m ahead, bowed 5 cm over +-5 m
    ranges = depth / directions[..., 0] + np.random.default_rng(0).normal(0, 0.005, depth.shape)
    points = directions * ranges[..., None]
    model_only = dataclasses.replace(PROFILES['lidar'], quadrant_jackknife=False, row_jackknife=False)
    with_spread = extract_planes(points, sensor=dataclasses.replace(model_only, quadrant_jackknife=True))
    model_only = extract_planes(points, sensor=model_only)
    np.testing.assert_array_equal(with_spread.labels, model_only.labels)
    big = int(np.argmax(with_spread.point_counts))
    assert np.trace(with_spread.covariances[big]) > 10 * np.trace(model_only.covariances[big])
    assert np.all(np.linalg.eigvalsh(with_spread.covariances[big]) > -1e-15)
