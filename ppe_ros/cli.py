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


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``ppe`` console script; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (OSError, ValueError) as exc:
        print(f'ppe {args.command}: error: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f'ppe {args.command}: interrupted', file=sys.stderr)
        return 130


if __name__ == '__main__':
    sys.exit(main())
