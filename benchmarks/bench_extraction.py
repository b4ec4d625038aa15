"""Speed and memory of PPE extraction: prints a markdown table.

    .venv/bin/python benchmarks/bench_extraction.py [--repeats 5] [--quick]

Rows: the SynPEB scan pc_01 (500 x 500, lmax 0.18 m, e 0.0484 m^2), real Ouster sweeps (128 x 1024
and 32 x 1024, with their beam origins) at those parameters and at the extractor node's defaults
(lmax inf, e 0.01 m^2), a scaling series of generated scans (125^2 .. 1000^2) and the first-call JIT
compile time (a fresh process with an empty numba cache). Each row runs in its own subprocess so
that peak memory (ru_maxrss) is that row's; one untimed subprocess first fills the numba cache, so
that no row's first call or peak memory includes compilation. Times are medians after a warm-up
call (numba cache on). A second table gives each row's time and the greedy's work per action (its
counters, PlaneHierarchy.stats): work that stays flat while the time per action grows is the memory
hierarchy, not the algorithm. Needs ../shared/data for the real-scan rows (skipped with a note
otherwise).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ppe_ros.benchmark.report import machine_description
from ppe_ros.core.sensor import PROFILES
from ppe_ros.ros.processing import PARAM_SPEC_BY_NAME

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / 'shared' / 'data'
E_SYNPEB = 0.0484
LMAX_SYNPEB = 0.18
# the extractor node's defaults: its sensor parameter's profile (its e and lmax parameters default to 0 = the profile's)
NODE_PROFILE = PROFILES[str(PARAM_SPEC_BY_NAME['sensor'].default)]
NODE_LMAX = float(NODE_PROFILE.max_neighbor_distance)
NODE_E = float(NODE_PROFILE.max_error_increment)

WORKER = r"""
import json, resource, sys, time
import numpy as np
spec = json.loads(sys.argv[1])
from ppe_ros.core.extraction import extract_plane_hierarchy
if spec['kind'] == 'file':
    from ppe_ros.io import load_scan
    scan = load_scan(spec['path'])
    points, origins = scan.points, scan.origins
else:
    from ppe_ros.core.synthetic import ScanGrid, generate_scan
    n = spec['size']
    grid = ScanGrid.uniform(n, n, azimuth_fov_deg=69.86, elevation_fov_deg=60.0)
    s = generate_scan(seed=0, grid=grid, radial_sigma=0.02)
    points, origins = s.points, s.origins
def run():
    start = time.perf_counter()
    h = extract_plane_hierarchy(points, origins=origins, max_neighbor_distance=spec['lmax'],
                                max_error_increment=spec['e'])
    planes = h.cut(max_error_increment=spec['e'])
    return time.perf_counter() - start, planes.num_planes, len(h.actions), h.stats
first = time.perf_counter(); run(); first = time.perf_counter() - first
times = []
for _ in range(spec['repeats']):
    t, n_planes, n_actions, stats = run()
    times.append(t)
