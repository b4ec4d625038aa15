"""Exceptions of the scan-file readers."""

from __future__ import annotations


class ScanFileError(ValueError):
    """A scan file cannot be used: unknown format, malformed header, truncated or corrupt data,
    or a cloud that is not organized. The message names the file and what was expected vs found."""
