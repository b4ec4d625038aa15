"""``ppe warmup``: compile the numba kernels once into numba's on-disk cache.

The first process that calls a kernel compiles it (minutes on a busy machine with a cold cache);
every later process loads it from the cache (``__pycache__`` next to the module, or
``$NUMBA_CACHE_DIR``). ``make venv`` runs this step; in a colcon workspace run it once after
``colcon build`` (``ros2 run ppe_ros ppe warmup``), with the same user and ``NUMBA_CACHE_DIR`` as the node.
"""

from __future__ import annotations

import argparse
import sys
import time

from ppe_ros.ros.warmup import WARM_UP_SENSORS


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        'warmup',
        help='compile the numba kernels into the on-disk cache (once after an install)',
        description='Run the frame pipeline (conversion, extraction, labelled cloud, markers, plane table) on a '
        'small generated cloud once per sensor profile, so that the numba kernels are compiled and cached. '
        'Progress lines go to stderr while it compiles; the table of steps goes to stdout.',
    )
    parser.add_argument(
        '--sensor',
        action='append',
        choices=WARM_UP_SENSORS,
        default=None,
        help=f'profile to warm up (repeatable; default all: {", ".join(WARM_UP_SENSORS)})',
    )
    parser.add_argument('--quiet', action='store_true', help='no progress lines, only the table')
    parser.set_defaults(func=run)


def _progress(line: str) -> None:
    print(f'ppe warmup: {line}', file=sys.stderr, flush=True)


def _warm_up_lzf(log) -> float:
    """Compress and decompress a few bytes: the kernels of binary_compressed PCD files (``ppe extract``)."""
    from ppe_ros.io.lzf import lzf_compress, lzf_decompress

    if log:
        log('JIT warm-up: the LZF kernels of PCD files ...')
    start = time.perf_counter()
    data = bytes(range(64)) * 4
    if bytes(lzf_decompress(lzf_compress(data), len(data))) != data:
        raise RuntimeError('LZF round trip changed the data')
    return time.perf_counter() - start


def run(args: argparse.Namespace) -> int:
    from ppe_ros.ros.messages import rosbags_message_types
    from ppe_ros.ros.warmup import warm_up

    start = time.perf_counter()
    log = None if args.quiet else _progress
    if log:
        log('importing numba and the kernels ...')
    types = rosbags_message_types()
    steps = [
        (f'sensor {step.sensor}', step.seconds)
        for step in warm_up(types, sensors=args.sensor or WARM_UP_SENSORS, log=log)
    ]
    steps.append(('PCD files (LZF)', _warm_up_lzf(log)))
    from ppe_ros.ros.compressed_depth import warm_up_rvl

    if log:
        log('JIT warm-up: the RVL kernel of compressedDepth images ...')
    steps.append(('compressedDepth images (RVL)', warm_up_rvl()))
    total = time.perf_counter() - start
    print('| step | seconds |')
    print('|---|---|')
    for name, seconds in steps:
        print(f'| {name} | {seconds:.1f} |')
    print(f'| total (with imports) | {total:.1f} |')
    return 0
