"""``ros2 run ppe_ros process_bag IN OUT``: a bag of organized clouds in, a bag of planes out.

Offline twin of the live node (:mod:`ppe_ros.ros.node`): every frame goes through the same
:func:`ppe_ros.ros.processing.process_cloud` with the same parameters (the node's params file,
``--params``), using rosbags message classes instead of rclpy (no ROS installation needed).

Input (read with rosbags): a rosbag2 directory (sqlite3 or mcap, compressed or not), a bare
``.mcap`` / ``.db3`` file, or a ROS 1 ``.bag``. Damaged inputs are read as far as they go: a
rosbag2 directory without ``metadata.yaml`` (recorder killed) is read from its storage files, an
MCAP file without footer and a ROS 1 bag without index are scanned record by record (a chunk cut
short gives the records complete in it), a ``.db3`` that SQLite refuses is read page by page
(:class:`SalvageSqliteReader`), and a cut or corrupt ``.zstd`` storage file (``compression_mode:
file``) is decompressed up to the damage.

Output: a rosbag2 (``--storage mcap`` default, or ``sqlite3``) with, for every input topic, the
node's three outputs at the input message's bag timestamp, each with the input's header:

* ``<ns>/planes/labeled_points`` (``sensor_msgs/msg/PointCloud2``: x y z label rgb),
* ``<ns>/planes/markers`` (``visualization_msgs/msg/MarkerArray``),
* ``<ns>/planes`` (``sensor_msgs/msg/PointCloud2``, one point per plane),

where ``<ns>`` is the input topic without its last element, as for the node, which subscribes to
``points`` and publishes ``planes/...`` in its namespace: ``/ouster/points`` gives
``/ouster/planes/labeled_points`` and so on. Input topics that would share outputs (``/ns/a`` and
``/ns/b``), or an output that would coincide with a copied input topic, use
``<input topic>/planes/...`` instead. ``publish_*: false`` in the params file leaves that output
out. ``--copy-input`` also copies the input topics (ROS 1 messages converted to ROS 2).

Safety: the input is only read. The output is written to a hidden staging directory next to OUT
and renamed to OUT when complete; an existing OUT is replaced only with ``--force``. A message that
does not decode or a frame the extractor cannot use is skipped, logged and counted. A read error in
the middle of the input, a dying worker or Ctrl-C (SIGINT/SIGTERM: the frames in flight are
finished first; a second Ctrl-C drops them) still closes the output as a valid bag holding every
frame processed before it.

Exit codes: 0 done; 1 the input is damaged or processing stopped on an error (OUT holds the frames
before it); 2 bad command line or input (no output written); 128 + signal number when interrupted.
"""

from __future__ import annotations

import argparse
import contextlib
import heapq
import json
import math
import os
import shutil
import signal
import struct
import sys
import tempfile
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import CancelledError, Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any

from rosbags.rosbag1 import Reader as Ros1Reader
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag1.reader import Header as Ros1Header
from rosbags.rosbag1.reader import RecordType as Ros1RecordType
from rosbags.rosbag1.reader import decompressors as ros1_decompressors
from rosbags.rosbag1.reader import normalize as normalize_ros1_topic
from rosbags.rosbag1.reader import read_bytes as ros1_read_bytes
from rosbags.rosbag1.reader import read_uint32 as ros1_read_uint32
from rosbags.rosbag2 import Reader as Ros2Reader
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.rosbag2 import StoragePlugin, Writer, WriterError
from rosbags.rosbag2.storage_mcap import McapReader, Statistics, read_sized
from rosbags.typesys.msg import normalize_msgtype

from ppe_ros.ros.messages import MessageTypes, rosbags_message_types
from ppe_ros.ros.processing import (
    PARAM_SPEC_BY_NAME,
    ROS_BUILTIN_PARAMETERS,
    ExtractorParams,
    FrameSkipped,
    OutputSelection,
    process_cloud,
)

POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
MARKER_ARRAY = 'visualization_msgs/msg/MarkerArray'

#: Output kinds in writing order: topic suffix (relative to the namespace) and message type.
OUTPUT_SUFFIXES: dict[str, str] = {
    'labeled_points': 'planes/labeled_points',
    'markers': 'planes/markers',
    'plane_table': 'planes',
}
OUTPUT_MSGTYPES: dict[str, str] = {
    'labeled_points': POINTCLOUD2,
    'markers': MARKER_ARRAY,
    'plane_table': POINTCLOUD2,
}
STORAGES: dict[str, StoragePlugin] = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
DEFAULT_STORAGE = 'mcap'
#: rosbag2 format version of the output (Jazzy's).
OUTPUT_BAG_VERSION = 9
#: Frames in flight per worker process (bounds memory: each holds an input and its outputs).
IN_FLIGHT_PER_JOB = 2
#: Skip reasons logged per input topic and kind before the rest are only counted.
SKIP_LOG_LIMIT = 5
#: How often (s) the main process checks for a second Ctrl-C while waiting for a worker.
POLL_S = 0.1
#: Key of the output bag's metadata custom_data entry describing the run.
CUSTOM_DATA_KEY = 'ppe_ros.process_bag'

EXIT_OK = 0
EXIT_DAMAGED = 1
EXIT_USAGE = 2

MCAP_MAGIC = b'\x89MCAP0\r\n'
SQLITE_MAGIC = b'SQLite format 3\x00'
ROS1_MAGIC = b'#ROSBAG V'
ZSTD_MAGIC = b'\x28\xb5\x2f\xfd'


class BagError(Exception):
    """A bad command line or an unusable input: reported before any output is written (exit code 2)."""


# --------------------------------------------------------------------------------------------
# output topics
# --------------------------------------------------------------------------------------------


def output_topics(input_topics: Sequence[str], *, kinds: Sequence[str] = tuple(OUTPUT_SUFFIXES),
                  reserved: Sequence[str] = ()) -> dict[str, dict[str, str]]:
    """Output topic of each output kind for each input topic.

    ``/ns/points`` -> ``/ns/planes/labeled_points``, ``/ns/planes/markers``, ``/ns/planes`` (the
    node's relative names in the input's namespace). An input whose outputs another input would
    also get, or that would coincide with a ``reserved`` topic (a copied input), uses
    ``<input topic>/planes/...`` instead.

    Raises:
        BagError: two outputs still coincide (only with contrived topic names).
    """
    def beside(topic: str) -> dict[str, str]:
        namespace = topic.rsplit('/', 1)[0]
        return {kind: f'{namespace}/{OUTPUT_SUFFIXES[kind]}' for kind in kinds}

    def under(topic: str) -> dict[str, str]:
        return {kind: f'{topic.rstrip("/")}/{OUTPUT_SUFFIXES[kind]}' for kind in kinds}

    names = {topic: beside(topic) for topic in input_topics}
    uses = Counter(name for outputs in names.values() for name in outputs.values())
    taken = set(reserved)
    for topic in input_topics:
        if any(uses[name] > 1 or name in taken for name in names[topic].values()):
            names[topic] = under(topic)
    everything = [name for outputs in names.values() for name in outputs.values()]
    clashes = sorted({name for name in everything if everything.count(name) > 1 or name in taken})
    if clashes:
        raise BagError(f'output topics {clashes} would be written twice; process these input topics separately')
    return names


# --------------------------------------------------------------------------------------------
# input
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class InputTopic:
    """A topic of the input bag: message type and message count (None when unknown)."""

    name: str
    msgtype: str
    count: int | None


class InputBag:
    """An open input bag: its topics and a stream of raw messages in time order.

    Attributes:
        path: the input path.
        description: what it is, e.g. ``'rosbag2 (mcap)'`` or ``'ROS 1 bag'``.
        encoding: ``'cdr'`` (rosbag2) or ``'ros1'``.
        topics: topic name -> :class:`InputTopic`.
        notes: remarks about how a damaged input is read.
        damage: known damage (a salvaged file) to report even if the stream ends without an error.
    """

    def __init__(self, path: Path, description: str, encoding: str, readers: Sequence[Any],
                 stack: contextlib.ExitStack, *, notes: Sequence[str] = (), damage: str | None = None,
                 counts_known: bool = True) -> None:
        self.path = path
        self.description = description
        self.encoding = encoding
        self.notes = list(notes)
        self.damage = damage
        self._readers = list(readers)
        self._stack = stack
        topics: dict[str, InputTopic] = {}
        for reader in self._readers:
            for conn in reader.connections:
                count = int(conn.msgcount) if counts_known else None
                if conn.topic in topics:
                    known = topics[conn.topic]
                    msgtype = known.msgtype if known.msgtype == conn.msgtype else f'{known.msgtype}|{conn.msgtype}'
                    total = None if known.count is None or count is None else known.count + count
                    topics[conn.topic] = InputTopic(conn.topic, msgtype, total)
                else:
                    topics[conn.topic] = InputTopic(conn.topic, conn.msgtype, count)
        self.topics = dict(sorted(topics.items()))

    def messages(self, topics: Sequence[str]) -> Iterator[tuple[str, int, bytes]]:
        """``(topic, bag timestamp ns, raw message)`` of ``topics`` in time order.

        Raises whatever the storage raises when it meets damage (the caller reports it).
        """
        wanted = set(topics)
        streams = []
        for reader in self._readers:
            connections = [conn for conn in reader.connections if conn.topic in wanted]
            if connections:
                streams.append(reader.messages(connections=connections))
        if not streams:
            return
        stream = streams[0] if len(streams) == 1 else heapq.merge(*streams, key=lambda item: item[1])
        decompress = self.encoding == 'cdr'
        for conn, timestamp, raw in stream:
            if decompress and bytes(raw[:4]) == ZSTD_MAGIC:
                raw = _zstd_message(raw)
            yield conn.topic, int(timestamp), raw

    def close(self) -> None:
        self._stack.close()


