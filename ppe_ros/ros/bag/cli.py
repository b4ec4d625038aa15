"""The command line of ``process_bag`` and ``ppe bag``."""

from __future__ import annotations

import argparse
import os
import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ppe_ros.ros.bag.errors import EXIT_USAGE, BagError
from ppe_ros.ros.bag.output import DEFAULT_STORAGE, STORAGES
from ppe_ros.ros.bag.report import BagOptions, format_report, report_problems
from ppe_ros.ros.bag.runner import process_bag
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


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``process_bag`` and ``ppe bag``."""
    parser.add_argument('input', metavar='IN',
                        help='input bag: rosbag2 directory (mcap or sqlite3), .mcap or .db3 file, or ROS 1 .bag')
    parser.add_argument('output', metavar='OUT', help='output rosbag2 directory (must not exist unless --force)')
    parser.add_argument('-t', '--topic', dest='topics', action='extend', nargs='+', metavar='T', default=[],
                        help='PointCloud2 topic(s) to process (default: every PointCloud2 topic)')
    parser.add_argument('--params', metavar='FILE.yaml', default=None,
                        help="the extractor node's parameter file (section 'extractor' or '/**'), e.g. "
                             'config/extractor.yaml; default: the node defaults')
    parser.add_argument('--copy-input', action='store_true', help='also copy the input topics into OUT')
    parser.add_argument('-j', '--jobs', type=_jobs, default=1, metavar='N',
                        help='worker processes (default 1; 0 = one per CPU core); output order is kept')
    parser.add_argument('--storage', choices=tuple(STORAGES), default=DEFAULT_STORAGE,
                        help=f'storage of OUT (default {DEFAULT_STORAGE})')
    parser.add_argument('--force', action='store_true', help='replace an existing OUT (never the input)')
    parser.add_argument('--progress', dest='progress', action='store_true', default=None,
                        help='always show the progress bar (default: when stderr is a terminal)')
    parser.add_argument('--no-progress', dest='progress', action='store_false', help='never show the progress bar')


def build_parser(prog: str = 'process_bag') -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog,
        description='Extract planes from every organized PointCloud2 of a bag, as the extractor node would, '
        'and write its outputs (labelled cloud, markers, plane table) to a new rosbag2.',
        epilog=f'Outputs of /ns/points: /ns/{OUTPUT_SUFFIXES["labeled_points"]}, /ns/{OUTPUT_SUFFIXES["markers"]}, '
        f'/ns/{OUTPUT_SUFFIXES["plane_table"]}. Exit codes: 0 done, 1 damaged input or stopped on an error '
        '(OUT holds the frames before it), 2 bad arguments or unusable input, 130 (143) interrupted by Ctrl-C '
        '(SIGTERM).',
    )
    add_arguments(parser)
    return parser


def options_from_args(args: argparse.Namespace) -> BagOptions:
    """:class:`BagOptions` from parsed arguments (reads the params file).

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
            warnings.append(f'params file {args.params}: ignoring unknown parameter(s) {unknown} (a typo in the '
                            f'params file?); known: {sorted(PARAM_SPEC_BY_NAME)}')
    return BagOptions(input=Path(args.input), output=Path(args.output), topics=tuple(args.topics or ()),
                      params=params, params_source=source, copy_input=args.copy_input, jobs=args.jobs,
                      storage=args.storage, force=args.force, progress=args.progress,
                      params_warnings=tuple(warnings))


def _unknown_parameter_names(names: Any) -> list[str]:
    """Names the extractor does not have (ROS's own ones excepted), as the node reports them."""
    return sorted(str(name) for name in names
                  if name not in PARAM_SPEC_BY_NAME and name not in ROS_BUILTIN_PARAMETERS
                  and not str(name).startswith('qos_overrides'))


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


def run(args: argparse.Namespace, prog: str = 'process_bag') -> int:
    """Run from parsed arguments; print the plan, warnings, summary and errors; return the exit code."""
    signals = CommandSignals()
    signals.install()
    try:
        return _run_command(args, prog, signals)
    finally:
        signals.restore()


def _run_command(args: argparse.Namespace, prog: str, signals: CommandSignals) -> int:
    try:
        report = process_bag(options_from_args(args))
    except BagError as exc:
        signals.done = True
        print(f'{prog}: error: {exc}', file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:  # before processing started
        signals.done = True
        print(f'{prog}: interrupted', file=sys.stderr)
        return 128 + (signals.signum or signal.SIGINT)
    signals.done = True
    print(format_report(report))
    problems = report_problems(report)
    label = 'error' if report.interrupted_by is None else 'stopped'
    for problem in problems:
        print(f'{prog}: {label}: {problem}', file=sys.stderr)
    if problems and report.output_path is not None:
        print(f'{prog}: {report.output_path} is a complete, valid bag of the {report.frames_processed} frames '
              'processed before that', file=sys.stderr)
    return report.exit_code


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``ros2 run ppe_ros process_bag``; returns the exit code."""
    arguments = list(sys.argv[1:] if argv is None else argv)
    if '--ros-args' in arguments:  # ros2 launch appends ROS arguments; they mean nothing here
        arguments = arguments[:arguments.index('--ros-args')]
    return run(build_parser().parse_args(arguments))
