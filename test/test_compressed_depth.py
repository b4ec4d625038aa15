"""compressedDepth messages: the RVL kernel against slow references, PNG, 32FC1 inverse depth, bad data."""

from __future__ import annotations

import io
import struct
from types import SimpleNamespace

import numpy as np
import pytest
from depth_frames import rvl_encode
from PIL import Image

from ppe_ros.ros.compressed_depth import (
    CompressedDepthError,
    _decode_rvl,
    compressed_depth_size,
    decode_compressed_depth,
    parse_format,
)


def rvl_decode(code: bytes, pixels: int) -> list[int] | None:
    """Slow reference decoder: the values, or None when the code ends early or a run overflows."""
    words = struct.unpack(f'<{len(code) // 4}I', code[: len(code) // 4 * 4])
    nibbles = [(w >> (28 - 4 * k)) & 0xF for w in words for k in range(8)]
    position = 0

    def number():
        nonlocal position
        value, shift = 0, 0
        while True:
            if position == len(nibbles):
                return None
            nibble = nibbles[position]
            position += 1
            if shift < 48:
                value |= (nibble & 7) << shift
            shift += 3
            if not nibble & 8:
                return value

    out: list[int] = []
    previous = 0
    while len(out) < pixels:
        zeros = number()
        if zeros is None or zeros > pixels - len(out):
            return None
        out += [0] * zeros
        if len(out) == pixels:
            break
        nonzeros = number()
        if nonzeros is None or nonzeros > pixels - len(out):
            return None
        for _ in range(nonzeros):
            value = number()
            if value is None:
                return None
            previous = (previous + ((value >> 1) ^ -(value & 1))) & 0xFFFF
            out.append(previous)
    return out


def message(encoding: str, codec: str, body: bytes, quant=(0.0, 0.0)):
    fmt = f'{encoding}; compressedDepth {codec}' if codec else f'{encoding}; compressedDepth'
    return SimpleNamespace(format=fmt, data=struct.pack('<iff', 0, *quant) + body)


def rvl_message(encoding: str, values: np.ndarray, quant=(0.0, 0.0)):
    height, width = values.shape
    return message(encoding, 'rvl', struct.pack('<II', width, height) + rvl_encode(values), quant)


def png_bytes(values: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(values.astype(np.uint16)).save(buffer, format='PNG')
    return buffer.getvalue()


def kernel(code: bytes, pixels: int) -> list[int] | None:
    words = np.frombuffer(code[: len(code) // 4 * 4], dtype='<u4').astype(np.int64)
    out = np.zeros(pixels, np.uint16)
    written = _decode_rvl(words, out)
    return out.tolist() if written == pixels else None


@pytest.mark.parametrize('seed', range(6))
def test_rvl_kernel_decodes_what_the_reference_encodes(seed):
    rng = np.random.default_rng(seed)
    height, width = int(rng.integers(1, 40)), int(rng.integers(1, 60))
    values = rng.integers(0, 65536, (height, width)).astype(np.uint16)
    values[rng.random(values.shape) < rng.uniform(0, 0.9)] = 0  # runs of no depth
    if seed == 0:
        values[:] = 0
    smooth = np.cumsum(rng.integers(-3, 4, values.shape), axis=1) + 2000  # small deltas, as real depth
    values = np.where(values > 0, smooth, 0).astype(np.uint16) if seed % 2 else values
    code = rvl_encode(values)
    assert kernel(code, values.size) == values.ravel().tolist()
    decoded, scale = decode_compressed_depth(rvl_message('16UC1', values))
    np.testing.assert_array_equal(decoded, values)
    assert scale == 1.0e-3 and compressed_depth_size(rvl_message('16UC1', values)) == values.shape


def test_rvl_kernel_agrees_with_the_reference_decoder_on_corrupt_codes():
    rng = np.random.default_rng(7)
    for _ in range(300):
        values = np.where(rng.random((6, 9)) < 0.5, rng.integers(1, 65536, (6, 9)), 0).astype(np.uint16)
        code = bytearray(rvl_encode(values))
        for _ in range(int(rng.integers(1, 4))):
            what = rng.integers(0, 3)
            if what == 0 and code:
                code[int(rng.integers(0, len(code)))] = int(rng.integers(0, 256))
            elif what == 1:
                code = code[: int(rng.integers(0, len(code) + 1))]
            else:
                code += bytes(rng.integers(0, 256, 4, dtype=np.uint8))
        pixels = int(rng.choice([values.size, values.size - 5, values.size + 7]))
        assert kernel(bytes(code), pixels) == rvl_decode(bytes(code), pixels)


@pytest.mark.parametrize('codec', ['png', 'rvl', ''])
def test_16uc1_is_millimetres_and_32fc1_inverse_depth_is_metres(codec):
    rng = np.random.default_rng(3)
    millimetres = np.where(rng.random((12, 17)) < 0.8, rng.integers(300, 9000, (12, 17)), 0).astype(np.uint16)
    body = png_bytes(millimetres) if codec != 'rvl' else None
    msg = message('16UC1', codec, body) if body is not None else rvl_message('16UC1', millimetres)
    values, scale = decode_compressed_depth(msg)
    np.testing.assert_array_equal(values, millimetres)
    assert scale == 1.0e-3
    # 32FC1: inverse depth v, depth A / (v - B), 0 = none (the publisher's quantisation of depth_max 10 m, 1 cm)
    quant_a = 0.01 * (0.01 + 1.0)
    quant_b = 1.0 - quant_a / 10.0
    inverse = np.where(millimetres > 0, millimetres // 3 + 100, 0).astype(np.uint16)
    msg = message('32FC1', codec, png_bytes(inverse), (quant_a, quant_b)) if codec != 'rvl' else None
    msg = msg or rvl_message('32FC1', inverse, (quant_a, quant_b))
    depth, scale = decode_compressed_depth(msg)
    expected = np.where(inverse > 0, np.float32(quant_a) / (inverse - np.float64(np.float32(quant_b))), np.nan)
    np.testing.assert_allclose(depth, expected, rtol=1e-12)
    assert scale == 1.0 and np.isnan(depth[inverse == 0]).all()


@pytest.mark.parametrize(
    ('msg', 'reason'),
    [
        (
            SimpleNamespace(format='16UC1; png compressed 16UC1', data=b'x' * 20),
            "is not image_transport's compressedDepth",
        ),
        (SimpleNamespace(format='16UC1; compressedDepth zstd', data=b'x' * 20), "codec 'zstd' is not png or rvl"),
        (SimpleNamespace(format='16UC1; compressedDepth rvl', data=b'x' * 12), 'no room for the 12-byte header'),
        (message('rgb8', 'png', png_bytes(np.ones((3, 3)))), "compressedDepth of 'rgb8'"),
        (message('16UC1', 'png', b'not a png at all'), 'the PNG does not decode'),
        (message('16UC1', 'rvl', b'\x01\x00'), 'RVL data of 2 bytes has no size'),
        (message('16UC1', 'rvl', struct.pack('<II', 100000, 100000) + b'\x00' * 8), 'cannot hold 100000 x 100000'),
        (message('16UC1', 'rvl', struct.pack('<II', 40, 40) + rvl_encode(np.ones((3, 3)))), 'RVL code ends after'),
    ],
)
def test_bad_messages_are_named(msg, reason):
    with pytest.raises(CompressedDepthError, match=None) as caught:
        decode_compressed_depth(msg)
    assert reason in str(caught.value)


def test_an_8_bit_png_is_not_depth():
    buffer = io.BytesIO()
    Image.fromarray(np.ones((4, 4), np.uint8)).save(buffer, format='PNG')
    with pytest.raises(CompressedDepthError, match="the PNG is 'L', not 16-bit grayscale"):
        decode_compressed_depth(message('16UC1', 'png', buffer.getvalue()))


def test_the_format_string():
    assert parse_format('16UC1; compressedDepth rvl') == ('16UC1', 'rvl')
    assert parse_format('32FC1; compressedDepth png') == ('32FC1', 'png')
    assert parse_format('16UC1; compressedDepth') == ('16UC1', 'png')  # old publishers: png


def test_corrupt_messages_decode_or_raise_the_named_error_only():
    """300 seeded corruptions (bytes changed, cut, appended; header sizes) of RVL and PNG messages of both
    encodings: each decodes to an array or raises CompressedDepthError, without any other error or warning."""
    import warnings

    rng = np.random.default_rng(11)
    millimetres = np.where(rng.random((9, 13)) < 0.7, rng.integers(400, 6000, (9, 13)), 0).astype(np.uint16)
    outcomes = {'decoded': 0, 'refused': 0}
    for case in range(300):
        encoding = '16UC1' if case % 2 else '32FC1'
        msg = rvl_message(encoding, millimetres, (0.0102, 0.999)) if case % 3 else None
        msg = msg or message(encoding, 'png', png_bytes(millimetres), (0.0102, 0.999))
        data = bytearray(msg.data)
        for _ in range(int(rng.integers(1, 4))):
            what = int(rng.integers(0, 4))
            if what == 0 and data:
                data[int(rng.integers(0, len(data)))] = int(rng.integers(0, 256))
            elif what == 1:
                data = data[: int(rng.integers(0, len(data) + 1))]
            elif what == 2:
                data += bytes(rng.integers(0, 256, int(rng.integers(1, 9)), dtype=np.uint8))
            elif len(data) >= 20:
                data[12:20] = struct.pack('<II', *(int(v) for v in rng.integers(0, 70000, 2)))
        msg.data = bytes(data)
        with warnings.catch_warnings():
            warnings.simplefilter('error')
            try:
                values, _ = decode_compressed_depth(msg)
            except CompressedDepthError:
                outcomes['refused'] += 1
                continue
        assert values.ndim == 2
        outcomes['decoded'] += 1
    assert outcomes['decoded'] > 20 and outcomes['refused'] > 20, outcomes
