"""Reading a rosbag2 ``.db3`` that SQLite refuses, page by page."""

from __future__ import annotations

import contextlib
import struct
from collections import Counter
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from rosbags.rosbag2 import ReaderError as Ros2ReaderError

from ppe_ros.ros.bag.formats import SQLITE_MAGIC
from ppe_ros.ros.bag.salvage.ros1 import SalvagedConnection


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
        count = int.from_bytes(data[start + 3 : start + 5], 'big')
        interior = kind in (0x02, 0x05)
        array = start + (12 if interior else 8)
        if array + 2 * count > self.usable:
            raise ValueError(f'page {number} claims {count} cells, more than fit')
        offsets = [int.from_bytes(data[array + 2 * i : array + 2 * i + 2], 'big') for i in range(count)]
        if any(not array + 2 * count <= offset < self.usable for offset in offsets):
            raise ValueError(f'page {number} has a cell pointer outside the page')
        right = int.from_bytes(data[start + 8 : start + 12], 'big') if interior else 0
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
            overflow = int.from_bytes(data[offset + local : offset + local + 4], 'big')
        if offset + local > usable:
            raise ValueError('a cell runs past the end of its page')
        return rowid, payload_size, data[offset : offset + local], overflow

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
            raw = payload[position : position + size]
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
                children = [int.from_bytes(data[o : o + 4], 'big') for o in offsets] + [right]
                stack.extend(reversed(children))
            elif kind == 0x0D:
                for offset in offsets:
                    with contextlib.suppress(ValueError, IndexError):
                        rowid, size, local, first = self.leaf_cell(data, offset)
                        yield (
                            rowid,
                            self.record(
                                self.payload(
                                    local, size, self.overflow_pages(first, size - len(local)) if first else []
                                )
                            ),
                        )


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
        self.connections: list[SalvagedConnection] = []
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
        self.connections = [
            SalvagedConnection(topic_id, name, msgtype, counts[topic_id])
            for topic_id, (name, msgtype) in sorted(topics.items())
        ]

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
            raw = local[position : position + size]
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

    def messages(self, connections: Sequence[SalvagedConnection]) -> Iterator[tuple[SalvagedConnection, int, bytes]]:
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
