"""Benchmark data sets: generated scans with ground truth, train and test splits, one folder per level.

Three kinds (``make_dataset(kind=...)``, ``ppe dataset make --kind``):

* ``synpeb`` (default): SynPEB-style room scans per radial noise level, described below.
* ``lidar``: spinning-lidar sweeps of streets with real sensor errors
  (:func:`ppe_ros.core.synthetic_real.generate_lidar_scan`), one level per lidar model.
* ``depth_camera``: Kinect-v1-like depth frames of rooms with its errors
  (:func:`ppe_ros.core.synthetic_real.generate_depth_scan`), one level ``kinect-v1``.

Layout of a ``lidar`` / ``depth_camera`` data set::

    DIR/dataset.json
    DIR/<split>/<level>/<level>_NN.npy         (H, W, 3) float32 points, metres, NaN = no return
    DIR/<split>/<level>/<level>_NN_labels.npy  (H, W) int32 ground truth: one label (>= 10) per planar
                                               surface; 0 = clutter, too small surfaces and no return
    DIR/<split>/<level>/<level>.json           lidar only: Ouster-style metadata, so that
                                               ppe_ros.io.load_scan gives the beam origins

The points are in the sensor frame (lidar: x forward, y left, z up, destaggered; depth camera:
optical frame x right, y down, z forward). Their scene seeds come from :data:`SENSOR_SEED_SPLITS`:
train scans use seeds 0..999 and test (held-out) scans 1000..1999, so parameters tuned on the train
split never see a held-out scene.

SynPEB kind:

Layout of a data set directory::

    DIR/dataset.json                         parameters and one entry per scan (see make_dataset)
    DIR/<split>/<level>/pc_NN.pcd            split = train | test, level = sigma_0mm, sigma_7.1mm, ...

Each scan is a SynPEB-format PCD: fields ``x y z intensity`` (float32, metres, sensor frame: x
forward, y left, z up, sensor at the origin), organized ``WIDTH x HEIGHT``, ``DATA
binary_compressed``; the intensity holds the ground-truth plane label (>= 10; 3 = a visible piece of a
face too small to be a GT plane, as SynPEB's label 3; 0 = no return, whose point is NaN). Point k is
row ``k // WIDTH``, column ``k % WIDTH``; row 0 is the top.

Noise levels: SynPEB's folders gt, var1..var4 hold radial noise *variances* of 0, 0.5, 1, 2 and 4
cm^2, i.e. sigma = 0, 7.1, 10, 14.1 and 20 mm (the two shared noisy SynPEB scans measure 20 mm).
Each scan's room and sensor pose come from its scene seed; the same scenes are used at every noise
level (as SynPEB's levels share their scenes), train and test scenes differ.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ppe_ros.core.synthetic import (
    DEFAULT_MIN_REGION_PIXELS,
    SYNPEB_COLS,
    SYNPEB_ROWS,
    ScanGrid,
    SensorPose,
    generate_scan,
    make_room_scene,
)

MANIFEST_NAME = 'dataset.json'
FORMAT_NAME = 'ppe_ros SynPEB-style benchmark'

SYNPEB_VARIANCES_CM2 = (0.0, 0.5, 1.0, 2.0, 4.0)
"""Radial noise variances (cm^2) of SynPEB's levels gt, var1..var4."""

DEFAULT_SIGMAS = tuple(math.sqrt(v) * 0.01 for v in SYNPEB_VARIANCES_CM2)
"""Radial noise sigmas (m): 0, 7.07, 10, 14.1 and 20 mm."""

DEFAULT_ANGULAR_SIGMA_DEG = 0.001
DEFAULT_N_OBJECTS = 10
"""Objects per room: about 40 GT planes per 500 x 500 scan with the random sensor poses here (SynPEB: 42.6)."""

DEFAULT_TRAIN = 10
DEFAULT_TEST = 30
SPLITS = ('train', 'test')

