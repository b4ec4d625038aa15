"""Opening an input bag of any kind (damaged ones read as far as they go) and choosing its topics."""

from __future__ import annotations

import contextlib
import heapq
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rosbags.rosbag1 import Reader as Ros1Reader
from rosbags.rosbag2 import Reader as Ros2Reader
from rosbags.rosbag2 import ReaderError as Ros2ReaderError

from ppe_ros.ros.bag.compression import decompress_as_far_as_possible, zstd_message
from ppe_ros.ros.bag.errors import BagError, describe_read_error
from ppe_ros.ros.bag.formats import MCAP_MAGIC, ROS1_MAGIC, SQLITE_MAGIC, ZSTD_MAGIC
from ppe_ros.ros.bag.salvage import (
    SalvageRos1Reader,
    SalvageSqliteReader,
    counts_exact,
    salvage_scan_error,
    salvaged_mcap_reader,
)
from ppe_ros.ros.bag.topics import (
    CAMERA_INFO,
    COMPRESSED_DEPTH,
    COMPRESSED_IMAGE,
    IMAGE,
    POINTCLOUD2,
    base_image_topic,
    camera_info_topic,
)


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

    def __init__(
        self,
        path: Path,
        description: str,
        encoding: str,
        readers: Sequence[Any],
        stack: contextlib.ExitStack,
        *,
        notes: Sequence[str] = (),
        damage: str | None = None,
        counts_known: bool = True,
    ) -> None:
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
                raw = zstd_message(raw)
            yield conn.topic, int(timestamp), raw

    def close(self) -> None:
        self._stack.close()


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
        for known, kind in (
            (ROS1_MAGIC, 'a ROS 1 bag'),
            (MCAP_MAGIC, 'an MCAP file'),
            (SQLITE_MAGIC, 'an sqlite3 database'),
        ):
            if magic and len(magic) < len(known) and known.startswith(magic):
                raise BagError(
                    f'{path} is damaged: it is cut to {len(magic)} byte{"s" * (len(magic) != 1)}, '
                    f'inside the file signature of {kind}; nothing to read'
                )
        if not magic:
            raise BagError(f'{path} is empty (0 bytes); nothing to read')
        if magic.startswith(ROS1_MAGIC):
            return _open_ros1(path, stack)
        if magic.startswith(MCAP_MAGIC) or magic.startswith(SQLITE_MAGIC):
            expected = '.mcap' if magic.startswith(MCAP_MAGIC) else '.db3'
            if path.suffix != expected:
                raise BagError(
                    f'{path} looks like a rosbag2 {expected} storage file but is named {path.name!r}; '
                    f'rename it to end in {expected}'
                )
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
                files, damage = decompress_as_far_as_possible(compressed, stack)
                return _open_rosbag2_files(files, path, stack, notes=[], damage=damage)
            # a damaged metadata.yaml or storage file: the storage files tell (and an MCAP is salvaged)
            notes = (
                []
                if _is_unfinished_mcap(exc)
                else [f'cannot use {path}: {describe_read_error(exc)}; reading its storage files directly']
            )
            return _open_rosbag2_files(files, path, stack, notes=notes)
        storage = 'mcap' if any(f.name.endswith(('.mcap', '.mcap.zstd')) for f in files or compressed) else 'sqlite3'
        return InputBag(path, f'rosbag2 ({storage})', 'cdr', [reader], stack)
    if compressed:
        files, damage = decompress_as_far_as_possible(compressed, stack)
        note = f'{path} has no metadata.yaml (was the recording interrupted?): reading its storage files directly'
        return _open_rosbag2_files(files, path, stack, notes=[note], damage=damage)
    if not files:
        raise BagError(
            f'{path} is a directory but not a rosbag2 bag: it has no metadata.yaml and no .mcap or .db3 file'
        )
    note = (
        f'{path} has no metadata.yaml (was the recording interrupted?): reading its storage '
        f'file{"s" if len(files) > 1 else ""} {", ".join(f.name for f in files)} directly'
    )
    return _open_rosbag2_files(files, path, stack, notes=[note])


def _is_unfinished_mcap(exc: BaseException) -> bool:
    """A reader error of an MCAP file whose footer or summary is missing or damaged."""
    text = str(exc)
    return any(words in text for words in ('end magic', 'MCAP footer', 'summary offset', 'Truncated record'))


