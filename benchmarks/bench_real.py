"""Real-data benchmark: plane extraction on the real scans of ../shared/data, printed as markdown tables.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_real.py [--sensor none|auto|paper|lidar|depth_camera]
        [--paper] [--methods ppe,ransac,peac] [--scans NAME ...] [--png-dir docs/real] [--json OUT.json]
        [--set NAME=VALUE ...]

Scans: the 7 Ouster sweeps (with their beam origins), the TLS scan (cm), the Kinect frame and ICL-NUIM 0-2;
each is marked 'training' (may be used to choose defaults) or 'reported' (ppe_ros.benchmark.real.SCAN_SPLIT).
Methods: ``ppe`` (this project: ``--sensor none`` = the node's defaults e 0.01, lmax inf, min 20 points;
``--paper`` = e 0.0484, lmax 0.18; ``--sensor auto`` = the sensor profile of each scan, 'lidar' or
'depth_camera', when extract_planes has the ``sensor`` argument; ``--set surface_tolerance=0.065`` changes
fields of the profiles for a variant, ppe_ros.benchmark.real.profile_with_settings), ``ransac`` (Open3D
segment_plane in a loop, each plane split into 4-connected parts of >= 20 pixels; skipped when Open3D is
absent) and ``peac`` (only when the environment variable PEAC_BIN names a driver that reads a scan and writes
labels; docs/benchmarks.md, Real scans, Methods).
Tables: per scan and method the plane counts, the share of valid points in planes of >= 1000 points, the
time, the ground cover of the Ouster sweeps and ICL-NUIM's f and k; then the repeatability and covariance
calibration over the consecutive sweeps OS-1-128 1795 -> 1796 -> 1797, and the registration they use.
The first run compiles numba kernels (about a minute); they are compiled on a tiny scan before any timing.
"""

from __future__ import annotations

import argparse
import inspect
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ppe_ros.benchmark.real import (
    CHI2_3_MEDIAN,
    REAL_SCANS,
    SEQUENCE_PAIRS,
    RangeImageProjector,
    connected_parts,
    count_planes,
    fit_ground_plane,
    ground_cover,
    match_plane_sets,
    match_planes,
    motion_difference,
    rigid_fit_from_planes,
    share_in_large_planes,
    summarize_matches,
)

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get('PPE_SHARED_DATA', REPO.parent / 'shared' / 'data'))

NODE_MAX_ERROR_INCREMENT = 0.01  # the extractor node's defaults
NODE_MAX_NEIGHBOR_DISTANCE = math.inf
PAPER_MAX_ERROR_INCREMENT = 0.0484  # the paper's / reference's SynPEB parameters
PAPER_MAX_NEIGHBOR_DISTANCE = 0.18
MIN_PLANE_POINTS = 20
LARGE_PLANE_POINTS = 1000
REGISTRATION_PLANE_POINTS = 100  # planes used by the rigid fit from planes
SENSOR_CHOICES = ('none', 'auto', 'paper', 'lidar', 'depth_camera')
METHOD_CHOICES = ('ppe', 'ransac', 'peac')

#: Open3D RANSAC loop: inlier distance (m) per scan kind, RANSAC iterations, stop below this many inliers.
RANSAC_DISTANCE = {'lidar': 0.05, 'depth_camera': 0.02}
RANSAC_ITERATIONS = 1000
RANSAC_MIN_INLIERS = 500
RANSAC_MAX_PLANES = 100