_TEST_SEED_OFFSET = 50_000  # scene seeds: seed * 100000 + index (train) or + 50000 + index (test)

DATASET_KINDS = ('synpeb', 'lidar', 'depth_camera')
"""What ``make_dataset`` can generate (see the module docstring)."""

SENSOR_SEED_SPLITS: dict[str, tuple[int, int]] = {'train': (0, 1000), 'test': (1000, 2000)}
"""Scene seeds ``[first, end)`` of the ``lidar`` and ``depth_camera`` kinds per split: tune sensor
profiles on ``train`` (seeds 0-999) only; ``test`` (1000-1999) is held out."""

DEFAULT_LIDAR_MODELS = ('os1-128',)
DEPTH_CAMERA_LEVEL = 'kinect-v1'


def level_name(sigma: float) -> str:
    """Folder name of a noise level: ``sigma_14.1mm`` (sigma in metres, shown in mm to 0.1)."""
    millimetres = round(sigma * 1000.0, 1)
    text = f'{millimetres:.1f}'.rstrip('0').rstrip('.')
    return f'sigma_{text}mm'


def synpeb_grid(rows: int, cols: int) -> ScanGrid:
    """SynPEB's field of view on a ``rows x cols`` grid (500 x 500 gives exactly SynPEB's grid).

    Elevation ``linspace(+30, -30, rows)`` degrees, azimuth ``-35 + (70 / cols) * col`` degrees.
    """
    if int(rows) != rows or int(cols) != cols or rows < 2 or cols < 2:
        raise ValueError(f'rows and cols must be integers >= 2; got {rows} x {cols}')
    return ScanGrid(
        elevation_deg=np.linspace(30.0, -30.0, int(rows)), azimuth_deg=-35.0 + (70.0 / cols) * np.arange(cols)
    )


def min_region_pixels(rows: int, cols: int) -> int:
    """Smallest ground-truth region (pixels): the generator's 50 px on SynPEB's 500 x 500 grid, scaled with
    the pixel count (at least 4); smaller pieces of faces get label 3 (visible, no GT plane)."""
    return max(4, round(DEFAULT_MIN_REGION_PIXELS * rows * cols / (SYNPEB_ROWS * SYNPEB_COLS)))


def sensor_pose_for(scene_seed: int) -> SensorPose:
    """A random sensor pose (deterministic in the scene seed) in the default 7 x 6 x 3 m room.

    Position x 1.5..2.5 m, y 2.2..3.8 m, height 0.8..1.6 m; yaw -10..+30 deg, pitched 5..20 deg down,
    roll -3..+3 deg: the sensor looks into the room across the objects in front of it.
    """
    rng = np.random.default_rng([int(scene_seed), 7])
    position = (float(rng.uniform(1.5, 2.5)), float(rng.uniform(2.2, 3.8)), float(rng.uniform(0.8, 1.6)))
    return SensorPose(
        position=position,
        yaw_deg=float(rng.uniform(-10.0, 30.0)),
        pitch_deg=float(rng.uniform(5.0, 20.0)),
        roll_deg=float(rng.uniform(-3.0, 3.0)),
    )


def scene_seed_for(seed: int, split: str, index: int) -> int:
    """Scene seed of scan ``index`` (0-based) of a split."""
    if split not in SPLITS:
        raise ValueError(f'split must be one of {SPLITS}; got {split!r}')
    return int(seed) * 100_000 + (_TEST_SEED_OFFSET if split == 'test' else 0) + int(index)


@dataclass(frozen=True)
class DatasetScan:
    """One scan of a data set: where it is and what it is."""

    path: Path
    split: str
    level: str
    radial_sigma: float
    scene_seed: int
    n_planes: int

    @property
    def name(self) -> str:
        """``test/sigma_20mm/pc_01``."""
        return f'{self.split}/{self.level}/{self.path.stem}'


