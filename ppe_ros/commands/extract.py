"""``ppe extract SCAN -o OUT``: run PPE on a scan file and write planes (npz / PCD) and a picture."""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from ppe_ros.commands._options import add_ppe_options, add_scan_options, positive_float, read_scan
from ppe_ros.core.extraction import PROFILE_DEFAULT, extract_plane_hierarchy, extract_planes
from ppe_ros.core.planes import PlaneSet
from ppe_ros.core.projection import extract_planes_unorganized
from ppe_ros.core.sensor import PROFILES, SensorProfile, sensor_profile
from ppe_ros.io.files import (
    check_output_targets,
    refuse_overwriting_inputs,
    write_file_atomically,
    write_files_atomically,
)
from ppe_ros.io.loading import Scan, scan_input_files

#: Defaults of the command line (tuned on SynPEB by the reference: sqrt(e) = 0.22 m, lmax = 0.18 m).
#: Without --sensor, ppe extract takes its defaults from the paper profile (e 0.0484 m^2, lmax
#: 0.18 m, 4 points: the reference implementation's setting tuned on SynPEB) and runs the paper's model.
DEFAULT_PROFILE = PROFILES['paper']
OUTPUT_SUFFIXES = ('.npz', '.pcd')


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        'extract',
        help='extract planes from a scan file',
        description='Run Probabilistic Plane Extraction on a scan (PCD, NPY, 16-bit depth PNG, KITTI .bin) and '
        'write the planes: OUT.npz (labels and per-plane arrays, as PlaneSet.to_npz_dict) or OUT.pcd '
        '(the cloud with a label field). An unorganized cloud (a PCD of HEIGHT 1, a KITTI .bin) is put on a '
        'range image first (rows from its ring field or from the beams found in its elevation angles, columns '
        "by azimuth) and gets one label per point, in the file's order. "
        'With several -e/-n values one file is written per snapshot (each value '
        'once). Every output is written to a temporary file and renamed into place when all are complete; an '
        'output that is an input (also through a hard or symbolic link) is refused.',
    )
    parser.add_argument('scan', help='scan file: .pcd, .npy (H x W x 3, metres), .png (16-bit depth) or .bin (KITTI)')
    parser.add_argument('-o', '--output', required=True, help='output file: .npz or .pcd')
    parser.add_argument(
        '--png',
        default=None,
        help='also write a picture of the segmentation (ground truth beside it when the scan carries labels)',
    )
    add_ppe_options(parser)
    add_scan_options(parser)
    add_projection_options(parser)
    parser.add_argument('--force', action='store_true', help='replace existing output files')
    parser.add_argument('--json', action='store_true', help='print a JSON summary')
    parser.set_defaults(func=run)


def add_projection_options(parser: argparse.ArgumentParser) -> None:
    """Options of the range-image projection (unorganized clouds) and of the grid layout."""
    from ppe_ros.core.projection import DEFAULT_ANGULAR_RESOLUTION_DEG, DEFAULT_AZIMUTH_START_DEG, ROW_METHODS

    group = parser.add_argument_group('unorganized clouds and layouts')
    group.add_argument(
        '--rows',
        choices=ROW_METHODS,
        default='auto',
        help='rows of the range image of an unorganized cloud: rings (the ring field), elevation '
        '(beams found in the elevation angles), angular_grid (a fixed grid, for Livox); auto: rings '
        'if the file has a ring field, else elevation',
    )
    group.add_argument(
        '--azimuth-bins',
        type=int,
        default=None,
        metavar='N',
        help='columns per revolution (default: estimated from the points)',
    )
    group.add_argument(
        '--azimuth-start',
        type=float,
        default=DEFAULT_AZIMUTH_START_DEG,
        metavar='DEG',
        help='azimuth (deg, counter-clockwise from x) where the range image of a full circle starts '
        '(default: %(default)s, behind the sensor)',
    )
    group.add_argument(
        '--angular-resolution',
        type=positive_float,
        default=DEFAULT_ANGULAR_RESOLUTION_DEG,
        metavar='DEG',
        help='cell size of --rows angular_grid (default: %(default)s deg)',
    )
    group.add_argument(
        '--lost-point-tolerance',
        type=positive_float,
        default=None,
        metavar='M',
        help="a point that lost its range-image cell to a nearer return gets the cell's plane within "
        "this distance (default: the sensor profile's surface tolerance, else 0.05 m)",
    )
    group.add_argument(
        '--layout',
        choices=('rows_are_beams', 'columns_are_beams'),
        default='rows_are_beams',
        help="an organized scan with one beam per column (Velodyne's organized clouds) is "
        'transposed for the extraction and its labels back',
    )


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
    content = encode_pcd(points, labels=np.reshape(planes.labels, points.shape[:2]))
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
            raise ValueError(
                f'{seen[tag]} and {flag} both give the snapshot {snapshot_path(output, tag).name}; '
                f'give each threshold once'
            )
        seen[tag] = flag
    return [
        (
            snapshot_path(output, tag if several else None),
            snapshot_path(png, tag if several else None) if png is not None else None,
        )
        for _, tag in requests
    ]


