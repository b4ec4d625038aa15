"""Scan files -> organized clouds (ppe_ros.io) and the ``ppe info`` command."""

from __future__ import annotations

import json
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest

from ppe_ros.cli import main
from ppe_ros.io import PinholeIntrinsics, ScanFileError, backproject_depth, load_scan, read_pcd, save_pcd
from ppe_ros.io.lzf import lzf_compress, lzf_decompress

# --------------------------------------------------------------------------------------------
# the shared data sets: every file with its documented shape (../shared/data/README.md)
# --------------------------------------------------------------------------------------------

#: relative path -> (rows, columns, min valid fraction, max valid fraction, number of plane ids or None,
#:                   load_scan keyword arguments, (min, max) plausible range in metres)
SHARED_FILES: dict[str, tuple] = {
    'synpeb/test_500.pcd': (500, 500, 1.0, 1.0, 38, {}, (0.5, 10.0)),
    'synpeb/test_100.pcd': (100, 100, 1.0, 1.0, 12, {}, (0.5, 10.0)),
    'synpeb/pc_01.pcd': (500, 500, 1.0, 1.0, 60, {}, (0.5, 10.0)),
    'synpeb/pc_02.pcd': (500, 500, 1.0, 1.0, 30, {}, (0.1, 10.0)),
    'icl_nuim/icl_nuim_0.png': (480, 640, 0.99, 1.0, 17, {}, (0.5, 10.0)),
    'icl_nuim/icl_nuim_1.png': (480, 640, 0.99, 1.0, 17, {}, (0.5, 10.0)),
    'icl_nuim/icl_nuim_2.png': (480, 640, 0.99, 1.0, 17, {}, (0.5, 10.0)),
    'kinect/depth_0.png': (480, 640, 0.75, 0.95, None, {}, (0.4, 10.0)),
    'tls/andreashaus_scan000.pcd': (633, 513, 0.9, 0.99, None, {'units': 'cm'}, (0.5, 20.0)),
    'ouster/OS-0-128-U1_v2.3.0_1024x10_frame1491_xyz_m.npy': (128, 1024, 0.73, 0.92, None, {}, (0.2, 335.0)),
    'ouster/OS-1-128_v2.3.0_1024x10_lb_n3_frame1795_xyz_m.npy': (128, 1024, 0.73, 0.92, None, {}, (0.2, 335.0)),
    'ouster/OS-1-128_v2.3.0_1024x10_lb_n3_frame1796_xyz_m.npy': (128, 1024, 0.73, 0.92, None, {}, (0.2, 335.0)),
    'ouster/OS-1-128_v2.3.0_1024x10_lb_n3_frame1797_xyz_m.npy': (128, 1024, 0.73, 0.92, None, {}, (0.2, 335.0)),
    'ouster/OS-1-32-G_v2.1.1_1024x10_frame638_xyz_m.npy': (32, 1024, 0.73, 0.92, None, {}, (0.2, 335.0)),
    'ouster/OS-2-128-U1_v2.3.0_1024x10_frame1259_xyz_m.npy': (128, 1024, 0.73, 0.92, None, {}, (0.2, 335.0)),
    'ouster/OS-2-32-U0_v2.0.0_1024x10_frame5424_xyz_m.npy': (32, 1024, 0.73, 0.92, None, {}, (0.2, 335.0)),
}

SCAN_SUFFIXES = ('.pcd', '.npy', '.png')


def test_every_shared_scan_file_is_covered(shared_data: Path) -> None:
    found = {
        str(p.relative_to(shared_data))
        for p in shared_data.rglob('*')
        if p.suffix.lower() in SCAN_SUFFIXES and not p.name.endswith('_labels.npy')
    }
    assert found == set(SHARED_FILES), 'a scan file was added or removed: document it in SHARED_FILES'


@pytest.mark.parametrize('relative', sorted(SHARED_FILES))
def test_shared_file_loads_with_documented_shape(shared_data: Path, relative: str) -> None:
    rows, columns, min_valid, max_valid, n_planes, kwargs, (min_range, max_range) = SHARED_FILES[relative]
    scan = load_scan(shared_data / relative, **kwargs)
    assert scan.points.shape == (rows, columns, 3)
    assert scan.points.dtype == np.float64
    assert min_valid <= scan.valid_fraction <= max_valid
    # every pixel is either fully valid or fully NaN
    assert np.array_equal(np.isnan(scan.points).any(axis=2), np.isnan(scan.points).all(axis=2))
    ranges = np.linalg.norm(scan.points[scan.valid], axis=1)
    assert min_range <= ranges.min() and ranges.max() <= max_range
    if n_planes is None:
        assert scan.labels is None
    else:
        assert scan.labels is not None and scan.labels.shape == (rows, columns)
        assert scan.labels.dtype == np.int64
        ids = np.unique(scan.labels)
        assert int((ids >= scan.meta['min_plane_label']).sum()) == n_planes


def test_synpeb_binary_compressed_matches_the_ascii_crop(shared_data: Path) -> None:
    full = load_scan(shared_data / 'synpeb/test_500.pcd')
    assert full.meta['encoding'] == 'binary_compressed'
    crop = load_scan(shared_data / 'synpeb/test_100.pcd')
    assert crop.meta['encoding'] == 'ascii'
    # README: test_100 is exactly rows/cols 100..199 of test_500 (printed with 6 decimals)
    np.testing.assert_allclose(crop.points, full.points[100:200, 100:200], atol=2e-6, rtol=0)
    assert np.array_equal(crop.labels, full.labels[100:200, 100:200])


def test_synpeb_geometry_row_zero_is_the_top(shared_data: Path) -> None:
    scan = load_scan(shared_data / 'synpeb/pc_01.pcd')
    directions = scan.points / np.linalg.norm(scan.points, axis=2, keepdims=True)
    elevation = np.degrees(np.arcsin(directions[..., 2]))
    azimuth = np.degrees(np.arctan2(directions[..., 1], directions[..., 0]))
    # README: elevation +30 deg - (60/499) deg * row, azimuth -35 deg + 0.14 deg * col (noise is radial)
    np.testing.assert_allclose(np.median(elevation, axis=1), 30.0 - 60.0 / 499.0 * np.arange(500), atol=0.05)
    np.testing.assert_allclose(np.median(azimuth, axis=0), -35.0 + 0.14 * np.arange(500), atol=0.05)


