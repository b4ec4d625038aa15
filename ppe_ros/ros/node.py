"""``ros2 run ppe_ros extractor``: the live plane-extraction node.

Threads: the executor thread runs the subscription callback (it only drops the newest cloud into a
one-slot mailbox), the diagnostics timer and the parameter services; ``workers`` worker threads
(default 1) convert, extract and publish. A cloud that arrives while every worker is busy replaces
the waiting one and is counted as dropped, so the executor never stalls and the node always works
on the newest frame. With several workers, frames are numbered as they are taken and published in
that order (a worker that finishes early waits for the frames before its own).
The compiled kernels release the GIL (``nogil``; the parallel ones release it as numba's parallel
launches do), so the executor keeps receiving, answering parameter requests and publishing
diagnostics while the workers extract (a kernel holding the GIL froze it for the whole greedy,
about 0.2 s per 128 x 1024 sweep; ``test/test_threads.py``).

Topics (relative names, remappable):

* in ``points`` (``sensor_msgs/PointCloud2``, organized), QoS depth 1, reliability from the
  ``input_reliability`` parameter. No return: a point with a NaN or infinite coordinate, or exactly
  at (0, 0, 0) (what many drivers publish for a pixel without a return; the file loaders read it so
  too); such points get label 0 and NaN coordinates in ``planes/labeled_points``;
* out ``planes/labeled_points``, ``planes/markers``, ``planes`` (see :mod:`ppe_ros.ros.processing`)
  and ``/diagnostics`` (about 1 Hz). Outputs are reliable (they match reliable and best-effort
  subscribers); an output nobody subscribes to is not built.

Parameters: :data:`ppe_ros.ros.processing.PARAM_SPECS`, loaded with
``--ros-args --params-file config/extractor.yaml`` and changeable at runtime (an invalid value is
rejected with the reason; an integer array is accepted for ``ray_origin``; a name the node does not
have is refused naming it).

Bad input never stops the node: a cloud it cannot use is skipped (a warning per kind at most every
5 s, counted by kind), a frame whose extraction or publishing raises is counted as failed and logged
as one error line naming the frame (stamp, frame_id) and the reason; the worker goes on with the next
frame whatever the exception. Diagnostics say WARN for skipped, ERROR for failed frames and for a
worker thread that is not running.
"""

from __future__ import annotations

import array
import gc
import math
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import rclpy
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.exceptions import ParameterException, ParameterNotDeclaredException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Header

from ppe_ros.ros.messages import MessageTypes, rclpy_message_types
from ppe_ros.ros.pointcloud2 import xyz_to_pointcloud2
from ppe_ros.ros.processing import (
    PARAM_SPEC_BY_NAME,
    PARAM_SPECS,
    ROS_BUILTIN_PARAMETERS,
    ExtractorParams,
    FrameSkipped,
    OutputSelection,
    ParamSpec,
    failure_reason,
    frame_label,
    process_cloud,
)

NODE_NAME = 'extractor'
INPUT_TOPIC = 'points'
LABELED_POINTS_TOPIC = 'planes/labeled_points'
MARKERS_TOPIC = 'planes/markers'
PLANE_TABLE_TOPIC = 'planes'
DIAGNOSTICS_TOPIC = '/diagnostics'
DIAGNOSTICS_PERIOD_S = 1.0
#: At most one warning per kind of skipped frame (or failure) in this many seconds.
WARNING_THROTTLE_S = 5.0
#: The worker checks for a stop request at least this often (s).
WORKER_POLL_S = 0.1

_RELIABILITY = {'best_effort': ReliabilityPolicy.BEST_EFFORT, 'reliable': ReliabilityPolicy.RELIABLE}
_PARAMETER_TYPE = {
    'double': ParameterType.PARAMETER_DOUBLE,
    'integer': ParameterType.PARAMETER_INTEGER,
    'bool': ParameterType.PARAMETER_BOOL,
    'string': ParameterType.PARAMETER_STRING,
    'double_array': ParameterType.PARAMETER_DOUBLE_ARRAY,
}


