"""The options of a run, what it did, and the summary printed at the end."""

from __future__ import annotations

import math
import signal
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ppe_ros.ros.bag.errors import EXIT_DAMAGED, EXIT_OK, EXIT_USAGE
from ppe_ros.ros.bag.output import DEFAULT_STORAGE
from ppe_ros.ros.bag.ray_executor import DEFAULT_TASK_FRAMES, DEFAULT_TASK_RETRIES
from ppe_ros.ros.processing import ExtractorParams


@dataclass
class BagOptions:
    """What to do: the command line as values.

    Attributes:
        input, output: IN and OUT.
        topics: input topics to process; empty = every PointCloud2 topic and depth image topic.
        params: extractor parameters (the node's; see ``ExtractorParams.from_yaml``).
        params_source: where they came from, for the report and the output's metadata.
        copy_input: also copy the input topics.
        jobs: worker processes; 1 = in this process (with ``executor='ray'`` and no address: the
            CPUs, i.e. workers, of the local Ray).
        storage: ``'mcap'`` or ``'sqlite3'``.
        force: replace an existing OUT.
        progress: show a progress bar: True, False or None (when stderr is a terminal).
        executor: ``'local'`` (``jobs`` processes on this machine) or ``'ray'``.
        ray_address: the Ray cluster to join (``auto``, ``host:port``, ``ray://host:10001``); None
            starts a local Ray on 127.0.0.1.
        task_frames: frames per Ray task.
        task_retries: times Ray runs a task again whose worker died.
    """

    input: Path
    output: Path
    topics: tuple[str, ...] = ()
    params: ExtractorParams = field(default_factory=ExtractorParams)
    params_source: str = 'defaults'
    copy_input: bool = False
    jobs: int = 1
    storage: str = DEFAULT_STORAGE
    force: bool = False
    progress: bool | None = None
    params_warnings: tuple[str, ...] = ()
    executor: str = 'local'
    ray_address: str | None = None
    task_frames: int = DEFAULT_TASK_FRAMES
    task_retries: int = DEFAULT_TASK_RETRIES


@dataclass
class TopicReport:
    """Counts of one input topic."""

    input_topic: str
    outputs: dict[str, str]
    expected: int | None
    msgtype: str = 'sensor_msgs/msg/PointCloud2'  # or sensor_msgs/msg/Image (a depth image with its camera info)
    read: int = 0
    processed: int = 0
    copied: int = 0
    skipped: Counter[str] = field(default_factory=Counter)
    reasons: dict[str, str] = field(default_factory=dict)
    planes: list[int] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)

    @property
    def skipped_total(self) -> int:
        return sum(self.skipped.values())


@dataclass
class BagReport:
    """What a run did (returned by :func:`process_bag`, printed by :func:`format_report`)."""

    options: BagOptions
    input_description: str = ''
    topics: dict[str, TopicReport] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    messages_written: int = 0
    wall_seconds: float = 0.0
    input_error: str | None = None
    worker_error: str | None = None
    output_error: str | None = None
    interrupted_by: int | None = None
    dropped_in_flight: int = 0
    output_path: Path | None = None
    #: Why the input could not be used at all (several inputs: the others go on).
    error: str | None = None
    #: Where the frames went, e.g. 'Ray, 4 CPUs' (empty: ``jobs`` local processes).
    executor_description: str = ''

    @property
    def complete(self) -> bool:
        """Whether the output holds every frame of the input."""
        return self.output_path is not None and not report_problems(self)

    @property
    def frames_read(self) -> int:
        return sum(t.read for t in self.topics.values())

    @property
    def frames_processed(self) -> int:
        return sum(t.processed for t in self.topics.values())

    @property
    def frames_skipped(self) -> int:
        return sum(t.skipped_total for t in self.topics.values())

    @property
    def frames_per_second(self) -> float:
        done = self.frames_processed + self.frames_skipped
        return done / self.wall_seconds if self.wall_seconds > 0 else 0.0

    @property
    def exit_code(self) -> int:
        if self.interrupted_by is not None:
            return 128 + int(self.interrupted_by)
        if self.input_error or self.worker_error or self.output_error or self.error:
            return EXIT_DAMAGED
        return EXIT_OK


def _mean(values: Sequence[float]) -> float:
    return math.fsum(values) / len(values) if values else math.nan