#: Settings passed to the PEAC driver (PEAC's ini names; mm and degrees): its own Kinect and TLS settings
#: (plane_fitter_pcd.ini = its built-in defaults, plane_fitter_pcd.tls.ini) and, for the Ouster sweeps, its
#: defaults with 4x4 windows, min support 100 and constant 30/40 mm tolerances (no depth-dependent term).
PEAC_KINECT = {
    'stdTol_merge': 8,
    'stdTol_init': 5,
    'depthSigma': 1.6e-6,
    'z_near': 500,
    'z_far': 4000,
    'angleDegree_near': 15,
    'angleDegree_far': 90,
    'similarityDegreeTh_merge': 60,
    'similarityDegreeTh_refine': 30,
    'depthAlpha': 0.04,
    'depthChangeTol': 0.02,
    'initType': 0,
    'minSupport': 3000,
    'windowWidth': 10,
    'windowHeight': 10,
    'doRefine': 1,
}
PEAC_TLS = {
    'stdTol_merge': 6,
    'stdTol_init': 3,
    'depthSigma': 0,
    'z_near': 500,
    'z_far': 4000,
    'angleDegree_near': 15,
    'angleDegree_far': 45,
    'similarityDegreeTh_merge': 45,
    'similarityDegreeTh_refine': 15,
    'depthAlpha': 0.004,
    'depthChangeTol': 30,
    'initType': 1,
    'minSupport': 200,
    'windowWidth': 10,
    'windowHeight': 10,
    'doRefine': 1,
}
PEAC_OUSTER = {
    **PEAC_KINECT,
    'depthSigma': 0,
    'windowWidth': 4,
    'windowHeight': 4,
    'minSupport': 100,
    'stdTol_init': 30,
    'stdTol_merge': 40,
}


def peac_settings(spec) -> dict:
    if spec.kind == 'depth_camera':
        return PEAC_KINECT
    return PEAC_OUSTER if spec.name.startswith('OS-') else PEAC_TLS


class BenchmarkError(Exception):
    """Bad input of the benchmark: one line for the user, exit code 2."""


# --------------------------------------------------------------------------------------------- methods


def has_sensor_argument() -> bool:
    from ppe_ros import extract_planes

    return 'sensor' in inspect.signature(extract_planes).parameters


def ppe_settings(sensor: str, paper: bool, kind: str, settings: Sequence[str] = ()) -> tuple[dict, str]:
    """Keyword arguments of extract_planes for a scan kind, and the method's name in the tables; ``settings``
    (``NAME=VALUE``, JSON values) change fields of a sensor profile."""
    if paper:
        return (
            {
                'max_error_increment': PAPER_MAX_ERROR_INCREMENT,
                'max_neighbor_distance': PAPER_MAX_NEIGHBOR_DISTANCE,
                'min_plane_points': MIN_PLANE_POINTS,
            },
            'PPE paper (e 0.0484, lmax 0.18)',
        )
    if sensor == 'none':
        return (
            {
                'max_error_increment': NODE_MAX_ERROR_INCREMENT,
                'max_neighbor_distance': NODE_MAX_NEIGHBOR_DISTANCE,
                'min_plane_points': MIN_PLANE_POINTS,
            },
            'PPE node defaults (e 0.01, lmax inf)',
        )
    profile = kind if sensor == 'auto' else sensor
    if settings:
        from ppe_ros.benchmark.real import profile_with_settings

        return {'sensor': profile_with_settings(profile, settings)}, f'PPE sensor={profile} ({" ".join(settings)})'
    return {'sensor': profile}, f'PPE sensor={profile}'


def run_ppe(points, origins, kwargs):
    from ppe_ros import extract_planes

    start = time.perf_counter()
    planes = extract_planes(points, origins=origins, **kwargs)
    return planes, time.perf_counter() - start


def open3d_or_none():
    try:
        import open3d
    except ImportError:
        return None
    return open3d


def run_ransac(o3d, points, kind):
    """Open3D segment_plane in a loop, then each plane's inliers split into 4-connected parts (>= 20 px)."""
    height, width = points.shape[:2]
    flat = points.reshape(-1, 3)
    remaining = np.flatnonzero(np.isfinite(flat).all(axis=1))
    labels = np.zeros(height * width, np.int64)
    start = time.perf_counter()
    o3d.utility.random.seed(0)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(flat[remaining]))
    label = 0
    while len(remaining) >= max(RANSAC_MIN_INLIERS, 3) and label < RANSAC_MAX_PLANES:
        _, inliers = cloud.segment_plane(
            distance_threshold=RANSAC_DISTANCE[kind], ransac_n=3, num_iterations=RANSAC_ITERATIONS
        )
        inliers = np.asarray(inliers, dtype=np.int64)
        if len(inliers) < RANSAC_MIN_INLIERS:
            break
        label += 1
        labels[remaining[inliers]] = label
        cloud = cloud.select_by_index(inliers.tolist(), invert=True)
        remaining = np.delete(remaining, inliers)
    parts = connected_parts(labels.reshape(height, width), MIN_PLANE_POINTS)
    return parts, time.perf_counter() - start


