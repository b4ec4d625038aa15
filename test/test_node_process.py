"""The ``extractor`` console script as a separate process, talked to over DDS on localhost.

Each test starts the node with config/extractor.yaml on its own ROS domain id (localhost discovery
only), checks that it answers a cloud, stops it with SIGINT or SIGTERM and checks the exit code and
that no C++ "terminate" message appeared. Every wait is bounded.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from ppe_ros.core.synthetic import plane_scan
from ppe_ros.ros.diagnostics import RATE_WINDOW_S
from ppe_ros.ros.pointcloud2 import pointcloud2_to_structured, structured_to_pointcloud2, xyz_to_pointcloud2

pytestmark = [pytest.mark.ros, pytest.mark.timeout(420)]

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / 'config' / 'extractor.yaml'
EXTRACTOR = Path(sys.executable).parent / 'extractor'
READY_TIMEOUT_S = 300.0  # a cold numba cache compiles the kernels in the child
EXIT_TIMEOUT_S = 30.0


def unique_domain_id(offset: int) -> int:
    """A domain id of its own: 1..99, never the session's ROS_DOMAIN_ID, which the in-process tests' nodes
    (also named extractor) use (conftest: 100 + pid % 100 unless the environment sets it, as .ci/run does)."""
    domain = 1 + (os.getpid() * 7 + offset) % 99
    if str(domain) == os.environ.get('ROS_DOMAIN_ID'):
        domain = 1 + domain % 99  # the next one
    return domain


class ExtractorProcess:
    """``extractor --ros-args --params-file config/extractor.yaml`` with its output collected by a thread."""

    def __init__(
        self,
        domain_id: int,
        *extra_args: str,
        interrupt_on: str | None = None,
        interrupt_signal: int = signal.SIGINT,
        env: dict[str, str] | None = None,
        preexec_fn: Any = None,
    ) -> None:
        """``interrupt_on``: the reader thread sends ``interrupt_signal`` the moment a line containing it is read."""
        assert EXTRACTOR.is_file(), f'{EXTRACTOR} is missing: run `make venv` (editable install)'
        env = dict(
            os.environ,
            ROS_DOMAIN_ID=str(domain_id),
            ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
            PYTHONUNBUFFERED='1',
            PYTHONFAULTHANDLER='1',  # the threads' stacks on SIGABRT (a stop that hangs, see stop())
            RCUTILS_LOGGING_BUFFERED_STREAM='0',
            **(env or {}),
        )
        self.process = subprocess.Popen(
            [str(EXTRACTOR), '--ros-args', '--params-file', str(CONFIG), *extra_args],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            preexec_fn=preexec_fn,
        )
        self.lines: list[str] = []
        self._interrupt_on = interrupt_on
        self._interrupt_signal = interrupt_signal
        self.ready = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.process.stdout:
            if self._interrupt_on is not None and self._interrupt_on in line:
                self.process.send_signal(self._interrupt_signal)
                self._interrupt_on = None
            self.lines.append(line)
            if 'ready: waiting for PointCloud2' in line:
                self.ready.set()

    @property
    def output(self) -> str:
        return ''.join(self.lines)

    def stop(self, sig: int, timeout: float = EXIT_TIMEOUT_S) -> int:
        """Send ``sig`` and wait (bounded) for the exit code; kill as a last resort.

        A process still running after ``timeout`` gets SIGABRT (PYTHONFAULTHANDLER prints its threads'
        stacks) and the test fails with its output.
        """
        if self.process.poll() is None:
            self.process.send_signal(sig)
        try:
            return self.process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.process.send_signal(signal.SIGABRT)
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                pass
            self._reader.join(timeout=10)
            pytest.fail(
                f'the extractor did not exit within {timeout:g} s of {signal.Signals(sig).name}; its output '
                f'(the stacks of its threads at the end):\n{self.output}'
            )
        finally:
            if self.process.poll() is None:
                self.process.kill()
                self.process.wait(timeout=10)
            self._reader.join(timeout=10)


@pytest.fixture
def client_factory():
    """A context + executor + node on a given domain; torn down in order."""
    created = []

    def make(domain_id: int):
        context = rclpy.context.Context()
        rclpy.init(context=context, domain_id=domain_id)
        executor = SingleThreadedExecutor(context=context)
        node = rclpy.create_node('process_probe', context=context)
        executor.add_node(node)
        created.append((context, executor, node))
        return executor, node

    yield make
    for context, executor, node in created:
        executor.remove_node(node)
        node.destroy_node()
        executor.shutdown(timeout_sec=1.0)
        context.try_shutdown()


def spin_until(executor, predicate, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.05)
    return True


def plane_table_probe(client_factory, domain_id: int, depth: int = 5) -> tuple[Any, Any, list]:
    """(executor, probe node, the plane tables it receives on /planes, reliable with ``depth``) on ``domain_id``."""
    executor, probe = client_factory(domain_id)
    tables: list = []
    probe.create_subscription(
        PointCloud2, '/planes', tables.append, QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
    )
    return executor, probe, tables


def publish_until_a_table(executor, tables: list, publish, extractor: ExtractorProcess, timeout: float = 60.0) -> None:
    """Call ``publish`` about once a second until a plane table arrives in ``tables`` (the node builds /planes
    only once it sees the subscription); fail with the extractor's output after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not tables and time.monotonic() < deadline:
        publish()
        spin_until(executor, lambda: bool(tables), 1.0)
    assert tables, f'no plane table from the extractor process:\n{extractor.output}'