def format_report(report: BagReport) -> str:
    """The summary: a markdown table per input topic, skip reasons, and the outcome."""
    lines = [
        '| input topic | frames | processed | skipped | planes/frame mean (min-max) | s/frame mean (max) |',
        '|---|---:|---:|---:|---|---|',
    ]
    for entry in report.topics.values():
        if entry.planes:
            planes = f'{_mean(entry.planes):.1f} ({min(entry.planes)}-{max(entry.planes)})'
            seconds = f'{_mean(entry.seconds):.3f} ({max(entry.seconds):.3f})'
        else:
            planes = seconds = '-'
        lines.append(
            f'| {entry.input_topic} | {entry.read} | {entry.processed} | {entry.skipped_total} | {planes} | {seconds} |'
        )
    for entry in report.topics.values():
        for kind, count in entry.skipped.most_common():
            lines.append(f'skipped on {entry.input_topic}: {count} x {kind}, e.g. {entry.reasons[kind]}')
    done = report.frames_processed + report.frames_skipped
    jobs = report.options.jobs
    where = report.executor_description or f'{jobs} job{"s" * (jobs != 1)}'
    rate = f'{report.frames_per_second:.2f} frames/s with {where}'
    if report.output_path is not None:
        lines.append(
            f'wrote {report.output_path} ({report.options.storage}): {report.messages_written} messages; '
            f'{done} frames in {report.wall_seconds:.1f} s ({rate})'
        )
    return '\n'.join(lines)


def report_problems(report: BagReport) -> list[str]:
    """One line per reason the run did not complete normally."""
    problems = []
    if report.interrupted_by is not None:
        name = signal.Signals(report.interrupted_by).name
        dropped = (
            f'; {report.dropped_in_flight} frame{"s" * (report.dropped_in_flight != 1)} in flight dropped'
            if report.dropped_in_flight
            else ''
        )
        problems.append(f'interrupted ({name}) after {report.frames_read} frames{dropped}')
    for problem in (report.error, report.input_error, report.worker_error, report.output_error):
        if problem:
            problems.append(problem)
    return problems


@dataclass
class BagsReport:
    """What a run over several inputs did: one :class:`BagReport` per input, in input order."""

    reports: list[BagReport]
    wall_seconds: float = 0.0
    interrupted_by: int | None = None

    @property
    def exit_code(self) -> int:
        """128 + signal when interrupted; 2 when no input was usable; 1 when one had a problem; else 0."""
        if self.interrupted_by is not None:
            return 128 + int(self.interrupted_by)
        if all(report.error for report in self.reports):
            return EXIT_USAGE
        return max(report.exit_code for report in self.reports)


def _outcome(report: BagReport) -> str:
    if report.error:
        return 'not usable'
    if report.output_path is None:
        return 'not written' if report.interrupted_by is None and report.topics else 'not started'
    if report.interrupted_by is not None:
        return 'incomplete (interrupted)'
    if report.worker_error:
        return 'incomplete (worker failed)'
    if report.input_error:
        return 'damaged input: frames up to the damage'
    return 'incomplete (output failed)' if report.output_error else 'complete'


def format_summary(bags: BagsReport) -> str:
    """The table over all inputs: frames, rate and outcome of each, and the totals."""
    lines = [
        '| input | output | frames | processed | skipped | s | frames/s | outcome |',
        '|---|---|---:|---:|---:|---:|---:|---|',
    ]
    for report in bags.reports:
        output = report.output_path if report.output_path is not None else '-'
        lines.append(
            f'| {report.options.input} | {output} | {report.frames_read} | {report.frames_processed} | '
            f'{report.frames_skipped} | {report.wall_seconds:.1f} | {report.frames_per_second:.2f} | '
            f'{_outcome(report)} |'
        )
    done = sum(r.frames_processed + r.frames_skipped for r in bags.reports)
    rate = done / bags.wall_seconds if bags.wall_seconds > 0 else 0.0
    complete = sum(report.complete for report in bags.reports)
    lines.append(
        f'{len(bags.reports)} inputs, {complete} complete: {done} frames in {bags.wall_seconds:.1f} s '
        f'({rate:.2f} frames/s)'
    )
    return '\n'.join(lines)


def describe_completion(bags: BagsReport) -> str:
    """Which inputs are complete, which incomplete (a valid bag of the frames done) and which not started."""
    groups: dict[str, list[str]] = {
        'complete': [],
        'incomplete (a valid bag of the frames done)': [],
        'not usable': [],
        'not started': [],
    }
    for report in bags.reports:
        if report.error:
            key = 'not usable'
        elif report.output_path is None:
            key = 'not started'
        else:
            key = 'complete' if report.complete else 'incomplete (a valid bag of the frames done)'
        groups[key].append(str(report.options.input))
    return '; '.join(f'{key}: {", ".join(paths)}' for key, paths in groups.items() if paths)
