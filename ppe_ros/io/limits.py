"""Size limits of the scan-file readers, checked against a file's declared sizes BEFORE anything is allocated.

A header (PCD ``WIDTH``/``HEIGHT``/``SIZE``/``COUNT``, a ``.npy`` shape, a PNG's width and height) can
declare any size; a few hundred bytes of file must not be able to make a reader allocate gigabytes.
So every reader checks, before it allocates:

* the declared grid against :data:`MAX_SCAN_POINTS` and :data:`MAX_GRID_DIMENSION`;
* the declared data size against the size of the file: uncompressed data must be in the file
  (else "truncated"), compressed data may expand at most by the format's largest possible ratio
  (:data:`LZF_MAX_EXPANSION` for PCD ``binary_compressed``, :data:`DEFLATE_MAX_EXPANSION` for PNG).

Loading a scan of ``N`` points needs about 100 bytes per point at its peak (the raw data, the float64
``(H, W, 3)`` cloud and its cleaned copy), so the largest accepted scan needs about 5 GB.
"""

from __future__ import annotations

import os

from ppe_ros.io.errors import ScanFileError

#: Largest number of points (pixels, rays) of one scan: 50 million (a 10000 x 5000 TLS scan).
MAX_SCAN_POINTS = 50_000_000

#: Largest number of rows or of columns of one organized scan.
MAX_GRID_DIMENSION = 100_000

#: Largest number of values one PCD point may hold (the sum of COUNT; PCL's largest descriptor, SHOT, has 352).
MAX_PCD_VALUES_PER_POINT = 4096

#: An LZF block of n bytes expands to at most 88 n + 264 bytes: the longest back-reference (3 bytes)
#: writes 264 bytes (liblzf's format); a PCD ``binary_compressed`` size prefix claiming more is corrupt.
LZF_MAX_EXPANSION = 88

#: A deflate stream (PNG image data) expands at most about 1032-fold (zlib's documented maximum).
DEFLATE_MAX_EXPANSION = 1032

#: An ascii PCD needs at least 2 bytes per value ("0 "); a value is at most this many characters
#: (%.17g with sign and exponent is 24) -- used to refuse huge text before splitting it.
MAX_ASCII_BYTES_PER_VALUE = 64


def check_grid_size(path: str | os.PathLike[str], rows: int, columns: int, what: str = 'grid') -> None:
    """Refuse a declared grid beyond :data:`MAX_SCAN_POINTS` / :data:`MAX_GRID_DIMENSION` (before allocating).

    Raises:
        ScanFileError: names the file, the declared size and the limit.
    """
    if rows * columns > MAX_SCAN_POINTS:
        raise ScanFileError(
            f'{path}: declares a {rows} x {columns} {what} = {rows * columns} points; at most '
            f'{MAX_SCAN_POINTS} points per scan are supported'
        )
    if max(rows, columns) > MAX_GRID_DIMENSION:
        raise ScanFileError(
            f'{path}: declares a {rows} x {columns} {what}; at most {MAX_GRID_DIMENSION} rows and columns are supported'
        )
