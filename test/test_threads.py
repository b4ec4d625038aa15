"""Extraction from threads: the compiled kernels release the GIL, and concurrent calls do not interfere.

A node runs the extraction in a worker thread while its executor thread receives clouds, answers
parameter requests and publishes diagnostics: a kernel that held the GIL would stop all of that for
the whole extraction (about 0.2 s for a 128 x 1024 sweep).
"""

from __future__ import annotations

import importlib
import threading
import time

import numba as nb
import pytest

from ppe_ros.core.extraction import extract_plane_hierarchy
from ppe_ros.core.synthetic import ScanGrid, generate_scan

KERNEL_MODULES = (
    'ppe_ros.core.ppe.adjacency',
    'ppe_ros.core.ppe.greedy',
    'ppe_ros.core.ppe.queue',
    'ppe_ros.core.ppe.seeds',
    'ppe_ros.core.ppe.state',
    'ppe_ros.core.fitting',
    'ppe_ros.core.scan',
    'ppe_ros.core.synthetic',
    'ppe_ros.core.msac',
    'ppe_ros.io.lzf',
    'ppe_ros.ros.markers',
)


def _dispatchers():
    for name in KERNEL_MODULES:
        module = importlib.import_module(name)
        for attr, value in vars(module).items():
            if isinstance(value, nb.core.registry.CPUDispatcher) and value.__module__ == name:
                yield f'{name}.{attr}', value


def test_every_kernel_releases_the_gil():
    """Serial kernels are compiled with nogil=True (numba's parallel kernels release it while they run)."""
    found = dict(_dispatchers())
    assert len(found) > 60 and 'ppe_ros.core.ppe.greedy._ppe_kernel' in found
    holding = [
        name
        for name, dispatcher in found.items()
        if not dispatcher.targetoptions.get('nogil') and not dispatcher.targetoptions.get('parallel')
    ]
    assert holding == []


@pytest.fixture(scope='module')
def room():
    grid = ScanGrid.uniform(250, 250, azimuth_fov_deg=69.86, elevation_fov_deg=60.0)
    return generate_scan(seed=2, grid=grid, radial_sigma=0.02)


def _extract(scan):
    return extract_plane_hierarchy(
        scan.points, origins=scan.origins, max_neighbor_distance=0.18, max_error_increment=0.0484
    )


def test_other_threads_run_while_a_thread_extracts(room):
    """The main thread keeps ticking (1 ms sleeps) while another thread is inside the greedy.

    With the GIL held for the whole kernel the main thread would wait for all of it in one gap.
    """
    _extract(room)  # compiles
    reference = _extract(room)
    greedy = reference.seconds
    assert greedy > 0.05  # long enough to tell the two apart
    done = threading.Event()
    results = []

    def work():
        results.append(_extract(room))
        done.set()

    thread = threading.Thread(target=work)
    thread.start()
    gaps = []
    last = time.perf_counter()
    while not done.is_set():
        time.sleep(0.001)
        now = time.perf_counter()
        gaps.append(now - last)
        last = now
    thread.join()
    assert len(gaps) > 10 and max(gaps) < 0.5 * greedy, (len(gaps), max(gaps), greedy)
    assert results[0].actions.tobytes() == reference.actions.tobytes()


def test_concurrent_extractions_match_sequential_ones(room):
    """Two threads extracting different scans at once get exactly the results of one-at-a-time runs."""
    grid = ScanGrid.uniform(120, 140, azimuth_fov_deg=60.0, elevation_fov_deg=50.0)
    other = generate_scan(seed=5, grid=grid, radial_sigma=0.01)
    expected = [_extract(room).actions, _extract(other).actions]

    def work(slot, scan, results, errors):
        try:
            results[slot] = _extract(scan).actions
        except BaseException as exc:  # reported below, not lost in the thread
            errors.append(exc)

    for _ in range(3):
        results: list = [None, None]
        errors: list = []
        threads = [
            threading.Thread(target=work, args=(slot, scan, results, errors)) for slot, scan in enumerate((room, other))
        ]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        assert errors == []
        assert results[0].tobytes() == expected[0].tobytes()
        assert results[1].tobytes() == expected[1].tobytes()


