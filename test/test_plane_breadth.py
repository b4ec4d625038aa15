"""The breadth test of the lidar profile (SensorProfile.min_plane_breadth, ppe_ros.core.surfaces.plane_breadth):
thin things (poles, trunks, branches) whose one-sided view fits a plane are reported as no plane."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ppe_ros import extract_planes
from ppe_ros.core.planes import PlaneSet
from ppe_ros.core.scan import make_ray_scan
from ppe_ros.core.sensor import PROFILES, SensorProfile
from ppe_ros.core.surfaces import plane_breadth


def slow_breadth(points: np.ndarray, labels: np.ndarray, label: int) -> float:
    """plane_breadth by its definition: per grid row the largest distance of the plane's points from the one in
    the row's least column, per grid column from the one in the column's least row; the smaller median."""
    medians = []
    for axis in (0, 1):  # 0: rows (lines of constant row index), 1: columns
        extents = []
        for line in range(labels.shape[axis]):
            on_line = np.take(labels, line, axis=axis) == label
            if not on_line.any():
                continue
            line_points = np.take(points, line, axis=axis)[on_line]
            first = line_points[0]  # the least column of a row, the least row of a column
            extents.append(np.linalg.norm(line_points - first, axis=1).max())
        medians.append(np.median(extents))
    return float(min(medians))


def planes_of(labels: np.ndarray) -> PlaneSet:
    """A PlaneSet with these labels (plane_breadth reads only the labels and point counts)."""
    count = int(labels.max())
    return PlaneSet(
        labels=labels.astype(np.int32),
        normals=np.tile([0.0, 0.0, 1.0], (count, 1)),
        offsets=np.zeros(count),
        centroids=np.zeros((count, 3)),
        point_counts=np.bincount(labels.ravel(), minlength=count + 1)[1:],
        sse=np.zeros(count),
        rmse=np.zeros(count),
        covariances=np.zeros((count, 3, 3)),
    )


def test_plane_breadth_equals_a_slow_reference():
    rng = np.random.default_rng(7)
    height, width = 24, 90
    points = rng.normal(0.0, 3.0, (height, width, 3))
    points[rng.random((height, width)) < 0.1] = np.nan
    # blobs, strips of one row and of one column, a row that wraps the seam, single points
    labels = rng.integers(1, 6, (height, width))
    labels[rng.random((height, width)) < 0.3] = 0
    labels[5, :] = 6  # one whole row: breadth 0 across it
    labels[:, 40] = 7  # one whole column
    labels[10, np.r_[85:90, 0:4]] = 8  # a run across the seam
    labels[20, 20] = 9  # a single point
    labels[~np.isfinite(points).all(axis=2)] = 0
    planes = planes_of(labels)
    scan = make_ray_scan(points)
    breadth = plane_breadth(scan, planes)
    assert breadth.shape == (9,)
    for label in range(1, 10):
        assert breadth[label - 1] == pytest.approx(slow_breadth(points, labels, label), rel=1e-12, abs=1e-12)
    assert breadth[5] == 0.0 and breadth[6] == 0.0 and breadth[8] == 0.0
    assert np.all(breadth[:5] > 0.0)
    with pytest.raises(ValueError, match='grid'):
        plane_breadth(make_ray_scan(points[:, :80]), planes)


def lidar_rays(rows: int = 96, columns: int = 360, step_deg: float = 0.35) -> np.ndarray:
    """Unit directions (rows, columns, 3) of a sweep looking along +x, step_deg apart both ways."""
    elevation = np.radians((np.arange(rows) - (rows - 1) / 2) * -step_deg)[:, None]
    azimuth = np.radians((np.arange(columns) - (columns - 1) / 2) * -step_deg)[None, :]
    x, y, z = np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def wall_and_boards(board_widths: tuple[float, ...], seed: int = 0) -> tuple[np.ndarray, list[np.ndarray]]:
    """A wall x = 9 m seen by lidar_rays, with flat boards x = 5 m of the given widths (m) and 4 m height in
    front of it, 1 cm range noise; the points and each board's pixel mask."""
    rays = lidar_rays()
    ranges = 9.0 / rays[..., 0]
    masks = []
    for index, board_width in enumerate(board_widths):
        at_board = 5.0 / rays[..., 0]
        hit = rays * at_board[..., None]
        centre = -2.0 + 4.0 * index
        mask = (np.abs(hit[..., 1] - centre) <= board_width / 2) & (np.abs(hit[..., 2]) <= 2.0)
        ranges = np.where(mask, at_board, ranges)
        masks.append(mask)
    ranges = ranges + np.random.default_rng(seed).normal(0.0, 0.01, ranges.shape)
    return rays * ranges[..., None], masks


def test_the_lidar_profile_drops_a_thin_board_and_keeps_a_broad_one_and_the_wall():
    points, (thin, broad) = wall_and_boards((0.12, 0.6))
    profile = PROFILES['lidar']
    assert profile.min_plane_breadth == 0.1
    planes = extract_planes(points, sensor=profile)
    # the 12 cm board (a pole's width) is flat and holds 3 x 96 rays, far more than the smallest plane
    assert thin.sum() > 250 and np.mean(planes.labels[thin] > 0) < 0.05
    assert np.mean(planes.labels[broad] > 0) > 0.9
    wall = ~(thin | broad)
    assert np.mean(planes.labels[wall] > 0) > 0.9
    # without the test the thin board is a plane of its own
    unlimited = extract_planes(points, sensor=dataclasses.replace(profile, min_plane_breadth=None))
    labels, counts = np.unique(unlimited.labels[thin], return_counts=True)
    assert labels[np.argmax(counts)] > 0 and counts.max() > 0.9 * thin.sum()
    assert unlimited.num_planes == planes.num_planes + 1


@pytest.mark.parametrize('value', [0.0, -0.1, np.nan, np.inf, True, '0.1'])
def test_min_plane_breadth_must_be_a_length(value):
    with pytest.raises(ValueError, match='min_plane_breadth'):
        SensorProfile(name='x', min_plane_breadth=value)