def _zstd_message(raw: bytes) -> bytes:
    """A zstd-compressed message (``compression_mode: message``) read without its metadata.yaml, decompressed.

    Storage files read directly (a salvaged bag) do not say that their messages are compressed;
    a CDR message never starts with the zstd magic, so these are told apart. A message that does
    not decompress is returned as it is (it is then skipped as undecodable, with the reason).
    """
    try:
        from compression import zstd  # type: ignore[import-not-found]
    except ImportError:
        from backports import zstd  # type: ignore[no-redef]
    try:
        return zstd.decompress(raw)
    except Exception:
        return raw


def describe_read_error(exc: BaseException) -> str:
    """A read error of a storage library as one line."""
    if isinstance(exc, TypeError) and 'ord()' in str(exc):
        return 'the file ends in the middle of a record (truncated)'
    if isinstance(exc, struct.error | EOFError):
        return f'the file ends in the middle of a record (truncated): {exc}'
    text = str(exc).strip() or type(exc).__name__
    return text if isinstance(exc, Ros1ReaderError | Ros2ReaderError) else f'{type(exc).__name__}: {text}'


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
            parts.append(self._tail[max(self._position, self._cut) - self._cut:end - self._cut])
        self._position = end
        return b''.join(parts)

    def close(self) -> None:
        self._handle.close()


def _partial_decompress(data: bytes, compression: str) -> bytes:
    """As much of a cut chunk's compressed data as decompresses (empty if nothing does).

    ``compression``: an MCAP chunk's ('', 'zstd', 'lz4') or a ROS 1 chunk's ('none', 'bz2', 'lz4').
    """
    try:
        if compression in ('', 'none'):
            return data
        if compression == 'zstd':
            try:
                from compression import zstd  # type: ignore[import-not-found]
            except ImportError:
                from backports import zstd  # type: ignore[no-redef]
            return zstd.ZstdDecompressor().decompress(data)
        if compression == 'bz2':
            import bz2

            return bz2.BZ2Decompressor().decompress(data)
        if compression == 'lz4':
            import lz4.frame

            return lz4.frame.LZ4FrameDecompressor().decompress(data)
    except Exception:
        return b''
    return b''


def _complete_records(data: bytes) -> bytes:
    """The leading complete MCAP records (opcode, uint64 length, body) of ``data``."""
    position = 0
    while position + 9 <= len(data):
        length = int.from_bytes(data[position + 1:position + 9], 'little')
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
                    compression = body[32:32 + name_length].decode(errors='replace')
                    return position, _complete_records(_partial_decompress(body[data_start:], compression))
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
            self.scan_error = (f'the record at byte {cut} of {size} is cut short'
                               + (' (a chunk: the records complete in it are read)' if tail else ''))
        counts = self.statistics.channel_message_counts
        self.connections = [conn._replace(msgcount=counts.get(conn.id, 0)) for conn in self.connections]
        self.metadata = self.metadata._replace(message_count=self.statistics.message_count)


@dataclass(frozen=True)
class _SalvagedConnection:
    id: int
    topic: str
    msgtype: str
    msgcount: int


