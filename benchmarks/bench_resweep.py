"""Repeatability on training sweeps: each real sweep against the sweep its sensor would take after a known motion.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_resweep.py [--scans 'OS-0-128 1491' ...] [--range-sigma 0.005]
        [--set NAME=VALUE ...]

The consecutive OS-1-128 sweeps 1795-1797 that bench_real.py scores for repeatability are reported scans: no
default may be chosen on them. This benchmark gives the training sweeps (ppe_ros.benchmark.real.SCAN_SPLIT;
default the four Ouster training sweeps) a second sweep each: ``ppe_ros.benchmark.real.resweep`` moves the
sweep's returns by a motion ``x_B = R x_A + t`` and puts them on the same sensor's beam grid (the nearest
return per pixel stays), so that B sees A's surfaces through rays that fall elsewhere on them, with A's own
errors (and, with ``--range-sigma``, new range noise). Both sweeps are extracted with the lidar profile
(``extract_planes(points, origins=..., sensor='lidar')``; ``--set surface_tolerance=0.065`` measures a
variant, ppe_ros.benchmark.real.profile_with_settings) and A's planes of >= 1000 points are matched in B
after the true motion as bench_real.py does (ppe_ros.benchmark.real.match_planes: normal < 2 deg, offset
< 5 cm, IoU >= 0.7 for "found again"). Motions (MOTIONS): 0.25 m along x (about a car's 0.23 m between two
10 Hz sweeps), the same with 1 deg of yaw, 0.25 m along y.

Prints per scan and motion the planes of >= 20 points of A and B, A's large planes found again, the median
IoU, how many of those not found again miss each criterion (IoU / angle / offset) and the median Mahalanobis²
of the matched planes (the true motion: no registration error), then the sums per motion, and the machine.
"""

from __future__ import annotations

import argparse
import math
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get('PPE_SHARED_DATA', REPO.parent / 'shared' / 'data'))
#: Planes of at least this many points are matched (bench_real.py's repeatability limit).
LARGE_PLANE_POINTS = 1000


def _yaw(degrees: float) -> np.ndarray:
    angle = math.radians(degrees)
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


#: (name, R, t) of x_B = R x_A + t: the sensor moved by -R^T t.
MOTIONS = (
    ('0.25 m along x', np.eye(3), np.array([-0.25, 0.0, 0.0])),
    ('0.25 m along x, 1 deg yaw', _yaw(1.0), np.array([-0.25, 0.0, 0.0])),
    ('0.25 m along y', np.eye(3), np.array([0.0, -0.25, 0.0])),
)


def _default_scans() -> list[str]:
    from ppe_ros.benchmark.real import REAL_SCANS

    return [s.name for s in REAL_SCANS if s.split == 'training' and s.kind == 'lidar' and s.ground]


def _row(name: str, motion: str, planes_a, planes_b, matches) -> tuple[list[str], tuple[int, int]]:
    from ppe_ros.benchmark.real import count_planes, summarize_matches

    summary = summarize_matches(matches)
    share = f'{100 * summary.found_share:.0f} %' if summary.planes else ''
    row = [
        name,
        motion,
        f'{count_planes(planes_a.labels)} / {count_planes(planes_b.labels)}',
        f'{summary.found} / {summary.planes}',
        share,
        f'{summary.median_iou:.2f}' if summary.planes else '',
        f'{summary.missed_iou} / {summary.missed_angle} / {summary.missed_offset}',
        f'{summary.median_mahalanobis2:.2f}' if math.isfinite(summary.median_mahalanobis2) else '',
    ]
    return row, (summary.found, summary.planes)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        '--scans', nargs='+', default=None, help='real scan names (default: the Ouster training sweeps)'
    )
    parser.add_argument('--range-sigma', type=float, default=0.0, help='new range noise of sweep B (m, default 0)')
    parser.add_argument(
        '--set', nargs='+', default=[], metavar='NAME=VALUE', help='lidar profile fields to change (JSON values)'
    )
    args = parser.parse_args(argv)

    from ppe_ros import extract_planes
    from ppe_ros.benchmark.real import REAL_SCANS, match_plane_sets, profile_with_settings, resweep
    from ppe_ros.benchmark.report import machine_description
    from ppe_ros.io import load_scan

    specs = {spec.name: spec for spec in REAL_SCANS}
    names = args.scans or _default_scans()
    unknown = [n for n in names if n not in specs]
    if unknown:
        print(f'bench_resweep: error: unknown scan(s) {unknown}; known: {sorted(specs)}', file=sys.stderr)
        return 2
    try:
        profile = profile_with_settings('lidar', args.set)
    except ValueError as exc:
        print(f'bench_resweep: error: {exc}', file=sys.stderr)
        return 2
    if not SHARED.is_dir():
        print(f'bench_resweep: error: the shared data folder {SHARED} does not exist', file=sys.stderr)
        return 2
    header = [
        'scan',
        'motion',
        'planes >= 20, A / B',
        'found again',
        'share',
        'median IoU',
        'missed IoU / angle / offset',
    ]
    header.append('median Mahalanobis²')
    rows, totals = [], {m[0]: [0, 0] for m in MOTIONS}
    started = time.perf_counter()
    for name in names:
        spec = specs[name]
        scan = load_scan(SHARED / spec.path, units=spec.units)
        planes_a = extract_planes(scan.points, origins=scan.origins, sensor=profile)
        for motion, rotation, translation in MOTIONS:
            points_b = resweep(scan.points, scan.origins, rotation, translation, range_sigma=args.range_sigma)
            planes_b = extract_planes(points_b, origins=scan.origins, sensor=profile)
            matches = match_plane_sets(
                scan.points,
                planes_a,
                points_b,
                scan.origins,
                planes_b,
                rotation,
                translation,
                min_points=LARGE_PLANE_POINTS,
            )
            row, (found, planes) = _row(name, motion, planes_a, planes_b, matches)
            rows.append(row)
            totals[motion][0] += found
            totals[motion][1] += planes
            print(' | '.join(row), file=sys.stderr, flush=True)
    command = shlex.join(argv if argv is not None else sys.argv[1:])
    when = time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())
    print(f'machine: {machine_description()}; command: python benchmarks/bench_resweep.py {command}; {when}')
    changed = ', '.join(args.set) or 'none'
    seconds = time.perf_counter() - started
    print(f'lidar profile changes: {changed}; range noise of B: {args.range_sigma} m; {seconds:.0f} s\n')
    print('| ' + ' | '.join(header) + ' |')
    print('|' + '---|' * len(header))
    for row in rows:
        print('| ' + ' | '.join(row) + ' |')
    print('\n| motion | found again, all scans | share |')
    print('|---|---:|---:|')
    for motion, (found, planes) in totals.items():
        share = f'{100 * found / planes:.0f} %' if planes else ''
        print(f'| {motion} | {found} / {planes} | {share} |')
    return 0


if __name__ == '__main__':
    sys.exit(main())
