"""Message-class flavours (rclpy or rosbags) and a little-endian CDR writer.

ppe_ros builds the same output messages for two consumers: the live rclpy node and the offline
bag tool (rosbags, no rclpy). :class:`MessageTypes` carries the message classes of one flavour so
that :func:`ppe_ros.ros.processing.process_cloud` runs unchanged for both.

Marker arrays of finite planes hold hundreds of thousands of ``geometry_msgs/Point`` vertices;
building one Python object per vertex costs about a second per frame. Markers are therefore
serialized straight from numpy into CDR bytes (:class:`CdrWriter`), which rclpy publishes as they
are (``Publisher.publish(bytes)``) and rosbags writes as they are (``Writer.write``).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

#: CDR encapsulation header of a little-endian, plain CDR (XCDR1) payload, as ROS 2 uses it.
CDR_LE_HEADER = b'\x00\x01\x00\x00'


@dataclass(frozen=True)
class MessageTypes:
    """The message classes of one flavour.

    Attributes:
        flavour: ``'rclpy'`` or ``'rosbags'``.
        PointCloud2, PointField, Image, CameraInfo, CompressedImage: ``sensor_msgs/msg`` classes.
        MarkerArray: ``visualization_msgs/msg/MarkerArray`` (used to decode markers in tests and tools).
        DiagnosticArray, DiagnosticStatus, KeyValue: ``diagnostic_msgs/msg`` classes.
        typestore: the rosbags typestore (rosbags flavour only), for ``deserialize_cdr``.
    """

    flavour: str
    PointCloud2: type
    PointField: type
    MarkerArray: type
    Image: type | None = None
    CameraInfo: type | None = None
    CompressedImage: type | None = None
    DiagnosticArray: type | None = None
    DiagnosticStatus: type | None = None
    KeyValue: type | None = None
    typestore: Any = None

    def decode_markers(self, cdr: bytes) -> Any:
        """Deserialize CDR bytes of a ``visualization_msgs/msg/MarkerArray`` into this flavour's message."""
        if self.flavour == 'rclpy':
            from rclpy.serialization import deserialize_message

            return deserialize_message(bytes(cdr), self.MarkerArray)
        return self.typestore.deserialize_cdr(bytes(cdr), 'visualization_msgs/msg/MarkerArray')


def rclpy_message_types() -> MessageTypes:
    """Message classes of the installed ROS 2 Python packages (needs rclpy's message wheels)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2, PointField
    from visualization_msgs.msg import MarkerArray

    return MessageTypes(
        flavour='rclpy',
        PointCloud2=PointCloud2,
        PointField=PointField,
        MarkerArray=MarkerArray,
        Image=Image,
        CameraInfo=CameraInfo,
        CompressedImage=CompressedImage,
        DiagnosticArray=DiagnosticArray,
        DiagnosticStatus=DiagnosticStatus,
        KeyValue=KeyValue,
    )


def rosbags_message_types(typestore: Any = None) -> MessageTypes:
    """Message classes of a rosbags typestore (default: ROS 2 Jazzy); no rclpy needed."""
    if typestore is None:
        from rosbags.typesys import Stores, get_typestore

        typestore = get_typestore(Stores.ROS2_JAZZY)
    types = typestore.types
    return MessageTypes(
        flavour='rosbags',
        PointCloud2=types['sensor_msgs/msg/PointCloud2'],
        PointField=types['sensor_msgs/msg/PointField'],
        MarkerArray=types['visualization_msgs/msg/MarkerArray'],
        Image=types['sensor_msgs/msg/Image'],
        CameraInfo=types['sensor_msgs/msg/CameraInfo'],
        CompressedImage=types['sensor_msgs/msg/CompressedImage'],
        DiagnosticArray=types['diagnostic_msgs/msg/DiagnosticArray'],
        DiagnosticStatus=types['diagnostic_msgs/msg/DiagnosticStatus'],
        KeyValue=types['diagnostic_msgs/msg/KeyValue'],
        typestore=typestore,
    )


@dataclass(frozen=True)
class StampedFrame:
    """The part of a ``std_msgs/Header`` every output copies: stamp (s, ns) and frame_id."""

    sec: int
    nanosec: int
    frame_id: str

    @classmethod
    def of(cls, header: Any) -> StampedFrame:
        """Read a header of either flavour."""
        return cls(int(header.stamp.sec), int(header.stamp.nanosec), str(header.frame_id))

    @property
    def nanoseconds(self) -> int:
        """The stamp in integer nanoseconds."""
        return self.sec * 1_000_000_000 + self.nanosec


class CdrWriter:
    """Append-only writer of a little-endian CDR payload (with its 4-byte encapsulation header).

    Alignment follows plain CDR: every primitive is aligned to its own size, counted from the end
    of the encapsulation header. Large numeric blocks are appended in one ``tobytes`` call.
    """

    def __init__(self) -> None:
        self._chunks: list[bytes | memoryview] = [CDR_LE_HEADER]
        self._size = 0  # bytes after the encapsulation header

    @property
    def size(self) -> int:
        """Payload bytes written so far (without the encapsulation header)."""
        return self._size

    def _put(self, chunk: bytes | memoryview) -> None:
        self._chunks.append(chunk)
        self._size += len(chunk)

    def raw(self, *chunks: bytes | memoryview) -> None:
        """Append byte chunks as they are (the caller has laid out their alignment)."""
        self._chunks.extend(chunks)
        self._size += sum(map(len, chunks))

    def align(self, alignment: int) -> None:
        """Zero-pad to a multiple of ``alignment`` bytes."""
        pad = -self._size % alignment
        if pad:
            self._put(b'\x00' * pad)

    def uint8(self, value: int) -> None:
        self._put(struct.pack('<B', value))

    def boolean(self, value: bool) -> None:
        self._put(b'\x01' if value else b'\x00')

    def int32(self, value: int) -> None:
        self.align(4)
        self._put(struct.pack('<i', value))

    def uint32(self, value: int) -> None:
        self.align(4)
        self._put(struct.pack('<I', value))

    def float32s(self, *values: float) -> None:
        self.align(4)
        self._put(struct.pack(f'<{len(values)}f', *values))

    def float64s(self, *values: float) -> None:
        self.align(8)
        self._put(struct.pack(f'<{len(values)}d', *values))

    def string(self, value: str) -> None:
        encoded = value.encode('utf-8') + b'\x00'
        self.uint32(len(encoded))
        self._put(encoded)

    def header(self, stamped: StampedFrame) -> None:
        """A ``std_msgs/Header``: ``int32 sec, uint32 nanosec, string frame_id``."""
        self.int32(stamped.sec)
        self.uint32(stamped.nanosec)
        self.string(stamped.frame_id)

    def float64_block(self, values: np.ndarray) -> None:
        """A block of float64 values (e.g. the ``(N, 3)`` elements of a ``Point[]``), without a count."""
        self.align(8)
        block = np.ascontiguousarray(values, dtype='<f8')
        self._put(memoryview(block).cast('B'))  # no copy here; getvalue() copies once

    def getvalue(self) -> bytes:
        """The serialized message: encapsulation header + payload (no trailing padding, like rclpy)."""
        return b''.join(self._chunks)
