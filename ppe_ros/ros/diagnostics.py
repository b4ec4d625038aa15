"""The extractor node's frame counters, its ``/diagnostics`` status and its throttled log lines.

:class:`FrameStats` is shared by the executor thread (frames received) and the workers (frames
published, skipped, failed, idle); :func:`diagnostics_status` turns one report window of it into a
``diagnostic_msgs/DiagnosticStatus``. Rates (input, output) are over the last
:data:`RATE_WINDOW_S` seconds, so that a 1 Hz report of a 10 Hz sensor does not jump by a frame.

Levels, the first that applies: ERROR for a worker thread that is not running or a failed frame
in the report window; WARN for skipped frames, for an output rate below ``min_output_rate_fraction``
of the rate of frames that should have been extracted, and for dropped frames; else OK (warming
up, idle because nobody subscribes to any output, waiting for input, or extracting planes).
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Input and output rates are counted over this many seconds (s).
RATE_WINDOW_S = 5.0
#: The output-rate check needs at least this many frames to extract in the rate window.
MIN_FRAMES_FOR_RATE_CHECK = 3
#: At most one warning per kind of skipped frame (or failure) in this many seconds.
WARNING_THROTTLE_S = 5.0


@dataclass
class FrameStats:
    """Counters for diagnostics; the workers and the executor thread share it under ``lock``.

    Times are ``time.monotonic()`` seconds.
    """

    lock: threading.Lock = field(default_factory=threading.Lock)
    received: int = 0
    processed: int = 0  # extracted and published
    dropped: int = 0
    skipped: int = 0
    failed: int = 0
    idle: int = 0  # taken but not extracted: no output had a subscriber
    skipped_by_kind: Counter = field(default_factory=Counter)
    last_error: str = ''
    last_error_time: float = math.nan
    last_output_time: float = math.nan
    last_planes: int = 0
    last_frame_id: str = ''
    # since the last diagnostics report
    window_start: float = field(default_factory=time.monotonic)
    window_received: int = 0
    window_skipped: int = 0
    window_failed: int = 0
    window_dropped: int = 0
    window_times: list = field(default_factory=list)
    # event times within the last RATE_WINDOW_S (pruned on every report)
    received_times: deque = field(default_factory=deque)
    published_times: deque = field(default_factory=deque)
    idle_times: deque = field(default_factory=deque)
    started: float = field(default_factory=time.monotonic)
    busy: int = 0  # frames being extracted right now
    busy_peak: int = 0  # the most at once since start

    def record_received(self, dropped: bool) -> None:
        """A cloud arrived (``dropped``: it replaced one no worker had taken)."""
        now = time.monotonic()
        with self.lock:
            self.received += 1
            self.window_received += 1
            self.received_times.append(now)
            if dropped:
                self.dropped += 1
                self.window_dropped += 1

    def record_published(self, elapsed_s: float, planes: int, frame_id: str) -> None:
        """A frame's outputs went out, ``elapsed_s`` after the worker took it."""
        now = time.monotonic()
        with self.lock:
            self.processed += 1
            self.window_times.append(elapsed_s)
            self.published_times.append(now)
            self.last_output_time = now
            self.last_planes = planes
            self.last_frame_id = frame_id

    def record_idle(self) -> None:
        """A frame was taken but not extracted: nobody subscribes to any output."""
        now = time.monotonic()
        with self.lock:
            self.idle += 1
            self.idle_times.append(now)

    def record_skip(self, kind: str, reason: str) -> None:
        """A frame the extractor cannot use (kind as in ``FrameSkipped.kind``)."""
        with self.lock:
            self.skipped += 1
            self.window_skipped += 1
            self.skipped_by_kind[kind] += 1
            self.last_error = f'skipped ({kind}): {reason}'
            self.last_error_time = time.monotonic()

    def record_failure(self, message: str) -> None:
        """A frame (or the worker around it) raised."""
        with self.lock:
            self.failed += 1
            self.window_failed += 1
            self.last_error = message
            self.last_error_time = time.monotonic()

    def counts(self) -> dict[str, Any]:
        """Totals since start: received, processed, dropped, skipped, failed, idle, skipped_by_kind, last_error."""
        with self.lock:
            return dict(**self._totals(), skipped_by_kind=dict(self.skipped_by_kind), last_error=self.last_error)

    def _totals(self) -> dict[str, int]:
        """The totals since start (call with the lock held)."""
        return dict(
            received=self.received,
            processed=self.processed,
            dropped=self.dropped,
            skipped=self.skipped,
            failed=self.failed,
            idle=self.idle,
        )

    def take_window(self) -> ReportWindow:
        """The counters of the report window since the previous call, and the totals; starts a new window."""
        now = time.monotonic()
        with self.lock:
            for times in (self.received_times, self.published_times, self.idle_times):
                while times and times[0] < now - RATE_WINDOW_S:
                    times.popleft()
            rate_span = max(min(RATE_WINDOW_S, now - self.started), 1e-9)
            window = ReportWindow(
                received=self.window_received,
                skipped=self.window_skipped,
                failed=self.window_failed,
                dropped=self.window_dropped,
                times_ms=np.array(self.window_times) * 1e3,
                input_rate_hz=len(self.received_times) / rate_span,
                output_rate_hz=len(self.published_times) / rate_span,
                to_extract_in_rate_window=len(self.received_times) - len(self.idle_times),
                idle_in_rate_window=len(self.idle_times),
                totals=self._totals(),
                skipped_by_kind=dict(self.skipped_by_kind),
                last_error=self.last_error,
                last_error_age_s=now - self.last_error_time if self.last_error else math.nan,
                since_last_output_s=now - self.last_output_time,
                last_planes=self.last_planes,
                last_frame_id=self.last_frame_id,
                busy=self.busy,
                busy_peak=self.busy_peak,
            )
            self.window_start = now
            self.window_received = self.window_skipped = self.window_failed = self.window_dropped = 0
            self.window_times = []
        return window