def extract_snapshots(
    scan: Scan,
    args: argparse.Namespace,
    profile: SensorProfile | None,
    e_list: list[float] | None,
    n_list: list[int] | None,
    lmax: float,
    min_points,
) -> list[PlaneSet]:
    """One PlaneSet per requested snapshot (e values, then n values) of ``scan``; ``min_points``: the smallest
    plane (rays), or PROFILE_DEFAULT (the profile's for this scan: SensorProfile.min_plane_points_for).

    An unorganized scan goes through :func:`ppe_ros.core.projection.extract_planes_unorganized`
    (labels ``(N,)``); an organized one with ``--layout columns_are_beams`` is transposed and back.
    """
    if not scan.organized:
        rings = None if scan.rings is None else scan.rings.reshape(-1)
        tolerance = PROFILE_DEFAULT if args.surface_tolerance is None else args.surface_tolerance
        profile_options = {} if profile is None else {'sensor': profile, 'surface_tolerance': tolerance}
        return list(
            extract_planes_unorganized(
                scan.points.reshape(-1, 3),
                rings,
                origins=scan.origins,
                rows=args.rows,
                azimuth_bins=args.azimuth_bins,
                azimuth_start=args.azimuth_start,
                angular_resolution=args.angular_resolution,
                lost_point_tolerance=args.lost_point_tolerance,
                max_error_increment=list(e_list or []) or None,
                max_planes=list(n_list) if n_list else None,
                max_neighbor_distance=lmax,
                min_plane_points=min_points,
                **profile_options,
            )
        )
    transposed = args.layout == 'columns_are_beams'
    points = np.ascontiguousarray(scan.points.transpose(1, 0, 2)) if transposed else scan.points
    origins = scan.origins
    if transposed and origins is not None and np.ndim(origins) == 3:
        origins = np.ascontiguousarray(origins.transpose(1, 0, 2))
    snapshots: list[PlaneSet] = []
    if profile is None:
        hierarchy = extract_plane_hierarchy(
            points,
            origins=origins,
            max_neighbor_distance=lmax,
            max_error_increment=max(e_list) if e_list else None,
            max_planes=min(n_list) if n_list else None,
        )
        for e in e_list or []:
            snapshots.append(hierarchy.cut(max_error_increment=e, min_plane_points=min_points))
        for n in n_list or []:
            snapshots.append(hierarchy.cut(max_planes=n, min_plane_points=min_points))
    else:
        tolerance = PROFILE_DEFAULT if args.surface_tolerance is None else args.surface_tolerance
        snapshots = list(
            extract_planes(
                points,
                origins=origins,
                sensor=profile,
                max_error_increment=list(e_list or []) or None,
                max_planes=list(n_list) if n_list else None,
                max_neighbor_distance=lmax,
                min_plane_points=min_points,
                surface_tolerance=tolerance,
            )
        )
    if transposed:
        snapshots = [dataclasses.replace(planes, labels=np.ascontiguousarray(planes.labels.T)) for planes in snapshots]
    return snapshots


def _picture_labels(scan: Scan, planes: PlaneSet) -> tuple[np.ndarray, np.ndarray | None]:
    """Labels and ground truth to draw: the range image's for an unorganized scan, else the scan's."""
    if scan.organized:
        return planes.labels, scan.labels
    projection = planes.meta['projection']
    truth = None
    if scan.labels is not None and projection.rows * projection.columns:
        held = projection.cell_points
        truth = np.where(held >= 0, scan.labels.reshape(-1)[np.maximum(held, 0)], 0).reshape(projection.shape)
    return planes.meta['cell_labels'], truth


