"""Ray starts from the Ouster ROS driver's metadata (``std_msgs/String`` JSON, latched).

The driver (ouster-ros) publishes the sensor's metadata JSON on ``<ns>/metadata`` with a
transient-local QoS. It holds ``lidar_origin_to_beam_origin_mm`` (13-28 mm: where each beam starts,
off the lidar axis), ``lidar_to_sensor_transform`` and the image layout; :mod:`ppe_ros.io.ouster`
turns them into one ray start per pixel, exactly as for Ouster files. Both layouts of the JSON are
read: the legacy one (those fields at the top level, as in ``*.json`` files next to recorded
scans) and the newer one (``beam_intrinsics``, ``lidar_intrinsics``, ``lidar_data_format``).

Frames (REP 103): ouster-ros publishes the cloud either in ``os_lidar`` (the lidar frame: beams
start at ``n (cos theta, sin theta, 0)``) or in ``os_sensor`` (the housing frame, shifted and
rotated by ``lidar_to_sensor_transform``). A cloud whose frame_id ends in ``lidar`` gets the
lidar-frame starts, any other the sensor-frame ones.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import numpy as np

from ppe_ros.io.errors import ScanFileError
from ppe_ros.io.ouster import ouster_ray_origins

#: Newer metadata layout -> legacy keys: (section, key) -> legacy top-level key.
_NESTED_KEYS = {
    ('beam_intrinsics', 'lidar_origin_to_beam_origin_mm'): 'lidar_origin_to_beam_origin_mm',
    ('beam_intrinsics', 'beam_altitude_angles'): 'beam_altitude_angles',
    ('beam_intrinsics', 'beam_azimuth_angles'): 'beam_azimuth_angles',
    ('lidar_intrinsics', 'lidar_to_sensor_transform'): 'lidar_to_sensor_transform',
    ('lidar_data_format', None): 'data_format',
}


def legacy_metadata(text: str, *, source: str = 'metadata') -> dict[str, Any]:
    """The metadata JSON as the legacy layout :func:`ppe_ros.io.ouster.ouster_ray_origins` reads.

    Raises:
        ScanFileError: not JSON, not an object, or without the beam-origin fields.
    """
    try:
        metadata = json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise ScanFileError(f'{source}: not JSON: {exc}') from None
    if not isinstance(metadata, dict):
        raise ScanFileError(f'{source}: not Ouster metadata (a JSON {type(metadata).__name__}, expected an object)')
    legacy = dict(metadata)
    for (section, key), legacy_key in _NESTED_KEYS.items():
        nested = metadata.get(section)
        if legacy_key in legacy or not isinstance(nested, dict):
            continue
        if key is None:
            legacy[legacy_key] = nested
        elif key in nested:
            legacy[legacy_key] = nested[key]
    missing = [
        key
        for key in ('lidar_origin_to_beam_origin_mm', 'lidar_to_sensor_transform', 'data_format')
        if key not in legacy
    ]
    if missing:
        raise ScanFileError(f'{source}: not Ouster metadata (missing {", ".join(missing)})')
    return legacy


class OusterRayOrigins:
    """Per-pixel ray starts of the clouds of one Ouster sensor, from its metadata message.

    :meth:`for_cloud` computes the ``(H, W, 3)`` starts once per frame kind (lidar or sensor frame)
    and returns the same read-only array afterwards.
    """

    def __init__(self, text: str, *, source: str = 'metadata') -> None:
        self.source = source
        self.metadata = legacy_metadata(text, source=source)
        data_format = self.metadata['data_format']
        rows = data_format.get('pixels_per_column') if isinstance(data_format, dict) else None
        columns = data_format.get('columns_per_frame') if isinstance(data_format, dict) else None
        if not (isinstance(rows, int) and isinstance(columns, int)) or rows < 1 or columns < 1:
            raise ScanFileError(f'{source}: data_format must give pixels_per_column and columns_per_frame')
        self.shape = (rows, columns)
        self._sensor_frame = ouster_ray_origins(self.metadata, rows, columns, source=source)  # validates
        self.beam_origin_mm = float(self.metadata['lidar_origin_to_beam_origin_mm'])
        self._sensor_frame.setflags(write=False)
        self._lidar_frame: np.ndarray | None = None

    @staticmethod
    def in_lidar_frame(frame_id: str) -> bool:
        """Whether a cloud of ``frame_id`` is in the lidar frame (``os_lidar``), else the sensor frame."""
        return frame_id.rstrip('/').endswith('lidar')

    def for_cloud(self, height: int, width: int, frame_id: str) -> np.ndarray | None:
        """``(H, W, 3)`` float64 starts (m) in the cloud's frame, or None for a cloud of another size."""
        if (height, width) != self.shape:
            return None
        if not self.in_lidar_frame(frame_id):
            return self._sensor_frame
        if self._lidar_frame is None:
            transform = np.asarray(self.metadata['lidar_to_sensor_transform'], dtype=np.float64).reshape(4, 4)
            rotation, translation = transform[:3, :3], transform[:3, 3] / 1000.0
            lidar = (self._sensor_frame - translation) @ rotation  # sensor = lidar @ R.T + t
            lidar.setflags(write=False)
            self._lidar_frame = lidar
        return self._lidar_frame


class RayStarts:
    """The node's ray starts: the Ouster metadata's per-beam ones while ``ray_origin`` is [0, 0, 0].

    ``warn(key, message)`` gets throttled warnings, ``info(message)`` the line saying the metadata arrived.
    """

    def __init__(self, warn: Callable[[str, str], None], info: Callable[[str], None]) -> None:
        self._warn = warn
        self._info = info
        self.ouster: OusterRayOrigins | None = None

    def update(self, text: str, topic: str) -> None:
        """A metadata message arrived on ``topic``: use it from the next frame on (a bad one is warned about)."""
        try:
            ouster = OusterRayOrigins(text, source=f'metadata on {topic}')
        except (ScanFileError, ValueError, TypeError) as exc:
            self._warn('metadata', f'metadata ignored (ray origins stay ray_origin): {exc}')
            return
        self.ouster = ouster
        rows, columns = ouster.shape
        self._info(
            f'Ouster metadata on {topic}: beam origins {ouster.beam_origin_mm:g} mm off the lidar axis; '
            f'{rows} x {columns} clouds get per-beam ray starts while ray_origin is [0, 0, 0]'
        )

    def for_cloud(self, msg: Any, ray_origin: tuple[float, float, float]) -> np.ndarray | None:
        """``(H, W, 3)`` starts for this cloud, or None (``ray_origin`` applies): no metadata, another
        size (warned about), or a ``ray_origin`` set by hand (it wins)."""
        ouster = self.ouster
        if ouster is None or any(ray_origin):
            return None
        try:
            height, width, frame_id = int(msg.height), int(msg.width), str(msg.header.frame_id)
        except (AttributeError, TypeError, ValueError):
            return None  # process_cloud reports the cloud
        origins = ouster.for_cloud(height, width, frame_id)
        if origins is None:
            self._warn(
                'metadata_size',
                f'the Ouster metadata describes {ouster.shape[0]} x {ouster.shape[1]} '
                f'clouds; this one is {height} x {width}: ray_origin used',
            )
        return origins
