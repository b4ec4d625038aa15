"""``process_bag``: read, process and write one bag in input order until done, damaged or stopped."""

from __future__ import annotations

import contextlib
import json
import sys
import time
from collections import Counter, deque
from collections.abc import Callable
from concurrent.futures import CancelledError, Future
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

from rosbags.rosbag2 import WriterError

from ppe_ros.ros.bag.errors import BagError, describe_read_error
from ppe_ros.ros.bag.executors import (
    IN_FLIGHT_PER_JOB,
    InlineExecutor,
    PoolExecutor,
    default_numba_threads,
    set_numba_threads,
)
from ppe_ros.ros.bag.frames import FrameProcessor, FrameResult
from ppe_ros.ros.bag.inputs import InputBag, open_input_bag, select_topics
from ppe_ros.ros.bag.output import STORAGES, OutputBag, check_paths
from ppe_ros.ros.bag.report import BagOptions, BagReport, TopicReport
from ppe_ros.ros.bag.signals import StopRequests
from ppe_ros.ros.bag.topics import OUTPUT_MSGTYPES, OUTPUT_SUFFIXES, POINTCLOUD2, output_topics
from ppe_ros.ros.processing import OutputSelection

#: Skip reasons logged per input topic and kind before the rest are only counted.
SKIP_LOG_LIMIT = 5
#: How often (s) the main process checks for a second Ctrl-C while waiting for a worker.
POLL_S = 0.1
#: Key of the output bag's metadata custom_data entry describing the run.
CUSTOM_DATA_KEY = 'ppe_ros.process_bag'


def _print(text: str, *, file: Any = None) -> None:
    from tqdm import tqdm

    tqdm.write(text, file=file or sys.stdout)


def process_bag(options: BagOptions, *, log: Callable[[str], None] | None = None,
                warn: Callable[[str], None] | None = None) -> BagReport:
    """Turn the PointCloud2 topics of a bag into the extractor's outputs in a new rosbag2.

    Args:
        options: see :class:`BagOptions`.
        log: prints progress information (default: stdout).
        warn: prints skipped frames and problems (default: stderr).

    Returns:
        The report; ``report.exit_code`` is non-zero when the input was damaged, processing stopped
        on an error or the run was interrupted (OUT then holds every frame before that).

    Raises:
        BagError: bad options or an unusable input; nothing was written.
    """
    log = log or _print
    warn = warn or (lambda text: _print(text, file=sys.stderr))
    start = time.perf_counter()
    if options.storage not in STORAGES:
        raise BagError(f'unknown storage {options.storage!r}; choose one of {", ".join(STORAGES)}')
    if options.jobs < 1:
        raise BagError(f'--jobs must be >= 1; got {options.jobs}')
    input_path, output_path = Path(options.input), Path(options.output)
    if not input_path.exists():
        raise BagError(f'no such file or directory: {input_path}')
    check_paths(input_path, output_path, options.force)

    for text in options.params_warnings:
        warn(f'warning: {text}')
    report = BagReport(options)
    bag = open_input_bag(input_path)
    with contextlib.closing(bag):
        report.input_description = bag.description
        report.notes = list(bag.notes)
        selected = select_topics(bag, options.topics)
        selection = OutputSelection.from_params(options.params)
        kinds = [kind for kind in OUTPUT_SUFFIXES if getattr(selection, kind)]
        names = output_topics(selected, kinds=kinds, reserved=selected if options.copy_input else ())
        for topic in selected:
            report.topics[topic] = TopicReport(topic, names[topic], bag.topics[topic].count)
        if bag.damage and all(entry.expected == 0 for entry in report.topics.values()):
            raise BagError(f'{input_path} is damaged before its first complete frame ({bag.damage}); '
                           'nothing to process')
        _log_plan(report, bag, log, warn, requested=bool(options.topics))
        try:
            output = OutputBag(output_path, options.storage, options.force)
        except (OSError, WriterError) as exc:
            raise BagError(f'cannot create the output next to {output_path}: {exc}') from None
        stops = StopRequests()  # also while the output is closed and moved: never left half-written
        stops.install()
        try:
            _run(bag, output, report, options, warn, stops)
        except (OSError, WriterError) as exc:  # e.g. disk full: keep what was written
            report.output_error = f'writing the output failed: {type(exc).__name__}: {exc}'
        finally:
            try:
                _finish_output(output, report, options)
            finally:
                stops.restore()
                if stops.first_signal is not None:
                    report.interrupted_by = stops.first_signal
    report.wall_seconds = time.perf_counter() - start
    return report


def _log_plan(report: BagReport, bag: InputBag, log: Callable[[str], None], warn: Callable[[str], None], *,
              requested: bool) -> None:
    for note in report.notes:
        warn(f'warning: {note}')
    total = sum(t.count or 0 for t in bag.topics.values())
    known = all(t.count is not None for t in bag.topics.values())
    count = f'{total} messages' if known else 'message count unknown'
    log(f'reading {bag.path}: {bag.description}, {len(bag.topics)} topics, {count}')
    which = 'the requested topics' if requested else f'every {POINTCLOUD2} topic'
    log(f'processing {which}:')
    for topic in report.topics.values():
        expected = '?' if topic.expected is None else topic.expected
        outputs = ', '.join(topic.outputs.values()) or '(no output enabled)'
        log(f'  {topic.input_topic} ({expected} messages) -> {outputs}')