@dataclass(frozen=True)
class ReportWindow:
    """One report window of :class:`FrameStats` (counts since the previous report; rates over the rate window)."""

    received: int
    skipped: int
    failed: int
    dropped: int
    times_ms: np.ndarray  # per published frame: taking it to its outputs going out (ms)
    input_rate_hz: float
    output_rate_hz: float
    to_extract_in_rate_window: int  # received minus idle, in the rate window
    idle_in_rate_window: int
    totals: dict[str, int]
    skipped_by_kind: dict[str, int]
    last_error: str
    last_error_age_s: float
    since_last_output_s: float  # nan before the first output
    last_planes: int
    last_frame_id: str
    busy: int
    busy_peak: int

    def output_rate_too_low(self, min_fraction: float) -> bool:
        """Whether fewer than ``min_fraction`` of the frames to extract came out (0 never warns)."""
        if min_fraction <= 0.0 or self.to_extract_in_rate_window < MIN_FRAMES_FOR_RATE_CHECK:
            return False
        expected_hz = (
            self.input_rate_hz
            * self.to_extract_in_rate_window
            / max(self.to_extract_in_rate_window + self.idle_in_rate_window, 1)
        )
        return self.output_rate_hz < min_fraction * expected_hz


@dataclass(frozen=True)
class NodeState:
    """What the diagnostics report about the node besides its counters."""

    name: str  # the status name
    input_topic: str
    ready: bool  # the JIT warm-up is done
    stopping: bool
    workers: int  # workers that take frames
    stopped_workers: tuple[str, ...]  # worker threads that should run but do not
    worker_threads_alive: int
    idle: bool  # no output has a subscriber and process_without_subscribers is false
    min_output_rate_fraction: float
    marker_mesh_stride: int  # the stride of the last marker mesh (0: none built yet)
    depth_image_topic: str = ''  # the depth image input ('': none)


