"""``--executor ray``: frames go, ``--task-frames`` at a time, to Ray tasks anywhere on a cluster.

This process reads the inputs and writes the outputs in input order, as with ``--jobs N``; a task
gets the raw messages of up to ``task_frames`` consecutive frames (through Ray's object store) and
returns their :class:`FrameResult`, one Ray object per frame. A task whose worker dies is retried
(``retries`` times, by Ray) and then fails as :class:`TaskFailed`. Every node needs ppe_ros
importable (the same version); the files are only read and written here.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future, InvalidStateError
from typing import Any

from ppe_ros.ros.bag.errors import BagError
from ppe_ros.ros.bag.executors import IN_FLIGHT_PER_JOB, TaskFailed, set_numba_threads
from ppe_ros.ros.bag.frames import FrameInput, FrameProcessor, FrameResult
from ppe_ros.ros.processing import ExtractorParams

#: Frames of one task by default: a few seconds of work at 0.2-0.6 s a frame, against Ray's
#: per-task cost of milliseconds, and small enough that a long bag spreads over many workers.
DEFAULT_TASK_FRAMES = 4
#: Times Ray runs a task again whose worker died (killed, out of memory, node lost).
DEFAULT_TASK_RETRIES = 3

#: The processor of this Ray worker process, kept across tasks of the same parameters.
_WORKER_PROCESSOR: FrameProcessor | None = None

#: One frame of a task: raw message (or depth image with camera info), encoding ('cdr' or 'ros1'), whether to
#: convert a copy to ROS 2.
Frame = tuple[FrameInput, str, bool]


def process_frames(params: ExtractorParams, numba_threads: int, frames: Sequence[Frame]) -> Any:
    """A Ray task's body: the :class:`FrameResult` of each frame (a lone result for one frame).

    Runs in a Ray worker process; the processor is built once per worker and parameters.
    """
    global _WORKER_PROCESSOR
    if _WORKER_PROCESSOR is None or _WORKER_PROCESSOR.params != params:
        set_numba_threads(numba_threads)
        _WORKER_PROCESSOR = FrameProcessor(params)
    results = [_WORKER_PROCESSOR.process(raw, encoding, convert_copy) for raw, encoding, convert_copy in frames]
    return results if len(results) != 1 else results[0]


def _run_task(body: Callable[..., Any], params: ExtractorParams, numba_threads: int, frames: Sequence[Frame]) -> Any:
    """What Ray runs: ``body`` (:func:`process_frames`, or a test's wrapper of it) on a task's frames."""
    return body(params, numba_threads, frames)


def _import_ray() -> Any:
    try:
        import ray
    except ImportError:
        raise BagError('--executor ray needs Ray: pip install the ray version pinned in requirements.txt') from None
    return ray


#: Seconds to wait for a cluster's address to accept a connection (ray.init itself retries for minutes).
CONNECT_TIMEOUT_S = 10.0


def check_reachable(address: str) -> None:
    """BagError unless ``host:port`` (or ``ray://host:port``) accepts a TCP connection ('auto' is Ray's to find)."""
    if address == 'auto':
        return
    host, _, port = address.removeprefix('ray://').rpartition(':')
    if not host or not port.isdigit():
        raise BagError(f"--ray-address {address!r} is not 'auto', HOST:PORT or ray://HOST:PORT")
    try:
        socket.create_connection((host.strip('[]'), int(port)), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as exc:
        raise BagError(
            f'cannot connect to the Ray cluster at {address}: {exc.strerror or exc} (is Ray running '
            'there? `ray start --head` starts one)'
        ) from None


def start_ray(address: str | None, local_cpus: int) -> bool:
    """Join the Ray cluster at ``address`` or (None) start a local one of ``local_cpus`` CPUs on 127.0.0.1.

    Returns whether this call started Ray (False: this process is connected to a Ray already, which
    is then used whatever ``address`` says).
    Keeps this process's SIGTERM handler (ray.init replaces it with one that exits at once).

    Raises:
        BagError: Ray is missing or the cluster cannot be reached.
    """
    ray = _import_ray()
    if ray.is_initialized():
        return False
    if address is not None:
        check_reachable(address)
    on_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGTERM) if on_main_thread else None
    try:
        if address is None:
            os.environ.setdefault('RAY_USAGE_STATS_ENABLED', '0')
            ray.init(
                num_cpus=local_cpus,
                include_dashboard=False,
                _node_ip_address='127.0.0.1',
                log_to_driver=False,
                configure_logging=False,
            )
        else:
            ray.init(address=address, log_to_driver=False, configure_logging=False)
    except Exception as exc:  # connection refused, bad address, ...
        where = 'start a local Ray' if address is None else f'connect to the Ray cluster at {address}'
        raise BagError(f'cannot {where}: {type(exc).__name__}: {str(exc).strip().splitlines()[0]}') from None
    finally:
        if on_main_thread and previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return True


class RayExecutor:
    """Frames in tasks of ``task_frames`` on Ray; ``capacity`` keeps two tasks per cluster CPU in flight.

    Args:
        params: the extractor parameters (put in the object store once).
        numba_threads: numba threads per task (Ray gives each task one CPU: 1 unless set).
        address: the cluster (``auto``, ``host:port``, ``ray://host:10001``) or None for a local Ray.
        local_cpus: CPUs (workers) of a local Ray.
        task_frames: frames per task (>= 1).
        retries: times a task whose worker died runs again.
        task_function: the task body (:func:`process_frames`; tests wrap it to kill a worker).
    """

    def __init__(
        self,
        params: ExtractorParams,
        *,
        numba_threads: int = 1,
        address: str | None = None,
        local_cpus: int = 1,
        task_frames: int = DEFAULT_TASK_FRAMES,
        retries: int = DEFAULT_TASK_RETRIES,
        task_function: Callable[..., Any] = process_frames,
    ) -> None:
        if task_frames < 1:
            raise BagError(f'--task-frames must be >= 1; got {task_frames}')
        if retries < 0:
            raise BagError(f'--task-retries must be >= 0; got {retries}')
        self._ray = _import_ray()
        self._started = start_ray(address, local_cpus)
        self._task_frames = task_frames
        self._retries = retries
        self._numba_threads = numba_threads
        cpus = max(1, int(self._ray.cluster_resources().get('CPU', 1)))
        self.cpus = cpus
        self.capacity = IN_FLIGHT_PER_JOB * cpus * task_frames
        self.description = f'Ray, {cpus} CPU{"s" * (cpus != 1)}, {task_frames} frame{"s" * (task_frames != 1)} a task'
        self._params = self._ray.put(params)
        self._body = task_function
        self._task = self._ray.remote(num_cpus=1, max_retries=retries)(_run_task)
        self._batch: list[tuple[Frame, Future]] = []
        self._in_flight: list[tuple[Any, Future]] = []  # (Ray object, the frame's future)
        self._tasks = 0

    def submit(self, raw: FrameInput, encoding: str, convert_copy: bool) -> Future:
        future: Future = Future()
        self._batch.append(((raw, encoding, convert_copy), future))
        if len(self._batch) >= self._task_frames:
            self.flush()
        return future

    def flush(self) -> None:
        """Send the frames buffered so far as one task."""
        if not self._batch:
            return
        batch, self._batch = self._batch, []
        self._tasks += 1
        refs = self._task.options(num_returns=len(batch)).remote(
            self._body, self._params, self._numba_threads, [frame for frame, _ in batch]
        )
        refs = list(refs) if len(batch) > 1 else [refs]
        self._in_flight = [(ref, future) for ref, future in self._in_flight if not future.done()]
        self._in_flight += [(ref, future) for ref, (_, future) in zip(refs, batch, strict=True)]
        task = self._tasks
        for ref, (_, future) in zip(refs, batch, strict=True):
            ref.future().add_done_callback(lambda done, future=future: self._deliver(done, future, task, len(batch)))

    def _deliver(self, done: Future, future: Future, task: int, frames: int) -> None:
        """Pass a frame's Ray result (or the task's failure as :class:`TaskFailed`) to its future."""
        try:
            result = done.result()
        except Exception as exc:
            reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            what = f'Ray task {task} ({frames} frame{"s" * (frames != 1)}) failed'
            if not isinstance(exc, self._ray.exceptions.RayTaskError):  # a dead worker: retried by Ray
                what += f' after {self._retries} retr{"ies" if self._retries != 1 else "y"}'
            outcome: Any = TaskFailed(f'{what}: {type(exc).__name__}: {reason}')
        else:
            outcome = (
                result
                if isinstance(result, FrameResult)
                else TaskFailed(f'Ray task {task} returned {type(result).__name__}, not a FrameResult')
            )
        with contextlib.suppress(InvalidStateError):  # dropped meanwhile (abandon)
            if isinstance(outcome, TaskFailed):
                future.set_exception(outcome)
            else:
                future.set_result(outcome)

    def abandon(self) -> None:
        """Cancel the tasks in flight (second Ctrl-C, or a task that failed): their frames are dropped."""
        for _, future in self._batch:
            future.cancel()
        self._batch = []
        in_flight, self._in_flight = self._in_flight, []
        for ref, future in in_flight:
            future.cancel()
            with contextlib.suppress(Exception):
                self._ray.cancel(ref)

    def shutdown(self, *, abandon: bool) -> None:
        if abandon:
            self.abandon()
        if self._started:
            with contextlib.suppress(Exception):
                self._ray.shutdown()
            self._started = False
