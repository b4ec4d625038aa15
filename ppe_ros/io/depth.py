"""16-bit depth images + pinhole intrinsics -> organized clouds in the camera frame.

Camera frame: x right, y down, z forward (optical axis), metres. Pixel (row v, column u) with
depth value d becomes ``z = d * depth_scale``, ``x = (u - cx) z / fx``, ``y = (v - cy) z / fy``;
``d == 0`` means no measurement (NaN). The depth is the z coordinate (not the ray length), as in
TUM RGB-D, ICL-NUIM's PNG frames and Kinect depth maps.

Known calibration files recognised next to a PNG (see :func:`find_depth_calibration`):

* ICL-NUIM: a ``*.K`` file holding the 3x3 camera matrix (``configs_ICL_living_room.K``).
  Depth scale 1/5000 m per count. ICL writes ``fy = -480`` for its y-up convention; the y-down
  frame used here takes ``|fy|``.
* CAPE / Kinect v1: ``calib_params.xml`` (OpenCV storage); ``IR_intrinsic_params`` is the depth
  camera matrix. Depth in millimetres.

Pillow reads the PNG (imported when a PNG is read, so the rest of ``ppe_ros.io`` does not need it).
"""

from __future__ import annotations

import os
import struct
import xml.etree.ElementTree as ElementTree
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ppe_ros.io.errors import ScanFileError
from ppe_ros.io.limits import DEFLATE_MAX_EXPANSION, check_grid_size

_PNG_SIGNATURE = b'\x89PNG\r\n\x1a\n'

#: Metres per depth count of ICL-NUIM PNG frames.
ICL_NUIM_DEPTH_SCALE = 1.0 / 5000.0
#: Metres per depth count of Kinect v1 / CAPE PNG frames (millimetres).
KINECT_DEPTH_SCALE = 1.0e-3


