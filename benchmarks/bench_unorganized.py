"""Unorganized clouds (issue 20): the cost of the range-image projection and of the labels back, against the
extraction, and how well the planes of the organized sweep are reproduced. Prints markdown tables.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_unorganized.py [--scans NAME ...] [--repeat 5] [--no-livox]

Each Ouster sweep of ../shared/data/ouster is extracted with the lidar profile as the organized cloud it is,
then turned into what a Hesai driver publishes (its returns shuffled, no-returns dropped, float32, a ring
field) and extracted through :func:`ppe_ros.core.projection.project_points` (rows from the rings, or without
them from elevation bins), PPE on the range image, and the labels back
(:func:`ppe_ros.core.projection.planes_for_points`). Columns: the range image, the points that lost their cell,
the projection and label-mapping times (median of ``--repeat`` runs, alternating with each other), the
extraction time on the range image, their ratio, and the share of points with the organized sweep's plane
after matching labels, with the range image cut at the default 180 deg and at the sweep's own seam.
A second table: a synthetic Livox-like (non-repetitive, rosette) cloud on the fixed angular grid at several
resolutions: the grid's fill and the share of wall and floor points labelled with their surface's plane.
The first run compiles numba kernels (a minute or more); everything is run once on a small cloud first.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time
from pathlib import Path

import numpy as np

from ppe_ros.core.extraction import extract_planes
from ppe_ros.core.projection import (
    DEFAULT_AZIMUTH_START_DEG,
    matched_label_agreement,
    planes_for_points,
    project_points,
)

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get('PPE_SHARED_DATA', REPO.parent / 'shared' / 'data'))
LIDAR_TOLERANCE = 0.05  # the lidar profile's surface_tolerance: the lost-point rule's distance


def load_sweep(path: Path) -> np.ndarray:
    points = np.load(path).astype(np.float32).astype(np.float64)  # what a driver's float32 fields give
    points[(points == 0).all(axis=2)] = np.nan
    return points


def seam_of(sweep: np.ndarray) -> float:
    """Azimuth (deg) between the sweep's last and first column."""
    first = np.nanmedian(np.arctan2(sweep[:, 0, 1], sweep[:, 0, 0]))
    last = np.nanmedian(np.arctan2(sweep[:, -1, 1], sweep[:, -1, 0]))
    return math.degrees(math.atan2(math.sin(first) + math.sin(last), math.cos(first) + math.cos(last)))


def hesai_like(sweep: np.ndarray, seed: int = 20) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shuffled returns, their rings and their indices in the organized sweep."""
    width = sweep.shape[1]
    flat = sweep.reshape(-1, 3)
    index = np.flatnonzero(np.isfinite(flat).all(axis=1))
    np.random.default_rng(seed).shuffle(index)
    return flat[index], index // width, index


def median_time(function, repeat: int) -> tuple[float, object]:
    times, result = [], None
    for _ in range(repeat):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def sweep_rows(path: Path, repeat: int) -> list[str]:
    sweep = load_sweep(path)
    seam = seam_of(sweep)
    start = time.perf_counter()
    organized = extract_planes(sweep, sensor='lidar')
    organized_s = time.perf_counter() - start
    points, rings, index = hesai_like(sweep)
    reference = organized.labels.reshape(-1)[index]
    rows = []
    for name, given in (('ring field', rings), ('no ring field', None)):
        agreements, extract_s, project_s, label_s, projection = [], [], [], [], None
        for azimuth_start in (DEFAULT_AZIMUTH_START_DEG, seam):
            # projection and label mapping alternate within one loop, so load changes hit both alike
            project_times, label_times = [], []
            planes = None
            for _ in range(repeat):
                mark = time.perf_counter()
                projection = project_points(points, given, azimuth_start=azimuth_start)
                project_times.append(time.perf_counter() - mark)
                if planes is None:
                    mark = time.perf_counter()
                    grid_planes = extract_planes(projection.image(points), sensor='lidar')
                    extract_s.append(time.perf_counter() - mark)
                mark = time.perf_counter()
                planes = planes_for_points(projection, grid_planes, points, LIDAR_TOLERANCE)
                label_times.append(time.perf_counter() - mark)
            project_s.append(statistics.median(project_times))
            label_s.append(statistics.median(label_times))
            agreements.append(matched_label_agreement(reference, planes.labels))
        project, labels, extract = statistics.median(project_s), statistics.median(label_s), min(extract_s)
        rows.append(
            f'| {path.name.split("_v")[0]} {path.name.split("frame")[1].split("_")[0]} | {len(points)} | {name} | '
            f'{projection.rows}x{projection.columns} | {projection.lost_points} | {1e3 * project:.0f} | '
            f'{1e3 * labels:.1f} | {extract:.2f} ({organized_s:.2f}) | {100 * (project + labels) / extract:.1f} % | '
            f'{100 * agreements[0]:.2f} % | {100 * agreements[1]:.2f} % ({seam:.1f} deg) |'
        )
    return rows


def livox_like(n_points: int = 20000, seed: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """A rosette-like non-repetitive pattern over a 70 deg cone onto a wall 5 m ahead and the floor 1.5 m below:
    the points ``(n, 3)`` and whether each hit the wall."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0, 1, n_points))
    radius = np.radians(35) * np.abs(np.sin(2 * math.pi * 37 * t)) * np.sqrt(rng.uniform(0.2, 1, n_points))
    angle = 2 * math.pi * 5.1 * t
    elevation, azimuth = radius * np.sin(angle), radius * np.cos(angle)
    direction = np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=1
    )
    with np.errstate(divide='ignore'):
        to_wall = np.where(direction[:, 0] > 0, 5.0 / direction[:, 0], np.inf)
        to_floor = np.where(direction[:, 2] < 0, -1.5 / direction[:, 2], np.inf)
    ranges = np.minimum(to_wall, to_floor) + rng.normal(0, 0.01, n_points)
    return direction * ranges[:, None], to_wall < to_floor