def _check_synpeb_levels(
    sigmas: Sequence[float], n_train: int, n_test: int, angular_sigma_deg: float
) -> tuple[list[float], list[str]]:
    """The noise levels (radial sigmas, metres) and their folder names; checks the scan counts and the jitter."""
    levels = [float(s) for s in sigmas]
    if not levels or any(not (math.isfinite(s) and s >= 0.0) for s in levels):
        raise ValueError(f'sigmas must be a non-empty list of finite noise levels >= 0 (metres); got {sigmas}')
    names = [level_name(s) for s in levels]
    if len(set(names)) != len(names):
        raise ValueError(f'noise levels must differ by at least 0.1 mm; got {sigmas}')
    for count, what in ((n_train, 'n_train'), (n_test, 'n_test')):
        if isinstance(count, bool) or int(count) != count or count < 0:
            raise ValueError(f'{what} must be a non-negative integer; got {count!r}')
    if n_train + n_test == 0:
        raise ValueError('the data set needs at least one scan (n_train + n_test >= 1)')
    if not (math.isfinite(angular_sigma_deg) and angular_sigma_deg >= 0.0):
        raise ValueError(f'angular_sigma_deg must be finite and >= 0; got {angular_sigma_deg}')
    return levels, names


def _new_dataset_directory(directory: str | os.PathLike[str]) -> Path:
    """Create the data set directory; refuse one that already holds a data set (nothing is overwritten)."""
    root = Path(directory)
    if (root / MANIFEST_NAME).exists() or any((root / split).exists() for split in SPLITS):
        raise FileExistsError(f'{root} already holds a data set; choose a new directory')
    root.mkdir(parents=True, exist_ok=True)
    return root


def _write_synpeb_scan(root: Path, split: str, index: int, level: str, scan, compressed: bool) -> Path:
    """Write one scan as ``root/split/level/pc_NN.pcd`` (SynPEB format, label in ``intensity``)."""
    from ppe_ros.io import save_pcd

    folder = root / split / level
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f'pc_{index + 1:02d}.pcd'
    points = np.where(np.isfinite(scan.points), scan.points, np.nan)
    save_pcd(path, points, extra_fields={'intensity': scan.labels.astype(np.float32)}, compressed=compressed)
    return path


def _synpeb_manifest(
    *,
    seed: int,
    rows: int,
    cols: int,
    angular_sigma_deg: float,
    n_objects: int,
    n_train: int,
    n_test: int,
    levels: list[float],
    names: list[str],
    min_region: int,
    entries: list[dict],
) -> dict:
    """The ``dataset.json`` content of a SynPEB-style data set."""
    return {
        'format': FORMAT_NAME,
        'seed': int(seed),
        'rows': int(rows),
        'cols': int(cols),
        'angular_sigma_deg': float(angular_sigma_deg),
        'n_objects': int(n_objects),
        'n_train': int(n_train),
        'n_test': int(n_test),
        'levels': [
            {'name': name, 'radial_sigma': sigma, 'variance_cm2': round((sigma * 100.0) ** 2, 6)}
            for sigma, name in zip(levels, names, strict=True)
        ],
        'min_region_pixels': min_region,
        'labels': 'PCD field intensity: ground-truth plane id (>= 10); 3 = visible but no GT plane (a face piece '
        f'smaller than {min_region} px); 0 = no return (NaN point)',
        'scans': entries,
    }


