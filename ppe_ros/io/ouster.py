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
import math
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
    """Read and check the fields of an Ouster sensor metadata JSON that the ray model needs.

    Raises:
        ScanFileError: not JSON, not an object, or a required field missing (their types are
            checked by :func:`ouster_ray_origins`).
    """
    file_path = Path(path)
    try:
        metadata = json.loads(file_path.read_text(encoding='utf-8'))
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise ScanFileError(f'{file_path}: not a readable JSON file: {exc}') from None
    if not isinstance(metadata, dict):
        raise ScanFileError(
            f'{file_path}: not Ouster sensor metadata (a JSON {type(metadata).__name__}, expected an object)'
        )
    required = ('lidar_origin_to_beam_origin_mm', 'lidar_to_sensor_transform', 'data_format')
    missing = [key for key in required if key not in metadata]
    if missing:
        raise ScanFileError(f'{file_path}: not Ouster sensor metadata (missing {", ".join(missing)})')
    return metadata


def _json_kind(value: Any) -> str:
    return 'null' if value is None else f'{type(value).__name__} {json.dumps(value)[:60]}'


def _number(source: str, name: str, value: Any) -> float:
    number = float('nan')
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        try:
            number = float(value)
        except OverflowError:  # an integer beyond float range
            pass
    if not math.isfinite(number):
        raise ScanFileError(f'{source}: {name} must be a finite number; found {_json_kind(value)}')
    return number


def _count(source: str, name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ScanFileError(f'{source}: {name} must be a positive integer; found {_json_kind(value)}')
    return value


def _numbers(source: str, name: str, value: Any, size: int, what: str) -> np.ndarray:
    if not isinstance(value, list) or len(value) != size:
        found = f'{len(value)} values' if isinstance(value, list) else _json_kind(value)
        raise ScanFileError(f'{source}: {name} must be {size} numbers ({what}); found {found}')
    return np.array([_number(source, f'{name}[{index}]', v) for index, v in enumerate(value)], dtype=np.float64)


def ouster_ray_origins(metadata: dict[str, Any], height: int, width: int, *, source: str = 'metadata') -> np.ndarray:
    """``(H, W, 3)`` float64 ray starts in the sensor frame (metres) of a destaggered Ouster image.

    Raises:
        ScanFileError: the metadata does not describe an ``height x width`` image with all columns,
            or a field the model needs is missing, null or of the wrong type (the message names ``source``).
    """
    data_format = metadata.get('data_format')
    if not isinstance(data_format, dict):
        raise ScanFileError(f'{source}: data_format must be a JSON object; found {_json_kind(data_format)}')
    rows = _count(source, 'data_format.pixels_per_column', data_format.get('pixels_per_column'))
    columns = _count(source, 'data_format.columns_per_frame', data_format.get('columns_per_frame'))
    if (rows, columns) != (height, width):
        raise ScanFileError(f'{source}: describes a {rows} x {columns} image, the scan is {height} x {width}')
    window = data_format.get('column_window', [0, width - 1])
    if window != [0, width - 1]:
        raise ScanFileError(f'{source}: column_window {window} is not the full sweep; ray starts unknown')
    shifts = _numbers(
        source,
        'data_format.pixel_shift_by_row',
        data_format.get('pixel_shift_by_row', [0] * height),
        height,
        'one per row',
    )
    transform = _numbers(
        source, 'lidar_to_sensor_transform', metadata.get('lidar_to_sensor_transform'), 16, 'a row-major 4 x 4 matrix'
    ).reshape(4, 4)
    rotation = transform[:3, :3]
    translation = transform[:3, 3] / 1000.0
    offset = _number(source, 'lidar_origin_to_beam_origin_mm', metadata.get('lidar_origin_to_beam_origin_mm')) / 1000.0
    encoder = 2.0 * np.pi * (shifts[:, None] - np.arange(width, dtype=np.float64)[None, :]) / width
    starts_lidar = np.stack([offset * np.cos(encoder), offset * np.sin(encoder), np.zeros_like(encoder)], axis=-1)
    return starts_lidar @ rotation.T + translation