class SalvageRos1Reader:
    """A ROS 1 bag without a usable index (``rosbag record`` killed: a ``.bag.active`` file).

    The chunks are read in file order (connection and message records, compressed or not) up to
    the damage, which :attr:`scan_error` describes. Same interface as the rosbags readers used by
    :class:`InputBag`: ``connections`` and ``messages(connections=...)``.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.connections: list[_SalvagedConnection] = []
        self.scan_error: str | None = None
        self._bio: Any = None
        self._data_start = 0

    def open(self) -> None:
        self._bio = self.path.open('rb')
        bio = self._bio
        magic = bio.readline()
        if magic != b'#ROSBAG V2.0\n':
            raise Ros1ReaderError(f'not a ROS 1 bag of version 2.0 (starts with {magic[:16]!r})')
        Ros1Header.read(bio, Ros1RecordType.BAGHEADER)
        bio.seek(ros1_read_uint32(bio), os.SEEK_CUR)  # the bag header's padding
        self._data_start = bio.tell()
        topics: dict[int, tuple[str, str]] = {}
        counts: Counter[int] = Counter()
        try:
            for kind, conn_id, payload in self._records():
                if kind == 'connection':
                    topics.setdefault(conn_id, payload)
                else:
                    counts[conn_id] += 1
        except Exception as exc:
            self.scan_error = describe_read_error(exc)
        self.connections = [_SalvagedConnection(conn_id, topic, msgtype, counts[conn_id])
                            for conn_id, (topic, msgtype) in sorted(topics.items())]

    def close(self) -> None:
        if self._bio is not None:
            self._bio.close()
            self._bio = None

    def messages(self, connections: Sequence[_SalvagedConnection]) -> Iterator[tuple[_SalvagedConnection, int, bytes]]:
        wanted = {conn.id: conn for conn in connections}
        for kind, conn_id, payload in self._records():
            if kind == 'message' and conn_id in wanted:
                timestamp, data = payload
                yield wanted[conn_id], timestamp, data

    def _records(self) -> Iterator[tuple[str, int, Any]]:
        bio = self._bio
        end = bio.seek(0, os.SEEK_END)
        bio.seek(self._data_start)
        while bio.tell() < end:
            start = bio.tell()
            header = Ros1Header.read(bio)
            size = ros1_read_uint32(bio)
            if header.get_uint8('op') == Ros1RecordType.CHUNK:
                compression = header.get_string('compression')
                if compression not in ros1_decompressors:
                    raise Ros1ReaderError(f'Compression {compression!r} is not supported.')
                data = bio.read(size)
                if len(data) < size:  # a chunk cut short: the records complete in it
                    yield from self._chunk_records(_partial_decompress(data, compression), partial=True)
                    raise Ros1ReaderError(f'the chunk at byte {start} is cut short ({len(data)} of {size} bytes); '
                                          'the records complete in it are read')
                yield from self._chunk_records(ros1_decompressors[compression](data), partial=False)
            else:
                yield from self._record(header, ros1_read_bytes(bio, size))

    def _chunk_records(self, chunk: bytes, *, partial: bool) -> Iterator[tuple[str, int, Any]]:
        inner = BytesIO(chunk)
        while inner.tell() < len(chunk):
            try:
                inner_header = Ros1Header.read(inner)
                data = ros1_read_bytes(inner, ros1_read_uint32(inner))
            except Ros1ReaderError:
                if partial:
                    return
                raise
            yield from self._record(inner_header, data)

    @staticmethod
    def _record(header: Any, data: bytes) -> Iterator[tuple[str, int, Any]]:
        op = header.get_uint8('op')
        if op == Ros1RecordType.CONNECTION:
            info = Ros1Header.read(BytesIO(struct.pack('<I', len(data)) + data))
            yield ('connection', header.get_uint32('conn'),
                   (normalize_ros1_topic(header.get_string('topic')), normalize_msgtype(info.get_string('type'))))
        elif op == Ros1RecordType.MSGDATA:
            yield 'message', header.get_uint32('conn'), (header.get_time('time'), data)


class _SqliteFile:
    """Read-only access to the b-tree pages of an SQLite 3 file, every read bounds-checked.

    Only what a rosbag2 ``.db3`` needs: table b-tree pages (leaf and interior), records and
    overflow chains (https://www.sqlite.org/fileformat2.html). Pages past the end of a cut file
    do not exist; a damaged page raises ValueError.
    """

    def __init__(self, handle: Any, size: int) -> None:
        self._handle = handle
        header = self.read(0, 100)
        if len(header) < 100 or not header.startswith(SQLITE_MAGIC):
            raise ValueError('the 100-byte database header is incomplete')
        page_size = int.from_bytes(header[16:18], 'big')
        self.page_size = 65536 if page_size == 1 else page_size
        if self.page_size < 512 or self.page_size & (self.page_size - 1):
            raise ValueError(f'the header gives an invalid page size {page_size}')
        self.usable = self.page_size - header[20]
        if self.usable < 480:
            raise ValueError(f'the header gives an invalid reserved space {header[20]}')
        if int.from_bytes(header[56:60], 'big') not in (0, 1):
            raise ValueError('the database text encoding is not UTF-8')
        self.page_count = size // self.page_size  # complete pages only

    def read(self, offset: int, size: int) -> bytes:
        self._handle.seek(offset)
        return self._handle.read(size)

    def page(self, number: int) -> bytes:
        if not 1 <= number <= self.page_count:
            raise ValueError(f'page {number} is beyond the end of the file ({self.page_count} complete pages)')
        return self.read((number - 1) * self.page_size, self.page_size)

    @staticmethod
    def varint(data: bytes, offset: int) -> tuple[int, int]:
        value = 0
        for i in range(9):
            byte = data[offset + i]
            if i == 8:
                return (value << 8) | byte, offset + 9
            value = (value << 7) | (byte & 0x7F)
            if byte < 0x80:
                return value, offset + i + 1
        raise AssertionError('unreachable')

    def cells(self, number: int, data: bytes) -> tuple[int, list[int], int]:
        """Page type, cell offsets and (interior pages) the right-most child of a b-tree page."""
        start = 100 if number == 1 else 0
        kind = data[start]
        if kind not in (0x02, 0x05, 0x0A, 0x0D):
            return kind, [], 0
        count = int.from_bytes(data[start + 3:start + 5], 'big')
        interior = kind in (0x02, 0x05)
        array = start + (12 if interior else 8)
        if array + 2 * count > self.usable:
            raise ValueError(f'page {number} claims {count} cells, more than fit')
        offsets = [int.from_bytes(data[array + 2 * i:array + 2 * i + 2], 'big') for i in range(count)]
        if any(not array + 2 * count <= offset < self.usable for offset in offsets):
            raise ValueError(f'page {number} has a cell pointer outside the page')
        right = int.from_bytes(data[start + 8:start + 12], 'big') if interior else 0
        return kind, offsets, right

    def leaf_cell(self, data: bytes, offset: int) -> tuple[int, int, bytes, int]:
        """A table leaf cell: rowid, payload size, local payload, first overflow page (0: none)."""
        payload_size, offset = self.varint(data, offset)
        rowid, offset = self.varint(data, offset)
        usable = self.usable
        most = usable - 35
        if payload_size <= most:
            local, overflow = payload_size, 0
        else:
            least = (usable - 12) * 32 // 255 - 23
            local = least + (payload_size - least) % (usable - 4)
            if local > most:
                local = least
            if offset + local + 4 > usable:
                raise ValueError('a cell runs past the end of its page')
            overflow = int.from_bytes(data[offset + local:offset + local + 4], 'big')
        if offset + local > usable:
            raise ValueError('a cell runs past the end of its page')
        return rowid, payload_size, data[offset:offset + local], overflow

    def overflow_pages(self, first: int, missing: int) -> list[int]:
        """The overflow chain from ``first`` holding ``missing`` more payload bytes (ValueError if broken)."""
        pages: list[int] = []
        seen: set[int] = set()
        number = first
        while missing > 0:
            if number in seen or not 2 <= number <= self.page_count:
                raise ValueError(f'overflow page {number} is missing (cut or corrupt file)')
            seen.add(number)
            pages.append(number)
            missing -= self.usable - 4
            number = int.from_bytes(self.read((number - 1) * self.page_size, 4), 'big')
        return pages

    def payload(self, local: bytes, size: int, pages: Sequence[int]) -> bytes:
        parts = [local]
        missing = size - len(local)
        for number in pages:
            chunk = self.read((number - 1) * self.page_size + 4, min(self.usable - 4, missing))
            parts.append(chunk)
            missing -= len(chunk)
        if missing:
            raise ValueError('an overflow page is cut short')
        return b''.join(parts)

    @classmethod
    def record(cls, payload: bytes) -> list[Any]:
        """The values of a record (NULL, int, float, bytes for BLOB and TEXT); ValueError if malformed."""
        header_size, offset = cls.varint(payload, 0)
        if not offset <= header_size <= len(payload):
            raise ValueError('a record header is malformed')
        types = []
        while offset < header_size:
            serial, offset = cls.varint(payload, offset)
            types.append(serial)
        values: list[Any] = []
        position = header_size
        for serial in types:
            if serial in (0, 8, 9):
                values.append(None if serial == 0 else serial - 8)
                continue
            if serial in (10, 11):
                raise ValueError('a record has a reserved serial type')
            size = (0, 1, 2, 3, 4, 6, 8, 8)[serial] if serial < 8 else (serial - 12 - (serial & 1)) // 2
            if position + size > len(payload):
                raise ValueError('a record is longer than its payload')
            raw = payload[position:position + size]
            position += size
            if serial == 7:
                values.append(struct.unpack('>d', raw)[0])
            elif serial < 7:
                values.append(int.from_bytes(raw, 'big', signed=True))
            else:
                values.append(raw)  # BLOB or TEXT (UTF-8)
        return values

    def table_rows(self, root: int) -> Iterator[tuple[int, list[Any]]]:
        """(rowid, values) of a table b-tree from its root page, skipping what is missing or damaged."""
        stack, seen = [root], set()
        while stack:
            number = stack.pop()
            if number in seen or len(seen) > self.page_count:
                continue
            seen.add(number)
            try:
                data = self.page(number)
                kind, offsets, right = self.cells(number, data)
            except ValueError:
                continue
            if kind == 0x05:
                children = [int.from_bytes(data[o:o + 4], 'big') for o in offsets] + [right]
                stack.extend(reversed(children))
            elif kind == 0x0D:
                for offset in offsets:
                    with contextlib.suppress(ValueError, IndexError):
                        rowid, size, local, first = self.leaf_cell(data, offset)
                        yield rowid, self.record(self.payload(local, size, self.overflow_pages(
                            first, size - len(local)) if first else []))


class SalvageSqliteReader:
    """A rosbag2 ``.db3`` that SQLite refuses (cut by a killed recorder, or corrupt): read page by page.

    The topics come from the ``topics`` table, the messages from every complete leaf page of the
    ``messages`` table found in the file, whole messages only (their overflow pages all present),
    in time order. What is lost: pages past the cut, and messages whose own pages are missing or
    damaged. SQLite keeps no checksums: a changed byte inside a message's data is not detected.
    Same interface as the rosbags readers used by :class:`InputBag`.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.connections: list[_SalvagedConnection] = []
        self.scan_error: str | None = None
        self.lost = 0
        self._file: _SqliteFile | None = None
        self._handle: Any = None
        self._rows: list[tuple[int, int, int, int, int]] = []  # timestamp, rowid, topic, page, cell offset

    def open(self) -> None:
        self._handle = self.path.open('rb')
        try:
            self._file = database = _SqliteFile(self._handle, self.path.stat().st_size)
            roots = {}
            for _, values in database.table_rows(1):
                if len(values) >= 4 and values[0] == b'table' and isinstance(values[3], int):
                    roots[bytes(values[1]).decode(errors='replace')] = values[3]
            if 'topics' not in roots or 'messages' not in roots:
                raise ValueError('its schema (page 1) does not list the topics and messages tables')
            topics = {}
            for rowid, values in database.table_rows(roots['topics']):
                if len(values) >= 4 and isinstance(values[1], bytes) and isinstance(values[2], bytes):
                    if values[3] == b'cdr':
                        topics[rowid] = (values[1].decode(errors='replace'), values[2].decode(errors='replace'))
            if not topics:
                raise ValueError('its topics table is missing or damaged')
        except (ValueError, IndexError, OSError) as exc:
            self.close()
            raise Ros2ReaderError(f'{self.path.name} is damaged: {exc}') from None
        try:
            self._scan(set(topics), skip={1, roots['topics']})
        except OSError as exc:
            self.close()
            raise Ros2ReaderError(f'cannot read {self.path.name}: {exc.strerror or exc}') from None
        counts = Counter(topic for _, _, topic, _, _ in self._rows)
        self.connections = [_SalvagedConnection(topic_id, name, msgtype, counts[topic_id])
                            for topic_id, (name, msgtype) in sorted(topics.items())]

    def _scan(self, topics: set[int], skip: set[int]) -> None:
        """Index the complete messages of every leaf page of the file (no payloads kept)."""
        database = self._file
        assert database is not None
        rows: dict[int, tuple[int, int, int, int, int]] = {}
        damaged_pages = 0
        for number in range(2, database.page_count + 1):
            if number in skip:
                continue
            data = database.page(number)
            try:
                kind, offsets, _ = database.cells(number, data)
            except ValueError:
                damaged_pages += 1
                continue
            if kind != 0x0D:
                continue
            for offset in offsets:
                try:
                    rowid, size, local, first = database.leaf_cell(data, offset)
                    header = self._message_header(local)
                    if header is None:
                        continue
                    topic_id, timestamp = header
                    if first:  # a whole message only: every overflow page present
                        database.overflow_pages(first, size - len(local))
                    elif len(database.record(local)) != 4:
                        continue
                except (ValueError, IndexError):
                    self.lost += 1
                    continue
                if topic_id in topics and rowid not in rows:
                    rows[rowid] = (timestamp, rowid, topic_id, number, offset)
        self._rows = sorted(rows.values())
        problems = []
        if self.lost:
            problems.append(f'{self.lost} message{"s" * (self.lost != 1)} lost (pages missing or damaged)')
        if damaged_pages:
            problems.append(f'{damaged_pages} damaged page{"s" * (damaged_pages != 1)} skipped')
        self.scan_error = '; '.join(problems) or None

    @staticmethod
    def _message_header(local: bytes) -> tuple[int, int] | None:
        """(topic_id, timestamp) when a record starts like a messages row (NULL, int, int, blob)."""
        header_size, offset = _SqliteFile.varint(local, 0)
        types = []
        while offset < header_size and len(types) < 5:
            serial, offset = _SqliteFile.varint(local, offset)
            types.append(serial)
        if len(types) != 4 or types[0] != 0 or not all(1 <= t <= 9 and t != 7 for t in types[1:3]):
            return None
        if types[3] < 12 or types[3] & 1:
            return None
        position = header_size
        fields = []
        for serial in types[1:3]:
            size = (0, 1, 2, 3, 4, 6, 8, 8)[serial] if serial < 8 else 0
            raw = local[position:position + size]
            if len(raw) != size:
                raise ValueError('a message row is cut short')
            fields.append(serial - 8 if serial >= 8 else int.from_bytes(raw, 'big', signed=True))
            position += size
        return fields[0], fields[1]

    def describe_damage(self) -> str:
        count = len(self._rows)
        text = f'; read page by page: {count} complete message{"s" * (count != 1)} recovered'
        return text + (f', {self.scan_error}' if self.scan_error else '')

    def close(self) -> None:
        if self._handle is not None:
            self._handle.close()
            self._handle = None

    def messages(self, connections: Sequence[_SalvagedConnection]) -> Iterator[tuple[_SalvagedConnection, int, bytes]]:
        database = self._file
        assert database is not None
        wanted = {conn.id: conn for conn in connections}
        for timestamp, _, topic_id, number, offset in self._rows:
            if topic_id not in wanted:
                continue
            _, size, local, first = database.leaf_cell(database.page(number), offset)
            payload = database.payload(local, size, database.overflow_pages(first, size - len(local)) if first else [])
            values = database.record(payload)
            yield wanted[topic_id], timestamp, values[3]


def _magic(path: Path) -> bytes:
    try:
        with path.open('rb') as handle:
            return handle.read(16)
    except OSError as exc:
        raise BagError(f'cannot read {path}: {exc.strerror or exc}') from None


def open_input_bag(path: str | os.PathLike[str]) -> InputBag:
    """Open a rosbag2 directory, an ``.mcap`` / ``.db3`` file or a ROS 1 bag for reading.

    Raises:
        BagError: no such file, not a bag, or a bag that cannot be opened at all.
    """
    path = Path(path)
    if not path.exists():
        raise BagError(f'no such file or directory: {path}')
    if path.is_file() and path.name == 'metadata.yaml':
        path = path.parent
    stack = contextlib.ExitStack()
    try:
        if path.is_dir():
            return _open_rosbag2_directory(path, stack)
        magic = _magic(path)
        for known, kind in ((ROS1_MAGIC, 'a ROS 1 bag'), (MCAP_MAGIC, 'an MCAP file'),
                            (SQLITE_MAGIC, 'an sqlite3 database')):
            if magic and len(magic) < len(known) and known.startswith(magic):
                raise BagError(f'{path} is damaged: it is cut to {len(magic)} byte{"s" * (len(magic) != 1)}, '
                               f'inside the file signature of {kind}; nothing to read')
        if not magic:
            raise BagError(f'{path} is empty (0 bytes); nothing to read')
        if magic.startswith(ROS1_MAGIC):
            return _open_ros1(path, stack)
        if magic.startswith(MCAP_MAGIC) or magic.startswith(SQLITE_MAGIC):
            expected = '.mcap' if magic.startswith(MCAP_MAGIC) else '.db3'
            if path.suffix != expected:
                raise BagError(f'{path} looks like a rosbag2 {expected} storage file but is named {path.name!r}; '
                               f'rename it to end in {expected}')
            return _open_rosbag2_files([path], path, stack, notes=[])
        raise BagError(
            f'{path} is not a bag: expected a rosbag2 directory (with metadata.yaml), an .mcap or .db3 '
            f'file, or a ROS 1 .bag file (it starts with {magic[:12]!r})'
        )
    except BaseException:
        stack.close()
        raise


def _open_reader(reader: Any, stack: contextlib.ExitStack) -> Any:
    reader.open()
    stack.callback(reader.close)
    return reader


def _open_rosbag2_directory(path: Path, stack: contextlib.ExitStack) -> InputBag:
    files = sorted(path.glob('*.mcap')) or sorted(path.glob('*.db3'))
    compressed = [] if files else sorted(path.glob('*.mcap.zstd')) or sorted(path.glob('*.db3.zstd'))
    if (path / 'metadata.yaml').is_file():
        try:
            reader = _open_reader(Ros2Reader(path), stack)
        except Exception as exc:  # any storage error: a damaged file is read as far as it goes below
            if not files and not compressed:
                raise BagError(f'cannot read rosbag2 {path}: {describe_read_error(exc)}') from None
            if compressed:  # compression_mode: file, a damaged .zstd: decompress what there is
                files, damage = _decompress_as_far_as_possible(compressed, stack)
                return _open_rosbag2_files(files, path, stack, notes=[], damage=damage)
            # a damaged metadata.yaml or storage file: the storage files tell (and an MCAP is salvaged)
            notes = [] if _is_unfinished_mcap(exc) else [
                f'cannot use {path}: {describe_read_error(exc)}; reading its storage files directly']
            return _open_rosbag2_files(files, path, stack, notes=notes)
        storage = 'mcap' if any(f.name.endswith(('.mcap', '.mcap.zstd')) for f in files or compressed) else 'sqlite3'
        return InputBag(path, f'rosbag2 ({storage})', 'cdr', [reader], stack)
    if compressed:
        files, damage = _decompress_as_far_as_possible(compressed, stack)
        note = f'{path} has no metadata.yaml (was the recording interrupted?): reading its storage files directly'
        return _open_rosbag2_files(files, path, stack, notes=[note], damage=damage)
    if not files:
        raise BagError(f'{path} is a directory but not a rosbag2 bag: it has no metadata.yaml and no .mcap or '
                       '.db3 file')
    note = (f'{path} has no metadata.yaml (was the recording interrupted?): reading its storage '
            f'file{"s" if len(files) > 1 else ""} {", ".join(f.name for f in files)} directly')
    return _open_rosbag2_files(files, path, stack, notes=[note])


#: Bytes read from a compressed storage file at a time (small: what decompressed before a corrupt spot is kept).
DECOMPRESS_BLOCK = 1 << 14


def _decompress_as_far_as_possible(files: Sequence[Path], stack: contextlib.ExitStack) -> tuple[list[Path], list[str]]:
    """zstd-compressed storage files (``compression_mode: file``) decompressed up to their damage.

    The decompressed files go to a temporary directory removed when ``stack`` closes. Returns
    them and one line per file whose compressed stream is cut or corrupt.
    """
    try:
        from compression import zstd  # type: ignore[import-not-found]
    except ImportError:
        from backports import zstd  # type: ignore[no-redef]

    folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix='process_bag.')))
    out_files, damage = [], []
    for file in files:
        target = folder / file.name.removesuffix('.zstd')
        decompressor = zstd.ZstdDecompressor()
        problem = None
        frames = 0
        in_frame = False
        try:
            with file.open('rb') as source, target.open('wb') as sink:
                while block := source.read(DECOMPRESS_BLOCK):
                    while block:
                        in_frame = True
                        sink.write(decompressor.decompress(block))
                        if not decompressor.eof:
                            break
                        frames += 1
                        in_frame = False
                        block = decompressor.unused_data  # a next zstd frame
                        decompressor = zstd.ZstdDecompressor()
            if in_frame or not frames:
                problem = 'its zstd stream is cut short'
        except zstd.ZstdError as exc:
            problem = f'its zstd stream is corrupt ({exc})'
        except OSError as exc:
            raise BagError(f'cannot decompress {file}: {exc.strerror or exc}') from None
        if problem:
            size = target.stat().st_size
            damage.append(f'{file.name} is damaged: {problem}; {size} bytes decompressed before the damage')
        out_files.append(target)
    return out_files, damage


