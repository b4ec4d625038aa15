"""``ppe extract SCAN -o OUT``: run PPE on a scan file and write planes (npz / PCD) and a picture."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from ppe_ros.commands._options import add_ppe_options, add_scan_options, read_scan
from ppe_ros.core.extraction import PROFILE_DEFAULT, extract_plane_hierarchy, extract_planes
from ppe_ros.core.planes import PlaneSet
from ppe_ros.core.sensor import sensor_profile
from ppe_ros.io.files import (
    check_output_targets,
    refuse_overwriting_inputs,
    write_file_atomically,
    write_files_atomically,
)
from ppe_ros.io.loading import scan_input_files

#: Defaults of the command line (tuned on SynPEB by the reference: sqrt(e) = 0.22 m, lmax = 0.18 m).
DEFAULT_MAX_ERROR_INCREMENT = 0.0484
DEFAULT_MAX_NEIGHBOR_DISTANCE = 0.18
DEFAULT_MIN_PLANE_POINTS = 4
OUTPUT_SUFFIXES = ('.npz', '.pcd')


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        'extract',
        help='extract planes from a scan file',
        description='Run Probabilistic Plane Extraction on an organized scan (PCD, NPY, 16-bit depth PNG) and '
        'write the planes: OUT.npz (labels and per-plane arrays, as PlaneSet.to_npz_dict) or OUT.pcd '
        '(the cloud with a label field). With several -e/-n values one file is written per snapshot (each value '
        'once). Every output is written to a temporary file and renamed into place when all are complete; an '
        'output that is an input (also through a hard or symbolic link) is refused.',
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


def planes_writer(path: Path, planes: PlaneSet, points: np.ndarray, *, meta: dict):
    """A writer (for :func:`ppe_ros.io.files.write_files_atomically`) of one snapshot as .npz or .pcd."""
    from ppe_ros.io.pcd import encode_pcd

    if path.suffix == '.npz':
        arrays = planes.to_npz_dict()
        arrays['meta'] = np.array(json.dumps(meta))
        return lambda stream: np.savez(stream, **arrays)
    content = encode_pcd(points, labels=planes.labels)
    return lambda stream: stream.write(content)


def write_planes(path: Path, planes: PlaneSet, points: np.ndarray, *, meta: dict, force: bool) -> Path:
    """Write one snapshot as .npz or .pcd, atomically; refuses to replace a file unless ``force``."""
    return write_file_atomically(path, planes_writer(path, planes, points, meta=meta), overwrite=force)


def _snapshot_requests(e_list: list[float] | None, n_list: list[int] | None) -> list[tuple[str, str]]:
    """``(flag, tag)`` per requested snapshot, e.g. ``('-e 0.01', 'e0.01')``, in command-line order."""
    requests = [(f'-e {e:g}', f'e{e:g}') for e in e_list or []]
    return requests + [(f'-n {n}', f'n{n}') for n in n_list or []]


def planned_outputs(output: Path, png: Path | None, requests: list[tuple[str, str]]) -> list[tuple[Path, Path | None]]:
    """The (planes file, picture) of every snapshot.

    Raises:
        ValueError: two snapshots would write the same file (a threshold given twice, or two values
            that print alike): each snapshot must be asked for once.
    """
    several = len(requests) > 1
    seen: dict[str, str] = {}
    for flag, tag in requests:
        if tag in seen:
            raise ValueError(f'{seen[tag]} and {flag} both give the snapshot {snapshot_path(output, tag).name}; '
                             f'give each threshold once')
        seen[tag] = flag
    return [(snapshot_path(output, tag if several else None),
             snapshot_path(png, tag if several else None) if png is not None else None) for _, tag in requests]


def run(args: argparse.Namespace) -> int:
    output = Path(args.output)
    if output.suffix not in OUTPUT_SUFFIXES:
        raise ValueError(f'output must end in .npz or .pcd; got {output.name!r}')
    png = Path(args.png) if args.png else None
    profile = None if args.sensor is None else sensor_profile(args.sensor)
    if args.surface_tolerance is not None and profile is None:
        raise ValueError('--surface-tolerance needs --sensor (a sensor profile)')
    min_points = args.min_plane_points
    if min_points is None:
        min_points = DEFAULT_MIN_PLANE_POINTS if profile is None else profile.min_plane_points
    if min_points < 1:
        raise ValueError(f'--min-plane-points must be >= 1; got {min_points}')
    e_list = args.max_error_increment
    n_list = args.max_planes
    if n_list is not None and any(n < 1 for n in n_list):
        raise ValueError(f'-n/--max-planes must be >= 1; got {n_list}')
    if e_list is None and n_list is None:
        e_list = [DEFAULT_MAX_ERROR_INCREMENT if profile is None else profile.max_error_increment]
    lmax = args.max_neighbor_distance
    if lmax is None:
        lmax = DEFAULT_MAX_NEIGHBOR_DISTANCE if profile is None else profile.max_neighbor_distance
    # every output is checked (inputs by device and inode, collisions, existing files) before anything runs
    plan = planned_outputs(output, png, _snapshot_requests(e_list, n_list))
    targets = [path for pair in plan for path in pair if path is not None]
    refuse_overwriting_inputs(targets, scan_input_files(args.scan, gt=args.gt))
    check_output_targets(targets, overwrite=args.force)

    scan = read_scan(args, args.scan)
    start = time.perf_counter()
    snapshots: list[PlaneSet] = []
    if profile is None:
        hierarchy = extract_plane_hierarchy(
            scan.points, origins=scan.origins, max_neighbor_distance=lmax,
            max_error_increment=max(e_list) if e_list else None, max_planes=min(n_list) if n_list else None,
        )
        for e in e_list or []:
            snapshots.append(hierarchy.cut(max_error_increment=e, min_plane_points=min_points))
        for n in n_list or []:
            snapshots.append(hierarchy.cut(max_planes=n, min_plane_points=min_points))
    else:
        tolerance = PROFILE_DEFAULT if args.surface_tolerance is None else args.surface_tolerance
        snapshots = list(extract_planes(
            scan.points, origins=scan.origins, sensor=profile, max_error_increment=list(e_list or []) or None,
            max_planes=list(n_list) if n_list else None, max_neighbor_distance=lmax, min_plane_points=min_points,
            surface_tolerance=tolerance))
    seconds = time.perf_counter() - start
    summary = {'scan': str(args.scan), 'grid': list(scan.shape), 'valid_fraction': scan.valid_fraction,
               'max_neighbor_distance': lmax, 'sensor': args.sensor, 'seconds': seconds, 'snapshots': []}
    files = []
    for planes, (path, png_path) in zip(snapshots, plan, strict=True):
        meta = {'scan': str(args.scan), 'max_neighbor_distance': lmax, 'sensor': args.sensor,
                'max_error_increment': planes.max_error_increment, 'max_planes': planes.max_planes,
                'seconds': seconds}
        files.append((path, planes_writer(path, planes, scan.points, meta=meta)))
        entry = {'file': str(path), 'planes': planes.num_planes, 'actions': planes.actions,
                 'max_error_increment': planes.max_error_increment, 'max_planes': planes.max_planes,
                 'labelled_fraction': float((planes.labels > 0).mean())}
        if png_path is not None:
            from ppe_ros.render import segmentation_png_writer

            files.append((png_path, segmentation_png_writer(
                planes.labels, ground_truth=scan.labels, gt_min_label=scan.meta.get('min_plane_label', 1))))
            entry['png'] = str(png_path)
        summary['snapshots'].append(entry)
    write_files_atomically(files, overwrite=args.force)  # all complete, or none changed
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f'{args.scan}: {scan.shape[0]}x{scan.shape[1]} grid, {scan.valid_fraction:.1%} valid, '
              f'extraction {seconds:.2f} s (lmax {lmax:g} m' + (f', sensor {args.sensor})' if args.sensor else ')'))
        unit = ' m^2' if profile is None or profile.noise is None else ''
        for entry in summary['snapshots']:
            which = (f"e = {entry['max_error_increment']:g}{unit}" if entry['max_error_increment'] is not None
                     else f"n = {entry['max_planes']}")
            extra = f", picture {entry['png']}" if 'png' in entry else ''
            print(f"  {which}: {entry['planes']} planes covering {entry['labelled_fraction']:.1%} of the grid "
                  f"-> {entry['file']}{extra}")
    return 0
