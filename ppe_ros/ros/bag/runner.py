"""``process_bag``: read, process and write one bag in input order until done, damaged or stopped."""

from __future__ import annotations

import contextlib
import json
import sys
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from concurrent.futures import CancelledError, Future
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

from rosbags.rosbag2 import WriterError
from tqdm import tqdm

from ppe_ros.ros.bag.discovery import check_output_directory
from ppe_ros.ros.bag.errors import BagError, describe_read_error
from ppe_ros.ros.bag.executors import (
    FrameExecutor,
    InlineExecutor,
    PoolExecutor,
    TaskFailed,
    default_numba_threads,
    set_numba_threads,
)
from ppe_ros.ros.bag.frames import DepthMessages, FrameInput, FrameProcessor, FrameResult, ros2_cdr
from ppe_ros.ros.bag.inputs import InputBag, open_input_bag, select_topics
from ppe_ros.ros.bag.output import STORAGES, OutputBag, check_paths
from ppe_ros.ros.bag.ray_executor import RayExecutor
from ppe_ros.ros.bag.report import BagOptions, BagReport, BagsReport, TopicReport, format_report
from ppe_ros.ros.bag.signals import StopRequests
from ppe_ros.ros.bag.topics import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    IMAGE,
    OUTPUT_MSGTYPES,
    OUTPUT_SUFFIXES,
    POINTCLOUD2,
    base_image_topic,
    camera_info_topic,
    output_topics,
)
from ppe_ros.ros.processing import OutputSelection

#: The pending entry of a copied camera info: nothing to wait for.
_COPIED: Future = Future()
_COPIED.set_result(FrameResult())
#: Message types of depth image topics (each image goes with the camera info beside it).
DEPTH_IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)
#: Skip reasons logged per input topic and kind before the rest are only counted.
SKIP_LOG_LIMIT = 5
#: How often (s) the main process checks for a second Ctrl-C while waiting for a worker.
POLL_S = 0.1
#: The executors of ``--executor``.
EXECUTORS = ('local', 'ray')
#: Key of the output bag's metadata custom_data entry describing the run.
CUSTOM_DATA_KEY = 'ppe_ros.process_bag'


def _print(text: str, *, file: Any = None) -> None:
    from tqdm import tqdm

    tqdm.write(text, file=file or sys.stdout)


def process_bag(
    options: BagOptions,
    *,
    log: Callable[[str], None] | None = None,
    warn: Callable[[str], None] | None = None,
    executor: FrameExecutor | None = None,
) -> BagReport:
    """Turn the PointCloud2 and depth image topics of a bag into the extractor's outputs in a new rosbag2.

    Args:
        options: see :class:`BagOptions`.
        log: prints progress information (default: stdout).
        warn: prints skipped frames and problems (default: stderr).
        executor: where frames go (default: as ``options`` say; see :mod:`.executors`).

    Returns:
        The report; ``report.exit_code`` is non-zero when the input was damaged, processing stopped
        on an error or the run was interrupted (OUT then holds every frame before that).

    Raises:
        BagError: bad options or an unusable input; nothing was written.
        KeyboardInterrupt: a signal while the input was opened and scanned (nothing written).
    """
    return process_bags([options], log=log, warn=warn, executor=executor, keep_going=False).reports[0]