def test_concurrent_tiled_extractions_with_different_thread_counts_match_sequential_ones():
    """Callers asking the shared strip pool for 1, 2, 3 and 4 threads at once (the pool grows while
    others use it) get exactly the logs of one-at-a-time runs."""
    grid = ScanGrid.uniform(60, 160, azimuth_fov_deg=120.0, elevation_fov_deg=40.0)
    scan = generate_scan(seed=4, grid=grid, radial_sigma=0.02)

    def tiled(threads):
        return extract_plane_hierarchy(
            scan.points, origins=scan.origins, max_error_increment=0.0484, tiles=6, threads=threads
        ).actions.tobytes()

    expected = tiled(1)
    results: dict = {}
    errors: list = []

    def work(threads):
        try:
            results[threads] = [tiled(threads) for _ in range(3)]
        except BaseException as exc:  # reported below, not lost in the thread
            errors.append(exc)

    workers = [threading.Thread(target=work, args=(threads,)) for threads in (1, 2, 3, 4)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    assert errors == []
    assert sorted(results) == [1, 2, 3, 4]
    assert all(log == expected for logs in results.values() for log in logs)


def test_strips_with_the_most_seeds_are_taken_first():
    import numpy as np

    from ppe_ros.core.ppe.tiles import _largest_first

    seed_key = np.full((4, 12), np.inf)
    seed_key[:, 4:8] = 1.0  # strip 1 (columns 4-7) has 16 seeds
    seed_key[0, 0] = seed_key[1, 9] = 2.0  # strips 0 and 2 one each: ties by index
    assert _largest_first(seed_key.reshape(-1), 4, 12, [0, 4, 8, 12]) == [1, 0, 2]


def test_the_strips_logs_are_merged_in_the_order_of_a_stable_argsort():
    import numpy as np

    from ppe_ros.core.ppe.tiles import _merged_runs_order

    rng = np.random.default_rng(5)
    for _ in range(50):
        lengths = rng.integers(0, 30, size=rng.integers(1, 9))
        runs = [np.sort(rng.choice([0.0, 0.5, 1.0, 2.0, np.inf, *rng.random(4)], size=n)) for n in lengths]
        keys = np.concatenate(runs)
        starts = np.cumsum([0, *lengths])
        np.testing.assert_array_equal(_merged_runs_order(keys, starts), np.argsort(keys, kind='stable'))


def test_run_tasks_returns_the_results_in_task_order_from_any_number_of_threads():
    from ppe_ros.core.thread_pool import SharedThreadPool, run_tasks

    pool = SharedThreadPool('ppe-test')
    ran_on = {}

    def square(i):
        time.sleep(0.002 * (i % 3))  # uneven tasks: the threads interleave
        ran_on[i] = threading.current_thread().name
        return i * i

    for threads in (1, 2, 4):
        assert run_tasks(square, [5, 1, 4, 0, 3, 2], threads, pool) == [0, 1, 4, 9, 16, 25]
    assert pool.executor(1) is pool.executor(3)  # grown once to 3 workers, then reused
    assert any(name.startswith('ppe-test') for name in ran_on.values())

    def fails(i):
        if i == 2:
            raise ValueError('task 2')
        return i

    with pytest.raises(ValueError, match='task 2'):
        run_tasks(fails, range(4), 2, pool)


_OPENMP_PROBE = """
import os, sys
import numpy as np
import ppe_ros.core.scan as scan
print('before', os.environ.get('OMP_WAIT_POLICY'), 'runtime loaded', 'numba.np.ufunc.omppool' in sys.modules)
scan.make_ray_scan(np.ones((8, 8, 3)))  # a parallel loop: numba loads its threading layer here
import numba
print('layer', numba.threading_layer())
"""


def _probe_openmp(**env_overrides: str) -> tuple[str, str]:
    """stdout and stderr of _OPENMP_PROBE in a fresh interpreter (OpenMP prints its settings to stderr)."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ('OMP_WAIT_POLICY', 'GOMP_SPINCOUNT')}
    env.update(env_overrides, OMP_DISPLAY_ENV='TRUE')
    done = subprocess.run([sys.executable, '-c', _OPENMP_PROBE], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return done.stdout, done.stderr


def test_openmp_threads_sleep_after_a_parallel_loop_unless_the_user_says_otherwise():
    # set before numba's OpenMP runtime loads, and the runtime takes it (it prints its settings)
    out, err = _probe_openmp()
    assert 'before PASSIVE runtime loaded False' in out
    if 'layer omp' in out:  # numba's OpenMP layer (GNU OpenMP on Linux)
        assert "OMP_WAIT_POLICY = 'PASSIVE'" in err
    out, err = _probe_openmp(OMP_WAIT_POLICY='ACTIVE')
    assert 'before ACTIVE' in out
    if 'layer omp' in out:
        assert "OMP_WAIT_POLICY = 'ACTIVE'" in err
    out, _ = _probe_openmp(GOMP_SPINCOUNT='1000')
    assert 'before None' in out