def make_dataset(
    directory: str | os.PathLike[str],
    *,
    kind: str = 'synpeb',
    seed: int = 0,
    sigmas: Sequence[float] = DEFAULT_SIGMAS,
    n_train: int = DEFAULT_TRAIN,
    n_test: int = DEFAULT_TEST,
    rows: int | None = None,
    cols: int | None = None,
    angular_sigma_deg: float = DEFAULT_ANGULAR_SIGMA_DEG,
    n_objects: int = DEFAULT_N_OBJECTS,
    compressed: bool = True,
    lidar_models: Sequence[str] = DEFAULT_LIDAR_MODELS,
    progress=None,
) -> dict:
    """Write a data set into ``directory`` (created; must not hold a data set already).

    Args:
        directory: output directory; refused if it already contains ``dataset.json`` or scan folders.
        kind: one of :data:`DATASET_KINDS`; ``'synpeb'`` (default) writes the SynPEB-style data set
            exactly as before the other kinds existed.
        seed: non-negative integer; every scene, pose and noise draw is deterministic in it. For the
            sensor kinds it offsets the scene seeds inside each split's range of
            :data:`SENSOR_SEED_SPLITS` (scan ``index`` of a split has seed ``first + seed + index``).
        sigmas: (synpeb) radial noise standard deviations in metres, one level each.
        n_train, n_test: scans per level in each split.
        rows, cols: grid size. synpeb: default 500 x 500; lidar: ``cols`` columns per sweep (default
            1024; the rows are the model's beams, ``rows`` must be None); depth_camera: default 480 x 640.
        angular_sigma_deg: (synpeb) beam-direction jitter (degrees per axis); SynPEB: 1 mdeg.
        n_objects: (synpeb, depth_camera) objects per room (default 10: about 40 planes per SynPEB scan).
        compressed: (synpeb) ``DATA binary_compressed`` (as SynPEB) instead of ``binary``.
        lidar_models: (lidar) one level per model of :data:`ppe_ros.core.synthetic_real.LIDAR_MODELS`.
        progress: optional callable ``progress(done, total)`` called after each written scan.

    Returns:
        The manifest (also written to ``dataset.json``).

    Raises:
        ValueError: bad parameters. FileExistsError: the directory already holds a data set.
    """
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f'seed must be a non-negative integer; got {seed!r}')
    if kind not in DATASET_KINDS:
        raise ValueError(f'kind must be one of {", ".join(DATASET_KINDS)}; got {kind!r}')
    if kind != 'synpeb':
        return _make_sensor_dataset(
            directory,
            kind=kind,
            seed=int(seed),
            n_train=n_train,
            n_test=n_test,
            rows=rows,
            cols=cols,
            n_objects=n_objects,
            lidar_models=lidar_models,
            progress=progress,
        )
    rows = 500 if rows is None else rows
    cols = 500 if cols is None else cols
    levels, names = _check_synpeb_levels(sigmas, n_train, n_test, angular_sigma_deg)
    grid = synpeb_grid(rows, cols)
    root = _new_dataset_directory(directory)
    min_region = min_region_pixels(rows, cols)
    if isinstance(n_objects, bool) or int(n_objects) != n_objects or n_objects < 0:
        raise ValueError(f'n_objects must be a non-negative integer; got {n_objects!r}')

    entries = []
    total = (n_train + n_test) * len(levels)
    done = 0
    for split, count in (('train', int(n_train)), ('test', int(n_test))):
        for index in range(count):
            scene_seed = scene_seed_for(seed, split, index)
            pose = sensor_pose_for(scene_seed)
            scene = make_room_scene(
                scene_seed, keep_clear=pose.position[:2], view_yaw_deg=pose.yaw_deg, n_objects=int(n_objects)
            )
            for sigma, name in zip(levels, names, strict=True):
                scan = generate_scan(
                    scene,
                    seed=scene_seed,
                    grid=grid,
                    sensor_pose=pose,
                    radial_sigma=sigma,
                    angular_sigma_deg=angular_sigma_deg,
                    min_region_pixels=min_region,
                )
                path = _write_synpeb_scan(root, split, index, name, scan, compressed)
                entries.append(
                    {
                        'file': path.relative_to(root).as_posix(),
                        'split': split,
                        'level': name,
                        'radial_sigma': sigma,
                        'scene_seed': scene_seed,
                        'n_planes': len(scan.visible_labels()),
                        'sensor_pose': pose.to_dict(),
                    }
                )
                done += 1
                if progress is not None:
                    progress(done, total)
    manifest = _synpeb_manifest(
        seed=seed,
        rows=rows,
        cols=cols,
        angular_sigma_deg=angular_sigma_deg,
        n_objects=n_objects,
        n_train=n_train,
        n_test=n_test,
        levels=levels,
        names=names,
        min_region=min_region,
        entries=entries,
    )
    (root / MANIFEST_NAME).write_text(json.dumps(manifest, indent=1) + '\n')
    return manifest


