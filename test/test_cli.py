"""The ``ppe`` command line: extract and demo end to end, and its errors."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from ppe_ros.cli import build_parser, main
from ppe_ros.core.synthetic import ScanGrid, generate_scan
from ppe_ros.io import load_scan, save_pcd


@pytest.fixture(scope='module')
def small_scan(tmp_path_factory):
    """A 48 x 64 generated room scan (20 mm noise) saved as SynPEB-style PCD with labels."""
    grid = ScanGrid.uniform(48, 64, azimuth_fov_deg=70.0, elevation_fov_deg=60.0)
    scan = generate_scan(seed=3, grid=grid, radial_sigma=0.02)
    path = tmp_path_factory.mktemp('scan') / 'room.pcd'
    save_pcd(path, scan.points, extra_fields={'intensity': scan.labels.astype(np.float32)})
    return path, scan


def test_help_lists_only_existing_subcommands(capsys):
    parser = build_parser()
    with pytest.raises(SystemExit):
        parser.parse_args(['--help'])
    text = capsys.readouterr().out
    for name in ('info', 'extract', 'demo'):
        assert name in text


def test_extract_writes_npz_pcd_and_png(small_scan, tmp_path, capsys):
    path, scan = small_scan
    out = tmp_path / 'planes.npz'
    png = tmp_path / 'seg.png'
    assert main(['extract', str(path), '-o', str(out), '--png', str(png), '-e', '0.0484', '--json']) == 0
    summary = json.loads(capsys.readouterr().out)
    data = np.load(out)
    labels = data['labels']
    assert labels.shape == scan.labels.shape
    n_planes = summary['snapshots'][0]['planes']
    assert n_planes >= 3
    assert labels.max() == n_planes == len(data['normals']) == len(data['point_counts'])
    np.testing.assert_array_equal(np.bincount(labels.ravel(), minlength=n_planes + 1)[1:], data['point_counts'])
    np.testing.assert_allclose(np.linalg.norm(data['normals'], axis=1), 1.0, atol=1e-12)
    assert png.stat().st_size > 1000
    # PCD output carries the labels as a field
    out_pcd = tmp_path / 'planes.pcd'
    assert main(['extract', str(path), '-o', str(out_pcd), '-e', '0.0484']) == 0
    from ppe_ros.io import read_pcd

    cloud = read_pcd(out_pcd)
    assert 'label' in cloud.data.dtype.names
    np.testing.assert_array_equal(cloud.data['label'], labels)


def test_extract_several_thresholds_write_one_file_each(small_scan, tmp_path):
    path, _ = small_scan
    out = tmp_path / 'p.npz'
    assert main(['extract', str(path), '-o', str(out), '-e', '0.01', '0.1', '-n', '40']) == 0
    files = sorted(p.name for p in tmp_path.glob('p_*.npz'))
    assert files == ['p_e0.01.npz', 'p_e0.1.npz', 'p_n40.npz']
    fine = np.load(tmp_path / 'p_e0.01.npz')
    coarse = np.load(tmp_path / 'p_e0.1.npz')
    assert int(fine['actions']) <= int(coarse['actions'])


def test_extract_refuses_to_overwrite(small_scan, tmp_path, capsys):
    path, _ = small_scan
    out = tmp_path / 'planes.npz'
    out.write_bytes(b'keep me')
    assert main(['extract', str(path), '-o', str(out)]) == 2
    assert 'exists' in capsys.readouterr().err
    assert out.read_bytes() == b'keep me'
    before = path.read_bytes()
    assert main(['extract', str(path), '-o', str(path.with_suffix('.pcd')), '--force']) == 2
    assert path.read_bytes() == before


@pytest.mark.parametrize(
    ('args', 'message'),
    [
        (['-o', 'x.txt'], '.npz or .pcd'),
        (['-o', 'x.npz', '--min-plane-points', '0'], 'min-plane-points'),
    ],
)
def test_extract_rejects_bad_arguments(small_scan, tmp_path, capsys, args, message):
    path, _ = small_scan
    args = [a if a not in ('x.txt', 'x.npz') else str(tmp_path / a) for a in args]
    assert main(['extract', str(path), *args]) == 2
    assert message in capsys.readouterr().err


def test_extract_rejects_negative_threshold(small_scan, tmp_path):
    path, _ = small_scan
    with pytest.raises(SystemExit):
        main(['extract', str(path), '-o', str(tmp_path / 'x.npz'), '-e', '-1'])


def test_extract_missing_file(tmp_path, capsys):
    assert main(['extract', str(tmp_path / 'nope.pcd'), '-o', str(tmp_path / 'x.npz')]) == 2
    assert 'not found' in capsys.readouterr().err


@pytest.mark.timeout(600)
def test_demo_writes_results_and_scores_them(tmp_path, capsys):
    out = tmp_path / 'demo'
    assert main(['demo', '--out', str(out)]) == 0
    text = capsys.readouterr().out
    assert str(out) in text
    for name in ('planes.npz', 'segmentation.png', 'scan.pcd', 'summary.txt', 'summary.json'):
        assert (out / name).is_file(), name
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['planes'] >= 20
    # the written scan carries its ground truth (SynPEB layout: intensity = plane id)
    scan = load_scan(out / 'scan.pcd')
    assert scan.labels is not None and scan.labels.max() >= 10
    assert summary['f'] > 0.2


# --------------------------------------------------------------------------------------------
# issue 17: inputs compared by device and inode, atomic all-or-nothing outputs, one-line errors
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize('link', ['hard', 'symbolic'])
@pytest.mark.parametrize('option', ['-o', '--png'])
def test_extract_refuses_a_link_to_its_input(small_scan, tmp_path, capsys, link, option):
    path, _ = small_scan
    before = path.read_bytes()
    alias = tmp_path / ('alias.pcd' if option == '-o' else 'alias.png')
    (alias.hardlink_to if link == 'hard' else alias.symlink_to)(path)
    args = ['-o', str(alias)] if option == '-o' else ['-o', str(tmp_path / 'p.npz'), '--png', str(alias)]
    assert main(['extract', str(path), *args, '--force']) == 2
    err = capsys.readouterr().err
    assert 'refusing to overwrite the input' in err and err.count('\n') == 1
    assert path.read_bytes() == before and not (tmp_path / 'p.npz').exists()


def test_extract_refuses_a_link_to_its_labels_file(small_scan, tmp_path, capsys):
    path, scan = small_scan
    gt = tmp_path / 'gt.npy'
    np.save(gt, scan.labels)
    (tmp_path / 'out.png').hardlink_to(gt)
    before = gt.read_bytes()
    assert (
        main(
            [
                'extract',
                str(path),
                '--gt',
                str(gt),
                '-o',
                str(tmp_path / 'p.npz'),
                '--png',
                str(tmp_path / 'out.png'),
                '--force',
            ]
        )
        == 2
    )
    assert f'refusing to overwrite the input {gt}' in capsys.readouterr().err
    assert gt.read_bytes() == before


def test_eval_and_tune_refuse_a_link_to_an_input(tmp_path, capsys):
    from ppe_ros.benchmark.dataset import make_dataset

    make_dataset(tmp_path / 'ds', seed=0, sigmas=(0.02,), n_train=1, n_test=1, rows=8, cols=10, n_objects=0)
    manifest = tmp_path / 'ds' / 'dataset.json'
    before = manifest.read_bytes()
    (tmp_path / 'report.md').hardlink_to(manifest)
    assert (
        main(['eval', str(tmp_path / 'ds'), '--methods', 'ppe', '--out', str(tmp_path / 'report.md'), '--quiet']) == 2
    )
    assert 'refusing to overwrite the input' in capsys.readouterr().err
    scan = next((tmp_path / 'ds' / 'train').rglob('*.pcd'))
    scan_before = scan.read_bytes()
    (tmp_path / 'tuned.yaml').hardlink_to(scan)
    assert (
        main(['tune', str(tmp_path / 'ds'), '--noise', '20', '-o', str(tmp_path / 'tuned.yaml'), '--force', '--quiet'])
        == 2
    )
    assert 'refusing to overwrite the input' in capsys.readouterr().err
    assert manifest.read_bytes() == before and scan.read_bytes() == scan_before


def test_extract_checks_every_snapshot_before_writing_any(small_scan, tmp_path, capsys):
    path, _ = small_scan
    out = tmp_path / 'p.npz'
    (tmp_path / 'p_e0.1.npz').write_bytes(b'keep me')  # the second snapshot exists
    assert main(['extract', str(path), '-o', str(out), '-e', '0.01', '0.1']) == 2
    assert 'p_e0.1.npz exists' in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ['p_e0.1.npz']  # the first was not written either
    assert (tmp_path / 'p_e0.1.npz').read_bytes() == b'keep me'


@pytest.mark.parametrize('thresholds', [['-e', '0.01', '0.01'], ['-e', '0.01', '0.0100000001'], ['-n', '5', '5']])
def test_extract_rejects_a_snapshot_asked_for_twice(small_scan, tmp_path, capsys, thresholds):
    path, _ = small_scan
    assert main(['extract', str(path), '-o', str(tmp_path / 'p.npz'), *thresholds, '--force']) == 2
    err = capsys.readouterr().err
    assert 'both give the snapshot p_' in err and 'give each threshold once' in err
    assert list(tmp_path.iterdir()) == []


def test_extract_rejects_the_same_file_for_planes_and_picture(small_scan, tmp_path, capsys):
    path, _ = small_scan
    out = tmp_path / 'p.pcd'
    assert main(['extract', str(path), '-o', str(out), '--png', str(out)]) == 2
    assert 'two outputs would be written to the same file' in capsys.readouterr().err


@pytest.mark.parametrize('room', [0, 100, 5000])
def test_extract_on_a_full_disk_leaves_no_output_and_no_temporary_file(small_scan, tmp_path, capsys, monkeypatch, room):
    from test_io_files import full_disk

    path, _ = small_scan
    full_disk(monkeypatch, room)
    args = ['extract', str(path), '-o', str(tmp_path / 'p.npz'), '--png', str(tmp_path / 'p.png'), '-e', '0.01', '0.1']
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f'cannot write {tmp_path}/p_e0.01.npz: No space left on device' in err and err.count('\n') == 1
    assert list(tmp_path.iterdir()) == []
    for name in ('p_e0.01.npz', 'p_e0.1.npz', 'p_e0.01.png', 'p_e0.1.png'):  # old outputs survive a --force run
        (tmp_path / name).write_bytes(b'old')
    assert main([*args, '--force']) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ['p_e0.01.npz', 'p_e0.01.png', 'p_e0.1.npz', 'p_e0.1.png']
    assert all(p.read_bytes() == b'old' for p in tmp_path.iterdir())
    monkeypatch.undo()
    assert main([*args, '--force', '--lmax', '0.3']) == 0
    assert np.load(tmp_path / 'p_e0.1.npz')['labels'].shape == (48, 64)
    assert sorted(p.name for p in tmp_path.iterdir()) == ['p_e0.01.npz', 'p_e0.01.png', 'p_e0.1.npz', 'p_e0.1.png']


def test_extract_reports_a_missing_output_folder_before_running(small_scan, tmp_path, capsys, monkeypatch):
    import ppe_ros.commands.extract as extract

    monkeypatch.setattr(extract, 'extract_plane_hierarchy', None)  # would raise TypeError if it ran
    path, _ = small_scan
    assert main(['extract', str(path), '-o', str(tmp_path / 'p.npz'), '--png', str(tmp_path / 'no' / 'p.png')]) == 2
    assert f'output folder {tmp_path / "no"} does not exist' in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_extract_huge_plane_count_is_an_argument_error(small_scan, tmp_path, capsys):
    path, _ = small_scan
    with pytest.raises(SystemExit) as stop:
        main(['extract', str(path), '-o', str(tmp_path / 'p.npz'), '-n', str(10**30)])
    assert stop.value.code == 2
    assert 'must be 1 .. 50000000' in capsys.readouterr().err


@pytest.mark.parametrize('content', [b'', b'\x93NUMPY\x01\x00\x10\x00{broken', b'\x93NUMPY'])
def test_damaged_npy_is_one_line_and_exit_2(tmp_path, capsys, content):
    path = tmp_path / 'scan.npy'
    path.write_bytes(content)
    assert main(['info', str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f'ppe info: error: {path}: ') and err.count('\n') == 1


def test_memory_error_is_one_line_and_exit_2(small_scan, capsys, monkeypatch):
    import ppe_ros.commands.info as info

    def exhausted(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr(info, 'load_scan', exhausted)
    path, _ = small_scan
    assert main(['info', str(path)]) == 2
    err = capsys.readouterr().err
    assert err == 'ppe info: error: out of memory (MemoryError); the input is too large for this machine\n'


def test_extract_with_a_sensor_profile_uses_its_defaults_and_the_python_api_agrees(small_scan, tmp_path, capsys):
    from ppe_ros import extract_planes
    from ppe_ros.core.sensor import PROFILES

    path, _ = small_scan
    out = tmp_path / 'lidar.npz'
    assert main(['extract', str(path), '-o', str(out), '--sensor', 'lidar', '--json']) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary['sensor'] == 'lidar'
    assert summary['snapshots'][0]['max_error_increment'] == PROFILES['lidar'].max_error_increment
    saved = np.load(out)
    expected = extract_planes(load_scan(path).points, sensor='lidar')
    np.testing.assert_array_equal(saved['labels'], expected.labels)
    assert saved['point_counts'].min() >= PROFILES['lidar'].min_plane_points_for(load_scan(path).points)


def test_range_noise_changes_the_profiles_noise_model_and_needs_one(small_scan, tmp_path, capsys):
    import dataclasses

    from ppe_ros import extract_planes
    from ppe_ros.core.sensor import PROFILES

    path, _ = small_scan
    out = tmp_path / 'noisy.npz'
    assert main(['extract', str(path), '-o', str(out), '--sensor', 'lidar', '--range-noise', '0.05', '--json']) == 0
    assert json.loads(capsys.readouterr().out)['range_noise'] == 0.05
    lidar = PROFILES['lidar']
    noisy = dataclasses.replace(lidar, noise=dataclasses.replace(lidar.noise, constant=0.05))
    expected = extract_planes(load_scan(path).points, sensor=noisy)
    saved = np.load(out)
    np.testing.assert_array_equal(saved['labels'], expected.labels)
    np.testing.assert_allclose(saved['covariances'], expected.covariances, rtol=1e-12)
    default = extract_planes(load_scan(path).points, sensor='lidar')
    assert not np.array_equal(saved['covariances'], default.covariances)  # the noise reached the fit
    for extra in ([], ['--sensor', 'paper']):
        assert main(['extract', str(path), '-o', str(tmp_path / 'x.npz'), '--range-noise', '0.03', *extra]) == 2
        assert '--range-noise needs --sensor lidar or depth_camera' in capsys.readouterr().err
    with pytest.raises(SystemExit) as exited:  # argparse's own error
        main(['extract', str(path), '-o', str(tmp_path / 'x.npz'), '--sensor', 'lidar', '--range-noise', '0'])
    assert exited.value.code == 2
    assert 'must be > 0' in capsys.readouterr().err


def test_surface_tolerance_needs_a_sensor(small_scan, tmp_path, capsys):
    path, _ = small_scan
    assert main(['extract', str(path), '-o', str(tmp_path / 'x.npz'), '--surface-tolerance', '0.03']) == 2
    assert '--surface-tolerance needs --sensor' in capsys.readouterr().err


#: Test-only start-up hook for the child (sitecustomize on its PYTHONPATH): the first import of numpy, which
#: every command's modules make while they load, prints a marker and takes 2 s, so that a SIGINT sent on the
#: marker arrives while the command is still being imported.
SLOW_NUMPY_IMPORT_HOOK = """
import sys
import time