def input_qos(reliability: str) -> QoSProfile:
    """QoS of the ``points`` subscription: keep last 1, volatile, the given reliability."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=_RELIABILITY[reliability],
                      durability=DurabilityPolicy.VOLATILE)


def output_qos() -> QoSProfile:
    """QoS of the plane outputs: reliable keep-last 1 (matches reliable and best-effort readers)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def parameter_descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """The ROS descriptor of a parameter: type, description, range or allowed values."""
    descriptor = ParameterDescriptor(
        name=spec.name,
        type=_PARAMETER_TYPE[spec.kind],
        description=spec.description,
        additional_constraints=spec.constraints(),
        read_only=spec.read_only,
    )
    if spec.kind == 'double' and spec.low is not None and spec.high is not None:
        descriptor.floating_point_range = [FloatingPointRange(from_value=float(spec.low),
                                                              to_value=float(spec.high), step=0.0)]
    elif spec.kind == 'integer' and spec.low is not None and spec.high is not None:
        descriptor.integer_range = [IntegerRange(from_value=int(spec.low), to_value=int(spec.high), step=1)]
    return descriptor


def _as_declared_type(spec: ParamSpec, value: Any) -> Any:
    """Integers given for a double (array) parameter become floats (``-p max_error_increment:=1``).

    An integer array arrives as a list (``-p ray_origin:=[0,0,1]``) or, through the parameter
    service (``ros2 param set /extractor ray_origin "[0, 0, 1]"``), as an ``array.array('q')``.
    """
    if spec.kind == 'double' and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if spec.kind == 'double_array' and isinstance(value, list | tuple | array.array) and all(
            isinstance(v, int | float) and not isinstance(v, bool) for v in value):
        return [float(v) for v in value]
    return value


def unknown_parameter_names(names: Any) -> list[str]:
    """Names given to the node (params file, ``-p``) that it does not have (ROS's own ones excepted)."""
    return sorted(
        str(name) for name in names
        if name not in PARAM_SPEC_BY_NAME and name not in ROS_BUILTIN_PARAMETERS
        and not str(name).startswith('qos_overrides')
    )


class LatestMailbox:
    """A one-slot mailbox: ``put`` replaces a waiting item (counted as dropped); ``take`` waits, bounded."""

    def __init__(self) -> None:
        self._condition = threading.Condition()
        self._item: Any = None
        self._closed = False
        self._taken = 0

    def put(self, item: Any) -> bool:
        """Leave ``item`` for the worker; True if it replaced an item nobody had taken (a dropped frame)."""
        with self._condition:
            replaced = self._item is not None
            self._item = item
            self._condition.notify()
            return replaced

    def take(self, timeout: float) -> Any:
        """The waiting item (emptying the slot), or None after ``timeout`` seconds or once closed."""
        taken = self.take_numbered(timeout)
        return None if taken is None else taken[1]

    def take_numbered(self, timeout: float) -> tuple[int, Any] | None:
        """(number, item) like :meth:`take`; items are numbered 0, 1, 2, ... in the order they are taken."""
        with self._condition:
            if self._item is None and not self._closed:
                self._condition.wait(timeout)
            item, self._item = self._item, None
            if item is None:
                return None
            self._taken += 1
            return self._taken - 1, item

    def pending(self) -> bool:
        """True while an item waits to be taken."""
        with self._condition:
            return self._item is not None

    def close(self) -> None:
        """Wake every waiting ``take``."""
        with self._condition:
            self._closed = True
            self._condition.notify_all()


class Turnstile:
    """Lets numbered holders through in number order (0, 1, 2, ...): the workers' publishing order.

    A holder with nothing to publish (a skipped or failed frame) releases its number at once; the
    others wait for their turn, publish, then release theirs.
    """

    def __init__(self) -> None:
        self._condition = threading.Condition()
        self._next = 0
        self._released: set[int] = set()
        self._closed = False

    def wait_turn(self, number: int, timeout: float | None = None) -> bool:
        """Wait until every lower number is released; False on timeout or once closed."""
        with self._condition:
            self._condition.wait_for(lambda: self._next == number or self._closed, timeout)
            return self._next == number and not self._closed

    def release(self, number: int) -> None:
        """``number`` is done (published, skipped or failed); in any order."""
        with self._condition:
            self._released.add(number)
            while self._next in self._released:
                self._released.remove(self._next)
                self._next += 1
            self._condition.notify_all()

    def close(self) -> None:
        """Release every waiter (they get False)."""
        with self._condition:
            self._closed = True
            self._condition.notify_all()


