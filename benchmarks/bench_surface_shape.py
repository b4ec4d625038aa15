"""Which large planes of a real scan are strips of one curved surface: plane and quadric fits of their unions.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_surface_shape.py [--scans Kinect 'ICL-NUIM 0' ...]
        [--min-points 10000] [--max-quadric-rms 0.01] [--min-touching 50]

Extracts each scan with its sensor profile (``extract_planes(points, origins=..., sensor=...)``: 'lidar' for the
Ouster sweeps and the TLS scan, 'depth_camera' for the Kinect and ICL-NUIM frames; default the Kinect frame)
and joins its planes of at least ``--min-points`` points that touch (``--min-touching`` 4-neighbour pixel
pairs) while the union's least-squares quadric height field fits within ``--max-quadric-rms`` metres RMS
(``ppe_ros.benchmark.real.smooth_surfaces``). A group of several planes whose plane fit is far worse than
its quadric fit is a curved surface that the extractor cut into flat strips (a cylinder of radius R has
one principal radius R and one of inf); flat surfaces meeting at an edge stay apart.

Prints per scan each group of two or more planes and every large plane alone: its planes, points, the
RMS distance from one plane (m), the quadric's RMS residual (m), the principal radii of curvature (m) and
the largest angle (deg) between the member planes' normals, then the machine.
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get('PPE_SHARED_DATA', REPO.parent / 'shared' / 'data'))


def _largest_angle_deg(normals: np.ndarray) -> float:
    """Largest angle (deg) between two of the unit normals (0 for one)."""
    angles = [math.degrees(math.acos(min(1.0, abs(float(a @ b))))) for a, b in itertools.combinations(normals, 2)]
    return max(angles, default=0.0)


def _radius(value: float) -> str:
    return 'inf' if not math.isfinite(value) or value > 1000.0 else f'{value:.2f}'


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scans', nargs='+', default=['Kinect'], help='names of ppe_ros.benchmark.real.REAL_SCANS')
    parser.add_argument('--min-points', type=int, default=10000)
    parser.add_argument('--max-quadric-rms', type=float, default=0.01, help='metres')
    parser.add_argument('--min-touching', type=int, default=50)
    args = parser.parse_args(argv)

    from ppe_ros.benchmark.real import REAL_SCANS, smooth_surfaces, surface_shape
    from ppe_ros.benchmark.report import machine_description
    from ppe_ros.core.extraction import extract_planes
    from ppe_ros.io import load_scan

    specs = {s.name: s for s in REAL_SCANS}
    unknown = [name for name in args.scans if name not in specs]
    if unknown:
        print(f'unknown scan(s) {unknown}; known: {sorted(specs)}', file=sys.stderr)
        return 2
    columns = ('scan', 'planes', 'points', 'plane RMS m', 'quadric RMS m', 'radii of curvature m', 'largest angle deg')
    print('| ' + ' | '.join(columns) + ' |')
    print('|' + '---|' * len(columns))
    for name in args.scans:
        spec = specs[name]
        scan = load_scan(SHARED / spec.path, units=spec.units)
        sensor = 'depth_camera' if spec.kind == 'depth_camera' else 'lidar'
        planes = extract_planes(scan.points, origins=scan.origins, sensor=sensor)
        groups = smooth_surfaces(
            scan.points,
            planes.labels,
            min_points=args.min_points,
            max_quadric_rms=args.max_quadric_rms,
            min_touching=args.min_touching,
        )
        for members, shape in groups:
            if len(members) > 1:
                # and each strip alone, for comparison
                rows = [(members, shape)] + [
                    ([p], surface_shape(scan.points.reshape(-1, 3)[planes.labels.ravel() == p])) for p in members
                ]
            else:
                rows = [(members, shape)]
            for plane_ids, s in rows:
                angle = _largest_angle_deg(planes.normals[np.asarray(plane_ids) - 1])
                print(
                    f'| {name} ({sensor}) | {" + ".join(map(str, plane_ids))} | {s.points} | {s.plane_rms:.4f} | '
                    f'{s.quadric_rms:.4f} | {_radius(s.radii[0])}, {_radius(s.radii[1])} | {angle:.1f} |'
                )
    command = shlex.join(sys.argv[1:] if argv is None else argv)
    when = time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())
    print(f'\nmachine: {machine_description()}; command: python benchmarks/bench_surface_shape.py {command}; {when}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
