"""Depth images (``sensor_msgs/Image`` with its ``sensor_msgs/CameraInfo``) as organized clouds.

A depth camera's driver publishes the depth image and its camera info (RealSense
``/camera/depth/image_rect_raw`` and ``/camera/depth/camera_info``; Kinect and Azure Kinect drivers,
depth_image_proc's inputs). The node takes them on ``depth/image`` and ``depth/camera_info`` and
back-projects every pixel as depth_image_proc's ``point_cloud_xyz`` does:

* encodings of REP 118: ``16UC1`` (and ``mono16``) in millimetres, ``32FC1`` in metres; 0, NaN and
  infinite depths are no returns;
* the image is taken as rectified: pixel (u, v) with depth z becomes
  ``(z (u - cx) / fx, z (v - cy) / fy, z)`` in the image's optical frame (x right, y down, z forward),
  with fx, fy, cx, cy from the projection matrix P (the camera matrix K when P is all zero),
  adjusted for the camera info's binning and region of interest. The distortion coefficients D are
  not applied; with ``rectified=False`` (the node's ``depth_image_rectified: false``) the image is
  raw instead: the camera matrix K and the coefficients D (``plumb_bob`` or
  ``rational_polynomial``) give each pixel its undistorted ray, and the point is z times it;
* the image's size must be the one the camera info describes (its ROI's, or its own, over the binning);
* a ``sensor_msgs/CompressedImage`` of image_transport's compressedDepth transport is decoded first
  (:mod:`ppe_ros.ros.compressed_depth`).

Nothing here imports rclpy: messages of either flavour (rclpy or rosbags) work.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from ppe_ros.io.depth import PinholeIntrinsics, backproject_depth
from ppe_ros.ros.compressed_depth import CompressedDepthError, compressed_depth_size, decode_compressed_depth
from ppe_ros.ros.pointcloud2 import message_bytes

#: Image encodings read as depth (REP 118), with their numpy type and metres per count.
DEPTH_ENCODINGS: dict[str, tuple[str, float]] = {
    '16UC1': ('u2', 1.0e-3),
    'mono16': ('u2', 1.0e-3),
    '32FC1': ('f4', 1.0),
}


#: Largest sideways extent of an image's rays per unit of depth (tan of half the field of view); a calibration
#: beyond it (a field of view of more than 179.9999 degrees) is not a pinhole camera's.
MAX_RAY_SLOPE = 1.0e6


class DepthImageError(ValueError):
    """A depth image or camera info that cannot be used; ``kind`` says which part (a FrameSkipped kind).

    Attributes:
        kind: ``'invalid_image'``, ``'invalid_camera_info'`` or ``'camera_info_mismatch'``.
    """

    def __init__(self, kind: str, reason: str) -> None:
        super().__init__(reason)
        self.kind = kind
        self.reason = reason


@dataclass(frozen=True)
class DepthFrame:
    """A depth image and the camera info it goes with (None: none received yet), as the node's mailbox
    holds them. ``header`` is the image's, so that log lines name the frame as they name a cloud's."""

    image: Any
    camera_info: Any
    camera_info_topic: str = 'depth/camera_info'

    @property
    def header(self) -> Any:
        return self.image.header


@dataclass(frozen=True)
class DepthCamera:
    """The pinhole model of one depth image: intrinsics in the image's own pixels and its size.

    Attributes:
        intrinsics: fx, fy (pixels, > 0), cx, cy (pixels, from the image's first column and row).
        height, width: the image size the camera info describes (after ROI and binning).
        distorted: the camera info has non-zero distortion coefficients (not applied: see the module).
        source: ``'P'`` or ``'K'``, the matrix the intrinsics come from.
        distortion: (k1, k2, p1, p2, k3, k4, k5, k6) to undo (a raw image's), or () for a rectified one.
        distortion_model: the camera info's model name when ``distortion`` is set.
    """

    intrinsics: PinholeIntrinsics
    height: int
    width: int
    distorted: bool
    source: str = 'P'
    distortion: tuple[float, ...] = ()
    distortion_model: str = ''

    def describe(self) -> str:
        """One line for the log: size, intrinsics and where they came from, what becomes of D."""
        fx, fy, cx, cy = self.intrinsics.as_tuple()
        text = (
            f'{self.width} x {self.height} images, fx {fx:.1f} fy {fy:.1f} cx {cx:.1f} cy {cy:.1f} (from {self.source})'
        )
        if self.distortion:
            text += f'; {self.distortion_model} distortion undone (the image is taken as raw)'
        elif self.distorted:
            text += '; distortion coefficients not applied (the image is taken as rectified)'
        return text


def _numbers(values: Any, count: int, name: str) -> np.ndarray:
    try:
        array = np.asarray(values, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise DepthImageError('invalid_camera_info', f'camera info {name} is not a list of numbers') from None
    if array.size != count:
        raise DepthImageError('invalid_camera_info', f'camera info {name} has {array.size} numbers, not {count}')
    return array


def camera_model(info: Any, *, rectified: bool = True) -> DepthCamera:
    """The pinhole model a ``sensor_msgs/CameraInfo`` gives the images it describes.

    Binning 0 counts as 1; a ROI of zero size is the whole image. With binning (bx, by) and a ROI at
    (x0, y0): fx / bx, fy / by, (cx - x0) / bx, (cy - y0) / by. Rectified images: from P (K when P is
    zero), D not applied; raw images (``rectified=False``): from K, with D to undo
    (:data:`DISTORTION_MODELS`).

    Raises:
        DepthImageError: ``invalid_camera_info`` (no calibration: P and K zero or not finite, a
            non-positive focal length, rays more than :data:`MAX_RAY_SLOPE` times their depth sideways,
            a size of zero, a ROI outside the image; for a raw image a distortion model other than
            :data:`DISTORTION_MODELS` with non-zero coefficients).
    """
    try:
        height, width = int(info.height), int(info.width)
        binning_x, binning_y = max(int(info.binning_x), 1), max(int(info.binning_y), 1)
        roi = info.roi
        roi_x, roi_y, roi_height, roi_width = (int(roi.x_offset), int(roi.y_offset), int(roi.height), int(roi.width))
        distortion, distortion_model = info.d, str(info.distortion_model)
    except (AttributeError, TypeError, ValueError):
        raise DepthImageError('invalid_camera_info', 'not a sensor_msgs/CameraInfo message') from None
    projection = _numbers(info.p, 12, 'P').reshape(3, 4)
    camera = _numbers(info.k, 9, 'K').reshape(3, 3)
    if rectified and (projection[0, 0] != 0.0 or projection[1, 1] != 0.0):
        fx, fy, cx, cy, source = projection[0, 0], projection[1, 1], projection[0, 2], projection[1, 2], 'P'
    else:
        fx, fy, cx, cy, source = camera[0, 0], camera[1, 1], camera[0, 2], camera[1, 2], 'K'
    if not (fx > 0 and fy > 0 and np.isfinite([fx, fy, cx, cy]).all()):
        raise DepthImageError(
            'invalid_camera_info',
            f'camera info has no usable calibration: fx {fx:g}, fy {fy:g}, cx {cx:g}, cy {cy:g} (from {source}; '
            'an uncalibrated camera publishes zeros)',
        )
    if height <= 0 or width <= 0:
        raise DepthImageError('invalid_camera_info', f'camera info size is {height} x {width}')
    if roi_width > 0 and roi_height > 0:
        if roi_x < 0 or roi_y < 0 or roi_x + roi_width > width or roi_y + roi_height > height:
            raise DepthImageError(
                'invalid_camera_info',
                f'camera info ROI {roi_width} x {roi_height} at ({roi_x}, {roi_y}) is outside its '
                f'{width} x {height} image',
            )
        height, width = roi_height, roi_width
    else:
        roi_x = roi_y = 0
    try:
        coefficients = np.asarray(distortion, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise DepthImageError('invalid_camera_info', 'camera info D is not a list of numbers') from None
    distorted = bool(np.any(coefficients != 0.0))
    undo = () if rectified or not distorted else _distortion_to_undo(distortion_model, coefficients)
    intrinsics = PinholeIntrinsics(fx / binning_x, fy / binning_y, (cx - roi_x) / binning_x, (cy - roi_y) / binning_y)
    height, width = height // binning_y, width // binning_x
    fx, fy, cx, cy = intrinsics.as_tuple()
    sideways = max(abs(cx), abs(width - 1 - cx)) / fx, max(abs(cy), abs(height - 1 - cy)) / fy
    if not max(sideways) <= MAX_RAY_SLOPE:  # also NaN (fx 1e-300 overflows)
        raise DepthImageError(
            'invalid_camera_info',
            f'camera info gives rays up to {max(sideways):g} times their depth sideways (fx {fx:g}, fy {fy:g}, '
            f'cx {cx:g}, cy {cy:g} for {width} x {height} images): not a pinhole calibration',
        )
    return DepthCamera(intrinsics, height, width, distorted, source, undo, distortion_model if undo else '')


#: Distortion models of raw depth images that are undone (ROS camera_calibration_parsers' names), with the
#: number of coefficients each uses: k1 k2 p1 p2 k3, and k4 k5 k6 of the rational model's denominator.
DISTORTION_MODELS = {'plumb_bob': 5, 'rational_polynomial': 8}


def _distortion_to_undo(model: str, coefficients: np.ndarray) -> tuple[float, ...]:
    """(k1, k2, p1, p2, k3, k4, k5, k6) of a raw image's distortion (missing trailing ones 0)."""
    used = DISTORTION_MODELS.get(model)
    if used is None or not np.isfinite(coefficients).all() or np.any(coefficients[used:] != 0.0):
        known = ', '.join(DISTORTION_MODELS)
        raise DepthImageError(
            'invalid_camera_info',
            f'camera info distortion {model!r} with D = {coefficients.tolist()} cannot be undone: raw depth images '
            f'take {known} (finite coefficients); rectify the image and set depth_image_rectified to true',
        )
    padded = np.zeros(8)
    padded[: min(used, coefficients.size)] = coefficients[:used]
    return tuple(float(c) for c in padded)


#: Fixed-point iterations of the undistortion at most (it stops when settled); a pixel whose ray then
#: reprojects more than UNDISTORTION_TOLERANCE_PX away from it (a distortion that folds over, far outside
#: the calibrated field of view) gets no ray and is no return.
UNDISTORTION_ITERATIONS = 50
UNDISTORTION_TOLERANCE_PX = 1e-3
#: The iteration stops when no pixel's normalized coordinates moved more than this in the last step.
UNDISTORTION_STEP = 1e-12


def _distort(x: np.ndarray, y: np.ndarray, k: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Normalized image coordinates of the undistorted ones (x, y) under distortion k (OpenCV's model)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = k
    r2 = x * x + y * y
    radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    return (
        x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
        y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
    )


@functools.lru_cache(maxsize=4)
def pixel_rays(camera: DepthCamera) -> np.ndarray:
    """``(H, W, 2)`` undistorted normalized coordinates (x / z, y / z) of every pixel's ray (read-only; NaN
    where the undistortion does not converge), by OpenCV's fixed-point iteration."""
    fx, fy, cx, cy = camera.intrinsics.as_tuple()
    xd = np.broadcast_to((np.arange(camera.width) - cx) / fx, (camera.height, camera.width))
    yd = np.broadcast_to(((np.arange(camera.height) - cy) / fy)[:, None], (camera.height, camera.width))
    k1, k2, p1, p2, k3, k4, k5, k6 = camera.distortion
    x, y = xd.copy(), yd.copy()
    with np.errstate(all='ignore'):  # a diverging pixel is caught below
        for _ in range(UNDISTORTION_ITERATIONS):
            r2 = x * x + y * y
            inverse = (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))) / (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)))
            previous_x, previous_y = x, y
            x, y = (
                (xd - 2.0 * p1 * x * y - p2 * (r2 + 2.0 * x * x)) * inverse,
                (yd - p1 * (r2 + 2.0 * y * y) - 2.0 * p2 * x * y) * inverse,
            )
            if max(np.abs(x - previous_x).max(), np.abs(y - previous_y).max()) <= UNDISTORTION_STEP:
                break  # every pixel settled (NaN, a diverged pixel, compares False: it iterates on)
        again_x, again_y = _distort(x, y, camera.distortion)
        error = np.hypot((again_x - xd) * fx, (again_y - yd) * fy)
    rays = np.stack([x, y], axis=-1)
    rays[~(error <= UNDISTORTION_TOLERANCE_PX)] = np.nan
    rays.setflags(write=False)
    return rays


