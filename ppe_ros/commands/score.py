"""``ppe score SCAN PRED.npz``: score a predicted segmentation against the ground truth of a scan file."""

from __future__ import annotations

import argparse
import json
import math
import zipfile
import zlib
from pathlib import Path

import numpy as np

from ppe_ros.commands._options import add_scan_options, read_scan
from ppe_ros.io.limits import check_grid_size
from ppe_ros.io.npy import read_npy, read_npy_stream

SUMMARY_KEYS = (
    'f',
    'k',
    'k_all_rays',
    'rmse',
    'n_gt',
    'n_pred',
    'n_correct',
    'n_over',
    'n_under',
    'n_missed',
    'n_noise',
    'n_rmse_dropped',
    'consistent',
    'threshold',
)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        'score',
        help='score a prediction (npz from `ppe extract`) against ground truth',
        description='Score predicted plane labels (an .npz with a `labels` array, as `ppe extract -o OUT.npz` writes) '
        "against the ground truth of the scan with the paper's metrics: f, k, RMSE of the exact radial fit of every "
        'predicted plane, and the Hoover counts (T = 0.8). Ground truth: SynPEB PCD intensity (planes >= 10), a label '
        'field, a <name>_labels.npy next to the scan, or --gt (planes >= 1).',
    )
    parser.add_argument('scan', help='scan file with ground truth: .pcd, .npy or .png')
    parser.add_argument('prediction', help='.npz with a labels array (H x W integers, 0 = no plane), or a labels .npy')
    add_scan_options(parser)
    parser.add_argument(
        '--gt-min-label',
        type=int,
        default=None,
        help='smallest ground-truth label that is a plane (default: 10 for SynPEB intensity, else 1)',
    )
    parser.add_argument('--threshold', type=float, default=0.8, help='Hoover tolerance T (default 0.8)')
    parser.add_argument('--json', action='store_true', help='print one JSON object')
    parser.set_defaults(func=run)


def _check_prediction(name: str, shape: tuple[int, ...], dtype: np.dtype) -> None:
    if len(shape) != 2:
        raise ValueError(f'{name}: labels must be a 2-D (H, W) image; got shape {shape}')
    if not np.issubdtype(dtype, np.integer):
        raise ValueError(f'{name}: labels must be integers; got dtype {dtype}')
    check_grid_size(name, shape[0], shape[1], 'labels image')


def read_prediction(path: str | Path) -> np.ndarray:
    """The ``labels`` array of an npz (``ppe extract`` output) or a labels .npy.

    The array's header is checked (2-D integers, size within :mod:`ppe_ros.io.limits`, data present)
    before the array is read.

    Raises:
        FileNotFoundError, ValueError: missing file, no labels array, not an integer image, damaged file.
    """
    file = Path(path)
    if not file.is_file():
        raise FileNotFoundError(f'prediction file not found: {file}')
    if not zipfile.is_zipfile(file):
        labels = read_npy(
            file, lambda shape, dtype: _check_prediction(str(file), shape, dtype), what='.npz/.npy labels file'
        )
        return labels.astype(np.int64)
    try:
        with zipfile.ZipFile(file) as archive:
            names = [name.removesuffix('.npy') for name in archive.namelist()]
            if 'labels' not in names:
                raise ValueError(f'{file}: no "labels" array (has: {", ".join(names) or "nothing"})')
            member = archive.getinfo('labels.npy')
            with archive.open(member) as stream:
                labels = read_npy_stream(
                    stream,
                    member.file_size,
                    f'{file} (labels)',
                    lambda shape, dtype: _check_prediction(f'{file} (labels)', shape, dtype),
                )
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, NotImplementedError, zlib.error) as exc:
        raise ValueError(f'{file}: not a readable .npz file: {" ".join(str(exc).split())}') from None
    return labels.astype(np.int64)


def run(args: argparse.Namespace) -> int:
    from ppe_ros.benchmark.runner import score_prediction

    scan = read_scan(args, args.scan)
    if scan.labels is None:
        raise ValueError(
            f'{args.scan}: the scan carries no ground truth (SynPEB intensity, label field, '
            f'<name>_labels.npy); pass --gt LABELS.npy'
        )
    pred = read_prediction(args.prediction)
    if pred.shape != scan.shape:
        raise ValueError(
            f'prediction {args.prediction} is {pred.shape[0]} x {pred.shape[1]}, the scan is '
            f'{scan.shape[0]} x {scan.shape[1]}'
        )
    if np.any(pred < 0):
        raise ValueError(f'{args.prediction}: labels must be >= 0 (0 = no plane)')
    gt_min_label = args.gt_min_label if args.gt_min_label is not None else int(scan.meta.get('min_plane_label', 1))
    if not 0.0 <= args.threshold < 1.0:
        raise ValueError(f'--threshold must be in [0, 1); got {args.threshold}')
    score = score_prediction(
        scan.points, scan.origins, scan.labels, pred, gt_min_label=gt_min_label, threshold=args.threshold
    )
    full = score.to_dict()
    summary = {'scan': str(args.scan), 'prediction': str(args.prediction), 'gt_min_label': gt_min_label}
    summary.update({key: full[key] for key in SUMMARY_KEYS})
    if args.json:
        print(json.dumps(summary))
        return 0

    def pct(value):
        return '–' if value is None else f'{value * 100:.1f} %'

    rmse = '–' if score.rmse is None or not math.isfinite(score.rmse) else f'{score.rmse * 1000:.1f} mm'
    print(f'{args.scan} vs {args.prediction} (GT planes: labels >= {gt_min_label}, T = {score.threshold:g})')
    print(f'  f {pct(full["f"])}  k {pct(full["k"])}  RMSE {rmse}')
    print(
        f'  GT planes {score.n_gt}, predicted planes {score.n_pred}: correct {score.n_correct}, over-segmented '
        f'{score.n_over}, under-segmented {score.n_under}, missed {score.n_missed}, spurious {score.n_noise}'
    )
    return 0