def test_icl_nuim_labels_picked_up_and_segments_are_flat(shared_data: Path) -> None:
    scan = load_scan(shared_data / 'icl_nuim/icl_nuim_0.png')
    assert scan.meta['intrinsics'] == [481.2, 480.0, 319.5, 239.5]
    assert scan.meta['depth_scale'] == pytest.approx(1 / 5000)
    assert scan.meta['labels_source'].endswith('icl_nuim_0_labels.npy')
    assert set(np.unique(scan.labels)) == set(range(18))
    for label in range(1, 18):
        segment = scan.points[scan.labels == label]
        centred = segment - segment.mean(axis=0)
        normal = np.linalg.svd(centred, full_matrices=False)[2][2]
        # README: every labelled segment is flat to about 2.6 mm (z-depth, y-down back-projection)
        assert np.sqrt(np.mean((centred @ normal) ** 2)) < 0.003, label


def test_kinect_uses_ir_intrinsics_and_millimetres(shared_data: Path) -> None:
    scan = load_scan(shared_data / 'kinect/depth_0.png')
    fx, fy, cx, cy = scan.meta['intrinsics']
    assert (round(fx, 1), round(fy, 1), round(cx, 1), round(cy, 1)) == (575.9, 576.4, 315.2, 230.6)
    assert scan.meta['depth_scale'] == 0.001
    from PIL import Image

    depth = np.asarray(Image.open(shared_data / 'kinect/depth_0.png'))
    row, col = np.argwhere(depth > 0)[1000]
    z = depth[row, col] / 1000.0
    np.testing.assert_allclose(scan.points[row, col], [(col - cx) * z / fx, (row - cy) * z / fy, z])
    assert np.all(np.isnan(scan.points[depth == 0]))


def test_tls_scan_is_centimetres(shared_data: Path) -> None:
    raw = load_scan(shared_data / 'tls/andreashaus_scan000.pcd')
    metres = load_scan(shared_data / 'tls/andreashaus_scan000.pcd', units='cm')
    np.testing.assert_allclose(metres.points, raw.points / 100.0, equal_nan=True)
    assert 100.0 < np.nanmedian(np.linalg.norm(raw.points, axis=2)) < 1000.0


@pytest.mark.parametrize('relative', sorted(k for k in SHARED_FILES if k.startswith('ouster/')))
def test_ouster_beam_origins_reproduce_the_beam_elevations(shared_data: Path, relative: str) -> None:
    scan = load_scan(shared_data / relative)
    assert scan.origins is not None and scan.origins.shape == scan.points.shape
    sensor = json.loads(Path(scan.meta['origins_source'].split(' (')[0]).read_text())
    offset_m = sensor['lidar_origin_to_beam_origin_mm'] / 1000.0
    lift_m = sensor['lidar_to_sensor_transform'][11] / 1000.0
    np.testing.assert_allclose(np.hypot(scan.origins[..., 0], scan.origins[..., 1]), offset_m)
    np.testing.assert_allclose(scan.origins[..., 2], lift_m)
    rays = scan.points - scan.origins
    elevation = np.degrees(np.arctan2(rays[..., 2], np.hypot(rays[..., 0], rays[..., 1])))
    error = np.abs(elevation - np.asarray(sensor['beam_altitude_angles'])[:, None])[scan.valid]
    assert np.percentile(error, 99) < 0.01
    # rays from the sensor origin instead are off by up to degrees at short range
    naive = np.degrees(np.arctan2(scan.points[..., 2] - lift_m, np.hypot(scan.points[..., 0], scan.points[..., 1])))
    assert np.abs(naive - np.asarray(sensor['beam_altitude_angles'])[:, None])[scan.valid].max() > 0.01


# --------------------------------------------------------------------------------------------
# PCD files written here
# --------------------------------------------------------------------------------------------


def _grid(height: int = 3, width: int = 4) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.mgrid[0:height, 0:width]
    points = np.stack([1.0 + 0.5 * cols, -0.25 * rows, 2.0 + 0.125 * (rows + cols)], axis=-1)
    points[1, 2] = np.nan
    labels = (10 + rows * width + cols).astype(np.int64)
    return points, labels


@pytest.mark.parametrize(
    ('binary', 'compressed', 'encoding'),
    [(False, False, 'ascii'), (True, False, 'binary'), (True, True, 'binary_compressed')],
)
def test_save_pcd_round_trip(tmp_path: Path, binary: bool, compressed: bool, encoding: str) -> None:
    points, labels = _grid()
    intensity = np.linspace(0.0, 1.0, 12, dtype=np.float32).reshape(3, 4)
    ring = np.arange(12, dtype=np.uint16).reshape(3, 4)
    offset = np.full((3, 4), -7, dtype=np.int8)
    path = save_pcd(
        tmp_path / 'cloud.pcd',
        points,
        labels=labels,
        extra_fields={'intensity': intensity, 'ring': ring, 'offset': offset},
        binary=binary,
        compressed=compressed,
    )
    cloud = read_pcd(path)
    assert cloud.header.encoding == encoding
    assert cloud.header.fields == ('x', 'y', 'z', 'label', 'intensity', 'ring', 'offset')
    assert cloud.header.types == ('F', 'F', 'F', 'U', 'F', 'U', 'I')
    assert cloud.data.shape == (3, 4)
    assert np.array_equal(cloud.data['ring'], ring) and np.array_equal(cloud.data['offset'], offset)
    assert np.array_equal(cloud.data['intensity'], intensity)
    scan = load_scan(path)
    assert scan.format == 'pcd' and scan.meta['encoding'] == encoding
    np.testing.assert_array_equal(scan.points, points.astype(np.float32).astype(np.float64))
    assert np.array_equal(scan.labels, labels)
    assert scan.origins is None


def test_save_pcd_refuses_to_overwrite(tmp_path: Path) -> None:
    points, _ = _grid()
    path = save_pcd(tmp_path / 'cloud.pcd', points)
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match='refusing to overwrite'):
        save_pcd(path, points * 2.0)
    assert path.read_bytes() == before
    save_pcd(path, points * 2.0, overwrite=True)
    np.testing.assert_allclose(load_scan(path).points, points * 2.0, equal_nan=True)


