"""Tiles: the real-sensor extraction with 1 and 2 threads, one greedy over the sweep (1 tile) against tiles, accuracy.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_tiles.py [--repeats 9] [--accuracy-scans 4] [--quick]

``extract_planes(points, origins=..., sensor='lidar')`` on real Ouster sweeps (../shared/data/ouster, with
their beam origins), four ways, alternated in one process so that the machine's load hits all of them alike:
``tiles=1`` (one greedy over the whole sweep, what the lidar profile ran before the tiles) and
``tiles='auto'`` (one strip per 128 columns), each with 1 and 2 threads (numba's threads for the seeds and
the strips' greedies). The row ``sensor=None`` (the node's defaults without a profile, code the tiles do not
touch) is the machine's calibration: ratios to it do not depend on how fast or loaded the VM is. Times are
medians (and minima) over the repeats after one warm-up call; "seeds + greedy" is the hierarchy's own time
(PlaneHierarchy.seconds), the rest of "extract" is the consolidation and the plane fits; "CPU s" is the
process's CPU time of the call (all threads: the work, which other processes' load changes less than the
wall time; on a loaded machine a second thread waits for a core and the wall times of 2 threads mislead).

First, the machine's own two-thread ceiling: two copies of a small nogil kernel run at once on two
threads against one copy alone (SCALING_KERNELS: dependent arithmetic, random reads in 8 MB and in 64 MB),
as a throughput ratio (2.00x: two independent cores; less where the two vCPUs share a physical core or
its caches and memory are contended). The extraction's "2 threads vs 1" is judged against it.

Accuracy: the same two settings (1 tile, auto) on generated OS-1-128 and OS-1-32 street sweeps
(ppe_ros.core.synthetic_real, test-split seeds 1000, 1001, ...) scored against their per-surface ground
truth (f, k of score_segmentation), and on every real Ouster sweep the plane counts the real-data benchmark
reports (planes of >= 20 and >= 100 points, share of the valid points in planes of >= 1000).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numba
import numpy as np

REPO = Path(__file__).resolve().parents[1]
OUSTER = REPO.parent / 'shared' / 'data' / 'ouster'
SPEED_SCANS = ('OS-1-128_v2.3.0_1024x10_lb_n3_frame1795_xyz_m.npy', 'OS-1-32-G_v2.1.1_1024x10_frame638_xyz_m.npy')
#: (label, extract_planes arguments, numba threads)
CONFIGS = (
    ('sensor=None (calibration)', {}, 2),
    ('lidar, 1 tile', {'sensor': 'lidar', 'tiles': 1}, 1),
    ('lidar, 1 tile', {'sensor': 'lidar', 'tiles': 1}, 2),
    ('lidar, tiles auto', {'sensor': 'lidar', 'tiles': 'auto'}, 1),
    ('lidar, tiles auto', {'sensor': 'lidar', 'tiles': 'auto'}, 2),
)


def _timed_extraction(points, origins, kwargs: dict, threads: int) -> tuple[float, float, float, object]:
    """Wall time of extract_planes, the hierarchy's seeds + greedy time, the process's CPU time, the planes."""
    from ppe_ros.core import extraction
    from ppe_ros.core.ppe import api

    numba.set_num_threads(threads)
    seen = []
    original = api.extract_plane_hierarchy

    def recording(*args, **kw):
        hierarchy = original(*args, **kw)
        seen.append(hierarchy.seconds)
        return hierarchy

    api.extract_plane_hierarchy = recording
    try:
        start, cpu = time.perf_counter(), time.process_time()
        planes = extraction.extract_planes(points, origins=origins, threads=threads, **kwargs)
        total, cpu = time.perf_counter() - start, time.process_time() - cpu
    finally:
        api.extract_plane_hierarchy = original
    return total, seen[0], cpu, planes


def speed_table(repeats: int) -> list[str]:
    from ppe_ros.io import load_scan

    lines = [
        '| scan | setting | threads | extract median s (min) | seeds + greedy median s | CPU s median '
        '| vs 1 tile, same threads | vs 1 tile, 2 threads (before) | 2 threads vs 1 | vs calibration |',
        '|---|---|---:|---:|---:|---:|---:|---:|---:|---:|',
    ]
    for name in SPEED_SCANS:
        scan = load_scan(OUSTER / name)
        runs = {i: [] for i in range(len(CONFIGS))}
        for _, kwargs, threads in CONFIGS:  # warm-up (and JIT of the first call)
            _timed_extraction(scan.points, scan.origins, kwargs, threads)
        for _ in range(repeats):
            for i, (_, kwargs, threads) in enumerate(CONFIGS):
                total, greedy, cpu, _ = _timed_extraction(scan.points, scan.origins, kwargs, threads)
                runs[i].append((total, greedy, cpu))
        median = {i: float(np.median([r[0] for r in v])) for i, v in runs.items()}
        calibration = median[0]
        for i, (label, _, threads) in enumerate(CONFIGS):
            totals = [r[0] for r in runs[i]]
            greedy = float(np.median([r[1] for r in runs[i]]))
            cpu = float(np.median([r[2] for r in runs[i]]))
            same_one_tile = next(j for j, c in enumerate(CONFIGS) if c[0] == 'lidar, 1 tile' and c[2] == threads)
            one_thread = next((j for j, c in enumerate(CONFIGS) if c[0] == label and c[2] == 1), None)
            before = 2
            cells = ['', '', '', '']
            if i:
                cells[0] = f'{median[same_one_tile] / median[i]:.2f}x'
                cells[1] = f'{median[before] / median[i]:.2f}x'
                cells[2] = f'{median[one_thread] / median[i]:.2f}x' if threads == 2 and one_thread is not None else ''
            cells[3] = f'{median[i] / calibration:.2f}'
            lines.append(
                f'| {name.split("_")[0]} {scan.points.shape[0]}x{scan.points.shape[1]} | {label} | {threads} '
                f'| {median[i]:.3f} ({min(totals):.3f}) | {greedy:.3f} | {cpu:.3f} | ' + ' | '.join(cells) + ' |'
            )
    return lines


@numba.njit(cache=True, nogil=True)
def _dependent_arithmetic(steps):
    """A chain of dependent multiply-adds: bound by one core's arithmetic, not by memory."""
    total, x = 0.0, 1.0001
    for _ in range(steps):
        total += x * 1.0000001
        x = x * 0.9999999 + 1e-9
    return total


