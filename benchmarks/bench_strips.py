"""Strips: the greedy's CPU time per strip of an Ouster sweep, and the critical path on T threads.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_strips.py [--repeats 5] [--scan FILE]

The lidar profile runs its greedy on vertical strips of the sweep (``tiles``). This prints, for the whole
sweep as one strip and for 8 and 16 strips, the sum of the strips' greedy CPU times and the critical path
when T threads take the strips in order (each thread the next strip when it is free): what bounds a tiled
extraction's seeds + greedy on T cores. Each strip is extracted alone as its own scan
(``extract_plane_hierarchy`` with the profile's noise model and greedy options, one numba thread), timed by
``time.thread_time`` (CPU time of the calling thread: other processes' load changes it less than wall time),
median over the repeats after one warm-up call.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numba
import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SCAN = REPO.parent / 'shared' / 'data' / 'ouster' / 'OS-1-128_v2.3.0_1024x10_lb_n3_frame1795_xyz_m.npy'
STRIP_COUNTS = (1, 8, 16)
THREADS = (2, 4, 8, 16)


def critical_path(times: list[float], threads: int) -> float:
    """Finish time of the last strip when ``threads`` threads take the strips in order."""
    free = [0.0] * threads
    for t in times:
        free[int(np.argmin(free))] += t
    return max(free)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeats', type=int, default=5)
    parser.add_argument('--scan', type=Path, default=DEFAULT_SCAN, help='an Ouster .npy sweep (H, W, 3)')
    args = parser.parse_args(argv)
    if not args.scan.exists():
        print(f'bench_strips: {args.scan} not found (the shared data folder is beside the repository)')
        return 2
    sys.path.insert(0, str(REPO))
    from ppe_ros.benchmark.report import machine_description
    from ppe_ros.core.ppe.api import _profile_greedy_options, extract_plane_hierarchy
    from ppe_ros.core.sensor import PROFILES
    from ppe_ros.io import load_scan

    numba.set_num_threads(1)
    profile = PROFILES['lidar']
    scan = load_scan(str(args.scan))
    noise = profile.noise_for(scan.points, scan.origins)
    options = _profile_greedy_options(profile)

    def greedy_cpu(first: int, stop: int) -> float:
        points = np.ascontiguousarray(scan.points[:, first:stop])
        origins = np.ascontiguousarray(scan.origins[:, first:stop])
        kwargs = dict(origins=origins, max_error_increment=profile.max_error_increment, noise=noise, tiles=1)
        extract_plane_hierarchy(points, threads=1, options=options, **kwargs)
        times = []
        for _ in range(args.repeats):
            start = time.thread_time()
            extract_plane_hierarchy(points, threads=1, options=options, **kwargs)
            times.append(time.thread_time() - start)
        return float(np.median(times))

    width = scan.points.shape[1]
    print(
        f'machine: {machine_description()}; command: python benchmarks/bench_strips.py --repeats {args.repeats}; '
        f'{time.strftime("%Y-%m-%d %H:%M", time.gmtime())}; scan {args.scan.name}\n'
    )
    print('| strips | total greedy CPU s | ' + ' | '.join(f'critical path, {t} threads' for t in THREADS) + ' |')
    print('|---:|---:|' + '---:|' * len(THREADS))
    for count in STRIP_COUNTS:
        edges = [round(i * width / count) for i in range(count + 1)]
        times = [greedy_cpu(edges[i], edges[i + 1]) for i in range(count)]
        paths = ' | '.join(f'{critical_path(times, t):.3f}' for t in THREADS)
        print(f'| {count} | {sum(times):.3f} | {paths} |', flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