def _is_unfinished_mcap(exc: BaseException) -> bool:
    """A reader error of an MCAP file whose footer or summary is missing or damaged."""
    text = str(exc)
    return any(words in text for words in ('end magic', 'MCAP footer', 'summary offset', 'Truncated record'))


def _open_rosbag2_files(files: Sequence[Path], path: Path, stack: contextlib.ExitStack, *,
                        notes: list[str], damage: Sequence[str] = ()) -> InputBag:
    """Storage files read directly (no or unusable metadata.yaml); an unfinished MCAP is salvaged."""
    readers = []
    damage = list(damage)
    storage = 'mcap' if files[0].suffix == '.mcap' else 'sqlite3'
    for file in files:
        reader = None
        try:
            reader = _open_reader(Ros2Reader(file), stack)
        except Exception as exc:
            if file.suffix == '.db3':
                try:
                    reader = _open_reader(SalvageSqliteReader(file), stack)
                except Ros2ReaderError as salvage_error:
                    raise BagError(f'cannot read {file}: {describe_read_error(exc)}; {salvage_error}; '
                                   'nothing readable') from None
                damage.append(f'{file.name} cannot be opened as a database ({describe_read_error(exc)})'
                              f'{reader.describe_damage()}')
            elif file.suffix != '.mcap':
                raise BagError(f'cannot read {file}: {describe_read_error(exc)}') from None
        if reader is None:  # an MCAP without footer: scan it record by record
            reader = Ros2Reader(file)
            reader.storage = SalvageMcapReader(file)
            try:
                _open_reader(reader, stack)
            except Exception as exc:
                if damage:  # a decompressed file: its .zstd is what is damaged
                    raise BagError(f'{path} is damaged ({"; ".join(damage)}); nothing readable') from None
                raise BagError(f'{file} is damaged: {describe_read_error(exc)}; nothing readable') from None
            where = f'; the scan stops at: {reader.storage.scan_error}' if reader.storage.scan_error else ''
            damage.append(f'{file.name} has no usable MCAP footer or summary (the recording was not closed){where}')
        readers.append(reader)
    if damage:
        notes = [*notes, f'{"; ".join(damage)}: reading it record by record up to the damage']
    complete_scans = all(getattr(getattr(reader, 'storage', reader), 'counts_exact', True) for reader in readers)
    return InputBag(path, f'rosbag2 ({storage})', 'cdr', readers, stack, notes=notes,
                    damage='; '.join(damage) or None, counts_known=complete_scans)


