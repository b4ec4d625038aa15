"""``ppe tune DATASET``: grid search of PPE's lmax x e on the train split; writes the best as a params YAML."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from ppe_ros.benchmark.dataset import MANIFEST_NAME, iter_scans
from ppe_ros.benchmark.methods import ERROR_GRID
from ppe_ros.benchmark.tuning import COARSE_LMAX_GRID, FULL_LMAX_GRID, params_yaml, tune_ppe
from ppe_ros.commands._options import positive_float
from ppe_ros.io.files import refuse_overwriting_inputs, write_file_atomically

DEFAULT_NOISE_MM = 14.1
DEFAULT_OUT = 'ppe_tuned.yaml'


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        'tune',
        help='tune PPE (lmax x e) on the train split of a data set',
        description="Grid search of PPE's lmax (m) x e (m^2) on the train split of a data set made by `ppe dataset "
        "make`, maximising the mean f over the scans (as the reference's trainppe.m). One PPE run per (scan, lmax) "
        'gives every e. The default grid is coarse (lmax = 0.06, 0.12, 0.18 m x the 50 e = (0.02:0.02:1)^2, '
        "3 runs per scan); --grid full is the reference's (lmax = 0.02:0.02:0.2 m, 10 runs per scan, about 10 "
        'minutes for 10 scans of 500 x 500). Writes the best parameters as a ROS 2 params file of the extractor node '
        '(also read by `ppe eval --params`).',
    )
    parser.add_argument('dataset', help='data set directory (with dataset.json)')
    parser.add_argument(
        '--noise',
        type=float,
        default=DEFAULT_NOISE_MM,
        metavar='MM',
        help=f"radial noise level in mm to tune on (default {DEFAULT_NOISE_MM}, the paper's level)",
    )
    parser.add_argument('--split', choices=('train', 'test'), default='train', help='split to tune on (default train)')
    parser.add_argument('--grid', choices=('coarse', 'full'), default='coarse', help='lmax grid (default coarse)')
    parser.add_argument(
        '--lmax',
        type=positive_float,
        nargs='+',
        default=None,
        metavar='M',
        help='explicit lmax values in m (overrides --grid)',
    )
    parser.add_argument(
        '--sqrt-e',
        type=positive_float,
        nargs='+',
        default=None,
        metavar='M',
        help='explicit sqrt(e) values in m (default 0.02:0.02:1)',
    )
    parser.add_argument('--max-scans', type=int, default=None, metavar='N', help='use at most N scans')
    parser.add_argument('-o', '--out', default=DEFAULT_OUT, help=f'params YAML to write (default {DEFAULT_OUT})')
    parser.add_argument('--force', action='store_true', help='replace an existing output file')
    parser.add_argument('--quiet', action='store_true', help='no progress bar')
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ppe_ros.benchmark.runner import dataset_scans

    out = Path(args.out)
    if args.max_scans is not None and args.max_scans < 1:
        raise ValueError(f'--max-scans must be >= 1; got {args.max_scans}')
    dataset_files = [Path(args.dataset) / MANIFEST_NAME]
    dataset_files += [
        entry.path
        for entry in iter_scans(args.dataset, split=args.split, noise_mm=[args.noise], max_scans=args.max_scans)
    ]
    refuse_overwriting_inputs([out], dataset_files)
    if (out.exists() or out.is_symlink()) and not args.force:
        raise FileExistsError(f'{out} exists (use --force to replace it)')
    lmax_grid = tuple(args.lmax) if args.lmax else (FULL_LMAX_GRID if args.grid == 'full' else COARSE_LMAX_GRID)
    error_grid = tuple(v * v for v in args.sqrt_e) if args.sqrt_e else ERROR_GRID
    scans = dataset_scans(args.dataset, split=args.split, noise_mm=[args.noise], max_scans=args.max_scans)
    if not scans:
        raise ValueError(f'no {args.split} scans at {args.noise:g} mm in {args.dataset}')
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(total=len(scans) * len(lmax_grid), unit='run', file=sys.stderr, desc='ppe tune')
    try:
        result = tune_ppe(
            [load for _, load in scans],
            lmax_grid=lmax_grid,
            error_grid=error_grid,
            progress=(lambda text: (bar.set_postfix_str(text), bar.update(1))) if bar else None,
        )
    finally:
        if bar is not None:
            bar.close()

    print(f'mean f over {result.n_scans} {args.split} scans at {args.noise:g} mm (rows lmax m, columns sqrt(e) m):')
    shown = list(range(0, len(result.error_grid), max(1, len(result.error_grid) // 10)))
    if result.best_index[1] not in shown:
        shown = sorted({*shown, result.best_index[1]})
    print('lmax   ' + ' '.join(f'{math.sqrt(result.error_grid[j]):6.2f}' for j in shown))
    for i, lmax in enumerate(result.lmax_grid):
        print(f'{lmax:5.2f}  ' + ' '.join(f'{result.scores[i, j] * 100:6.1f}' for j in shown))
    best_lmax, best_e = result.best_lmax, result.best_error
    row = result.scores[result.best_index[0]]
    flat = [math.sqrt(result.error_grid[j]) for j in np.flatnonzero(row >= result.best_score - 0.01)]
    print(
        f'best: lmax = {best_lmax:g} m, e = {best_e:.6g} m^2 (sqrt(e) = {math.sqrt(best_e):.2f} m), mean f = '
        f'{result.best_score * 100:.1f} %; within 1 point of it at this lmax: sqrt(e) = {min(flat):.2f}..'
        f'{max(flat):.2f} m ({result.seconds:.0f} s)'
    )
    comments = [
        f'PPE parameters tuned by `ppe tune` on {result.n_scans} {args.split} scans of {args.dataset} at radial sigma '
        f'{args.noise:g} mm:',
        f'mean f = {result.best_score * 100:.1f} % (grid lmax {", ".join(f"{v:g}" for v in result.lmax_grid)} m x '
        f'{len(result.error_grid)} e values).',
        f'Use: ros2 run ppe_ros extractor --ros-args --params-file {out.name}   or   ppe eval DATASET --params '
        f'{out.name}',
    ]
    text = params_yaml(best_lmax, best_e, comments=comments).encode('utf-8')
    write_file_atomically(out, lambda stream: stream.write(text), overwrite=args.force)
    print(f'wrote {out}')
    return 0
