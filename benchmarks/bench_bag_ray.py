"""Throughput of ``process_bag`` over several bags: ``--executor local --jobs 2`` against ``--executor ray``.

The bags (mcap, in a temporary directory) hold the three consecutive OS-1-128 sweeps of
``../shared/data/ouster`` repeated, in the Ouster driver's 48-byte point layout (as
``bench_bag.py``). The runs alternate, local then Ray, ``--repeat`` times, on the same bags: local
is the whole command (worker pool start included); Ray runs on a local Ray of two CPUs started
once before (its start is printed apart, as a cluster would be up already), the first Ray run
starting its workers. Outputs of every run are checked byte for byte against the first local run.

    .venv/bin/python benchmarks/bench_bag_ray.py [--bags 3] [--frames 8] [--task-frames 4] [--repeat 2]

Prints the machine, the command and a markdown table: per run, wall time, frames/s, the ratio to
the mean local rate, and the median seconds a frame takes inside its worker; then the per-frame
input and output sizes that bound scaling over nodes.
"""

from __future__ import annotations

import argparse
import filecmp
import os
import platform
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

from bench_bag import SHARED, write_input

from ppe_ros.ros.bag import BagOptions, process_bags
from ppe_ros.ros.messages import rosbags_message_types
from ppe_ros.ros.processing import ExtractorParams, process_cloud

REPO = Path(__file__).resolve().parents[1]


def machine() -> str:
    """CPU model, cores available, memory and load: the machine line of the table."""
    model = platform.processor() or platform.machine()
    with open('/proc/cpuinfo') as handle:  # Linux
        names = [line.split(':', 1)[1].strip() for line in handle if line.startswith('model name')]
    model = names[0] if names else model
    cores = len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else os.cpu_count()
    memory = os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2**30
    return f'{model}, {cores} cores, {memory:.0f} GiB, Python {platform.python_version()}'


def commit() -> str:
    result = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], capture_output=True, text=True, cwd=REPO)
    return result.stdout.strip() or 'unknown'


def run(inputs: list[Path], out: Path, params: ExtractorParams, executor: str, task_frames: int) -> tuple:
    """One run over all bags: (report of the run, median s/frame in the workers)."""
    runs = [
        BagOptions(
            source, out / source.name, params=params, jobs=2, executor=executor, progress=False, task_frames=task_frames
        )
        for source in inputs
    ]
    bags = process_bags(runs, log=lambda text: None, output_directory=out)
    if bags.exit_code != 0:
        raise SystemExit(f'{executor}: exit code {bags.exit_code}: {[r.worker_error or r.error for r in bags.reports]}')
    seconds = [s for report in bags.reports for topic in report.topics.values() for s in topic.seconds]
    return bags, statistics.median(seconds)


def same_outputs(a: Path, b: Path) -> bool:
    return all(filecmp.cmp(x, b / x.relative_to(a), shallow=False) for x in a.rglob('*') if x.is_file())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--bags', type=int, default=3, help='input bags (default 3)')
    parser.add_argument('--frames', type=int, default=8, help='clouds per bag (default 8)')
    parser.add_argument('--task-frames', type=int, default=4, help='frames per Ray task (default 4)')
    parser.add_argument('--repeat', type=int, default=2, help='local/Ray pairs of runs (default 2)')
    args = parser.parse_args(argv)
    if not (SHARED / 'ouster').is_dir():
        print(f'needs the Ouster sweeps in {SHARED / "ouster"} (set PPE_SHARED_DATA)', file=sys.stderr)
        return 2
    import ray

    params = ExtractorParams()
    rows = []
    with tempfile.TemporaryDirectory(prefix='bench_bag_ray_') as tmp:
        folder = Path(tmp)
        inputs = [folder / 'in' / f'bag{i}' for i in range(args.bags)]
        for path in inputs:
            messages = write_input(path, args.frames)
        warm = process_cloud(messages[0], params, rosbags_message_types())  # numba's cache, in this process
        print(f'warm-up frame: {warm.planes.num_planes} planes', file=sys.stderr)
        start = time.perf_counter()
        os.environ.setdefault('RAY_USAGE_STATS_ENABLED', '0')
        ray.init(
            num_cpus=2,
            include_dashboard=False,
            _node_ip_address='127.0.0.1',
            log_to_driver=False,
            configure_logging=False,
        )
        ray_start = time.perf_counter() - start
        try:
            for repeat in range(args.repeat):
                for executor in ('local', 'ray'):
                    out = folder / f'out_{executor}_{repeat}'
                    bags, median = run(inputs, out, params, executor, args.task_frames)
                    if not same_outputs(folder / 'out_local_0', out):
                        raise SystemExit(f'{out.name}: outputs differ from the first local run')
                    frames = sum(r.frames_processed for r in bags.reports)
                    label = (
                        'local --jobs 2'
                        if executor == 'local'
                        else f'ray, 2 workers, {args.task_frames} frames/task'
                        + (' (workers starting)' if repeat == 0 else '')
                    )
                    rows.append((label, executor, frames, bags.wall_seconds, frames / bags.wall_seconds, median))
        finally:
            ray.shutdown()
        in_bytes = sum(f.stat().st_size for path in inputs for f in path.glob('*.mcap'))
        out_bytes = sum(f.stat().st_size for f in (folder / 'out_local_0').rglob('*.mcap'))
    frames_total = args.bags * args.frames
    local_rate = statistics.mean(rate for _, executor, _, _, rate, _ in rows if executor == 'local')
    print(f'process_bag over {args.bags} bags of {args.frames} Ouster OS-1-128 clouds (128 x 1024, 48-byte points)')
    print(
        f'machine: {machine()}; load average {os.getloadavg()[0]:.1f} at the end; '
        f'{datetime.now(UTC):%Y-%m-%d %H:%M} UTC, commit {commit()}'
    )
    print(f'command: {" ".join(shlex.quote(a) for a in [sys.executable, *sys.argv])}')
    print(
        f'local Ray (2 CPUs, 127.0.0.1) started in {ray_start:.1f} s, before the runs; every output byte-identical '
        'to the first local run'
    )
    print()
    print('| run | frames | wall s | frames/s | vs local | s/frame in worker (median) |')
    print('|---|---:|---:|---:|---:|---:|')
    for label, _, frames, wall, rate, median in rows:
        print(f'| {label} | {frames} | {wall:.2f} | {rate:.2f} | {rate / local_rate:.2f} | {median:.3f} |')
    print()
    print(
        f'per frame: {in_bytes / frames_total / 1e6:.2f} MB in (mcap), {out_bytes / frames_total / 1e6:.2f} MB out '
        '(labelled cloud, markers, plane table)'
    )
    return 0


if __name__ == '__main__':
    sys.exit(main())