def peac_binary():
    """(the PEAC driver named by PEAC_BIN, None) or (None, a note saying why PEAC is skipped)."""
    binary = os.environ.get('PEAC_BIN')
    if not binary:
        return None, 'peac skipped: set PEAC_BIN to a PEAC driver (docs/benchmarks.md: Methods)'
    if not os.access(binary, os.X_OK) or not os.path.isfile(binary):
        return None, f'peac skipped: PEAC_BIN={binary} is not an executable file'
    return binary, ''


def run_peac(binary, points, settings):
    """PEAC through an external driver: ``$PEAC_BIN IN.bin OUT.bin key=value...`` (docs/benchmarks.md: Methods)."""
    height, width = points.shape[:2]
    with tempfile.TemporaryDirectory() as tmp:
        inp, out = Path(tmp) / 'cloud.bin', Path(tmp) / 'labels.bin'
        with inp.open('wb') as handle:
            np.array([height, width], '<i4').tofile(handle)
            np.ascontiguousarray(points, dtype='<f8').tofile(handle)
        start = time.perf_counter()
        options = [f'{key}={value:g}' for key, value in settings.items()]
        result = subprocess.run([binary, str(inp), str(out), *options], capture_output=True, text=True, timeout=600)
        seconds = time.perf_counter() - start
        if result.returncode != 0 or not out.is_file():
            raise RuntimeError(f'PEAC driver failed ({result.returncode}): {result.stderr.strip()[-300:]}')
        labels = np.fromfile(out, '<i4')
    if labels.size != height * width:
        raise RuntimeError(f'PEAC driver wrote {labels.size} labels for a {height}x{width} grid')
    reported = result.stdout.strip().splitlines()
    for line in reported:  # the driver may report its own extraction time (without file input/output)
        if line.startswith('seconds '):
            seconds = float(line.split()[1])
    return labels.reshape(height, width).astype(np.int64), seconds


def warm_up(specs, data, sensor, paper, settings=()):
    """Compile the numba kernels before anything is timed.

    Runs PPE once per scan kind on the first scan of that kind, subsampled to a quarter of its rows and
    columns: a real scene reaches every code path (the sensor profiles' later stages too), which a tiny
    synthetic plane does not.
    """
    from ppe_ros.io import load_scan

    seen = set()
    for spec in specs:
        if spec.kind in seen:
            continue
        seen.add(spec.kind)
        scan = load_scan(Path(data) / spec.path, units=spec.units)
        origins = scan.origins
        if origins is not None and np.ndim(origins) == 3:
            origins = np.ascontiguousarray(origins[::4, ::4])
        kwargs = ppe_settings(sensor, paper, spec.kind, settings)[0]
        run_ppe(np.ascontiguousarray(scan.points[::4, ::4]), origins, kwargs)
    connected_parts(np.ones((4, 4), np.int64))


# --------------------------------------------------------------------------------------------- per scan


def scan_metrics(spec, scan, labels, seconds, ground):
    from ppe_ros.core.evaluation import score_segmentation

    row = {
        'planes_20': count_planes(labels, MIN_PLANE_POINTS),
        'planes_100': count_planes(labels, 100),
        'large_share': share_in_large_planes(labels, scan.valid, LARGE_PLANE_POINTS),
        'seconds': seconds,
    }
    if ground is not None:
        cover = ground_cover(labels, ground.mask, 0.8)
        row.update(
            ground_points=cover.ground_points,
            ground_largest=cover.largest_share,
            ground_planes_80=cover.planes_for_share,
            ground_covered=cover.covered_share,
        )
    if spec.labelled and scan.labels is not None:
        score = score_segmentation(
            labels, scan.labels, gt_min_label=int(scan.meta.get('min_plane_label', 1)), valid=scan.valid
        )
        row.update(f=score.f, k=score.k, n_gt=score.n_gt)
    return row


