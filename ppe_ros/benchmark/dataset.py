"""SynPEB-style benchmark data sets: generated room scans per radial noise level, train and test splits.

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
    return ScanGrid(elevation_deg=np.linspace(30.0, -30.0, int(rows)),
                    azimuth_deg=-35.0 + (70.0 / cols) * np.arange(cols))


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


def make_dataset(
    directory: str | os.PathLike[str],
    *,
    seed: int = 0,
    sigmas: Sequence[float] = DEFAULT_SIGMAS,
    n_train: int = DEFAULT_TRAIN,
    n_test: int = DEFAULT_TEST,
    rows: int = 500,
    cols: int = 500,
    angular_sigma_deg: float = DEFAULT_ANGULAR_SIGMA_DEG,
    n_objects: int = DEFAULT_N_OBJECTS,
    compressed: bool = True,
    progress=None,
) -> dict:
    """Write a SynPEB-style data set into ``directory`` (created; must not hold a data set already).

    Args:
        directory: output directory; refused if it already contains ``dataset.json`` or scan folders.
        seed: non-negative integer; every scene, pose and noise draw is deterministic in it.
        sigmas: radial noise standard deviations in metres, one level each.
        n_train, n_test: scans per level in each split.
        rows, cols: grid size (SynPEB: 500 x 500).
        angular_sigma_deg: beam-direction jitter (degrees per axis); SynPEB: 1 mdeg.
        n_objects: objects per room (default 10: about 40 planes per scan).
        compressed: ``DATA binary_compressed`` (as SynPEB) instead of ``binary``.
        progress: optional callable ``progress(done, total)`` called after each written scan.

    Returns:
        The manifest (also written to ``dataset.json``).

    Raises:
        ValueError: bad parameters. FileExistsError: the directory already holds a data set.
    """
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f'seed must be a non-negative integer; got {seed!r}')
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
    grid = synpeb_grid(rows, cols)
    root = Path(directory)
    if (root / MANIFEST_NAME).exists() or any((root / split).exists() for split in SPLITS):
        raise FileExistsError(f'{root} already holds a data set; choose a new directory')
    root.mkdir(parents=True, exist_ok=True)

    from ppe_ros.io import save_pcd

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
            scene = make_room_scene(scene_seed, keep_clear=pose.position[:2], view_yaw_deg=pose.yaw_deg,
                                    n_objects=int(n_objects))
            for sigma, name in zip(levels, names, strict=True):
                scan = generate_scan(scene, seed=scene_seed, grid=grid, sensor_pose=pose, radial_sigma=sigma,
                                     angular_sigma_deg=angular_sigma_deg, min_region_pixels=min_region)
                folder = root / split / name
                folder.mkdir(parents=True, exist_ok=True)
                path = folder / f'pc_{index + 1:02d}.pcd'
                points = np.where(np.isfinite(scan.points), scan.points, np.nan)
                save_pcd(path, points, extra_fields={'intensity': scan.labels.astype(np.float32)},
                         compressed=compressed)
                entries.append({
                    'file': path.relative_to(root).as_posix(),
                    'split': split,
                    'level': name,
                    'radial_sigma': sigma,
                    'scene_seed': scene_seed,
                    'n_planes': len(scan.visible_labels()),
                    'sensor_pose': pose.to_dict(),
                })
                done += 1
                if progress is not None:
                    progress(done, total)
    manifest = {
        'format': FORMAT_NAME,
        'seed': int(seed),
        'rows': int(rows),
        'cols': int(cols),
        'angular_sigma_deg': float(angular_sigma_deg),
        'n_objects': int(n_objects),
        'n_train': int(n_train),
        'n_test': int(n_test),
        'levels': [{'name': name, 'radial_sigma': sigma, 'variance_cm2': round((sigma * 100.0) ** 2, 6)}
                   for sigma, name in zip(levels, names, strict=True)],
        'min_region_pixels': min_region,
        'labels': 'PCD field intensity: ground-truth plane id (>= 10); 3 = visible but no GT plane (a face piece '
                  f'smaller than {min_region} px); 0 = no return (NaN point)',
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
            have = ', '.join(f"{lv['radial_sigma'] * 1000:.1f}" for lv in levels)
            raise ValueError(f'no noise level of {wanted:g} mm in the data set (levels: {have} mm)')
        if match[0] not in chosen:
            chosen.append(match[0])
    return chosen


def iter_scans(directory: str | os.PathLike[str], *, split: str = 'test', noise_mm: Sequence[float] | None = None,
               max_scans: int | None = None) -> Iterator[DatasetScan]:
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
        entries = sorted((e for e in manifest['scans'] if e['split'] == split and e['level'] == level['name']),
                         key=lambda e: e['file'])
        if max_scans is not None:
            entries = entries[:max_scans]
        for entry in entries:
            yield DatasetScan(path=root / entry['file'], split=split, level=level['name'],
                              radial_sigma=float(level['radial_sigma']), scene_seed=int(entry['scene_seed']),
                              n_planes=int(entry['n_planes']))
