"""Throughput of ``process_bag`` (frames/s) on real 128 x 1024 Ouster clouds, at ``--jobs 1`` and ``--jobs 2``.

The input bag (mcap, in a temporary directory) holds the three consecutive OS-1-128 sweeps of
``../shared/data/ouster`` (frames 1795-1797) repeated to ``--frames`` clouds, in the Ouster ROS
driver's 48-byte point layout (x y z, intensity, t, reflectivity, ring, ambient, range). Each run is
the whole command as a user sees it: open the bag, start the workers, process, write the three
outputs, close and rename; the first run is preceded by one untimed frame so that numba's cache is
compiled. Parameters: the node's defaults (``config/extractor.yaml``) unless ``--params``.

    .venv/bin/python benchmarks/bench_bag.py [--frames 12] [--jobs 1 2] [--params FILE.yaml]

Prints a markdown table: per ``--jobs``, wall time, frames/s, speed-up over the first row, and the
median seconds one frame takes inside its process (decode, extract, outputs, serialize).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from ppe_ros.io import load_scan
from ppe_ros.ros.bag import BagOptions, process_bag
from ppe_ros.ros.messages import rosbags_message_types
from ppe_ros.ros.pointcloud2 import structured_to_pointcloud2
from ppe_ros.ros.processing import ExtractorParams, process_cloud

SHARED = Path(os.environ.get('PPE_SHARED_DATA', Path(__file__).resolve().parents[2] / 'shared' / 'data'))
OUSTER_FRAMES = [f'OS-1-128_v2.3.0_1024x10_lb_n3_frame{n}_xyz_m.npy' for n in (1795, 1796, 1797)]
TOPIC = '/ouster/points'
POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'

#: The point layout of the Ouster ROS driver's cloud.
OUSTER_POINT = np.dtype(
    {
        'names': ['x', 'y', 'z', 'intensity', 't', 'reflectivity', 'ring', 'ambient', 'range'],
        'formats': ['<f4', '<f4', '<f4', '<f4', '<u4', '<u2', '<u2', '<u2', '<u4'],
        'offsets': [0, 4, 8, 16, 20, 24, 26, 28, 32],
        'itemsize': 48,
    }
)


def ouster_cloud(typestore, points: np.ndarray, index: int):
    """A driver-like PointCloud2 of ``(128, 1024, 3)`` points (NaN = no return), stamped 10 Hz."""
    types = typestore.types
    table = np.zeros(points.shape[:2], OUSTER_POINT)
    for axis, name in enumerate('xyz'):
        table[name] = points[..., axis]
    ranges = np.linalg.norm(np.nan_to_num(points), axis=-1)
    table['range'] = np.round(ranges * 1000.0).astype(np.uint32)
    table['ring'] = np.arange(points.shape[0], dtype=np.uint16)[:, None]
    stamp = types['builtin_interfaces/msg/Time'](sec=1_700_000_000 + index // 10, nanosec=(index % 10) * 100_000_000)
    header = types['std_msgs/msg/Header'](stamp=stamp, frame_id='os_sensor')
    return structured_to_pointcloud2(
        table,
        header=header,
        msg_class=types[POINTCLOUD2],
        field_class=types['sensor_msgs/msg/PointField'],
        is_dense=False,
    )


def write_input(path: Path, frames: int) -> list:
    """The input bag; returns the messages (for the warm-up)."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    sweeps = [load_scan(SHARED / 'ouster' / name).points for name in OUSTER_FRAMES]
    messages = [ouster_cloud(typestore, sweeps[i % len(sweeps)], i) for i in range(frames)]
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    connection = writer.add_connection(TOPIC, POINTCLOUD2, typestore=typestore)
    for i, msg in enumerate(messages):
        writer.write(
            connection,
            1_700_000_000_000_000_000 + i * 100_000_000 + 5_000_000,
            typestore.serialize_cdr(msg, POINTCLOUD2),
        )
    writer.close()
    return messages


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--frames', type=int, default=12, help='clouds in the bag (default 12)')
    parser.add_argument('--jobs', type=int, nargs='+', default=[1, 2], help='--jobs values to run (default 1 2)')
    parser.add_argument('--params', default=None, help="the node's params file (default: node defaults)")
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap', help='output storage')
    args = parser.parse_args(argv)
    if not (SHARED / 'ouster').is_dir():
        print(f'needs the Ouster sweeps in {SHARED / "ouster"} (set PPE_SHARED_DATA)', file=sys.stderr)
        return 2
    params = ExtractorParams.from_yaml(args.params) if args.params else ExtractorParams()
    rows = []
    with tempfile.TemporaryDirectory(prefix='bench_bag_') as tmp:
        folder = Path(tmp)
        messages = write_input(folder / 'in', args.frames)
        start = time.perf_counter()
        warm = process_cloud(messages[0], params, rosbags_message_types())
        print(f'warm-up frame: {time.perf_counter() - start:.2f} s, {warm.planes.num_planes} planes', file=sys.stderr)
        for jobs in args.jobs:
            options = BagOptions(
                folder / 'in', folder / f'out_{jobs}', params=params, jobs=jobs, storage=args.storage, progress=False
            )
            report = process_bag(options, log=lambda text: None)
            if report.exit_code != 0 or report.frames_processed != args.frames:
                print(
                    f'--jobs {jobs}: exit code {report.exit_code}, {report.frames_processed} frames processed',
                    file=sys.stderr,
                )
                return 1
            seconds = [s for topic in report.topics.values() for s in topic.seconds]
            planes = [n for topic in report.topics.values() for n in topic.planes]
            rows.append(
                (
                    jobs,
                    report.frames_processed,
                    report.wall_seconds,
                    report.frames_per_second,
                    statistics.median(seconds),
                    statistics.mean(planes),
                )
            )
    cores = len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else os.cpu_count()
    print(
        f'process_bag throughput: {args.frames} Ouster OS-1-128 clouds (128 x 1024, 48-byte points), '
        f'{args.storage} output, {cores} cores, load average {os.getloadavg()[0]:.1f} at the end'
    )
    print()
    print('| --jobs | frames | wall s | frames/s | speed-up | s/frame in worker (median) | planes/frame |')
    print('|---:|---:|---:|---:|---:|---:|---:|')
    for jobs, frames, wall, rate, median, planes in rows:
        print(
            f'| {jobs} | {frames} | {wall:.2f} | {rate:.2f} | {rate / rows[0][3]:.2f} | {median:.3f} | {planes:.0f} |'
        )
    return 0


if __name__ == '__main__':
    sys.exit(main())
