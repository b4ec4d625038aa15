"""``ppe info FILE``: what a scan file holds (grid, valid pixels, ranges, bounding box, ground truth)."""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np

from ppe_ros.io import UNIT_SCALES, load_scan
from ppe_ros.io.loading import Scan

#: Above this median range (in metres) the coordinates are probably not metres: say so.
SUSPICIOUS_MEDIAN_RANGE_M = 200.0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        'info',
        help='describe a scan file (PCD, NPY, 16-bit depth PNG)',
        description='Print the grid size, valid fraction, range statistics (|p| from the coordinate origin, '
        'metres), bounding box and ground-truth labels of an organized scan file.',
    )
    parser.add_argument('file', help='scan file: .pcd, .npy (H x W x 3) or .png (16-bit depth)')
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
    parser.add_argument('--json', action='store_true', help='print one JSON object instead of text')
    parser.set_defaults(func=run)


def _stats(values: np.ndarray) -> dict[str, float] | None:
    if values.size == 0:
        return None
    return {
        'min': float(values.min()),
        'median': float(np.median(values)),
        'max': float(values.max()),
    }


def describe_scan(scan: Scan) -> dict[str, Any]:
    """A JSON-ready summary of a scan (lengths in metres)."""
    valid = scan.valid
    points = scan.points[valid]
    ranges = np.linalg.norm(points, axis=1)
    height, width = scan.shape
    summary: dict[str, Any] = {
        'file': str(scan.path),
        'format': scan.format,
        'rows': height,
        'columns': width,
        'points': height * width,
        'valid_points': int(valid.sum()),
        'valid_fraction': float(valid.mean()),
        'range_m': _stats(ranges),
        'bounding_box_m': None
        if points.size == 0
        else {'min': points.min(axis=0).tolist(), 'max': points.max(axis=0).tolist()},
        'ray_origins': None if scan.origins is None else f'array of shape {list(np.shape(scan.origins))}',
        'meta': {key: value for key, value in scan.meta.items()},
        'labels': None,
    }
    if scan.labels is not None:
        min_plane_label = int(scan.meta.get('min_plane_label', 1))
        ids, counts = np.unique(scan.labels, return_counts=True)
        plane = ids >= min_plane_label
        plane_counts = counts[plane]
        summary['labels'] = {
            'source': scan.meta.get('labels_source'),
            'distinct_ids': int(ids.size),
            'min_plane_label': min_plane_label,
            'planes': int(plane.sum()),
            'ids_ge_10': int((ids >= 10).sum()),
            'unlabelled_points': int(counts[~plane].sum()),
            'points_per_plane': None
            if plane_counts.size == 0
            else {
                'min': int(plane_counts.min()),
                'median': float(np.median(plane_counts)),
                'max': int(plane_counts.max()),
            },
            'counts': {str(int(i)): int(c) for i, c in zip(ids, counts, strict=True)},
        }
    return summary


def _format_text(summary: dict[str, Any]) -> str:
    lines = [
        f'file:            {summary["file"]} ({summary["format"]})',
        f'grid:            {summary["rows"]} rows x {summary["columns"]} columns = {summary["points"]} pixels',
        f'valid:           {summary["valid_points"]} points ({100.0 * summary["valid_fraction"]:.2f} %)',
    ]
    meta = summary['meta']
    keys = ('encoding', 'fields', 'units', 'depth_scale', 'intrinsics')
    details = [f'{key}={meta[key]}' for key in keys if meta.get(key) is not None]
    if details:
        lines.append(f'details:         {", ".join(str(d) for d in details)}')
    ranges = summary['range_m']
    if ranges is None:
        lines.append('range |p|:       no valid points')
    else:
        lines.append(
            f'range |p| [m]:   min {ranges["min"]:.4g}  median {ranges["median"]:.4g}  max {ranges["max"]:.4g}'
        )
        if ranges['median'] > SUSPICIOUS_MEDIAN_RANGE_M:
            lines.append(
                f'warning:         median range {ranges["median"]:.4g} m is large: are the coordinates '
                f'in cm or mm? (use --units)'
            )
    box = summary['bounding_box_m']
    if box is not None:
        low = ', '.join(f'{v:.4g}' for v in box['min'])
        high = ', '.join(f'{v:.4g}' for v in box['max'])
        lines.append(f'bounding box [m]: min ({low})  max ({high})')
    if summary['ray_origins'] is not None:
        lines.append(f'ray origins:     {summary["ray_origins"]} ({meta.get("origins_source", "file")})')
    else:
        lines.append('ray origins:     coordinate origin')
    labels = summary['labels']
    if labels is None:
        lines.append('ground truth:    none')
    else:
        lines.append(f'ground truth:    {labels["source"]}')
        synpeb = '' if labels['min_plane_label'] == 10 else f' ({labels["ids_ge_10"]} ids >= 10, the SynPEB convention)'
        lines.append(
            f'  {labels["distinct_ids"]} distinct ids, {labels["planes"]} planes (ids >= {labels["min_plane_label"]})'
            f'{synpeb}, {labels["unlabelled_points"]} unlabelled points'
        )
        per_plane = labels['points_per_plane']
        if per_plane is not None:
            lines.append(
                f'  points per plane: min {per_plane["min"]}  median {per_plane["median"]:.0f}  max {per_plane["max"]}'
            )
    return '\n'.join(lines)


def run(args: argparse.Namespace) -> int:
    scan = load_scan(
        args.file,
        units=args.units,
        gt=args.gt,
        intrinsics=tuple(args.intrinsics) if args.intrinsics is not None else None,
        depth_scale=args.depth_scale,
    )
    summary = describe_scan(scan)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(_format_text(summary))
    return 0
