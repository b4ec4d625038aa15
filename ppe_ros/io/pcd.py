"""PCD v0.7 files (Point Cloud Library format): reader for ascii / binary / binary_compressed, writer.

Layout facts used here (PCL ``pcd_io``, MATLAB ``pcwrite``):

* The header is text lines ``KEYWORD values``; ``#`` starts a comment (MATLAB's comments contain
  non-ASCII bytes, so the header is decoded as Latin-1). It ends with the ``DATA`` line.
* ``DATA ascii``: one point per line, values separated by white space.
* ``DATA binary``: ``POINTS`` packed little-endian records (fields in header order, no padding).
* ``DATA binary_compressed``: uint32 compressed size, uint32 raw size, then one LZF block whose
  payload is field by field: all values of the first field, then all of the second, ...
* Organized clouds: ``HEIGHT > 1``; point k is row ``k // WIDTH``, column ``k % WIDTH``.

:func:`read_pcd` returns the raw fields as a structured array of shape ``(HEIGHT, WIDTH)``;
:func:`ppe_ros.io.loading.load_scan` turns that into metres and labels.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ppe_ros.io.errors import ScanFileError
from ppe_ros.io.files import write_file_atomically
from ppe_ros.io.limits import (
    LZF_MAX_EXPANSION,
    MAX_ASCII_BYTES_PER_VALUE,
    MAX_GRID_DIMENSION,
    MAX_PCD_VALUES_PER_POINT,
    MAX_SCAN_POINTS,
)
from ppe_ros.io.lzf import lzf_compress, lzf_decompress

ENCODINGS = ('ascii', 'binary', 'binary_compressed')

#: (PCD TYPE, SIZE) -> little-endian numpy type.
_PCD_TO_NUMPY: dict[tuple[str, int], str] = {
    ('I', 1): 'i1',
    ('I', 2): '<i2',
    ('I', 4): '<i4',
    ('I', 8): '<i8',
    ('U', 1): 'u1',
    ('U', 2): '<u2',
    ('U', 4): '<u4',
    ('U', 8): '<u8',
    ('F', 4): '<f4',
    ('F', 8): '<f8',
}

_KEYWORDS = ('VERSION', 'FIELDS', 'SIZE', 'TYPE', 'COUNT', 'WIDTH', 'HEIGHT', 'VIEWPOINT', 'POINTS', 'DATA')

#: The header is at most this long (a real one is a few hundred bytes).
_MAX_HEADER_BYTES = 1 << 16


@dataclass(frozen=True)
class PcdHeader:
    """The parsed header of a PCD file.

    Attributes:
        version: the VERSION value as written (e.g. ``'0.7'`` or ``'.7'``).
        fields, sizes, types, counts: per-field name, byte size, type letter (I/U/F) and count.
        width, height: grid size; ``height == 1`` means unorganized.
        points: number of points (``width * height``).
        viewpoint: ``(tx, ty, tz, qw, qx, qy, qz)`` acquisition pose in the points' frame.
        encoding: ``'ascii'``, ``'binary'`` or ``'binary_compressed'``.
        data_offset: byte offset of the point data in the file.
    """

    version: str
    fields: tuple[str, ...]
    sizes: tuple[int, ...]
    types: tuple[str, ...]
    counts: tuple[int, ...]
    width: int
    height: int
    points: int
    viewpoint: tuple[float, ...]
    encoding: str
    data_offset: int

    @property
    def is_organized(self) -> bool:
        """True for a 2-D grid (``HEIGHT > 1``)."""
        return self.height > 1

    def dtype(self) -> np.dtype:
        """Packed little-endian structured dtype of one point (duplicate names get a suffix)."""
        names: list[str] = []
        formats: list[object] = []
        for name, size, kind, count in zip(self.fields, self.sizes, self.types, self.counts, strict=True):
            unique = name
            suffix = 1
            while unique in names:
                unique = f'{name}_{suffix}'
                suffix += 1
            names.append(unique)
            base = np.dtype(_PCD_TO_NUMPY[(kind, size)])
            formats.append(base if count == 1 else (base, (count,)))
        return np.dtype({'names': names, 'formats': formats})


@dataclass(frozen=True, eq=False)
class PcdCloud:
    """A PCD file's header and its points as a structured array of shape ``(height, width)``."""

    header: PcdHeader
    data: np.ndarray