def sensor_scene_seed(split: str, index: int, *, seed: int = 0) -> int:
    """Scene seed of scan ``index`` of a split of a ``lidar`` / ``depth_camera`` data set.

    Raises:
        ValueError: unknown split, or the seed would leave the split's range of :data:`SENSOR_SEED_SPLITS`.
    """
    if split not in SENSOR_SEED_SPLITS:
        raise ValueError(f'split must be one of {tuple(SENSOR_SEED_SPLITS)}; got {split!r}')
    first, end = SENSOR_SEED_SPLITS[split]
    scene_seed = first + int(seed) + int(index)
    if not first <= scene_seed < end:
        raise ValueError(f'{split} scene seeds are {first}..{end - 1}: seed {seed} + scan {index} leaves the range')
    return scene_seed


def _ouster_metadata(model: str, cols: int, errors) -> dict:
    """Ouster-style sensor metadata of a generated sweep: with it ``load_scan`` reconstructs the beam
    origins of :func:`ppe_ros.core.synthetic_real.generate_lidar_scan` exactly (no pixel shifts, the
    lidar frame = the sensor frame)."""
    from ppe_ros.core.synthetic_real import LIDAR_MODELS

    altitudes = list(LIDAR_MODELS[model])
    return {
        'prod_line': f'ppe_ros synthetic {model}',
        'lidar_mode': f'{cols}x10',
        'beam_altitude_angles': altitudes,
        'beam_azimuth_angles': [0.0] * len(altitudes),
        'lidar_origin_to_beam_origin_mm': errors.beam_origin_radius * 1000.0,
        'lidar_to_sensor_transform': [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
        'data_format': {
            'pixels_per_column': len(altitudes),
            'columns_per_frame': int(cols),
            'column_window': [0, int(cols) - 1],
            'pixel_shift_by_row': [0] * len(altitudes),
        },
    }


def _check_sensor_counts(*, seed: int, n_train: int, n_test: int, n_objects: int) -> None:
    """Refuse scan and object counts that are not non-negative integers, or a split out of its seed range."""
    for count, what in ((n_train, 'n_train'), (n_test, 'n_test')):
        if isinstance(count, bool) or int(count) != count or count < 0:
            raise ValueError(f'{what} must be a non-negative integer; got {count!r}')
    if n_train + n_test == 0:
        raise ValueError('the data set needs at least one scan (n_train + n_test >= 1)')
    if isinstance(n_objects, bool) or int(n_objects) != n_objects or n_objects < 0:
        raise ValueError(f'n_objects must be a non-negative integer; got {n_objects!r}')
    for split, count in (('train', n_train), ('test', n_test)):
        if count:
            sensor_scene_seed(split, int(count) - 1, seed=seed)  # the whole split stays in its range


def _sensor_levels(*, kind: str, rows: int | None, cols: int | None, lidar_models: Sequence[str]) -> tuple:
    """The checked ``(rows, cols, errors, levels, error_params, shape_note)`` of a lidar or depth-camera data set."""
    from ppe_ros.core.synthetic_real import LIDAR_MODELS, DepthErrorModel, LidarErrorModel

    if kind == 'lidar':
        models = list(dict.fromkeys(lidar_models))
        unknown = [m for m in models if m not in LIDAR_MODELS]
        if not models or unknown:
            raise ValueError(f'lidar models must be some of {", ".join(LIDAR_MODELS)}; got {list(lidar_models)}')
        if rows is not None:
            raise ValueError('a lidar data set takes its rows from the lidar model; give cols only')
        cols = 1024 if cols is None else cols
        if isinstance(cols, bool) or int(cols) != cols or cols < 8:
            raise ValueError(f'cols must be an integer >= 8; got {cols!r}')
        errors = LidarErrorModel()
        levels = [
            {'name': m, 'radial_sigma': errors.range_sigma, 'model': m, 'rows': len(LIDAR_MODELS[m])} for m in models
        ]
        error_params = errors.to_dict()
        shape_note = f'{cols} columns'
    else:
        rows = 480 if rows is None else rows
        cols = 640 if cols is None else cols
        for value, what in ((rows, 'rows'), (cols, 'cols')):
            if isinstance(value, bool) or int(value) != value or value < 8:
                raise ValueError(f'{what} must be an integer >= 8; got {value!r}')
        errors = DepthErrorModel()
        levels = [
            {
                'name': DEPTH_CAMERA_LEVEL,
                'radial_sigma': errors.axial_noise_coefficient * 2.0**2,
                'rows': int(rows),
            }
        ]
        error_params = errors.to_dict()
        shape_note = f'{rows} x {cols}'
    return rows, cols, errors, levels, error_params, shape_note


def _make_sensor_dataset(
    directory,
    *,
    kind: str,
    seed: int,
    n_train: int,
    n_test: int,
    rows: int | None,
    cols: int | None,
    n_objects: int,
    lidar_models: Sequence[str],
    progress,
) -> dict:
    from ppe_ros.core.synthetic_real import generate_depth_scan, generate_lidar_scan, make_indoor_scene

    _check_sensor_counts(seed=seed, n_train=n_train, n_test=n_test, n_objects=n_objects)
    rows, cols, errors, levels, error_params, shape_note = _sensor_levels(
        kind=kind, rows=rows, cols=cols, lidar_models=lidar_models
    )
    root = Path(directory)
    if (root / MANIFEST_NAME).exists() or any((root / split).exists() for split in SPLITS):
        raise FileExistsError(f'{root} already holds a data set; choose a new directory')
    root.mkdir(parents=True, exist_ok=True)

    entries = []
    total = (n_train + n_test) * len(levels)
    done = 0
    for split, count in (('train', int(n_train)), ('test', int(n_test))):
        for level in levels:
            folder = root / split / level['name']
            folder.mkdir(parents=True, exist_ok=True)
            if kind == 'lidar':
                metadata = _ouster_metadata(level['model'], int(cols), errors)
                (folder / f'{level["name"]}.json').write_text(json.dumps(metadata, indent=1) + '\n')
            for index in range(count):
                scene_seed = sensor_scene_seed(split, index, seed=seed)
                if kind == 'lidar':
                    scan = generate_lidar_scan(seed=scene_seed, model=level['model'], cols=int(cols), errors=errors)
                else:
                    pose = sensor_pose_for(scene_seed)
                    scene = make_indoor_scene(scene_seed, sensor_pose=pose, n_objects=int(n_objects))
                    scan = generate_depth_scan(
                        scene, seed=scene_seed, width=int(cols), height=int(rows), sensor_pose=pose, errors=errors
                    )
                path = folder / f'{level["name"]}_{index + 1:02d}.npy'
                np.save(path, scan.points.astype(np.float32))
                ground_truth = np.where(scan.labels >= 10, scan.labels, 0).astype(np.int32)
                np.save(path.with_name(f'{path.stem}_labels.npy'), ground_truth)
                entries.append(
                    {
                        'file': path.relative_to(root).as_posix(),
                        'split': split,
                        'level': level['name'],
                        'radial_sigma': level['radial_sigma'],
                        'scene_seed': scene_seed,
                        'n_planes': len(np.unique(ground_truth[ground_truth >= 10])),
                        'clutter_fraction': float(np.mean(scan.labels == 2)),
                        'valid_fraction': float(np.mean(np.isfinite(scan.points[..., 0]))),
                        'sensor_pose': scan.sensor_pose.to_dict(),
                    }
                )
                done += 1
                if progress is not None:
                    progress(done, total)
    manifest = {
        'format': FORMAT_NAME,
        'kind': kind,
        'seed': int(seed),
        'rows': None if kind == 'lidar' else int(rows),
        'cols': int(cols),
        'n_objects': int(n_objects),
        'n_train': int(n_train),
        'n_test': int(n_test),
        'seed_splits': {split: list(bounds) for split, bounds in SENSOR_SEED_SPLITS.items()},
        'levels': levels,
        'errors': error_params,
        'frame': (
            'lidar sensor frame: x forward, y left, z up; rows = beams (top first), destaggered'
            if kind == 'lidar'
            else 'camera optical frame: x right, y down, z forward'
        ),
        'labels': '<scan>_labels.npy: one ground-truth label (>= 10) per planar surface, the same label for all '
        'pieces of a surface an occluder cuts apart; 0 = no ground-truth plane (clutter such as trees, '
        'cars, people, plants; surfaces too small to count; no return)',
        'shape': shape_note,
        'scans': entries,
    }
    (root / MANIFEST_NAME).write_text(json.dumps(manifest, indent=1) + '\n')
    return manifest


def read_manifest(directory: str | os.PathLike[str]) -> dict:
    """The ``dataset.json`` of a data set directory.

    Raises:
        FileNotFoundError: no data set there. ValueError: not a manifest of this format.
    """
    path = Path(directory) / MANIFEST_NAME
    if not path.is_file():
        raise FileNotFoundError(f'{directory} is not a data set: no {MANIFEST_NAME} (make one with `ppe dataset make`)')
    try:
        manifest = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f'{path}: not valid JSON: {exc}') from None
    if not isinstance(manifest, dict) or manifest.get('format') != FORMAT_NAME or 'scans' not in manifest:
        raise ValueError(f'{path}: not a {FORMAT_NAME} manifest')
    return manifest


