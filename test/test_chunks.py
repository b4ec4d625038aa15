"""Runs of planes per thread (chunks.group_chunks) and the per-plane kernels that loop over them."""

from __future__ import annotations

import numpy as np
import pytest

from ppe_ros.core.chunks import group_chunks, plane_members
from ppe_ros.core.fitting import (
    FIT_MAX_ITERATIONS,
    FIT_RELATIVE_TOLERANCE,
    _fit_groups,
    fit_pixel_groups,
    fit_pixel_groups_with_members,
)
from ppe_ros.core.quadrants import _jackknife_kernel
from ppe_ros.core.scan import make_ray_scan
from ppe_ros.core.surfaces import _plane_sums_kernel, _quadric_reduction_kernel


def _reference_chunks(counts, n_chunks):
    """The rule, one group at a time: run c ends at the first group that brings the running total to
    c / C of the whole or more."""
    total, running, bounds, g = float(sum(counts)), 0.0, [0], 0
    for c in range(1, n_chunks):
        while g < len(counts) and running < total * c / n_chunks:
            running += counts[g]
            g += 1
        bounds.append(g)
    return [*bounds, len(counts)]


@pytest.mark.parametrize('n_chunks', [1, 2, 3, 8])
def test_group_chunks_follow_the_rule_and_cover_every_group_once(n_chunks):
    rng = np.random.default_rng(n_chunks)
    for counts in (np.sort(rng.integers(1, 500, 200))[::-1], rng.integers(0, 50, 37), np.zeros(5), np.ones(0)):
        bounds = group_chunks(counts, n_chunks)
        assert bounds.tolist() == _reference_chunks(counts.tolist(), n_chunks)
        assert bounds[0] == 0 and bounds[-1] == len(counts) and np.all(np.diff(bounds) >= 0)


def test_a_group_larger_than_a_share_is_a_run_of_its_own_and_sizes_of_one_order_are_balanced():
    counts = np.array([600, 100, 100, 100, 100])
    assert group_chunks(counts, 2).tolist() == [0, 1, 5]
    assert group_chunks(counts, 3).tolist() == [0, 1, 2, 5]  # the largest run is the large group alone
    sizes = np.sort(np.random.default_rng(0).integers(40, 400, 300))[::-1]
    bounds = group_chunks(sizes, 4)
    loads = np.add.reduceat(sizes, bounds[:-1])
    assert loads.max() - loads.min() <= sizes.max()  # equal up to one group
    with pytest.raises(ValueError, match='n_chunks'):
        group_chunks(sizes, 0)


def test_plane_members_group_each_planes_pixels_in_pixel_order():
    rng = np.random.default_rng(3)
    for n_planes, size in ((5, 300), (1, 7), (40, 2000), (3, 0)):
        labels = rng.integers(0, n_planes + 1, size).astype(np.int32)
        members, starts = plane_members(labels, n_planes)
        on = np.flatnonzero(labels > 0)
        np.testing.assert_array_equal(members, on[np.argsort(labels[on], kind='stable')])
        np.testing.assert_array_equal(
            starts, np.concatenate([[0], np.cumsum(np.bincount(labels, minlength=n_planes + 1)[1:])])
        )
    with pytest.raises(ValueError, match=r'labels must be in 0\.\.2'):
        plane_members(np.array([0, 3]), 2)
    with pytest.raises(ValueError, match='one-dimensional'):
        plane_members(np.zeros((2, 2), np.int32), 2)