@dataclass(frozen=True)
class PinholeIntrinsics:
    """Pinhole camera matrix entries in pixels (y-down image: fx, fy > 0)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        values = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(v) for v in values):
            raise ValueError(f'intrinsics must be finite; got fx, fy, cx, cy = {values}')
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(
                f'focal lengths must be positive for the y-down camera frame; got fx={self.fx}, fy={self.fy} '
                f"(a negative fy, like ICL-NUIM's -480, means +480 here)"
            )

    def as_tuple(self) -> tuple[float, float, float, float]:
        return (float(self.fx), float(self.fy), float(self.cx), float(self.cy))


@dataclass(frozen=True)
class DepthCalibration:
    """Intrinsics and depth scale (metres per count) of a depth camera, with where they came from."""

    intrinsics: PinholeIntrinsics
    depth_scale: float
    source: str


#: Chunks :func:`_check_png_chunks` walks at most (a PNG has a few; more are not checked, and cost no memory).
PNG_MAX_CHECKED_CHUNKS = 100_000


def _check_png_chunks(file_path: Path, file_size: int) -> None:
    """ScanFileError unless the data of every chunk, as long as its header declares (a chunk: 4-byte length,
    4-byte type, data, 4-byte CRC), is in the file, up to IEND: Pillow reads a chunk's data with one
    buffered read of its declared length, and Python allocates that length before it reads (a flipped
    length byte in a 100-byte file would allocate up to 4 GB). A file that ends in a chunk's CRC or
    before IEND passes, as Pillow reads its pixels."""
    with file_path.open('rb') as stream:
        position = len(_PNG_SIGNATURE)
        stream.seek(position)
        for _ in range(PNG_MAX_CHECKED_CHUNKS):
            header = stream.read(8)
            if len(header) < 8:
                return  # truncated: Pillow reports it
            length, kind = struct.unpack('>I4s', header)
            if kind == b'IEND':
                return  # Pillow does not read its data
            left = file_size - position - 8
            if length > left:
                name = kind.decode('latin-1').encode('unicode_escape').decode('ascii')
                raise ScanFileError(
                    f'{file_path}: corrupt PNG: chunk {name!r} at byte {position} declares {length} bytes of '
                    f'data, the file has {left} left'
                )
            position += 12 + length
            stream.seek(position)


def read_depth_png(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a single-channel 16-bit PNG as an ``(H, W)`` uint16 array of raw depth counts.

    Raises:
        FileNotFoundError: no such file.
        ScanFileError: not a readable PNG, not a 16-bit single-channel image, or a declared size beyond
            :mod:`ppe_ros.io.limits` or beyond what the file can hold (checked before decoding).
    """
    from PIL import Image, UnidentifiedImageError

    file_path = Path(path)
    if not file_path.is_file():
        raise FileNotFoundError(f'depth image not found: {file_path}')
    file_size = file_path.stat().st_size
    with file_path.open('rb') as stream:
        head = stream.read(24)
    if len(head) == 24 and head[:8] == _PNG_SIGNATURE and head[12:16] == b'IHDR':  # before Pillow's bomb check
        width, height = struct.unpack('>II', head[16:24])
        check_grid_size(file_path, height, width, 'depth image (PNG header)')
        _check_png_chunks(file_path, file_size)
    try:
        with Image.open(file_path) as image:  # reads the header only
            mode = image.mode
            if mode not in ('I;16', 'I;16B', 'I;16L', 'I'):
                raise ScanFileError(
                    f'{file_path}: expected a 16-bit single-channel depth PNG, found image mode {mode!r}'
                )
            width, height = image.size
            check_grid_size(file_path, height, width, 'depth image')
            raw_bytes = height * (width * (4 if mode == 'I' else 2) + 1)  # + one filter byte per row
            if raw_bytes > DEFLATE_MAX_EXPANSION * file_size:
                raise ScanFileError(
                    f'{file_path}: corrupt PNG: a file of {file_size} bytes cannot hold the declared {width} x '
                    f'{height} image ({raw_bytes} bytes; deflate expands at most {DEFLATE_MAX_EXPANSION}-fold)'
                )
            image.load()
            depth = np.array(image)
    except (
        UnidentifiedImageError,
        Image.DecompressionBombError,
        OSError,
        SyntaxError,
        ValueError,
        TypeError,
        IndexError,
        struct.error,
        zlib.error,
        EOFError,
    ) as exc:
        if isinstance(exc, ScanFileError):
            raise
        text = ' '.join(str(exc).split()) or type(exc).__name__
        raise ScanFileError(f'{file_path}: cannot read the PNG (corrupt or truncated?): {text}') from None
    if depth.ndim != 2:
        raise ScanFileError(f'{file_path}: expected a single-channel depth image, found shape {depth.shape}')
    if depth.dtype != np.uint16:
        if depth.size and (depth.min() < 0 or depth.max() > np.iinfo(np.uint16).max):
            raise ScanFileError(f'{file_path}: depth values outside the 16-bit range')
        depth = depth.astype(np.uint16)
    return depth


def _floats(text: str, source: Path, expected: int) -> np.ndarray:
    try:
        values = np.array(text.split(), dtype=np.float64)
    except ValueError:
        raise ScanFileError(f'{source}: expected {expected} numbers, found non-numeric text') from None
    if values.size != expected:
        raise ScanFileError(f'{source}: expected {expected} numbers (a 3x3 camera matrix), found {values.size}')
    return values


def read_camera_matrix_file(path: str | os.PathLike[str]) -> PinholeIntrinsics:
    """Read a whitespace-separated 3x3 camera matrix (ICL-NUIM ``*.K``); ``|fy|`` is used."""
    file_path = Path(path)
    matrix = _floats(file_path.read_text(encoding='latin-1'), file_path, 9).reshape(3, 3)
    return _intrinsics(file_path, fx=abs(matrix[0, 0]), fy=abs(matrix[1, 1]), cx=matrix[0, 2], cy=matrix[1, 2])


def _intrinsics(source: Path, **values: float) -> PinholeIntrinsics:
    try:
        return PinholeIntrinsics(**values)
    except ValueError as exc:  # zero or non-finite entries in the file
        raise ScanFileError(f'{source}: unusable camera matrix: {exc}') from None


