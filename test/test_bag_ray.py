"""``process_bag --executor ray`` on a local Ray of two workers (127.0.0.1 only, no dashboard).

Outputs are compared byte for byte with ``--executor local`` on three small bags; a worker killed
in the middle of a task (its task is retried) and killed for good (the input is reported
incomplete, the others go on); and Ctrl-C to a real ``process_bag`` joining this Ray.
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import pytest
from test_bag import JAZZY, bag_time, cloud, read_bag, serialized, write_rosbag2
from test_bag_many import frames, same_bag

from ppe_ros.core.synthetic import plane_scan
from ppe_ros.ros.bag import BagError, BagOptions, main, process_bags
from ppe_ros.ros.bag.ray_executor import RayExecutor, process_frames

ray = pytest.importorskip('ray', reason='Ray is pinned in requirements.txt; install it with make venv')

REPO = Path(__file__).resolve().parents[1]
LABELED = '/sensor/planes/labeled_points'
OUTPUTS = ('/sensor/planes/labeled_points', '/sensor/planes/markers', '/sensor/planes')
NAMES = ('a', 'b', 'c')


@pytest.fixture(scope='module')
def local_ray():
    """Ray in this process: two CPUs (two workers), 127.0.0.1 only, no dashboard, a small object store."""
    os.environ.setdefault('RAY_USAGE_STATS_ENABLED', '0')
    ray.init(
        num_cpus=2,
        include_dashboard=False,
        _node_ip_address='127.0.0.1',
        object_store_memory=100 << 20,
        log_to_driver=False,
        configure_logging=False,
    )
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the killing task bodies below
    yield ray.get_runtime_context().gcs_address
    ray.shutdown()


@pytest.fixture(scope='module')
def three_bags(tmp_path_factory) -> tuple[list[Path], Path]:
    """Three bags of 5, 3 and 6 frames, and what ``--executor local`` writes for them."""
    folder = tmp_path_factory.mktemp('bags')
    inputs = [
        write_rosbag2(folder / name, frames(count, 50 + 10 * index))
        for index, (name, count) in enumerate(zip(NAMES, (5, 3, 6), strict=True))
    ]
    assert main([*map(str, inputs), str(folder / 'local'), '--no-progress']) == 0
    return inputs, folder / 'local'


def runs(inputs: list[Path], out: Path, **options) -> list[BagOptions]:
    return [BagOptions(source, out / source.name, executor='ray', progress=False, **options) for source in inputs]


def kill_the_first_attempt(flag: str, params, numba_threads, frames_of_task):
    """Task body that kills its worker (SIGKILL, as the kernel's OOM killer would) the first time any task runs."""
    marker = Path(flag)
    if not marker.exists():
        marker.write_text(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)
    return process_frames(params, numba_threads, frames_of_task)


def kill_when_holding(digest: str, params, numba_threads, frames_of_task):
    """Task body that kills its worker every time its task holds the frame of this sha1."""
    if any(hashlib.sha1(raw).hexdigest() == digest for raw, _, _ in frames_of_task):
        os.kill(os.getpid(), signal.SIGKILL)
    return process_frames(params, numba_threads, frames_of_task)


def test_ray_writes_the_bytes_local_writes(local_ray, three_bags, tmp_path, capsys):
    inputs, local = three_bags
    bags = process_bags(runs(inputs, tmp_path, task_frames=2), output_directory=tmp_path)
    assert bags.exit_code == 0
    for name in NAMES:
        assert same_bag(tmp_path / name, local / name), name
    assert 'frames/s with Ray, 2 CPUs, 2 frames a task' in capsys.readouterr().out


def test_a_killed_worker_is_retried_and_nothing_is_lost(local_ray, three_bags, tmp_path):
    inputs, local = three_bags
    flag = tmp_path / 'killed'
    executor = RayExecutor(
        BagOptions(inputs[0], tmp_path).params,
        task_frames=2,
        retries=2,
        task_function=functools.partial(kill_the_first_attempt, str(flag)),
    )
    bags = process_bags(runs(inputs, tmp_path / 'out'), output_directory=tmp_path / 'out', executor=executor)
    assert flag.exists()  # a worker was killed
    assert bags.exit_code == 0, [r.worker_error for r in bags.reports]
    for name in NAMES:
        assert same_bag(tmp_path / 'out' / name, local / name), name


def test_a_task_that_keeps_failing_is_reported_and_the_other_inputs_go_on(local_ray, three_bags, tmp_path, capsys):
    inputs, local = three_bags
    doomed = cloud_messages(inputs[0])[2]  # frame 2 of bag a: in the second task
    executor = RayExecutor(
        BagOptions(inputs[0], tmp_path).params,
        task_frames=2,
        retries=1,
        task_function=functools.partial(kill_when_holding, hashlib.sha1(doomed).hexdigest()),
    )
    options = runs(inputs, tmp_path / 'out')
    bags = process_bags(options, output_directory=tmp_path / 'out', executor=executor)
    a, b, c = bags.reports
    assert bags.exit_code == 1
    assert 'Ray task 2 (2 frames) failed after 1 retry' in a.worker_error
    assert 'frames/s' in capsys.readouterr().out
    written = read_bag(tmp_path / 'out' / 'a')
    assert [t for t, _ in written[LABELED]] == [bag_time(0), bag_time(1)]  # the frames before the task
    assert same_bag(tmp_path / 'out' / 'b', local / 'b') and same_bag(tmp_path / 'out' / 'c', local / 'c')
    assert not a.complete and b.complete and c.complete


def cloud_messages(bag: Path) -> list[bytes]:
    """The raw cloud messages of a rosbag2, in order."""
    from rosbags.rosbag2 import Reader

    with Reader(bag) as reader:
        connections = [c for c in reader.connections if c.topic == '/sensor/points']
        return [bytes(raw) for _, _, raw in reader.messages(connections=connections)]


def test_ctrl_c_keeps_every_finished_bag_and_names_the_incomplete_ones(local_ray, tmp_path):
    """The real thing: SIGINT to ``process_bag a b c OUT --executor ray --ray-address <this Ray>`` during b."""
    big = [
        (
            bag_time(i),
            serialized(JAZZY, cloud(JAZZY, i, plane_scan(3, rows=64, cols=512, radial_sigma=0.005, seed=i % 4).points)),
        )
        for i in range(40)
    ]
    inputs = [
        write_rosbag2(tmp_path / 'in' / 'a', frames(3, 70)),
        write_rosbag2(tmp_path / 'in' / 'b', big),
        write_rosbag2(tmp_path / 'in' / 'c', frames(3, 80)),
    ]
    out = tmp_path / 'out'
    process = subprocess.Popen(
        [
            sys.executable,
            '-m',
            'ppe_ros.ros.bag',
            *map(str, inputs),
            str(out),
            '--executor',
            'ray',
            '--ray-address',
            local_ray,
            '--task-frames',
            '1',
            '--progress',
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=REPO,
    )
    seen = bytearray()

    def read_stderr():
        while chunk := process.stderr.read1(4096):
            seen.extend(chunk)

    reader = threading.Thread(target=read_stderr)
    reader.start()
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and process.poll() is None:
        if re.search(rb'process_bag 2/3[^\r\n]*?\b([4-9]|[1-9]\d)/43', bytes(seen)):
            process.send_signal(signal.SIGINT)
            break
        time.sleep(0.05)
    try:
        returncode = process.wait(timeout=120)
    finally:
        process.kill()
        reader.join()
    err = seen.decode(errors='replace')
    stdout = process.stdout.read().decode()
    assert returncode == 130, (stdout, err[-3000:])
    assert 'Traceback' not in err
    assert f'incomplete (a valid bag of the frames done): {inputs[1]}; not started: {inputs[2]}' in err, err[-2000:]
    assert f'complete: {inputs[0]};' in err
    assert len(read_bag(out / 'a')[LABELED]) == 3
    written = read_bag(out / 'b')
    times = [t for t, _ in written[LABELED]]
    assert 1 <= len(times) < 40 and times == [bag_time(i) for i in range(len(times))]  # in order, no gap
    assert all(len(written[topic]) == len(times) for topic in OUTPUTS)
    assert not (out / 'c').exists()
    assert [p.name for p in out.iterdir() if p.name.startswith('.')] == []  # no staging left


def test_options_of_the_ray_executor_are_checked(tmp_path):
    source = write_rosbag2(tmp_path / 'in', frames(1, 90))
    for flag, value in (('--task-frames', '0'), ('--task-retries', '-1')):
        with pytest.raises(SystemExit) as exc:
            main([str(source), str(tmp_path / 'out'), '--executor', 'ray', flag, value])
        assert exc.value.code == 2
    with pytest.raises(BagError, match='--task-frames must be >= 1'):
        process_bags([replace(BagOptions(source, tmp_path / 'out'), executor='ray', task_frames=0)])
    for address, message in (
        ('127.0.0.1:1', 'cannot connect to the Ray cluster at 127.0.0.1:1: Connection refused'),
        ('nowhere', "--ray-address 'nowhere' is not 'auto', HOST:PORT or ray://HOST:PORT"),
    ):
        started = time.monotonic()  # a process of its own: this one may be connected to Ray already
        result = subprocess.run(
            [
                sys.executable,
                '-m',
                'ppe_ros.ros.bag',
                str(source),
                str(tmp_path / 'out'),
                '--executor',
                'ray',
                '--ray-address',
                address,
                '--no-progress',
            ],
            capture_output=True,
            text=True,
            cwd=REPO,
            timeout=120,
        )
        assert result.returncode == 2, result.stderr
        assert f'process_bag: error: {message}' in result.stderr and 'Traceback' not in result.stderr, result.stderr
        assert time.monotonic() - started < 60  # not minutes of ray.init retrying
    assert not (tmp_path / 'out').exists()
