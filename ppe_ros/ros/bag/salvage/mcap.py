"""Reading an MCAP file without a usable footer or summary (a killed recorder)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from rosbags.rosbag2 import Reader as Ros2Reader
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.rosbag2.storage_mcap import McapReader, Statistics, read_sized

from ppe_ros.ros.bag.compression import partial_decompress
from ppe_ros.ros.bag.errors import describe_read_error
from ppe_ros.ros.bag.formats import MCAP_MAGIC


class _SalvagedMcapStream:
    """The start of an MCAP file up to ``cut``, followed by ``tail`` (records recovered from a cut chunk).

    Read-only and seekable, like the file object rosbags' MCAP reader uses; a seek never goes past
    the end, so a record that claims to go further is seen as cut.
    """

    def __init__(self, handle: Any, cut: int, tail: bytes) -> None:
        self._handle = handle
        self._cut = cut
        self._tail = tail
        self._size = cut + len(tail)
        self._position = 0

    def tell(self) -> int:
        return self._position

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        base = {os.SEEK_SET: 0, os.SEEK_CUR: self._position, os.SEEK_END: self._size}[whence]
        self._position = min(max(base + offset, 0), self._size)
        return self._position

    def read(self, size: int = -1) -> bytes:
        end = self._size if size is None or size < 0 else min(self._size, self._position + size)
        parts = []
        if self._position < self._cut:
            self._handle.seek(self._position)
            parts.append(self._handle.read(min(end, self._cut) - self._position))
        if end > self._cut:
            parts.append(self._tail[max(self._position, self._cut) - self._cut : end - self._cut])
        self._position = end
        return b''.join(parts)

    def close(self) -> None:
        self._handle.close()


def _complete_records(data: bytes) -> bytes:
    """The leading complete MCAP records (opcode, uint64 length, body) of ``data``."""
    position = 0
    while position + 9 <= len(data):
        length = int.from_bytes(data[position + 1 : position + 9], 'little')
        if data[position] == 0 or position + 9 + length > len(data):
            break
        position += 9 + length
    return data[:position]


def _mcap_cut(handle: Any, start: int, size: int) -> tuple[int, bytes]:
    """Where the complete top-level records of an MCAP file end, and the complete records of a cut chunk there.

    A record whose length runs past the end of the file (a killed recorder, or a corrupt length)
    ends the readable part; when it is a chunk, the records inside it that are complete before
    the end are recovered (uncompressed or zstd / lz4 chunks).
    """
    position = start
    while position + 9 <= size:
        handle.seek(position)
        head = handle.read(9)
        length = int.from_bytes(head[1:9], 'little')
        if position + 9 + length <= size:
            position += 9 + length
            continue
        if head[0] == 0x06:  # a chunk cut short: start, end, uncompressed size, crc, compression, data
            body = handle.read(size - position - 9)
            if len(body) >= 32:
                name_length = int.from_bytes(body[28:32], 'little')
                data_start = 32 + name_length + 8
                if data_start <= len(body):
                    compression = body[32 : 32 + name_length].decode(errors='replace')
                    return position, _complete_records(partial_decompress(body[data_start:], compression))
        return position, b''
    return position, b''


class SalvageMcapReader(McapReader):
    """rosbags' MCAP storage reader for a file without a usable footer or summary.

    ``ros2 bag record`` writes the summary and footer when it closes the file: a killed recorder
    leaves an MCAP that the normal reader refuses. This reader scans the records from the start
    (schemas, channels, chunks, messages) and stops at the damage; :attr:`scan_error` says where.
    A chunk cut short gives the records complete in it before the cut.
    """

    scan_error: str | None = None
    #: Whether the message counts are those :meth:`messages` will give (the scan reached the end or the cut).
    counts_exact = True

    def _open(self) -> None:
        bio = self.bio
        assert bio is not None
        if bio.read(8) != MCAP_MAGIC:
            raise Ros2ReaderError('File magic is invalid.')
        if bio.read(1) != b'\x01':
            raise Ros2ReaderError('the header record is missing (the file is cut after its magic)')
        read_sized(bio)  # the header record (profile, library)
        self.data_start = bio.tell()
        size = bio.seek(0, os.SEEK_END)
        cut, tail = _mcap_cut(bio, self.data_start, size)
        self.bio = _SalvagedMcapStream(bio, cut, tail)
        self.data_end = cut + len(tail)
        try:
            self.meta_scan()
        except Exception as exc:  # damage: keep the schemas and channels found before it
            self.scan_error = describe_read_error(exc)
            self.counts_exact = False
            self.statistics = Statistics(0, len(self.schemas), len(self.channels), 0, 0, 0, 2**63 - 1, 0, {})
        if cut < size and self.scan_error is None:
            self.scan_error = f'the record at byte {cut} of {size} is cut short' + (
                ' (a chunk: the records complete in it are read)' if tail else ''
            )
        counts = self.statistics.channel_message_counts
        self.connections = [conn._replace(msgcount=counts.get(conn.id, 0)) for conn in self.connections]
        self.metadata = self.metadata._replace(message_count=self.statistics.message_count)


def salvaged_mcap_reader(path: Path) -> Ros2Reader:
    """rosbags' rosbag2 reader of one MCAP file, its storage a :class:`SalvageMcapReader` (not yet open)."""
    reader = Ros2Reader(path)
    reader.storage = SalvageMcapReader(path)
    return reader


def salvage_scan_error(reader: Any) -> str | None:
    """Where the scan of a reader from :func:`salvaged_mcap_reader` stopped (None: it read to the end)."""
    return getattr(getattr(reader, 'storage', None), 'scan_error', None)


def counts_exact(reader: Any) -> bool:
    """Whether a reader's message counts are what it will give (False only for a salvaged MCAP cut inside its data)."""
    return bool(getattr(getattr(reader, 'storage', reader), 'counts_exact', True))
