"""One frame: decode an input message, run the node's processing, serialize the outputs."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from ppe_ros.ros.bag.topics import POINTCLOUD2
from ppe_ros.ros.messages import MessageTypes, rosbags_message_types
from ppe_ros.ros.processing import (
    ExtractorParams,
    FrameSkipped,
    OutputSelection,
    process_cloud,
)


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
    return types[POINTCLOUD2](
        header=header,
        height=msg.height,
        width=msg.width,
        fields=fields,
        is_bigendian=msg.is_bigendian,
        point_step=msg.point_step,
        row_step=msg.row_step,
        data=msg.data,
        is_dense=msg.is_dense,
    )


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
            return FrameResult(
                'undecodable',
                f'the message does not decode as {POINTCLOUD2}: {type(exc).__name__}: {exc}',
                seconds=time.perf_counter() - start,
            )
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
