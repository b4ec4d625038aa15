"""KITTI-style Velodyne ``.bin`` files: float32 little-endian ``x y z reflectance`` per point, nothing else.

The format of the KITTI odometry and raw data sets (an HDL-64E, metres, the sensor frame: x forward,
y left, z up) and of many other data sets since. The file has no header: its size must be a whole
number of 16-byte points, at most :data:`ppe_ros.io.limits.MAX_SCAN_POINTS` of them. There is no
ring field; the points of one sweep come in no order that this reader relies on.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ppe_ros.io.errors import ScanFileError
from ppe_ros.io.limits import MAX_SCAN_POINTS

#: Bytes per point: four float32 (x, y, z, reflectance).
KITTI_POINT_BYTES = 16


def read_kitti_bin(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """The points ``(N, 3)`` float64 (m) and reflectances ``(N,)`` float32 of a KITTI ``.bin`` file.

    Raises:
        ScanFileError: a size that is not a whole number of points, an empty file, or more points
            than the readers accept.
    """
    file_path = Path(path)
    size = file_path.stat().st_size
    if size == 0:
        raise ScanFileError(f'{file_path}: empty file; a KITTI .bin holds 16-byte points (float32 x y z reflectance)')
    if size % KITTI_POINT_BYTES:
        raise ScanFileError(
            f'{file_path}: {size} bytes is not a whole number of 16-byte points '
            f'(float32 x y z reflectance): truncated, or not a KITTI .bin file'
        )
    count = size // KITTI_POINT_BYTES
    if count > MAX_SCAN_POINTS:
        raise ScanFileError(
            f'{file_path}: holds {count} points; at most {MAX_SCAN_POINTS} points per scan are supported'
        )
    values = np.fromfile(file_path, dtype='<f4', count=count * 4).reshape(count, 4)
    with np.errstate(invalid='ignore', over='ignore'):
        return values[:, :3].astype(np.float64), values[:, 3].copy()


def write_kitti_bin(path: str | os.PathLike[str], points: np.ndarray, reflectance: np.ndarray | None = None) -> None:
    """Write ``(N, 3)`` points (m) and optional ``(N,)`` reflectances as a KITTI ``.bin`` file."""
    cloud = np.asarray(points, dtype=np.float64)
    if cloud.ndim != 2 or cloud.shape[1] != 3:
        raise ValueError(f'points must be (N, 3); got shape {cloud.shape}')
    table = np.zeros((len(cloud), 4), '<f4')
    table[:, :3] = cloud
    if reflectance is not None:
        table[:, 3] = np.asarray(reflectance, dtype=np.float32).reshape(len(cloud))
    table.tofile(Path(path))