def _run(bag: InputBag, output: OutputBag, report: BagReport, options: BagOptions,
         warn: Callable[[str], None], stops: StopRequests) -> None:
    """Read, process (inline or in workers) and write in input order until done, damaged or stopped."""
    from rosbags.typesys import Stores, get_typestore
    from tqdm import tqdm

    typestore = get_typestore(Stores.ROS2_JAZZY)
    copy_connections = {}
    if options.copy_input:
        for topic in report.topics:
            copy_connections[topic] = output.add_connection(topic, POINTCLOUD2, typestore)
    connections = {
        topic: {kind: output.add_connection(name, OUTPUT_MSGTYPES[kind], typestore)
                for kind, name in entry.outputs.items()}
        for topic, entry in report.topics.items()
    }
    output.writer.set_custom_data(CUSTOM_DATA_KEY, json.dumps({
        'input': str(options.input),
        'topics': {topic: entry.outputs for topic, entry in report.topics.items()},
        'params': options.params.as_dict(),
        'params_source': options.params_source,
    }, default=str))

    convert_copy = options.copy_input and bag.encoding == 'ros1'
    numba_threads = default_numba_threads(options.params, options.jobs)
    expected = [t.expected for t in report.topics.values()]
    total = None if any(count is None for count in expected) else sum(expected)
    bar = tqdm(total=total, unit='frame', desc='process_bag', file=sys.stderr, dynamic_ncols=True,
               disable=(None if options.progress is None else not options.progress), smoothing=0.1)
    logged: Counter[tuple[str, str]] = Counter()
    pending: deque[tuple[str, int, bytes | None, Future]] = deque()
    executor: InlineExecutor | PoolExecutor | None = None
    stream = bag.messages(list(report.topics))
    abandon = False
    try:
        if options.jobs == 1:
            set_numba_threads(numba_threads)
            executor = InlineExecutor(FrameProcessor(options.params), stops)
        else:
            executor = PoolExecutor(options.jobs, options.params, numba_threads)
        reading = True
        announced = False
        while True:
            while reading and len(pending) < IN_FLIGHT_PER_JOB * options.jobs and not stops.stop:
                try:
                    topic, timestamp, raw = next(stream)
                except StopIteration:
                    reading = False
                    break
                except Exception as exc:  # damage in the input: keep what was read before it
                    read = report.frames_read
                    report.input_error = (f'{bag.path} is damaged after {read} frame{"s" * (read != 1)}: '
                                          f'{describe_read_error(exc)}')
                    reading = False
                    break
                report.topics[topic].read += 1
                raw = bytes(raw)
                future = executor.submit(raw, bag.encoding, convert_copy)
                pending.append((topic, timestamp, raw if options.copy_input and not convert_copy else None, future))
            if stops.stop and not announced:
                announced = True
                reading = False
                busy = sum(1 for *_, future in pending if not future.done())
                extra = (f'finishing the {busy} frame{"s" * (busy != 1)} in flight, ' if busy else '')
                warn(f'interrupted: {extra}closing {options.output} with the frames done so far '
                     f'({"press Ctrl-C again to drop the frames in flight" if busy else "please wait"})')
            if not pending:
                break
            topic, timestamp, raw, future = pending[0]
            result = _wait(future, stops, report)
            if result is None:
                abandon = True
                break
            pending.popleft()
            _write_frame(output, report, topic, timestamp, raw, result, copy_connections, connections[topic])
            if result.skip_kind:
                logged[(topic, result.skip_kind)] += 1
                shown = logged[(topic, result.skip_kind)]
                if shown <= SKIP_LOG_LIMIT:
                    more = ' (further ones of this kind are only counted)' if shown == SKIP_LOG_LIMIT else ''
                    warn(f'skipped a frame of {topic} at t = {timestamp} ns ({result.skip_kind}): '
                         f'{result.reason}{more}')
            bar.update(1)
            if report.frames_skipped:
                bar.set_postfix(skipped=report.frames_skipped, refresh=False)
        if bag.damage and not report.input_error and not stops.stop and not abandon:
            read = report.frames_read
            report.input_error = f'{bag.path} is damaged ({bag.damage}); {read} frame{"s" * (read != 1)} read'
    finally:
        stream.close()
        report.dropped_in_flight = len(pending)
        if executor is not None:
            executor.shutdown(abandon=abandon or bool(pending))
        bar.close()


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
            report.worker_error = (f'a worker process died ({exc}); was it killed, e.g. for lack of memory? '
                                   'Try fewer --jobs')
            return None


def _write_frame(output: OutputBag, report: BagReport, topic: str, timestamp: int, raw: bytes | None,
                 result: FrameResult, copy_connections: dict[str, Any], connections: dict[str, Any]) -> None:
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
        problems.append(f'could not finish the output bag: {type(exc).__name__}: {exc}; the partial files are in '
                        f'{output.staging}')
    else:
        try:
            report.output_path = output.publish()
        except OSError as exc:
            problems.append(f'could not move the output to {options.output}: {exc}')
    report.output_error = '; '.join(problems) or None
