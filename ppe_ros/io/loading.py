"""Scan files -> clouds (organized grids, or lidar point lists): one entry point, :func:`load_scan`, for every format.

Supported formats (chosen by the file suffix, case-insensitive):

* ``.pcd`` — PCD v0.7, ``DATA ascii``, ``binary`` or ``binary_compressed`` (LZF); organized
  (``HEIGHT > 1``) or unorganized (``HEIGHT 1``: a lidar's point list, with its beams in a ``ring``
  field if the file has one). Fields ``x y z`` plus any others. Ground-truth labels come from a ``label``
  field, or from an ``intensity`` field of floats that are all whole numbers >= 0 (SynPEB stores
  the plane id there; ids >= 10 are planes; ``intensity_labels=False`` turns this off). A non-zero
  ``VIEWPOINT`` translation becomes the ray start (``origins``).
* ``.npy`` — an organized ``(H, W, 3)`` float array (e.g. the Ouster sweeps), NaN = no return. If an
  Ouster sensor metadata ``*.json`` whose name is a prefix of the file name lies next to it, the
  per-pixel beam origins become ``origins`` (``(H, W, 3)``, metres; see :mod:`ppe_ros.io.ouster`).
* ``.bin`` — a KITTI-style Velodyne file (float32 ``x y z reflectance``, no ring field): unorganized
  (:mod:`ppe_ros.io.kitti`).
* ``.png`` — a 16-bit depth image, back-projected with pinhole intrinsics into the camera frame
  (x right, y down, z forward). Intrinsics and depth scale come from the arguments or from a known
  calibration file next to the PNG (ICL-NUIM ``*.K``, Kinect ``calib_params.xml``; see
  :mod:`ppe_ros.io.depth`).

Units: coordinates in PCD and NPY files are taken as metres unless ``units`` says otherwise
(``'cm'`` for the TLS scan ``andreashaus_scan000.pcd``); there is no guessing. For PNGs ``units`` is
the unit of one depth count (``'mm'`` = Kinect), unless the calibration file implies a scale.

Ground truth: ``gt=`` a labels ``.npy`` file; otherwise ``<stem>_labels.npy`` next to the scan if it
exists (ICL-NUIM's ``icl_nuim_0_labels.npy``); otherwise labels stored in the file itself.
Points whose coordinates are not all finite, or exactly (0, 0, 0), are set to NaN (no return).

Bad input: every reader checks the sizes a file declares against the file's size and against the
limits of :mod:`ppe_ros.io.limits` (50 million points, 100000 rows or columns) before it allocates,
and raises :class:`ScanFileError` naming the file (also for sidecars: labels, Ouster JSON, calibration).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ppe_ros.io.depth import (
    DepthCalibration,
    PinholeIntrinsics,
    backproject_depth,
    find_depth_calibration,
    read_depth_png,
)
from ppe_ros.io.errors import ScanFileError
from ppe_ros.io.limits import check_grid_size
from ppe_ros.io.npy import read_npy
from ppe_ros.io.ouster import find_ouster_metadata, ouster_ray_origins, read_ouster_metadata
from ppe_ros.io.pcd import read_pcd

#: Metres per unit.
UNIT_SCALES: dict[str, float] = {'m': 1.0, 'cm': 0.01, 'mm': 0.001}

#: File suffix -> format name.
FORMATS: dict[str, str] = {'.pcd': 'pcd', '.npy': 'npy', '.png': 'depth_png', '.bin': 'kitti_bin'}

#: Labels of this id and above are planes in SynPEB files (smaller ids are unlabelled points).
SYNPEB_MIN_PLANE_LABEL = 10


@dataclass(frozen=True, eq=False)
class Scan:
    """A scan read from a file: organized, or unorganized (a lidar's point list, ``H == 1``).

    Attributes:
        points: ``(H, W, 3)`` float64 endpoints in metres in the file's frame (sensor frame for
            laser scans, camera frame x right / y down / z forward for depth images); NaN = no return.
            An unorganized scan is ``(1, N, 3)`` in the file's point order.
        labels: ``(H, W)`` int64 ground-truth plane labels, or None. The id convention depends on
            the data set: ``meta['min_plane_label']`` is the smallest id that denotes a plane
            (10 for SynPEB, 1 for label files where 0 = unlabelled).
        origins: ray starts in metres in the frame of ``points``: None (all rays start at the
            coordinate origin), ``(3,)`` (PCD VIEWPOINT) or ``(H, W, 3)`` (Ouster beam origins).
        path: the file read.
        format: ``'pcd'``, ``'npy'``, ``'depth_png'`` or ``'kitti_bin'``.
        meta: format details (encoding, fields, units, scale, intrinsics, label source...).
        rings: ``(1, N)`` int64 beam number of each point of an unorganized scan (a PCD ``ring``
            field), or None.
    """

    points: np.ndarray
    labels: np.ndarray | None
    origins: np.ndarray | None
    path: Path
    format: str
    meta: dict[str, Any] = field(default_factory=dict)
    rings: np.ndarray | None = None

    @property
    def organized(self) -> bool:
        """False for a point list (``H == 1``), which is put on a range image for the extraction."""
        return self.points.shape[0] > 1

    @property
    def shape(self) -> tuple[int, int]:
        """Grid size ``(rows, columns)``."""
        return (self.points.shape[0], self.points.shape[1])

    @property
    def valid(self) -> np.ndarray:
        """``(H, W)`` bool: the pixel holds a measured point."""
        return np.isfinite(self.points).all(axis=2)

    @property
    def valid_fraction(self) -> float:
        """Fraction of pixels with a measured point."""
        return float(self.valid.mean())


def _unit_scale(units: str | None) -> float | None:
    if units is None:
        return None
    key = units.strip().lower()
    if key not in UNIT_SCALES:
        raise ValueError(f'units must be one of {", ".join(UNIT_SCALES)}; got {units!r}')
    return UNIT_SCALES[key]


def _clean_points(points: np.ndarray) -> np.ndarray:
    """float64 array (in place if ``points`` is float64) where every non-finite or exactly-zero point is all NaN."""
    cloud = np.asarray(points, dtype=np.float64)
    with np.errstate(invalid='ignore'):
        invalid = ~np.isfinite(cloud).all(axis=2) | (cloud == 0.0).all(axis=2)
    cloud[invalid] = np.nan
    return cloud


def _as_labels(values: np.ndarray, source: str, shape: tuple[int, int]) -> np.ndarray:
    array = np.asarray(values)
    if array.shape != shape:
        raise ScanFileError(f'{source}: ground-truth labels have shape {array.shape}, the scan is {shape}')
    if np.issubdtype(array.dtype, np.integer):
        return array.astype(np.int64)
    if np.issubdtype(array.dtype, np.floating):
        if not np.all(np.isfinite(array)) or not np.all(array == np.round(array)):
            raise ScanFileError(f'{source}: ground-truth labels must be whole numbers')
        return array.astype(np.int64)
    raise ScanFileError(f'{source}: ground-truth labels must be integers; found dtype {array.dtype}')


def _load_labels_file(path: Path, shape: tuple[int, int]) -> np.ndarray:
    if not path.is_file():
        raise FileNotFoundError(f'ground-truth labels file not found: {path}')

    def check(declared: tuple[int, ...], dtype: np.dtype) -> None:
        if shape[0] == 1 and declared == (shape[1],):  # one label per point of an unorganized scan
            declared = shape
        if declared != shape:
            raise ScanFileError(f'{path}: ground-truth labels have shape {declared}, the scan is {shape}')
        if not (np.issubdtype(dtype, np.integer) or np.issubdtype(dtype, np.floating)):
            raise ScanFileError(f'{path}: ground-truth labels must be integers; found dtype {dtype}')

    values = read_npy(path, check, what='ground-truth labels .npy (H x W integers)')
    return _as_labels(np.reshape(values, shape), str(path), shape)


def _load_pcd(path: Path, scale: float | None, intensity_labels: bool | None, meta: dict[str, Any]):
    cloud = read_pcd(path)
    header = cloud.header
    meta.update(
        encoding=header.encoding,
        fields=list(header.fields),
        viewpoint=list(header.viewpoint),
    )
    names = cloud.data.dtype.names
    missing = [axis for axis in 'xyz' if axis not in names]
    if missing:
        raise ScanFileError(f'{path}: no {"/".join(missing)} field (fields: {" ".join(header.fields)})')
    for axis in 'xyz':
        if cloud.data.dtype[axis].shape != ():
            raise ScanFileError(f'{path}: field {axis!r} has COUNT > 1; expected one value per point')
    with np.errstate(invalid='ignore'):  # a signalling NaN in the file (a damaged one) is a NaN: no return
        points = np.stack([cloud.data[axis].astype(np.float64) for axis in 'xyz'], axis=-1)
    factor = 1.0 if scale is None else scale
    points *= factor
    translation = np.array(header.viewpoint[:3], dtype=np.float64) * factor
    origins = translation if np.any(translation != 0.0) else None

    labels = None
    if 'label' in names and cloud.data.dtype['label'].shape == ():
        labels = _as_labels(cloud.data['label'], f'{path} field label', points.shape[:2])
        meta.update(labels_source='field label', min_plane_label=1)
    elif 'intensity' in names and cloud.data.dtype['intensity'].shape == () and intensity_labels is not False:
        intensity = cloud.data['intensity']
        whole = bool(
            np.all(np.isfinite(intensity))
            and np.all(intensity >= 0)
            and np.all(intensity == np.round(intensity))
            and np.all(intensity < 2**31)
        )
        if intensity_labels and not whole:
            raise ScanFileError(f'{path}: intensity_labels=True but the intensity field is not whole numbers >= 0')
        if whole and (intensity_labels or np.issubdtype(intensity.dtype, np.floating)):
            labels = intensity.astype(np.int64)
            meta.update(labels_source='field intensity (SynPEB plane ids)', min_plane_label=SYNPEB_MIN_PLANE_LABEL)
    elif intensity_labels:
        raise ScanFileError(f'{path}: intensity_labels=True but the file has no intensity field')
    if not header.is_organized and 'ring' in names and cloud.data.dtype['ring'].shape == ():
        rings = cloud.data['ring']
        if not (np.issubdtype(rings.dtype, np.integer) or np.all(rings[np.isfinite(rings)] % 1 == 0)):
            raise ScanFileError(f'{path}: the ring field must hold whole beam numbers')
        meta.update(rings_source='field ring')
        with np.errstate(invalid='ignore'):
            meta['rings'] = np.where(np.isfinite(rings), rings, -1).astype(np.int64)
    return points, origins, labels


def _load_kitti(path: Path, scale: float | None, meta: dict[str, Any]):
    from ppe_ros.io.kitti import read_kitti_bin

    points, _ = read_kitti_bin(path)
    meta.update(fields=['x', 'y', 'z', 'reflectance'])
    if scale is not None and scale != 1.0:
        points *= scale
    return points.reshape(1, -1, 3), None, None


def _check_npy_scan(path: Path, shape: tuple[int, ...], dtype: np.dtype) -> None:
    if len(shape) != 3 or shape[2] != 3:
        raise ScanFileError(f'{path}: expected an organized (H, W, 3) array of x, y, z; found shape {shape}')
    if not np.issubdtype(dtype, np.floating):
        raise ScanFileError(f'{path}: expected float32 or float64 coordinates; found dtype {dtype}')
    if shape[0] < 2 or shape[1] < 1:
        raise ScanFileError(f'{path}: the cloud is not organized: shape {shape} (needs H >= 2 rows)')
    check_grid_size(path, shape[0], shape[1], 'grid (.npy shape)')


def _load_npy(path: Path, scale: float | None, meta: dict[str, Any]):
    array = read_npy(
        path, lambda shape, dtype: _check_npy_scan(path, shape, dtype), what='.npy scan (an H x W x 3 float array)'
    )
    meta.update(dtype=str(array.dtype))
    factor = 1.0 if scale is None else scale
    origins = None
    sensor_json = find_ouster_metadata(path)
    if sensor_json is not None:
        metadata = read_ouster_metadata(sensor_json)
        origins = ouster_ray_origins(metadata, array.shape[0], array.shape[1], source=str(sensor_json))
        meta.update(origins_source=f'{sensor_json} (Ouster beam origins)')
    with np.errstate(invalid='ignore', over='ignore'):  # e.g. float128 beyond float64: inf, then no return
        points = array.astype(np.float64, copy=False)  # the array read is ours: no second copy
    del array
    if factor != 1.0:
        points *= factor
    return points, origins, None


def _load_depth_png(
    path: Path,
    scale: float | None,
    intrinsics: tuple[float, float, float, float] | PinholeIntrinsics | None,
    depth_scale: float | None,
    meta: dict[str, Any],
):
    depth = read_depth_png(path)
    if depth.shape[0] < 2:
        raise ScanFileError(f'{path}: the depth image has {depth.shape[0]} row; needs at least 2')
    calibration: DepthCalibration | None = None
    if intrinsics is None or (depth_scale is None and scale is None):
        calibration = find_depth_calibration(path)
    if intrinsics is not None:
        camera = intrinsics if isinstance(intrinsics, PinholeIntrinsics) else PinholeIntrinsics(*map(float, intrinsics))
        intrinsics_source = 'argument'
    elif calibration is not None:
        camera = calibration.intrinsics
        intrinsics_source = calibration.source
    else:
        raise ScanFileError(
            f'{path}: no camera intrinsics: pass intrinsics=(fx, fy, cx, cy) (CLI: --intrinsics) or put a known '
            f'calibration file next to the image (ICL-NUIM *.K, Kinect calib_params.xml)'
        )
    if depth_scale is not None:
        metres_per_count, scale_source = float(depth_scale), 'argument depth_scale'
    elif scale is not None:
        metres_per_count, scale_source = scale, 'argument units'
    elif calibration is not None:
        metres_per_count, scale_source = calibration.depth_scale, calibration.source
    else:
        raise ScanFileError(f'{path}: unknown depth unit: pass units (e.g. "mm") or depth_scale (metres per count)')
    meta.update(
        intrinsics=list(camera.as_tuple()),
        intrinsics_source=intrinsics_source,
        depth_scale=metres_per_count,
        depth_scale_source=scale_source,
        frame='camera: x right, y down, z forward',
    )
    return backproject_depth(depth, camera, metres_per_count), None, None


def scan_input_files(path: str | os.PathLike[str], *, gt: str | os.PathLike[str] | None = None) -> list[Path]:
    """Every existing file :func:`load_scan` reads for ``path``: the scan, the labels (``gt`` or the
    ``<stem>_labels.npy`` sidecar), the Ouster JSON of a ``.npy``, the calibration files next to a ``.png``.

    Used to refuse outputs that would overwrite an input (compare with :func:`ppe_ros.io.files.same_file`).
    """
    file_path = Path(path)
    files = [file_path]
    if gt is not None:
        files.append(Path(gt))
    else:
        files.append(file_path.with_name(f'{file_path.stem}_labels.npy'))
    fmt = FORMATS.get(file_path.suffix.lower())
    if fmt == 'npy' and file_path.parent.is_dir():
        files.append(find_ouster_metadata(file_path))
    elif fmt == 'depth_png' and file_path.parent.is_dir():
        files += [file_path.parent / 'calib_params.xml', *sorted(file_path.parent.glob('*.K'))]
    return [f for f in files if f is not None and f.exists()]


def load_scan(
    path: str | os.PathLike[str],
    *,
    units: str | None = None,
    intrinsics: tuple[float, float, float, float] | PinholeIntrinsics | None = None,
    depth_scale: float | None = None,
    gt: str | os.PathLike[str] | None = None,
    intensity_labels: bool | None = None,
) -> Scan:
    """Read a scan file (PCD, NPY, 16-bit depth PNG or KITTI ``.bin``) into a :class:`Scan`.

    Args:
        path: the scan file; the format follows the suffix (``.pcd``, ``.npy``, ``.png``, ``.bin``).
        units: unit of the file's coordinates, ``'m'`` (default for PCD/NPY), ``'cm'`` or ``'mm'``;
            for a depth PNG the unit of one depth count (default: from the calibration file).
        intrinsics: ``(fx, fy, cx, cy)`` in pixels for a depth PNG (default: calibration file).
        depth_scale: metres per depth count for a depth PNG (overrides ``units``).
        gt: a ``.npy`` file of ``(H, W)`` integer ground-truth labels to attach.
        intensity_labels: for PCD files, whether the ``intensity`` field holds SynPEB plane ids:
            None (default) = yes if it is float and every value is a whole number >= 0;
            True = required (error otherwise); False = never.

    Raises:
        FileNotFoundError: the scan or the labels file does not exist.
        ScanFileError: unknown format, malformed/truncated/corrupt data,
            declared sizes beyond :mod:`ppe_ros.io.limits`, labels of the wrong shape, a damaged
            Ouster JSON or calibration file, depth PNG without intrinsics or scale.
        ValueError: bad argument values (unknown units, non-positive focal lengths...).
    """
    file_path = Path(path)
    scale = _unit_scale(units)
    if not file_path.exists():
        raise FileNotFoundError(f'scan file not found: {file_path}')
    if not file_path.is_file():
        raise ScanFileError(f'{file_path}: not a regular file')
    fmt = FORMATS.get(file_path.suffix.lower())
    if fmt is None:
        raise ScanFileError(
            f'{file_path}: unknown scan format {file_path.suffix!r}; supported: '
            f'.pcd (PCD v0.7), .npy (organized H x W x 3 array), .png (16-bit depth image), '
            f'.bin (KITTI: float32 x y z reflectance)'
        )
    if fmt != 'depth_png' and (intrinsics is not None or depth_scale is not None):
        raise ValueError(f'{file_path}: intrinsics and depth_scale apply to depth PNGs only')
    meta: dict[str, Any] = {'units': units if units is not None else ('m' if fmt != 'depth_png' else None)}
    if fmt == 'pcd':
        points, origins, labels = _load_pcd(file_path, scale, intensity_labels, meta)
    elif fmt == 'npy':
        points, origins, labels = _load_npy(file_path, scale, meta)
    elif fmt == 'kitti_bin':
        points, origins, labels = _load_kitti(file_path, scale, meta)
    else:
        points, origins, labels = _load_depth_png(file_path, scale, intrinsics, depth_scale, meta)
    points = _clean_points(points)
    shape = (int(points.shape[0]), int(points.shape[1]))

    sidecar = file_path.with_name(f'{file_path.stem}_labels.npy')
    if gt is not None:
        labels = _load_labels_file(Path(gt), shape)
        meta.update(labels_source=str(gt), min_plane_label=1)
    elif sidecar.is_file():
        labels = _load_labels_file(sidecar, shape)
        meta.update(labels_source=str(sidecar), min_plane_label=1)
    rings = meta.pop('rings', None)
    return Scan(
        points=points,
        labels=labels,
        origins=origins,
        path=file_path,
        format=fmt,
        meta=meta,
        rings=None if rings is None else rings.reshape(shape),
    )
