"""One frame: decode an input message, run the node's processing, serialize the outputs."""

from __future__ import annotations

import dataclasses
import functools
import time
from dataclasses import dataclass, field
from typing import Any

from ppe_ros.ros.bag.topics import CAMERA_INFO, IMAGE, POINTCLOUD2
from ppe_ros.ros.depth_image import DepthFrame
from ppe_ros.ros.messages import MessageTypes, rosbags_message_types
from ppe_ros.ros.processing import (
    ExtractorParams,
    FrameSkipped,
    OutputSelection,
    process_cloud,
    process_depth_image,
)


@dataclass(frozen=True)
class DepthMessages:
    """A depth image frame as read from a bag: the raw image and the raw camera info read last before it
    on ``camera_info_topic`` (None: none yet). What an executor takes instead of a cloud's raw bytes."""

    image: bytes
    camera_info: bytes | None
    camera_info_topic: str
    msgtype: str = IMAGE  # or sensor_msgs/msg/CompressedImage (compressedDepth)


#: One input frame: a cloud's raw message, or a depth image with its camera info.
FrameInput = bytes | DepthMessages


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


def ros1_as_ros2(msg: Any, typestore: Any) -> Any:
    """A ROS 1 message (rosbags) as the ROS 2 message of the same type in ``typestore``: field by field of the
    ROS 2 type, nested messages likewise; a ROS 2 field missing in ROS 1 is read from its upper-case name
    (CameraInfo's ``D K R P``), and ROS 1 fields without a ROS 2 twin are dropped (the header's ``seq``)."""
    cls = typestore.types[msg.__msgtype__]
    values = {}
    for item in dataclasses.fields(cls):
        if item.name == '__msgtype__':
            continue
        value = getattr(msg, item.name) if hasattr(msg, item.name) else getattr(msg, item.name.upper())
        if hasattr(value, '__msgtype__'):
            value = ros1_as_ros2(value, typestore)
        elif isinstance(value, list):
            value = [ros1_as_ros2(v, typestore) if hasattr(v, '__msgtype__') else v for v in value]
        values[item.name] = value
    return cls(**values)


@functools.lru_cache(maxsize=1)
def _typestores() -> tuple[Any, Any]:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC), get_typestore(Stores.ROS2_JAZZY)


def ros2_cdr(raw: bytes, encoding: str, msgtype: str) -> bytes:
    """A raw message of a bag as ROS 2 CDR bytes: as it is (``encoding`` 'cdr'), or converted from ROS 1."""
    if encoding == 'cdr':
        return raw
    ros1, ros2 = _typestores()
    return bytes(ros2.serialize_cdr(ros1_as_ros2(ros1.deserialize_ros1(raw, msgtype), ros2), msgtype))


def ros1_cloud_as_ros2(msg: Any, typestore: Any) -> Any:
    """A ROS 1 ``sensor_msgs/PointCloud2`` (rosbags) as a ROS 2 message of ``typestore`` (no ``seq``)."""
    return ros1_as_ros2(msg, typestore)


class FrameProcessor:
    """Decodes input messages and runs the node's processing on them (one per process)."""

    def __init__(self, params: ExtractorParams) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.params = params
        self.selection = OutputSelection.from_params(params)
        self.types: MessageTypes = rosbags_message_types(get_typestore(Stores.ROS2_JAZZY))
        self._ros1_typestore: Any = None

    def decode(self, raw: bytes, encoding: str, msgtype: str = POINTCLOUD2) -> Any:
        """A ``msgtype`` message of the Jazzy typestore from raw CDR or ROS 1 bytes."""
        typestore = self.types.typestore
        if encoding == 'cdr':
            return typestore.deserialize_cdr(raw, msgtype)
        if self._ros1_typestore is None:
            from rosbags.typesys import Stores, get_typestore

            self._ros1_typestore = get_typestore(Stores.ROS1_NOETIC)
        return ros1_as_ros2(self._ros1_typestore.deserialize_ros1(raw, msgtype), typestore)

    def _decode_frame(self, raw: FrameInput, encoding: str) -> Any:
        """The PointCloud2, or the :class:`DepthFrame` of a depth image and its camera info."""
        if not isinstance(raw, DepthMessages):
            return self.decode(raw, encoding)
        image = self.decode(raw.image, encoding, raw.msgtype)
        info = None if raw.camera_info is None else self.decode(raw.camera_info, encoding, CAMERA_INFO)
        return DepthFrame(image, info, raw.camera_info_topic)

    def process(self, raw: FrameInput, encoding: str, convert_copy: bool = False) -> FrameResult:
        """Decode, process and serialize one frame; failures become a skipped :class:`FrameResult`."""
        start = time.perf_counter()
        typestore = self.types.typestore
        depth = isinstance(raw, DepthMessages)
        try:
            msg = self._decode_frame(raw, encoding)
        except Exception as exc:
            what = f'{raw.msgtype} with its {CAMERA_INFO}' if depth else POINTCLOUD2
            return FrameResult(
                'undecodable',
                f'the message does not decode as {what}: {type(exc).__name__}: {exc}',
                seconds=time.perf_counter() - start,
            )
        result = FrameResult()
        try:
            if convert_copy:
                copied = msg.image if depth else msg
                result.copy = bytes(typestore.serialize_cdr(copied, raw.msgtype if depth else POINTCLOUD2))
            if depth:
                frame = process_depth_image(msg, self.params, self.types, outputs=self.selection)
            else:
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
