"""``ppe score SCAN PRED.npz``: the expected Hoover counts, f, k and RMSE on small hand-made cases."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ppe_ros.cli import main
from ppe_ros.core.synthetic import plane_scan
from ppe_ros.io import save_pcd


@pytest.fixture(scope='module')
def scene(tmp_path_factory):
    """A noise-free 3-plane scan as a SynPEB PCD (labels 10, 11, 12 in the intensity field)."""
    scan = plane_scan(3, rows=24, cols=32)
    folder = tmp_path_factory.mktemp('score')
    path = save_pcd(folder / 'scan.pcd', scan.points, extra_fields={'intensity': scan.labels.astype(np.float32)})
    return scan, path


def _write_prediction(path, labels):
    with open(path, 'wb') as handle:
        np.savez(handle, labels=labels.astype(np.int32), normals=np.zeros((0, 3)))
    return path


def _score_json(capsys, *argv) -> dict:
    assert main(['score', *map(str, argv), '--json']) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1
    return json.loads(out[0])


def test_perfect_prediction(scene, tmp_path, capsys):
    scan, path = scene
    pred = _write_prediction(tmp_path / 'perfect.npz', scan.labels - 9)
    result = _score_json(capsys, path, pred)
    assert result['f'] == 1.0 and result['k'] == 1.0
    assert (
        result['n_gt'],
        result['n_correct'],
        result['n_over'],
        result['n_under'],
        result['n_missed'],
        result['n_noise'],
    ) == (3, 3, 0, 0, 0, 0)
    assert result['rmse'] < 1e-6  # noise-free: every plane fits exactly
    assert result['gt_min_label'] == 10


def test_split_merged_missed_and_spurious_regions(scene, tmp_path, capsys):
    scan, path = scene
    gt = scan.labels
    sizes = {label: int(np.count_nonzero(gt == label)) for label in (10, 11, 12)}
    pred = np.zeros_like(gt)
    # label 10 (largest): split into two halves along its pixel order -> over-segmented
    rows, cols = np.nonzero(gt == 10)
    half = len(rows) // 2
    pred[rows[:half], cols[:half]] = 1
    pred[rows[half:], cols[half:]] = 2
    # labels 11 and 12 merged into one predicted plane -> under-segmented
    pred[(gt == 11) | (gt == 12)] = 3
    result = _score_json(capsys, path, _write_prediction(tmp_path / 'bad.npz', pred))
    assert (
        result['n_gt'],
        result['n_correct'],
        result['n_over'],
        result['n_under'],
        result['n_missed'],
        result['n_noise'],
    ) == (3, 0, 1, 1, 0, 0)
    assert result['f'] == 0.0 and result['k'] == 0.0
    assert result['rmse'] > 0.01  # the merged plane does not fit two walls
    # now: 10 correct, 11 missed (no plane), 12 covered by a plane of mostly unlabelled pixels is missed too,
    # and a small spurious plane on the border of 11
    pred = np.zeros_like(gt)
    pred[gt == 10] = 5
    rows, cols = np.nonzero(gt == 11)
    pred[rows[:10], cols[:10]] = 7
    result = _score_json(capsys, path, _write_prediction(tmp_path / 'partial.npz', pred))
    assert (result['n_correct'], result['n_over'], result['n_under'], result['n_missed'], result['n_noise']) == (
        1,
        0,
        0,
        2,
        1,
    )
    assert result['f'] == pytest.approx(1 / 3)
    assert result['k'] == pytest.approx(sizes[10] / sum(sizes.values()))


def test_text_output_and_labels_npy_ground_truth(scene, tmp_path, capsys):
    scan, _ = scene
    points = tmp_path / 'scan.npy'
    np.save(points, scan.points)
    gt = tmp_path / 'gt.npy'
    np.save(gt, (scan.labels - 9).astype(np.int32))  # planes 1, 2, 3 (0 = unlabelled)
    pred = _write_prediction(tmp_path / 'p.npz', scan.labels - 9)
    assert main(['score', str(points), str(pred), '--gt', str(gt)]) == 0
    text = capsys.readouterr().out
    assert 'f 100.0 %' in text and 'GT planes 3' in text and 'labels >= 1' in text


def test_prediction_from_ppe_extract(scene, tmp_path, capsys):
    _, path = scene
    out = tmp_path / 'planes.npz'
    assert main(['extract', str(path), '-o', str(out), '--lmax', '0.5', '-e', '0.0001']) == 0
    capsys.readouterr()
    result = _score_json(capsys, path, out)
    assert result['n_correct'] == 3 and result['f'] == 1.0


def test_errors(scene, tmp_path, capsys):
    scan, path = scene
    wrong = _write_prediction(tmp_path / 'wrong.npz', np.zeros((5, 5), int))
    assert main(['score', str(path), str(wrong)]) == 2
    assert 'prediction' in capsys.readouterr().err
    nolabels = tmp_path / 'nolabels.npz'
    np.savez(nolabels, normals=np.zeros((1, 3)))
    assert main(['score', str(path), str(nolabels)]) == 2
    assert 'no "labels" array' in capsys.readouterr().err
    unlabelled = tmp_path / 'plain.npy'
    np.save(unlabelled, scan.points)
    assert main(['score', str(unlabelled), str(wrong)]) == 2
    assert 'no ground truth' in capsys.readouterr().err
    assert main(['score', str(path), str(tmp_path / 'missing.npz')]) == 2
    assert 'not found' in capsys.readouterr().err


def _npy_header(shape: tuple, descr: str = '<i8') -> bytes:
    import struct

    header = repr({'descr': descr, 'fortran_order': False, 'shape': shape}).encode('latin-1')
    header += b' ' * (-(len(header) + 11) % 64) + b'\n'
    return b'\x93NUMPY\x01\x00' + struct.pack('<H', len(header)) + header


def test_damaged_or_huge_predictions_are_one_line_errors(scene, tmp_path, capsys):
    import zipfile

    _, path = scene
    empty = tmp_path / 'empty.npy'
    empty.write_bytes(b'')
    huge = tmp_path / 'huge.npz'
    with zipfile.ZipFile(huge, 'w') as archive:  # 80 bytes declaring 8 TB of labels
        archive.writestr('labels.npy', _npy_header((1000000, 1000000)))
    good = _write_prediction(tmp_path / 'good.npz', np.zeros((4, 4), int))
    cut = tmp_path / 'cut.npz'
    cut.write_bytes(good.read_bytes()[:-30])
    corrupt = tmp_path / 'corrupt.npz'
    np.savez_compressed(corrupt, labels=np.arange(10000).reshape(100, 100))
    raw = bytearray(corrupt.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    corrupt.write_bytes(bytes(raw))
    for bad, message in (
        (empty, 'no .npy header'),
        (huge, 'at most 50000000 points'),
        (cut, 'not a readable .npz'),
        (corrupt, 'not a readable .npz'),
    ):
        assert main(['score', str(path), str(bad)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f'ppe score: error: {bad}') and message in err and err.count('\n') == 1, err