def _error(path: Path | str, message: str) -> ScanFileError:
    return ScanFileError(f'{path}: {message}')


def _parse_ints(path: Path | str, keyword: str, values: list[str], expected: int | None) -> tuple[int, ...]:
    try:
        numbers = tuple(int(v) for v in values)
    except ValueError:
        raise _error(path, f'PCD header {keyword} must be integers; found {" ".join(values)!r}') from None
    if expected is not None and len(numbers) != expected:
        raise _error(path, f'PCD header {keyword} has {len(numbers)} values, FIELDS has {expected}')
    return numbers


def parse_pcd_header(raw: bytes, path: Path | str = '<bytes>') -> PcdHeader:
    """Parse the header at the start of a PCD file's bytes.

    Raises:
        ScanFileError: not a PCD header, missing or inconsistent entries, unsupported types.
    """
    entries: dict[str, list[str]] = {}
    position = 0
    data_offset = -1
    line_number = 0
    while position < len(raw) and position < _MAX_HEADER_BYTES:
        end = raw.find(b'\n', position)
        if end < 0:
            end = len(raw)
        line = raw[position:end].decode('latin-1').strip()
        position = end + 1
        line_number += 1
        if not line or line.startswith('#'):
            continue
        keyword, *values = line.split()
        keyword = keyword.upper()
        if keyword not in _KEYWORDS:
            if not entries:
                raise _error(
                    path,
                    f'not a PCD file: line {line_number} starts with {keyword[:40]!r}, '
                    f'expected a PCD header keyword such as VERSION or FIELDS',
                )
            raise _error(path, f'unknown PCD header keyword {keyword[:40]!r} on line {line_number}')
        entries[keyword] = values
        if keyword == 'DATA':
            data_offset = min(position, len(raw))
            break
    if data_offset < 0:
        if not entries:
            raise _error(path, 'not a PCD file: no header found')
        raise _error(path, 'incomplete PCD header: no DATA line (file truncated?)')
    for required in ('FIELDS', 'SIZE', 'TYPE', 'WIDTH', 'HEIGHT'):
        if required not in entries:
            raise _error(path, f'PCD header has no {required} line')

    fields = tuple(entries['FIELDS'])
    if not fields:
        raise _error(path, 'PCD header FIELDS is empty')
    n_fields = len(fields)
    sizes = _parse_ints(path, 'SIZE', entries['SIZE'], n_fields)
    types = tuple(t.upper() for t in entries['TYPE'])
    if len(types) != n_fields:
        raise _error(path, f'PCD header TYPE has {len(types)} values, FIELDS has {n_fields}')
    counts = _parse_ints(path, 'COUNT', entries['COUNT'], n_fields) if 'COUNT' in entries else (1,) * n_fields
    for name, size, kind, count in zip(fields, sizes, types, counts, strict=True):
        if (kind, size) not in _PCD_TO_NUMPY:
            raise _error(
                path,
                f'field {name!r}: unsupported TYPE {kind} with SIZE {size} '
                f'(supported: I/U with 1, 2, 4, 8 bytes, F with 4 or 8)',
            )
        if count < 1:
            raise _error(path, f'field {name!r}: COUNT must be >= 1; found {count}')
    (width,) = _parse_ints(path, 'WIDTH', entries['WIDTH'], 1)
    (height,) = _parse_ints(path, 'HEIGHT', entries['HEIGHT'], 1)
    if width < 0 or height < 0:
        raise _error(path, f'PCD header WIDTH {width} / HEIGHT {height} must be >= 0')
    points = width * height
    if 'POINTS' in entries:
        (declared,) = _parse_ints(path, 'POINTS', entries['POINTS'], 1)
        if declared != points:
            raise _error(
                path, f'PCD header POINTS {declared} differs from WIDTH × HEIGHT = {width} × {height} = {points}'
            )
    viewpoint = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    if 'VIEWPOINT' in entries:
        try:
            viewpoint = tuple(float(v) for v in entries['VIEWPOINT'])
        except ValueError:
            raise _error(path, f'PCD header VIEWPOINT must be 7 numbers; found {entries["VIEWPOINT"]}') from None
        if len(viewpoint) != 7:
            raise _error(path, f'PCD header VIEWPOINT must be 7 numbers (tx ty tz qw qx qy qz); found {len(viewpoint)}')
    encoding = ' '.join(entries['DATA']).lower()
    if encoding not in ENCODINGS:
        raise _error(path, f'unsupported PCD DATA encoding {encoding!r} (supported: {", ".join(ENCODINGS)})')
    version = entries['VERSION'][0] if entries.get('VERSION') else '0.7'
    return PcdHeader(
        version=version,
        fields=fields,
        sizes=sizes,
        types=types,
        counts=counts,
        width=width,
        height=height,
        points=points,
        viewpoint=viewpoint,
        encoding=encoding,
        data_offset=data_offset,
    )