def plane_arrays(planes):
    return planes.labels, planes.normals, planes.offsets, planes.covariances


def fitted_planes(points, origins, labels):
    from ppe_ros.core.fitting import fit_labeled_planes

    return fit_labeled_planes(points, labels, origins=origins, min_plane_points=MIN_PLANE_POINTS).planes


# --------------------------------------------------------------------------------------------- registration


def register_open3d(o3d, points_a, points_b):
    """Point-to-plane ICP of sweep A onto sweep B (0.1 m voxels, 1.0 -> 0.3 -> 0.1 m correspondences)."""

    def cloud(points):
        flat = points.reshape(-1, 3)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(flat[np.isfinite(flat).all(axis=1)]))
        pcd = pcd.voxel_down_sample(0.1)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.5, max_nn=30))
        return pcd

    source, target = cloud(points_a), cloud(points_b)
    transform = np.eye(4)
    result = None
    for distance in (1.0, 0.3, 0.1):
        result = o3d.pipelines.registration.registration_icp(
            source,
            target,
            distance,
            transform,
            o3d.pipelines.registration.TransformationEstimationPointToPlane(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=50),
        )
        transform = np.asarray(result.transformation)
    return (
        transform[:3, :3].copy(),
        transform[:3, 3].copy(),
        {
            'method': 'Open3D point-to-plane ICP',
            'fitness': float(result.fitness),
            'inlier_rmse': float(result.inlier_rmse),
        },
    )


def register_planes(labels_a, points_a, planes_a, labels_b, points_b, origins_b, planes_b):
    """Rigid fit from matched planes (Open3D absent or --registration planes).

    Planes of >= 100 points are matched at the identity (normal < 5 deg, offset < 0.5 m), the motion is fitted
    (rigid_fit_from_planes, weighted by size) and the planes are re-matched with tighter gates (2 deg, 0.1 m,
    IoU > 0.3), six rounds. Less accurate than ICP in a street, where few planes constrain the motion along it
    (OS-1-128: 2-5 cm off ICP's translation); the method string gives the weakest direction's share.
    """
    projector = RangeImageProjector(points_b, origins_b)
    rotation, translation = np.eye(3), np.zeros(3)
    used, weakest = 0, math.nan
    for round_index in range(6):
        max_angle, max_offset, min_iou = (5.0, 0.5, 0.0) if round_index == 0 else (2.0, 0.1, 0.3)
        matches = [
            m
            for m in match_planes(
                labels_a,
                points_a,
                planes_a.normals,
                planes_a.offsets,
                None,
                labels_b,
                projector,
                planes_b.normals,
                planes_b.offsets,
                None,
                rotation,
                translation,
                min_points=REGISTRATION_PLANE_POINTS,
            )
            if m.label_b > 0 and m.angle_deg < max_angle and m.offset_diff < max_offset and m.iou > min_iou
        ]
        if len(matches) < 3:
            break
        ia = np.array([m.label_a - 1 for m in matches])
        ib = np.array([m.label_b - 1 for m in matches])
        weights = np.array([m.points_a for m in matches], float)
        try:
            rotation, translation = rigid_fit_from_planes(
                planes_a.normals[ia], planes_a.offsets[ia], planes_b.normals[ib], planes_b.offsets[ib], weights
            )
        except ValueError:
            break
        moved = planes_a.normals[ia] @ rotation.T
        eigenvalues = np.linalg.eigvalsh((weights[:, None] * moved).T @ moved)
        used, weakest = len(matches), float(eigenvalues[0] / eigenvalues[-1])
    return (
        rotation,
        translation,
        {
            'method': f'rigid fit from {used} matched planes (weakest direction '
            f'{100 * weakest:.1f} % of the strongest)',
            'fitness': math.nan,
            'inlier_rmse': math.nan,
        },
    )


# --------------------------------------------------------------------------------------------- tables


