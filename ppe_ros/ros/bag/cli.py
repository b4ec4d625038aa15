"""The command line of ``process_bag`` and ``ppe bag``."""

from __future__ import annotations

import argparse
import os
import signal
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from ppe_ros.ros.bag.discovery import expand_inputs, output_paths
from ppe_ros.ros.bag.errors import EXIT_USAGE, BagError
from ppe_ros.ros.bag.output import DEFAULT_STORAGE, STORAGES
from ppe_ros.ros.bag.ray_executor import DEFAULT_TASK_FRAMES, DEFAULT_TASK_RETRIES
from ppe_ros.ros.bag.report import (
    BagOptions,
    BagReport,
    describe_completion,
    format_report,
    format_summary,
    report_problems,
)
from ppe_ros.ros.bag.runner import EXECUTORS, process_bag, process_bags
from ppe_ros.ros.bag.signals import CommandSignals
from ppe_ros.ros.bag.topics import OUTPUT_SUFFIXES
from ppe_ros.ros.processing import (
    PARAM_SPEC_BY_NAME,
    ROS_BUILTIN_PARAMETERS,
    ExtractorParams,
)


def _jobs(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'not an integer: {text!r}') from None
    if value < 0:
        raise argparse.ArgumentTypeError(f'must be >= 0 (0 = one per CPU core): {text!r}')
    if value == 0:
        value = len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else (os.cpu_count() or 1)
    return value


def _count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'not an integer: {text!r}') from None
    if value < 0:
        raise argparse.ArgumentTypeError(f'must be >= 0: {text!r}')
    return value


