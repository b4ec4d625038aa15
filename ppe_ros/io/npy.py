"""``.npy`` arrays read with their header checked first (shape, dtype, size against the file size).

:func:`numpy.load` allocates whatever a header declares and raises assorted exception types on a
damaged header (EOFError for an empty file, tokenize errors for a flipped byte). Here the header is
parsed with :mod:`numpy.lib.format`, the caller checks the declared shape and dtype, the declared data
size is compared with the bytes in the file, and only then is the array read.
"""

from __future__ import annotations

import math
import os
import tokenize
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

import numpy as np

from ppe_ros.io.errors import ScanFileError

#: Exceptions numpy's header parser raises on damaged bytes (found by fuzzing).
_HEADER_ERRORS = (ValueError, SyntaxError, TypeError, KeyError, EOFError, tokenize.TokenError, RecursionError)


def read_npy(
    path: str | os.PathLike[str],
    check: Callable[[tuple[int, ...], np.dtype], None] | None = None,
    *,
    what: str = '.npy array',
) -> np.ndarray:
    """Read a ``.npy`` file after checking its header.

    Args:
        path: the file.
        check: called with the declared ``(shape, dtype)`` before anything is allocated; raises
            :class:`ScanFileError` to refuse the array (wrong shape, too large, wrong dtype).
        what: what the file should be, for the messages (e.g. ``'ground-truth labels .npy'``).

    Raises:
        ScanFileError: not a .npy file, damaged header, object dtype, truncated data, refused by ``check``.
    """
    file_path = Path(path)
    with file_path.open('rb') as stream:
        return read_npy_stream(stream, file_path.stat().st_size, str(file_path), check, what=what)


def read_npy_stream(
    stream: BinaryIO,
    size: int,
    name: str,
    check: Callable[[tuple[int, ...], np.dtype], None] | None = None,
    *,
    what: str = '.npy array',
) -> np.ndarray:
    """:func:`read_npy` from an open binary stream of ``size`` bytes (e.g. a member of an ``.npz``)
    named ``name`` in the messages."""
    try:
        version = np.lib.format.read_magic(stream)
    except _HEADER_ERRORS as exc:
        raise ScanFileError(
            f'{name}: not a readable {what} (no .npy header; empty or not a .npy file): {_one_line(exc)}'
        ) from None
    if version not in ((1, 0), (2, 0)):
        raise ScanFileError(f'{name}: unsupported .npy format version {version[0]}.{version[1]}')
    reader = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    try:
        shape, fortran_order, dtype = reader(stream)
    except _HEADER_ERRORS as exc:
        raise ScanFileError(f'{name}: not a readable {what}: damaged .npy header ({_one_line(exc)})') from None
    if dtype.hasobject:
        raise ScanFileError(f'{name}: the .npy array holds Python objects ({dtype}); expected numbers')
    if check is not None:
        check(shape, dtype)
    count = math.prod(shape)
    declared = count * dtype.itemsize
    available = size - stream.tell()
    if declared > available:
        raise ScanFileError(
            f'{name}: truncated .npy data: the header declares shape {shape} of {dtype} '
            f'= {declared} bytes, the file holds {available} after the header'
        )
    buffer = bytearray(declared)
    filled = 0
    view = memoryview(buffer)
    while filled < declared:
        got = stream.readinto(view[filled:])
        if not got:
            break
        filled += got
    del view
    if filled < declared:
        raise ScanFileError(f'{name}: truncated .npy data: read {filled} of {declared} bytes')
    data = np.frombuffer(buffer, dtype=dtype, count=count) if count else np.empty(0, dtype=dtype)
    return data.reshape(shape, order='F' if fortran_order else 'C')


def _one_line(exc: BaseException) -> str:
    text = ' '.join(str(exc).split())
    return text[:200] or type(exc).__name__
