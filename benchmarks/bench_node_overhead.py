"""Per-frame overhead of the extractor node beyond extraction, for a 128 x 1024 lidar cloud.

Measures exactly what :func:`ppe_ros.ros.processing.process_cloud` does around ``extract_planes``:
conversion in (PointCloud2 with an Ouster-like 48-byte point layout -> validated (H, W, 3) float64)
and building the three outputs (labelled cloud, CDR MarkerArray, plane table) with rclpy message
classes. The planes are found once, untimed.

Input (``--cloud``): by default a synthetic 128 x 1024 spinning-lidar scan of a 28-sided room with
floor and ceiling: 30 planes fitted to the true faces, 98 % of pixels planar (the worst case for
the mesh size); or a real Ouster OS-1-128 sweep from ``../shared/data/ouster`` (or
``$PPE_SHARED_DATA/ouster``) with the planes the node finds (with a params file of ``sensor: none``
about a thousand small ones, the worst case for the number of markers); or ``depth``: a generated
640 x 480 Kinect-like depth frame of a furnished room (optical frame, NaN invalid), with the planes
the node finds; or ``depth_image``: the same frame as the depth camera publishes it (a 16UC1
``sensor_msgs/Image`` in millimetres with its ``CameraInfo``), converted by the node's depth image path;
``depth_rvl`` / ``depth_png``: the same image as image_transport's compressedDepth transport sends it (RVL, or
PNG at OpenCV's default level 3 here: Pillow's ``compress_level=3``), decoded and converted by the node;
``depth_raw_lens``: the 16UC1 image as a raw, distorted camera publishes it (an Azure Kinect-like
rational_polynomial D), converted with ``depth_image_rectified: false`` (the rays are undistorted on the first
frame, whose conversion time the header line gives; the table's repeats use the cached rays).

    .venv/bin/python benchmarks/bench_node_overhead.py [--repeats 30]
        [--cloud synthetic|ouster|depth|depth_image|depth_rvl|depth_png|depth_raw_lens]
        [--params FILE.yaml]

``--params`` takes the node's params file (default: the node defaults, as in config/extractor.yaml);
e.g. ``marker_mesh_stride: 2`` shows what a coarser mesh saves, ``marker_max_triangles: 0`` what the
mesh budget saves (config/depth_camera.yaml with ``--cloud depth`` is the depth-camera case).

Prints a markdown table (median and max over the repeats, milliseconds; wall time per step and the
thread's CPU time for the total, which other processes on a busy machine do not inflate).

``--idle SECONDS``: instead, what an in-process node costs with nobody subscribed to its outputs: the
cloud at ``--rate`` Hz (default 10) into its subscription callback for SECONDS, once idling (the
default) and once with ``process_without_subscribers: true``; prints the process's CPU time per
second (cores) and the frames extracted.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from ppe_ros.core.fitting import fit_labeled_planes
from ppe_ros.core.synthetic import polygon_room_lidar_scan
from ppe_ros.ros.messages import StampedFrame, rclpy_message_types
from ppe_ros.ros.pointcloud2 import FLOAT32, structured_to_pointcloud2
from ppe_ros.ros.processing import (
    ExtractorParams,
    OutputSelection,
    ProcessedFrame,
    build_outputs,
    cloud_points,
    depth_frame_points,
    process_cloud,
)

OUSTER = Path(os.environ.get('PPE_SHARED_DATA', Path(__file__).resolve().parents[2] / 'shared' / 'data')) / 'ouster'
OUSTER_FILE = 'OS-1-128_v2.3.0_1024x10_lb_n3_frame1795_xyz_m.npy'
BUDGET_MS = 15.0

#: The point layout of the Ouster ROS driver's cloud (x y z, intensity, t, reflectivity, ring, ambient, range).
OUSTER_POINT = np.dtype(
    {
        'names': ['x', 'y', 'z', 'intensity', 't', 'reflectivity', 'ring', 'ambient', 'range'],
        'formats': ['<f4', '<f4', '<f4', '<f4', '<u4', '<u2', '<u2', '<u2', '<u4'],
        'offsets': [0, 4, 8, 16, 20, 24, 26, 28, 32],
        'itemsize': 48,
    }
)


def synthetic_room(
    height: int = 128, width: int = 1024, sides: int = 28, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Scan of a ``sides``-gon room (radius 8 m, floor -1.5 m, ceiling 2.5 m), 1 cm noise, 2 % no-returns.

    Returns ``(H, W, 3)`` points and ``(H, W)`` true face labels (0 = no return, faces 1..sides + 2).
    """
    points, labels, _, _ = polygon_room_lidar_scan(height, width, sides=sides, no_return_fraction=0.02, seed=seed)
    return points, labels


