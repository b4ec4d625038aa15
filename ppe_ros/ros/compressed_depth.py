"""Depth images of image_transport's ``compressedDepth`` transport (``sensor_msgs/CompressedImage``).

compressed_depth_image_transport publishes a depth image on ``<image topic>/compressedDepth`` with ``format``
``"<encoding>; compressedDepth <codec>"`` (``"<encoding>; compressedDepth"`` in old versions: png) and ``data`` =
a 12-byte header (int32 format, float32 quantisation parameters A and B, little-endian) followed by

* ``png``: a 16-bit grayscale PNG;
* ``rvl``: uint32 columns, uint32 rows and the RVL code (Wilson 2017) of the 16-bit values: 32-bit words whose
  nibbles, most significant first, hold variable-length numbers (3 bits each, the 4th bit: more follow):
  alternately a run of zeros and a run of non-zeros, each non-zero value as the zigzag-coded difference to the
  previous non-zero value.

``16UC1`` images carry millimetres; ``32FC1`` ones inverse depth: a value v != 0 is the depth A / (v - B) in
metres, 0 is no depth. Decoding is bounded by the message: a size that does not fit the data or a code that
runs past either end is an error, never a read outside the buffers.
"""

from __future__ import annotations

import contextlib
import io
import struct
import warnings
from collections.abc import Iterator
from typing import Any

import numba as nb
import numpy as np

from ppe_ros.ros.pointcloud2 import message_bytes

#: Bytes of the header in front of the compressed data (compressionFormat int32, depthParam float32[2]).
HEADER_BYTES = 12
#: Codecs of the format string's "compressedDepth <codec>".
CODECS = ('png', 'rvl')
#: Pixels an RVL frame may claim per byte of its code: an all-zero 4K frame takes a handful of bytes, so the
#: bound is loose; callers check a frame's size (max_points) from its header before decoding it.
RVL_MAX_PIXELS_PER_BYTE = 2**20


class CompressedDepthError(ValueError):
    """A compressedDepth message that cannot be decoded (the reason says why)."""


def parse_format(text: str) -> tuple[str, str]:
    """``(encoding, codec)`` of a compressedDepth ``format`` string, e.g. ``('16UC1', 'rvl')``.

    Raises:
        CompressedDepthError: not a compressedDepth format, or an unknown codec.
    """
    encoding, _, rest = str(text).partition(';')
    words = rest.split()
    if not words or words[0] != 'compressedDepth':
        raise CompressedDepthError(
            f'format {text!r} is not image_transport\'s compressedDepth ("<encoding>; compressedDepth png|rvl")'
        )
    codec = words[1] if len(words) > 1 else 'png'
    if codec not in CODECS:
        raise CompressedDepthError(f'format {text!r}: codec {codec!r} is not png or rvl')
    return encoding.strip(), codec


def _payload(msg: Any) -> tuple[str, str, float, float, np.ndarray]:
    """(encoding, codec, A, B, the bytes after the header, a uint8 view of the message's data: no copy)."""
    encoding, codec = parse_format(msg.format)
    data = message_bytes(msg.data)
    if len(data) <= HEADER_BYTES:
        raise CompressedDepthError(f'{len(data)} data bytes: no room for the {HEADER_BYTES}-byte header and an image')
    _, quant_a, quant_b = struct.unpack_from('<iff', data)
    return encoding, codec, quant_a, quant_b, data[HEADER_BYTES:]


def compressed_depth_size(msg: Any) -> tuple[int, int]:
    """``(height, width)`` a compressedDepth message says it holds, read from its header (nothing decoded)."""
    _, codec, _, _, body = _payload(msg)
    if codec == 'rvl':
        width, height = _rvl_size(body)
    else:
        with _opened_png(body, 'open') as image:
            width, height = image.size
    return height, width


def _rvl_size(body: np.ndarray) -> tuple[int, int]:
    """(width, height) at the start of RVL data."""
    if len(body) < 8:
        raise CompressedDepthError(f'RVL data of {len(body)} bytes has no size')
    return struct.unpack_from('<II', body)


@contextlib.contextmanager
def _opened_png(body: np.ndarray, doing: str) -> Iterator[Any]:
    """The Pillow image of PNG bytes; Pillow's errors of a corrupt file (OSError, SyntaxError, zlib.error, ...),
    also while the caller reads it, become a CompressedDepthError saying what it does not ``doing``."""
    from PIL import Image

    try:
        with warnings.catch_warnings():  # a huge size is the caller's to refuse (max_points), not a warning
            warnings.simplefilter('ignore', Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(body)) as image:
                yield image
    except CompressedDepthError:
        raise
    except Exception as exc:
        raise CompressedDepthError(f'the PNG does not {doing}: {type(exc).__name__}: {exc}') from None