def _positive(text: str) -> int:
    value = _count(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f'must be >= 1: {text!r}')
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``process_bag`` and ``ppe bag``."""
    parser.add_argument(
        'inputs',
        metavar='IN',
        nargs='+',
        help='input bag(s): rosbag2 directory (mcap or sqlite3), .mcap or .db3 file, ROS 1 .bag, or '
        'a directory of such bags',
    )
    parser.add_argument(
        'output',
        metavar='OUT',
        help='output rosbag2 directory (must not exist unless --force); with several inputs, the '
        'directory of their output bags, one per input named after it',
    )
    parser.add_argument(
        '-t',
        '--topic',
        dest='topics',
        action='extend',
        nargs='+',
        metavar='T',
        default=[],
        help='PointCloud2 or depth image topic(s) to process (default: every PointCloud2 topic, and every '
        'sensor_msgs/Image topic, or its image_transport compressedDepth topic, with a camera_info topic beside '
        'it and "depth" in its name)',
    )
    parser.add_argument(
        '--params',
        metavar='FILE.yaml',
        default=None,
        help="the extractor node's parameter file (section 'extractor' or '/**'), e.g. "
        'config/extractor.yaml; default: the node defaults',
    )
    parser.add_argument('--copy-input', action='store_true', help='also copy the input topics into OUT')
    parser.add_argument(
        '-j',
        '--jobs',
        type=_jobs,
        default=1,
        metavar='N',
        help='worker processes (default 1; 0 = one per CPU core); output order is kept',
    )
    parser.add_argument(
        '--storage',
        choices=tuple(STORAGES),
        default=DEFAULT_STORAGE,
        help=f'storage of OUT (default {DEFAULT_STORAGE})',
    )
    parser.add_argument('--force', action='store_true', help='replace an existing OUT (never the input)')
    parser.add_argument(
        '--progress',
        dest='progress',
        action='store_true',
        default=None,
        help='always show the progress bar (default: when stderr is a terminal)',
    )
    parser.add_argument('--no-progress', dest='progress', action='store_false', help='never show the progress bar')
    parser.add_argument(
        '--executor',
        choices=EXECUTORS,
        default='local',
        help="where frames are processed: 'local' (default: --jobs processes here) or 'ray' (Ray "
        'tasks; outputs byte-identical to local)',
    )
    parser.add_argument(
        '--ray-address',
        metavar='ADDRESS',
        default=None,
        help="with --executor ray: the cluster to join ('auto', HOST:PORT or ray://HOST:10001); "
        'default: start a local Ray of --jobs CPUs on 127.0.0.1',
    )
    parser.add_argument(
        '--task-frames',
        type=_positive,
        default=DEFAULT_TASK_FRAMES,
        metavar='N',
        help=f'with --executor ray: frames per task (default {DEFAULT_TASK_FRAMES})',
    )
    parser.add_argument(
        '--task-retries',
        type=_count,
        default=DEFAULT_TASK_RETRIES,
        metavar='N',
        help='with --executor ray: times a task whose worker died runs again before the input is '
        f'reported incomplete (default {DEFAULT_TASK_RETRIES})',
    )


def build_parser(prog: str = 'process_bag') -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog,
        description='Extract planes from every PointCloud2 and depth image of a bag, as the extractor node would, '
        'and write its outputs (labelled cloud, markers, plane table) to a new rosbag2; several bags (or a '
        'directory of bags) go to one output bag each, processed here (--jobs) or on a Ray cluster.',
        epilog=f'Outputs of /ns/points: /ns/{OUTPUT_SUFFIXES["labeled_points"]}, /ns/{OUTPUT_SUFFIXES["markers"]}, '
        f'/ns/{OUTPUT_SUFFIXES["plane_table"]}. Exit codes: 0 done, 1 damaged input or stopped on an error '
        '(OUT holds the frames before it), 2 bad arguments or unusable input, 130 (143) interrupted by Ctrl-C '
        '(SIGTERM).',
    )
    add_arguments(parser)
    return parser


def options_from_args(args: argparse.Namespace) -> BagOptions:
    """:class:`BagOptions` of the first input from parsed arguments (reads the params file).

    Raises:
        BagError: unreadable or invalid params file.
    """
    params = ExtractorParams()
    source = 'defaults'
    warnings: list[str] = []
    if args.params is not None:
        try:
            params, unknown = read_params_file(args.params)
        except ValueError as exc:
            raise BagError(str(exc)) from None
        source = str(args.params)
        if unknown:  # like the node: a warning, not an error
            warnings.append(
                f'params file {args.params}: ignoring unknown parameter(s) {unknown} (a typo in the '
                f'params file?); known: {sorted(PARAM_SPEC_BY_NAME)}'
            )
    if args.executor != 'ray' and (args.ray_address is not None):
        raise BagError('--ray-address needs --executor ray')
    if args.ray_address is not None and args.jobs != 1:
        warnings.append(f'--jobs {args.jobs} is ignored with --ray-address: the tasks use the CPUs of the cluster')
    return BagOptions(
        input=Path(args.inputs[0]),
        output=Path(args.output),
        topics=tuple(args.topics or ()),
        params=params,
        params_source=source,
        copy_input=args.copy_input,
        jobs=args.jobs,
        storage=args.storage,
        force=args.force,
        progress=args.progress,
        params_warnings=tuple(warnings),
        executor=args.executor,
        ray_address=args.ray_address,
        task_frames=args.task_frames,
        task_retries=args.task_retries,
    )


def runs_from_args(args: argparse.Namespace) -> tuple[list[BagOptions], Path | None]:
    """The run of each input, and the directory of the outputs when there are several (else None).

    Several inputs, or a directory of bags, make OUT a directory with one output bag per input.

    Raises:
        BagError: bad params file, an input given twice, two inputs of the same output name.
    """
    base = options_from_args(args)
    inputs, expanded = expand_inputs(args.inputs)
    if len(inputs) == 1 and not expanded:
        return [replace(base, input=inputs[0])], None
    directory = Path(args.output)
    outputs = output_paths(inputs, directory)
    return [
        replace(base, input=source, output=output) for source, output in zip(inputs, outputs, strict=True)
    ], directory


def _unknown_parameter_names(names: Any) -> list[str]:
    """Names the extractor does not have (ROS's own ones excepted), as the node reports them."""
    return sorted(
        str(name)
        for name in names
        if name not in PARAM_SPEC_BY_NAME
        and name not in ROS_BUILTIN_PARAMETERS
        and not str(name).startswith('qos_overrides')
    )


def read_params_file(path: str | os.PathLike[str]) -> tuple[ExtractorParams, list[str]]:
    """The node's params file as :class:`ExtractorParams`, and the unknown names it ignored.

    The node warns about unknown parameters and goes on; so does ``process_bag``. Every other
    problem (unreadable file, no section, invalid value) raises ValueError.
    """
    unknown: list[str] = []

    class _IgnoringUnknown(ExtractorParams):  # from_yaml builds through cls.from_mapping
        @classmethod
        def from_mapping(cls, values: Any, *, source: str = 'parameters') -> ExtractorParams:
            if isinstance(values, dict):
                unknown.extend(_unknown_parameter_names(values))
                values = {name: value for name, value in values.items() if str(name) not in unknown}
            return ExtractorParams.from_mapping(values, source=source)

    params = _IgnoringUnknown.from_yaml(path, node_name='extractor')
    return params, unknown


def run(args: argparse.Namespace, prog: str = 'process_bag', *, ignore_later_signals: bool = False) -> int:
    """Run from parsed arguments; print the plan, warnings, summary and errors; return the exit code.

    ignore_later_signals: ignore SIGINT and SIGTERM after the run (for the process's own command line: a
    signal that arrives while Python exits would otherwise kill the process and replace the exit code
    128 + signal); else the handlers found before the run are put back.
    """
    signals = CommandSignals()
    signals.install()
    try:
        return _run_command(args, prog, signals)
    finally:
        signals.done = True
        if ignore_later_signals:
            signals.ignore()
        else:
            signals.restore()


def _run_command(args: argparse.Namespace, prog: str, signals: CommandSignals) -> int:
    try:
        runs, directory = runs_from_args(args)
        if directory is None:
            return _print_outcome(process_bag(runs[0]), prog, signals)
        bags = process_bags(runs, output_directory=directory)
    except BagError as exc:
        signals.done = True
        print(f'{prog}: error: {exc}', file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt as exc:  # before processing started
        signals.done = True
        print(f'{prog}: interrupted', file=sys.stderr)
        return 128 + (getattr(exc, 'signum', None) or signals.signum or signal.SIGINT)
    signals.done = True
    print(format_summary(bags))
    for report in bags.reports:
        label = 'error' if report.interrupted_by is None else 'stopped'
        for problem in report_problems(report):
            print(f'{prog}: {label}: {report.options.input}: {problem}', file=sys.stderr)
    if bags.interrupted_by is not None:
        print(
            f'{prog}: stopped: interrupted ({signal.Signals(bags.interrupted_by).name}); {describe_completion(bags)}',
            file=sys.stderr,
        )
    return bags.exit_code


def _print_outcome(report: BagReport, prog: str, signals: CommandSignals) -> int:
    """One input: the summary, then what went wrong; the exit code."""
    signals.done = True
    print(format_report(report))
    problems = report_problems(report)
    label = 'error' if report.interrupted_by is None else 'stopped'
    for problem in problems:
        print(f'{prog}: {label}: {problem}', file=sys.stderr)
    if problems and report.output_path is not None:
        print(
            f'{prog}: {report.output_path} is a complete, valid bag of the {report.frames_processed} frames '
            'processed before that',
            file=sys.stderr,
        )
    return report.exit_code


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``ros2 run ppe_ros process_bag``; returns the exit code."""
    arguments = list(sys.argv[1:] if argv is None else argv)
    if '--ros-args' in arguments:  # ros2 launch appends ROS arguments; they mean nothing here
        arguments = arguments[: arguments.index('--ros-args')]
    # the process's own command line: signals after the run are ignored until it has exited
    return run(build_parser().parse_args(arguments), ignore_later_signals=argv is None)