def test_save_pcd_rejects_bad_input(tmp_path: Path) -> None:
    points, labels = _grid()
    with pytest.raises(ValueError, match=r'\(H, W, 3\)'):
        save_pcd(tmp_path / 'a.pcd', points[..., :2])
    with pytest.raises(ValueError, match='labels must lie in 0'):
        save_pcd(tmp_path / 'b.pcd', points, labels=labels - 20)
    with pytest.raises(ValueError, match='labels must have shape'):
        save_pcd(tmp_path / 'c.pcd', points, labels=labels[:2])
    with pytest.raises(ValueError, match='needs binary=True'):
        save_pcd(tmp_path / 'd.pcd', points, binary=False, compressed=True)
    with pytest.raises(ValueError, match='cannot be stored'):
        save_pcd(tmp_path / 'e.pcd', points, extra_fields={'flag': np.zeros((3, 4), dtype=bool)})
    assert not list(tmp_path.iterdir())


def _header(fields: str, size: str, type_: str, width: int, height: int, data: str, extra: str = '') -> bytes:
    return (
        '# .PCD v.7 - Point Cloud Data file format\nVERSION .7\n'
        f'FIELDS {fields}\nSIZE {size}\nTYPE {type_}\nCOUNT {" ".join("1" for _ in fields.split())}\n'
        f'WIDTH {width}\nHEIGHT {height}\n{extra}POINTS {width * height}\nDATA {data}\n'
    ).encode()


def test_hand_written_ascii_pcd_with_matlab_header(tmp_path: Path) -> None:
    body = '1 2 3 10\n4 5 6 11\nnan nan nan 3\n7 8 9 12\n'
    path = tmp_path / 'ascii.pcd'
    header = '# This PCD file was generated using the MATLAB\u00ae pcwrite function\n'.encode('latin-1')
    path.write_bytes(header + _header('x y z intensity', '4 4 4 4', 'F F F F', 2, 2, 'ascii') + body.encode())
    scan = load_scan(path)
    assert scan.points.shape == (2, 2, 3)
    np.testing.assert_array_equal(scan.points[0, 1], [4, 5, 6])  # point 1 is row 0, column 1
    np.testing.assert_array_equal(scan.points[1, 1], [7, 8, 9])
    assert np.all(np.isnan(scan.points[1, 0]))
    assert scan.labels.tolist() == [[10, 11], [3, 12]]
    assert scan.meta['min_plane_label'] == 10


def test_hand_written_binary_pcd_with_padding_field_and_viewpoint(tmp_path: Path) -> None:
    # PCL style: a one-byte padding field "_" and a uint8 label; a viewpoint 1 m above the origin
    values = [(1.0, 2.0, 3.0, 0, 5), (4.0, 5.0, 6.0, 0, 6), (7.0, 8.0, 9.0, 0, 7), (0.0, 0.0, 0.0, 0, 0)]
    body = b''.join(struct.pack('<fffBB', *v) for v in values)
    path = tmp_path / 'binary.pcd'
    extra = 'VIEWPOINT 0 0 100 1 0 0 0\n'
    path.write_bytes(_header('x y z _ label', '4 4 4 1 1', 'F F F U U', 2, 2, 'binary', extra) + body)
    scan = load_scan(path, units='cm')
    np.testing.assert_allclose(scan.points[0, 0], [0.01, 0.02, 0.03])
    assert np.all(np.isnan(scan.points[1, 1]))  # exactly (0, 0, 0) = no return
    assert scan.labels.tolist() == [[5, 6], [7, 0]]
    np.testing.assert_allclose(scan.origins, [0.0, 0.0, 1.0])


def test_intensity_is_ground_truth_only_when_it_holds_plane_ids(tmp_path: Path) -> None:
    points, labels = _grid()
    measured = save_pcd(
        tmp_path / 'measured.pcd', points, extra_fields={'intensity': np.full((3, 4), 0.37, dtype=np.float32)}
    )
    assert load_scan(measured).labels is None  # a real intensity is not a label
    with pytest.raises(ScanFileError, match='intensity field is not whole numbers'):
        load_scan(measured, intensity_labels=True)
    ids = save_pcd(tmp_path / 'ids.pcd', points, extra_fields={'intensity': labels.astype(np.float32)})
    assert np.array_equal(load_scan(ids).labels, labels)
    assert load_scan(ids, intensity_labels=False).labels is None
    plain = save_pcd(tmp_path / 'plain.pcd', points)
    with pytest.raises(ScanFileError, match='no intensity field'):
        load_scan(plain, intensity_labels=True)