def pct(value, digits=1):
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return ''
    return f'{100 * value:.{digits}f} %'


def num(value, fmt='{:.2f}'):
    return '' if value is None or (isinstance(value, float) and not math.isfinite(value)) else fmt.format(value)


def markdown(header, rows):
    lines = ['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
    lines += ['| ' + ' | '.join(str(c) for c in row) + ' |' for row in rows]
    return '\n'.join(lines)


def main_table(results):
    header = [
        'scan',
        'split',
        'method',
        'planes >= 20',
        'planes >= 100',
        'valid pts in planes >= 1000',
        'time s',
        'ground pts (25 m)',
        'ground: largest plane',
        'ground: planes for 80 %',
        'ICL f',
        'ICL k',
    ]
    rows = []
    for r in results:
        if 'error' in r:
            rows.append([r['scan'], r['split'], r['method'], f'failed: {r["error"]}'] + [''] * 8)
            continue
        g80 = r.get('ground_planes_80', '')
        if 'ground_points' in r and g80 is None:
            g80 = f'never ({pct(r["ground_covered"], 0)} in planes)'
        rows.append(
            [
                r['scan'],
                r['split'],
                r['method'],
                r['planes_20'],
                r['planes_100'],
                pct(r['large_share']),
                num(r['seconds']),
                r.get('ground_points', ''),
                pct(r.get('ground_largest')),
                g80,
                pct(r.get('f')),
                pct(r.get('k')),
            ]
        )
    return markdown(header, rows)


def repeat_table(pairs):
    header = [
        'A -> B',
        'method',
        'planes >= 1000 in A',
        'found again',
        'not found: IoU < 0.7 / angle >= 2 deg / offset >= 5 cm',
        'median IoU',
        'matched pairs',
        'median angle deg',
        'median abs(d_A - d_B) mm',
        'median gap at the planes mm',
        'median predicted sigma_d mm',
        f'median Mahalanobis² (calibrated {CHI2_3_MEDIAN:.2f})',
        'same + registration error',
    ]
    rows = []
    for p in pairs:
        s = p['summary']
        found = f'{s["found"]} / {s["planes"]} ({pct(s["found_share"], 0)})' if s['planes'] else '0 / 0'
        rows.append(
            [
                p['pair'],
                p['method'],
                s['planes'],
                found,
                f'{s.get("missed_iou", 0)} / {s.get("missed_angle", 0)} / {s.get("missed_offset", 0)}',
                num(s['median_iou']),
                s['pairs'],
                num(s['median_angle_deg']),
                num(1000 * s['median_offset_diff'], '{:.1f}'),
                num(1000 * s.get('median_gap_at_planes', math.nan), '{:.1f}'),
                num(1000 * s['median_sigma_d_predicted'], '{:.1f}'),
                num(s['median_mahalanobis2'], '{:.1f}'),
                num(s['median_mahalanobis2_with_registration'], '{:.1f}'),
            ]
        )
    return markdown(header, rows)


def registration_table(registrations, chain):
    header = ['A -> B', 'registration', 'motion m', 'rotation deg', 'ICP fitness', 'ICP inlier RMSE mm']
    rows = [
        [
            r['pair'],
            r['method'],
            num(r['translation'], '{:.3f}'),
            num(r['rotation_deg'], '{:.3f}'),
            num(r['fitness'], '{:.3f}'),
            num(1000 * r['inlier_rmse'], '{:.1f}'),
        ]
        for r in registrations
    ]
    text = markdown(header, rows)
    if chain is not None:
        text += (
            f'\n\nRegistration error estimate: the loop {chain["pair"]} registered directly differs from the '
            f'composition of the two steps by {chain["rotation_deg"]:.3f} deg and '
            f'{1000 * chain["translation"]:.1f} mm; three registrations enter that loop, so one registration '
            f'is taken to err by {chain["sigma_rotation_deg"]:.3f} deg and '
            f'{1000 * chain["sigma_translation"]:.1f} mm per axis (1 sigma). This error is in abs(d_A - d_B) '
            f"and in the Mahalanobis², not in the planes' covariances; the last column of the repeatability "
            f'table adds it (ppe_ros.benchmark.real.registration_covariance).'
        )
    return text


# --------------------------------------------------------------------------------------------- main


def parse_args(argv):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--data', default=str(SHARED), help='the shared data folder (default ../shared/data)')
    parser.add_argument(
        '--scans',
        nargs='+',
        default=None,
        metavar='NAME',
        help='subset of scans by name or prefix (e.g. "OS-1-128" "ICL-NUIM 0"); default all',
    )
    parser.add_argument(
        '--methods',
        default='ppe,ransac,peac',
        help='comma-separated methods: ppe, ransac (Open3D), peac (needs PEAC_BIN); default all',
    )
    parser.add_argument(
        '--sensor',
        choices=SENSOR_CHOICES,
        default='none',
        help='PPE profile: none = node defaults without the sensor argument (default); auto = '
        "'lidar' for Ouster/TLS, 'depth_camera' for Kinect/ICL; or one profile for all",
    )
    parser.add_argument('--paper', action='store_true', help="PPE at the paper's e 0.0484 m², lmax 0.18 m")
    parser.add_argument('--png-dir', default=None, help='write a segmentation PNG per scan and method here')
    parser.add_argument('--json', default=None, help='also write all numbers to this JSON file')
    parser.add_argument('--no-repeat', action='store_true', help='skip the repeatability / covariance tables')
    parser.add_argument(
        '--registration',
        choices=('auto', 'icp', 'planes'),
        default='auto',
        help='registration of consecutive sweeps: icp = Open3D point-to-plane ICP, planes = rigid fit '
        "from the first method's matched planes; auto (default) = icp when Open3D is installed",
    )
    parser.add_argument(
        '--set',
        nargs='+',
        default=[],
        metavar='NAME=VALUE',
        help='fields of the sensor profile(s) to change (JSON values), e.g. surface_tolerance=0.065',
    )
    args = parser.parse_args(argv)
    methods = [m.strip() for m in args.methods.split(',') if m.strip()]
    unknown = sorted(set(methods) - set(METHOD_CHOICES))
    if unknown or not methods:
        raise BenchmarkError(
            f'unknown method(s) {", ".join(unknown) or "(none given)"}; choose from {", ".join(METHOD_CHOICES)}'
        )
    args.methods = methods
    if args.paper and args.sensor != 'none':
        raise BenchmarkError('--paper sets e and lmax itself; it cannot be combined with --sensor')
    if args.set:
        if args.paper or args.sensor == 'none':
            raise BenchmarkError('--set changes a sensor profile: give --sensor auto, lidar, depth_camera or paper')
        from ppe_ros.benchmark.real import profile_with_settings

        for profile in sorted({s.kind for s in REAL_SCANS}) if args.sensor == 'auto' else [args.sensor]:
            try:
                profile_with_settings(profile, args.set)
            except ValueError as exc:
                raise BenchmarkError(f'--set: {exc}') from None
    if args.sensor != 'none' and not has_sensor_argument():
        raise BenchmarkError(
            f"--sensor {args.sensor}: this ppe_ros's extract_planes has no sensor argument yet; "
            f'use --sensor none or --paper'
        )
    specs = list(REAL_SCANS)
    if args.scans:
        chosen = [s for s in specs if any(s.name == n or s.name.startswith(n) for n in args.scans)]
        if not chosen:
            raise BenchmarkError(f'no scan matches {args.scans}; scans: {", ".join(s.name for s in specs)}')
        specs = chosen
    args.specs = specs
    data = Path(args.data)
    missing = [s.path for s in specs if not (data / s.path).is_file()]
    if missing:
        raise BenchmarkError(f'missing scan files under {data}: {", ".join(missing)}')
    if args.png_dir:
        Path(args.png_dir).mkdir(parents=True, exist_ok=True)
    return args


def available_methods(methods):
    """(name -> runner handle, notes for skipped methods)."""
    handles, notes = {}, []
    for name in methods:
        if name == 'ppe':
            handles[name] = True
        elif name == 'ransac':
            o3d = open3d_or_none()
            if o3d is None:
                notes.append(
                    'ransac skipped: Open3D is not installed (pip install the open3d pinned in '
                    'requirements.txt; Debian also needs apt-get install libusb-1.0-0)'
                )
            else:
                handles[name] = o3d
        elif name == 'peac':
            binary, note = peac_binary()
            if binary is None:
                notes.append(note)
            else:
                handles[name] = binary
    return handles, notes


def png_tag(method: str, kwargs: dict, paper: bool, settings: Sequence[str] = ()) -> str:
    """The method's part of a PNG's name: ppe_paper, ppe_node, ppe_<profile> (a changed profile: its name and
    the --set settings, never the profile's whole repr), or the method's key."""
    if method != 'ppe':
        return method
    if 'sensor' not in kwargs:
        return 'ppe_paper' if paper else 'ppe_node'
    sensor = kwargs['sensor']
    name = getattr(sensor, 'name', sensor)
    return '_'.join([f'ppe_{name}', *settings]) if settings else f'ppe_{name}'


def png_path(directory, scan_name, method):
    slug = lambda text: ''.join(c if c.isalnum() else '_' for c in text).strip('_')  # noqa: E731
    return Path(directory) / f'{slug(scan_name)}_{slug(method)}.png'


def run(args) -> int:
    from ppe_ros.io import load_scan

    handles, notes = available_methods(args.methods)
    for note in notes:
        print(f'note: {note}', file=sys.stderr)
    if 'ppe' in handles:
        warm_up(args.specs, args.data, args.sensor, args.paper, args.set)
    sequence_names = {name for pair in SEQUENCE_PAIRS for name in pair}
    chosen_names = {s.name for s in args.specs}
    keep_sequence = not args.no_repeat and any(all(n in chosen_names for n in pair) for pair in SEQUENCE_PAIRS)
    results, kept = [], {}
    for spec in args.specs:
        scan = load_scan(Path(args.data) / spec.path, units=spec.units)
        ground = fit_ground_plane(scan.points) if spec.ground else None
        for method in handles:
            try:
                if method == 'ppe':
                    kwargs, label = ppe_settings(args.sensor, args.paper, spec.kind, args.set)
                    planes, seconds = run_ppe(scan.points, scan.origins, kwargs)
                    labels = planes.labels
                else:
                    if method == 'ransac':
                        labels, seconds = run_ransac(handles[method], scan.points, spec.kind)
                        label = f'Open3D RANSAC loop ({RANSAC_DISTANCE[spec.kind] * 100:g} cm) + connected parts'
                    else:
                        settings = peac_settings(spec)
                        labels, seconds = run_peac(handles[method], scan.points, settings)
                        label = (
                            f'PEAC ({settings["windowWidth"]}x{settings["windowHeight"]} windows, min support '
                            f'{settings["minSupport"]})'
                        )
                    planes = None
            except Exception as exc:  # a failing method must not lose the other rows
                results.append(
                    {'scan': spec.name, 'split': spec.split, 'method': method, 'error': f'{type(exc).__name__}: {exc}'}
                )
                print(f'note: {method} failed on {spec.name}: {exc}', file=sys.stderr)
                continue
            row = {'scan': spec.name, 'split': spec.split, 'method': label, 'method_key': method}
            row.update(scan_metrics(spec, scan, labels, seconds, ground))
            results.append(row)
            print(f'{spec.name}: {label}: {row["planes_20"]} planes, {seconds:.2f} s', file=sys.stderr)
            if args.png_dir:
                from ppe_ros.render import save_segmentation_png

                height, width = labels.shape
                scale = max(1, min(math.ceil(400 / height), max(1, 4096 // width)))
                save_segmentation_png(
                    png_path(args.png_dir, spec.name, png_tag(method, kwargs, args.paper, args.set)),
                    labels,
                    ground_truth=scan.labels if spec.labelled else None,
                    gt_min_label=int(scan.meta.get('min_plane_label', 1)),
                    scale=scale,
                )
            if keep_sequence and spec.name in sequence_names:
                if planes is None:
                    planes = fitted_planes(scan.points, scan.origins, labels)
                kept[(spec.name, method)] = (scan, planes, label)

    print('## Real scans\n')
    print(main_table(results))
    output = {'results': results, 'notes': notes}
    if keep_sequence:
        pairs_out, registrations, chain = repeatability(args, handles, kept)
        print('\n## Repeatability and covariance calibration (planes of >= 1000 points)\n')
        print(repeat_table(pairs_out))
        print('\n## Registration of the consecutive sweeps\n')
        print(registration_table(registrations, chain))
        output.update(repeatability=pairs_out, registration=registrations, registration_chain=chain)
    for note in notes:
        print(f'\nNote: {note}')
    if args.json:
        Path(args.json).write_text(json.dumps(output, indent=2, default=_json_default) + '\n', encoding='utf-8')
    return 0


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f'not JSON serialisable: {type(value).__name__}')


def repeatability(args, handles, kept):
    o3d = None if args.registration == 'planes' else handles.get('ransac') or open3d_or_none()
    if args.registration == 'icp' and o3d is None:
        raise BenchmarkError('--registration icp needs Open3D (not installed)')
    methods = [m for m in handles if all((name, m) in kept for pair in SEQUENCE_PAIRS for name in pair)]
    motions, registrations = {}, []
    pair_list = [p for p in SEQUENCE_PAIRS if all((n, methods[0]) in kept for n in p)] if methods else []
    for a, b in pair_list:
        scan_a, planes_a, _ = kept[(a, methods[0])]
        scan_b, planes_b, _ = kept[(b, methods[0])]
        if o3d is not None:
            motion = register_open3d(o3d, scan_a.points, scan_b.points)
        else:
            motion = register_planes(
                planes_a.labels, scan_a.points, planes_a, planes_b.labels, scan_b.points, scan_b.origins, planes_b
            )
        motions[(a, b)] = motion
        angle, _ = motion_difference(np.eye(3), np.zeros(3), motion[0], motion[1])
        registrations.append(
            {'pair': f'{a} -> {b}', 'translation': float(np.linalg.norm(motion[1])), 'rotation_deg': angle, **motion[2]}
        )
    chain = None
    if len(pair_list) == 2 and o3d is not None:
        (a, b), (_, c) = pair_list
        r13, t13, _ = register_open3d(o3d, kept[(a, methods[0])][0].points, kept[(c, methods[0])][0].points)
        r12, t12, _ = motions[pair_list[0]]
        r23, t23, _ = motions[pair_list[1]]
        angle, dist = motion_difference(r13, t13, r23 @ r12, r23 @ t12 + t23)
        # three registration errors enter the loop: per registration and axis about |loop error| / 3
        chain = {
            'pair': f'{a} -> {c}',
            'rotation_deg': angle,
            'translation': dist,
            'sigma_translation': dist / 3,
            'sigma_rotation_deg': angle / 3,
        }
    registration_sigma = (
        None if chain is None else (chain['sigma_translation'], math.radians(chain['sigma_rotation_deg']))
    )
    pairs_out = []
    for method in methods:
        for a, b in pair_list:
            scan_a, planes_a, label = kept[(a, method)]
            scan_b, planes_b, _ = kept[(b, method)]
            rotation, translation, _ = motions[(a, b)]
            matches = match_plane_sets(
                scan_a.points,
                planes_a,
                scan_b.points,
                scan_b.origins,
                planes_b,
                rotation,
                translation,
                min_points=LARGE_PLANE_POINTS,
                registration_sigma=registration_sigma,
            )
            pairs_out.append(
                {
                    'pair': f'{a} -> {b}',
                    'method': label,
                    'summary': summarize_matches(matches).__dict__,
                    'matches': [m.__dict__ for m in matches],
                }
            )
    return pairs_out, registrations, chain


def main(argv: list[str] | None = None) -> int:
    try:
        args = parse_args(argv)
        return run(args)
    except BenchmarkError as exc:
        print(f'bench_real: error: {exc}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