def make_cloud(sec: int) -> PointCloud2:
    points = plane_scan(3, rows=24, cols=32, radial_sigma=0.005, seed=3).points
    header = Header(frame_id='proc_lidar')
    header.stamp.sec = sec
    return xyz_to_pointcloud2(points, header=header, msg_class=PointCloud2, field_class=PointField)


@pytest.mark.parametrize('stop_signal', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_console_script_answers_over_dds_and_exits_cleanly(client_factory, stop_signal):
    domain_id = unique_domain_id(int(stop_signal))
    extractor = ExtractorProcess(domain_id)
    try:
        assert extractor.ready.wait(READY_TIMEOUT_S), f'not ready in time:\n{extractor.output}'
        executor, probe, tables = plane_table_probe(client_factory, domain_id)
        publisher = probe.create_publisher(PointCloud2, '/points', qos_profile_sensor_data)
        assert spin_until(executor, lambda: publisher.get_subscription_count() > 0, 30.0), extractor.output
        # the node builds /planes only once it sees our subscription; resend until a table arrives
        publish_until_a_table(executor, tables, lambda: publisher.publish(make_cloud(sec=123)), extractor)
        table = tables[-1]
        assert (table.header.frame_id, table.header.stamp.sec) == ('proc_lidar', 123)
        assert pointcloud2_to_structured(table)['point_count'].sum() > 500
    finally:
        exit_code = extractor.stop(stop_signal)
    output = extractor.output
    assert exit_code == 0, f'exit code {exit_code}:\n{output}'
    assert 'terminate called' not in output and 'Traceback' not in output, output
    assert 'JIT warm-up done' in output


def test_two_workers_publish_in_order_and_stop_cleanly_while_busy(client_factory):
    """`-p workers:=2`: clouds at 10 Hz come back in stamp order; SIGINT during extraction exits with 0."""
    domain_id = unique_domain_id(70)
    # reliable input: best-effort clouds of 1.4 MB are mostly lost with Fast DDS's default settings (README)
    extractor = ExtractorProcess(domain_id, '-p', 'workers:=2', '-p', 'input_reliability:=reliable')
    try:
        assert extractor.ready.wait(READY_TIMEOUT_S), f'not ready in time:\n{extractor.output}'
        assert '2 worker(s)' in extractor.output
        executor, probe, tables = plane_table_probe(client_factory, domain_id, depth=50)
        reliable = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
        publisher = probe.create_publisher(PointCloud2, '/points', reliable)
        assert spin_until(executor, lambda: publisher.get_subscription_count() > 0, 30.0), extractor.output
        publish_until_a_table(executor, tables, lambda: publisher.publish(make_cloud(sec=1)), extractor)
        big = plane_scan(3, rows=200, cols=600, radial_sigma=0.005, seed=4).points

        def publish_big(sec: int) -> None:
            header = Header(frame_id='proc_lidar')
            header.stamp.sec = sec
            publisher.publish(xyz_to_pointcloud2(big, header=header, msg_class=PointCloud2, field_class=PointField))

        for sec in range(2, 12):
            publish_big(sec)
            spin_until(executor, lambda: False, 0.1)
        assert spin_until(executor, lambda: len(tables) >= 4, 60.0), extractor.output
        stamps = [t.header.stamp.sec for t in tables]
        assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps), stamps
        for sec in range(12, 15):  # busy again when the signal comes
            publish_big(sec)
        spin_until(executor, lambda: False, 0.2)
    finally:
        exit_code = extractor.stop(signal.SIGINT)
    output = extractor.output
    assert exit_code == 0, f'exit code {exit_code}:\n{output}'
    assert 'terminate called' not in output and 'Traceback' not in output, output