def driver_message(points: np.ndarray, types):
    """A PointCloud2 like a lidar driver publishes (48-byte points, float32 xyz)."""
    from std_msgs.msg import Header

    table = np.zeros(points.shape[:2], OUSTER_POINT)
    for index, axis in enumerate('xyz'):
        table[axis] = points[..., index]
    table['ring'] = np.arange(points.shape[0])[:, None]
    header = Header(frame_id='os_lidar')
    header.stamp.sec = 1_700_000_000
    return structured_to_pointcloud2(
        table,
        header=header,
        msg_class=types.PointCloud2,
        field_class=types.PointField,
        datatypes={'intensity': FLOAT32},
    )


def depth_camera_message(scan, types, kind: str = 'depth_image'):
    """A generated depth frame as a depth camera publishes it: a :class:`DepthFrame` of a 16UC1 image
    (millimetres, 0 = no return), or of its compressedDepth message (``kind`` depth_rvl, depth_png), and its
    CameraInfo (the generator's intrinsics)."""
    from sensor_msgs.msg import CameraInfo, CompressedImage, Image

    from ppe_ros.ros.depth_image import DepthFrame

    depth = np.nan_to_num(scan.points[..., 2], nan=0.0)
    millimetres = np.clip(np.round(depth * 1000.0), 0, 65535).astype('<u2')
    height, width = millimetres.shape
    header = driver_message(scan.points[:2, :2], types).header
    image = Image(header=header, height=height, width=width, encoding='16UC1', step=2 * width)
    image.data = millimetres.tobytes()
    if kind in ('depth_rvl', 'depth_png'):
        image = CompressedImage(header=header, format=f'16UC1; compressedDepth {kind[6:]}')
        image.data = compressed_depth_payload(millimetres, kind[6:])
    fx, fy, cx, cy = scan.intrinsics
    info = CameraInfo(header=header, height=height, width=width, distortion_model='plumb_bob')
    info.k = [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]
    info.p = [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    if kind == 'depth_raw_lens':
        info.distortion_model = 'rational_polynomial'
        info.d = list(AZURE_KINECT_LIKE_D)
    return DepthFrame(image, info)


#: k1 k2 p1 p2 k3 k4 k5 k6 of a wide depth lens with large rational coefficients that nearly cancel.
AZURE_KINECT_LIKE_D = (5.0, 3.3, -6e-5, 1e-5, 0.17, 5.3, 5.1, 0.86)


def compressed_depth_payload(millimetres: np.ndarray, codec: str) -> bytes:
    """compressed_depth_image_transport's data for 16UC1 millimetres: its 12-byte header, then RVL (the code
    of the test suite's reference encoder) or a 16-bit PNG."""
    import io
    import struct

    header = struct.pack('<iff', 0, 0.0, 0.0)
    if codec == 'rvl':
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'test'))
        from depth_frames import rvl_encode

        height, width = millimetres.shape
        return header + struct.pack('<II', width, height) + rvl_encode(millimetres)
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(millimetres).save(buffer, format='PNG', compress_level=3)
    return header + buffer.getvalue()