def _open_rosbag2_files(
    files: Sequence[Path], path: Path, stack: contextlib.ExitStack, *, notes: list[str], damage: Sequence[str] = ()
) -> InputBag:
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
                    raise BagError(
                        f'cannot read {file}: {describe_read_error(exc)}; {salvage_error}; nothing readable'
                    ) from None
                damage.append(
                    f'{file.name} cannot be opened as a database ({describe_read_error(exc)}){reader.describe_damage()}'
                )
            elif file.suffix != '.mcap':
                raise BagError(f'cannot read {file}: {describe_read_error(exc)}') from None
        if reader is None:  # an MCAP without footer: scan it record by record
            reader = salvaged_mcap_reader(file)
            try:
                _open_reader(reader, stack)
            except Exception as exc:
                if damage:  # a decompressed file: its .zstd is what is damaged
                    raise BagError(f'{path} is damaged ({"; ".join(damage)}); nothing readable') from None
                raise BagError(f'{file} is damaged: {describe_read_error(exc)}; nothing readable') from None
            scan_error = salvage_scan_error(reader)
            where = f'; the scan stops at: {scan_error}' if scan_error else ''
            damage.append(f'{file.name} has no usable MCAP footer or summary (the recording was not closed){where}')
        readers.append(reader)
    if damage:
        notes = [*notes, f'{"; ".join(damage)}: reading it record by record up to the damage']
    complete_scans = all(counts_exact(reader) for reader in readers)
    return InputBag(
        path,
        f'rosbag2 ({storage})',
        'cdr',
        readers,
        stack,
        notes=notes,
        damage='; '.join(damage) or None,
        counts_known=complete_scans,
    )


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
        raise BagError(
            f'cannot read ROS 1 bag {path} (damaged or cut short before its first record?): {problem}; '
            f'{describe_read_error(exc)}'
        ) from None
    where = f'; the scan stops at: {salvage.scan_error}' if salvage.scan_error else ''
    damage = f'the ROS 1 bag has no usable index ({problem}){where}'
    return InputBag(
        path,
        'ROS 1 bag',
        'ros1',
        [salvage],
        stack,
        damage=damage,
        notes=[f'{damage}: reading its chunks in file order up to the damage'],
    )


def select_topics(bag: InputBag, requested: Sequence[str] | None) -> list[str]:
    """The topics to process: ``requested`` (checked), or every PointCloud2 topic and every depth image topic.

    A depth image topic is a ``sensor_msgs/msg/Image`` topic, or an image's ``compressedDepth`` topic
    (``sensor_msgs/msg/CompressedImage``), with a ``sensor_msgs/msg/CameraInfo`` topic beside the image
    (:func:`~ppe_ros.ros.bag.topics.camera_info_topic`); by default only those with ``depth`` in their name (a
    camera's colour images have a camera info too), and an image's compressedDepth topic only when the image
    itself is not in the bag; requested, any.

    Raises:
        BagError: a requested topic is not in the bag, is neither a PointCloud2 nor an Image, or is an
            Image without its camera info; nothing to process.
    """
    clouds = [name for name, topic in bag.topics.items() if topic.msgtype == POINTCLOUD2]
    depth = [name for name in bag.topics if _has_camera_info(bag, name) and 'depth' in name.lower()]
    depth = [name for name in depth if base_image_topic(name) == name or base_image_topic(name) not in depth]
    listing = ', '.join(f'{name} ({topic.msgtype})' for name, topic in bag.topics.items()) or 'none'
    if not requested:
        if not (clouds or depth) and bag.damage:
            raise BagError(
                f'{bag.path} is damaged before its first complete {POINTCLOUD2} message '
                f'({bag.damage}); nothing to process'
            )
        if not (clouds or depth):
            raise BagError(
                f'{bag.path} has no {POINTCLOUD2} topic and no depth image topic ({IMAGE} with a {CAMERA_INFO} '
                f'beside it and "depth" in its name); its topics: {listing}'
            )
        return [name for name in bag.topics if name in clouds or name in depth]
    selected: list[str] = []
    for name in requested:
        topic = name if name.startswith('/') else f'/{name}'
        if topic not in bag.topics:
            available = ', '.join(clouds + depth) or f'none (its topics: {listing})'
            raise BagError(f'topic {name!r} is not in {bag.path}; its point cloud and depth image topics: {available}')
        msgtype = bag.topics[topic].msgtype
        if msgtype == COMPRESSED_IMAGE and base_image_topic(topic) == topic:
            raise BagError(f'topic {topic} is a {COMPRESSED_IMAGE} but not a .../{COMPRESSED_DEPTH} depth image topic')
        if msgtype in (IMAGE, COMPRESSED_IMAGE) and not _has_camera_info(bag, topic):
            raise BagError(
                f'topic {topic} is an image without its camera info: {bag.path} has no {camera_info_topic(topic)} '
                f'({CAMERA_INFO}) beside it'
            )
        if msgtype not in (POINTCLOUD2, IMAGE, COMPRESSED_IMAGE):
            raise BagError(f'topic {topic} has type {msgtype}, not {POINTCLOUD2} or {IMAGE}')
        if topic not in selected:
            selected.append(topic)
    return selected


def _has_camera_info(bag: InputBag, topic: str) -> bool:
    """Whether ``topic`` is an Image (or an image's compressedDepth topic) with a CameraInfo topic beside it."""
    info = bag.topics.get(camera_info_topic(topic))
    msgtype = bag.topics[topic].msgtype
    image = msgtype == IMAGE or (msgtype == COMPRESSED_IMAGE and base_image_topic(topic) != topic)
    return image and info is not None and info.msgtype == CAMERA_INFO