def _open_ros1(path: Path, stack: contextlib.ExitStack) -> InputBag:
    try:
        reader = _open_reader(Ros1Reader(path), stack)
        return InputBag(path, 'ROS 1 bag', 'ros1', [reader], stack)
    except Exception as exc:  # any error of a damaged index (e.g. UnicodeDecodeError): scan the chunks
        problem = describe_read_error(exc)
    salvage = SalvageRos1Reader(path)
    try:
        _open_reader(salvage, stack)
    except Exception as exc:
        raise BagError(f'cannot read ROS 1 bag {path} (damaged or cut short before its first record?): {problem}; '
                       f'{describe_read_error(exc)}') from None
    where = f'; the scan stops at: {salvage.scan_error}' if salvage.scan_error else ''
    damage = f'the ROS 1 bag has no usable index ({problem}){where}'
    return InputBag(path, 'ROS 1 bag', 'ros1', [salvage], stack, damage=damage,
                    notes=[f'{damage}: reading its chunks in file order up to the damage'])


def select_topics(bag: InputBag, requested: Sequence[str] | None) -> list[str]:
    """The PointCloud2 topics to process: ``requested`` (checked) or every PointCloud2 topic.

    Raises:
        BagError: a requested topic is not in the bag or is not a PointCloud2; no PointCloud2 topic.
    """
    clouds = [name for name, topic in bag.topics.items() if topic.msgtype == POINTCLOUD2]
    listing = ', '.join(f'{name} ({topic.msgtype})' for name, topic in bag.topics.items()) or 'none'
    if not requested:
        if not clouds and bag.damage:
            raise BagError(f'{bag.path} is damaged before its first complete {POINTCLOUD2} message '
                           f'({bag.damage}); nothing to process')
        if not clouds:
            raise BagError(f'{bag.path} has no {POINTCLOUD2} topic; its topics: {listing}')
        return clouds
    selected: list[str] = []
    for name in requested:
        topic = name if name.startswith('/') else f'/{name}'
        if topic not in bag.topics:
            available = ', '.join(clouds) or f'none (its topics: {listing})'
            raise BagError(f'topic {name!r} is not in {bag.path}; its {POINTCLOUD2} topics: {available}')
        if bag.topics[topic].msgtype != POINTCLOUD2:
            raise BagError(f'topic {topic} has type {bag.topics[topic].msgtype}, not {POINTCLOUD2}')
        if topic not in selected:
            selected.append(topic)
    return selected


# --------------------------------------------------------------------------------------------
# one frame (inline or in a worker process)
# --------------------------------------------------------------------------------------------


@dataclass
class FrameResult:
    """What became of one input message.

    Attributes:
        skip_kind: '' when processed; else a :class:`FrameSkipped` kind, ``'undecodable'`` or
            ``'failed'`` (an unexpected error in processing).
        reason: why it was skipped.
        outputs: output kind -> CDR bytes, in :data:`OUTPUT_SUFFIXES` order.
        copy: the input converted to ROS 2 CDR (ROS 1 input with ``--copy-input``), or None.
        num_planes: planes found.
        seconds: wall time of decoding, processing and serializing (s).
    """

    skip_kind: str = ''
    reason: str = ''
    outputs: dict[str, bytes] = field(default_factory=dict)
    copy: bytes | None = None
    num_planes: int = 0
    seconds: float = 0.0


def ros1_cloud_as_ros2(msg: Any, typestore: Any) -> Any:
    """A ROS 1 ``sensor_msgs/PointCloud2`` (rosbags) as a ROS 2 message of ``typestore`` (no ``seq``)."""
    types = typestore.types
    stamp = types['builtin_interfaces/msg/Time'](sec=int(msg.header.stamp.sec), nanosec=int(msg.header.stamp.nanosec))
    header = types['std_msgs/msg/Header'](stamp=stamp, frame_id=str(msg.header.frame_id))
    field_class = types['sensor_msgs/msg/PointField']
    fields = [field_class(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count) for f in msg.fields]
    return types[POINTCLOUD2](header=header, height=msg.height, width=msg.width, fields=fields,
                              is_bigendian=msg.is_bigendian, point_step=msg.point_step, row_step=msg.row_step,
                              data=msg.data, is_dense=msg.is_dense)


class FrameProcessor:
    """Decodes input messages and runs the node's processing on them (one per process)."""

    def __init__(self, params: ExtractorParams) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.params = params
        self.selection = OutputSelection.from_params(params)
        self.types: MessageTypes = rosbags_message_types(get_typestore(Stores.ROS2_JAZZY))
        self._ros1_typestore: Any = None

    def decode(self, raw: bytes, encoding: str) -> Any:
        """A ``sensor_msgs/msg/PointCloud2`` of the Jazzy typestore from raw CDR or ROS 1 bytes."""
        typestore = self.types.typestore
        if encoding == 'cdr':
            return typestore.deserialize_cdr(raw, POINTCLOUD2)
        if self._ros1_typestore is None:
            from rosbags.typesys import Stores, get_typestore

            self._ros1_typestore = get_typestore(Stores.ROS1_NOETIC)
        return ros1_cloud_as_ros2(self._ros1_typestore.deserialize_ros1(raw, POINTCLOUD2), typestore)

    def process(self, raw: bytes, encoding: str, convert_copy: bool = False) -> FrameResult:
        """Decode, process and serialize one message; failures become a skipped :class:`FrameResult`."""
        start = time.perf_counter()
        typestore = self.types.typestore
        try:
            msg = self.decode(raw, encoding)
        except Exception as exc:
            return FrameResult('undecodable', f'the message does not decode as {POINTCLOUD2}: '
                               f'{type(exc).__name__}: {exc}', seconds=time.perf_counter() - start)
        result = FrameResult()
        try:
            if convert_copy:
                result.copy = bytes(typestore.serialize_cdr(msg, POINTCLOUD2))
            frame = process_cloud(msg, self.params, self.types, outputs=self.selection)
            if frame.labeled_points is not None:
                result.outputs['labeled_points'] = bytes(typestore.serialize_cdr(frame.labeled_points, POINTCLOUD2))
            if frame.markers is not None:
                result.outputs['markers'] = bytes(frame.markers)
            if frame.plane_table is not None:
                result.outputs['plane_table'] = bytes(typestore.serialize_cdr(frame.plane_table, POINTCLOUD2))
            result.num_planes = frame.planes.num_planes
        except FrameSkipped as exc:
            result = FrameResult(exc.kind, exc.reason, copy=result.copy)
        except Exception as exc:  # like the node: one bad frame never stops the run
            if _caused_by_interrupt(exc):  # Ctrl-C inside a numba kernel: a SystemError from it
                raise KeyboardInterrupt from None
            result = FrameResult('failed', f'processing failed: {type(exc).__name__}: {exc}', copy=result.copy)
        result.seconds = time.perf_counter() - start
        return result


def _caused_by_interrupt(exc: BaseException) -> bool:
    """Whether ``exc`` wraps a KeyboardInterrupt (a signal handler that raised inside native code).

    A second Ctrl-C while a numba kernel returns surfaces as ``SystemError: CPUDispatcher(...)
    returned a result with an exception set`` whose cause is the KeyboardInterrupt.
    """
    seen = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt):
            return True
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return False


_WORKER_PROCESSOR: FrameProcessor | None = None


def _set_numba_threads(count: int) -> None:
    if count > 0:
        import numba

        numba.set_num_threads(min(count, numba.config.NUMBA_NUM_THREADS))


def _init_worker(params: ExtractorParams, numba_threads: int) -> None:
    """Worker process start: Ctrl-C is the main process's business; load the parameters once."""
    global _WORKER_PROCESSOR
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _set_numba_threads(numba_threads)
    _WORKER_PROCESSOR = FrameProcessor(params)


def _process_in_worker(raw: bytes, encoding: str, convert_copy: bool) -> FrameResult:
    assert _WORKER_PROCESSOR is not None, 'worker not initialized'
    return _WORKER_PROCESSOR.process(raw, encoding, convert_copy)


class _InlineExecutor:
    """``--jobs 1``: frames are processed in this process, when submitted."""

    def __init__(self, processor: FrameProcessor, stops: _StopRequests) -> None:
        self._processor = processor
        self._stops = stops

    def submit(self, raw: bytes, encoding: str, convert_copy: bool) -> Future:
        future: Future = Future()
        self._stops.abortable = True  # a second Ctrl-C may abandon this frame
        try:
            result = self._processor.process(raw, encoding, convert_copy)
        except KeyboardInterrupt:
            result = None
        finally:
            self._stops.abortable = False
        if result is None or (self._stops.drop and result.skip_kind == 'failed'):
            future.cancel()  # dropped by the second Ctrl-C (a failure it caused is no failure)
        else:
            future.set_result(result)
        return future

    def shutdown(self, *, abandon: bool) -> None:
        pass


