"""Generated scans with real sensor errors (ppe_ros.core.synthetic_real): f and k of the sensor profiles
against PPE at the node's settings without a profile, Open3D's RANSAC loop and PEAC, on held-out scene seeds.

    .venv/bin/python benchmarks/bench_sensor_scans.py [--seeds 1000 1001 1002] [--kinds lidar depth_camera]
                                                       [--lidar-models os1-128 os1-32 vlp16 hdl32 hdl64]
                                                       [--no-ransac] [--no-peac] [--set NAME=VALUE ...]

PEAC runs through the external driver named by PEAC_BIN, as in bench_real.py (docs/benchmarks.md: Methods),
twice per kind (PEAC_SETTINGS): with bench_real's settings (its Ouster settings for the lidar sweeps, its
Kinect settings for the depth frames) and with settings chosen on the training seeds 0-3; without PEAC_BIN
it is skipped with a note.

``--set surface_tolerance=0.065`` measures a variant of the profiles (ppe_ros.benchmark.real.profile_with_settings;
on training seeds: ``--seeds 0 1 2 3``).

Seeds 1000-1999 are the test split of `ppe dataset make --kind lidar|depth_camera` (SENSOR_SEED_SPLITS):
the profiles' defaults were chosen on seeds below 1000. Prints one markdown table per sensor kind (f and k
pooled over the seeds as in ppe eval: f = correct / GT regions, k = mean over scans), for PPE the covariance
calibration against the generated true planes (ppe_ros.benchmark.real.truth_mahalanobis: the median
Mahalanobis² of the planes of >= 1000 points, with their count), the share of the clutter's points (trees,
cars, people, plants, lamps: CLUTTER_LABEL, non-planar things that should be no plane) that a method puts
in planes, and the machine.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_real

from ppe_ros import extract_planes
from ppe_ros.benchmark.real import CHI2_3_MEDIAN, profile_with_settings, truth_mahalanobis
from ppe_ros.benchmark.report import machine_description
from ppe_ros.core.evaluation import score_segmentation
from ppe_ros.core.synthetic_real import CLUTTER_LABEL, LIDAR_MODELS, generate_depth_scan, generate_lidar_scan

GENERATORS = {'lidar': generate_lidar_scan, 'depth_camera': generate_depth_scan}


#: PEAC's settings per sensor kind: (name, settings) of bench_real's (its Ouster and Kinect settings) and of the
#: best of a grid on the training seeds 0-3 (the largest f + k):
#: lidar 2 x 2 windows, min support 100, stdTol 10 / 20 mm, merge angle 30 deg; depth 6 x 6 windows, min
#: support 1000 (its other keys changed nothing there).
PEAC_SETTINGS = {
    'lidar': (
        ('PEAC (4x4 windows, min support 100)', bench_real.PEAC_OUSTER),
        (
            'PEAC tuned on seeds 0-3 (2x2 windows, min support 100, 10 / 20 mm)',
            {
                **bench_real.PEAC_OUSTER,
                'windowWidth': 2,
                'windowHeight': 2,
                'stdTol_init': 10,
                'stdTol_merge': 20,
                'similarityDegreeTh_merge': 30,
            },
        ),
    ),
    'depth_camera': (
        ('PEAC (10x10 windows, min support 3000)', bench_real.PEAC_KINECT),
        (
            'PEAC tuned on seeds 0-3 (6x6 windows, min support 1000)',
            {**bench_real.PEAC_KINECT, 'windowWidth': 6, 'windowHeight': 6, 'minSupport': 1000},
        ),
    ),
}


def methods(kind: str, with_ransac: bool, peac: str | None = None, settings: Sequence[str] = ()):
    """(name, function points, origins -> labels) of the compared methods; peac: the PEAC driver or None;
    settings: NAME=VALUE changes of the profile (profile_with_settings)."""
    profile = profile_with_settings(kind, settings)
    label = f'PPE sensor={kind}' + (f' ({", ".join(settings)})' if settings else '')
    out = [
        (label, lambda p, o: extract_planes(p, origins=o, sensor=profile)),
        (
            'PPE e 0.01, lmax inf, 20 points (no profile)',
            lambda p, o: extract_planes(p, origins=o, max_error_increment=0.01, min_plane_points=20),
        ),
    ]
    o3d = bench_real.open3d_or_none() if with_ransac else None
    if o3d is not None:
        out.append(('Open3D RANSAC loop + connected parts', lambda p, o: bench_real.run_ransac(o3d, p, kind)[0]))
    for name, settings in PEAC_SETTINGS[kind] if peac is not None else ():
        out.append((name, lambda p, o, settings=settings: bench_real.run_peac(peac, p, settings)[0]))
    return out


def run(
    kinds: list[str],
    seeds: list[int],
    with_ransac: bool,
    with_peac: bool = True,
    settings: Sequence[str] = (),
    lidar_models: Sequence[str] = ('os1-128',),
) -> None:
    print(f'machine: {machine_description()}; seeds {seeds}')
    peac, note = bench_real.peac_binary() if with_peac else (None, '')
    if note:
        print(note)
    for kind, model in [(k, m) for k in kinds for m in (lidar_models if k == 'lidar' else [None])]:
        scans = [GENERATORS[kind](seed=seed, **({} if model is None else {'model': model})) for seed in seeds]
        rows = []
        for name, method in methods(kind, with_ransac, peac, settings):
            scores, seconds, calibration, clutter = [], [], [], [0, 0]
            for scan in scans:
                start = time.perf_counter()
                result = method(scan.points, getattr(scan, 'origins', None))
                seconds.append(time.perf_counter() - start)
                labels = getattr(result, 'labels', result)
                scores.append(score_segmentation(labels, scan.labels))
                on_clutter = np.asarray(scan.labels).reshape(np.shape(labels)) == CLUTTER_LABEL
                clutter[0] += int(np.count_nonzero(np.asarray(labels)[on_clutter] > 0))
                clutter[1] += int(np.count_nonzero(on_clutter))
                if hasattr(result, 'covariances'):  # PPE's planes: their covariances against the true planes
                    calibration.extend(
                        truth_mahalanobis(
                            labels, result.offsets, result.normals, result.covariances, scan.labels, scan.plane_of_label
                        )
                    )
            f = sum(s.n_correct for s in scores) / max(sum(s.n_gt for s in scores), 1)
            k = float(np.mean([s.k for s in scores]))
            mahalanobis = f'{np.nanmedian(calibration):.2f} ({len(calibration)})' if calibration else ''
            in_planes = f'{100 * clutter[0] / clutter[1]:.1f} %' if clutter[1] else ''
            cells = (f'{100 * f:.1f} %', f'{100 * k:.1f} %', in_planes, mahalanobis, f'{np.median(seconds):.2f}')
            rows.append(f'| {name} | ' + ' | '.join(cells) + ' |')
        title = kind if model is None else f'{kind} {model}'
        print(
            f'\n### {title} ({len(seeds)} scans)\n\n| method | f | k | clutter points in planes | median Mahalanobis² '
            f'vs the true planes (planes >= 1000 points; calibrated {CHI2_3_MEDIAN:.2f}) | median s per scan |'
            '\n|---|---|---|---|---|---|'
        )
        print('\n'.join(rows))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[1000, 1001, 1002], help='scene seeds (test split)')
    parser.add_argument('--kinds', nargs='+', choices=tuple(GENERATORS), default=list(GENERATORS))
    parser.add_argument(
        '--lidar-models',
        nargs='+',
        choices=tuple(LIDAR_MODELS),
        default=['os1-128'],
        help='beam layouts of the generated lidar sweeps, one table each (default os1-128)',
    )
    parser.add_argument('--no-ransac', action='store_true', help='skip Open3D (also skipped when it is absent)')
    parser.add_argument('--no-peac', action='store_true', help='skip PEAC (also skipped without PEAC_BIN)')
    parser.add_argument(
        '--set', nargs='+', default=[], metavar='NAME=VALUE', help="the profiles' fields to change (JSON values)"
    )
    args = parser.parse_args(argv)
    try:
        for kind in args.kinds:
            profile_with_settings(kind, args.set)
    except ValueError as exc:
        print(f'bench_sensor_scans: error: {exc}', file=sys.stderr)
        return 2
    run(args.kinds, args.seeds, not args.no_ransac, not args.no_peac, args.set, args.lidar_models)
    return 0


if __name__ == '__main__':
    sys.exit(main())
