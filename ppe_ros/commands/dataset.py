"""``ppe dataset make DIR``: write a SynPEB-style benchmark data set (train/test x radial noise level)."""

from __future__ import annotations

import argparse
import sys

from ppe_ros.benchmark.dataset import (
    DEFAULT_ANGULAR_SIGMA_DEG,
    DEFAULT_N_OBJECTS,
    DEFAULT_SIGMAS,
    DEFAULT_TEST,
    DEFAULT_TRAIN,
    make_dataset,
)


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f'not an integer: {text!r}') from exc
    if value < 0:
        raise argparse.ArgumentTypeError(f'must be >= 0: {text!r}')
    return value


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        'dataset',
        help='make a SynPEB-style benchmark data set',
        description='Benchmark data sets: generated room scans in SynPEB format (PCD x y z intensity, label in '
        'intensity >= 10), train and test splits per radial noise level.',
    )
    actions = parser.add_subparsers(dest='dataset_action', metavar='ACTION', required=True)
    make = actions.add_parser(
        'make',
        help='generate a data set into a new directory',
        description='Generate DIR/{train,test}/sigma_<mm>mm/pc_NN.pcd and DIR/dataset.json. Default: SynPEB\'s '
        'size and levels (500 x 500 grid, 10 train + 30 test scans at sigma = 0, 7.1, 10, 14.1, 20 mm, angular '
        'noise 1 mdeg, about 40 planes per scan), deterministic in --seed. Takes about 1 s per scan.',
    )
    make.add_argument('directory', help='output directory (must not hold a data set yet)')
    make.add_argument('--seed', type=_non_negative_int, default=0, help='random seed (default 0)')
    make.add_argument('--noise', type=float, nargs='+', default=None, metavar='MM',
                      help='radial noise sigmas in mm (default: ' +
                      ' '.join(f'{s * 1000:.1f}' for s in DEFAULT_SIGMAS) + ')')
    make.add_argument('--train', type=_non_negative_int, default=DEFAULT_TRAIN,
                      help=f'train scans per level (default {DEFAULT_TRAIN})')
    make.add_argument('--test', type=_non_negative_int, default=DEFAULT_TEST,
                      help=f'test scans per level (default {DEFAULT_TEST})')
    make.add_argument('--scans', type=_non_negative_int, default=None,
                      help='shorthand: this many train and this many test scans per level')
    make.add_argument('--rows', type=int, default=500, help='grid rows (default 500)')
    make.add_argument('--cols', type=int, default=500, help='grid columns (default 500)')
    make.add_argument('--angular-noise', type=float, default=DEFAULT_ANGULAR_SIGMA_DEG * 1000.0, metavar='MDEG',
                      help='beam-direction jitter in millidegrees (default 1)')
    make.add_argument('--objects', type=_non_negative_int, default=DEFAULT_N_OBJECTS,
                      help=f'objects per room (default {DEFAULT_N_OBJECTS})')
    make.add_argument('--uncompressed', action='store_true', help='write DATA binary instead of binary_compressed')
    make.add_argument('--quiet', action='store_true', help='no progress bar')
    make.set_defaults(func=run_make)


def run_make(args: argparse.Namespace) -> int:
    sigmas = DEFAULT_SIGMAS if args.noise is None else tuple(v / 1000.0 for v in args.noise)
    n_train, n_test = (args.scans, args.scans) if args.scans is not None else (args.train, args.test)
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(total=(n_train + n_test) * len(sigmas), unit='scan', file=sys.stderr, desc='ppe dataset make')
    try:
        manifest = make_dataset(
            args.directory, seed=args.seed, sigmas=sigmas, n_train=n_train, n_test=n_test, rows=args.rows,
            cols=args.cols, angular_sigma_deg=args.angular_noise / 1000.0, n_objects=args.objects,
            compressed=not args.uncompressed, progress=(lambda done, total: bar.update(1)) if bar else None,
        )
    finally:
        if bar is not None:
            bar.close()
    scans = manifest['scans']
    planes = [s['n_planes'] for s in scans]
    levels = ', '.join(f"{lv['name']}" for lv in manifest['levels'])
    print(f'{args.directory}: {len(scans)} scans ({n_train} train + {n_test} test per level; levels {levels}), '
          f"{manifest['rows']} x {manifest['cols']} grid, {sum(planes) / max(len(planes), 1):.1f} planes per scan")
    return 0