def read_opencv_intrinsics(path: str | os.PathLike[str], node: str = 'IR_intrinsic_params') -> PinholeIntrinsics:
    """Read a 3x3 camera matrix ``node`` from an OpenCV XML storage file (CAPE ``calib_params.xml``)."""
    file_path = Path(path)
    try:
        root = ElementTree.parse(file_path).getroot()
    except ElementTree.ParseError as exc:
        raise ScanFileError(f'{file_path}: not a readable XML file: {exc}') from None
    element = root.find(f'{node}/data')
    if element is None or element.text is None:
        raise ScanFileError(f'{file_path}: no <{node}><data> camera matrix in the XML file')
    matrix = _floats(element.text, file_path, 9).reshape(3, 3)
    return _intrinsics(file_path, fx=matrix[0, 0], fy=abs(matrix[1, 1]), cx=matrix[0, 2], cy=matrix[1, 2])


def find_depth_calibration(png_path: str | os.PathLike[str]) -> DepthCalibration | None:
    """The calibration of a known data set stored next to a depth PNG, or None.

    Looks for ``calib_params.xml`` (Kinect v1 / CAPE: millimetres, IR intrinsics) and for a single
    ``*.K`` camera matrix (ICL-NUIM: 1/5000 m per count).

    Raises:
        ScanFileError: several ``*.K`` files (ambiguous) or an unreadable calibration file.
    """
    folder = Path(png_path).parent
    calib = folder / 'calib_params.xml'
    if calib.is_file():
        return DepthCalibration(read_opencv_intrinsics(calib), KINECT_DEPTH_SCALE, f'{calib} (Kinect v1, mm)')
    matrices = sorted(folder.glob('*.K'))
    if len(matrices) > 1:
        names = ', '.join(m.name for m in matrices)
        raise ScanFileError(f'{folder}: several camera matrix files ({names}); pass the intrinsics explicitly')
    if matrices:
        return DepthCalibration(
            read_camera_matrix_file(matrices[0]), ICL_NUIM_DEPTH_SCALE, f'{matrices[0]} (ICL-NUIM, 1/5000 m)'
        )
    return None


def backproject_depth(
    depth: np.ndarray, intrinsics: PinholeIntrinsics, depth_scale: float, *, rays: np.ndarray | None = None
) -> np.ndarray:
    """Organized ``(H, W, 3)`` float64 cloud (camera frame, metres) from raw depth counts.

    Args:
        depth: ``(H, W)`` non-negative depth counts; 0 = no measurement (NaN in the output).
        intrinsics: pinhole parameters in pixels.
        depth_scale: metres per count (> 0).
        rays: ``(H, W, 2)`` each pixel's ray as (x / z, y / z) instead of the pinhole's ((u - cx) / fx,
            (v - cy) / fy), e.g. a distorted camera's undistorted rays; NaN = no ray (no return).
    """
    counts = np.asarray(depth)
    if counts.ndim != 2:
        raise ValueError(f'depth must be an (H, W) image; got shape {counts.shape}')
    if not (np.isfinite(depth_scale) and depth_scale > 0):
        raise ValueError(f'depth_scale must be a positive number of metres per count; got {depth_scale}')
    height, width = counts.shape
    z = counts.astype(np.float64) * float(depth_scale)
    z[~(z > 0)] = np.nan
    if rays is None:
        x_per_z = ((np.arange(width, dtype=np.float64) - intrinsics.cx) / intrinsics.fx)[None, :]
        y_per_z = ((np.arange(height, dtype=np.float64) - intrinsics.cy) / intrinsics.fy)[:, None]
    else:
        if rays.shape != (height, width, 2):
            raise ValueError(f'rays must be ({height}, {width}, 2) for this depth image; got {rays.shape}')
        x_per_z, y_per_z = rays[..., 0], rays[..., 1]
        z[np.isnan(x_per_z)] = np.nan
    cloud = np.empty((height, width, 3), dtype=np.float64)
    cloud[..., 0] = z * x_per_z
    cloud[..., 1] = z * y_per_z
    cloud[..., 2] = z
    return cloud