@dataclass
class FrameStats:
    """Counters for diagnostics; the workers and the executor thread share it under ``lock``."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    received: int = 0
    processed: int = 0
    dropped: int = 0
    skipped: int = 0
    failed: int = 0
    skipped_by_kind: Counter = field(default_factory=Counter)
    last_error: str = ''
    last_error_time: float = math.nan
    last_planes: int = 0
    last_frame_id: str = ''
    # since the last diagnostics report
    window_start: float = field(default_factory=time.monotonic)
    window_received: int = 0
    window_skipped: int = 0
    window_failed: int = 0
    window_dropped: int = 0
    window_times: list = field(default_factory=list)
    busy: int = 0  # frames being extracted right now
    busy_peak: int = 0  # the most at once since start


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
            self._params = self._declare_parameters()
        except ValueError:
            super().destroy_node()  # no worker yet: release the node handle and report the parameter
            raise
        self.add_pre_set_parameters_callback(self._coerce_parameters)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        self._labeled_points_pub = self.create_publisher(self._types.PointCloud2, LABELED_POINTS_TOPIC,
                                                         output_qos())
        self._markers_pub = self.create_publisher(self._types.MarkerArray, MARKERS_TOPIC, output_qos())
        self._plane_table_pub = self.create_publisher(self._types.PointCloud2, PLANE_TABLE_TOPIC,
                                                      output_qos())
        self._diagnostics_pub = self.create_publisher(self._types.DiagnosticArray, DIAGNOSTICS_TOPIC, 10)

        self._stats = FrameStats()
        self._mailbox = LatestMailbox()
        self._turns = Turnstile()
        self._warned_at: dict[str, float] = {}
        self._warned_lock = threading.Lock()
        self._suppressed: Counter = Counter()
        self._stop_requested = threading.Event()
        self.ready = threading.Event()
        """Set once the JIT warm-up is done and the workers wait for clouds."""
        self._numba_threads_applied: list[int | None] = []  # per worker: numba's count is per thread
        self._workers: list[threading.Thread] = []
        self._workers_lock = threading.Lock()
        self._parallel_workers_safe = True  # False under numba's workqueue layer (see _work)

        self._subscription_lock = threading.Lock()
        self._subscription = self._subscribe(self._params.input_reliability)
        self._diagnostics_timer = self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_diagnostics)
        self._start_workers(self._params.workers)

    # ---------------------------------------------------------------- parameters

    @property
    def params(self) -> ExtractorParams:
        """The current validated parameters (replaced as a whole on every accepted change)."""
        return self._params

    def _declare_parameters(self) -> ExtractorParams:
        overrides = getattr(self, '_parameter_overrides', {})
        values = {}
        for spec in PARAM_SPECS:
            override = overrides.get(spec.name)
            if override is not None:
                coerced = _as_declared_type(spec, override.value)
                if coerced is not override.value:
                    overrides[spec.name] = Parameter(spec.name, value=coerced)
            default = list(spec.default) if spec.kind == 'double_array' else spec.default
            try:
                value = self.declare_parameter(spec.name, default, parameter_descriptor(spec)).value
                values[spec.name] = spec.validate(value)
            except (ParameterException, ValueError) as exc:
                raise ValueError(f'invalid parameter {spec.name!r}: {exc}') from None
        try:
            params = ExtractorParams(**values)
            self._check_numba_threads(params.numba_threads)
        except ValueError as exc:
            raise ValueError(f'invalid parameters: {exc}') from None
        unknown = unknown_parameter_names(overrides)
        if unknown:
            self.get_logger().warning(
                f'ignoring unknown parameter(s) {unknown} (a typo in the params file?); '
                f'known: {sorted(PARAM_SPEC_BY_NAME)}'
            )
        return params

    @staticmethod
    def _check_numba_threads(count: int) -> None:
        import numba

        if count > numba.config.NUMBA_NUM_THREADS:
            raise ValueError(
                f'numba_threads must be 0 (all) or at most {numba.config.NUMBA_NUM_THREADS} '
                f'(NUMBA_NUM_THREADS); got {count}'
            )

    def _coerce_parameters(self, parameters: list[Parameter]) -> list[Parameter]:
        unknown = sorted(p.name for p in parameters if not self.has_parameter(p.name))
        if unknown:  # rclpy's own message would be "Invalid access to undeclared parameter(s): []"
            raise ParameterNotDeclaredException(
                f'{unknown}: the extractor has no such parameter; known: {sorted(PARAM_SPEC_BY_NAME)}')
        out = []
        for parameter in parameters:
            spec = PARAM_SPEC_BY_NAME.get(parameter.name)
            value = parameter.value
            coerced = value if spec is None else _as_declared_type(spec, value)
            out.append(parameter if coerced is value else Parameter(parameter.name, value=coerced))
        return out

    def _changes(self, parameters: list[Parameter]) -> dict[str, Any]:
        return {p.name: p.value for p in parameters if p.name in PARAM_SPEC_BY_NAME}

    def _validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        try:
            changed = self._params.replace(**self._changes(parameters))
            self._check_numba_threads(changed.numba_threads)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters: list[Parameter]) -> None:
        changes = self._changes(parameters)
        if not changes:
            return
        previous = self._params
        self._params = previous.replace(**changes)
        self.get_logger().info('parameters changed: ' + ', '.join(f'{k}={v!r}' for k, v in changes.items()))
        if self._params.input_reliability != previous.input_reliability:
            self._resubscribe(self._params.input_reliability)
        if self._params.workers > previous.workers:
            self._start_workers(self._params.workers)

    # ---------------------------------------------------------------- input

    def _subscribe(self, reliability: str):
        return self.create_subscription(self._types.PointCloud2, INPUT_TOPIC, self._on_cloud,
                                        input_qos(reliability))

    def _resubscribe(self, reliability: str) -> None:
        with self._subscription_lock:
            self.destroy_subscription(self._subscription)
            self._subscription = self._subscribe(reliability)
        self.get_logger().info(f'input {self._subscription.topic_name} now subscribed with {reliability} QoS')

    @property
    def input_topic(self) -> str:
        """Resolved name of the input topic."""
        return self._subscription.topic_name

    def _on_cloud(self, msg: Any) -> None:
        dropped = self._mailbox.put(msg)
        stats = self._stats
        with stats.lock:
            stats.received += 1
            stats.window_received += 1
            if dropped:
                stats.dropped += 1
                stats.window_dropped += 1

    # ---------------------------------------------------------------- worker

    def _start_workers(self, count: int) -> None:
        """Start worker threads up to ``count`` (a lower ``workers`` value parks the extra ones)."""
        with self._workers_lock:
            while len(self._workers) < count and not self._stop_requested.is_set():
                index = len(self._workers)
                self._numba_threads_applied.append(None)
                worker = threading.Thread(target=self._work, args=(index,),
                                          name=f'{self.get_name()}-worker-{index}', daemon=False)
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
        """Run the whole pipeline once on a small synthetic cloud (compiles or loads the numba cache)."""
        start = time.perf_counter()
        cloud = warm_up_cloud(self._types)
        frame = process_cloud(cloud, ExtractorParams(min_plane_points=4), self._types,
                              outputs=OutputSelection(True, True, True))
        # numba's compiler leaves some 600 k long-lived objects; a full garbage collection scanned
        # them all (about 50 ms, every few hundred frames). Frozen, the collector skips them.
        gc.freeze()
        self.get_logger().info(
            f'JIT warm-up done in {time.perf_counter() - start:.2f} s ({frame.planes.num_planes} planes '
            'in the warm-up cloud)'
        )

    def _check_threading_layer(self) -> None:
        """Several workers launch numba's parallel kernels at once: only the omp and tbb layers allow that."""
        import numba

        try:
            layer = numba.threading_layer()
        except ValueError:  # no parallel kernel has run yet (the warm-up failed)
            return
        if layer == 'workqueue':
            self._parallel_workers_safe = False
            if self._params.workers > 1:
                self.get_logger().error(
                    "workers > 1 needs numba's omp or tbb threading layer (numba uses 'workqueue' here, which "
                    'aborts the process when two threads launch parallel kernels at once; pip install tbb): '
                    'running one worker')

    def _active(self, index: int) -> bool:
        """Whether worker ``index`` takes frames under the current ``workers`` value."""
        return index == 0 or (index < self._params.workers and self._parallel_workers_safe)

    def _work(self, index: int) -> None:
        """Worker ``index``'s thread: it ends only on :meth:`stop` (any exception is a failed frame)."""
        while not self._stop_requested.is_set():
            try:
                self._serve(index)
            except Exception as exc:  # outside any frame (a defect): report it, wait a little, go on
                self._record_failure(f'worker {index} error: {failure_reason(exc)}')
                self._stop_requested.wait(WORKER_POLL_S)

    def _serve(self, index: int) -> None:
        """Warm up (worker 0), then take, extract and publish frames until :meth:`stop`."""
        if index == 0 and not self.ready.is_set():
            try:
                self._apply_numba_threads(index, self._params)
                self._warm_up()
                self._check_threading_layer()
            except Exception as exc:  # a failed warm-up must not kill the node
                self._record_failure(f'warm-up failed: {failure_reason(exc)}')
            self.ready.set()
            if not self._stop_requested.is_set():
                self.get_logger().info(
                    f'ready: waiting for organized PointCloud2 on {self.input_topic} '
                    f'({self._params.input_reliability}, {self._params.workers} worker(s))'
                )
        while not self._stop_requested.is_set():
            if not self.ready.is_set() or not self._active(index):
                self._stop_requested.wait(WORKER_POLL_S)  # warming up, or parked by a lower workers value
                continue
            taken = self._mailbox.take_numbered(WORKER_POLL_S)
            if taken is None:
                continue
            number, msg = taken
            try:
                self._process(index, msg, number)
            except Exception as exc:  # a defect in the node itself: count it, say why, keep serving
                self._record_failure(f'frame failed ({frame_label(msg)}): internal error: {failure_reason(exc)}')
            finally:
                self._turns.release(number)  # published, skipped or failed: the next frame may go

    def _wanted_outputs(self, params: ExtractorParams) -> OutputSelection:
        """The enabled outputs that somebody subscribes to (nobody listening: not built)."""
        return OutputSelection(
            labeled_points=(params.publish_labeled_points
                            and self._labeled_points_pub.get_subscription_count() > 0),
            markers=params.publish_markers and self._markers_pub.get_subscription_count() > 0,
            plane_table=params.publish_plane_table and self._plane_table_pub.get_subscription_count() > 0,
        )

    def _process(self, index: int, msg: Any, number: int) -> None:
        """Extract frame ``number`` (taken in that order) and publish it when the frames before it are out."""
        params = self._params
        start = time.perf_counter()
        stats = self._stats
        with stats.lock:
            stats.busy += 1
            stats.busy_peak = max(stats.busy_peak, stats.busy)
        try:
            self._apply_numba_threads(index, params)
            frame = process_cloud(msg, params, self._types, outputs=self._wanted_outputs(params))
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
            if frame.labeled_points is not None:
                self._labeled_points_pub.publish(frame.labeled_points)
            if frame.markers is not None:
                self._markers_pub.publish(frame.markers)  # CDR bytes of a MarkerArray
            if frame.plane_table is not None:
                self._plane_table_pub.publish(frame.plane_table)
        except Exception as exc:
            if self.context.ok():
                self._record_failure(f'publishing failed ({frame_label(msg)}): {failure_reason(exc)}')
            return
        elapsed = time.perf_counter() - start
        with stats.lock:
            stats.processed += 1
            stats.window_times.append(elapsed)
            stats.last_planes = frame.planes.num_planes
            stats.last_frame_id = frame.stamped.frame_id

    def _warn_throttled(self, key: str, message: str, *, error: bool = False) -> None:
        """Log ``message`` (a warning, or an error) unless one of ``key`` went out in the last 5 s.

        Never raises: the workers call it on their way to the next frame.
        """
        now = time.monotonic()
        with self._warned_lock:
            last = self._warned_at.get(key)
            if last is not None and now - last < WARNING_THROTTLE_S:
                self._suppressed[key] += 1
                return
            suppressed = self._suppressed.pop(key, 0)
            self._warned_at[key] = now
        if suppressed:
            message += f' ({suppressed} more like this in the last {now - last:.0f} s)'
        logger = self.get_logger()
        try:
            # one call site per severity: rclpy's logger raises "Logger severity cannot be changed
            # between calls" when one source line logs at two severities
            if error:
                logger.error(message)
            else:
                logger.warning(message)
        except Exception as exc:  # logging must not take a worker down
            print(f'extractor: {message} (logging failed: {type(exc).__name__}: {exc})', file=sys.stderr)

    def _record_skip(self, exc: FrameSkipped) -> None:
        stats = self._stats
        with stats.lock:
            stats.skipped += 1
            stats.window_skipped += 1
            stats.skipped_by_kind[exc.kind] += 1
            stats.last_error = f'skipped ({exc.kind}): {exc.reason}'
            stats.last_error_time = time.monotonic()
        self._warn_throttled(exc.kind, f'frame skipped: {exc.reason}')

    def _record_failure(self, message: str) -> None:
        stats = self._stats
        with stats.lock:
            stats.failed += 1
            stats.window_failed += 1
            stats.last_error = message
            stats.last_error_time = time.monotonic()
        self._warn_throttled('failure', message, error=True)

    # ---------------------------------------------------------------- diagnostics

    def frame_counts(self) -> dict[str, Any]:
        """Totals since start: received, processed, dropped, skipped, failed, skipped_by_kind, last_error."""
        stats = self._stats
        with stats.lock:
            return dict(received=stats.received, processed=stats.processed, dropped=stats.dropped,
                        skipped=stats.skipped, failed=stats.failed, skipped_by_kind=dict(stats.skipped_by_kind),
                        last_error=stats.last_error)

    def diagnostics_status(self) -> Any:
        """A ``diagnostic_msgs/DiagnosticStatus`` for the window since the previous call (resets it)."""
        stats = self._stats
        now = time.monotonic()
        with stats.lock:
            elapsed = max(now - stats.window_start, 1e-9)
            times = np.array(stats.window_times) * 1e3
            window = (stats.window_received, stats.window_skipped, stats.window_failed, stats.window_dropped)
            totals = dict(received=stats.received, processed=stats.processed, dropped=stats.dropped,
                          skipped=stats.skipped, failed=stats.failed)
            by_kind = dict(stats.skipped_by_kind)
            last_error = stats.last_error
            last_error_age = now - stats.last_error_time if stats.last_error else math.nan
            last_planes, frame_id = stats.last_planes, stats.last_frame_id
            busy, busy_peak = stats.busy, stats.busy_peak
            stats.window_start = now
            stats.window_received = stats.window_skipped = stats.window_failed = stats.window_dropped = 0
            stats.window_times = []
        received, skipped, failed, dropped = window
        with self._workers_lock:
            workers = list(self._workers)
        stopped = [] if self._stop_requested.is_set() else [w.name for w in workers if not w.is_alive()]
        status_type = self._types.DiagnosticStatus
        if stopped:
            level, message = status_type.ERROR, (f'worker thread(s) {", ".join(stopped)} not running: '
                                                 f'frames are not processed; last error: {last_error or "none"}')
        elif failed:
            level, message = status_type.ERROR, f'{failed} frame(s) failed: {last_error}'
        elif skipped:
            level, message = status_type.WARN, f'{skipped} frame(s) skipped: {last_error}'
        elif dropped:
            level, message = status_type.WARN, f'{dropped} frame(s) dropped: input faster than processing'
        elif not self.ready.is_set():
            level, message = status_type.OK, 'warming up (JIT compilation)'
        elif totals['received'] == 0:
            level, message = status_type.OK, f'waiting for input on {self.input_topic}'
        else:
            level, message = status_type.OK, 'extracting planes'
        key_value = self._types.KeyValue
        values = {
            'input_topic': self.input_topic,
            'input_rate_hz': f'{received / elapsed:.2f}',
            'processing_time_mean_ms': f'{times.mean():.1f}' if times.size else 'nan',
            'processing_time_max_ms': f'{times.max():.1f}' if times.size else 'nan',
            'frames_received': str(totals['received']),
            'frames_processed': str(totals['processed']),
            'frames_dropped': str(totals['dropped']),
            'frames_skipped': str(totals['skipped']),
            'frames_failed': str(totals['failed']),
            'skipped_by_kind': ', '.join(f'{k}={v}' for k, v in sorted(by_kind.items())),
            'last_error': last_error,
            'last_error_age_s': f'{last_error_age:.1f}',
            'planes_last_frame': str(last_planes),
            'workers': str(self._params.workers if self._parallel_workers_safe else 1),
            'frames_in_progress': str(busy),
            'frames_in_progress_peak': str(busy_peak),
            'worker_threads_alive': str(len(workers) - len(stopped)) if not self._stop_requested.is_set() else '0',
        }
        return status_type(
            level=level,
            name=f'{self.get_fully_qualified_name().lstrip("/")}: plane extraction',
            message=message,
            hardware_id=frame_id,
            values=[key_value(key=k, value=v) for k, v in values.items()],
        )

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

    def destroy_node(self) -> None:
        """Join the workers, then destroy the node."""
        self.stop()
        super().destroy_node()


