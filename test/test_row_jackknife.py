"""The delete-one-row (beam) jackknife (ppe_ros.core.quadrants.jackknife_of_members with row_width) against a slow,
obviously correct reference, and the lidar profile's covariances that use it."""

from __future__ import annotations

import dataclasses

import numpy as np

from ppe_ros.core.chunks import plane_members
from ppe_ros.core.quadrants import MIN_QUADRANT_POINTS, MIN_ROWS, jackknife_of_members


def reference_row_jackknife(points, rows, centroid, axes):
    """Delete-one-row jackknife of the least-squares (a, b, c) of w = a + b u + c v with numpy's lstsq: the
    groups are the rows holding at least MIN_QUADRANT_POINTS points (the others stay in every refit)."""
    u, v, w = ((points - centroid) @ axes.T).T
    values, counts = np.unique(rows, return_counts=True)
    groups = values[counts >= MIN_QUADRANT_POINTS]
    if len(groups) < MIN_ROWS:
        return np.zeros((3, 3))
    thetas = []
    for row in groups:
        keep = rows != row
        design = np.stack([np.ones(keep.sum()), u[keep], v[keep]], axis=1)
        thetas.append(np.linalg.lstsq(design, w[keep], rcond=None)[0])
    thetas = np.array(thetas)
    spread = thetas - thetas.mean(axis=0)
    return (len(groups) - 1) / len(groups) * spread.T @ spread


def _wall_pixels(rng, width, rows, columns, bias_sigma, noise=0.003):
    """Pixel ids and points of a wall x = 5 m seen by the given rows (beams 1 deg apart) and columns of a
    grid width columns wide, each row's points shifted along the normal by its own bias."""
    pixel, point = [], []
    for row in rows:
        bias = rng.normal(0.0, bias_sigma)
        for column in columns:
            elevation, azimuth = np.radians(5.0 - row), np.radians(0.3 * (column - width / 2))
            direction = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), 0.0])
            direction[2] = np.sin(elevation)
            x = 5.0 + bias + rng.normal(0.0, noise)
            pixel.append(row * width + column)
            point.append(direction * x / direction[0])
    return np.array(pixel), np.array(point)


def test_the_kernel_matches_the_reference_on_planes_of_several_rows():
    rng = np.random.default_rng(7)
    width = 200
    grid = np.full((40 * width, 3), np.nan)
    labels = np.zeros(40 * width, np.int64)
    row_sets = [range(2, 14), range(15, 17), range(18, 22), range(25, 40)]  # 12, 2 (too few), 4, 15 rows
    for j, rows in enumerate(row_sets):
        pixels, points = _wall_pixels(rng, width, rows, range(10 + 40 * j, 45 + 40 * j), 0.01)
        grid[pixels], labels[pixels] = points, j + 1
    # a sparse row of plane 1: two points on row 14, below MIN_QUADRANT_POINTS, in every refit
    pixels, points = _wall_pixels(rng, width, [14], range(10, 12), 0.01)
    grid[pixels], labels[pixels] = points, 1
    axes = np.tile(np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), (len(row_sets), 1, 1))
    centroids = np.array([grid[labels == j + 1].mean(axis=0) for j in range(len(row_sets))])
    members, starts = plane_members(labels, len(row_sets))
    got = jackknife_of_members(grid, np.zeros(3), members, starts, centroids, axes, row_width=width)
    for j in range(len(row_sets)):
        ids = np.flatnonzero(labels == j + 1)
        want = reference_row_jackknife(grid[ids], ids // width, centroids[j], axes[j])
        np.testing.assert_allclose(got[j], want, rtol=1e-8, atol=1e-20)
    assert np.all(got[1] == 0)  # two rows: no jackknife
    assert np.trace(got[0]) > 0 and np.trace(got[3]) > 0


def test_per_beam_biases_widen_the_spread():
    rng = np.random.default_rng(3)
    width = 100
    spreads = []
    for bias in (0.0, 0.02):
        pixels, points = _wall_pixels(rng, width, range(6), range(20, 80), bias)
        members, starts = plane_members(np.r_[np.ones(len(pixels), np.int64)], 1)
        order = pixels[members]
        grid = np.full((6 * width, 3), np.nan)
        grid[pixels] = points
        axes = np.array([[[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]])
        spreads.append(
            jackknife_of_members(grid, np.zeros(3), order, starts, points.mean(axis=0)[None], axes, row_width=width)[0]
        )
    # six beams with 2 cm biases: the offset's spread is of the order of 2 cm / sqrt(6), far above the noise's
    assert spreads[1][0, 0] > 100 * spreads[0][0, 0]
    assert 0.002**2 < spreads[1][0, 0] < 0.03**2


def test_the_lidar_profile_is_calibrated_on_thirty_two_beam_sweeps():
    """Against the generated true planes (HDL-32-like training sweeps), the lidar profile's covariances (per
    plane the wider of the quadrant and the row jackknife) give a median Mahalanobis² near the chi²(3)
    median 2.37, where the quadrant jackknife alone gave covariances 3-4 times too small: few beams see each
    plane, and each beam's bias moves it."""
    from ppe_ros import extract_planes
    from ppe_ros.benchmark.real import truth_mahalanobis
    from ppe_ros.core.sensor import PROFILES
    from ppe_ros.core.synthetic_real import generate_lidar_scan

    lidar = PROFILES['lidar']
    assert lidar.row_jackknife and lidar.quadrant_jackknife
    variants = {
        'profile': lidar,
        'quadrants': dataclasses.replace(lidar, row_jackknife=False),
        'rows': dataclasses.replace(lidar, quadrant_jackknife=False),
    }
    values = {name: [] for name in variants}
    for seed in (0, 1, 2, 3):
        scan = generate_lidar_scan(seed=seed, model='hdl32')
        for name, profile in variants.items():
            planes = extract_planes(scan.points, origins=scan.origins, sensor=profile)
            values[name].extend(
                truth_mahalanobis(
                    planes.labels, planes.offsets, planes.normals, planes.covariances, scan.labels, scan.plane_of_label
                )
            )
    assert len(values['profile']) >= 15
    medians = {name: float(np.median(v)) for name, v in values.items()}
    assert 1.5 < medians['profile'] < 4.5
    assert medians['quadrants'] > 2 * medians['profile']
    assert medians['rows'] <= medians['profile'] * (1 + 1e-9)