def process_bags(
    runs: Sequence[BagOptions],
    *,
    log: Callable[[str], None] | None = None,
    warn: Callable[[str], None] | None = None,
    executor: FrameExecutor | None = None,
    output_directory: Path | None = None,
    keep_going: bool = True,
) -> BagsReport:
    """:func:`process_bag` for each of ``runs`` in turn, sharing one executor (worker pool or Ray).

    The executor, progress bar, ``jobs``, ``executor``, ``ray_address`` and ``progress`` come from
    the first run. With ``keep_going``, an input that cannot be used is reported and the others
    go on; the first Ctrl-C finishes the frames in flight, closes that input's output as a
    valid bag and starts no further input.

    Args:
        output_directory: the directory of the outputs (several inputs), created when all paths
            are checked.

    Raises:
        BagError: bad options or paths (checked for every run before anything is written), or
            Ray cannot be started; without ``keep_going``, an unusable input too.
    """
    log = log or _print
    warn = warn or (lambda text: _print(text, file=sys.stderr))
    start = time.perf_counter()
    _check_runs(runs, output_directory)
    if output_directory is not None:
        output_directory.mkdir(exist_ok=True)
    first = runs[0]
    for text in first.params_warnings:
        warn(f'warning: {text}')
    bags = BagsReport([BagReport(options) for options in runs])
    stops = StopRequests()
    executors = _Executors(first, stops, given=executor, log=log)
    progress = _Progress(first, len(runs))
    stops.install()
    try:
        for index, report in enumerate(bags.reports):
            try:
                if stops.stop:
                    break
                progress.input_number = index + 1
                _process_one(report, executors, stops, progress, log, warn)
                if keep_going and report.output_path is not None:
                    log(format_report(report))
            except BagError as exc:
                if not keep_going or executors.failed:
                    raise
                report.error = str(exc)
                warn(f'error: {report.options.input}: {exc}')
            except KeyboardInterrupt:
                if not keep_going:
                    raise
                break
    finally:
        stops.interruptible = False
        abandon = stops.drop or any(report.dropped_in_flight for report in bags.reports)
        try:
            executors.shutdown(abandon=abandon)
        finally:
            progress.close()
            stops.restore()
    bags.interrupted_by = stops.first_signal
    bags.wall_seconds = time.perf_counter() - start
    return bags


def _check_runs(runs: Sequence[BagOptions], output_directory: Path | None) -> None:
    """Every option and path of every run checked before anything is written (BagError)."""
    if not runs:
        raise BagError('no input')
    for options in runs:
        if options.storage not in STORAGES:
            raise BagError(f'unknown storage {options.storage!r}; choose one of {", ".join(STORAGES)}')
        if options.jobs < 1:
            raise BagError(f'--jobs must be >= 1; got {options.jobs}')
        if options.executor not in EXECUTORS:
            raise BagError(f'unknown executor {options.executor!r}; choose one of {", ".join(EXECUTORS)}')
        if options.task_frames < 1:
            raise BagError(f'--task-frames must be >= 1; got {options.task_frames}')
        if options.task_retries < 0:
            raise BagError(f'--task-retries must be >= 0; got {options.task_retries}')
        if len(runs) == 1 and not Path(options.input).exists():
            raise BagError(f'no such file or directory: {options.input}')
    inputs = [Path(options.input) for options in runs]
    if output_directory is None:
        check_paths(inputs[0], Path(runs[0].output), runs[0].force)
    else:
        check_output_directory(output_directory, inputs, [Path(options.output) for options in runs], runs[0].force)


class _Executors:
    """The executor of a run over inputs, made when the first usable input needs it (not for a bad one)."""

    def __init__(
        self, options: BagOptions, stops: StopRequests, *, given: FrameExecutor | None, log: Callable[[str], None]
    ) -> None:
        self._options = options
        self._stops = stops
        self._log = log
        self._shared: FrameExecutor | None = given
        self._own = given is None
        #: Whether making the executor failed (Ray unreachable): no input can go on.
        self.failed = False

    def get(self) -> FrameExecutor:
        options = self._options
        if self._shared is not None:
            return self._shared
        if options.executor == 'ray':
            try:
                return self._start_ray()
            except BagError:
                self.failed = True
                raise
        numba_threads = default_numba_threads(options.params, options.jobs)
        if options.jobs == 1:  # inline: nothing to share
            set_numba_threads(numba_threads)
            return InlineExecutor(FrameProcessor(options.params), self._stops)
        self._shared = PoolExecutor(options.jobs, options.params, numba_threads)
        return self._shared

    def _start_ray(self) -> FrameExecutor:
        options = self._options
        where = (
            f'the Ray cluster at {options.ray_address}'
            if options.ray_address
            else (f'a local Ray with {options.jobs} CPU{"s" * (options.jobs != 1)} on 127.0.0.1')
        )
        self._log(f'starting {where}' if options.ray_address is None else f'connecting to {where}')
        numba_threads = options.params.numba_threads if options.params.numba_threads > 0 else 1
        start = time.perf_counter()
        ray = RayExecutor(
            options.params,
            numba_threads=numba_threads,
            address=options.ray_address,
            local_cpus=options.jobs,
            task_frames=options.task_frames,
            retries=options.task_retries,
        )
        self._log(f'Ray ready in {time.perf_counter() - start:.1f} s: {ray.cpus} CPU{"s" * (ray.cpus != 1)}')
        self._shared = ray
        return ray

    def shutdown(self, *, abandon: bool) -> None:
        if self._shared is not None and self._own:
            self._shared.shutdown(abandon=abandon)