def _grouped_scene(seed):
    """A noisy curved scan cut into groups of very different sizes (the first one holds most rays)."""
    rng = np.random.default_rng(seed)
    y, z = np.meshgrid(np.linspace(-1.0, 1.0, 90), np.linspace(-0.5, 0.5, 40))
    depth = 6.0 - 0.3 * y**2 + 0.2 * z + rng.normal(0.0, 0.01, y.shape)
    points = np.stack([depth, y * depth / 6.0, z * depth / 6.0], axis=-1)
    ids = np.where(y < 0.2, 0, 1 + (np.arange(90)[None, :] // 7) + 20 * (np.arange(40)[:, None] // 9))
    planes, _ = fit_pixel_groups(make_ray_scan(points), ids.reshape(-1), min_plane_points=4, residuals=False)
    return points, planes


@pytest.mark.parametrize('seed', [0, 1])
def test_the_fits_members_are_plane_members_of_their_labels(seed):
    """fit_pixel_groups_with_members hands on its own grouping of the pixels by plane: it must be what
    plane_members makes of the labels (the planarity test and the covariances use it instead), with
    invalid rays and groups below min_plane_points left out."""
    points, _ = _grouped_scene(seed)
    points[3, 5] = np.nan
    scan = make_ray_scan(points)
    ids = np.where(np.arange(scan.size) % 97 == 0, 5000, 0) + np.arange(scan.size) // 400
    planes, residuals, (members, starts) = fit_pixel_groups_with_members(
        scan, ids, min_plane_points=300, residuals=False, sigmas=None
    )
    assert residuals is None and 2 < planes.num_planes < len(np.unique(ids))
    want_members, want_starts = plane_members(planes.labels.reshape(-1), planes.num_planes)
    np.testing.assert_array_equal(members, want_members)
    np.testing.assert_array_equal(starts, want_starts)
    same, _ = fit_pixel_groups(scan, ids, min_plane_points=300, residuals=False)
    np.testing.assert_array_equal(same.labels, planes.labels)
    _, _, (no_members, no_starts) = fit_pixel_groups_with_members(
        scan, ids, min_plane_points=10**6, residuals=False, sigmas=None
    )
    assert len(no_members) == 0 and list(no_starts) == [0]


@pytest.mark.parametrize('seed', [0, 1])
def test_the_per_plane_kernels_give_the_same_bits_for_any_runs(seed):
    """Each plane is computed by one thread in its own order, so every split into runs gives the
    same result: one run (one thread's loop), the balanced runs and one run per plane."""
    points, planes = _grouped_scene(seed)
    scan = make_ray_scan(points)
    labels = planes.labels.reshape(-1)
    n = planes.num_planes
    counts = planes.point_counts.astype(np.float64)
    sigmas = np.where(scan.valid, 0.01, np.nan)
    splits = [np.array([0, n]), group_chunks(counts, 3), np.arange(n + 1)]
    assert n > 20 and planes.point_counts[0] > counts.sum() / 3

    members, starts = plane_members(labels, n)

    def sums(bounds):
        args = (scan.endpoints, scan.center, scan.directions, sigmas, planes.normals, planes.offsets, counts)
        return _plane_sums_kernel(members, starts, bounds, *args)

    first = sums(splits[0])
    centroid, scatter = first[:, :3], first[:, [[3, 4, 5], [4, 6, 7], [5, 7, 8]]]
    vectors = np.linalg.eigh(scatter)[1]
    scales = np.ones((n, 3))
    assert (labels > 0).all()
    w, sse, info, metric = np.empty((n, 3)), np.empty(n), np.empty((n, 6)), np.empty(n)
    results = []
    for bounds in splits:
        for out in (w, sse, info, metric):
            out.fill(np.nan)  # a plane a split missed stays NaN
        _fit_groups(
            scan.endpoints,
            scan.directions,
            members,
            starts,
            bounds,
            FIT_MAX_ITERATIONS,
            FIT_RELATIVE_TOLERANCE,
            w,
            sse,
            info,
            sigmas,
            metric,
        )
        results.append(
            (
                sums(bounds),
                _quadric_reduction_kernel(
                    members, starts, bounds, scan.endpoints, scan.center, centroid, vectors, scales
                ),
                _jackknife_kernel(scan.endpoints, scan.center, 0, members, starts, bounds, centroid, vectors),
                _jackknife_kernel(  # the row jackknife
                    scan.endpoints, scan.center, scan.width, members, starts, bounds, centroid, vectors
                ),
                w.copy(),
                sse.copy(),
                info.copy(),
                metric.copy(),
            )
        )
    for other in results[1:]:
        for got, want in zip(other, results[0], strict=True):
            np.testing.assert_array_equal(got, want)
    assert np.isfinite(results[0][1]).all() and results[0][1].max() > 0.0
    assert np.isfinite(results[0][4]).all() and (results[0][2] != 0.0).any() and (results[0][3] != 0.0).any()
