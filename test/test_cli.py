"""The ``ppe`` command line: extract and demo end to end, and its errors."""

from __future__ import annotations

import json

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


@pytest.mark.parametrize(('args', 'message'), [
    (['-o', 'x.txt'], '.npz or .pcd'),
    (['-o', 'x.npz', '--min-plane-points', '0'], 'min-plane-points'),
])
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
