"""JIT warm-up: the whole frame pipeline once per sensor profile on small generated clouds.

The numba kernels compile on their first call and go to numba's on-disk cache (``cache=True``:
``__pycache__`` next to each module, or ``$NUMBA_CACHE_DIR``); a later process loads them in well
under a second. The extractor node warms up before it takes its first frame; ``ppe warmup`` does
the same for every profile once after an install, so that the first start of the node (or of
``ppe extract``, ``ppe bag``) does not compile for minutes. Progress goes to ``log`` while it runs:
one line per step and a "still compiling" line every ``tick_s`` seconds.

Nothing here imports rclpy: the clouds are built with the message classes passed in (rclpy's or a
rosbags typestore's; the kernels are the same).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ppe_ros.ros.messages import MessageTypes
from ppe_ros.ros.pointcloud2 import xyz_to_pointcloud2
from ppe_ros.ros.processing import ExtractorParams, OutputSelection, process_cloud

#: The profiles ``ppe warmup`` compiles for (each takes its own kernels' paths).
WARM_UP_SENSORS: tuple[str, ...] = ('none', 'lidar', 'depth_camera')
#: A "still compiling" line this often (s).
TICK_S = 15.0


def warm_up_header(types: MessageTypes) -> Any:
    """A ``std_msgs/Header`` of ``types``' flavour: stamp 0, frame_id ``warm_up``."""
    if types.flavour == 'rclpy':
        from std_msgs.msg import Header

        return Header(frame_id='warm_up')
    store = types.typestore.types
    return store['std_msgs/msg/Header'](
        stamp=store['builtin_interfaces/msg/Time'](sec=0, nanosec=0), frame_id='warm_up'
    )


def warm_up_cloud(types: MessageTypes, height: int = 12, width: int = 16, *, header: Any = None) -> Any:
    """A small organized PointCloud2 of a floor and a wall (x forward, z up, 5 mm range noise) for the warm-up."""
    elevation = np.radians(np.linspace(10.0, -40.0, height))[:, None]
    azimuth = np.radians(np.linspace(-30.0, 30.0, width))[None, :]
    directions = np.stack(
        np.broadcast_arrays(
            np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)
        ),
        -1,
    )
    with np.errstate(divide='ignore'):
        to_wall = np.where(directions[..., 0] > 0, 4.0 / directions[..., 0], np.inf)
        to_floor = np.where(directions[..., 2] < 0, -1.0 / directions[..., 2], np.inf)
    ranges = np.minimum(to_wall, to_floor) + np.random.default_rng(0).normal(0.0, 0.005, (height, width))
    points = (directions * ranges[..., None]).astype('<f4')
    points[0, 0] = np.nan  # a no-return, as real clouds have
    return xyz_to_pointcloud2(
        points,
        header=warm_up_header(types) if header is None else header,
        msg_class=types.PointCloud2,
        field_class=types.PointField,
    )


@dataclass(frozen=True)
class WarmUpStep:
    """One warm-up run: the sensor profile, its seconds and the planes found in the warm-up cloud."""

    sensor: str
    seconds: float
    planes: int


class _Ticker:
    """Calls ``log`` every ``period_s`` seconds from a thread of its own while a step compiles."""

    def __init__(self, log: Callable[[str], None], period_s: float) -> None:
        self._log = log
        self._period_s = period_s
        self._stop = threading.Event()
        self._start = time.perf_counter()
        self._what = ''
        self._thread = threading.Thread(target=self._run, name='warm-up-ticker', daemon=True)

    def __enter__(self) -> _Ticker:
        if self._period_s > 0:
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

    def step(self, what: str) -> None:
        self._what = what

    def _run(self) -> None:
        while not self._stop.wait(self._period_s):
            self._log(
                f'JIT warm-up: still compiling ({self._what}; {time.perf_counter() - self._start:.0f} s '
                'so far; a cold cache takes minutes on a busy machine)'
            )


def warm_up(
    types: MessageTypes,
    params: ExtractorParams | None = None,
    *,
    sensors: Sequence[str] | None = None,
    log: Callable[[str], None] | None = None,
    tick_s: float = TICK_S,
) -> list[WarmUpStep]:
    """Run :func:`~ppe_ros.ros.processing.process_cloud` with every output once per sensor profile.

    Args:
        types: message classes to build the clouds and outputs with.
        params: the settings to warm up with (default the node defaults); ``min_plane_points`` is
            lowered to 4 and ``max_points`` is the default's, for the small cloud.
        sensors: profiles to run (default ``params.sensor`` only).
        log: gets the progress lines (default: none).
        tick_s: a "still compiling" line this often (s); 0 = none.

    Returns the steps with their seconds. Exceptions of the pipeline propagate.
    """
    params = ExtractorParams() if params is None else params
    sensors = (params.sensor,) if sensors is None else tuple(sensors)
    say = log or (lambda line: None)
    steps = []
    cloud = warm_up_cloud(types)
    with _Ticker(say, tick_s) as ticker:
        for number, sensor in enumerate(sensors, 1):
            what = f'step {number}/{len(sensors)}: sensor {sensor}'
            ticker.step(what)
            say(f'JIT warm-up {what} ...')
            start = time.perf_counter()
            settings = params.replace(sensor=sensor, min_plane_points=4, max_points=ExtractorParams().max_points)
            frame = process_cloud(cloud, settings, types, outputs=OutputSelection(True, True, True))
            # one start per pixel (Ouster metadata) takes other paths of the ray model and the markers
            beam_starts = np.zeros((int(cloud.height), int(cloud.width), 3))
            beam_starts[..., 0] = 0.0158
            process_cloud(cloud, settings, types, outputs=OutputSelection(False, True, False), ray_origins=beam_starts)
            steps.append(WarmUpStep(sensor, time.perf_counter() - start, frame.planes.num_planes))
    return steps


#: Logged when ``workers`` > 1 but numba runs its parallel kernels on the workqueue layer.
WORKQUEUE_LAYER_ERROR = (
    "workers > 1 needs numba's omp or tbb threading layer (numba uses 'workqueue' here, which aborts the process "
    'when two threads launch parallel kernels at once; pip install tbb): running one worker'
)


def parallel_workers_safe() -> bool:
    """Whether several threads may launch numba's parallel kernels at once (omp and tbb: yes; workqueue: no).

    Call it after a parallel kernel ran (the warm-up): before that numba has no layer yet, and this says True.
    """
    import numba

    try:
        return numba.threading_layer() != 'workqueue'
    except ValueError:  # no parallel kernel has run yet (the warm-up failed)
        return True