@numba.njit(cache=True, nogil=True)
def _random_reads(values, steps):
    """Reads of ``values`` at pseudo-random positions (a stride coprime with its length): bound by the
    caches and memory, as the greedy's scattered reads of its plane and queue state are."""
    total, n = 0.0, len(values)
    for i in range(steps):
        total += values[(i * 7919) % n]
    return total


#: (kernel, size of its data in MB, steps): the machine's own two-thread ceiling for that kind of work
SCALING_KERNELS = (
    ('dependent arithmetic (no memory)', 0, 100_000_000),
    ('random reads in 8 MB (the L3 cache)', 8, 20_000_000),
    ('random reads in 64 MB (main memory)', 64, 10_000_000),
)


def _one_and_two(run, repeats: int) -> tuple[float, float]:
    """Median seconds of ``run()`` alone and of the slower of two copies run at once on two threads."""
    import threading

    def timed(seconds: list, slot: int) -> None:
        begin = time.perf_counter()
        run()
        seconds[slot] = time.perf_counter() - begin

    alone, both = [], []
    for _ in range(repeats):
        one, two = [0.0], [0.0, 0.0]
        timed(one, 0)
        helper = threading.Thread(target=timed, args=(two, 1))
        helper.start()
        timed(two, 0)
        helper.join()
        alone.append(one[0])
        both.append(max(two))
    return float(np.median(alone)), float(np.median(both))


