"""Ray starts of Ouster lidar sweeps from the sensor's JSON metadata.

An Ouster beam does not start at the sensor origin. In the lidar frame the beam of encoder angle
``theta`` starts at ``n (cos theta, sin theta, 0)`` with ``n = lidar_origin_to_beam_origin_mm``
(13-28 mm), and the lidar frame sits in the sensor frame by ``lidar_to_sensor_transform`` (a
rotation and a 36-74 mm lift). In a destaggered ``(H, W)`` image, pixel (row i, column j) was
measured at encoder angle ``theta = 2 pi (pixel_shift_by_row[i] - j) / W``.

This model reproduces the shared sweeps exactly: with these starts, every ray ``p - s`` of row i
has the elevation ``beam_altitude_angles[i]`` (checked in test/test_io_files.py).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from ppe_ros.io.errors import ScanFileError


def find_ouster_metadata(scan_path: str | os.PathLike[str]) -> Path | None:
    """The Ouster ``*.json`` next to a scan whose name is the longest prefix of the scan's name."""
    path = Path(scan_path)
    best: Path | None = None
    for candidate in path.parent.glob('*.json'):
        stem = candidate.stem
        if path.stem.startswith(stem) and (best is None or len(stem) > len(best.stem)):
            best = candidate
    return best


def read_ouster_metadata(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read and check the fields of an Ouster sensor metadata JSON that the ray model needs."""
    file_path = Path(path)
    try:
        metadata = json.loads(file_path.read_text(encoding='utf-8'))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ScanFileError(f'{file_path}: not a readable JSON file: {exc}') from None
    required = ('lidar_origin_to_beam_origin_mm', 'lidar_to_sensor_transform', 'data_format')
    missing = [key for key in required if key not in metadata]
    if missing:
        raise ScanFileError(f'{file_path}: not Ouster sensor metadata (missing {", ".join(missing)})')
    return metadata


def ouster_ray_origins(metadata: dict[str, Any], height: int, width: int, *, source: str = 'metadata') -> np.ndarray:
    """``(H, W, 3)`` float64 ray starts in the sensor frame (metres) of a destaggered Ouster image.

    Raises:
        ScanFileError: the metadata does not describe an ``height x width`` image with all columns.
    """
    data_format = metadata['data_format']
    rows = int(data_format.get('pixels_per_column', -1))
    columns = int(data_format.get('columns_per_frame', -1))
    if (rows, columns) != (height, width):
        raise ScanFileError(
            f'{source}: describes a {rows} x {columns} image, the scan is {height} x {width}'
        )
    window = data_format.get('column_window', [0, width - 1])
    if list(window) != [0, width - 1]:
        raise ScanFileError(f'{source}: column_window {window} is not the full sweep; ray starts unknown')
    shifts = np.asarray(data_format.get('pixel_shift_by_row', [0] * height), dtype=np.float64)
    if shifts.shape != (height,):
        raise ScanFileError(f'{source}: pixel_shift_by_row has {shifts.size} entries, expected {height}')
    transform = np.asarray(metadata['lidar_to_sensor_transform'], dtype=np.float64).reshape(4, 4)
    rotation = transform[:3, :3]
    translation = transform[:3, 3] / 1000.0
    offset = float(metadata['lidar_origin_to_beam_origin_mm']) / 1000.0
    encoder = 2.0 * np.pi * (shifts[:, None] - np.arange(width, dtype=np.float64)[None, :]) / width
    starts_lidar = np.stack([offset * np.cos(encoder), offset * np.sin(encoder), np.zeros_like(encoder)], axis=-1)
    return starts_lidar @ rotation.T + translation
