"""``ros2 run ppe_ros extractor``: the live plane-extraction node.

Threads: the executor thread runs the subscription callbacks (a cloud only goes into a one-slot
mailbox, :mod:`ppe_ros.ros.concurrency`), the diagnostics timer and the parameter services;
``workers`` worker threads (default 1) convert, extract and publish. A cloud that arrives while
every worker is busy replaces the waiting one and is counted as dropped, so the executor never
stalls and the node always works on the newest frame. With several workers, frames are numbered
as they are taken and published in that order (a worker that finishes early waits for the frames
before its own). The compiled kernels release the GIL (``nogil``; the parallel ones release it as
numba's parallel launches do), so the executor keeps receiving, answering parameter requests and
publishing diagnostics while the workers extract (``test/test_threads.py``).

Topics (relative names, remappable):

* in ``points`` (``sensor_msgs/PointCloud2``, organized, transposed or height 1), QoS depth 1, reliability from the
  ``input_reliability`` parameter. No return: a point with a NaN or infinite coordinate, or exactly
  at (0, 0, 0) (what many drivers publish for a pixel without a return; the file loaders read it so
  too); such points get label 0 and NaN coordinates in ``planes/labeled_points``;
* in ``depth/image`` (``sensor_msgs/Image``, QoS as ``points``) with ``depth/camera_info``
  (``sensor_msgs/CameraInfo``, best effort; the latest one goes with each image): a depth camera's
  depth image, back-projected and extracted as an organized cloud in the image's optical frame
  (:mod:`ppe_ros.ros.depth_image`);
* in ``metadata`` (``std_msgs/String``, reliable, transient local): the Ouster driver's metadata
  JSON; while ``ray_origin`` is [0, 0, 0], clouds of the size it describes get its per-beam ray
  starts (:mod:`ppe_ros.ros.sensor_metadata`);
* out ``planes/labeled_points``, ``planes/markers``, ``planes`` (see :mod:`ppe_ros.ros.processing`)
  and ``/diagnostics`` (about 1 Hz, :mod:`ppe_ros.ros.diagnostics`). Outputs are reliable (they
  match reliable and best-effort subscribers); an output nobody subscribes to is not built, and
  with no subscriber on any output the node idles (frames are counted, not extracted) unless
  ``process_without_subscribers`` is true.

QoS: ``-p qos_overrides.<topic>.<subscription|publisher>.<history|depth|reliability>:=...`` (rclpy's
``QoSOverridingOptions``; ``<topic>`` is the resolved name, after remapping) sets the input's and
the outputs' QoS; for the input the reliability override wins over ``input_reliability``. An
override for a topic or policy the node does not have is warned about.

Parameters: :data:`ppe_ros.ros.processing.PARAM_SPECS`, loaded with
``--ros-args --params-file config/extractor.yaml`` and changeable at runtime (an invalid value is
rejected with the reason; an integer array is accepted for ``ray_origin``; a name the node does not
have is refused naming it).

Bad input never stops the node: a cloud it cannot use is skipped (a warning per kind at most every
5 s, counted by kind), a frame whose extraction or publishing raises is counted as failed and logged
as one error line naming the frame (stamp, frame_id) and the reason; the worker goes on with the next
frame whatever the exception. Diagnostics say WARN for skipped frames and a low output rate, ERROR
for failed frames and for a worker thread that is not running.
"""

from __future__ import annotations

import ctypes
import faulthandler
import gc
import math
import os
import sys
import threading
import time
from typing import Any

import rclpy
from rcl_interfaces.msg import SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions

from ppe_ros.ros.compressed_depth import warm_up_rvl
from ppe_ros.ros.concurrency import LatestMailbox, Turnstile
from ppe_ros.ros.depth_image import DepthCamera, DepthFrame, DepthImageError, camera_model
from ppe_ros.ros.diagnostics import WARNING_THROTTLE_S, FrameStats, NodeState, ThrottledLog, diagnostics_status
from ppe_ros.ros.messages import rclpy_message_types
from ppe_ros.ros.parameters import (
    QOS_OVERRIDES_PREFIX,
    as_declared_type,
    coerce_parameters,
    declare_extractor_parameters,
    input_qos,
    metadata_qos,
    output_qos,
    parameter_changes,
    parameter_descriptor,
    qos_override_names,
    unknown_parameter_names,
    validate_parameter_changes,
)
from ppe_ros.ros.processing import (
    PARAM_SPECS,
    ExtractorParams,
    FrameSkipped,
    OutputSelection,
    failure_reason,
    frame_label,
    process_cloud,
    process_depth_image,
)
from ppe_ros.ros.sensor_metadata import RayStarts
from ppe_ros.ros.warmup import WORKQUEUE_LAYER_ERROR, parallel_workers_safe, warm_up, warm_up_cloud

