"""Where frames are processed: inline (``--jobs 1``), in worker processes (``--jobs N``) or on Ray.

Every executor takes frames with ``submit`` (a :class:`~concurrent.futures.Future` of the
:class:`FrameResult` per frame), holds at most ``capacity`` of them in flight, sends what it
buffers on ``flush`` and ends with ``shutdown``; ``abandon`` drops what is in flight (a second
Ctrl-C, a dead worker) and leaves the executor usable for the next input.
"""

from __future__ import annotations

import contextlib
import os
import signal
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Protocol

from ppe_ros.ros.bag.frames import FrameInput, FrameProcessor, FrameResult
from ppe_ros.ros.bag.signals import StopRequests
from ppe_ros.ros.processing import ExtractorParams

#: Frames in flight per worker process (bounds memory: each holds an input and its outputs).
IN_FLIGHT_PER_JOB = 2

#: The frame processor of a worker process (set by its initializer).
_WORKER_PROCESSOR: FrameProcessor | None = None


class TaskFailed(Exception):
    """A task of frames that failed on the executor (after its retries): the frames are lost, the run stops."""


class FrameExecutor(Protocol):
    """What :func:`~ppe_ros.ros.bag.runner.process_bag` needs of an executor."""

    capacity: int

    def submit(self, raw: FrameInput, encoding: str, convert_copy: bool) -> Future: ...

    def flush(self) -> None: ...

    def abandon(self) -> None: ...

    def shutdown(self, *, abandon: bool) -> None: ...


def set_numba_threads(count: int) -> None:
    """Threads of numba's parallel kernels in this process (0: leave numba's default)."""
    if count > 0:
        import numba

        numba.set_num_threads(min(count, numba.config.NUMBA_NUM_THREADS))


def _init_worker(params: ExtractorParams, numba_threads: int) -> None:
    """Worker process start: Ctrl-C is the main process's business; load the parameters once."""
    global _WORKER_PROCESSOR
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    set_numba_threads(numba_threads)
    _WORKER_PROCESSOR = FrameProcessor(params)


def _process_in_worker(raw: FrameInput, encoding: str, convert_copy: bool) -> FrameResult:
    assert _WORKER_PROCESSOR is not None, 'worker not initialized'
    return _WORKER_PROCESSOR.process(raw, encoding, convert_copy)


class InlineExecutor:
    """``--jobs 1``: frames are processed in this process, when submitted."""

    def __init__(self, processor: FrameProcessor, stops: StopRequests) -> None:
        self._processor = processor
        self._stops = stops
        self.capacity = IN_FLIGHT_PER_JOB

    def submit(self, raw: FrameInput, encoding: str, convert_copy: bool) -> Future:
        future: Future = Future()
        self._stops.abortable = True  # a second Ctrl-C may abandon this frame
        try:
            result = self._processor.process(raw, encoding, convert_copy)
        except KeyboardInterrupt:
            result = None
        finally:
            self._stops.abortable = False
        if result is None or (self._stops.drop and result.skip_kind == 'failed'):
            future.cancel()  # dropped by the second Ctrl-C (a failure it caused is no failure)
        else:
            future.set_result(result)
        return future

    def flush(self) -> None:
        pass

    def abandon(self) -> None:
        pass

    def shutdown(self, *, abandon: bool) -> None:
        pass


class PoolExecutor:
    """``--jobs N``: frames go to N worker processes (forkserver, or spawn where there is none)."""

    def __init__(self, jobs: int, params: ExtractorParams, numba_threads: int) -> None:
        self.capacity = IN_FLIGHT_PER_JOB * jobs
        self._jobs = jobs
        self._initargs = (params, numba_threads)
        self._pool: ProcessPoolExecutor | None = None
        self._start()

    def _start(self) -> None:
        import multiprocessing

        methods = multiprocessing.get_all_start_methods()
        context = multiprocessing.get_context('forkserver' if 'forkserver' in methods else 'spawn')
        self._pool = ProcessPoolExecutor(
            max_workers=self._jobs, mp_context=context, initializer=_init_worker, initargs=self._initargs
        )

    def submit(self, raw: FrameInput, encoding: str, convert_copy: bool) -> Future:
        if self._pool is None:  # abandoned by the previous input
            self._start()
        assert self._pool is not None
        return self._pool.submit(_process_in_worker, raw, encoding, convert_copy)

    def flush(self) -> None:
        pass

    def abandon(self) -> None:
        """Stop the workers (the frames in flight are dropped); the next submit starts new ones."""
        self.shutdown(abandon=True)

    def shutdown(self, *, abandon: bool) -> None:
        if self._pool is None:
            return
        pool, self._pool = self._pool, None
        if not abandon:
            pool.shutdown(wait=True)
            return
        processes = list(getattr(pool, '_processes', {}).values())  # the workers this run started
        pool.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            with contextlib.suppress(Exception):
                process.terminate()
        for process in processes:
            with contextlib.suppress(Exception):
                process.join(timeout=5)


def default_numba_threads(params: ExtractorParams, jobs: int) -> int:
    """Threads per worker: the ``numba_threads`` parameter, or (0) the cores shared out among the jobs."""
    if params.numba_threads > 0:
        return params.numba_threads
    if jobs <= 1:
        return 0
    cores = len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else (os.cpu_count() or 1)
    return max(1, cores // jobs)