def livox_rows() -> list[str]:
    points, on_wall = livox_like()
    truth = np.where(on_wall, 1, 2)
    rows = []
    for resolution in (0.2, 0.4, 0.8, 1.6):
        start = time.perf_counter()
        projection = project_points(points, rows='angular_grid', angular_resolution=resolution)
        planes = planes_for_points(
            projection, extract_planes(projection.image(points), sensor='lidar'), points, LIDAR_TOLERANCE
        )
        seconds = time.perf_counter() - start
        filled = np.count_nonzero(projection.cell_points >= 0) / projection.cell_points.size
        rows.append(
            f'| {resolution} | {projection.rows}x{projection.columns} | {100 * filled:.0f} % '
            f'| {projection.lost_points} | {planes.num_planes} | '
            f'{100 * matched_label_agreement(truth, planes.labels):.1f} % | {seconds:.2f} |'
        )
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--scans', nargs='*', default=None, help='Ouster file names (default: all 7 sweeps)')
    parser.add_argument('--repeat', type=int, default=5)
    parser.add_argument('--no-livox', action='store_true')
    args = parser.parse_args()
    folder = SHARED / 'ouster'
    if not folder.is_dir():
        print(f'needs the Ouster sweeps in {folder}')
        return 1
    paths = sorted(folder.glob('*_xyz_m.npy'))
    if args.scans:
        paths = [p for p in paths if any(name in p.name for name in args.scans)]
    warm, warm_rings, _ = hesai_like(load_sweep(paths[0])[:16, :128])
    for given in (warm_rings, None):  # compile every kernel before any timing
        projection = project_points(warm, given)
        planes_for_points(projection, extract_planes(projection.image(warm), sensor='lidar'), warm, LIDAR_TOLERANCE)
    print('## Unorganized Ouster sweeps (Hesai-like: shuffled, no-returns dropped), lidar profile\n')
    print(
        '| sweep | points | cloud | range image | lost | projection ms | labels ms | extraction s (organized) '
        "| (projection + labels) / extraction | same plane, seam 180 deg | same plane, sweep's seam |"
    )
    print('|---|---|---|---|---|---|---|---|---|---|---|')
    for path in paths:
        for row in sweep_rows(path, args.repeat):
            print(row, flush=True)
    if not args.no_livox:
        print('\n## Livox-like synthetic cloud (20000 rays, 70 deg cone, wall and floor) on the angular grid\n')
        print('| resolution deg | grid | cells filled | lost | planes | same plane as the truth | seconds |')
        print('|---|---|---|---|---|---|---|')
        for row in livox_rows():
            print(row, flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
