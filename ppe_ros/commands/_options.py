"""Command-line options shared by the ``ppe`` subcommands that read scans or run PPE."""

from __future__ import annotations

import argparse
from pathlib import Path

from ppe_ros.io import UNIT_SCALES, load_scan
from ppe_ros.io.limits import MAX_SCAN_POINTS
from ppe_ros.io.loading import Scan


def add_scan_options(parser: argparse.ArgumentParser) -> None:
    """``--units``, ``--gt``, ``--intrinsics``, ``--depth-scale`` for reading a scan file."""
    parser.add_argument(
        '--units',
        choices=sorted(UNIT_SCALES),
        default=None,
        help='unit of the coordinates in the file (default: metres; the TLS scan andreashaus_scan000.pcd is cm); '
        'for a depth PNG the unit of one depth count',
    )
    parser.add_argument('--gt', default=None, help='ground-truth labels .npy (H x W integers) to attach')
    parser.add_argument(
        '--intrinsics',
        nargs=4,
        type=float,
        metavar=('FX', 'FY', 'CX', 'CY'),
        default=None,
        help='pinhole intrinsics of a depth PNG in pixels (default: a known calibration file next to it)',
    )
    parser.add_argument('--depth-scale', type=float, default=None, help='metres per depth count of a depth PNG')


def read_scan(args: argparse.Namespace, path: str | Path) -> Scan:
    """Load the scan named on the command line with the shared options."""
    return load_scan(path, units=args.units, gt=args.gt, intrinsics=args.intrinsics, depth_scale=args.depth_scale)


def positive_float(text: str) -> float:
    """argparse type: a finite float > 0 (inf allowed for distances)."""
    try:
        value = float(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f'not a number: {text!r}') from exc
    if not value > 0:
        raise argparse.ArgumentTypeError(f'must be > 0: {text!r}')
    return value


def plane_count(text: str) -> int:
    """argparse type: an integer 1 .. :data:`~ppe_ros.io.limits.MAX_SCAN_POINTS` (no scan has more planes)."""
    try:
        value = int(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f'not an integer: {text!r}') from exc
    if not 1 <= value <= MAX_SCAN_POINTS:
        raise argparse.ArgumentTypeError(f'must be 1 .. {MAX_SCAN_POINTS} (the most points a scan may have): {text!r}')
    return value


def non_negative_float(text: str) -> float:
    """argparse type: a finite float >= 0."""
    try:
        value = float(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f'not a number: {text!r}') from exc
    if not (value >= 0 and value != float('inf')):
        raise argparse.ArgumentTypeError(f'must be finite and >= 0: {text!r}')
    return value


def add_ppe_options(parser: argparse.ArgumentParser) -> None:
    """``-e``, ``--lmax``, ``-n``, ``--min-plane-points`` (PPE parameters)."""
    parser.add_argument(
        '-e',
        '--max-error-increment',
        type=non_negative_float,
        nargs='+',
        default=None,
        metavar='E',
        help="maximum error increment e in m^2 (the paper's stopping rule); several values give one "
        'snapshot each (default 0.0484 = 0.22^2, tuned on SynPEB)',
    )
    parser.add_argument(
        '--lmax',
        '--max-neighbor-distance',
        dest='max_neighbor_distance',
        type=positive_float,
        default=None,
        help='largest distance in m between neighbouring endpoints that may be joined (default 0.18; inf = none)',
    )
    parser.add_argument(
        '-n',
        '--max-planes',
        type=plane_count,
        nargs='+',
        default=None,
        metavar='N',
        help='plane-count snapshots J <= N (atomic rays count as planes)',
    )
    parser.add_argument(
        '--min-plane-points',
        type=int,
        default=None,
        help=(
            "planes with fewer rays are reported as no plane (default 4; with --sensor the profile's, "
            'fewer on a scan whose rays are spaced wider than those it was chosen on: docs/parameters.md)'
        ),
    )
    parser.add_argument(
        '--sensor',
        choices=('lidar', 'depth_camera', 'paper'),
        default=None,
        help='sensor profile: a range noise model and whole surfaces (e is then dimensionless, in '
        "units of the noise variance; e, lmax and --min-plane-points default to the profile's; "
        "see docs/algorithm.md); default: the paper's model",
    )
    parser.add_argument(
        '--surface-tolerance',
        type=positive_float,
        default=None,
        metavar='M',
        help="with --sensor: RMS deviation (m) one physical surface may show from its plane (default: the profile's)",
    )
    parser.add_argument(
        '--range-noise',
        type=positive_float,
        default=None,
        metavar='M',
        help="with --sensor lidar or depth_camera: the sensor's range noise (m) at short range, the constant term "
        "of the profile's noise model (default: the profile's, lidar 0.02)",
    )