def machine_scaling_table(repeats: int) -> list[str]:
    """What a second thread gains on this machine for work bound by arithmetic and by memory: the throughput
    of two copies of a kernel run at once relative to one copy alone (2.00x: two independent cores). The
    extraction's "2 threads vs 1" can only approach the ratio of work like its own (scattered reads)."""
    lines = [
        '| kernel (nogil numba, one copy per thread) | one copy s | two copies at once s '
        '| 2 threads vs 1 (throughput) |',
        '|---|---:|---:|---:|',
    ]
    rng = np.random.default_rng(0)
    for label, megabytes, steps in SCALING_KERNELS:
        if megabytes:
            values = rng.random(megabytes * 2**20 // 8)

            def run(values=values, steps=steps):
                return _random_reads(values, steps)
        else:

            def run(steps=steps):
                return _dependent_arithmetic(steps)

        run()  # compile (or load from the cache) before timing
        alone, both = _one_and_two(run, repeats)
        lines.append(f'| {label} | {alone:.3f} | {both:.3f} | {2 * alone / both:.2f}x |')
    return lines


def accuracy_tables(n_scans: int) -> list[str]:
    from ppe_ros.benchmark.real import count_planes, share_in_large_planes
    from ppe_ros.core.evaluation import score_segmentation
    from ppe_ros.core.extraction import extract_planes
    from ppe_ros.core.synthetic_real import generate_lidar_scan
    from ppe_ros.io import load_scan

    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    lines = [
        '| generated sweep | seed | f % 1 tile | f % tiles | k % 1 tile | k % tiles | planes 1 tile | planes tiles |',
        '|---|---:|---:|---:|---:|---:|---:|---:|',
    ]
    totals = {1: [], 'auto': []}
    for model in ('os1-128', 'os1-32'):
        for seed in range(1000, 1000 + n_scans):
            scan = generate_lidar_scan(seed=seed, model=model)
            row = {}
            for tiles in (1, 'auto'):
                planes = extract_planes(scan.points, origins=scan.origins, sensor='lidar', tiles=tiles)
                score = score_segmentation(planes.labels, scan.labels)
                row[tiles] = (100 * score.f, 100 * score.k, planes.num_planes)
                totals[tiles].append(row[tiles][:2])
            lines.append(
                f'| {model} | {seed} | {row[1][0]:.1f} | {row["auto"][0]:.1f} | {row[1][1]:.1f} | '
                f'{row["auto"][1]:.1f} | {row[1][2]} | {row["auto"][2]} |'
            )
    mean = {t: np.mean(v, axis=0) for t, v in totals.items()}
    lines.append(
        f'| mean | | {mean[1][0]:.1f} | {mean["auto"][0]:.1f} | {mean[1][1]:.1f} | {mean["auto"][1]:.1f} | | |'
    )
    lines += [
        '',
        '| real sweep | planes >= 20, 1 tile / tiles | planes >= 100 | share in planes >= 1000 |',
        '|---|---:|---:|---:|',
    ]
    for path in sorted(OUSTER.glob('*_xyz_m.npy')):
        scan = load_scan(path)
        valid = np.isfinite(scan.points).all(axis=2)
        cells = []
        for tiles in (1, 'auto'):
            labels = extract_planes(scan.points, origins=scan.origins, sensor='lidar', tiles=tiles).labels
            cells.append((count_planes(labels, 20), count_planes(labels, 100), share_in_large_planes(labels, valid)))
        lines.append(
            f'| {path.name.split("_xyz")[0]} | {cells[0][0]} / {cells[1][0]} | {cells[0][1]} / {cells[1][1]} '
            f'| {cells[0][2]:.3f} / {cells[1][2]:.3f} |'
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeats', type=int, default=9, help='alternated timed runs per setting (default 9)')
    parser.add_argument('--accuracy-scans', type=int, default=4, help='generated sweeps per lidar model (default 4)')
    parser.add_argument('--quick', action='store_true', help='3 repeats, 1 generated sweep per model')
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.accuracy_scans < 0:
        parser.error('--repeats must be >= 1 and --accuracy-scans >= 0')
    if not all((OUSTER / name).is_file() for name in SPEED_SCANS):
        print(f'needs the Ouster sweeps {SPEED_SCANS} in {OUSTER}', file=sys.stderr)
        return 1
    repeats, n_scans = (3, 1) if args.quick else (args.repeats, args.accuracy_scans)
    from ppe_ros.benchmark.report import machine_description

    command = 'python benchmarks/bench_tiles.py ' + ' '.join(argv if argv is not None else sys.argv[1:])
    print(
        f'machine: {machine_description()}; numba threads available: {numba.config.NUMBA_NUM_THREADS}; '
        f'command: {command.strip()}; {time.strftime("%Y-%m-%d %H:%M")}\n'
    )
    for line in machine_scaling_table(repeats):
        print(line, flush=True)
    print()
    for line in speed_table(repeats):
        print(line, flush=True)
    if n_scans:
        print()
        for line in accuracy_tables(n_scans):
            print(line, flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
