"""``ppe``: command-line interface of ppe_ros (scans, extraction, evaluation, benchmarks).

Each subcommand lives in ``ppe_ros/commands/<name>.py`` and exposes ``register(subparsers)``;
only subcommands listed in ``SUBCOMMANDS`` exist, so nothing unfinished is advertised.
"""

from __future__ import annotations

import argparse
import importlib
import sys

SUBCOMMANDS: tuple[str, ...] = (
    'info',
    'dataset',
    'eval',
    'tune',
    'score',
    'extract',
    'demo',
    'bag',
    'warmup',
)


def build_parser() -> argparse.ArgumentParser:
    """The ``ppe`` argument parser with every registered subcommand."""
    parser = argparse.ArgumentParser(
        prog='ppe',
        description='Probabilistic Plane Extraction (PPE) for organized 3-D scans.',
    )
    sub = parser.add_subparsers(dest='command', metavar='COMMAND', required=True)
    for name in SUBCOMMANDS:
        importlib.import_module(f'ppe_ros.commands.{name}').register(sub)
    return parser


def error_line(exc: BaseException) -> str:
    """An exception as one line of text (white space runs, newlines included, become one space)."""
    text = ' '.join(str(exc).split())
    if isinstance(exc, OSError) and exc.filename is not None and str(exc.filename) not in text:
        text = f'{exc.filename}: {text}'
    return text or type(exc).__name__


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``ppe`` console script; returns the process exit code."""
    try:
        parser = build_parser()  # imports the subcommands' modules (numpy, numba, rosbags): about 0.5 s
    except KeyboardInterrupt:
        print('ppe: interrupted', file=sys.stderr)
        return 130
    args = parser.parse_args(argv)
    args.own_command_line = argv is None  # the process's own: a subcommand may keep its signal handlers to exit
    try:
        return int(args.func(args) or 0)
    except (OSError, ValueError) as exc:  # ScanFileError is a ValueError: bad input files and arguments
        print(f'ppe {args.command}: error: {error_line(exc)}', file=sys.stderr)
        return 2
    except MemoryError as exc:
        print(
            f'ppe {args.command}: error: out of memory ({error_line(exc)}); the input is too large for this machine',
            file=sys.stderr,
        )
        return 2
    except KeyboardInterrupt:
        print(f'ppe {args.command}: interrupted', file=sys.stderr)
        return 130


if __name__ == '__main__':
    sys.exit(main())