def _literal_lzf(payload: bytes) -> bytes:
    """An LZF block made of literal runs only (independent of ppe_ros's compressor)."""
    out = bytearray()
    for start in range(0, len(payload), 32):
        chunk = payload[start : start + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def test_hand_written_binary_compressed_pcd_is_field_by_field(tmp_path: Path) -> None:
    xyz = np.arange(18, dtype=np.float32).reshape(6, 3) + 1.0
    intensity = np.array([10, 11, 12, 13, 14, 15], dtype=np.float32)
    payload = xyz[:, 0].tobytes() + xyz[:, 1].tobytes() + xyz[:, 2].tobytes() + intensity.tobytes()
    block = _literal_lzf(payload)
    path = tmp_path / 'compressed.pcd'
    header = _header('x y z intensity', '4 4 4 4', 'F F F F', 3, 2, 'binary_compressed')
    path.write_bytes(header + struct.pack('<II', len(block), len(payload)) + block)
    scan = load_scan(path)
    np.testing.assert_array_equal(scan.points.reshape(6, 3), xyz)
    assert scan.labels.tolist() == [[10, 11, 12], [13, 14, 15]]


def test_lzf_back_references_and_round_trip() -> None:
    # 'abcabcabca': literal 'abc' then a match of length 7 at distance 3 (overlapping copy)
    block = bytes([2]) + b'abc' + bytes([(5 << 5) | 0, 2])
    assert lzf_decompress(block, 10).tobytes() == b'abcabcabca'
    rng = np.random.default_rng(1)
    for data in (
        b'',
        b'a',
        bytes(1000),
        rng.integers(0, 4, 5000).astype(np.uint8).tobytes(),
        rng.integers(0, 256, 3000).astype(np.uint8).tobytes(),
    ):
        assert lzf_decompress(lzf_compress(data), len(data)).tobytes() == data
    assert len(lzf_compress(bytes(10000))) < 200
    with pytest.raises(ValueError, match='back-reference before the start'):
        lzf_decompress(bytes([(1 << 5) | 0, 5]), 3)
    with pytest.raises(ValueError, match='ends inside a run'):
        lzf_decompress(bytes([9]) + b'abc', 10)
    with pytest.raises(ValueError, match='expected 12 decompressed bytes, found 10'):
        lzf_decompress(block, 12)
    with pytest.raises(ValueError, match='expands beyond the expected 5 bytes'):
        lzf_decompress(block, 5)


@pytest.mark.parametrize('encoding', ['ascii', 'binary', 'binary_compressed'])
def test_truncated_pcd_says_expected_and_found(tmp_path: Path, encoding: str) -> None:
    points, labels = _grid(20, 30)
    full = save_pcd(
        tmp_path / 'full.pcd',
        points,
        labels=labels,
        binary=encoding != 'ascii',
        compressed=encoding == 'binary_compressed',
    )
    raw = full.read_bytes()
    cut = tmp_path / 'cut.pcd'
    cut.write_bytes(raw[: len(raw) - 100])
    expected_message = {
        'ascii': r'truncated DATA ascii: expected 2400 values .* found 23\d\d',
        'binary': r'truncated DATA binary: expected 9600 bytes .* found 9500',
        'binary_compressed': r'truncated DATA binary_compressed: expected \d+ compressed bytes, found \d+',
    }[encoding]
    with pytest.raises(ScanFileError, match=expected_message):
        load_scan(cut)


def test_corrupt_compressed_sizes_and_headers(tmp_path: Path) -> None:
    header = _header('x y z', '4 4 4', 'F F F', 2, 2, 'binary_compressed')
    path = tmp_path / 'bad.pcd'
    path.write_bytes(header + struct.pack('<II', 10, 40) + bytes(10))
    with pytest.raises(ScanFileError, match='says 40 raw bytes, the header needs 48'):
        load_scan(path)
    path.write_bytes(header + b'\x01\x00')
    with pytest.raises(ScanFileError, match='expected an 8-byte size prefix, found 2 bytes'):
        load_scan(path)
    payload = bytes(48)
    block = _literal_lzf(payload)[:-5]
    path.write_bytes(header + struct.pack('<II', len(block), 48) + block)
    with pytest.raises(ScanFileError, match='corrupt or truncated LZF data'):
        load_scan(path)
    path.write_bytes(_header('x y z', '4 4 4', 'F F F', 2, 2, 'binary')[:60])
    with pytest.raises(ScanFileError, match='no DATA line'):
        load_scan(path)
    path.write_bytes(b'ply\nformat ascii 1.0\n')
    with pytest.raises(ScanFileError, match='not a PCD file'):
        load_scan(path)
    path.write_bytes(_header('x y z', '4 4 4', 'F F F', 2, 2, 'binary').replace(b'POINTS 4', b'POINTS 5'))
    with pytest.raises(ScanFileError, match='POINTS 5 differs from WIDTH × HEIGHT'):
        load_scan(path)
    path.write_bytes(_header('x y z', '4 4 2', 'F F F', 2, 2, 'binary') + bytes(40))
    with pytest.raises(ScanFileError, match="field 'z': unsupported TYPE F with SIZE 2"):
        load_scan(path)
    path.write_bytes(_header('x y z', '4 4 4', 'F F F', 2, 2, 'lzma') + bytes(48))
    with pytest.raises(ScanFileError, match="unsupported PCD DATA encoding 'lzma'"):
        load_scan(path)
    path.write_bytes(_header('a b c', '4 4 4', 'F F F', 2, 2, 'binary') + bytes(48))
    with pytest.raises(ScanFileError, match='no x/y/z field'):
        load_scan(path)
    path.write_bytes(_header('x y z', '4 4 4', 'F F F', 2, 2, 'ascii') + b'1 2 3\n4 5 6\n7 8 x\n1 1 1\n')
    with pytest.raises(ScanFileError, match='not a number'):
        load_scan(path)


def test_unorganized_pcd_is_read_as_a_point_list(tmp_path: Path) -> None:
    """HEIGHT 1: a lidar's point list (issue 20), in the file's order; a ring field gives Scan.rings."""
    path = tmp_path / 'list.pcd'
    path.write_bytes(_header('x y z', '4 4 4', 'F F F', 3, 1, 'ascii') + b'1 2 3\n4 5 6\n7 8 9\n')
    assert read_pcd(path).data.shape == (1, 3)
    scan = load_scan(path)
    assert scan.points.shape == (1, 3, 3) and not scan.organized and scan.rings is None
    np.testing.assert_array_equal(scan.points[0, 1], [4, 5, 6])
    ringed = tmp_path / 'ringed.pcd'
    ringed.write_bytes(_header('x y z ring', '4 4 4 2', 'F F F U', 3, 1, 'ascii') + b'1 2 3 7\n4 5 6 0\n7 8 9 3\n')
    np.testing.assert_array_equal(load_scan(ringed).rings, [[7, 0, 3]])


def test_missing_and_unknown_files(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match='scan file not found'):
        load_scan(tmp_path / 'nothing.pcd')
    other = tmp_path / 'scan.ply'
    other.write_bytes(b'ply\n')
    with pytest.raises(ScanFileError, match=r"unknown scan format '\.ply'"):
        load_scan(other)
    points, _ = _grid()
    path = save_pcd(tmp_path / 'cloud.pcd', points)
    with pytest.raises(ValueError, match='units must be one of'):
        load_scan(path, units='inch')
    with pytest.raises(FileNotFoundError, match='labels file not found'):
        load_scan(path, gt=tmp_path / 'none.npy')


# --------------------------------------------------------------------------------------------
# NPY, labels, depth PNG
# --------------------------------------------------------------------------------------------


def test_npy_scan_units_and_ground_truth(tmp_path: Path) -> None:
    points, labels = _grid()
    np.save(tmp_path / 'scan.npy', (points * 1000.0).astype(np.float32))
    scan = load_scan(tmp_path / 'scan.npy', units='mm')
    np.testing.assert_allclose(scan.points, points, equal_nan=True, rtol=1e-6)
    assert scan.labels is None and scan.origins is None
    np.save(tmp_path / 'gt.npy', labels.astype(np.int32))
    assert np.array_equal(load_scan(tmp_path / 'scan.npy', gt=tmp_path / 'gt.npy').labels, labels)
    np.save(tmp_path / 'scan_labels.npy', labels)  # picked up automatically
    assert np.array_equal(load_scan(tmp_path / 'scan.npy').labels, labels)
    np.save(tmp_path / 'short.npy', labels[:2])
    with pytest.raises(ScanFileError, match=r'labels have shape \(2, 4\), the scan is \(3, 4\)'):
        load_scan(tmp_path / 'scan.npy', gt=tmp_path / 'short.npy')
    np.save(tmp_path / 'flat.npy', points.reshape(-1, 3))
    with pytest.raises(ScanFileError, match=r'expected an organized \(H, W, 3\) array .* found shape \(12, 3\)'):
        load_scan(tmp_path / 'flat.npy')
    (tmp_path / 'broken.npy').write_bytes((tmp_path / 'scan.npy').read_bytes()[:100])
    with pytest.raises(ScanFileError, match=r'not a readable \.npy'):
        load_scan(tmp_path / 'broken.npy')


def test_depth_png_with_explicit_intrinsics(tmp_path: Path) -> None:
    from PIL import Image

    depth = np.array([[0, 1000, 2000], [1500, 0, 3000]], dtype=np.uint16)
    path = tmp_path / 'depth.png'
    Image.fromarray(depth).save(path)
    with pytest.raises(ScanFileError, match='no camera intrinsics'):
        load_scan(path)
    with pytest.raises(ScanFileError, match='unknown depth unit'):
        load_scan(path, intrinsics=(100.0, 110.0, 1.0, 0.5))
    scan = load_scan(path, intrinsics=(100.0, 110.0, 1.0, 0.5), units='mm')
    assert scan.points.shape == (2, 3, 3)
    assert np.all(np.isnan(scan.points[0, 0])) and np.all(np.isnan(scan.points[1, 1]))
    np.testing.assert_allclose(scan.points[1, 2], [(2 - 1.0) * 3.0 / 100.0, (1 - 0.5) * 3.0 / 110.0, 3.0])
    np.testing.assert_allclose(scan.points[0, 1, 2], 1.0)
    scaled = load_scan(path, intrinsics=(100.0, 110.0, 1.0, 0.5), depth_scale=0.0002)
    np.testing.assert_allclose(scaled.points[0, 1, 2], 0.2)
    with pytest.raises(ValueError, match='focal lengths must be positive'):
        load_scan(path, intrinsics=(100.0, -110.0, 1.0, 0.5), units='mm')
    Image.fromarray(depth.astype(np.uint8)).save(tmp_path / 'eight_bit.png')
    with pytest.raises(ScanFileError, match="expected a 16-bit single-channel depth PNG, found image mode 'L'"):
        load_scan(tmp_path / 'eight_bit.png', intrinsics=(1.0, 1.0, 0.0, 0.0), units='mm')


def test_depth_png_calibration_files_next_to_it(tmp_path: Path) -> None:
    from PIL import Image

    depth = np.full((4, 5), 5000, dtype=np.uint16)
    icl = tmp_path / 'icl'
    icl.mkdir()
    Image.fromarray(depth).save(icl / 'frame.png')
    (icl / 'camera.K').write_text('4.812e+02 0. 3.195e+02\n0. -4.80e+02 2.395e+02\n0. 0. 1.')
    scan = load_scan(icl / 'frame.png')
    assert scan.meta['intrinsics'] == [481.2, 480.0, 319.5, 239.5]
    np.testing.assert_allclose(scan.points[..., 2], 1.0)  # 5000 counts = 1 m
    assert np.all(scan.points[..., 1] < 0)  # rows above cy are up: negative y in a y-down frame
    (icl / 'other.K').write_text('1 0 0 0 1 0 0 0 1')
    with pytest.raises(ScanFileError, match='several camera matrix files'):
        load_scan(icl / 'frame.png')
    # explicit arguments need no calibration file
    scan = load_scan(icl / 'frame.png', intrinsics=(500.0, 500.0, 2.0, 1.5), units='mm')
    np.testing.assert_allclose(scan.points[..., 2], 5.0)
    (icl / 'other.K').unlink()
    (icl / 'camera.K').write_text('0 0 3.195e+02\n0. -4.80e+02 2.395e+02\n0. 0. 1.')  # fx = 0
    with pytest.raises(ScanFileError, match=rf'^{icl / "camera.K"}: unusable camera matrix: focal lengths must be'):
        load_scan(icl / 'frame.png')
    (icl / 'camera.K').unlink()
    (icl / 'calib_params.xml').write_text(
        '<opencv_storage><IR_intrinsic_params><data>nan 0 1 0 1 1 0 0 1</data></IR_intrinsic_params></opencv_storage>'
    )
    with pytest.raises(ScanFileError, match=r'calib_params\.xml: unusable camera matrix: intrinsics must be finite'):
        load_scan(icl / 'frame.png')


def test_backproject_depth_validates() -> None:
    camera = PinholeIntrinsics(500.0, 500.0, 1.0, 1.0)
    with pytest.raises(ValueError, match='depth_scale must be a positive'):
        backproject_depth(np.ones((2, 2)), camera, 0.0)
    with pytest.raises(ValueError, match=r'\(H, W\) image'):
        backproject_depth(np.ones(4), camera, 0.001)
    with pytest.raises(ValueError, match=r'rays must be \(2, 2, 2\) for this depth image; got \(2, 3, 2\)'):
        backproject_depth(np.ones((2, 2)), camera, 0.001, rays=np.zeros((2, 3, 2)))


def test_backproject_depth_along_given_rays() -> None:
    """Each point is z times its pixel's ray (x / z, y / z, 1); a NaN ray is no return."""
    rays = np.array([[[0.5, -0.25], [np.nan, np.nan]], [[0.0, 0.0], [-1.0, 2.0]]])
    cloud = backproject_depth(
        np.array([[2000, 1000], [0, 500]]), PinholeIntrinsics(1.0, 1.0, 0.0, 0.0), 0.001, rays=rays
    )
    np.testing.assert_array_equal(cloud[0, 0], [1.0, -0.5, 2.0])
    np.testing.assert_array_equal(cloud[1, 1], [-0.5, 1.0, 0.5])
    assert np.isnan(cloud[0, 1]).all() and np.isnan(cloud[1, 0]).all()  # no ray; no depth


# --------------------------------------------------------------------------------------------
# ppe info
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize('relative', sorted(SHARED_FILES))
def test_info_on_every_shared_file(shared_data: Path, relative: str, capsys: pytest.CaptureFixture[str]) -> None:
    rows, columns, min_valid, max_valid, n_planes, kwargs, _ = SHARED_FILES[relative]
    argv = ['info', str(shared_data / relative)]
    if 'units' in kwargs:
        argv += ['--units', kwargs['units']]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert f'{rows} rows x {columns} columns' in text
    assert 'range |p| [m]' in text and 'bounding box [m]' in text
    assert ('ground truth:    none' in text) == (n_planes is None)
    if n_planes is not None:
        assert f'{n_planes} planes' in text

    assert main([*argv, '--json']) == 0
    summary = json.loads(capsys.readouterr().out)
    assert (summary['rows'], summary['columns']) == (rows, columns)
    assert min_valid <= summary['valid_fraction'] <= max_valid
    assert summary['range_m']['min'] <= summary['range_m']['median'] <= summary['range_m']['max']
    assert len(summary['bounding_box_m']['min']) == 3
    if n_planes is not None:
        assert summary['labels']['planes'] == n_planes
        assert summary['labels']['points_per_plane']['min'] >= 1
        assert sum(summary['labels']['counts'].values()) == rows * columns


def test_info_synpeb_counts_ids_from_ten(shared_data: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(['info', '--json', str(shared_data / 'synpeb/pc_01.pcd')]) == 0
    labels = json.loads(capsys.readouterr().out)['labels']
    assert labels['min_plane_label'] == 10 and labels['ids_ge_10'] == 60 and labels['planes'] == 60
    assert labels['unlabelled_points'] == labels['counts']['3']


def test_info_warns_about_centimetres(shared_data: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(['info', str(shared_data / 'tls/andreashaus_scan000.pcd')]) == 0
    assert 'are the coordinates in cm or mm?' in capsys.readouterr().out


def test_info_with_gt_and_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    points, labels = _grid()
    path = save_pcd(tmp_path / 'cloud.pcd', points)
    np.save(tmp_path / 'gt.npy', labels)
    assert main(['info', str(path), '--gt', str(tmp_path / 'gt.npy'), '--json']) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary['labels']['distinct_ids'] == 12 and summary['valid_points'] == 11
    assert main(['info', str(tmp_path / 'missing.pcd')]) == 2
    assert 'scan file not found' in capsys.readouterr().err
    cut = tmp_path / 'cut.pcd'
    cut.write_bytes(path.read_bytes()[:-10])
    assert main(['info', str(cut)]) == 2
    assert 'truncated DATA binary' in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# issue 17: declared sizes checked before allocating, damaged headers and sidecars, atomic writes
# --------------------------------------------------------------------------------------------


def _png_bytes(width: int, height: int, idat: bytes, bit_depth: int = 16) -> bytes:
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack('>I', len(data)) + kind + data + struct.pack('>I', zlib.crc32(kind + data))

    ihdr = struct.pack('>IIBBBBB', width, height, bit_depth, 0, 0, 0, 0)
    return b'\x89PNG\r\n\x1a\n' + chunk(b'IHDR', ihdr) + chunk(b'IDAT', idat) + chunk(b'IEND', b'')


def _npy_with_header(shape: tuple, descr: str = '<f8', data: bytes = b'') -> bytes:
    header = repr({'descr': descr, 'fortran_order': False, 'shape': shape}).encode('latin-1')
    header += b' ' * (-(len(header) + 11) % 64) + b'\n'
    return b'\x93NUMPY\x01\x00' + struct.pack('<H', len(header)) + header + data


def _peak_allocation(function) -> int:
    """Peak bytes allocated by numpy and Python while ``function()`` runs (tracemalloc)."""
    import tracemalloc

    tracemalloc.start()
    try:
        function()
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak


@pytest.mark.parametrize(
    ('name', 'content', 'message'),
    [
        # a 280-byte-scale PNG claiming 12000 x 12000 (the file was all zeros, 280 KB)
        (
            'zeros.png',
            _png_bytes(12000, 12000, b'x\x9c' + bytes(100)),
            r'zeros\.png: declares a 12000 x 12000 depth image .* = 144000000 points; at most 50000000 points',
        ),
        (
            'bomb.png',
            _png_bytes(100000, 100000, b'x\x9c' + bytes(10)),
            r'bomb\.png: declares a 100000 x 100000 depth image',
        ),
        (
            'thin.png',
            _png_bytes(200000, 2, b'x\x9c' + bytes(10)),
            r'thin\.png: declares a 2 x 200000 depth image .* at '
            r'most 100000 rows and columns',
        ),
        (
            'ratio.png',
            _png_bytes(5000, 5000, b'x\x9c' + bytes(10)),
            r'ratio\.png: corrupt PNG: a file of \d+ bytes cannot '
            r'hold the declared 5000 x 5000 image .*deflate expands at most 1032-fold',
        ),
        (
            'huge.npy',
            _npy_with_header((1000000, 1000000, 3)),
            r'huge\.npy: declares a 1000000 x 1000000 grid \(\.npy shape\) = 1000000000000 points; at most 50000000',
        ),
        (
            'short.npy',
            _npy_with_header((1000, 1000, 3), data=bytes(800)),
            r'short\.npy: truncated \.npy data: the header declares shape \(1000, 1000, 3\) of float64 = '
            r'24000000 bytes, the file holds 800',
        ),
        (
            'gig.pcd',
            _header('x y z', '4 4 4', 'F F F', 10000, 9000, 'binary_compressed')
            + struct.pack('<II', 20, 1080000000)
            + bytes(20),
            r'gig\.pcd: PCD header declares 90000000 points .* at most 50000000 points per scan',
        ),
        (
            'lzf.pcd',
            _header('x y z', '4 4 4', 'F F F', 1000, 1000, 'binary_compressed')
            + struct.pack('<II', 100, 12000000)
            + bytes(100),
            r'lzf\.pcd: corrupt DATA binary_compressed: 100 compressed bytes cannot expand to the declared '
            r'12000000 raw bytes \(LZF expands at most 88-fold\)',
        ),
        (
            'wide.pcd',
            _header('x y z', '4 4 4', 'F F F', 200000, 2, 'binary'),
            r'wide\.pcd: PCD header declares a 2 × '
            r'200000 grid; at most 100000 rows and columns',
        ),
        (
            'ascii.pcd',
            _header('x y z', '4 4 4', 'F F F', 5000, 5000, 'ascii') + b'1 2 3\n',
            r'ascii\.pcd: truncated DATA '
            r'ascii: expected 75000000 values .* found only 6 bytes of text',
        ),
        (
            'count.pcd',
            _header('x y z', '4 4 4', 'F F F', 2, 2, 'binary').replace(b'COUNT 1 1 1', b'COUNT 1 1 2147483648'),
            r'count\.pcd: PCD header COUNT declares 2147483650 values per point; at most 4096',
        ),
    ],
)
def test_declared_sizes_are_checked_before_allocating(tmp_path: Path, name: str, content: bytes, message: str) -> None:
    path = tmp_path / name
    path.write_bytes(content)

    def load() -> None:
        with pytest.raises(ScanFileError, match=message):
            load_scan(path, intrinsics=(500.0, 500.0, 320.0, 240.0), units='mm') if name.endswith(
                '.png'
            ) else load_scan(path)

    assert _peak_allocation(load) < 4_000_000  # bytes: nothing of the declared size was allocated


@pytest.mark.parametrize('chunk', [b'IHDR', b'IDAT'])
@pytest.mark.parametrize('declared', [10**6, 956301368, 2**32 - 1])
def test_a_png_chunk_longer_than_the_file_is_refused_before_reading(
    tmp_path: Path, chunk: bytes, declared: int
) -> None:
    """A chunk length beyond the file's end (one flipped byte of a small PNG) is a ScanFileError before Pillow
    reads the chunk: Python would allocate the declared length (up to 4 GB) for it first."""
    from PIL import Image

    path = tmp_path / 'depth.png'
    Image.fromarray(np.arange(12, dtype=np.uint16).reshape(3, 4) * 1000).save(path)
    content = bytearray(path.read_bytes())
    at = content.index(chunk) - 4
    content[at : at + 4] = struct.pack('>I', declared)
    path.write_bytes(bytes(content))
    left = len(content) - at - 8
    message = rf"^{path}: corrupt PNG: chunk '{chunk.decode()}' at byte {at} declares {declared} bytes of data, "
    message += rf'the file has {left} left$'

    def load() -> None:
        with pytest.raises(ScanFileError, match=message):
            load_scan(path, intrinsics=(10.0, 10.0, 2.0, 1.5), units='mm')

    assert _peak_allocation(load) < 4_000_000  # bytes


def test_a_png_whose_end_marker_declares_data_is_read(tmp_path: Path) -> None:
    """IEND's length is not checked: Pillow does not read it, and the pixels are all in the file."""
    from PIL import Image

    path = tmp_path / 'depth.png'
    Image.fromarray(np.arange(12, dtype=np.uint16).reshape(3, 4) * 1000).save(path)
    full = load_scan(path, intrinsics=(10.0, 10.0, 2.0, 1.5), units='mm').points
    content = bytearray(path.read_bytes())
    at = content.index(b'IEND') - 4
    content[at : at + 4] = struct.pack('>I', 2**32 - 1)
    path.write_bytes(bytes(content))
    np.testing.assert_array_equal(load_scan(path, intrinsics=(10.0, 10.0, 2.0, 1.5), units='mm').points, full)


def test_a_signalling_nan_in_a_pcd_is_a_no_return_without_a_warning(tmp_path: Path) -> None:
    """A damaged binary PCD can hold float32 signalling NaNs; their conversion to float64 sets numpy's
    invalid flag, which printed a RuntimeWarning: the point is a no-return, quietly."""
    points, _ = _grid()
    path = save_pcd(tmp_path / 'scan.pcd', points)
    content = bytearray(path.read_bytes())
    data = content.index(b'DATA binary\n') + len(b'DATA binary\n')
    content[data : data + 4] = struct.pack('<I', 0x7F800001)  # x of the first point
    path.write_bytes(bytes(content))
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        scan = load_scan(path)
    assert np.isnan(scan.points[0, 0]).all() and np.isfinite(scan.points[0, 1]).all()


def test_every_truncation_of_a_png_is_a_scan_file_error(tmp_path: Path) -> None:
    from PIL import Image

    path = tmp_path / 'depth.png'
    Image.fromarray(np.arange(12, dtype=np.uint16).reshape(3, 4) * 1000).save(path)
    content = path.read_bytes()
    full = load_scan(path, intrinsics=(10.0, 10.0, 2.0, 1.5), units='mm').points
    # the IDAT data end 8 bytes before 'IEND' (its CRC, IEND's length); the last 5 of them (zlib's Adler-32,
    # the end of the last deflate block) are not needed for the pixels
    image_data_end = content.index(b'IEND') - 8 - 5
    for length in range(len(content)):
        path.write_bytes(content[:length])
        if length < image_data_end:
            with pytest.raises(ScanFileError, match=rf'^{path}: '):
                load_scan(path, intrinsics=(10.0, 10.0, 2.0, 1.5), units='mm')
        else:  # only checksums or the end marker are missing: Pillow reads all pixels
            try:
                points = load_scan(path, intrinsics=(10.0, 10.0, 2.0, 1.5), units='mm').points
            except ScanFileError as exc:
                assert str(exc).startswith(f'{path}: ')
            else:
                np.testing.assert_array_equal(points, full)


def test_labels_npy_with_a_huge_or_damaged_header_is_refused_before_reading(tmp_path: Path) -> None:
    points, _ = _grid()
    scan = tmp_path / 'scan.npy'
    np.save(scan, points)
    gt = tmp_path / 'gt.npy'
    gt.write_bytes(_npy_with_header((1000000, 1000000), '<i8'))

    def load() -> None:
        with pytest.raises(
            ScanFileError,
            match=r'gt\.npy: ground-truth labels have shape \(1000000, 1000000\), '
            r'the scan is \(3, 4\)',
        ):
            load_scan(scan, gt=gt)

    assert _peak_allocation(load) < 4_000_000
    gt.write_bytes(_npy_with_header((3, 4), '|O'))
    with pytest.raises(ScanFileError, match='holds Python objects'):
        load_scan(scan, gt=gt)


@pytest.mark.parametrize('which', ['scan', 'gt', 'sidecar'])
def test_empty_npy_files_are_a_scan_file_error(tmp_path: Path, which: str) -> None:
    points, _ = _grid()
    scan = tmp_path / 'scan.npy'
    np.save(scan, points)
    empty = {'scan': scan, 'gt': tmp_path / 'gt.npy', 'sidecar': tmp_path / 'scan_labels.npy'}[which]
    empty.write_bytes(b'')
    with pytest.raises(
        ScanFileError,
        match=rf'{empty.name}: not a readable .* \(no \.npy header; empty or not a '
        rf'\.npy file\)',
    ):
        load_scan(scan, gt=empty if which == 'gt' else None)


def test_every_flipped_byte_of_a_npy_header_is_a_scan_file_error(tmp_path: Path) -> None:
    points, _ = _grid()
    np.save(tmp_path / 'good.npy', points)
    good = (tmp_path / 'good.npy').read_bytes()
    header_end = good.index(b'\n') + 1
    path = tmp_path / 'flipped.npy'
    outcomes = set()
    for index in range(header_end):
        for mask in (0x01, 0x20, 0xFF):
            damaged = bytearray(good)
            damaged[index] ^= mask
            path.write_bytes(bytes(damaged))
            try:
                scan = load_scan(path)
            except ScanFileError as exc:
                assert str(exc).startswith(f'{path}: ') and '\n' not in str(exc)
                outcomes.add('error')
            else:
                assert scan.points.shape[2] == 3
                outcomes.add('read')
    assert 'error' in outcomes


def _ouster_fixture(tmp_path: Path) -> tuple[Path, dict]:
    points = np.random.default_rng(0).uniform(1.0, 5.0, size=(4, 8, 3))
    np.save(tmp_path / 'os_frame1_xyz_m.npy', points)
    metadata = {
        'lidar_origin_to_beam_origin_mm': 15.8,
        'lidar_to_sensor_transform': [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 36.18, 0, 0, 0, 1],
        'data_format': {
            'pixels_per_column': 4,
            'columns_per_frame': 8,
            'column_window': [0, 7],
            'pixel_shift_by_row': [0, 1, 2, 3],
        },
    }
    return tmp_path / 'os_frame1_xyz_m.npy', metadata


def test_ouster_sidecar_is_read(tmp_path: Path) -> None:
    scan_path, metadata = _ouster_fixture(tmp_path)
    (tmp_path / 'os.json').write_text(json.dumps(metadata))
    scan = load_scan(scan_path)
    assert scan.origins.shape == (4, 8, 3)
    np.testing.assert_allclose(np.linalg.norm(scan.origins[..., :2], axis=-1), 0.0158)


@pytest.mark.parametrize(
    ('edit', 'message'),
    [
        (lambda m: m.update(data_format=None), 'data_format must be a JSON object; found null'),
        (lambda m: m.update(data_format=[4, 8]), 'data_format must be a JSON object; found list'),
        (
            lambda m: m.update(lidar_origin_to_beam_origin_mm=None),
            'lidar_origin_to_beam_origin_mm must be a finite number; found null',
        ),
        (
            lambda m: m.update(lidar_origin_to_beam_origin_mm='15'),
            'lidar_origin_to_beam_origin_mm must be a finite number',
        ),
        (
            lambda m: m['data_format'].update(pixels_per_column=None),
            'data_format.pixels_per_column must be a positive integer; found null',
        ),
        (
            lambda m: m['data_format'].update(pixel_shift_by_row=[0, None, 2, 3]),
            r'data_format.pixel_shift_by_row\[1\] must be a finite',
        ),
        (
            lambda m: m['data_format'].update(pixel_shift_by_row=[0, 1]),
            r'data_format.pixel_shift_by_row must be 4 numbers \(one per row\); found 2 values',
        ),
        (
            lambda m: m.update(lidar_to_sensor_transform=list(range(15))),
            r'lidar_to_sensor_transform must be 16 numbers '
            r'\(a row-major 4 x 4 matrix\); found 15 values',
        ),
        (lambda m: m.clear(), 'not Ouster sensor metadata'),
    ],
)
def test_ouster_sidecar_with_null_or_wrong_fields_names_the_file(tmp_path: Path, edit, message: str) -> None:
    scan_path, metadata = _ouster_fixture(tmp_path)
    edit(metadata)
    sidecar = tmp_path / 'os.json'
    sidecar.write_text(json.dumps(metadata))
    with pytest.raises(ScanFileError, match=rf'^{sidecar}: {message}'):
        load_scan(scan_path)
    sidecar.write_text('[1, 2]')
    with pytest.raises(ScanFileError, match=rf'^{sidecar}: not Ouster sensor metadata \(a JSON list'):
        load_scan(scan_path)


class _FullDisk:
    """A binary stream that takes ``room`` bytes, then raises OSError(ENOSPC) like a full disk."""

    def __init__(self, stream, room: int, error: BaseException | None = None) -> None:
        self.stream, self.room, self.error = stream, room, error

    def write(self, data) -> int:
        import errno
        import os

        data = bytes(data)
        if len(data) > self.room:
            self.stream.write(data[: self.room])
            self.room = 0
            raise self.error or OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.room -= len(data)
        return self.stream.write(data)

    def __getattr__(self, name):
        return getattr(self.stream, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.stream.close()


def full_disk(monkeypatch: pytest.MonkeyPatch, room: int, error: BaseException | None = None) -> None:
    """Make every file written through ppe_ros.io.files hit a full disk (or ``error``) after ``room`` bytes."""
    import ppe_ros.io.files as files

    original = files._open_for_writing
    monkeypatch.setattr(files, '_open_for_writing', lambda path: _FullDisk(original(path), room, error))


def test_save_pcd_on_a_full_disk_leaves_no_file_and_keeps_the_old_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    points, labels = _grid(20, 30)
    full_disk(monkeypatch, room=500)
    target = tmp_path / 'out.pcd'
    with pytest.raises(OSError, match='No space left'):
        save_pcd(target, points, labels=labels)
    assert list(tmp_path.iterdir()) == []  # neither the target nor a temporary file
    target.write_bytes(b'old')
    with pytest.raises(OSError, match='No space left'):
        save_pcd(target, points, labels=labels, overwrite=True)
    assert target.read_bytes() == b'old' and list(tmp_path.iterdir()) == [target]
    monkeypatch.undo()
    save_pcd(target, points, labels=labels, overwrite=True)
    assert read_pcd(target).data.shape == (20, 30) and list(tmp_path.iterdir()) == [target]


def test_ctrl_c_while_writing_leaves_no_temporary_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    points, labels = _grid(20, 30)
    target = tmp_path / 'out.pcd'
    target.write_bytes(b'old')
    full_disk(monkeypatch, room=700, error=KeyboardInterrupt())
    with pytest.raises(KeyboardInterrupt):
        save_pcd(target, points, labels=labels, overwrite=True)
    assert target.read_bytes() == b'old' and list(tmp_path.iterdir()) == [target]