def _check_limits(path: Path | str, header: PcdHeader) -> int:
    """Refuse declared sizes beyond :mod:`ppe_ros.io.limits`; returns the bytes per point."""
    values_per_point = sum(header.counts)
    if values_per_point > MAX_PCD_VALUES_PER_POINT:
        raise _error(
            path,
            f'PCD header COUNT declares {values_per_point} values per point; at most '
            f'{MAX_PCD_VALUES_PER_POINT} are supported (corrupt header?)',
        )
    if header.points > MAX_SCAN_POINTS:
        raise _error(
            path,
            f'PCD header declares {header.points} points (WIDTH {header.width} × HEIGHT '
            f'{header.height}); at most {MAX_SCAN_POINTS} points per scan are supported',
        )
    if header.height > 1 and max(header.width, header.height) > MAX_GRID_DIMENSION:
        raise _error(
            path,
            f'PCD header declares a {header.height} × {header.width} grid; at most '
            f'{MAX_GRID_DIMENSION} rows and columns are supported',
        )
    return sum(size * count for size, count in zip(header.sizes, header.counts, strict=True))


def _ascii_chunks(body: bytes, chunk_bytes: int = 1 << 23):
    """``body`` in pieces of about ``chunk_bytes`` that end at white space (no value is split)."""
    position = 0
    while position < len(body):
        end = min(position + chunk_bytes, len(body))
        while end < len(body) and not body[end : end + 1].isspace():
            end += 1
        yield body[position:end]
        position = end


def _read_ascii(path: Path | str, header: PcdHeader, body: bytes, dtype: np.dtype) -> np.ndarray:
    values_per_point = sum(header.counts)
    expected = header.points * values_per_point
    numbers = np.empty(expected, dtype=np.float64)
    found = 0
    for chunk in _ascii_chunks(body):  # in pieces: a list of all tokens would need ~50 bytes per value
        tokens = chunk.split()
        if found + len(tokens) > expected:
            raise _error(
                path,
                f'corrupt DATA ascii: expected {expected} values (POINTS {header.points} × '
                f'{values_per_point} per point), found more',
            )
        try:
            numbers[found : found + len(tokens)] = np.array(tokens, dtype=np.float64)
        except ValueError as exc:
            raise _error(path, f'corrupt DATA ascii: a value is not a number ({exc})') from None
        found += len(tokens)
    if found != expected:
        raise _error(
            path,
            f'truncated DATA ascii: expected {expected} values (POINTS {header.points} × '
            f'{values_per_point} per point), found {found}',
        )
    numbers = numbers.reshape(header.points, values_per_point)
    out = np.zeros(header.points, dtype=dtype)
    column = 0
    for name, count in zip(dtype.names, header.counts, strict=True):
        block = numbers[:, column : column + count]
        target = out[name]
        if np.issubdtype(target.dtype, np.integer):
            if not np.all(np.isfinite(block)):
                raise _error(path, f'corrupt DATA ascii: integer field {name!r} holds a non-finite value')
        with np.errstate(invalid='ignore', over='ignore'):
            out[name] = block[:, 0] if count == 1 else block
        column += count
    return out