__all__ = [  # the names tests and tools import from here (their homes are the modules above)
    'WARNING_THROTTLE_S',
    'ExtractorNode',
    'FrameStats',
    'LatestMailbox',
    'Turnstile',
    'input_qos',
    'main',
    'output_qos',
    'parameter_descriptor',
    'unknown_parameter_names',
    'usage',
    'warm_up_cloud',
]

NODE_NAME = 'extractor'
INPUT_TOPIC = 'points'
DEPTH_IMAGE_TOPIC = 'depth/image'
CAMERA_INFO_TOPIC = 'depth/camera_info'
METADATA_TOPIC = 'metadata'
LABELED_POINTS_TOPIC = 'planes/labeled_points'
MARKERS_TOPIC = 'planes/markers'
PLANE_TABLE_TOPIC = 'planes'
DIAGNOSTICS_TOPIC = '/diagnostics'
DIAGNOSTICS_PERIOD_S = 1.0
#: The worker checks for a stop request at least this often (s).
WORKER_POLL_S = 0.1
#: How long a stop (SIGINT, SIGTERM) waits for the workers to finish the frame in hand (s). A worker still
#: busy then (the JIT warm-up compiling on a cold numba cache takes minutes) is not waited for: the
#: process logs which and exits without it.
STOP_TIMEOUT_S = 5.0
#: Longer than STOP_TIMEOUT_S plus this for the whole shutdown, and the process prints its threads'
#: stacks and exits with code 1 (a hang in rclpy's or DDS's teardown).
SHUTDOWN_GRACE_S = 10.0

_as_declared_type = as_declared_type  # its former name here


