"""``ppe bag IN [IN ...] OUT``: the same as ``ros2 run ppe_ros process_bag IN [IN ...] OUT`` (ros.bag)."""

from __future__ import annotations

import argparse

from ppe_ros.ros.bag import add_arguments, run


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        'bag',
        help='extract planes from every PointCloud2 of a bag into a new rosbag2 (= process_bag)',
        description='Extract planes from every organized PointCloud2 of a bag (rosbag2 mcap/sqlite3 or ROS 1), '
        'as the extractor node would with the same parameter file, and write its outputs (labelled cloud, '
        "markers, plane table) under each input topic's namespace to a new rosbag2. Several inputs (or a "
        'directory of bags) write one output bag each into the directory OUT; --executor ray spreads the frames '
        'over a Ray cluster with byte-identical outputs. Exit codes: 0 done, '
        '1 damaged input or stopped on an error (OUT holds the frames before it), 2 bad arguments or unusable '
        'input, 130 (143) interrupted by Ctrl-C (SIGTERM).',
    )
    add_arguments(parser)
    parser.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    # from the process's own command line, signals after the run are ignored until it has exited (as process_bag)
    return run(args, prog='ppe bag', ignore_later_signals=getattr(args, 'own_command_line', False))