class _Progress:
    """The progress bar over all inputs, shown from the first input that is processed."""

    def __init__(self, options: BagOptions, inputs: int) -> None:
        self._disable = None if options.progress is None else not options.progress
        self._inputs = inputs
        self.input_number = 1
        self.bar: Any = None

    def start(self, report: BagReport) -> Any:
        """The bar, its total grown by this input's frames (unknown from then on if its count is)."""
        expected = [t.expected for t in report.topics.values()]
        frames = None if any(count is None for count in expected) else sum(expected)
        if self.bar is None:
            self.bar = tqdm(
                total=frames,
                unit='frame',
                desc='process_bag',
                file=sys.stderr,
                dynamic_ncols=True,
                disable=self._disable,
                smoothing=0.1,
            )
        elif self.bar.total is not None:
            self.bar.total = None if frames is None else self.bar.total + frames
        if self._inputs > 1:
            self.bar.set_description(f'process_bag {self.input_number}/{self._inputs}', refresh=False)
        self.bar.refresh()
        return self.bar

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _process_one(
    report: BagReport,
    executors: _Executors,
    stops: StopRequests,
    progress: _Progress,
    log: Callable[[str], None],
    warn: Callable[[str], None],
) -> None:
    """One input: open it, plan its topics, process it into its output (the report says how it went)."""
    start = time.perf_counter()
    options = report.options
    stops.interruptible = True  # opening and scanning: a signal stops at once, nothing is written yet
    bag = open_input_bag(Path(options.input))
    with contextlib.closing(bag):
        _plan(report, bag, log, warn)
        before = time.perf_counter()
        executor = executors.get()
        if options.executor == 'ray':  # starting or joining Ray is not this input's processing time
            start += time.perf_counter() - before
        report.executor_description = getattr(executor, 'description', '')
        try:
            output = OutputBag(Path(options.output), options.storage, options.force)
        except (OSError, WriterError) as exc:
            raise BagError(f'cannot create the output next to {options.output}: {exc}') from None
        stops.interruptible = False  # also while the output is closed and moved: never left half-written
        try:
            _run(bag, output, report, options, warn, stops, executor, progress.start(report))
        except (OSError, WriterError) as exc:  # e.g. disk full: keep what was written
            report.output_error = f'writing the output failed: {type(exc).__name__}: {exc}'
        finally:
            _finish_output(output, report, options)
            if stops.first_signal is not None:
                report.interrupted_by = stops.first_signal
    stops.interruptible = not stops.stop
    report.wall_seconds = time.perf_counter() - start


def _plan(report: BagReport, bag: InputBag, log: Callable[[str], None], warn: Callable[[str], None]) -> None:
    """The topics to process and their outputs, in the report; BagError when there is nothing to do."""
    options = report.options
    report.input_description = bag.description
    report.notes = list(bag.notes)
    selected = select_topics(bag, options.topics)
    selection = OutputSelection.from_params(options.params)
    kinds = [kind for kind in OUTPUT_SUFFIXES if getattr(selection, kind)]
    # a compressedDepth topic's outputs go where its image's would: beside the image topic
    bases = [base_image_topic(topic) for topic in selected]
    named = [base if bases.count(base) == 1 else topic for topic, base in zip(selected, bases, strict=True)]
    by_name = output_topics(named, kinds=kinds, reserved=selected if options.copy_input else ())
    names = {topic: by_name[name] for topic, name in zip(selected, named, strict=True)}
    for topic in selected:
        report.topics[topic] = TopicReport(topic, names[topic], bag.topics[topic].count, bag.topics[topic].msgtype)
    if bag.damage and all(entry.expected == 0 for entry in report.topics.values()):
        raise BagError(f'{options.input} is damaged before its first complete frame ({bag.damage}); nothing to process')
    _log_plan(report, bag, log, warn, requested=bool(options.topics))


