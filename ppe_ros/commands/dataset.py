"""``ppe dataset make DIR``: write a benchmark data set (train/test x level): SynPEB-style rooms, or
realistic lidar streets / depth-camera rooms (``--kind``)."""

from __future__ import annotations

import argparse
import sys

from ppe_ros.benchmark.dataset import (
    DATASET_KINDS,
    DEFAULT_ANGULAR_SIGMA_DEG,
    DEFAULT_LIDAR_MODELS,
    DEFAULT_N_OBJECTS,
    DEFAULT_SIGMAS,
    DEFAULT_TEST,
    DEFAULT_TRAIN,
    SENSOR_SEED_SPLITS,
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
        description="Generate DIR/{train,test}/sigma_<mm>mm/pc_NN.pcd and DIR/dataset.json. Default: SynPEB's "
        'size and levels (500 x 500 grid, 10 train + 30 test scans at sigma = 0, 7.1, 10, 14.1, 20 mm, angular '
        'noise 1 mdeg, about 40 planes per scan), deterministic in --seed. Takes about 1 s per scan.',
    )
    make.add_argument('directory', help='output directory (must not hold a data set yet)')
    train_seeds, test_seeds = SENSOR_SEED_SPLITS['train'], SENSOR_SEED_SPLITS['test']
    make.add_argument(
        '--kind',
        choices=DATASET_KINDS,
        default='synpeb',
        help='synpeb (default): SynPEB-style rooms as PCD; lidar: OS-1 sweeps of streets with real '
        'lidar errors; depth_camera: Kinect-v1-like frames of rooms with its errors (both as .npy '
        f'points + _labels.npy; scene seeds {train_seeds[0]}-{train_seeds[1] - 1} for train, '
        f'{test_seeds[0]}-{test_seeds[1] - 1} held out for test)',
    )
    make.add_argument(
        '--lidar-models',
        nargs='+',
        default=list(DEFAULT_LIDAR_MODELS),
        metavar='MODEL',
        help='--kind lidar: one level per lidar model (os1-128, os1-32, vlp16, hdl32, hdl64; default os1-128)',
    )
    make.add_argument('--seed', type=_non_negative_int, default=0, help='random seed (default 0)')
    make.add_argument(
        '--noise',
        type=float,
        nargs='+',
        default=None,
        metavar='MM',
        help='radial noise sigmas in mm (default: ' + ' '.join(f'{s * 1000:.1f}' for s in DEFAULT_SIGMAS) + ')',
    )
    make.add_argument(
        '--train',
        type=_non_negative_int,
        default=DEFAULT_TRAIN,
        help=f'train scans per level (default {DEFAULT_TRAIN})',
    )
    make.add_argument(
        '--test', type=_non_negative_int, default=DEFAULT_TEST, help=f'test scans per level (default {DEFAULT_TEST})'
    )
    make.add_argument(
        '--scans',
        type=_non_negative_int,
        default=None,
        help='shorthand: this many train and this many test scans per level',
    )
    make.add_argument(
        '--rows', type=int, default=None, help="grid rows (default 500; depth_camera 480; lidar: the model's beams)"
    )
    make.add_argument('--cols', type=int, default=None, help='grid columns (default 500; lidar 1024; depth_camera 640)')
    make.add_argument(
        '--angular-noise',
        type=float,
        default=DEFAULT_ANGULAR_SIGMA_DEG * 1000.0,
        metavar='MDEG',
        help='beam-direction jitter in millidegrees (default 1)',
    )
    make.add_argument(
        '--objects',
        type=_non_negative_int,
        default=DEFAULT_N_OBJECTS,
        help=f'objects per room (synpeb, depth_camera; default {DEFAULT_N_OBJECTS})',
    )
    make.add_argument('--uncompressed', action='store_true', help='write DATA binary instead of binary_compressed')
    make.add_argument('--quiet', action='store_true', help='no progress bar')
    make.set_defaults(func=run_make)


def run_make(args: argparse.Namespace) -> int:
    if args.kind != 'synpeb' and args.noise is not None:
        raise ValueError(f'--noise sets SynPEB radial noise levels; --kind {args.kind} uses its sensor error model')
    sigmas = DEFAULT_SIGMAS if args.noise is None or args.kind != 'synpeb' else tuple(v / 1000.0 for v in args.noise)
    if args.kind != 'synpeb':
        sigmas = (0.0,)  # one level per lidar model / the depth camera
    n_train, n_test = (args.scans, args.scans) if args.scans is not None else (args.train, args.test)
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        levels = len(args.lidar_models) if args.kind == 'lidar' else len(sigmas)
        bar = tqdm(total=(n_train + n_test) * levels, unit='scan', file=sys.stderr, desc='ppe dataset make')
    try:
        manifest = make_dataset(
            args.directory,
            kind=args.kind,
            seed=args.seed,
            sigmas=sigmas,
            lidar_models=args.lidar_models,
            n_train=n_train,
            n_test=n_test,
            rows=args.rows,
            cols=args.cols,
            angular_sigma_deg=args.angular_noise / 1000.0,
            n_objects=args.objects,
            compressed=not args.uncompressed,
            progress=(lambda done, total: bar.update(1)) if bar else None,
        )
    finally:
        if bar is not None:
            bar.close()
    scans = manifest['scans']
    planes = [s['n_planes'] for s in scans]
    levels = ', '.join(f'{lv["name"]}' for lv in manifest['levels'])
    grid = f'{manifest["rows"]} x {manifest["cols"]}' if manifest['rows'] is not None else f'{manifest["cols"]}-column'
    kind = '' if args.kind == 'synpeb' else f'{args.kind} '
    print(
        f'{args.directory}: {len(scans)} {kind}scans ({n_train} train + {n_test} test per level; levels '
        f'{levels}), {grid} grid, {sum(planes) / max(len(planes), 1):.1f} planes per scan'
    )
    return 0