def is_compressed(image: Any) -> bool:
    """Whether ``image`` is a ``sensor_msgs/CompressedImage`` (compressedDepth) rather than an Image."""
    return hasattr(image, 'format') and not hasattr(image, 'encoding')


def depth_image_size(image: Any) -> tuple[int, int]:
    """``(height, width)`` of a depth image, of a compressed one from its header (nothing decoded).

    Raises:
        DepthImageError: ``invalid_image`` (a compressed image whose header cannot be read).
    """
    if not is_compressed(image):
        return int(image.height), int(image.width)
    try:
        return compressed_depth_size(image)
    except CompressedDepthError as exc:
        raise DepthImageError('invalid_image', f'compressedDepth: {exc}') from None


def depth_values(image: Any) -> tuple[np.ndarray, float]:
    """The ``(H, W)`` depth counts of a ``sensor_msgs/Image`` (or of a compressedDepth ``sensor_msgs/CompressedImage``,
    :mod:`ppe_ros.ros.compressed_depth`) and the metres per count of its encoding.

    Raises:
        DepthImageError: ``invalid_image`` (not a depth encoding, a size of zero, a row step shorter than
            a row, a data size other than step x height; compressed data that do not decode).
    """
    if is_compressed(image):
        try:
            return decode_compressed_depth(image)
        except CompressedDepthError as exc:
            raise DepthImageError('invalid_image', f'compressedDepth: {exc}') from None
    try:
        height, width, step = int(image.height), int(image.width), int(image.step)
        encoding, big_endian, data = str(image.encoding), bool(image.is_bigendian), image.data
    except (AttributeError, TypeError, ValueError):
        raise DepthImageError('invalid_image', 'not a sensor_msgs/Image message') from None
    if encoding not in DEPTH_ENCODINGS:
        raise DepthImageError(
            'invalid_image',
            f'image encoding {encoding!r} is not a depth encoding: 16UC1 (or mono16) in millimetres or 32FC1 in '
            'metres (REP 118)',
        )
    kind, scale = DEPTH_ENCODINGS[encoding]
    dtype = np.dtype(('>' if big_endian else '<') + kind)
    if height <= 0 or width <= 0:
        raise DepthImageError('invalid_image', f'empty depth image (height {height}, width {width})')
    if step < width * dtype.itemsize:
        raise DepthImageError(
            'invalid_image', f'row step {step} bytes is shorter than a row of {width} x {dtype.itemsize} bytes'
        )
    buffer = message_bytes(data)
    if buffer.size != step * height:
        raise DepthImageError(
            'invalid_image', f'{buffer.size} data bytes, not step x height = {step} x {height} = {step * height}'
        )
    rows = buffer.reshape(height, step)[:, : width * dtype.itemsize]
    return np.ascontiguousarray(rows).view(dtype).reshape(height, width), scale


def depth_image_points(image: Any, camera_info: Any, *, rectified: bool = True) -> np.ndarray:
    """The ``(H, W, 3)`` float64 points (m, the image's optical frame; NaN = no return) of a depth image,
    rectified (P) or raw (``rectified=False``: K and D, see :func:`camera_model`).

    A pixel whose depth is 0, NaN or infinite is no return.

    Raises:
        DepthImageError: see :func:`depth_values` and :func:`camera_model`; ``camera_info_mismatch``
            when the image's size is not the one the camera info describes.
    """
    counts, scale = depth_values(image)
    camera = camera_model(camera_info, rectified=rectified)
    if counts.shape != (camera.height, camera.width):
        raise DepthImageError(
            'camera_info_mismatch',
            f'its size {counts.shape[1]} x {counts.shape[0]} is not the {camera.width} x {camera.height} that its '
            'camera info describes',
        )
    if counts.dtype.kind == 'f':  # NaN and +-inf: no return (backproject_depth: a depth <= 0 is none)
        counts = np.where(np.isfinite(counts), counts, 0.0)
    return backproject_depth(counts, camera.intrinsics, scale, rays=pixel_rays(camera) if camera.distortion else None)