def _log_plan(
    report: BagReport, bag: InputBag, log: Callable[[str], None], warn: Callable[[str], None], *, requested: bool
) -> None:
    for note in report.notes:
        warn(f'warning: {note}')
    total = sum(t.count or 0 for t in bag.topics.values())
    known = all(t.count is not None for t in bag.topics.values())
    count = f'{total} messages' if known else 'message count unknown'
    log(f'reading {bag.path}: {bag.description}, {len(bag.topics)} topics, {count}')
    which = 'the requested topics' if requested else f'every {POINTCLOUD2} topic and depth image topic'
    log(f'processing {which}:')
    for topic in report.topics.values():
        expected = '?' if topic.expected is None else topic.expected
        outputs = ', '.join(topic.outputs.values()) or '(no output enabled)'
        info = f' with {camera_info_topic(topic.input_topic)}' if topic.msgtype in DEPTH_IMAGE_TYPES else ''
        log(f'  {topic.input_topic} ({expected} messages{info}) -> {outputs}')


def _set_up_output(
    output: OutputBag, report: BagReport, options: BagOptions, info_topics: set[str]
) -> tuple[dict, dict]:
    """The output's connections (copies of the inputs and their camera infos, then outputs per input topic)
    and its custom data."""
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_JAZZY)
    copy_connections = {}
    if options.copy_input:
        for topic, entry in report.topics.items():
            copy_connections[topic] = output.add_connection(topic, entry.msgtype, typestore)
        for topic in sorted(info_topics):
            copy_connections[topic] = output.add_connection(topic, CAMERA_INFO, typestore)
    connections = {
        topic: {
            kind: output.add_connection(name, OUTPUT_MSGTYPES[kind], typestore) for kind, name in entry.outputs.items()
        }
        for topic, entry in report.topics.items()
    }
    output.writer.set_custom_data(
        CUSTOM_DATA_KEY,
        json.dumps(
            {
                'input': str(options.input),
                'topics': {topic: entry.outputs for topic, entry in report.topics.items()},
                'params': options.params.as_dict(),
                'params_source': options.params_source,
            },
            default=str,
        ),
    )
    return copy_connections, connections


def _run(
    bag: InputBag,
    output: OutputBag,
    report: BagReport,
    options: BagOptions,
    warn: Callable[[str], None],
    stops: StopRequests,
    executor: FrameExecutor,
    bar: Any,
) -> None:
    """Read, process (inline, in workers or on Ray) and write in input order until done, damaged or stopped."""
    # depth images: the camera info topics read along, and the last camera info read on each
    info_topics = {
        camera_info_topic(topic) for topic, entry in report.topics.items() if entry.msgtype in DEPTH_IMAGE_TYPES
    } - set(report.topics)
    copy_connections, connections = _set_up_output(output, report, options, info_topics)
    convert_copy = options.copy_input and bag.encoding == 'ros1'
    logged: Counter[tuple[str, str]] = Counter()
    pending: deque[tuple[str, int, bytes | None, Future]] = deque()
    latest_info: dict[str, bytes] = {}
    stream = bag.messages([*report.topics, *sorted(info_topics)])
    abandon = False
    try:
        reading = True
        announced = False
        while True:
            while reading and len(pending) < executor.capacity and not stops.stop:
                try:
                    topic, timestamp, raw = next(stream)
                except StopIteration:
                    reading = False
                    break
                except Exception as exc:  # damage in the input: keep what was read before it
                    read = report.frames_read
                    report.input_error = (
                        f'{bag.path} is damaged after {read} frame{"s" * (read != 1)}: {describe_read_error(exc)}'
                    )
                    reading = False
                    break
                raw = bytes(raw)
                if topic in info_topics:  # goes with the images after it (and, copied, in input order)
                    latest_info[topic] = raw
                    if options.copy_input:
                        pending.append((topic, timestamp, ros2_cdr(raw, bag.encoding, CAMERA_INFO), _COPIED))
                    continue
                report.topics[topic].read += 1
                frame: FrameInput = raw
                if report.topics[topic].msgtype in DEPTH_IMAGE_TYPES:
                    info = camera_info_topic(topic)
                    frame = DepthMessages(raw, latest_info.get(info), info, report.topics[topic].msgtype)
                future = executor.submit(frame, bag.encoding, convert_copy)
                pending.append((topic, timestamp, raw if options.copy_input and not convert_copy else None, future))
            executor.flush()
            if stops.stop and not announced:
                announced = True
                reading = False
                busy = sum(1 for *_, future in pending if not future.done())
                extra = f'finishing the {busy} frame{"s" * (busy != 1)} in flight, ' if busy else ''
                warn(
                    f'interrupted: {extra}closing {options.output} with the frames done so far '
                    f'({"press Ctrl-C again to drop the frames in flight" if busy else "please wait"})'
                )
            if not pending:
                break
            topic, timestamp, raw, future = pending[0]
            result = _wait(future, stops, report)
            if result is None:
                abandon = True
                break
            pending.popleft()
            if topic in info_topics:
                output.write(copy_connections[topic], timestamp, raw)
                continue
            _write_frame(output, report, topic, timestamp, raw, result, copy_connections, connections[topic])
            _log_skip(result, topic, timestamp, logged, warn)
            bar.update(1)
            if report.frames_skipped:
                bar.set_postfix(skipped=report.frames_skipped, refresh=False)
        if bag.damage and not report.input_error and not stops.stop and not abandon:
            read = report.frames_read
            report.input_error = f'{bag.path} is damaged ({bag.damage}); {read} frame{"s" * (read != 1)} read'
    finally:
        stream.close()
        report.dropped_in_flight = sum(1 for topic, *_ in pending if topic not in info_topics)
        if abandon or pending:
            executor.abandon()