def _read_exactly(stream, size: int) -> bytearray:
    buffer = bytearray(size)
    view = memoryview(buffer)
    filled = 0
    while filled < size:
        got = stream.readinto(view[filled:])
        if not got:
            break
        filled += got
    del view
    if filled < size:
        del buffer[filled:]
    return buffer


def _read_body(path: Path, header: PcdHeader, dtype: np.dtype, bytes_per_point: int) -> np.ndarray:
    """Check the declared data size against the file size, then read and decode the point data."""
    available = path.stat().st_size - header.data_offset
    with path.open('rb') as stream:
        stream.seek(header.data_offset)
        if header.encoding == 'binary':
            expected = header.points * bytes_per_point
            if available < expected:
                raise _error(
                    path,
                    f'truncated DATA binary: expected {expected} bytes (POINTS {header.points} × '
                    f'{bytes_per_point} bytes per point), found {available}',
                )
            body = _read_exactly(stream, expected)
            return np.frombuffer(body, dtype=dtype, count=header.points)
        if header.encoding == 'ascii':
            values = header.points * sum(header.counts)
            if available < 2 * values - 1:  # each value takes a character and a separator
                raise _error(
                    path,
                    f'truncated DATA ascii: expected {values} values (POINTS {header.points} × '
                    f'{sum(header.counts)} per point), found only {available} bytes of text',
                )
            if available > values * MAX_ASCII_BYTES_PER_VALUE + (1 << 16):
                raise _error(
                    path,
                    f'corrupt DATA ascii: {available} bytes of text for {values} values '
                    f'(POINTS {header.points}); a value takes at most {MAX_ASCII_BYTES_PER_VALUE}',
                )
            return _read_ascii(path, header, bytes(_read_exactly(stream, available)), dtype)
        if available < 8:
            raise _error(
                path, f'truncated DATA binary_compressed: expected an 8-byte size prefix, found {available} bytes'
            )
        compressed_size, raw_size = struct.unpack('<II', _read_exactly(stream, 8))
        expected_raw = header.points * bytes_per_point
        if raw_size != expected_raw:
            raise _error(
                path,
                f'corrupt DATA binary_compressed: the size prefix says {raw_size} raw bytes, '
                f'the header needs {expected_raw} (POINTS {header.points} × {bytes_per_point})',
            )
        if available - 8 < compressed_size:
            raise _error(
                path,
                f'truncated DATA binary_compressed: expected {compressed_size} compressed bytes, found {available - 8}',
            )
        if raw_size > LZF_MAX_EXPANSION * compressed_size + 264:
            raise _error(
                path,
                f'corrupt DATA binary_compressed: {compressed_size} compressed bytes cannot expand to '
                f'the declared {raw_size} raw bytes (LZF expands at most {LZF_MAX_EXPANSION}-fold)',
            )
        block = np.frombuffer(_read_exactly(stream, compressed_size), dtype=np.uint8)
    try:
        raw = lzf_decompress(block, raw_size)
    except ValueError as exc:
        raise _error(path, str(exc)) from None
    del block
    out = np.empty(header.points, dtype=dtype)
    start = 0
    for name in dtype.names:
        field_dtype = dtype.fields[name][0]
        nbytes = header.points * field_dtype.itemsize
        base = field_dtype.base
        values = raw[start : start + nbytes].view(base)
        out[name] = values.reshape((header.points, *field_dtype.shape))
        start += nbytes
    return out


