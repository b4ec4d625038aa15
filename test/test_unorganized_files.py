"""Unorganized scan files (issue 20 item 4): KITTI .bin and PCDs of HEIGHT 1 through load_scan and ppe extract."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from lidar_sweeps import HDL_LIKE_ELEVATIONS, room_sweep, shuffled

from ppe_ros.cli import main
from ppe_ros.core.extraction import extract_planes
from ppe_ros.core.projection import matched_label_agreement
from ppe_ros.io import ScanFileError, load_scan, read_pcd, save_pcd
from ppe_ros.io.kitti import read_kitti_bin, write_kitti_bin


@pytest.fixture(scope='module')
def sweep():
    """A 32-beam (HDL-like uneven) 720-column sweep of a room, 10 % no-returns."""
    points = room_sweep(HDL_LIKE_ELEVATIONS[::2], 720, sigma=0.005)
    points[np.random.default_rng(9).random(points.shape[:2]) < 0.1] = np.nan
    return points


def test_kitti_bin_round_trip_and_load_scan(tmp_path: Path, sweep):
    points, _, _ = shuffled(sweep)
    path = tmp_path / '000000.bin'
    write_kitti_bin(path, points, np.linspace(0, 1, len(points)))
    read, reflectance = read_kitti_bin(path)
    np.testing.assert_array_equal(read, points.astype(np.float32))
    assert reflectance[-1] == 1.0
    scan = load_scan(path)
    assert scan.format == 'kitti_bin' and not scan.organized and scan.shape == (1, len(points))
    np.testing.assert_array_equal(scan.points[0], read)


@pytest.mark.parametrize(
    ('content', 'message'),
    [
        (b'', 'empty file'),
        (b'\0' * 17, 'not a whole number of 16-byte points'),
    ],
)
def test_damaged_kitti_bin_is_refused_with_the_reason(tmp_path: Path, content, message):
    path = tmp_path / 'bad.bin'
    path.write_bytes(content)
    with pytest.raises(ScanFileError, match=message):
        load_scan(path)


def test_ppe_extract_labels_every_point_of_a_kitti_bin(tmp_path: Path, sweep, capsys):
    points, _, index = shuffled(sweep)
    path = tmp_path / 'sweep.bin'
    write_kitti_bin(path, points)
    out = tmp_path / 'planes.npz'
    assert (
        main(['extract', str(path), '-o', str(out), '--sensor', 'lidar', '--png', str(tmp_path / 'p.png'), '--json'])
        == 0
    )
    summary = json.loads(capsys.readouterr().out)
    assert summary['range_image'] == {
        'shape': [32, 720],
        'rows_from': 'elevation',
        'azimuth_bins': 720,
        'lost_points': 0,
    }
    labels = np.load(out)['labels']
    assert labels.shape == (len(points),)
    organized = extract_planes(sweep.astype(np.float32).astype(np.float64), sensor='lidar')
    assert matched_label_agreement(organized.labels.reshape(-1)[index], labels) >= 0.999
    assert (tmp_path / 'p.png').stat().st_size > 0
    # as a PCD: the input's height 1 and point order, a label per point
    assert main(['extract', str(path), '-o', str(tmp_path / 'planes.pcd'), '--sensor', 'lidar']) == 0
    cloud = read_pcd(tmp_path / 'planes.pcd').data
    assert cloud.shape == (1, len(points))
    np.testing.assert_array_equal(cloud['label'][0], labels)
    np.testing.assert_array_equal(cloud['x'][0], points[:, 0].astype(np.float32))


def test_ppe_extract_reads_a_pcd_of_height_1_with_a_ring_field(tmp_path: Path, sweep, capsys):
    points, rings, index = shuffled(sweep)
    path = tmp_path / 'hesai.pcd'
    save_pcd(path, points.reshape(1, -1, 3), extra_fields={'ring': rings.reshape(1, -1).astype(np.uint16)})
    assert main(['extract', str(path), '-o', str(tmp_path / 'planes.npz'), '--sensor', 'lidar', '--json']) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary['range_image']['rows_from'] == 'rings'
    labels = np.load(tmp_path / 'planes.npz')['labels']
    organized = extract_planes(sweep.astype(np.float32).astype(np.float64), sensor='lidar')
    assert matched_label_agreement(organized.labels.reshape(-1)[index], labels) >= 0.999
    # the paper's model (no profile) and two thresholds: one labelling per snapshot
    assert main(['extract', str(path), '-o', str(tmp_path / 'paper.npz'), '-e', '0.01', '0.05']) == 0
    assert np.load(tmp_path / 'paper_e0.01.npz')['labels'].shape == (len(points),)


def test_ppe_extract_transposes_a_columns_are_beams_scan(tmp_path: Path, sweep):
    path = tmp_path / 'velodyne.pcd'
    save_pcd(path, np.ascontiguousarray(sweep.transpose(1, 0, 2)))
    assert (
        main(
            [
                'extract',
                str(path),
                '-o',
                str(tmp_path / 'planes.npz'),
                '--sensor',
                'lidar',
                '--layout',
                'columns_are_beams',
            ]
        )
        == 0
    )
    labels = np.load(tmp_path / 'planes.npz')['labels']
    organized = extract_planes(load_scan(path).points.transpose(1, 0, 2), sensor='lidar')
    assert labels.shape == (720, 32)
    np.testing.assert_array_equal(labels, organized.labels.T)


def test_ppe_extract_reports_bad_projection_arguments(tmp_path: Path, sweep, capsys):
    points, _, _ = shuffled(sweep)
    path = tmp_path / 'sweep.bin'
    write_kitti_bin(path, points)
    assert main(['extract', str(path), '-o', str(tmp_path / 'p.npz'), '--azimuth-bins', '0']) == 2
    err = capsys.readouterr().err
    assert 'azimuth_bins must be' in err and 'Traceback' not in err
    assert main(['extract', str(path), '-o', str(tmp_path / 'p.npz'), '--rows', 'rings']) == 2
    assert "rows='rings' needs rings" in capsys.readouterr().err