class _PoolExecutor:
    """``--jobs N``: frames go to N worker processes (forkserver, or spawn where there is none)."""

    def __init__(self, jobs: int, params: ExtractorParams, numba_threads: int) -> None:
        import multiprocessing

        methods = multiprocessing.get_all_start_methods()
        context = multiprocessing.get_context('forkserver' if 'forkserver' in methods else 'spawn')
        self._pool = ProcessPoolExecutor(max_workers=jobs, mp_context=context, initializer=_init_worker,
                                         initargs=(params, numba_threads))

    def submit(self, raw: bytes, encoding: str, convert_copy: bool) -> Future:
        return self._pool.submit(_process_in_worker, raw, encoding, convert_copy)

    def shutdown(self, *, abandon: bool) -> None:
        if not abandon:
            self._pool.shutdown(wait=True)
            return
        processes = list(getattr(self._pool, '_processes', {}).values())  # the workers this run started
        self._pool.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            with contextlib.suppress(Exception):
                process.terminate()
        for process in processes:
            with contextlib.suppress(Exception):
                process.join(timeout=5)


# --------------------------------------------------------------------------------------------
# Ctrl-C
# --------------------------------------------------------------------------------------------


class _StopRequests:
    """SIGINT / SIGTERM during a run: the first stops reading, a second drops the frames in flight.

    The handlers only count (writing the output is never interrupted halfway); a second signal
    raises KeyboardInterrupt only while an inline frame is being processed (``abortable``).
    """

    def __init__(self) -> None:
        self.count = 0
        self.first_signal: int | None = None
        self.abortable = False
        self._previous: dict[int, Any] = {}

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return  # signals only reach the main thread; elsewhere the caller's handling applies
        for signum in (signal.SIGINT, signal.SIGTERM):
            self._previous[signum] = signal.signal(signum, self._handle)

    def restore(self) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()

    def _handle(self, signum: int, frame: Any) -> None:
        self.count += 1
        if self.first_signal is None:
            self.first_signal = signum
        if self.count > 1 and self.abortable:
            raise KeyboardInterrupt

    @property
    def stop(self) -> bool:
        return self.count > 0

    @property
    def drop(self) -> bool:
        return self.count > 1


# --------------------------------------------------------------------------------------------
# output
# --------------------------------------------------------------------------------------------


class OutputBag:
    """The output rosbag2, written in a staging directory next to OUT and renamed when closed."""

    def __init__(self, final: Path, storage: str, force: bool) -> None:
        self.final = final
        self.storage = storage
        self.force = force
        self.staging = Path(tempfile.mkdtemp(prefix=f'.{final.name}.', suffix='.partial', dir=final.parent))
        self.path = self.staging / final.name
        self.writer = Writer(self.path, version=OUTPUT_BAG_VERSION, storage_plugin=STORAGES[storage])
        self.written = 0
        self._typestore: Any = None
        try:
            self.writer.open()
        except BaseException:
            shutil.rmtree(self.staging, ignore_errors=True)
            raise

    def add_connection(self, topic: str, msgtype: str, typestore: Any) -> Any:
        return self.writer.add_connection(topic, msgtype, typestore=typestore)

    def write(self, connection: Any, timestamp: int, data: bytes) -> None:
        self.writer.write(connection, timestamp, data)
        self.written += 1

    def close(self) -> None:
        """Write the index and metadata.yaml; on failure the staging directory is kept as it is."""
        self.writer.close()

    def publish(self) -> Path:
        """Move the closed bag to OUT (replacing it only with ``force``) and remove the staging directory."""
        old = None
        if self.final.exists() or self.final.is_symlink():
            if not self.force:
                raise FileExistsError(f'{self.final} appeared while processing; the output is left in {self.path}')
            old = self.staging / f'{self.final.name}.replaced'
            os.rename(self.final, old)
        os.rename(self.path, self.final)
        if old is not None:
            if old.is_dir() and not old.is_symlink():
                shutil.rmtree(old)
            else:
                old.unlink()
        self.staging.rmdir()
        return self.final

    def discard(self) -> None:
        shutil.rmtree(self.staging, ignore_errors=True)


def _files_of(path: Path) -> list[Path]:
    """``path`` and, for a directory, the files and directories in it (not deeper: a bag is flat)."""
    if path.is_dir():
        with contextlib.suppress(OSError):
            return [path, *path.iterdir()]
    return [path]


def _shares_a_file(input_path: Path, output_path: Path) -> bool:
    """Whether OUT is (by device and inode: a hard link too) the input, one of its files, or holds one."""
    if not output_path.exists():
        return False
    for source in _files_of(input_path):
        for target in _files_of(output_path):
            with contextlib.suppress(OSError):
                if os.path.samefile(source, target):
                    return True
    return False


def check_paths(input_path: Path, output_path: Path, force: bool) -> None:
    """Refuse outputs that would overwrite the input or an existing path without ``force``.

    Raises:
        BagError: with the reason.
    """
    source = input_path.resolve()
    target = output_path.resolve()
    if (target == source or source.is_relative_to(target) or target.is_relative_to(source)
            or _shares_a_file(input_path, output_path)):
        raise BagError(f'refusing to write {output_path}: it is, contains or lies inside the input {input_path}')
    if output_path.exists() or output_path.is_symlink():
        if not force:
            raise BagError(f'{output_path} exists; use --force to replace it')
    if not target.parent.is_dir():
        raise BagError(f'the directory of the output, {target.parent}, does not exist')
    if not os.access(target.parent, os.W_OK):
        raise BagError(f'cannot write in {target.parent}: permission denied')


# --------------------------------------------------------------------------------------------
# the run
# --------------------------------------------------------------------------------------------


@dataclass
class BagOptions:
    """What to do: the command line as values.

    Attributes:
        input, output: IN and OUT.
        topics: input topics to process; empty = every PointCloud2 topic.
        params: extractor parameters (the node's; see ``ExtractorParams.from_yaml``).
        params_source: where they came from, for the report and the output's metadata.
        copy_input: also copy the input topics.
        jobs: worker processes; 1 = in this process.
        storage: ``'mcap'`` or ``'sqlite3'``.
        force: replace an existing OUT.
        progress: show a progress bar: True, False or None (when stderr is a terminal).
    """

    input: Path
    output: Path
    topics: tuple[str, ...] = ()
    params: ExtractorParams = field(default_factory=ExtractorParams)
    params_source: str = 'defaults'
    copy_input: bool = False
    jobs: int = 1
    storage: str = DEFAULT_STORAGE
    force: bool = False
    progress: bool | None = None
    params_warnings: tuple[str, ...] = ()


@dataclass
class TopicReport:
    """Counts of one input topic."""

    input_topic: str
    outputs: dict[str, str]
    expected: int | None
    read: int = 0
    processed: int = 0
    copied: int = 0
    skipped: Counter[str] = field(default_factory=Counter)
    reasons: dict[str, str] = field(default_factory=dict)
    planes: list[int] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)

    @property
    def skipped_total(self) -> int:
        return sum(self.skipped.values())


@dataclass
class BagReport:
    """What a run did (returned by :func:`process_bag`, printed by :func:`format_report`)."""

    options: BagOptions
    input_description: str = ''
    topics: dict[str, TopicReport] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    messages_written: int = 0
    wall_seconds: float = 0.0
    input_error: str | None = None
    worker_error: str | None = None
    output_error: str | None = None
    interrupted_by: int | None = None
    dropped_in_flight: int = 0
    output_path: Path | None = None

    @property
    def frames_read(self) -> int:
        return sum(t.read for t in self.topics.values())

    @property
    def frames_processed(self) -> int:
        return sum(t.processed for t in self.topics.values())

    @property
    def frames_skipped(self) -> int:
        return sum(t.skipped_total for t in self.topics.values())

    @property
    def frames_per_second(self) -> float:
        done = self.frames_processed + self.frames_skipped
        return done / self.wall_seconds if self.wall_seconds > 0 else 0.0

    @property
    def exit_code(self) -> int:
        if self.interrupted_by is not None:
            return 128 + int(self.interrupted_by)
        if self.input_error or self.worker_error or self.output_error:
            return EXIT_DAMAGED
        return EXIT_OK