def read_pcd(path: str | os.PathLike[str]) -> PcdCloud:
    """Read a PCD v0.7 file (ascii, binary or binary_compressed) without changing any value.

    The declared sizes are checked against the file size and :mod:`ppe_ros.io.limits` before the
    point data are read or allocated.

    Returns:
        :class:`PcdCloud` whose ``data`` is a structured array of shape ``(HEIGHT, WIDTH)``.

    Raises:
        FileNotFoundError: no such file.
        ScanFileError: malformed header, truncated or corrupt data, sizes beyond the limits (says
            expected vs found).
    """
    file_path = Path(path)
    if not file_path.is_file():
        raise FileNotFoundError(f'PCD file not found: {file_path}')
    with file_path.open('rb') as stream:
        head = stream.read(_MAX_HEADER_BYTES)
    header = parse_pcd_header(head, file_path)
    bytes_per_point = _check_limits(file_path, header)
    try:
        dtype = header.dtype()
    except (ValueError, TypeError) as exc:
        raise _error(file_path, f'PCD header fields cannot be represented: {exc}') from None
    data = _read_body(file_path, header, dtype, bytes_per_point)
    return PcdCloud(header=header, data=data.reshape(header.height, header.width))


# --------------------------------------------------------------------------------------------
# writer
# --------------------------------------------------------------------------------------------

_NUMPY_TO_PCD: dict[str, tuple[str, int]] = {
    'i1': ('I', 1),
    'i2': ('I', 2),
    'i4': ('I', 4),
    'i8': ('I', 8),
    'u1': ('U', 1),
    'u2': ('U', 2),
    'u4': ('U', 4),
    'u8': ('U', 8),
    'f4': ('F', 4),
    'f8': ('F', 8),
}


def _pcd_type(name: str, dtype: np.dtype) -> tuple[str, int]:
    key = f'{dtype.kind}{dtype.itemsize}'
    if key not in _NUMPY_TO_PCD:
        raise ValueError(
            f'field {name!r}: dtype {dtype} cannot be stored in a PCD file '
            f'(use int8..int64, uint8..uint64, float32 or float64)'
        )
    return _NUMPY_TO_PCD[key]


def encode_pcd(
    points: np.ndarray,
    *,
    labels: np.ndarray | None = None,
    extra_fields: Mapping[str, np.ndarray] | None = None,
    binary: bool = True,
    compressed: bool = False,
    viewpoint: tuple[float, ...] | None = None,
) -> bytes:
    """The bytes of the PCD v0.7 file that :func:`save_pcd` writes (same arguments, same checks)."""
    cloud = np.asarray(points)
    if cloud.ndim != 3 or cloud.shape[2] != 3:
        raise ValueError(f'points must be an organized (H, W, 3) array; got shape {cloud.shape}')
    height, width, _ = cloud.shape
    if height < 1 or width < 1:
        raise ValueError(f'points is empty: shape {cloud.shape}')
    if compressed and not binary:
        raise ValueError('compressed=True needs binary=True (there is no compressed ascii PCD)')
    columns: dict[str, np.ndarray] = {
        'x': cloud[..., 0].astype(np.float32),
        'y': cloud[..., 1].astype(np.float32),
        'z': cloud[..., 2].astype(np.float32),
    }
    if labels is not None:
        label_array = np.asarray(labels)
        if label_array.shape != (height, width):
            raise ValueError(f'labels must have shape {(height, width)} like points; got {label_array.shape}')
        if not np.issubdtype(label_array.dtype, np.integer):
            raise ValueError(f'labels must be integers; got dtype {label_array.dtype}')
        if label_array.size and (label_array.min() < 0 or label_array.max() > np.iinfo(np.uint32).max):
            raise ValueError(
                f'labels must lie in 0 .. 2**32-1 to be stored as uint32; '
                f'found {label_array.min()} .. {label_array.max()}'
            )
        columns['label'] = label_array.astype(np.uint32)
    for name, values in (extra_fields or {}).items():
        if name in columns:
            raise ValueError(f'extra field {name!r} duplicates a field that is already written')
        if not name or any(ch.isspace() for ch in name):
            raise ValueError(f'field name {name!r} must be non-empty without white space')
        array = np.asarray(values)
        if array.shape != (height, width):
            raise ValueError(f'extra field {name!r} must have shape {(height, width)}; got {array.shape}')
        _pcd_type(name, array.dtype)
        columns[name] = array
    view = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0) if viewpoint is None else tuple(float(v) for v in viewpoint)
    if len(view) != 7:
        raise ValueError(f'viewpoint must be 7 numbers (tx ty tz qw qx qy qz); got {len(view)}')

    types = [_pcd_type(name, array.dtype) for name, array in columns.items()]
    encoding = 'ascii' if not binary else ('binary_compressed' if compressed else 'binary')
    n_points = height * width
    header = '\n'.join(
        [
            '# .PCD v0.7 - Point Cloud Data file format (written by ppe_ros)',
            'VERSION 0.7',
            'FIELDS ' + ' '.join(columns),
            'SIZE ' + ' '.join(str(size) for _, size in types),
            'TYPE ' + ' '.join(kind for kind, _ in types),
            'COUNT ' + ' '.join('1' for _ in columns),
            f'WIDTH {width}',
            f'HEIGHT {height}',
            'VIEWPOINT ' + ' '.join(f'{v:.9g}' for v in view),
            f'POINTS {n_points}',
            f'DATA {encoding}',
            '',
        ]
    ).encode('ascii')

    record = np.dtype([(name, np.dtype(array.dtype).newbyteorder('<')) for name, array in columns.items()])
    if encoding == 'binary':
        table = np.empty(n_points, dtype=record)
        for name, array in columns.items():
            table[name] = array.reshape(-1)
        body = table.tobytes()
    elif encoding == 'binary_compressed':
        payload = b''.join(
            np.ascontiguousarray(array.reshape(-1), dtype=record[name]).tobytes() for name, array in columns.items()
        )
        block = lzf_compress(payload)
        body = struct.pack('<II', len(block), len(payload)) + block
    else:
        formats = []
        for array in columns.values():
            kind = np.dtype(array.dtype).kind
            formats.append('%d' if kind in 'iu' else ('%.9g' if array.dtype.itemsize == 4 else '%.17g'))
        table = np.column_stack([array.reshape(-1).astype(object) for array in columns.values()])
        lines = [' '.join(fmt % value for fmt, value in zip(formats, row, strict=True)) for row in table]
        body = ('\n'.join(lines) + '\n').encode('ascii')

    return header + body