print(json.dumps({'first_call': first, 'median': float(np.median(times)), 'min': float(min(times)),
                  'planes': n_planes, 'actions': n_actions, 'stats': stats, 'shape': list(points.shape[:2]),
                  'valid': float(np.isfinite(points).all(axis=2).mean()),
                  'peak_mb': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def run_row(spec: dict, env: dict | None = None) -> dict:
    result = subprocess.run(
        [sys.executable, '-c', WORKER, json.dumps(spec)],
        capture_output=True,
        text=True,
        cwd=REPO,
        env=env,
        timeout=3600,
    )
    if result.returncode != 0:
        raise RuntimeError(f'benchmark row {spec} failed:\n{result.stderr[-2000:]}')
    return json.loads(result.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeats', type=int, default=5)
    parser.add_argument('--quick', action='store_true', help='fewer rows (no 1000^2, no compile row)')
    args = parser.parse_args(argv)
    rows: list[tuple[str, dict]] = []
    ouster = SHARED / 'ouster'
    if SHARED.is_dir():
        rows.append(
            (
                'SynPEB pc_01, 500x500',
                {'kind': 'file', 'path': str(SHARED / 'synpeb' / 'pc_01.pcd'), 'lmax': LMAX_SYNPEB, 'e': E_SYNPEB},
            )
        )
        rows.append(
            (
                'Ouster OS-1-128, 128x1024',
                {
                    'kind': 'file',
                    'path': str(ouster / 'OS-1-128_v2.3.0_1024x10_lb_n3_frame1796_xyz_m.npy'),
                    'lmax': LMAX_SYNPEB,
                    'e': E_SYNPEB,
                },
            )
        )
        rows.append(
            (
                'Ouster OS-1-32, 32x1024',
                {
                    'kind': 'file',
                    'path': str(ouster / 'OS-1-32-G_v2.1.1_1024x10_frame638_xyz_m.npy'),
                    'lmax': LMAX_SYNPEB,
                    'e': E_SYNPEB,
                },
            )
        )
        for name, spec in rows[1:3]:  # the extractor node's defaults: no distance limit, e 0.01 m^2
            rows.append((name, dict(spec, lmax=NODE_LMAX, e=NODE_E)))
    else:
        print(f'note: {SHARED} not found: real-scan rows skipped', file=sys.stderr)
    sizes = (125, 250, 500) if args.quick else (125, 250, 500, 1000)
    for n in sizes:
        rows.append((f'generated room, {n}x{n}', {'kind': 'generated', 'size': n, 'lmax': LMAX_SYNPEB, 'e': E_SYNPEB}))
    print(
        f'machine: {machine_description()}; command: python benchmarks/bench_extraction.py --repeats {args.repeats}'
        f'{" --quick" if args.quick else ""}; {time.strftime("%Y-%m-%d")}\n'
    )
    warm = time.perf_counter()
    run_row({'kind': 'generated', 'size': 16, 'lmax': LMAX_SYNPEB, 'e': E_SYNPEB, 'repeats': 1})
    print(f'(numba cache checked and filled in an untimed process: {time.perf_counter() - warm:.1f} s)\n')
    print('| input | lmax m | e m² | valid | planes | actions | median s | min s | first call s | peak MB |')
    print('|---|---|---|---|---|---|---|---|---|---|')
    results = []
    for name, spec in rows:
        spec['repeats'] = args.repeats
        r = run_row(spec)
        name = (
            f'{name} ({"node defaults" if spec["lmax"] == NODE_LMAX else "SynPEB parameters"})'
            if spec['kind'] == 'file' and 'Ouster' in name
            else name
        )
        results.append((name, r))
        print(
            f'| {name} | {spec["lmax"]:g} | {spec["e"]:g} | {r["valid"]:.0%} | {r["planes"]} | {r["actions"]} | '
            f'{r["median"]:.3f} | {r["min"]:.3f} | {r["first_call"]:.2f} | {r["peak_mb"]:.0f} |',
            flush=True,
        )
    print("\nper action (median time / actions; the greedy's counters / actions):\n")
    print(
        '| input | µs | heap pops | merge valuations | merge refinements | refinement rays | new candidates '
        '| re-linearisation rays |'
    )
    print('|---|---|---|---|---|---|---|---|')
    for name, r in results:
        per = {key: value / max(r['actions'], 1) for key, value in r['stats'].items()}
        print(
            f'| {name} | {1e6 * r["median"] / max(r["actions"], 1):.2f} | {per["heap_pops"]:.2f} | '
            f'{per["merge_evaluations"]:.2f} | {per["merge_refinements"]:.2f} | {per["merge_refinement_rays"]:.2f} | '
            f'{per["new_candidates"]:.2f} | {per["relinearisation_rays"]:.2f} |'
        )
    if not args.quick:
        with tempfile.TemporaryDirectory() as cache:
            env = dict(os.environ, NUMBA_CACHE_DIR=cache)
            spec = {'kind': 'generated', 'size': 125, 'lmax': LMAX_SYNPEB, 'e': E_SYNPEB, 'repeats': 1}
            r = run_row(spec, env)
        print(
            f'\nfirst call with an empty numba cache (JIT compilation + one 125x125 run): {r["first_call"]:.1f} s; '
            f"the same call with a warm cache: see the 125x125 row's first-call column"
        )
    return 0


if __name__ == '__main__':
    sys.exit(main())
