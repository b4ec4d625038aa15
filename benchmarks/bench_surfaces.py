"""Stages of extract_planes with a sensor profile: the greedy, the whole-surface pass and the other overheads.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_surfaces.py [--repeats 9] [--scans 'OS-1-128 1795' ...]
        [--trees /work/main $PWD]

``extract_planes(points, origins=..., sensor=<the scan's kind>)`` on real scans of ../shared/data
(ppe_ros.benchmark.real.REAL_SCANS; default the OS-1-128 sweep 1795, 128 x 1024), with every stage timed by
wrapping the module-level functions it calls (time.perf_counter, inclusive: a stage's time contains the
stages it calls, e.g. ``_consolidate`` its ``columns_wrap``). Stages a tree does not have
are left blank. Times are medians over the repeats after one warm-up call (which also compiles the
kernels), wall time and CPU time (time.process_time, all threads: the work, which the machine's other load
changes less than the wall time); "whole_surfaces" is the serial pass after the greedy, "hierarchy" the ray
scan, noise scaling,
edge masks, seeds and greedy, "seeds + greedy" the hierarchy's own timer (PlaneHierarchy.seconds).

``--trees A B ...``: one worker process per source tree (PYTHONPATH=tree), the repeats alternated between
them (A, B, A, B, ...) so that the machine's load hits all alike; the last columns are each tree's median
relative to the first tree's (> 1: faster than the first).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get('PPE_SHARED_DATA', REPO.parent / 'shared' / 'data'))
DEFAULT_SCANS = ('OS-1-128 1795',)
#: (module attribute path, stage name) of the functions timed; module 'extract' is extract_planes's own module.
TIMED = (
    ('sensor:SensorProfile.noise_for', 'noise_for (noise scale)'),
    ('extract:extract_plane_hierarchy', 'hierarchy'),
    ('extract:make_ray_scan', '  make_ray_scan'),
    ('extract:_noise_scaled', '  _noise_scaled'),
    ('extract:whole_surfaces', 'whole_surfaces'),
    ('extract:PlaneHierarchy.plane_ids_for_error', '  plane ids at e (replay of the runs)'),
    ('surfaces:_consolidate', '  _consolidate'),
    ('surfaces:columns_wrap', '    columns_wrap'),
    ('surfaces:rows_wrap', '    rows_wrap'),
    ('surfaces:consolidated_surfaces', '    consolidated_surfaces'),
    ('consolidation:_dense_moments_kernel', '      piece moments'),
    ('consolidation:_unique_candidate_pairs', '      candidate pairs'),
    ('consolidation:_merge_pieces', '      merge loop (pair costs + heap)'),
    ('consolidation:_join_large_surfaces', '      large surfaces'),
    ('consolidation:_surface_moments_kernel', '      surface moments'),
    ('consolidation:_absorb_kernel', '      absorption'),
    ('surfaces:consolidate_pieces', '    consolidate_pieces'),
    ('surfaces:absorb_rays', '    absorb_rays'),
    ('surfaces:join_at_boundaries', '    join_at_boundaries (boundary round)'),
    ('surfaces:fit_pixel_groups_with_members', '  plane fits (fit_pixel_groups_with_members)'),
    ('surfaces:_drop_non_planar', '  _drop_non_planar'),
    ('surfaces:_plane_sums', '    _plane_sums (all calls)'),
    ('surfaces:_independent_sigmas', '  _independent_sigmas'),
    ('surfaces:systematic_covariances', '  systematic_covariances'),
)
SEEDS_GREEDY = 'seeds + greedy'
#: Key prefix of a stage's CPU time (time.process_time: every thread of the process).
CPU = 'cpu:'
TOTAL = 'extract_planes'


class _Timers:
    """Wraps the TIMED functions of the imported package; ``sums`` holds their seconds since reset()."""

    def __init__(self) -> None:
        import importlib

        from ppe_ros.core import extraction

        extract_module = sys.modules[extraction.extract_planes.__module__]
        self.extract_planes = extract_module.extract_planes
        modules = {
            'extract': extract_module,
            'sensor': importlib.import_module('ppe_ros.core.sensor'),
            'surfaces': importlib.import_module('ppe_ros.core.surfaces'),
            'consolidation': importlib.import_module('ppe_ros.core.consolidation'),
        }
        self.sums: dict[str, float] = {}
        self.names: list[str] = []
        for spec, name in TIMED:
            module_key, attribute = spec.split(':')
            owner = modules[module_key]
            *path, leaf = attribute.split('.')
            for part in path:
                owner = getattr(owner, part, None)
            if owner is None or not hasattr(owner, leaf):
                continue
            setattr(owner, leaf, self._wrapped(getattr(owner, leaf), name, isinstance(owner, type)))
            self.names.append(name)

    def _wrapped(self, function, name: str, method: bool):
        sums = self.sums

        def timed(*args, **kwargs):
            start, cpu = time.perf_counter(), time.process_time()
            try:
                return function(*args, **kwargs)
            finally:
                sums[name] = sums.get(name, 0.0) + time.perf_counter() - start
                sums[CPU + name] = sums.get(CPU + name, 0.0) + time.process_time() - cpu

        timed.__wrapped__ = function
        return timed

    def run(self, points, origins, sensor: str) -> dict[str, float]:
        """Seconds of every stage of one extract_planes call."""
        self.sums.clear()
        seconds = []
        original = sys.modules[self.extract_planes.__module__].extract_plane_hierarchy

        def recording(*args, **kwargs):
            hierarchy = original(*args, **kwargs)
            seconds.append(hierarchy.seconds)
            return hierarchy

        module = sys.modules[self.extract_planes.__module__]
        module.extract_plane_hierarchy = recording
        try:
            start, cpu = time.perf_counter(), time.process_time()
            self.extract_planes(points, origins=origins, sensor=sensor)
            total, cpu = time.perf_counter() - start, time.process_time() - cpu
        finally:
            module.extract_plane_hierarchy = original
        return {**self.sums, SEEDS_GREEDY: float(sum(seconds)), TOTAL: total, CPU + TOTAL: cpu}


def _load(names: list[str]) -> list[tuple]:
    from ppe_ros.benchmark.real import REAL_SCANS
    from ppe_ros.io import load_scan

    specs = {spec.name: spec for spec in REAL_SCANS}
    out = []
    for name in names:
        spec = specs[name]
        scan = load_scan(SHARED / spec.path, units=spec.units)
        out.append((name, scan.points, scan.origins, spec.kind))
    return out


def _worker() -> int:
    """Serve one tree: reads a JSON list of scan names, then 'run' lines; answers one JSON line each."""
    scans = _load(json.loads(sys.stdin.readline()))
    timers = _Timers()
    for points, origins, kind in ((s[1], s[2], s[3]) for s in scans):  # warm-up and JIT
        timers.run(points, origins, kind)
    print(json.dumps({'names': [TOTAL, SEEDS_GREEDY, *timers.names]}), flush=True)
    for line in sys.stdin:
        if line.strip() != 'run':
            break
        print(json.dumps([timers.run(s[1], s[2], s[3]) for s in scans]), flush=True)
    return 0


def _table(scans: list[str], trees: list[str], names: list[str], runs: dict) -> list[str]:
    """Markdown table: stage, each tree's median wall time (min) and median CPU time, and the first
    tree's medians divided by each other tree's (wall, CPU)."""
    head = '| scan | stage | ' + ' | '.join(f'{Path(t).name} wall median s (min) | CPU median s' for t in trees)
    head += ''.join(f' | {Path(trees[0]).name} / {Path(t).name} wall, CPU' for t in trees[1:]) + ' |'
    lines = [head, '|---|---|' + '---:|' * (3 * len(trees) - 1)]
    for s, scan in enumerate(scans):
        for name in names:
            cells, medians = [], []
            for tree in trees:
                walls = [run[s][name] for run in runs[tree] if name in run[s]]
                cpus = [run[s][CPU + name] for run in runs[tree] if CPU + name in run[s]]
                if walls:
                    medians.append((float(np.median(walls)), float(np.median(cpus)) if cpus else np.nan))
                    cpu_cell = f'{medians[-1][1]:.4f}' if cpus else ''
                    cells.append(f'{medians[-1][0]:.4f} ({min(walls):.4f}) | {cpu_cell}')
                else:
                    medians.append(None)
                    cells.append(' | ')
            for m in medians[1:]:
                ok = m is not None and medians[0] is not None and m[0] > 0
                cpu_ratio = f', {medians[0][1] / m[1]:.2f}x' if ok and m[1] > 0 else ''
                cells.append(f'{medians[0][0] / m[0]:.2f}x{cpu_ratio}' if ok else '')
            lines.append(f'| {scan} | {name} | ' + ' | '.join(cells) + ' |')
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeats', type=int, default=9, help='timed runs per tree (default 9)')
    parser.add_argument('--scans', nargs='+', default=list(DEFAULT_SCANS), help='REAL_SCANS names')
    parser.add_argument('--trees', nargs='+', default=[str(REPO)], help='source trees, alternated (default this)')
    parser.add_argument('--worker', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return _worker()
    if args.repeats < 1:
        parser.error('--repeats must be >= 1')
    from ppe_ros.benchmark.real import REAL_SCANS
    from ppe_ros.benchmark.report import machine_description

    known = {spec.name: spec for spec in REAL_SCANS}
    unknown = [name for name in args.scans if name not in known]
    if unknown:
        parser.error(f'unknown scans {unknown}; known: {sorted(known)}')
    missing = [name for name in args.scans if not (SHARED / known[name].path).is_file()]
    if missing:
        print(f'needs the scans {missing} in {SHARED}', file=sys.stderr)
        return 1
    workers = {}
    for tree in args.trees:
        env = {**os.environ, 'PYTHONPATH': str(Path(tree).resolve())}
        worker = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), '--worker'],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env=env,
            cwd=tree,
        )
        worker.stdin.write(json.dumps(args.scans) + '\n')
        worker.stdin.flush()
        workers[tree] = worker
    names: list[str] = []
    for worker in workers.values():  # after every worker's warm-up
        for name in json.loads(worker.stdout.readline())['names']:
            if name not in names:
                names.append(name)
    order = [TOTAL, SEEDS_GREEDY] + [name for _, name in TIMED if name in names]
    runs = {tree: [] for tree in args.trees}
    for _ in range(args.repeats):
        for tree, worker in workers.items():
            worker.stdin.write('run\n')
            worker.stdin.flush()
            runs[tree].append(json.loads(worker.stdout.readline()))
    for worker in workers.values():
        worker.stdin.close()
        worker.wait()
    import numba

    command = 'python benchmarks/bench_surfaces.py ' + ' '.join(argv if argv is not None else sys.argv[1:])
    print(
        f'machine: {machine_description()}; numba threads: {numba.config.NUMBA_NUM_THREADS}; '
        f'load average at the end: {os.getloadavg()[0]:.2f}; command: {command.strip()}; '
        f'{time.strftime("%Y-%m-%d %H:%M")}\n'
    )
    for line in _table(args.scans, args.trees, order, runs):
        print(line)
    return 0


if __name__ == '__main__':
    sys.exit(main())