def test_invalid_parameter_exits_with_code_2_and_says_why():
    extractor = ExtractorProcess(unique_domain_id(50), '-p', 'marker_alpha:=4.0')
    try:
        exit_code = extractor.process.wait(timeout=120)
    finally:
        extractor.stop(signal.SIGKILL)
    assert exit_code == 2, extractor.output
    assert "invalid parameter 'marker_alpha'" in extractor.output
    assert 'Traceback' not in extractor.output


def test_skipped_frames_do_not_stop_the_process(client_factory):
    domain_id = unique_domain_id(60)
    extractor = ExtractorProcess(domain_id)
    try:
        assert extractor.ready.wait(READY_TIMEOUT_S), extractor.output
        executor, probe = client_factory(domain_id)
        # a subscriber on an output: with none the node idles and does not look at the clouds (issue 19 item 5)
        probe.create_subscription(
            PointCloud2, '/planes', lambda msg: None, QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
        )
        publisher = probe.create_publisher(PointCloud2, '/points', qos_profile_sensor_data)
        assert spin_until(executor, lambda: publisher.get_subscription_count() > 0, 30.0)
        organized = make_cloud(sec=1)  # flattened, with a ring field of no beam numbers: no range image
        flat = pointcloud2_to_structured(organized).reshape(-1)
        ringed = np.zeros(len(flat), [('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('ring', '<i4')])
        ringed['x'], ringed['y'], ringed['z'], ringed['ring'] = flat['x'], flat['y'], flat['z'], -5
        unorganized = structured_to_pointcloud2(
            ringed, header=organized.header, msg_class=PointCloud2, field_class=PointField
        )
        deadline = time.monotonic() + 30.0
        while 'frame skipped: unorganized cloud' not in extractor.output and time.monotonic() < deadline:
            publisher.publish(unorganized)
            spin_until(executor, lambda: False, 0.5)
        assert 'frame skipped: unorganized cloud (height 1, width 768)' in extractor.output
        assert extractor.process.poll() is None
    finally:
        exit_code = extractor.stop(signal.SIGINT)
    assert exit_code == 0, extractor.output


def test_help_prints_the_topics_and_parameters_and_starts_nothing():
    result = subprocess.run([str(EXTRACTOR), '--help'], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith('usage: ros2 run ppe_ros extractor')
    for name in ('planes/labeled_points', 'planes/markers', 'max_error_increment', 'input_reliability'):
        assert name in result.stdout
    assert 'JIT warm-up' not in result.stdout + result.stderr


def test_unreadable_params_file_exits_with_code_2_without_a_traceback(tmp_path):
    missing = tmp_path / 'missing.yaml'
    env = dict(os.environ, ROS_DOMAIN_ID=str(unique_domain_id(70)), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    result = subprocess.run(
        [str(EXTRACTOR), '--ros-args', '--params-file', str(missing)],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )
    assert result.returncode == 2, result.stdout + result.stderr
    assert 'extractor: error: invalid ROS arguments' in result.stderr and str(missing) in result.stderr
    assert 'Traceback' not in result.stderr


def test_unknown_parameter_names_are_warned_about():
    """The warning comes from ExtractorNode.__init__: the SIGINT lands in the start-up (or in the warm-up,
    which the stop waits for, at most STOP_TIMEOUT_S)."""
    extractor = ExtractorProcess(unique_domain_id(80), '-p', 'max_error_incremnt:=0.1')
    try:
        deadline = time.monotonic() + READY_TIMEOUT_S
        while (
            'ignoring unknown parameter' not in extractor.output
            and extractor.process.poll() is None
            and time.monotonic() < deadline
        ):
            time.sleep(0.05)
    finally:
        exit_code = extractor.stop(signal.SIGINT, timeout=READY_TIMEOUT_S)
    assert "ignoring unknown parameter(s) ['max_error_incremnt']" in extractor.output, extractor.output
    assert exit_code == 0, extractor.output


#: Test-only start-up hook for the child (a sitecustomize module on its PYTHONPATH; nothing in ppe_ros): the
#: n-th call of one rclpy.node.Node method on the node named 'extractor' prints a marker and sleeps, so that
#: a SIGINT sent on the marker arrives inside ExtractorNode.__init__, at that call.
SLOW_CALL_HOOK = """
import os
import time

import rclpy.node

_method, _nth = os.environ['PPE_TEST_SLOW_CALL'].split(':')
_original = getattr(rclpy.node.Node, _method)
_calls = []


def _slow(self, *args, **kwargs):
    if self.get_name() == 'extractor':
        _calls.append(None)
        if len(_calls) == int(_nth):
            print(f'TEST HOOK: in call {_nth} of {_method}', flush=True)
            time.sleep(1.0)
    return _original(self, *args, **kwargs)


setattr(rclpy.node.Node, _method, _slow)
"""


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.parametrize('call', ['create_publisher:1', 'create_publisher:4', 'create_timer:1'])
@pytest.mark.parametrize('stop_signal', ['SIGTERM', 'SIGINT', 'SIGINT_inherited_ignored'])
def test_a_signal_inside_the_node_constructor_exits_0_without_a_traceback(child_hook_env, call, stop_signal):
    """Issue 17 item 10: a signal during ExtractorNode.__init__ made the next rclpy call raise RCLError
    (create_publisher: "rcl node's context is invalid"), and main exited 1 with a traceback. rclpy's handler
    shuts the context down; Python's KeyboardInterrupt follows only for a SIGINT whose inherited disposition
    is not "ignore" (a background job of a shell script, some launchers and supervisors: ignored)."""
    env = {**child_hook_env(SLOW_CALL_HOOK), 'PPE_TEST_SLOW_CALL': call}
    sig = signal.SIGTERM if stop_signal == 'SIGTERM' else signal.SIGINT
    extractor = ExtractorProcess(
        unique_domain_id(85),
        interrupt_on='TEST HOOK: in call',
        interrupt_signal=sig,
        env=env,
        preexec_fn=_ignore_sigint if stop_signal.endswith('ignored') else None,
    )
    try:
        exit_code = extractor.process.wait(timeout=READY_TIMEOUT_S)
    finally:
        extractor.stop(signal.SIGKILL)
    output = extractor.output
    assert f'TEST HOOK: in call {call.split(":")[1]}' in output, output
    assert exit_code == 0, f'exit code {exit_code}:\n{output}'
    assert 'Traceback' not in output and 'terminate called' not in output, output
    assert 'JIT warm-up' not in output  # stopped inside the constructor, before the worker started


#: A process whose main thread forgets a running node (what a SIGINT between ExtractorNode() and the name
#: that would hold it does to the extractor's main): it must still exit.
FORGOTTEN_NODE_SCRIPT = """
import rclpy
from ppe_ros.ros.node import ExtractorNode

rclpy.init()
node = ExtractorNode()
assert node.ready.wait(600), 'no warm-up'
print('ready, leaving the node running', flush=True)
"""


def test_a_node_nobody_stopped_does_not_keep_the_process_alive():
    """The workers end once the main thread has ended without stopping them (before, the interpreter waited
    for them at exit forever: a SIGINT in that window hung test_sigint_during_start_up... once in CI)."""
    env = dict(
        os.environ,
        ROS_DOMAIN_ID=str(unique_domain_id(95)),
        ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
        PYTHONFAULTHANDLER='1',
    )
    child = subprocess.Popen(
        [sys.executable, '-c', FORGOTTEN_NODE_SCRIPT],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        output, _ = child.communicate(timeout=READY_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        child.send_signal(signal.SIGABRT)  # the threads' stacks, then fail
        output, _ = child.communicate(timeout=30)
        pytest.fail(f'the process did not exit once its main thread had ended:\n{output}')
    assert 'ready, leaving the node running' in output, output
    assert child.returncode == 0, output


@pytest.mark.parametrize('delay_s', [0.0, 0.3, 1.5])
def test_sigint_during_start_up_exits_0_without_a_traceback(client_factory, delay_s):
    """A SIGINT as soon as the node shows up in the ROS graph (inside ExtractorNode.__init__ or just after it),
    or a little later (the warm-up): exit 0, no traceback (issue 17 item 10: RCLError in create_publisher)."""
    domain_id = unique_domain_id(90)
    executor, probe = client_factory(domain_id)
    extractor = ExtractorProcess(domain_id)
    try:
        appeared = spin_until(executor, lambda: 'extractor' in probe.get_node_names(), READY_TIMEOUT_S)
        time.sleep(delay_s)
    finally:
        exit_code = extractor.stop(signal.SIGINT, timeout=READY_TIMEOUT_S)
    output = extractor.output
    assert appeared, f'the node never appeared in the graph:\n{output}'
    assert exit_code == 0, f'exit code {exit_code}:\n{output}'
    assert 'Traceback' not in output and 'terminate called' not in output, output
    assert 'Failed to publish log message to rosout' not in output, output  # start-up lines after the signal


#: Test-only hooks for the child (sitecustomize, as SLOW_CALL_HOOK): the JIT warm-up never ends (a cold
#: cache under load, or a kernel that never returns), or rclpy's shutdown never returns.
STUCK_HOOKS = {
    'warm-up': """
import time
import ppe_ros.ros.warmup

def _stuck(*args, **kwargs):
    print('TEST HOOK: warm-up stuck', flush=True)
    time.sleep(3600)

ppe_ros.ros.warmup.warm_up = _stuck
""",
    'rclpy shutdown': """
import time
import rclpy

def _stuck(*args, **kwargs):
    time.sleep(3600)

rclpy.try_shutdown = _stuck
""",
}


@pytest.mark.parametrize('stop_signal', [signal.SIGINT, signal.SIGTERM])
def test_a_stop_does_not_wait_for_a_worker_that_stays_busy(child_hook_env, stop_signal):
    """A stop during a warm-up that does not end (a cold numba cache compiles for minutes; the node waited
    for it, so a Ctrl-C did nothing for minutes): after STOP_TIMEOUT_S the node says which worker it leaves
    and exits with 0, without a traceback."""
    from ppe_ros.ros.node import STOP_TIMEOUT_S

    extractor = ExtractorProcess(
        unique_domain_id(60),
        interrupt_on='TEST HOOK: warm-up stuck',
        interrupt_signal=stop_signal,
        env=child_hook_env(STUCK_HOOKS['warm-up']),
    )
    try:
        exit_code = extractor.process.wait(timeout=READY_TIMEOUT_S)
    finally:
        extractor.stop(signal.SIGKILL)
    output = extractor.output
    assert 'TEST HOOK: warm-up stuck' in output, output
    assert exit_code == 0, f'exit code {exit_code}:\n{output}'
    busy = f'stopping without waiting for worker 0 (the JIT warm-up): still busy {STOP_TIMEOUT_S:g} s after'
    assert busy in output, output
    assert 'Traceback' not in output and 'terminate called' not in output, output


def test_a_shutdown_that_hangs_ends_with_the_threads_stacks_and_code_1(child_hook_env):
    """Whatever hangs after the workers stopped (rclpy's or DDS's teardown; here rclpy.try_shutdown never
    returns): the watchdog prints the threads' stacks and exits with 1 instead of hanging."""
    extractor = ExtractorProcess(unique_domain_id(65), env=child_hook_env(STUCK_HOOKS['rclpy shutdown']))
    try:
        assert extractor.ready.wait(READY_TIMEOUT_S), f'not ready in time:\n{extractor.output}'
    finally:
        exit_code = extractor.stop(signal.SIGINT, timeout=READY_TIMEOUT_S)
    output = extractor.output
    assert exit_code == 1, f'exit code {exit_code}:\n{output}'
    assert 'Timeout (0:00:' in output and 'in _stuck' in output, output


# ------------------------------------------------------------------ issue 19: QoS overrides, idling, diagnostics


def extractor_endpoints(infos) -> list:
    return [info for info in infos if info.node_name == 'extractor']


def test_qos_overrides_reach_the_ros_graph_and_unknown_ones_are_warned_about(client_factory):
    """`-p qos_overrides.<topic>.<entity>.<policy>:=...` as ROS 2 nodes take it (it was silently ignored)."""
    from rclpy.qos import ReliabilityPolicy as Reliability

    domain_id = unique_domain_id(20)
    extractor = ExtractorProcess(
        domain_id,
        '-p',
        'qos_overrides./points.subscription.reliability:=reliable',
        '-p',
        'qos_overrides./planes.publisher.reliability:=best_effort',
        '-p',
        'qos_overrides./nowhere.subscription.depth:=2',
    )
    try:
        executor, probe = client_factory(domain_id)

        def endpoints():
            return (
                extractor_endpoints(probe.get_subscriptions_info_by_topic('/points')),
                extractor_endpoints(probe.get_publishers_info_by_topic('/planes')),
            )

        assert spin_until(executor, lambda: all(endpoints()), READY_TIMEOUT_S), extractor.output
        [subscription], [table_publisher] = endpoints()
        assert subscription.qos_profile.reliability == Reliability.RELIABLE
        assert table_publisher.qos_profile.reliability == Reliability.BEST_EFFORT
        [markers] = extractor_endpoints(probe.get_publishers_info_by_topic('/planes/markers'))
        assert markers.qos_profile.reliability == Reliability.RELIABLE
        deadline = time.monotonic() + 30.0
        while 'ignoring QoS override' not in extractor.output and time.monotonic() < deadline:
            time.sleep(0.05)
        assert "ignoring QoS override(s) ['qos_overrides./nowhere.subscription.depth']" in extractor.output
    finally:
        exit_code = extractor.stop(signal.SIGINT, timeout=READY_TIMEOUT_S)
    assert exit_code == 0, extractor.output


def test_idle_without_subscribers_then_outputs_rate_diagnostics_and_an_rviz_drawable_table(client_factory):
    """Nobody listening: frames are counted as idle, not extracted; a subscriber brings the outputs back, with
    their rate and age in the diagnostics; the plane table's x y z are float32 (RViz's XYZ transformer)."""
    from diagnostic_msgs.msg import DiagnosticArray

    domain_id = unique_domain_id(30)
    extractor = ExtractorProcess(domain_id)
    try:
        assert extractor.ready.wait(READY_TIMEOUT_S), f'not ready in time:\n{extractor.output}'
        executor, probe = client_factory(domain_id)
        statuses = []
        probe.create_subscription(
            DiagnosticArray,
            '/diagnostics',
            lambda msg: statuses.extend(
                {kv.key: kv.value for kv in s.values} | {'_message': s.message}
                for s in msg.status
                if s.name == 'extractor: plane extraction'
            ),
            10,
        )
        publisher = probe.create_publisher(PointCloud2, '/points', qos_profile_sensor_data)
        assert spin_until(executor, lambda: publisher.get_subscription_count() > 0, 30.0), extractor.output

        def latest(predicate, timeout: float, publish: bool) -> dict | None:
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline:
                if publish:
                    publisher.publish(make_cloud(sec=5))
                spin_until(executor, lambda: False, 0.2)
                if statuses and predicate(statuses[-1]):
                    return statuses[-1]
            return None

        idle = latest(lambda s: int(s['frames_idle']) >= 3, 60.0, publish=True)
        assert idle is not None, f'{statuses[-3:]}\n{extractor.output}'
        assert (idle['idle'], idle['frames_processed'], idle['time_since_last_output_s']) == ('true', '0', 'nan')
        assert idle['_message'].startswith('idle: no subscriber on any output')
        tables = []
        probe.create_subscription(
            PointCloud2, '/planes', tables.append, QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
        )
        busy = latest(lambda s: int(s['frames_processed']) >= 5 and float(s['output_rate_hz']) > 0, 60.0, publish=True)
        assert busy is not None and tables, f'{statuses[-3:]}\n{extractor.output}'
        assert busy['idle'] == 'false' and float(busy['time_since_last_output_s']) < 5.0
        assert 0.0 < float(busy['output_rate_hz']) <= float(busy['input_rate_hz']) + 1.0
        table = tables[-1]
        assert [(f.name, f.offset, f.datatype, f.count) for f in table.fields[:4]] == [
            ('x', 0, PointField.FLOAT32, 1),
            ('y', 4, PointField.FLOAT32, 1),
            ('z', 8, PointField.FLOAT32, 1),
            ('rgb', 12, PointField.FLOAT32, 1),
        ]
        records = pointcloud2_to_structured(table)[0]
        np.testing.assert_allclose(records['x'], records['centroid_x'], rtol=1e-6)
        # no input: the age grows and, once the last output left the 5 s rate window, the rate is 0
        quiet = latest(lambda s: float(s['time_since_last_output_s']) >= RATE_WINDOW_S + 1.0, 30.0, publish=False)
        assert quiet is not None and quiet['output_rate_hz'] == '0.00', statuses[-3:]
    finally:
        exit_code = extractor.stop(signal.SIGINT)
    assert exit_code == 0, extractor.output
    assert 'Traceback' not in extractor.output


def test_a_depth_camera_with_its_params_file_and_remapped_topics(client_factory):
    """As a RealSense user starts it: config/depth_camera.yaml, the depth image and camera info remapped to
    the driver's topics; the plane table of the image comes back with its header, the camera model is logged."""
    from depth_frames import camera_info, corner_depth, depth_image
    from sensor_msgs.msg import CameraInfo, Image

    from ppe_ros.ros.messages import rclpy_message_types

    domain_id = unique_domain_id(80)
    extractor = ExtractorProcess(
        domain_id,
        '--params-file',
        str(REPO / 'config' / 'depth_camera.yaml'),
        '-r',
        'depth/image:=/camera/depth/image_rect_raw',
        '-r',
        'depth/camera_info:=/camera/depth/camera_info',
    )
    try:
        assert extractor.ready.wait(READY_TIMEOUT_S), f'not ready in time:\n{extractor.output}'
        assert 'depth images on /camera/depth/image_rect_raw' in extractor.output
        executor, probe, tables = plane_table_probe(client_factory, domain_id)
        reliable = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
        images = probe.create_publisher(Image, '/camera/depth/image_rect_raw', reliable)
        infos = probe.create_publisher(CameraInfo, '/camera/depth/camera_info', reliable)
        ready = lambda: images.get_subscription_count() > 0 and infos.get_subscription_count() > 0  # noqa: E731
        assert spin_until(executor, ready, 30.0), extractor.output
        types = rclpy_message_types()
        millimetres = np.round(corner_depth() * 1000.0).astype(np.uint16)

        def publish() -> None:
            infos.publish(camera_info(types))
            images.publish(depth_image(types, millimetres, '16UC1'))

        publish_until_a_table(executor, tables, publish, extractor)
        table = tables[-1]
        assert table.header.frame_id == 'camera_depth_optical_frame' and table.width == 2  # the wall and the floor
        assert 'camera info on /camera/depth/camera_info: 80 x 60 images, fx 120.0' in extractor.output
    finally:
        exit_code = extractor.stop(signal.SIGINT)
    output = extractor.output
    assert exit_code == 0, f'exit code {exit_code}:\n{output}'
    assert 'terminate called' not in output and 'Traceback' not in output, output
