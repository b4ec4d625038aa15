"""``ppe extract SCAN -o OUT``: run PPE on a scan file and write planes (npz / PCD) and a picture."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from ppe_ros.commands._options import add_ppe_options, add_scan_options, read_scan
from ppe_ros.core.extraction import extract_plane_hierarchy
from ppe_ros.core.planes import PlaneSet

#: Defaults of the command line (tuned on SynPEB by the reference: sqrt(e) = 0.22 m, lmax = 0.18 m).
DEFAULT_MAX_ERROR_INCREMENT = 0.0484
DEFAULT_MAX_NEIGHBOR_DISTANCE = 0.18
OUTPUT_SUFFIXES = ('.npz', '.pcd')


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        'extract',
        help='extract planes from a scan file',
        description='Run Probabilistic Plane Extraction on an organized scan (PCD, NPY, 16-bit depth PNG) and '
        'write the planes: OUT.npz (labels and per-plane arrays, as PlaneSet.to_npz_dict) or OUT.pcd '
        '(the cloud with a label field). With several -e/-n values one file is written per snapshot.',
    )
    parser.add_argument('scan', help='scan file: .pcd, .npy (H x W x 3, metres) or .png (16-bit depth)')
    parser.add_argument('-o', '--output', required=True, help='output file: .npz or .pcd')
    parser.add_argument('--png', default=None, help='also write a picture of the segmentation (ground truth beside '
                        'it when the scan carries labels)')
    add_ppe_options(parser)
    add_scan_options(parser)
    parser.add_argument('--force', action='store_true', help='replace existing output files')
    parser.add_argument('--json', action='store_true', help='print a JSON summary')
    parser.set_defaults(func=run)


def snapshot_path(output: Path, tag: str | None) -> Path:
    """``out.npz`` -> ``out_<tag>.npz`` when several snapshots are written."""
    return output if tag is None else output.with_name(f'{output.stem}_{tag}{output.suffix}')


def write_planes(path: Path, planes: PlaneSet, points: np.ndarray, *, meta: dict, force: bool) -> Path:
    """Write one snapshot as .npz or .pcd; refuses to replace a file unless ``force``."""
    from ppe_ros.io import save_pcd

    if path.exists() and not force:
        raise FileExistsError(f'{path} exists (use --force to replace it)')
    if path.suffix == '.npz':
        arrays = planes.to_npz_dict()
        arrays['meta'] = np.array(json.dumps(meta))
        with path.open('wb') as handle:
            np.savez(handle, **arrays)
    else:
        save_pcd(path, points, labels=planes.labels, overwrite=force)
    return path


def run(args: argparse.Namespace) -> int:
    output = Path(args.output)
    if output.suffix not in OUTPUT_SUFFIXES:
        raise ValueError(f'output must end in .npz or .pcd; got {output.name!r}')
    scan_path = Path(args.scan).resolve()
    outputs = [output] + ([Path(args.png)] if args.png else [])
    for out in outputs:
        if out.resolve() == scan_path:
            raise ValueError(f'refusing to overwrite the input scan {scan_path}')
    if args.min_plane_points < 1:
        raise ValueError(f'--min-plane-points must be >= 1; got {args.min_plane_points}')
    e_list = args.max_error_increment
    n_list = args.max_planes
    if n_list is not None and any(n < 1 for n in n_list):
        raise ValueError(f'-n/--max-planes must be >= 1; got {n_list}')
    if e_list is None and n_list is None:
        e_list = [DEFAULT_MAX_ERROR_INCREMENT]
    lmax = DEFAULT_MAX_NEIGHBOR_DISTANCE if args.max_neighbor_distance is None else args.max_neighbor_distance

    scan = read_scan(args, args.scan)
    start = time.perf_counter()
    hierarchy = extract_plane_hierarchy(
        scan.points, origins=scan.origins, max_neighbor_distance=lmax,
        max_error_increment=max(e_list) if e_list else None, max_planes=min(n_list) if n_list else None,
    )
    snapshots: list[tuple[str, PlaneSet]] = []
    for e in e_list or []:
        snapshots.append((f'e{e:g}', hierarchy.cut(max_error_increment=e, min_plane_points=args.min_plane_points)))
    for n in n_list or []:
        snapshots.append((f'n{n}', hierarchy.cut(max_planes=n, min_plane_points=args.min_plane_points)))
    seconds = time.perf_counter() - start
    several = len(snapshots) > 1
    summary = {'scan': str(args.scan), 'grid': list(scan.shape), 'valid_fraction': scan.valid_fraction,
               'max_neighbor_distance': lmax, 'seconds': seconds, 'snapshots': []}
    for tag, planes in snapshots:
        meta = {'scan': str(args.scan), 'max_neighbor_distance': lmax,
                'max_error_increment': planes.max_error_increment, 'max_planes': planes.max_planes,
                'seconds': seconds}
        path = write_planes(snapshot_path(output, tag if several else None), planes, scan.points, meta=meta,
                            force=args.force)
        entry = {'file': str(path), 'planes': planes.num_planes, 'actions': planes.actions,
                 'max_error_increment': planes.max_error_increment, 'max_planes': planes.max_planes,
                 'labelled_fraction': float((planes.labels > 0).mean())}
        if args.png:
            from ppe_ros.render import save_segmentation_png

            png = save_segmentation_png(snapshot_path(Path(args.png), tag if several else None), planes.labels,
                                        ground_truth=scan.labels, gt_min_label=scan.meta.get('min_plane_label', 1),
                                        overwrite=args.force)
            entry['png'] = str(png)
        summary['snapshots'].append(entry)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f'{args.scan}: {scan.shape[0]}x{scan.shape[1]} grid, {scan.valid_fraction:.1%} valid, '
              f'extraction {seconds:.2f} s (lmax {lmax:g} m)')
        for entry in summary['snapshots']:
            which = (f"e = {entry['max_error_increment']:g} m^2" if entry['max_error_increment'] is not None
                     else f"n = {entry['max_planes']}")
            extra = f", picture {entry['png']}" if 'png' in entry else ''
            print(f"  {which}: {entry['planes']} planes covering {entry['labelled_fraction']:.1%} of the grid "
                  f"-> {entry['file']}{extra}")
    return 0