def save_pcd(
    path: str | os.PathLike[str],
    points: np.ndarray,
    *,
    labels: np.ndarray | None = None,
    extra_fields: Mapping[str, np.ndarray] | None = None,
    binary: bool = True,
    compressed: bool = False,
    viewpoint: tuple[float, ...] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write an organized cloud as a PCD v0.7 file.

    Fields: ``x y z`` float32 (the coordinates as given, normally metres; NaN = no return), then
    ``label`` uint32 if ``labels`` is given, then each of ``extra_fields`` (e.g. ``intensity``) with
    its own dtype, in the given order.

    Args:
        path: output file; an existing file is refused unless ``overwrite=True``. Written to a
            temporary file in the same folder and renamed into place: never left truncated.
        points: ``(H, W, 3)`` organized cloud.
        labels: ``(H, W)`` non-negative integer labels, stored as field ``label`` (uint32).
        extra_fields: name -> ``(H, W)`` array of int, uint or float values.
        binary: ``DATA binary`` (default) or, if False, ``DATA ascii``.
        compressed: ``DATA binary_compressed`` (LZF, field by field); needs ``binary=True``.
        viewpoint: ``(tx, ty, tz, qw, qx, qy, qz)``, default the identity pose.
        overwrite: allow replacing an existing file.

    Returns:
        The path written.

    Raises:
        FileExistsError: the file exists and ``overwrite`` is False.
        ValueError: wrong shapes, labels out of the uint32 range, unsupported dtypes.
    """
    content = encode_pcd(
        points, labels=labels, extra_fields=extra_fields, binary=binary, compressed=compressed, viewpoint=viewpoint
    )
    out_path = Path(path)

    def write(stream) -> None:
        stream.write(content)

    try:
        return write_file_atomically(out_path, write, overwrite=overwrite)
    except FileExistsError:
        raise FileExistsError(f'{out_path} exists; refusing to overwrite it (pass overwrite=True)') from None