def _log_skip(
    result: FrameResult, topic: str, timestamp: int, logged: Counter[tuple[str, str]], warn: Callable[[str], None]
) -> None:
    if not result.skip_kind:
        return
    logged[(topic, result.skip_kind)] += 1
    shown = logged[(topic, result.skip_kind)]
    if shown <= SKIP_LOG_LIMIT:
        more = ' (further ones of this kind are only counted)' if shown == SKIP_LOG_LIMIT else ''
        warn(f'skipped a frame of {topic} at t = {timestamp} ns ({result.skip_kind}): {result.reason}{more}')


def _wait(future: Future, stops: StopRequests, report: BagReport) -> FrameResult | None:
    """The frame's result; None when dropped (second Ctrl-C) or when the worker died."""
    while True:
        try:
            return future.result(timeout=POLL_S)
        except TimeoutError:
            if stops.drop:
                return None
        except CancelledError:
            return None
        except BrokenProcessPool as exc:
            report.worker_error = (
                f'a worker process died ({exc}); was it killed, e.g. for lack of memory? Try fewer --jobs'
            )
            return None
        except TaskFailed as exc:
            report.worker_error = f'{exc}; the frames from there on are not written'
            return None


def _write_frame(
    output: OutputBag,
    report: BagReport,
    topic: str,
    timestamp: int,
    raw: bytes | None,
    result: FrameResult,
    copy_connections: dict[str, Any],
    connections: dict[str, Any],
) -> None:
    entry = report.topics[topic]
    copy = raw if raw is not None else result.copy
    if topic in copy_connections and copy is not None:
        output.write(copy_connections[topic], timestamp, copy)
        entry.copied += 1
    if result.skip_kind:
        entry.skipped[result.skip_kind] += 1
        entry.reasons.setdefault(result.skip_kind, result.reason)
        return
    for kind, connection in connections.items():
        output.write(connection, timestamp, result.outputs[kind])
    entry.processed += 1
    entry.planes.append(result.num_planes)
    entry.seconds.append(result.seconds)


def _finish_output(output: OutputBag, report: BagReport, options: BagOptions) -> None:
    """Close the output and move it to OUT; on failure say where the partial files are."""
    report.messages_written = output.written
    problems = [report.output_error] if report.output_error else []
    try:
        output.close()
    except Exception as exc:
        problems.append(
            f'could not finish the output bag: {type(exc).__name__}: {exc}; the partial files are in {output.staging}'
        )
    else:
        try:
            report.output_path = output.publish()
        except OSError as exc:
            problems.append(f'could not move the output to {options.output}: {exc}')
    report.output_error = '; '.join(problems) or None