def _level_and_message(window: ReportWindow, state: NodeState, status_type: type) -> tuple[int, str]:
    """The status level and its one-line message (module docstring: the first that applies)."""
    last_error = window.last_error
    if state.stopped_workers:
        return status_type.ERROR, (
            f'worker thread(s) {", ".join(state.stopped_workers)} not running: '
            f'frames are not processed; last error: {last_error or "none"}'
        )
    if window.failed:
        return status_type.ERROR, f'{window.failed} frame(s) failed: {last_error}'
    if window.skipped:
        return status_type.WARN, f'{window.skipped} frame(s) skipped: {last_error}'
    if state.ready and not state.idle and window.output_rate_too_low(state.min_output_rate_fraction):
        dropped = f'; {window.dropped} dropped in the last report' if window.dropped else ''
        return status_type.WARN, (
            f'output rate {window.output_rate_hz:.2f} Hz is below '
            f'{state.min_output_rate_fraction:g} x the input rate '
            f'{window.input_rate_hz:.2f} Hz{dropped}: processing is slower than the input'
        )
    if window.dropped:
        return status_type.WARN, f'{window.dropped} frame(s) dropped: input faster than processing'
    if not state.ready:
        return status_type.OK, 'warming up (JIT compilation)'
    if state.idle:
        return status_type.OK, (
            'idle: no subscriber on any output, frames are not extracted (process_without_subscribers: false)'
        )
    if window.totals['received'] == 0:
        topics = f'{state.input_topic} or {state.depth_image_topic}' if state.depth_image_topic else state.input_topic
        return status_type.OK, f'waiting for input on {topics}'
    return status_type.OK, 'extracting planes'


def diagnostics_status(window: ReportWindow, state: NodeState, types: Any) -> Any:
    """A ``diagnostic_msgs/DiagnosticStatus`` of ``types``' flavour for one report window."""
    status_type = types.DiagnosticStatus
    level, message = _level_and_message(window, state, status_type)
    times, totals = window.times_ms, window.totals
    values = {
        'input_topic': state.input_topic,
        'depth_image_topic': state.depth_image_topic,
        'input_rate_hz': f'{window.input_rate_hz:.2f}',
        'output_rate_hz': f'{window.output_rate_hz:.2f}',
        'time_since_last_output_s': f'{window.since_last_output_s:.1f}',
        'min_output_rate_fraction': f'{state.min_output_rate_fraction:g}',
        'idle': 'true' if state.idle else 'false',
        'processing_time_mean_ms': f'{times.mean():.1f}' if times.size else 'nan',
        'processing_time_max_ms': f'{times.max():.1f}' if times.size else 'nan',
        'frames_received': str(totals['received']),
        'frames_processed': str(totals['processed']),
        'frames_dropped': str(totals['dropped']),
        'frames_skipped': str(totals['skipped']),
        'frames_failed': str(totals['failed']),
        'frames_idle': str(totals['idle']),
        'skipped_by_kind': ', '.join(f'{k}={v}' for k, v in sorted(window.skipped_by_kind.items())),
        'last_error': window.last_error,
        'last_error_age_s': f'{window.last_error_age_s:.1f}',
        'planes_last_frame': str(window.last_planes),
        'marker_mesh_stride_last_frame': str(state.marker_mesh_stride),
        'workers': str(state.workers),
        'frames_in_progress': str(window.busy),
        'frames_in_progress_peak': str(window.busy_peak),
        'worker_threads_alive': '0' if state.stopping else str(state.worker_threads_alive),
    }
    key_value = types.KeyValue
    return status_type(
        level=level,
        name=state.name,
        message=message,
        hardware_id=window.last_frame_id,
        values=[key_value(key=k, value=v) for k, v in values.items()],
    )


class ThrottledLog:
    """Logs a warning (or an error) per key at most once every :data:`WARNING_THROTTLE_S` seconds.

    The next line of a key says how many were left out. Never raises: the workers call it on
    their way to the next frame.
    """

    def __init__(self, logger: Any, prefix: str = 'extractor') -> None:
        self._logger = logger
        self._prefix = prefix
        self.warned_at: dict[str, float] = {}
        self._suppressed: Counter = Counter()
        self._lock = threading.Lock()

    def __call__(self, key: str, message: str, *, error: bool = False) -> None:
        now = time.monotonic()
        with self._lock:
            last = self.warned_at.get(key)
            if last is not None and now - last < WARNING_THROTTLE_S:
                self._suppressed[key] += 1
                return
            suppressed = self._suppressed.pop(key, 0)
            self.warned_at[key] = now
        if suppressed:
            message += f' ({suppressed} more like this in the last {now - last:.0f} s)'
        try:
            # one call site per severity: rclpy's logger raises "Logger severity cannot be changed
            # between calls" when one source line logs at two severities
            if error:
                self._logger.error(message)
            else:
                self._logger.warning(message)
        except Exception as exc:  # logging must not take a worker down
            print(f'{self._prefix}: {message} (logging failed: {type(exc).__name__}: {exc})', file=sys.stderr)