class _SlowNumpy:
    def find_spec(self, name, path=None, target=None):
        if name == 'numpy':
            sys.meta_path.remove(self)
            print('TEST HOOK: importing numpy', flush=True)
            time.sleep(2.0)
        return None


sys.meta_path.insert(0, _SlowNumpy())
"""


@pytest.mark.parametrize(
    ('script', 'args', 'name'),
    [('ppe', ['info', 'x.npy'], 'ppe'), ('process_bag', ['in', 'out'], 'process_bag'), ('extractor', [], 'extractor')],
)
def test_a_ctrl_c_while_a_command_loads_ends_with_one_line_and_code_130(tmp_path, child_hook_env, script, args, name):
    """The console scripts import numpy, numba, rclpy or rosbags for about half a second before their main
    runs: a Ctrl-C then printed a traceback through the imports (and ended the process by SIGINT)."""
    env = {
        **os.environ,
        **child_hook_env(SLOW_NUMPY_IMPORT_HOOK),
        'PYTHONUNBUFFERED': '1',
        'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST',
    }
    process = subprocess.Popen(
        [str(Path(sys.executable).parent / script), *args],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # a background job's SIGINT is ignored
    )
    lines = []

    def read():
        for line in process.stdout:
            lines.append(line)
            if 'TEST HOOK: importing numpy' in line:
                process.send_signal(signal.SIGINT)

    reader = threading.Thread(target=read)
    reader.start()
    try:
        code = process.wait(timeout=120)
    finally:
        process.kill()
        reader.join(timeout=10)
    output = ''.join(lines)
    assert 'TEST HOOK: importing numpy' in output, output
    assert code == 130, f'exit code {code}:\n{output}'
    assert f'{name}: interrupted' in output and 'Traceback' not in output, output