def default_numba_threads(params: ExtractorParams, jobs: int) -> int:
    """Threads per worker: the ``numba_threads`` parameter, or (0) the cores shared out among the jobs."""
    if params.numba_threads > 0:
        return params.numba_threads
    if jobs <= 1:
        return 0
    cores = len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else (os.cpu_count() or 1)
    return max(1, cores // jobs)


def _print(text: str, *, file: Any = None) -> None:
    from tqdm import tqdm

    tqdm.write(text, file=file or sys.stdout)


def process_bag(options: BagOptions, *, log: Callable[[str], None] | None = None,
                warn: Callable[[str], None] | None = None) -> BagReport:
    """Turn the PointCloud2 topics of a bag into the extractor's outputs in a new rosbag2.

    Args:
        options: see :class:`BagOptions`.
        log: prints progress information (default: stdout).
        warn: prints skipped frames and problems (default: stderr).

    Returns:
        The report; ``report.exit_code`` is non-zero when the input was damaged, processing stopped
        on an error or the run was interrupted (OUT then holds every frame before that).

    Raises:
        BagError: bad options or an unusable input; nothing was written.
    """
    log = log or _print
    warn = warn or (lambda text: _print(text, file=sys.stderr))
    start = time.perf_counter()
    if options.storage not in STORAGES:
        raise BagError(f'unknown storage {options.storage!r}; choose one of {", ".join(STORAGES)}')
    if options.jobs < 1:
        raise BagError(f'--jobs must be >= 1; got {options.jobs}')
    input_path, output_path = Path(options.input), Path(options.output)
    if not input_path.exists():
        raise BagError(f'no such file or directory: {input_path}')
    check_paths(input_path, output_path, options.force)

    for text in options.params_warnings:
        warn(f'warning: {text}')
    report = BagReport(options)
    bag = open_input_bag(input_path)
    with contextlib.closing(bag):
        report.input_description = bag.description
        report.notes = list(bag.notes)
        selected = select_topics(bag, options.topics)
        selection = OutputSelection.from_params(options.params)
        kinds = [kind for kind in OUTPUT_SUFFIXES if getattr(selection, kind)]
        names = output_topics(selected, kinds=kinds, reserved=selected if options.copy_input else ())
        for topic in selected:
            report.topics[topic] = TopicReport(topic, names[topic], bag.topics[topic].count)
        if bag.damage and all(entry.expected == 0 for entry in report.topics.values()):
            raise BagError(f'{input_path} is damaged before its first complete frame ({bag.damage}); '
                           'nothing to process')
        _log_plan(report, bag, log, warn, requested=bool(options.topics))
        try:
            output = OutputBag(output_path, options.storage, options.force)
        except (OSError, WriterError) as exc:
            raise BagError(f'cannot create the output next to {output_path}: {exc}') from None
        stops = _StopRequests()  # also while the output is closed and moved: never left half-written
        stops.install()
        try:
            _run(bag, output, report, options, warn, stops)
        except (OSError, WriterError) as exc:  # e.g. disk full: keep what was written
            report.output_error = f'writing the output failed: {type(exc).__name__}: {exc}'
        finally:
            try:
                _finish_output(output, report, options)
            finally:
                stops.restore()
                if stops.first_signal is not None:
                    report.interrupted_by = stops.first_signal
    report.wall_seconds = time.perf_counter() - start
    return report


def _log_plan(report: BagReport, bag: InputBag, log: Callable[[str], None], warn: Callable[[str], None], *,
              requested: bool) -> None:
    for note in report.notes:
        warn(f'warning: {note}')
    total = sum(t.count or 0 for t in bag.topics.values())
    known = all(t.count is not None for t in bag.topics.values())
    count = f'{total} messages' if known else 'message count unknown'
    log(f'reading {bag.path}: {bag.description}, {len(bag.topics)} topics, {count}')
    which = 'the requested topics' if requested else f'every {POINTCLOUD2} topic'
    log(f'processing {which}:')
    for topic in report.topics.values():
        expected = '?' if topic.expected is None else topic.expected
        outputs = ', '.join(topic.outputs.values()) or '(no output enabled)'
        log(f'  {topic.input_topic} ({expected} messages) -> {outputs}')


def _run(bag: InputBag, output: OutputBag, report: BagReport, options: BagOptions,
         warn: Callable[[str], None], stops: _StopRequests) -> None:
    """Read, process (inline or in workers) and write in input order until done, damaged or stopped."""
    from rosbags.typesys import Stores, get_typestore
    from tqdm import tqdm

    typestore = get_typestore(Stores.ROS2_JAZZY)
    copy_connections = {}
    if options.copy_input:
        for topic in report.topics:
            copy_connections[topic] = output.add_connection(topic, POINTCLOUD2, typestore)
    connections = {
        topic: {kind: output.add_connection(name, OUTPUT_MSGTYPES[kind], typestore)
                for kind, name in entry.outputs.items()}
        for topic, entry in report.topics.items()
    }
    output.writer.set_custom_data(CUSTOM_DATA_KEY, json.dumps({
        'input': str(options.input),
        'topics': {topic: entry.outputs for topic, entry in report.topics.items()},
        'params': options.params.as_dict(),
        'params_source': options.params_source,
    }, default=str))

    convert_copy = options.copy_input and bag.encoding == 'ros1'
    numba_threads = default_numba_threads(options.params, options.jobs)
    expected = [t.expected for t in report.topics.values()]
    total = None if any(count is None for count in expected) else sum(expected)
    bar = tqdm(total=total, unit='frame', desc='process_bag', file=sys.stderr, dynamic_ncols=True,
               disable=(None if options.progress is None else not options.progress), smoothing=0.1)
    logged: Counter[tuple[str, str]] = Counter()
    pending: deque[tuple[str, int, bytes | None, Future]] = deque()
    executor: _InlineExecutor | _PoolExecutor | None = None
    stream = bag.messages(list(report.topics))
    abandon = False
    try:
        if options.jobs == 1:
            _set_numba_threads(numba_threads)
            executor = _InlineExecutor(FrameProcessor(options.params), stops)
        else:
            executor = _PoolExecutor(options.jobs, options.params, numba_threads)
        reading = True
        announced = False
        while True:
            while reading and len(pending) < IN_FLIGHT_PER_JOB * options.jobs and not stops.stop:
                try:
                    topic, timestamp, raw = next(stream)
                except StopIteration:
                    reading = False
                    break
                except Exception as exc:  # damage in the input: keep what was read before it
                    read = report.frames_read
                    report.input_error = (f'{bag.path} is damaged after {read} frame{"s" * (read != 1)}: '
                                          f'{describe_read_error(exc)}')
                    reading = False
                    break
                report.topics[topic].read += 1
                raw = bytes(raw)
                future = executor.submit(raw, bag.encoding, convert_copy)
                pending.append((topic, timestamp, raw if options.copy_input and not convert_copy else None, future))
            if stops.stop and not announced:
                announced = True
                reading = False
                busy = sum(1 for *_, future in pending if not future.done())
                extra = (f'finishing the {busy} frame{"s" * (busy != 1)} in flight, ' if busy else '')
                warn(f'interrupted: {extra}closing {options.output} with the frames done so far '
                     f'({"press Ctrl-C again to drop the frames in flight" if busy else "please wait"})')
            if not pending:
                break
            topic, timestamp, raw, future = pending[0]
            result = _wait(future, stops, report)
            if result is None:
                abandon = True
                break
            pending.popleft()
            _write_frame(output, report, topic, timestamp, raw, result, copy_connections, connections[topic])
            if result.skip_kind:
                logged[(topic, result.skip_kind)] += 1
                shown = logged[(topic, result.skip_kind)]
                if shown <= SKIP_LOG_LIMIT:
                    more = ' (further ones of this kind are only counted)' if shown == SKIP_LOG_LIMIT else ''
                    warn(f'skipped a frame of {topic} at t = {timestamp} ns ({result.skip_kind}): '
                         f'{result.reason}{more}')
            bar.update(1)
            if report.frames_skipped:
                bar.set_postfix(skipped=report.frames_skipped, refresh=False)
        if bag.damage and not report.input_error and not stops.stop and not abandon:
            read = report.frames_read
            report.input_error = f'{bag.path} is damaged ({bag.damage}); {read} frame{"s" * (read != 1)} read'
    finally:
        stream.close()
        report.dropped_in_flight = len(pending)
        if executor is not None:
            executor.shutdown(abandon=abandon or bool(pending))
        bar.close()


def _wait(future: Future, stops: _StopRequests, report: BagReport) -> FrameResult | None:
    """The frame's result; None when dropped (second Ctrl-C) or when the worker died."""
    while True:
        try:
            return future.result(timeout=POLL_S)
        except TimeoutError:
            if stops.drop:
                return None
        except CancelledError:
            return None
        except BrokenProcessPool as exc:
            report.worker_error = (f'a worker process died ({exc}); was it killed, e.g. for lack of memory? '
                                   'Try fewer --jobs')
            return None


def _write_frame(output: OutputBag, report: BagReport, topic: str, timestamp: int, raw: bytes | None,
                 result: FrameResult, copy_connections: dict[str, Any], connections: dict[str, Any]) -> None:
    entry = report.topics[topic]
    copy = raw if raw is not None else result.copy
    if topic in copy_connections and copy is not None:
        output.write(copy_connections[topic], timestamp, copy)
        entry.copied += 1
    if result.skip_kind:
        entry.skipped[result.skip_kind] += 1
        entry.reasons.setdefault(result.skip_kind, result.reason)
        return
    for kind, connection in connections.items():
        output.write(connection, timestamp, result.outputs[kind])
    entry.processed += 1
    entry.planes.append(result.num_planes)
    entry.seconds.append(result.seconds)


def _finish_output(output: OutputBag, report: BagReport, options: BagOptions) -> None:
    """Close the output and move it to OUT; on failure say where the partial files are."""
    report.messages_written = output.written
    problems = [report.output_error] if report.output_error else []
    try:
        output.close()
    except Exception as exc:
        problems.append(f'could not finish the output bag: {type(exc).__name__}: {exc}; the partial files are in '
                        f'{output.staging}')
    else:
        try:
            report.output_path = output.publish()
        except OSError as exc:
            problems.append(f'could not move the output to {options.output}: {exc}')
    report.output_error = '; '.join(problems) or None


# --------------------------------------------------------------------------------------------
# report
# --------------------------------------------------------------------------------------------


def _mean(values: Sequence[float]) -> float:
    return math.fsum(values) / len(values) if values else math.nan


def format_report(report: BagReport) -> str:
    """The summary: a markdown table per input topic, skip reasons, and the outcome."""
    lines = [
        '| input topic | frames | processed | skipped | planes/frame mean (min-max) | s/frame mean (max) |',
        '|---|---:|---:|---:|---|---|',
    ]
    for entry in report.topics.values():
        if entry.planes:
            planes = f'{_mean(entry.planes):.1f} ({min(entry.planes)}-{max(entry.planes)})'
            seconds = f'{_mean(entry.seconds):.3f} ({max(entry.seconds):.3f})'
        else:
            planes = seconds = '-'
        lines.append(f'| {entry.input_topic} | {entry.read} | {entry.processed} | {entry.skipped_total} | '
                     f'{planes} | {seconds} |')
    for entry in report.topics.values():
        for kind, count in entry.skipped.most_common():
            lines.append(f'skipped on {entry.input_topic}: {count} x {kind}, e.g. {entry.reasons[kind]}')
    done = report.frames_processed + report.frames_skipped
    jobs = report.options.jobs
    rate = f'{report.frames_per_second:.2f} frames/s with {jobs} job{"s" * (jobs != 1)}'
    if report.output_path is not None:
        lines.append(f'wrote {report.output_path} ({report.options.storage}): {report.messages_written} messages; '
                     f'{done} frames in {report.wall_seconds:.1f} s ({rate})')
    return '\n'.join(lines)


def report_problems(report: BagReport) -> list[str]:
    """One line per reason the run did not complete normally."""
    problems = []
    if report.interrupted_by is not None:
        name = signal.Signals(report.interrupted_by).name
        dropped = (f'; {report.dropped_in_flight} frame{"s" * (report.dropped_in_flight != 1)} in flight dropped'
                   if report.dropped_in_flight else '')
        problems.append(f'interrupted ({name}) after {report.frames_read} frames{dropped}')
    for problem in (report.input_error, report.worker_error, report.output_error):
        if problem:
            problems.append(problem)
    return problems


# --------------------------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------------------------


def _jobs(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'not an integer: {text!r}') from None
    if value < 0:
        raise argparse.ArgumentTypeError(f'must be >= 0 (0 = one per CPU core): {text!r}')
    if value == 0:
        value = len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else (os.cpu_count() or 1)
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``process_bag`` and ``ppe bag``."""
    parser.add_argument('input', metavar='IN',
                        help='input bag: rosbag2 directory (mcap or sqlite3), .mcap or .db3 file, or ROS 1 .bag')
    parser.add_argument('output', metavar='OUT', help='output rosbag2 directory (must not exist unless --force)')
    parser.add_argument('-t', '--topic', dest='topics', action='extend', nargs='+', metavar='T', default=[],
                        help='PointCloud2 topic(s) to process (default: every PointCloud2 topic)')
    parser.add_argument('--params', metavar='FILE.yaml', default=None,
                        help="the extractor node's parameter file (section 'extractor' or '/**'), e.g. "
                             'config/extractor.yaml; default: the node defaults')
    parser.add_argument('--copy-input', action='store_true', help='also copy the input topics into OUT')
    parser.add_argument('-j', '--jobs', type=_jobs, default=1, metavar='N',
                        help='worker processes (default 1; 0 = one per CPU core); output order is kept')
    parser.add_argument('--storage', choices=tuple(STORAGES), default=DEFAULT_STORAGE,
                        help=f'storage of OUT (default {DEFAULT_STORAGE})')
    parser.add_argument('--force', action='store_true', help='replace an existing OUT (never the input)')
    parser.add_argument('--progress', dest='progress', action='store_true', default=None,
                        help='always show the progress bar (default: when stderr is a terminal)')
    parser.add_argument('--no-progress', dest='progress', action='store_false', help='never show the progress bar')


def build_parser(prog: str = 'process_bag') -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog,
        description='Extract planes from every organized PointCloud2 of a bag, as the extractor node would, '
        'and write its outputs (labelled cloud, markers, plane table) to a new rosbag2.',
        epilog=f'Outputs of /ns/points: /ns/{OUTPUT_SUFFIXES["labeled_points"]}, /ns/{OUTPUT_SUFFIXES["markers"]}, '
        f'/ns/{OUTPUT_SUFFIXES["plane_table"]}. Exit codes: 0 done, 1 damaged input or stopped on an error '
        '(OUT holds the frames before it), 2 bad arguments or unusable input, 130 (143) interrupted by Ctrl-C '
        '(SIGTERM).',
    )
    add_arguments(parser)
    return parser


def options_from_args(args: argparse.Namespace) -> BagOptions:
    """:class:`BagOptions` from parsed arguments (reads the params file).

    Raises:
        BagError: unreadable or invalid params file.
    """
    params = ExtractorParams()
    source = 'defaults'
    warnings: list[str] = []
    if args.params is not None:
        try:
            params, unknown = read_params_file(args.params)
        except ValueError as exc:
            raise BagError(str(exc)) from None
        source = str(args.params)
        if unknown:  # like the node: a warning, not an error
            warnings.append(f'params file {args.params}: ignoring unknown parameter(s) {unknown} (a typo in the '
                            f'params file?); known: {sorted(PARAM_SPEC_BY_NAME)}')
    return BagOptions(input=Path(args.input), output=Path(args.output), topics=tuple(args.topics or ()),
                      params=params, params_source=source, copy_input=args.copy_input, jobs=args.jobs,
                      storage=args.storage, force=args.force, progress=args.progress,
                      params_warnings=tuple(warnings))


def _unknown_parameter_names(names: Any) -> list[str]:
    """Names the extractor does not have (ROS's own ones excepted), as the node reports them."""
    return sorted(str(name) for name in names
                  if name not in PARAM_SPEC_BY_NAME and name not in ROS_BUILTIN_PARAMETERS
                  and not str(name).startswith('qos_overrides'))


def read_params_file(path: str | os.PathLike[str]) -> tuple[ExtractorParams, list[str]]:
    """The node's params file as :class:`ExtractorParams`, and the unknown names it ignored.

    The node warns about unknown parameters and goes on; so does ``process_bag``. Every other
    problem (unreadable file, no section, invalid value) raises ValueError.
    """
    unknown: list[str] = []

    class _IgnoringUnknown(ExtractorParams):  # from_yaml builds through cls.from_mapping
        @classmethod
        def from_mapping(cls, values: Any, *, source: str = 'parameters') -> ExtractorParams:
            if isinstance(values, dict):
                unknown.extend(_unknown_parameter_names(values))
                values = {name: value for name, value in values.items() if str(name) not in unknown}
            return ExtractorParams.from_mapping(values, source=source)

    params = _IgnoringUnknown.from_yaml(path, node_name='extractor')
    return params, unknown


def run(args: argparse.Namespace, prog: str = 'process_bag') -> int:
    """Run from parsed arguments; print the plan, warnings, summary and errors; return the exit code."""
    signals = _CommandSignals()
    signals.install()
    try:
        return _run_command(args, prog, signals)
    finally:
        signals.restore()


class _CommandSignals:
    """SIGINT / SIGTERM outside :func:`process_bag`'s own handling: before it (opening and scanning
    the input) they stop the command; after it (the bag is closed, the summary is printed) they
    are ignored, so that a repeated Ctrl-C never ends in a traceback."""

    def __init__(self) -> None:
        self.done = False
        self.signum: int | None = None
        self._previous: dict[int, Any] = {}

    def install(self) -> None:
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                self._previous[signum] = signal.signal(signum, self._handle)

    def restore(self) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()

    def _handle(self, signum: int, frame: Any) -> None:
        if self.signum is None:
            self.signum = signum
        if not self.done:
            raise KeyboardInterrupt


def _run_command(args: argparse.Namespace, prog: str, signals: _CommandSignals) -> int:
    try:
        report = process_bag(options_from_args(args))
    except BagError as exc:
        signals.done = True
        print(f'{prog}: error: {exc}', file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:  # before processing started
        signals.done = True
        print(f'{prog}: interrupted', file=sys.stderr)
        return 128 + (signals.signum or signal.SIGINT)
    signals.done = True
    print(format_report(report))
    problems = report_problems(report)
    label = 'error' if report.interrupted_by is None else 'stopped'
    for problem in problems:
        print(f'{prog}: {label}: {problem}', file=sys.stderr)
    if problems and report.output_path is not None:
        print(f'{prog}: {report.output_path} is a complete, valid bag of the {report.frames_processed} frames '
              'processed before that', file=sys.stderr)
    return report.exit_code


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``ros2 run ppe_ros process_bag``; returns the exit code."""
    arguments = list(sys.argv[1:] if argv is None else argv)
    if '--ros-args' in arguments:  # ros2 launch appends ROS arguments; they mean nothing here
        arguments = arguments[:arguments.index('--ros-args')]
    return run(build_parser().parse_args(arguments))


if __name__ == '__main__':
    sys.exit(main())
