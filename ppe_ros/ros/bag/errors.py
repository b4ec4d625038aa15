"""The error ``process_bag`` reports before writing anything, the exit codes, and read errors as one line."""

from __future__ import annotations

import struct

from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag2 import ReaderError as Ros2ReaderError

EXIT_OK = 0
EXIT_DAMAGED = 1
EXIT_USAGE = 2


class BagError(Exception):
    """A bad command line or an unusable input: reported before any output is written (exit code 2)."""


def describe_read_error(exc: BaseException) -> str:
    """A read error of a storage library as one line."""
    if isinstance(exc, TypeError) and 'ord()' in str(exc):
        return 'the file ends in the middle of a record (truncated)'
    if isinstance(exc, struct.error | EOFError):
        return f'the file ends in the middle of a record (truncated): {exc}'
    text = str(exc).strip() or type(exc).__name__
    return text if isinstance(exc, Ros1ReaderError | Ros2ReaderError) else f'{type(exc).__name__}: {text}'
