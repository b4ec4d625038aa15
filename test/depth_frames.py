"""Depth images and camera infos of either message flavour (rclpy or rosbags) for the tests."""

from __future__ import annotations

import struct

import numpy as np

STAMP = (1_700_000_321, 654_000_000)
FX, FY, CX, CY = 120.0, 118.0, 39.5, 29.25


def message_header(types, frame_id, stamp):
    """A std_msgs/Header of either flavour."""
    if types.flavour == 'rclpy':
        from std_msgs.msg import Header

        result = Header(frame_id=frame_id)
        result.stamp.sec, result.stamp.nanosec = stamp
        return result
    store = types.typestore.types
    return store['std_msgs/msg/Header'](
        stamp=store['builtin_interfaces/msg/Time'](sec=stamp[0], nanosec=stamp[1]), frame_id=frame_id
    )


def header(types, frame_id='camera_depth_optical_frame'):
    return message_header(types, frame_id, STAMP)


def camera_info(types, *, width=80, height=60, k=None, p=None, d=(), binning=(0, 0), roi=(0, 0, 0, 0)):
    """A CameraInfo of either flavour; K and P default to (FX, FY, CX, CY)."""
    k = [FX, 0.0, CX, 0.0, FY, CY, 0.0, 0.0, 1.0] if k is None else k
    p = [FX, 0.0, CX, 0.0, 0.0, FY, CY, 0.0, 0.0, 0.0, 1.0, 0.0] if p is None else p
    fields = dict(
        height=height,
        width=width,
        distortion_model='plumb_bob',
        d=np.asarray(d, dtype=np.float64),
        k=np.asarray(k, dtype=np.float64),
        r=np.eye(3).ravel(),
        p=np.asarray(p, dtype=np.float64),
        binning_x=binning[0],
        binning_y=binning[1],
    )
    x_offset, y_offset, roi_height, roi_width = roi
    if types.flavour == 'rclpy':
        from sensor_msgs.msg import RegionOfInterest

        region = RegionOfInterest(x_offset=x_offset, y_offset=y_offset, height=roi_height, width=roi_width)
        return types.CameraInfo(header=header(types), roi=region, **{**fields, 'd': list(fields['d'])})
    region = types.typestore.types['sensor_msgs/msg/RegionOfInterest'](
        x_offset=x_offset, y_offset=y_offset, height=roi_height, width=roi_width, do_rectify=False
    )
    return types.CameraInfo(header=header(types), roi=region, **fields)


def depth_image(types, values, encoding='32FC1', *, big_endian=False, padding=0, data_size=None):
    """An Image of ``values`` ((H, W) metres for 32FC1, counts for 16UC1) with ``padding`` bytes after each row."""
    dtype = np.dtype(('>' if big_endian else '<') + ('f4' if encoding == '32FC1' else 'u2'))
    rows = np.asarray(values).astype(dtype)
    height, width = rows.shape
    raw = np.zeros((height, width * dtype.itemsize + padding), dtype=np.uint8)
    raw[:, : width * dtype.itemsize] = rows.view(np.uint8).reshape(height, -1)
    data = raw.ravel()
    if data_size is not None:
        data = np.resize(data, data_size)
    fields = dict(
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=int(big_endian),
        step=raw.shape[1],
    )
    if types.flavour == 'rclpy':
        return types.Image(header=header(types), data=data.tobytes(), **fields)
    return types.Image(header=header(types), data=data, **fields)


def corner_depth(height=60, width=80, *, fx=FX, fy=FY, cx=CX, cy=CY, wall=2.0, floor=0.3):
    """z (m) of a camera facing a wall at z = ``wall`` above a floor at y = ``floor`` (y down)."""
    v = (np.arange(height)[:, None] - cy) / fy
    with np.errstate(divide='ignore'):
        to_floor = np.where(v > 0, floor / np.where(v > 0, v, 1.0), np.inf)
    return np.minimum(wall, to_floor) * np.ones((1, width))


def reference_points(z, fx, fy, cx, cy):
    """Pixel by pixel: (z (u - cx) / fx, z (v - cy) / fy, z), NaN where z is not a positive finite number."""
    height, width = z.shape
    out = np.full((height, width, 3), np.nan)
    for v in range(height):
        for u in range(width):
            depth = float(z[v, u])
            if np.isfinite(depth) and depth > 0:
                out[v, u] = (depth * (u - cx) / fx, depth * (v - cy) / fy, depth)
    return out


def rvl_encode(values: np.ndarray) -> bytes:
    """The RVL code of uint16 values, written as the format describes it (slow, obviously correct): runs of
    zeros and non-zeros, non-zeros as zigzag differences, numbers as 3-bit nibbles lowest first with a
    continuation bit, eight nibbles a little-endian 32-bit word, most significant nibble first."""
    nibbles: list[int] = []

    def number(value: int) -> None:
        while True:
            nibble = value & 7
            value >>= 3
            nibbles.append(nibble | (8 if value else 0))
            if not value:
                return

    flat = [int(v) for v in np.asarray(values).ravel()]
    i, previous = 0, 0
    while i < len(flat):
        zeros = 0
        while i + zeros < len(flat) and flat[i + zeros] == 0:
            zeros += 1
        number(zeros)
        i += zeros
        nonzeros = 0
        while i + nonzeros < len(flat) and flat[i + nonzeros] != 0:
            nonzeros += 1
        number(nonzeros)
        for value in flat[i : i + nonzeros]:
            delta = value - previous
            number(2 * delta if delta >= 0 else -2 * delta - 1)
            previous = value
        i += nonzeros
    nibbles += [0] * (-len(nibbles) % 8)
    words = [int(''.join(f'{n:x}' for n in nibbles[k : k + 8]), 16) for k in range(0, len(nibbles), 8)]
    return struct.pack(f'<{len(words)}I', *words)


def compressed_depth_image(types, millimetres: np.ndarray, header_msg=None):
    """A compressedDepth sensor_msgs/CompressedImage ('16UC1; compressedDepth rvl') of uint16 millimetres."""
    height, width = millimetres.shape
    data = struct.pack('<iff', 0, 0.0, 0.0) + struct.pack('<II', width, height) + rvl_encode(millimetres)
    return types.CompressedImage(
        header=header_msg if header_msg is not None else header(types),
        format='16UC1; compressedDepth rvl',
        data=data if types.flavour == 'rclpy' else np.frombuffer(data, np.uint8),
    )
