"""Frames per second of the extractor node with 1, 2, ... workers on real Ouster OS-1-128 sweeps.

An in-process ExtractorNode (node defaults: lmax inf, e 0.01 m^2, min_plane_points 20) gets the three
128 x 1024 sweeps of ``../shared/data/ouster`` (frames 1795-1797, in the Ouster driver's 48-byte point
layout) in turn at ``--rate`` Hz for ``--seconds`` seconds through its subscription callback, called
directly so that the input's DDS transport (6.3 MB per cloud) does not compete for the cores; a probe
node subscribes to the plane table (``planes``), so the node builds and publishes it. Faster input
than the node can take is the point: the table shows how many frames it finishes per second, how
many it drops, its mean time per frame (from taking a cloud to publishing it), the median latency
(from handing the cloud to the node to the probe receiving its plane table) and whether the outputs
kept the input order.

``--sensor lidar`` runs the node with the lidar profile (the real-sensor path); ``--compare-tiles``
runs every worker count twice, alternated: with one greedy over the whole sweep (one tile, the
path before the tiles) and with extract_planes's default tiles, so that both are measured under the
same load.

    .venv/bin/python benchmarks/bench_node_workers.py [--workers 1 2] [--seconds 15] [--rate 20]
    .venv/bin/python benchmarks/bench_node_workers.py --sensor lidar --rate 10 --seconds 30 --compare-tiles
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
from bench_node_overhead import OUSTER, driver_message  # this directory: the driver's point layout

FRAMES = [f'OS-1-128_v2.3.0_1024x10_lb_n3_frame{n}_xyz_m.npy' for n in (1795, 1796, 1797)]


def ouster_clouds(types):
    """The three sweeps as driver-like PointCloud2 messages (bench_node_overhead's 48-byte layout)."""
    return [driver_message(np.load(OUSTER / name).astype(np.float64), types) for name in FRAMES]


def run(workers: int, seconds: float, rate: float, clouds, sensor: str = 'none') -> dict:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from ppe_ros.ros.node import ExtractorNode

    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=int(os.environ.get('ROS_DOMAIN_ID', '77')))
    executor = SingleThreadedExecutor(context=context)
    node = ExtractorNode(
        context=context,
        namespace=f'/bench_{os.getpid()}_{workers}',
        parameter_overrides=[Parameter('workers', value=workers), Parameter('sensor', value=sensor)],
    )
    probe = rclpy.create_node('probe', context=context, namespace=node.get_namespace())
    stamps: list[int] = []
    sent_at: dict[int, float] = {}
    latencies: list[float] = []

    def received(msg) -> None:
        stamps.append(msg.header.stamp.sec)
        latencies.append(time.monotonic() - sent_at[msg.header.stamp.sec])

    probe.create_subscription(
        node._types.PointCloud2, 'planes', received, QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    )
    executor.add_node(node)
    executor.add_node(probe)
    try:
        deadline = time.monotonic() + 600
        while not (node.ready.is_set() and node._plane_table_pub.get_subscription_count() > 0):
            executor.spin_once(timeout_sec=0.05)
            if time.monotonic() > deadline:
                raise RuntimeError('the node did not get ready')
        node.diagnostics_status()  # start the timing window now
        sent = 0
        start = time.monotonic()
        while time.monotonic() - start < seconds:
            template = clouds[sent % len(clouds)]  # a new message each time: a worker may still hold the last
            msg = node._types.PointCloud2(
                height=template.height,
                width=template.width,
                fields=template.fields,
                is_bigendian=template.is_bigendian,
                point_step=template.point_step,
                row_step=template.row_step,
                data=template.data,
                is_dense=template.is_dense,
            )
            msg.header.frame_id = template.header.frame_id
            msg.header.stamp.sec = sent + 1
            sent_at[sent + 1] = time.monotonic()
            node._on_cloud(msg)
            sent += 1
            next_at = start + sent / rate
            while time.monotonic() < next_at:
                executor.spin_once(timeout_sec=max(0.0, next_at - time.monotonic()))
        finished_feeding = time.monotonic()
        while (node._mailbox.pending() or node._stats.busy) and time.monotonic() - finished_feeding < 30:
            executor.spin_once(timeout_sec=0.02)
        elapsed = time.monotonic() - start
        settle = time.monotonic()
        counts = node.frame_counts()
        while len(stamps) < counts['processed'] and time.monotonic() - settle < 10:
            executor.spin_once(timeout_sec=0.02)
        status = {kv.key: kv.value for kv in node.diagnostics_status().values}
        return dict(
            workers=workers,
            sent=sent,
            processed=counts['processed'],
            dropped=counts['dropped'],
            failed=counts['failed'] + counts['skipped'],
            rate_out=counts['processed'] / elapsed,
            mean_ms=float(status['processing_time_mean_ms']),
            in_order=stamps == sorted(stamps),
            median_latency_ms=1000 * float(np.median(latencies)) if latencies else float('nan'),
            peak=status['frames_in_progress_peak'],
        )
    finally:
        executor.remove_node(probe)
        executor.remove_node(node)
        node.destroy_node()  # joins the workers
        probe.destroy_node()
        executor.shutdown(timeout_sec=1.0)
        context.try_shutdown()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--workers', type=int, nargs='+', default=[1, 2])
    parser.add_argument('--seconds', type=float, default=15.0)
    parser.add_argument('--rate', type=float, default=20.0, help='input clouds per second')
    parser.add_argument('--sensor', default='none', help="the node's sensor parameter (default none; e.g. lidar)")
    parser.add_argument(
        '--compare-tiles',
        action='store_true',
        help='each worker count with one tile (one greedy over the whole sweep) and with the default tiles',
    )
    args = parser.parse_args(argv)
    if not all((OUSTER / name).is_file() for name in FRAMES):
        print(f'needs the Ouster sweeps {FRAMES} in {OUSTER}', file=sys.stderr)
        return 1
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    from ppe_ros.benchmark.report import machine_description
    from ppe_ros.ros.messages import rclpy_message_types

    clouds = ouster_clouds(rclpy_message_types())
    from ppe_ros.core.ppe import tiles as extraction_tiles

    command = ' '.join(['python benchmarks/bench_node_workers.py', *(argv if argv is not None else sys.argv[1:])])
    print(f'machine: {machine_description()}; command: {command}; {time.strftime("%Y-%m-%d %H:%M")}\n')
    print(
        '| workers | sensor | tiles | clouds in | frames out | dropped | failed or skipped | frames/s out '
        '| mean ms per frame | median latency ms | most at once | outputs in input order |'
    )
    print('|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|')
    auto_columns = extraction_tiles.AUTO_TILE_COLUMNS
    for workers in args.workers:
        for one_tile in (True, False) if args.compare_tiles else (False,):
            # one tile: 'auto' then means one strip of the whole width (one greedy over the whole sweep)
            extraction_tiles.AUTO_TILE_COLUMNS = 2**31 if one_tile else auto_columns
            try:
                r = run(workers, args.seconds, args.rate, clouds, args.sensor)
            finally:
                extraction_tiles.AUTO_TILE_COLUMNS = auto_columns
            tiles = '1' if one_tile or args.sensor == 'none' else 'default'
            dropped = f'{r["dropped"]} ({100 * r["dropped"] / max(r["sent"], 1):.0f} %)'
            print(
                f'| {r["workers"]} | {args.sensor} | {tiles} | {r["sent"]} | {r["processed"]} | {dropped} | '
                f'{r["failed"]} | {r["rate_out"]:.2f} | {r["mean_ms"]:.0f} | {r["median_latency_ms"]:.0f} | '
                f'{r["peak"]} | {"yes" if r["in_order"] else "NO"} |',
                flush=True,
            )
    return 0


if __name__ == '__main__':
    sys.exit(main())
