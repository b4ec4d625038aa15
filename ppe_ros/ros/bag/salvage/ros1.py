"""Reading a ROS 1 bag without a usable index (``rosbag record`` killed)."""

from __future__ import annotations

import os
import struct
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path
from typing import Any

from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag1.reader import Header as Ros1Header
from rosbags.rosbag1.reader import RecordType as Ros1RecordType
from rosbags.rosbag1.reader import decompressors as ros1_decompressors
from rosbags.rosbag1.reader import normalize as normalize_ros1_topic
from rosbags.rosbag1.reader import read_bytes as ros1_read_bytes
from rosbags.rosbag1.reader import read_uint32 as ros1_read_uint32
from rosbags.typesys.msg import normalize_msgtype

from ppe_ros.ros.bag.compression import partial_decompress
from ppe_ros.ros.bag.errors import describe_read_error


@dataclass(frozen=True)
class SalvagedConnection:
    """A topic of a salvaged file, as the readers of :class:`~ppe_ros.ros.bag.inputs.InputBag` describe one."""

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
        self.connections: list[SalvagedConnection] = []
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
        self.connections = [
            SalvagedConnection(conn_id, topic, msgtype, counts[conn_id])
            for conn_id, (topic, msgtype) in sorted(topics.items())
        ]

    def close(self) -> None:
        if self._bio is not None:
            self._bio.close()
            self._bio = None

    def messages(self, connections: Sequence[SalvagedConnection]) -> Iterator[tuple[SalvagedConnection, int, bytes]]:
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
                    yield from self._chunk_records(partial_decompress(data, compression), partial=True)
                    raise Ros1ReaderError(
                        f'the chunk at byte {start} is cut short ({len(data)} of {size} bytes); '
                        'the records complete in it are read'
                    )
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
            yield (
                'connection',
                header.get_uint32('conn'),
                (normalize_ros1_topic(header.get_string('topic')), normalize_msgtype(info.get_string('type'))),
            )
        elif op == Ros1RecordType.MSGDATA:
            yield 'message', header.get_uint32('conn'), (header.get_time('time'), data)
