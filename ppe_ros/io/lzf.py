"""LZF (liblzf) block compression, as used by PCD ``DATA binary_compressed``.

An LZF block is a sequence of runs. A control byte ``c < 32`` starts a literal run of ``c + 1``
bytes that follow it; otherwise ``c >> 5`` is a match length code (7 = read one more length byte)
and the low 5 bits with the next byte give a back-reference offset: copy ``length + 2`` bytes
starting ``offset + 1`` bytes before the current output position (the source may overlap the
output, so the copy goes byte by byte).

Both directions are numba kernels (a 4 MB SynPEB payload decompresses in a few milliseconds).
The compressor is a straightforward greedy hash-chain-free variant of liblzf: any stream it
writes is a valid LZF stream, though not byte-identical to liblzf's output.
"""

from __future__ import annotations

import numba as nb
import numpy as np

_OK = 0
_TRUNCATED = 1
_OUTPUT_OVERFLOW = 2
_BAD_BACKREFERENCE = 3

_HASH_LOG = 14
_MAX_OFFSET = 1 << 13  # offsets 0 .. 8191 fit in 13 bits
_MAX_MATCH = 264  # encoded length (match - 2) at most 7 + 255
_MAX_LITERAL = 32


@nb.njit(cache=True, nogil=True)
def _lzf_decompress(src, dst):
    """Decode ``src`` into ``dst``; returns (status, input position, output position)."""
    n_in = src.shape[0]
    n_out = dst.shape[0]
    ip = 0
    op = 0
    while ip < n_in:
        ctrl = np.int64(src[ip])
        ip += 1
        if ctrl < 32:
            length = ctrl + 1
            if ip + length > n_in:
                return _TRUNCATED, ip, op
            if op + length > n_out:
                return _OUTPUT_OVERFLOW, ip, op
            for k in range(length):
                dst[op + k] = src[ip + k]
            ip += length
            op += length
        else:
            length = ctrl >> 5
            if length == 7:
                if ip >= n_in:
                    return _TRUNCATED, ip, op
                length += np.int64(src[ip])
                ip += 1
            if ip >= n_in:
                return _TRUNCATED, ip, op
            ref = op - ((ctrl & 0x1F) << 8) - np.int64(src[ip]) - 1
            ip += 1
            length += 2
            if ref < 0:
                return _BAD_BACKREFERENCE, ip, op
            if op + length > n_out:
                return _OUTPUT_OVERFLOW, ip, op
            for k in range(length):
                dst[op + k] = dst[ref + k]
            op += length
    return _OK, ip, op


@nb.njit(cache=True, nogil=True)
def _lzf_compress(src, dst):
    """Encode ``src`` into ``dst`` (large enough: n + n // 32 + 16); returns the output size."""
    n = src.shape[0]
    table = np.full(1 << _HASH_LOG, -1, dtype=np.int64)
    mask = (1 << _HASH_LOG) - 1
    op = 1  # dst[0] is the control byte of the first literal run
    lit = 0
    ip = 0
    while ip < n:
        matched = False
        if ip + 2 < n:
            key = (np.int64(src[ip]) << 16) | (np.int64(src[ip + 1]) << 8) | np.int64(src[ip + 2])
            slot = ((key * 2654435761) >> 12) & mask
            ref = table[slot]
            table[slot] = ip
            if ref >= 0:
                offset = ip - ref - 1
                if (
                    offset < _MAX_OFFSET
                    and src[ref] == src[ip]
                    and src[ref + 1] == src[ip + 1]
                    and src[ref + 2] == src[ip + 2]
                ):
                    matched = True
                    limit = min(n - ip, _MAX_MATCH)
                    length = 3
                    while length < limit and src[ref + length] == src[ip + length]:
                        length += 1
                    # close the pending literal run (or drop its unused control byte)
                    if lit > 0:
                        dst[op - lit - 1] = lit - 1
                    else:
                        op -= 1
                    code = length - 2
                    if code < 7:
                        dst[op] = (code << 5) | (offset >> 8)
                        op += 1
                    else:
                        dst[op] = (7 << 5) | (offset >> 8)
                        dst[op + 1] = code - 7
                        op += 2
                    dst[op] = offset & 0xFF
                    op += 1
                    op += 1  # control byte of the next literal run
                    lit = 0
                    ip += length
        if not matched:
            dst[op] = src[ip]
            op += 1
            ip += 1
            lit += 1
            if lit == _MAX_LITERAL:
                dst[op - lit - 1] = lit - 1
                op += 1
                lit = 0
    if lit > 0:
        dst[op - lit - 1] = lit - 1
    else:
        op -= 1
    return op


def _as_uint8(data: bytes | bytearray | memoryview | np.ndarray) -> np.ndarray:
    if isinstance(data, np.ndarray):
        return np.ascontiguousarray(data).view(np.uint8).reshape(-1)
    return np.frombuffer(data, dtype=np.uint8)


def lzf_decompress(data: bytes | bytearray | memoryview | np.ndarray, raw_size: int) -> np.ndarray:
    """Decompress an LZF block that must expand to exactly ``raw_size`` bytes.

    Returns:
        ``(raw_size,)`` uint8 array.

    Raises:
        ValueError: the block is truncated, refers before its start, or expands to a size other
            than ``raw_size`` (the message says expected vs found).
    """
    if raw_size < 0:
        raise ValueError(f'LZF raw size must be >= 0; got {raw_size}')
    src = _as_uint8(data)
    dst = np.empty(int(raw_size), dtype=np.uint8)
    status, ip, op = _lzf_decompress(src, dst)
    if status == _TRUNCATED:
        raise ValueError(
            f'corrupt or truncated LZF data: the block of {src.size} bytes ends inside a run '
            f'(at input byte {ip}, after {op} of the expected {raw_size} output bytes)'
        )
    if status == _OUTPUT_OVERFLOW:
        raise ValueError(
            f'corrupt LZF data: the block expands beyond the expected {raw_size} bytes '
            f'(at input byte {ip} of {src.size})'
        )
    if status == _BAD_BACKREFERENCE:
        raise ValueError(
            f'corrupt LZF data: back-reference before the start of the output at input byte {ip} (output position {op})'
        )
    if op != raw_size:
        raise ValueError(
            f'corrupt or truncated LZF data: expected {raw_size} decompressed bytes, found {op} '
            f'(compressed block of {src.size} bytes)'
        )
    return dst


def lzf_compress(data: bytes | bytearray | memoryview | np.ndarray) -> bytes:
    """Compress bytes into one LZF block (decodable by liblzf, PCL and :func:`lzf_decompress`)."""
    src = _as_uint8(data)
    dst = np.empty(src.size + src.size // 32 + 16, dtype=np.uint8)
    size = _lzf_compress(src, dst)
    return dst[:size].tobytes()