def warm_up_cloud(types: MessageTypes, height: int = 12, width: int = 16) -> Any:
    """A small organized PointCloud2 of a floor and a wall (x forward, z up, 5 mm range noise) for the warm-up."""
    elevation = np.radians(np.linspace(10.0, -40.0, height))[:, None]
    azimuth = np.radians(np.linspace(-30.0, 30.0, width))[None, :]
    directions = np.stack(np.broadcast_arrays(np.cos(elevation) * np.cos(azimuth),
                                              np.cos(elevation) * np.sin(azimuth), np.sin(elevation)), -1)
    with np.errstate(divide='ignore'):
        to_wall = np.where(directions[..., 0] > 0, 4.0 / directions[..., 0], np.inf)
        to_floor = np.where(directions[..., 2] < 0, -1.0 / directions[..., 2], np.inf)
    ranges = np.minimum(to_wall, to_floor) + np.random.default_rng(0).normal(0.0, 0.005, (height, width))
    points = (directions * ranges[..., None]).astype('<f4')
    points[0, 0] = np.nan  # a no-return, as real clouds have
    return xyz_to_pointcloud2(points, header=Header(frame_id='warm_up'), msg_class=types.PointCloud2,
                              field_class=types.PointField)


def usage() -> str:
    """The text of ``extractor --help``: topics, parameters with defaults and allowed values, how to start it."""
    lines = [
        'usage: ros2 run ppe_ros extractor [--ros-args [--params-file FILE.yaml] [-p NAME:=VALUE ...] '
        '[-r points:=TOPIC ...]]',
        '',
        'Plane extraction (PPE) on organized sensor_msgs/PointCloud2 clouds.',
        '',
        f'  in   {INPUT_TOPIC} (sensor_msgs/PointCloud2, organized; QoS depth 1, input_reliability;',
        '       NaN, infinite or exactly (0, 0, 0) points are no return)',
        f'  out  {LABELED_POINTS_TOPIC} (sensor_msgs/PointCloud2: x y z label rgb)',
        f'       {MARKERS_TOPIC} (visualization_msgs/MarkerArray)',
        f'       {PLANE_TABLE_TOPIC} (sensor_msgs/PointCloud2, one point per plane)',
        f'       {DIAGNOSTICS_TOPIC} (diagnostic_msgs/DiagnosticArray, about 1 Hz)',
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


def _run(argv: list[str]) -> int:
    extra = _non_ros_arguments(argv)
    if '-h' in extra or '--help' in extra:
        print(usage())
        return 0
    if extra:
        print(f'extractor: warning: ignoring arguments {extra} (ROS arguments go after --ros-args; see --help)',
              file=sys.stderr)
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
        rclpy.spin(node)
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
        if node is not None:
            node.stop()
            node.destroy_node()
        try:
            rclpy.try_shutdown()
        except RCLError:  # rclpy's signal handler shut the context down between try_shutdown's check and call
            pass
    return exit_code


if __name__ == '__main__':
    sys.exit(main())