def idle_cost(msg, seconds: float, rate: float, process_without_subscribers: bool) -> dict:
    """CPU cores an in-process node uses while ``msg`` arrives at ``rate`` Hz and nobody subscribes."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from ppe_ros.ros.node import ExtractorNode

    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=int(os.environ.get('ROS_DOMAIN_ID', '77')))
    executor = SingleThreadedExecutor(context=context)
    node = ExtractorNode(
        context=context,
        namespace=f'/bench_idle_{os.getpid()}',
        parameter_overrides=[Parameter('process_without_subscribers', value=process_without_subscribers)],
    )
    executor.add_node(node)
    try:
        deadline = time.monotonic() + 600
        while not node.ready.is_set() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        start, cpu_start, sent = time.monotonic(), time.process_time(), 0
        while time.monotonic() - start < seconds:
            node._on_cloud(msg)
            sent += 1
            next_at = start + sent / rate
            while time.monotonic() < next_at:
                executor.spin_once(timeout_sec=max(0.0, next_at - time.monotonic()))
        cores = (time.process_time() - cpu_start) / (time.monotonic() - start)
        counts = node.frame_counts()
        return dict(
            sent=sent, processed=counts['processed'], idle=counts['idle'], dropped=counts['dropped'], cores=cores
        )
    finally:
        executor.remove_node(node)
        node.destroy_node()
        executor.shutdown(timeout_sec=1.0)
        context.try_shutdown()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--repeats', type=int, default=30)
    parser.add_argument(
        '--cloud',
        choices=('synthetic', 'ouster', 'depth', 'depth_image', 'depth_rvl', 'depth_png', 'depth_raw_lens'),
        default='synthetic',
    )
    parser.add_argument(
        '--params', default=None, metavar='FILE.yaml', help="the node's params file (default: the node defaults)"
    )
    parser.add_argument(
        '--idle',
        type=float,
        default=0.0,
        metavar='SECONDS',
        help='measure the CPU use with no subscriber instead (in-process node)',
    )
    parser.add_argument('--rate', type=float, default=10.0, help='input clouds per second for --idle')
    args = parser.parse_args(argv)
    params = ExtractorParams.from_yaml(args.params) if args.params else ExtractorParams()
    if args.cloud == 'depth_raw_lens':
        params = params.replace(depth_image_rectified=False)
    types = rclpy_message_types()
    start = time.perf_counter()
    if args.cloud == 'ouster':
        if not (OUSTER / OUSTER_FILE).is_file():
            print(f'needs {OUSTER / OUSTER_FILE}', file=sys.stderr)
            return 2
        points = np.load(OUSTER / OUSTER_FILE).astype(np.float64)
        msg = driver_message(points, types)
        # the planes the node finds with these params (its e / lmax / min_plane_points of 0 are the profile's)
        planes = process_cloud(msg, params, types, outputs=OutputSelection(False, False, False)).planes
        description = f'Ouster {OUSTER_FILE}, planes from the node (sensor {params.sensor})'
    elif args.cloud.startswith('depth'):  # what the node finds with these params
        from ppe_ros.core.synthetic_real import generate_depth_scan

        scan = generate_depth_scan(seed=0)
        points = scan.points
        msg = driver_message(points, types) if args.cloud == 'depth' else depth_camera_message(scan, types, args.cloud)
        planes = process_cloud(
            driver_message(points, types), params, types, outputs=OutputSelection(False, False, False)
        ).planes
        what = {
            'depth': 'depth frame',
            'depth_image': 'depth image (16UC1 + CameraInfo)',
            'depth_rvl': 'compressedDepth RVL image + CameraInfo',
            'depth_png': 'compressedDepth PNG image + CameraInfo',
            'depth_raw_lens': 'raw, distorted depth image (16UC1 + rational_polynomial CameraInfo)',
        }[args.cloud]
        if args.cloud != 'depth':
            what += f', {len(msg.image.data) / 1e3:.0f} kB'
        description = f'generated 640 x 480 {what} (indoor scene, seed 0), planes from the node ({params.sensor})'
    else:  # the true faces, fitted: the overhead does not depend on how the planes were found
        points, labels = synthetic_room()
        msg = driver_message(points, types)
        planes = fit_labeled_planes(cloud_points(msg, params), labels).planes
        description = 'synthetic 28-gon room + floor + ceiling, planes fitted to the true faces'
    planes_s = time.perf_counter() - start
    if args.idle and args.cloud.startswith('depth_'):
        print('--idle feeds clouds; use --cloud depth for the depth frame', file=sys.stderr)
        return 2
    if args.idle:
        height, width, _ = points.shape
        print(
            f'Cloud: {description}, {height} x {width}, at {args.rate:g} Hz for {args.idle:g} s into an in-process '
            'node with no subscriber on any output.\n'
        )
        print('| process_without_subscribers | clouds | extracted | idle | dropped | CPU (cores) |')
        print('|---|---|---|---|---|---|')
        for anyway in (False, True):
            row = idle_cost(msg, args.idle, args.rate, anyway)
            print(
                f'| {str(anyway).lower()} | {row["sent"]} | {row["processed"]} | {row["idle"]} | {row["dropped"]} | '
                f'{row["cores"]:.2f} |'
            )
        print(f'\nLoad average during the run: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores.')
        return 0
    selection = OutputSelection(True, True, True)

    rows: dict[str, list[float]] = {k: [] for k in ('convert', 'labeled_points', 'markers', 'plane_table')}
    totals, builds, cpu_totals = [], [], []
    marker_bytes = marker_stride = 0
    for repeat in range(args.repeats + 1):  # the first run compiles / loads the numba cache
        start, cpu_start = time.perf_counter(), time.thread_time()
        depth = args.cloud not in ('synthetic', 'ouster', 'depth')
        points_in = depth_frame_points(msg, params) if depth else cloud_points(msg, params)
        convert = time.perf_counter() - start
        frame = ProcessedFrame(
            header=msg.header,
            stamped=StampedFrame.of(msg.header),
            points=points_in,
            planes=planes,
            timings={'convert': convert},
        )
        build_outputs(frame, params, types, selection)
        total = time.perf_counter() - start
        cpu_total = time.thread_time() - cpu_start
        if repeat == 0:
            marker_bytes, marker_stride, first_convert = len(frame.markers), frame.marker_stride, convert
            continue
        for key in rows:
            rows[key].append(frame.timings[key] * 1e3)
        totals.append(total * 1e3)
        cpu_totals.append(cpu_total * 1e3)
        builds.append((total - convert) * 1e3)

    height, width, _ = points.shape
    print(
        f'Cloud: {description}, {height} x {width}, {planes.num_planes} planes '
        f'({100 * np.mean(planes.labels > 0):.0f} % of pixels on a plane), markers {marker_bytes / 1e6:.1f} MB; '
        f'finding the planes (not part of the overhead) {planes_s:.2f} s. {args.repeats} repeats; '
        f'params: {args.params or "node defaults"} (marker_mesh_stride {params.marker_mesh_stride}, '
        f'marker_max_triangles {params.marker_max_triangles}: mesh stride used {marker_stride}); '
        f'conversion of the first frame (untimed in the table) {first_convert * 1e3:.1f} ms.\n'
    )
    print('| step | median ms | max ms |')
    print('|---|---|---|')
    labels = {
        'convert': 'conversion in (depth image + camera info -> validated points)'
        if args.cloud.startswith('depth_')
        else 'conversion in (PointCloud2 -> validated points)',
        'labeled_points': 'labelled cloud',
        'markers': 'markers (mesh + outline + arrows, CDR)',
        'plane_table': 'plane table',
    }
    for key, values in rows.items():
        print(f'| {labels[key]} | {statistics.median(values):.2f} | {max(values):.2f} |')
    print(f'| building outputs (sum of the three) | {statistics.median(builds):.2f} | {max(builds):.2f} |')
    print(f'| **total overhead** | **{statistics.median(totals):.2f}** | {max(totals):.2f} |')
    print(
        f'| total overhead, CPU time of the thread (not inflated by other processes) | '
        f'{statistics.median(cpu_totals):.2f} | {max(cpu_totals):.2f} |'
    )
    verdict = 'within' if statistics.median(totals) <= BUDGET_MS else 'OVER'
    print(
        f'\nBudget {BUDGET_MS:.0f} ms per frame (median wall time): {verdict}. '
        f'Load average during the run: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores.'
    )
    return 0


if __name__ == '__main__':
    sys.exit(main())