def run(args: argparse.Namespace) -> int:
    output = Path(args.output)
    if output.suffix not in OUTPUT_SUFFIXES:
        raise ValueError(f'output must end in .npz or .pcd; got {output.name!r}')
    png = Path(args.png) if args.png else None
    profile = None if args.sensor is None else sensor_profile(args.sensor)
    if args.surface_tolerance is not None and profile is None:
        raise ValueError('--surface-tolerance needs --sensor (a sensor profile)')
    if args.range_noise is not None:
        if profile is None or profile.noise is None:
            raise ValueError('--range-noise needs --sensor lidar or depth_camera (a profile with a noise model)')
        profile = profile.with_range_noise(args.range_noise)
    min_points = args.min_plane_points
    if min_points is not None and min_points < 1:
        raise ValueError(f'--min-plane-points must be >= 1; got {min_points}')
    if min_points is None:  # a profile's own: fewer rays on a coarser grid (SensorProfile.min_plane_points_for)
        min_points = DEFAULT_PROFILE.min_plane_points if profile is None else PROFILE_DEFAULT
    e_list = args.max_error_increment
    n_list = args.max_planes
    if n_list is not None and any(n < 1 for n in n_list):
        raise ValueError(f'-n/--max-planes must be >= 1; got {n_list}')
    if e_list is None and n_list is None:
        e_list = [(DEFAULT_PROFILE if profile is None else profile).max_error_increment]
    lmax = args.max_neighbor_distance
    if lmax is None:
        lmax = (DEFAULT_PROFILE if profile is None else profile).max_neighbor_distance
    # every output is checked (inputs by device and inode, collisions, existing files) before anything runs
    plan = planned_outputs(output, png, _snapshot_requests(e_list, n_list))
    targets = [path for pair in plan for path in pair if path is not None]
    refuse_overwriting_inputs(targets, scan_input_files(args.scan, gt=args.gt))
    check_output_targets(targets, overwrite=args.force)

    scan = read_scan(args, args.scan)
    start = time.perf_counter()
    snapshots = extract_snapshots(scan, args, profile, e_list, n_list, lmax, min_points)
    seconds = time.perf_counter() - start
    summary = {
        'scan': str(args.scan),
        'grid': list(scan.shape),
        'valid_fraction': scan.valid_fraction,
        'max_neighbor_distance': lmax,
        'sensor': args.sensor,
        'range_noise': args.range_noise,
        'seconds': seconds,
        'snapshots': [],
    }
    if not scan.organized and snapshots:
        projection = snapshots[0].meta['projection']
        summary['range_image'] = {
            'shape': list(projection.shape),
            'rows_from': projection.method,
            'azimuth_bins': projection.azimuth_bins,
            'lost_points': projection.lost_points,
        }
    files = []
    for planes, (path, png_path) in zip(snapshots, plan, strict=True):
        meta = {
            'scan': str(args.scan),
            'max_neighbor_distance': lmax,
            'sensor': args.sensor,
            'max_error_increment': planes.max_error_increment,
            'max_planes': planes.max_planes,
            'seconds': seconds,
        }
        files.append((path, planes_writer(path, planes, scan.points, meta=meta)))
        entry = {
            'file': str(path),
            'planes': planes.num_planes,
            'actions': planes.actions,
            'max_error_increment': planes.max_error_increment,
            'max_planes': planes.max_planes,
            'labelled_fraction': float((planes.labels > 0).mean()),
        }
        if png_path is not None:
            from ppe_ros.render import segmentation_png_writer

            picture, truth = _picture_labels(scan, planes)
            files.append(
                (
                    png_path,
                    segmentation_png_writer(
                        picture, ground_truth=truth, gt_min_label=scan.meta.get('min_plane_label', 1)
                    ),
                )
            )
            entry['png'] = str(png_path)
        summary['snapshots'].append(entry)
    write_files_atomically(files, overwrite=args.force)  # all complete, or none changed
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        grid = (
            f'{scan.shape[0]}x{scan.shape[1]} grid'
            if 'range_image' not in summary
            else '{} points on a {}x{} range image (rows from {})'.format(
                scan.shape[1], *summary['range_image']['shape'], summary['range_image']['rows_from']
            )
        )
        print(
            f'{args.scan}: {grid}, {scan.valid_fraction:.1%} valid, '
            f'extraction {seconds:.2f} s (lmax {lmax:g} m' + (f', sensor {args.sensor})' if args.sensor else ')')
        )
        unit = ' m^2' if profile is None or profile.noise is None else ''
        for entry in summary['snapshots']:
            which = (
                f'e = {entry["max_error_increment"]:g}{unit}'
                if entry['max_error_increment'] is not None
                else f'n = {entry["max_planes"]}'
            )
            extra = f', picture {entry["png"]}' if 'png' in entry else ''
            print(
                f'  {which}: {entry["planes"]} planes covering {entry["labelled_fraction"]:.1%} of the points '
                f'-> {entry["file"]}{extra}'
            )
    return 0