def decode_compressed_depth(msg: Any) -> tuple[np.ndarray, float]:
    """The ``(H, W)`` depth values of a compressedDepth message and metres per value: uint16 millimetres
    (0 = no depth) for 16UC1, float64 metres (NaN = no depth) for 32FC1. Check the size it claims
    (:func:`compressed_depth_size`) first: the values are allocated at that size.

    Raises:
        CompressedDepthError: see :func:`parse_format`; an encoding other than 16UC1 / 32FC1, a PNG that is not
            16-bit grayscale or does not decode, RVL data that does not hold its size's pixels.
    """
    encoding, codec, quant_a, quant_b, body = _payload(msg)
    if encoding not in ('16UC1', '32FC1'):
        raise CompressedDepthError(f'compressedDepth of {encoding!r}: only 16UC1 and 32FC1 are depth images')
    values = _rvl_values(body) if codec == 'rvl' else _png_values(body)
    if encoding == '16UC1':
        return values, 1.0e-3
    with np.errstate(divide='ignore', invalid='ignore'):
        depth = np.where(values > 0, float(quant_a) / (values.astype(np.float64) - float(quant_b)), np.nan)
    return depth, 1.0


def warm_up_rvl() -> float:
    """Decode a one-pixel RVL message: compiles (or loads) the decoder's kernel; returns the seconds taken."""
    import time
    from types import SimpleNamespace

    start = time.perf_counter()
    # one pixel of depth 1: a run of 0 zeros (nibble 0), a run of 1 non-zero (1), its zigzag delta 2 (2)
    code = struct.pack('<iffII', 0, 0.0, 0.0, 1, 1) + struct.pack('<I', 0x01200000)
    values, _ = decode_compressed_depth(SimpleNamespace(format='16UC1; compressedDepth rvl', data=code))
    if values.tolist() != [[1]]:
        raise RuntimeError(f'the RVL warm-up decoded {values.tolist()}, not [[1]]')
    return time.perf_counter() - start


def _png_values(body: np.ndarray) -> np.ndarray:
    with _opened_png(body, 'decode') as image:
        if image.mode not in ('I;16', 'I;16B', 'I;16L', 'I'):
            raise CompressedDepthError(f'the PNG is {image.mode!r}, not 16-bit grayscale')
        values = np.asarray(image)
    if values.ndim != 2 or values.min(initial=0) < 0 or values.max(initial=0) > 65535:
        raise CompressedDepthError('the PNG does not hold 16-bit depth values')
    return values.astype(np.uint16)


def _rvl_values(body: np.ndarray) -> np.ndarray:
    width, height = _rvl_size(body)
    code = body[8:]
    pixels = width * height
    if pixels == 0 or pixels > RVL_MAX_PIXELS_PER_BYTE * max(len(code), 1):
        raise CompressedDepthError(f'RVL data of {len(code)} bytes cannot hold {width} x {height} pixels')
    words = np.frombuffer(code[: len(code) // 4 * 4], dtype='<u4').astype(np.int64)
    out = np.empty(pixels, np.uint16)
    decoded = _decode_rvl(words, out)
    if decoded != pixels:
        raise CompressedDepthError(f'RVL code ends after {max(decoded, 0)} of {width} x {height} pixels')
    return out.reshape(height, width)


@nb.njit(cache=True, nogil=True)
def _next_number(words, state):
    """The code's next variable-length number (3 bits a nibble, lowest first; a nibble's 4th bit: more follow),
    or -1 when the words end. state: [next word's index, the current word's unread nibbles (top first), how
    many]."""
    value = 0
    shift = 0
    while True:
        if state[2] == 0:
            if state[0] == words.size:
                return -1
            state[1] = words[state[0]]
            state[0] += 1
            state[2] = 8
        nibble = (state[1] >> 28) & 0xF
        state[1] = (state[1] << 4) & 0xFFFFFFFF
        state[2] -= 1
        if shift < 48:  # a corrupt code's longer numbers saturate instead of overflowing
            value |= (nibble & 7) << shift
        shift += 3
        if not nibble & 8:
            return value


@nb.njit(cache=True, nogil=True)
def _decode_rvl(words, out):
    """Decode the RVL code ``words`` (uint32 as int64) into ``out`` (uint16); returns the pixels written: fewer
    than ``out.size`` when the code ends early, -1 when a run claims more pixels than are left."""
    n = out.size
    state = np.zeros(3, np.int64)
    position = 0
    previous = 0
    while position < n:
        zeros = _next_number(words, state)
        if zeros < 0:
            return position
        if zeros > n - position:
            return -1
        out[position : position + zeros] = 0
        position += zeros
        if position == n:
            break
        nonzeros = _next_number(words, state)
        if nonzeros < 0:
            return position
        if nonzeros > n - position:
            return -1
        for _ in range(nonzeros):
            value = _next_number(words, state)
            if value < 0:
                return position
            previous = (previous + ((value >> 1) ^ -(value & 1))) & 0xFFFF
            out[position] = previous
            position += 1
    return position