class ExtractorNode(Node):
    """The plane-extraction node (name ``extractor``); see the module docstring.

    Keyword arguments go to :class:`rclpy.node.Node` (``context``, ``namespace``,
    ``parameter_overrides``, ...). Call :meth:`stop` (or :meth:`destroy_node`, which calls it)
    before shutting the context down: it joins the worker threads.

    Raises:
        ValueError: a parameter given at start-up (params file, ``-p``, overrides) is invalid.
    """

    def __init__(self, node_name: str = NODE_NAME, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._types = rclpy_message_types()
        try:
            self._params = declare_extractor_parameters(self)
        except ValueError:
            super().destroy_node()  # no worker yet: release the node handle and report the parameter
            raise
        self.add_pre_set_parameters_callback(self._coerce_parameters)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        overridable = QoSOverridingOptions.with_default_policies()
        self._labeled_points_pub = self.create_publisher(
            self._types.PointCloud2, LABELED_POINTS_TOPIC, output_qos(), qos_overriding_options=overridable
        )
        self._markers_pub = self.create_publisher(
            self._types.MarkerArray, MARKERS_TOPIC, output_qos(), qos_overriding_options=overridable
        )
        self._plane_table_pub = self.create_publisher(
            self._types.PointCloud2, PLANE_TABLE_TOPIC, output_qos(), qos_overriding_options=overridable
        )
        self._diagnostics_pub = self.create_publisher(self._types.DiagnosticArray, DIAGNOSTICS_TOPIC, 10)

        self._stats = FrameStats()
        self._mailbox = LatestMailbox()
        self._turns = Turnstile()
        self._log_throttled = ThrottledLog(self.get_logger(), prefix=node_name)
        self._stop_requested = threading.Event()
        self.ready = threading.Event()
        """Set once the JIT warm-up is done and the workers wait for clouds."""
        self._numba_threads_applied: list[int | None] = []  # per worker: numba's count is per thread
        self._worker_tasks: list[str] = []  # per worker: what it is doing, for a stop that cannot wait for it
        self._workers: list[threading.Thread] = []
        self._workers_lock = threading.Lock()
        self._parallel_workers_safe = True  # False under numba's workqueue layer (see _work)
        self._ray_starts = RayStarts(self._warn_throttled, self.get_logger().info)  # Ouster metadata's
        self._marker_stride = 0  # of the last markers built

        self._subscription_lock = threading.Lock()
        self._subscription = self._subscribe(self._params.input_reliability)
        self._camera_info: Any = None  # the latest sensor_msgs/CameraInfo, for the depth images
        self._camera_logged: DepthCamera | None = None  # the camera model the log last named
        self._depth_subscription = self._subscribe(self._params.input_reliability, topic=DEPTH_IMAGE_TOPIC)
        self._camera_info_subscription = self.create_subscription(
            self._types.CameraInfo, CAMERA_INFO_TOPIC, self._on_camera_info, input_qos('best_effort')
        )
        from std_msgs.msg import String

        self._metadata_subscription = self.create_subscription(
            String, METADATA_TOPIC, self._on_metadata, metadata_qos()
        )
        self._warn_unused_qos_overrides()
        self._diagnostics_timer = self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_diagnostics)
        self._start_workers(self._params.workers)

    # ---------------------------------------------------------------- parameters

    @property
    def params(self) -> ExtractorParams:
        """The current validated parameters (replaced as a whole on every accepted change)."""
        return self._params

    def _coerce_parameters(self, parameters: list[Parameter]) -> list[Parameter]:
        return coerce_parameters(self, parameters)

    def _validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        return validate_parameter_changes(self._params, parameters)

    def _apply_parameters(self, parameters: list[Parameter]) -> None:
        changes = parameter_changes(parameters)
        if not changes:
            return
        previous = self._params
        self._params = previous.replace(**changes)
        self.get_logger().info('parameters changed: ' + ', '.join(f'{k}={v!r}' for k, v in changes.items()))
        if self._params.input_reliability != previous.input_reliability:
            self._resubscribe(self._params.input_reliability)
        elif self._params.depth_image_transport != previous.depth_image_transport:
            self._resubscribe(self._params.input_reliability, (DEPTH_IMAGE_TOPIC,))
        if self._params.workers > previous.workers:
            self._start_workers(self._params.workers)

    # ---------------------------------------------------------------- input

    def _subscribe(self, reliability: str, qos: QoSProfile | None = None, topic: str = INPUT_TOPIC):
        """The ``points`` (or ``depth/image``) subscription; the first one declares the QoS override parameters.

        The depth images of ``depth_image_transport: compressedDepth`` come on ``<depth/image, resolved and
        remapped>/compressedDepth``, as image_transport names its transports' topics.
        """
        options = QoSOverridingOptions.with_default_policies() if qos is None else None
        depth = topic == DEPTH_IMAGE_TOPIC
        message_type = self._types.Image if depth else self._types.PointCloud2
        if depth and self._params.depth_image_transport == 'compressedDepth':
            message_type, topic = self._types.CompressedImage, self.resolve_topic_name(topic) + '/compressedDepth'
        return self.create_subscription(
            message_type,
            topic,
            self._on_depth_image if depth else self._on_cloud,
            input_qos(reliability) if qos is None else qos,
            qos_overriding_options=options,
        )

    def _input_override(self, policy: str, subscription: Any = None) -> tuple[str, Any]:
        """(name, value given at start-up or None) of an input's QoS override parameter for ``policy``
        (default: the ``points`` input's)."""
        topic = (self._subscription if subscription is None else subscription).topic_name
        name = f'{QOS_OVERRIDES_PREFIX}{topic}.subscription.{policy}'
        given = getattr(self, '_parameter_overrides', {}).get(name)
        return name, None if given is None else given.value

    def _resubscribe(self, reliability: str, topics: tuple[str, ...] = (INPUT_TOPIC, DEPTH_IMAGE_TOPIC)) -> None:
        """New ``points`` and ``depth/image`` subscriptions (of ``topics``) for a changed ``input_reliability`` or
        ``depth_image_transport`` (a reliability override of a topic wins for that topic)."""
        attributes = {INPUT_TOPIC: '_subscription', DEPTH_IMAGE_TOPIC: '_depth_subscription'}
        for topic in topics:
            attribute = attributes[topic]
            subscription = getattr(self, attribute)
            name, forced = self._input_override('reliability', subscription)
            qos = input_qos(reliability)
            if forced is not None:  # the override keeps its reliability (the transport may still change)
                if qos.reliability != ReliabilityPolicy[str(forced).upper()]:
                    self.get_logger().warning(f'input_reliability {reliability} has no effect: {name} is {forced}')
                qos.reliability = ReliabilityPolicy[str(forced).upper()]
            for policy in ('history', 'depth'):  # keep the depth and history overrides of the first subscription
                policy_name = f'{QOS_OVERRIDES_PREFIX}{subscription.topic_name}.subscription.{policy}'
                if self.has_parameter(policy_name):
                    value = self.get_parameter(policy_name).value
                    setattr(qos, policy, HistoryPolicy[str(value).upper()] if policy == 'history' else int(value))
            with self._subscription_lock:
                self.destroy_subscription(subscription)
                setattr(self, attribute, self._subscribe(reliability, qos, topic))
            now = getattr(self, attribute)
            self.get_logger().info(
                f'input {now.topic_name} now subscribed with {now.qos_profile.reliability.name.lower()} QoS'
            )

    def _warn_unused_qos_overrides(self) -> None:
        """A QoS override naming a topic (or policy) the node does not have would be ignored silently."""
        unused = [
            name
            for name in qos_override_names(getattr(self, '_parameter_overrides', {}))
            if not self.has_parameter(name)
        ]
        if unused:
            known = sorted(name for name in self._parameters if name.startswith(QOS_OVERRIDES_PREFIX))
            self.get_logger().warning(
                f'ignoring QoS override(s) {unused}: no such topic or policy of this node '
                f'(topics are resolved names, after remapping); known: {known}'
            )

    @property
    def input_topic(self) -> str:
        """Resolved name of the input topic."""
        return self._subscription.topic_name

    @property
    def depth_image_topic(self) -> str:
        """Resolved name of the depth image input."""
        return self._depth_subscription.topic_name

    def _on_cloud(self, msg: Any) -> None:
        self._stats.record_received(dropped=self._mailbox.put(msg))

    def _on_depth_image(self, msg: Any) -> None:
        frame = DepthFrame(msg, self._camera_info, self._camera_info_subscription.topic_name)
        self._stats.record_received(dropped=self._mailbox.put(frame))

    def _on_camera_info(self, msg: Any) -> None:
        self._camera_info = msg  # one reference assignment: the depth image callback reads it as a whole
        try:
            camera = camera_model(msg, rectified=self._params.depth_image_rectified)
        except DepthImageError:
            return  # the images it goes with are skipped with the reason
        if camera != self._camera_logged:
            self._camera_logged = camera
            self.get_logger().info(f'camera info on {self._camera_info_subscription.topic_name}: {camera.describe()}')

    def _on_metadata(self, msg: Any) -> None:
        self._ray_starts.update(msg.data, self._metadata_subscription.topic_name)

    # ---------------------------------------------------------------- worker

    def _start_workers(self, count: int) -> None:
        """Start worker threads up to ``count`` (a lower ``workers`` value parks the extra ones)."""
        with self._workers_lock:
            while len(self._workers) < count and not self._stop_requested.is_set():
                index = len(self._workers)
                self._numba_threads_applied.append(None)
                self._worker_tasks.append('waiting for a cloud')
                worker = threading.Thread(
                    target=self._work, args=(index,), name=f'{self.get_name()}-worker-{index}', daemon=False
                )
                self._workers.append(worker)
                worker.start()

    def _apply_numba_threads(self, index: int, params: ExtractorParams) -> None:
        """numba's thread count is per calling thread: each worker sets its own before its kernels run.

        ``numba_threads`` 0 shares the cores numba sees out among the workers (at least one each).
        """
        import numba

        count = params.numba_threads or max(1, numba.config.NUMBA_NUM_THREADS // max(params.workers, 1))
        if count == self._numba_threads_applied[index]:
            return
        numba.set_num_threads(count)
        self._numba_threads_applied[index] = count

    def _warm_up(self) -> None:
        """Run the whole pipeline once with the node's sensor profile (compiles or loads the numba cache)."""
        start = time.perf_counter()
        self._start_up_info(
            'JIT warm-up: loading or compiling the kernels (a cold cache compiles for minutes; '
            '`ppe warmup` fills it once after an install)'
        )
        steps = warm_up(self._types, self._params, log=self._start_up_info)
        if self._params.depth_image_transport == 'compressedDepth':
            warm_up_rvl()  # its decoder's kernel
        # numba's compiler leaves some 600 k long-lived objects; a full garbage collection scanned
        # them all (about 50 ms, every few hundred frames). Frozen, the collector skips them.
        gc.freeze()
        self._start_up_info(
            f'JIT warm-up done in {time.perf_counter() - start:.2f} s ({steps[-1].planes} planes in the warm-up cloud)'
        )

    def _start_up_info(self, message: str) -> None:
        """An info line of the JIT warm-up, on the console only (``<node>.start_up``, not /rosout).

        A SIGINT or SIGTERM during the start-up shuts the context down from rclpy's signal thread while the
        warm-up goes on in a worker thread; a line that went to /rosout at that moment made rcl print
        "Failed to publish log message to rosout: publisher's context is invalid" (checking the context
        first still left the moment between the check and the publish)."""
        self.console_logger('start_up').info(message)

    def console_logger(self, part: str = 'shutdown') -> Any:
        """A child ``<node>.<part>`` of the node's logger that does not publish to /rosout (console only): for
        the warm-up's lines and for those after a signal shut the context down, when the node's /rosout
        publisher is gone."""
        return rclpy.logging.get_logger(f'{self.get_logger().name}.{part}')

    def _active(self, index: int) -> bool:
        """Whether worker ``index`` takes frames under the current ``workers`` value."""
        return index == 0 or (index < self._params.workers and self._parallel_workers_safe)

    def _running(self) -> bool:
        """True until :meth:`stop`, or until the main thread has ended without it: a SIGINT that reaches the
        main thread between the node's construction and its owner's name for it leaves nobody to stop the
        workers, and the interpreter would wait for them at exit forever."""
        return not self._stop_requested.is_set() and threading.main_thread().is_alive()

    def _work(self, index: int) -> None:
        """Worker ``index``'s thread: it ends on :meth:`stop` or once the main thread has ended (any exception
        is a failed frame)."""
        while self._running():
            try:
                self._serve(index)
            except Exception as exc:  # outside any frame (a defect): report it, wait a little, go on
                self._record_failure(f'worker {index} error: {failure_reason(exc)}')
                self._stop_requested.wait(WORKER_POLL_S)

    def _serve(self, index: int) -> None:
        """Warm up (worker 0), then take, extract and publish frames until :meth:`stop`."""
        if index == 0 and not self.ready.is_set():
            self._worker_tasks[index] = 'the JIT warm-up'
            try:
                self._apply_numba_threads(index, self._params)
                self._warm_up()
                self._parallel_workers_safe = parallel_workers_safe()
                if not self._parallel_workers_safe and self._params.workers > 1:
                    self.get_logger().error(WORKQUEUE_LAYER_ERROR)
            except Exception as exc:  # a failed warm-up must not kill the node
                self._record_failure(f'warm-up failed: {failure_reason(exc)}')
            self._worker_tasks[index] = 'waiting for a cloud'
            self.ready.set()
            if not self._stop_requested.is_set() and self.context.ok():  # else stopping: not ready for anything
                self.get_logger().info(
                    f'ready: waiting for PointCloud2 on {self.input_topic} or depth images on {self.depth_image_topic} '
                    f'({self._params.input_reliability}, {self._params.workers} worker(s))'
                )
        while self._running():
            if not self.ready.is_set() or not self._active(index):
                self._stop_requested.wait(WORKER_POLL_S)  # warming up, or parked by a lower workers value
                continue
            taken = self._mailbox.take_numbered(WORKER_POLL_S)
            if taken is None:
                continue
            number, msg = taken
            self._worker_tasks[index] = f'a frame ({frame_label(msg)})'
            try:
                self._process(index, msg, number)
            except Exception as exc:  # a defect in the node itself: count it, say why, keep serving
                self._record_failure(f'frame failed ({frame_label(msg)}): internal error: {failure_reason(exc)}')
            finally:
                self._turns.release(number)  # published, skipped or failed: the next frame may go
                self._worker_tasks[index] = 'waiting for a cloud'

    def _wanted_outputs(self, params: ExtractorParams) -> OutputSelection:
        """The enabled outputs that somebody subscribes to (nobody listening: not built)."""
        return OutputSelection(
            labeled_points=(params.publish_labeled_points and self._labeled_points_pub.get_subscription_count() > 0),
            markers=params.publish_markers and self._markers_pub.get_subscription_count() > 0,
            plane_table=params.publish_plane_table and self._plane_table_pub.get_subscription_count() > 0,
        )

    def _idle(self, params: ExtractorParams, outputs: OutputSelection | None = None) -> bool:
        """No output is wanted and ``process_without_subscribers`` is false: frames are not extracted."""
        outputs = self._wanted_outputs(params) if outputs is None else outputs
        wanted = outputs.labeled_points or outputs.markers or outputs.plane_table
        return not wanted and not params.process_without_subscribers

    def _process(self, index: int, msg: Any, number: int) -> None:
        """Extract frame ``number`` (taken in that order) and publish it when the frames before it are out."""
        params = self._params
        outputs = self._wanted_outputs(params)
        if self._idle(params, outputs):
            self._stats.record_idle()
            return
        start = time.perf_counter()
        stats = self._stats
        with stats.lock:
            stats.busy += 1
            stats.busy_peak = max(stats.busy_peak, stats.busy)
        try:
            self._apply_numba_threads(index, params)
            if isinstance(msg, DepthFrame):
                frame = process_depth_image(msg, params, self._types, outputs=outputs)
            else:
                frame = process_cloud(
                    msg,
                    params,
                    self._types,
                    outputs=outputs,
                    ray_origins=self._ray_starts.for_cloud(msg, params.ray_origin),
                )
        except FrameSkipped as exc:
            self._record_skip(exc)
            return
        except Exception as exc:  # the node keeps running on any per-frame failure
            if self.context.ok():  # shutting down: nothing to report
                self._record_failure(f'frame failed ({frame_label(msg)}): {failure_reason(exc)}')
            return
        finally:
            with stats.lock:
                stats.busy -= 1
        while not self._turns.wait_turn(number, WORKER_POLL_S):  # the frames taken before this one first
            if self._stop_requested.is_set():
                return
        try:
            self._publish(frame)
        except Exception as exc:
            if self.context.ok():
                self._record_failure(f'publishing failed ({frame_label(msg)}): {failure_reason(exc)}')
            return
        if frame.markers is not None:
            self._marker_stride = frame.marker_stride
        stats.record_published(time.perf_counter() - start, frame.planes.num_planes, frame.stamped.frame_id)

    def _publish(self, frame: Any) -> None:
        """Publish the outputs ``frame`` has (the markers as their CDR bytes)."""
        if frame.labeled_points is not None:
            self._labeled_points_pub.publish(frame.labeled_points)
        if frame.markers is not None:
            self._markers_pub.publish(frame.markers)
        if frame.plane_table is not None:
            self._plane_table_pub.publish(frame.plane_table)

    def _warn_throttled(self, key: str, message: str, *, error: bool = False) -> None:
        """Log ``message`` (a warning, or an error) unless one of ``key`` went out in the last 5 s; never raises."""
        self._log_throttled(key, message, error=error)

    @property
    def _warned_at(self) -> dict[str, float]:
        """Key -> when its last line went out (monotonic s)."""
        return self._log_throttled.warned_at

    def _record_skip(self, exc: FrameSkipped) -> None:
        self._stats.record_skip(exc.kind, exc.reason)
        self._warn_throttled(exc.kind, f'frame skipped: {exc.reason}')

    def _record_failure(self, message: str) -> None:
        self._stats.record_failure(message)
        self._warn_throttled('failure', message, error=True)

    # ---------------------------------------------------------------- diagnostics

    def frame_counts(self) -> dict[str, Any]:
        """Totals since start: received, processed, dropped, skipped, failed, idle, skipped_by_kind, last_error."""
        return self._stats.counts()

    def diagnostics_status(self) -> Any:
        """A ``diagnostic_msgs/DiagnosticStatus`` for the window since the previous call (resets it)."""
        window = self._stats.take_window()
        with self._workers_lock:
            workers = list(self._workers)
        stopping = self._stop_requested.is_set()
        stopped = () if stopping else tuple(w.name for w in workers if not w.is_alive())
        params = self._params
        state = NodeState(
            name=f'{self.get_fully_qualified_name().lstrip("/")}: plane extraction',
            input_topic=self.input_topic,
            ready=self.ready.is_set(),
            stopping=stopping,
            workers=params.workers if self._parallel_workers_safe else 1,
            stopped_workers=stopped,
            worker_threads_alive=len(workers) - len(stopped),
            idle=self._idle(params),
            min_output_rate_fraction=params.min_output_rate_fraction,
            marker_mesh_stride=self._marker_stride,
            depth_image_topic=self.depth_image_topic,
        )
        return diagnostics_status(window, state, self._types)

    def _publish_diagnostics(self) -> None:
        array = self._types.DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [self.diagnostics_status()]
        self._diagnostics_pub.publish(array)

    # ---------------------------------------------------------------- lifecycle

    def stop(self, timeout: float | None = None) -> bool:
        """Ask the workers to finish their frames and exit, and join them; True once all have exited."""
        self._stop_requested.set()
        self._mailbox.close()
        self._turns.close()
        with self._workers_lock:
            workers = list(self._workers)
        deadline = None if timeout is None else time.monotonic() + timeout
        for worker in workers:
            if worker.is_alive() and worker is not threading.current_thread():
                worker.join(None if deadline is None else max(0.0, deadline - time.monotonic()))
        return not any(worker.is_alive() for worker in workers)

    def busy_workers(self) -> list[str]:
        """'worker N (what it is doing)' for each worker thread still running (after :meth:`stop` timed out)."""
        with self._workers_lock:
            workers = list(enumerate(self._workers))
        return [f'worker {index} ({self._worker_tasks[index]})' for index, worker in workers if worker.is_alive()]

    def destroy_node(self) -> None:
        """Join the workers, then destroy the node."""
        self.stop()
        super().destroy_node()


def usage() -> str:
    """The text of ``extractor --help``: topics, parameters with defaults and allowed values, how to start it."""
    lines = [
        'usage: ros2 run ppe_ros extractor [--ros-args [--params-file FILE.yaml] [-p NAME:=VALUE ...] '
        '[-r points:=TOPIC ...]]',
        '',
        'Plane extraction (PPE) on sensor_msgs/PointCloud2 clouds (organized, transposed or unorganized) and on',
        'depth images with their camera info.',
        '',
        f'  in   {INPUT_TOPIC} (sensor_msgs/PointCloud2, any layout; QoS depth 1, input_reliability;',
        '       NaN, infinite or exactly (0, 0, 0) points are no return)',
        f'       {DEPTH_IMAGE_TOPIC} (sensor_msgs/Image, 16UC1 mm or 32FC1 m, rectified; QoS as points) with',
        f'       {CAMERA_INFO_TOPIC} (sensor_msgs/CameraInfo: P, or K when P is zero; binning and ROI)',
        f"       {METADATA_TOPIC} (std_msgs/String, transient local: the Ouster driver's metadata JSON; per-beam",
        '       ray starts while ray_origin is [0, 0, 0])',
        f'  out  {LABELED_POINTS_TOPIC} (sensor_msgs/PointCloud2: x y z label rgb)',
        f'       {MARKERS_TOPIC} (visualization_msgs/MarkerArray)',
        f'       {PLANE_TABLE_TOPIC} (sensor_msgs/PointCloud2, one point per plane)',
        f'       {DIAGNOSTICS_TOPIC} (diagnostic_msgs/DiagnosticArray, about 1 Hz)',
        '  With no subscriber on any output the node idles (process_without_subscribers: false).',
        '  QoS: -p qos_overrides.<resolved topic>.<subscription|publisher>.<history|depth|reliability>:=VALUE',
        '',
        'parameters (config/extractor.yaml lists them all; change at runtime with ros2 param set):',
    ]
    for spec in PARAM_SPECS:
        default = spec.default
        if isinstance(default, bool):
            shown = str(default).lower()
        elif isinstance(default, tuple):
            shown = f'[{", ".join(map(str, default))}]'
        else:
            shown = '.inf' if default == math.inf else str(default)
        allowed = f'; {spec.constraints()}' if spec.constraints() else ''
        lines.append(f'  {spec.name} (default {shown}{allowed}): {spec.description}')
    lines += ['', 'Exit codes: 0 stopped by SIGINT/SIGTERM, 2 invalid parameters or ROS arguments.']
    return '\n'.join(lines)


def _non_ros_arguments(argv: list[str]) -> list[str]:
    """The arguments outside ``--ros-args ... [--]`` (without the program name)."""
    rest, inside = [], False
    for argument in argv[1:]:
        if argument == '--ros-args':
            inside = True
        elif inside and argument == '--':
            inside = False
        elif not inside:
            rest.append(argument)
    return rest


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run ppe_ros extractor``.

    Exit code 0 on SIGINT/SIGTERM (and for ``--help``), at any point of the start-up too; 2 on
    invalid parameters or ROS arguments (e.g. an unreadable ``--params-file``).
    """
    try:
        return _run(list(sys.argv if args is None else args))
    except KeyboardInterrupt:  # Ctrl-C before rclpy took over the signals, or a second one at the end
        return 0
    except BrokenPipeError:  # `extractor --help | head`: the reader left; no traceback, none at exit either
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


def _run(argv: list[str]) -> int:
    extra = _non_ros_arguments(argv)
    if '-h' in extra or '--help' in extra:
        print(usage())
        return 0
    if extra:
        print(
            f'extractor: warning: ignoring arguments {extra} (ROS arguments go after --ros-args; see --help)',
            file=sys.stderr,
        )
    from rclpy._rclpy_pybind11 import RCLError

    try:
        rclpy.init(args=argv)
    except RCLError as exc:
        print(f'extractor: error: invalid ROS arguments: {exc}', file=sys.stderr)
        return 2
    context = rclpy.get_default_context()
    node = None
    exit_code = 0
    try:
        node = ExtractorNode()
        if context.ok():  # else a signal stopped the start-up: an executor built on a shut-down context
            rclpy.spin(node)  # fails half-made and prints a traceback when it is collected
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as exc:
        if context.ok():  # else a signal shut the context down during the start-up: a normal stop
            print(f'extractor: error: {exc}', file=sys.stderr)
            exit_code = 2
    except Exception:
        # a SIGINT/SIGTERM during ExtractorNode.__init__ shuts the context down under it: rclpy then
        # raises (RCLError from create_publisher, InvalidHandle, ...) where the node was being built
        if context.ok():
            raise
    finally:
        # the rest of the shutdown (rclpy, the DDS participant) must not hang either: past this the
        # threads' stacks go to stderr and the process exits with code 1
        faulthandler.dump_traceback_later(STOP_TIMEOUT_S + SHUTDOWN_GRACE_S, exit=True)
        if node is not None:
            _stop_workers(node, exit_code)
            node.destroy_node()
        try:
            rclpy.try_shutdown()
        except RCLError:  # rclpy's signal handler shut the context down between try_shutdown's check and call
            pass
        faulthandler.cancel_dump_traceback_later()
    return exit_code


def _stop_workers(node: ExtractorNode, exit_code: int) -> None:
    """Stop and join the workers; one still busy after STOP_TIMEOUT_S is not waited for: the process says
    which and exits at once (rclpy must not be shut down under a thread that may still use it)."""
    if not node.stop(STOP_TIMEOUT_S):
        node.console_logger().error(
            f'stopping without waiting for {", ".join(node.busy_workers())}: still busy {STOP_TIMEOUT_S:g} s '
            'after the stop was asked (a JIT warm-up on a cold cache compiles for minutes; what it compiled so '
            'far stays cached)'
        )
        _exit_now(exit_code)


def _exit_now(exit_code: int) -> None:
    """End the process at once (threads still running are not joined), after flushing Python's and C's streams."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    try:
        ctypes.CDLL(None).fflush(None)  # rcutils writes the log lines through C's stdio
    except (OSError, TypeError, AttributeError):  # no C library to load by None (Windows)
        pass
    os._exit(exit_code)


if __name__ == '__main__':
    sys.exit(main())