def select_levels(manifest: dict, noise_mm: Sequence[float] | None) -> list[dict]:
    """The manifest's levels whose sigma is within 0.1 mm of one of ``noise_mm`` (None: all).

    Raises:
        ValueError: a requested level is not in the data set.
    """
    levels = manifest['levels']
    if noise_mm is None:
        return list(levels)
    chosen = []
    for wanted in noise_mm:
        match = [lv for lv in levels if abs(lv['radial_sigma'] * 1000.0 - float(wanted)) <= 0.1]
        if not match:
            have = ', '.join(f'{lv["radial_sigma"] * 1000:.1f}' for lv in levels)
            raise ValueError(f'no noise level of {wanted:g} mm in the data set (levels: {have} mm)')
        if match[0] not in chosen:
            chosen.append(match[0])
    return chosen


def iter_scans(
    directory: str | os.PathLike[str],
    *,
    split: str = 'test',
    noise_mm: Sequence[float] | None = None,
    max_scans: int | None = None,
) -> Iterator[DatasetScan]:
    """The scans of one split, level by level (levels in manifest order, scans by file name).

    Args:
        directory: the data set.
        split: ``train`` or ``test``.
        noise_mm: radial sigmas in mm to keep (None: all levels).
        max_scans: at most this many scans per level (None: all).
    """
    if split not in SPLITS:
        raise ValueError(f'split must be one of {SPLITS}; got {split!r}')
    root = Path(directory)
    manifest = read_manifest(root)
    for level in select_levels(manifest, noise_mm):
        entries = sorted(
            (e for e in manifest['scans'] if e['split'] == split and e['level'] == level['name']),
            key=lambda e: e['file'],
        )
        if max_scans is not None:
            entries = entries[:max_scans]
        for entry in entries:
            yield DatasetScan(
                path=root / entry['file'],
                split=split,
                level=level['name'],
                radial_sigma=float(level['radial_sigma']),
                scene_seed=int(entry['scene_seed']),
                n_planes=int(entry['n_planes']),
            )
