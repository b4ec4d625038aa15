"""Bounded, seeded fuzzing of the scan-file readers and of ``ppe info`` / ``ppe extract`` (issue 17).

About 400 mutated files (PCD ascii / binary / binary_compressed, NPY scans and labels, 16-bit PNG,
Ouster JSON sidecars): byte flips, truncations, header edits and huge declared sizes. Every one goes
through :func:`load_scan` in process; a seeded sample goes through the ``ppe`` command line in
subprocesses. What must hold:

* the loader returns a well-formed :class:`Scan` or raises :class:`ScanFileError` whose one-line
  message starts with the offending file's name; never another exception;
* in process, no load allocates more than :data:`IN_PROCESS_PEAK_BYTES` (tracemalloc);
* a ``ppe`` subprocess exits 0, or 2 with exactly one line ``ppe CMD: error: ...`` on stderr; never a
  traceback; its peak resident memory (its own, measured by test/child_memory.py's launcher) stays under
  :data:`SUBPROCESS_MAX_RSS_KB`: the bombs declare 9 GB and more, an interpreter with numpy and numba
  needs about 120-300 MB (figures of up to 1 GB seen before were the test process's own memory, which a
  child's ru_maxrss includes);
* every output ``ppe extract`` writes is a valid file (npz with the labels, PNG), no temporary file
  is left behind.
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest
from child_memory import measured, peak_kib

from ppe_ros.io import ScanFileError, load_scan, save_pcd

SEED = 17
#: Mutations per base file (5 scan kinds + Ouster sidecar + labels: about 400 files).
MUTATIONS_PER_BASE = 55
#: Largest allocation (tracemalloc peak) one in-process load of a mutated file may make.
IN_PROCESS_PEAK_BYTES = 16 * 2**20
#: Largest resident memory of one ``ppe`` subprocess (KB, as ru_maxrss on Linux).
SUBPROCESS_MAX_RSS_KB = 1024 * 1024
#: How many mutated files go through ``ppe info`` in a subprocess (plus the issue's bombs).
INFO_SAMPLE = 5
INTRINSICS = (50.0, 50.0, 4.0, 3.0)

NASTY_NUMBERS = [
    '0',
    '1',
    '-1',
    '2',
    '2147483648',
    '4294967296',
    '18446744073709551616',
    '99999999999',
    '1e9',
    'nan',
    'inf',
    'x',
    '',
]


def _grid(rows: int = 6, cols: int = 8) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(SEED)
    points = np.stack(np.meshgrid(np.linspace(-1, 1, cols), np.linspace(-1, 1, rows)), axis=-1)
    points = np.concatenate([points, np.full((rows, cols, 1), 3.0)], axis=-1) + rng.normal(0, 1e-3, (rows, cols, 3))
    labels = np.where(np.arange(cols)[None, :] < cols // 2, 10, 11) * np.ones((rows, 1), dtype=np.int64)
    return points, labels


def _png(depth: np.ndarray) -> bytes:
    height, width = depth.shape
    rows = b''.join(b'\x00' + row.astype('>u2').tobytes() for row in depth)
    return _png_chunks(width, height, zlib.compress(rows))


def _png_chunks(width: int, height: int, idat: bytes, bit_depth: int = 16, colour: int = 0) -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack('>I', len(data)) + kind + data + struct.pack('>I', zlib.crc32(kind + data))

    ihdr = struct.pack('>IIBBBBB', width, height, bit_depth, colour, 0, 0, 0)
    return b'\x89PNG\r\n\x1a\n' + chunk(b'IHDR', ihdr) + chunk(b'IDAT', idat) + chunk(b'IEND', b'')


def _npy(array: np.ndarray) -> bytes:
    import io

    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


OUSTER_METADATA = {
    'lidar_origin_to_beam_origin_mm': 15.8,
    'lidar_to_sensor_transform': [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 36.18, 0, 0, 0, 1],
    'data_format': {
        'pixels_per_column': 6,
        'columns_per_frame': 8,
        'column_window': [0, 7],
        'pixel_shift_by_row': [0, 1, 2, 3, 4, 5],
    },
}


def _pcd(folder: Path, name: str, points: np.ndarray, **kwargs) -> bytes:
    return save_pcd(folder / f'{name}.pcd', points, **kwargs).read_bytes()


def base_files(folder: Path) -> dict[str, tuple[str, bytes]]:
    """kind -> (suffix, content) of the valid files that are mutated (``folder``: scratch space)."""
    points, labels = _grid()
    intensity = {'extra_fields': {'intensity': labels.astype(np.float32)}}
    depth = np.clip(points[..., 2] * 1000, 0, 65535).astype(np.uint16)
    folder.mkdir(parents=True, exist_ok=True)
    return {
        'pcd_ascii': ('.pcd', _pcd(folder, 'ascii', points, binary=False, **intensity)),
        'pcd_binary': ('.pcd', _pcd(folder, 'binary', points, **intensity)),
        'pcd_compressed': ('.pcd', _pcd(folder, 'compressed', points, compressed=True, **intensity)),
        'npy': ('.npy', _npy(points.astype(np.float32))),
        'png': ('.png', _png(depth)),
        'ouster_json': ('.json', json.dumps(OUSTER_METADATA).encode()),
        'labels_npy': ('.npy', _npy(labels.astype(np.int32))),
    }


def _header_length(kind: str, content: bytes) -> int:
    if kind.startswith('pcd'):
        return content.index(b'DATA') + 20
    if kind.endswith('npy'):
        return content.index(b'\n') + 1
    if kind == 'png':
        return 33
    return len(content)


def _edit_pcd_header(content: bytes, rng: np.random.Generator) -> bytes:
    lines = content.split(b'\n')
    keyed = [i for i, line in enumerate(lines[:12]) if line[:1].isalpha()]
    index = int(rng.choice(keyed))
    keyword, *values = lines[index].decode('latin-1').split(' ')
    if values and rng.random() < 0.8:
        values[int(rng.integers(len(values)))] = str(rng.choice(NASTY_NUMBERS))
    else:
        values = values[:-1] if rng.random() < 0.5 else [*values, str(rng.choice(NASTY_NUMBERS))]
    lines[index] = ' '.join([keyword, *values]).encode('latin-1')
    return b'\n'.join(lines)


def _edit_npy_header(content: bytes, rng: np.random.Generator) -> bytes:
    end = content.index(b'\n') + 1
    shapes = [
        '(1000000, 1000000, 3)',
        '(0, 8, 3)',
        '(6, 8)',
        '(6, 8, 3, 1)',
        '()',
        '(-1, 8, 3)',
        '(6, 8, 4)',
        '(3, 8, 3)',
        '(12, 8, 3)',
        '(6, 8, 2**40)',
        '(60000, 60000, 3)',
        '(6, 8, 6)',
    ]
    descrs = ["'<f8'", "'<i8'", "'|O'", "'<U3'", "'<f2'", "'>f4'", "'|b1'", "'<c16'", "'V12'", "[('x', '<f4')]"]
    header = {
        'descr': str(rng.choice(descrs)),
        'fortran_order': str(rng.choice(['False', 'True'])),
        'shape': str(rng.choice(shapes)),
    }
    text = '{' + ', '.join(f"'{k}': {v}" for k, v in header.items()) + ', }'
    raw = text.encode('latin-1')
    raw += b' ' * (-(len(raw) + 11) % 64) + b'\n'
    return b'\x93NUMPY\x01\x00' + struct.pack('<H', len(raw)) + raw + content[end:]


def _edit_png_header(content: bytes, rng: np.random.Generator) -> bytes:
    sizes = [0, 1, 2, 7, 8, 9, 12000, 100000, 2**31 - 1, 2**32 - 1]
    width, height = int(rng.choice(sizes)), int(rng.choice(sizes))
    bit_depth, colour = [(16, 0), (8, 0), (1, 0), (16, 2), (8, 4), (16, 0)][int(rng.integers(6))]
    idat_at = content.index(b'IDAT')
    idat = content[idat_at + 4 : idat_at + 4 + struct.unpack('>I', content[idat_at - 4 : idat_at])[0]]
    return _png_chunks(width, height, idat, bit_depth, colour)


def _edit_json(content: bytes, rng: np.random.Generator) -> bytes:
    metadata = json.loads(content)
    choices = [None, [], [1, 2], 'text', -1, 0, 1e308, True, {}, 2**64, 15]
    value = choices[int(rng.integers(len(choices)))]
    key = str(
        rng.choice(
            [
                'lidar_origin_to_beam_origin_mm',
                'lidar_to_sensor_transform',
                'data_format',
                'data_format.pixels_per_column',
                'data_format.columns_per_frame',
                'data_format.column_window',
                'data_format.pixel_shift_by_row',
            ]
        )
    )
    target, _, leaf = key.rpartition('.')
    holder = metadata[target] if target else metadata
    if rng.random() < 0.15:
        holder.pop(leaf)
    elif key == 'lidar_to_sensor_transform' and rng.random() < 0.5:
        holder[leaf] = list(range(int(rng.choice([15, 17, 0]))))
    else:
        holder[leaf] = value
    return json.dumps(metadata).encode()


def mutate(kind: str, content: bytes, rng: np.random.Generator) -> tuple[str, bytes]:
    """One seeded mutation of ``content``: (what was done, the mutated bytes)."""
    data = bytearray(content)
    header = _header_length(kind, content)
    how = rng.choice(['flip', 'flip_header', 'truncate', 'edit', 'edit', 'append'])
    if how == 'flip' or (how == 'flip_header' and header < 2):
        for position in rng.integers(0, len(data), size=int(rng.integers(1, 4))):
            data[position] ^= int(rng.integers(1, 256))
    elif how == 'flip_header':
        for position in rng.integers(0, min(header, len(data)), size=int(rng.integers(1, 3))):
            data[position] ^= int(rng.integers(1, 256))
    elif how == 'truncate':
        data = data[: int(rng.integers(0, len(data)))]
    elif how == 'append':
        data += bytes(rng.integers(0, 256, size=int(rng.integers(1, 64)), dtype=np.uint8))
    elif kind.startswith('pcd'):
        data = bytearray(_edit_pcd_header(content, rng))
    elif kind.endswith('npy'):
        data = bytearray(_edit_npy_header(content, rng))
    elif kind == 'png':
        data = bytearray(_edit_png_header(content, rng))
    else:
        data = bytearray(_edit_json(content, rng))
    return str(how), bytes(data)


def fuzz_cases(root: Path) -> list[tuple[str, str, Path, dict]]:
    """Write every mutated file under ``root``: (kind, how, scan path, load_scan keyword arguments)."""
    rng = np.random.default_rng(SEED)
    bases = base_files(root / 'bases')
    cases = []
    for kind, (suffix, content) in bases.items():
        for index in range(MUTATIONS_PER_BASE):
            how, data = mutate(kind, content, rng)
            folder = root / f'{kind}_{index:03d}'
            folder.mkdir()
            kwargs: dict = {}
            if kind == 'ouster_json':  # the scan is valid, its sidecar is mutated
                scan = folder / 'os_frame1_xyz_m.npy'
                scan.write_bytes(bases['npy'][1])
                (folder / 'os.json').write_bytes(data)
            elif kind == 'labels_npy':  # the scan is valid, its --gt labels are mutated
                scan = folder / 'scan.npy'
                scan.write_bytes(bases['npy'][1])
                (folder / 'gt.npy').write_bytes(data)
                kwargs['gt'] = folder / 'gt.npy'
            else:
                scan = folder / f'scan{suffix}'
                scan.write_bytes(data)
                if kind == 'png':
                    kwargs.update(intrinsics=INTRINSICS, units='mm')
            cases.append((kind, how, scan, kwargs))
    return cases


def _zero_rows_deflated(rows: int, row_bytes: int, rows_per_block: int = 400) -> bytes:
    """A zlib stream of ``rows * row_bytes`` zero bytes, built in 0.4 s instead of 4 s: after a full flush
    deflate starts afresh, so every block of ``rows_per_block`` zero rows compresses to the same bytes;
    the Adler-32 of n zero bytes is (n mod 65521) << 16 | 1."""
    compressor = zlib.compressobj(9)
    chunk = bytes(row_bytes * rows_per_block)
    first = compressor.compress(chunk) + compressor.flush(zlib.Z_FULL_FLUSH)
    block = compressor.compress(chunk) + compressor.flush(zlib.Z_FULL_FLUSH)
    end = compressor.flush()[:-4]
    total = rows * row_bytes
    return first + block * (rows // rows_per_block - 1) + end + (((total % 65521) << 16) | 1).to_bytes(4, 'big')


def issue_bombs(root: Path) -> list[Path]:
    """The issue's memory bombs, small files declaring gigabytes (the PNG is a valid 280 KB all-zero image)."""
    folder = root / 'bombs'
    folder.mkdir()
    (folder / 'zeros_12000.png').write_bytes(_png_chunks(12000, 12000, _zero_rows_deflated(12000, 2 * 12000 + 1)))
    (folder / 'claims_1e10.png').write_bytes(_png_chunks(100000, 100000, zlib.compress(b'\0' * 16)))  # 69 bytes
    header = (
        b'VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 9000\nHEIGHT 10000\n'
        b'POINTS 90000000\nDATA binary_compressed\n'
    )
    (folder / 'claims_1gb.pcd').write_bytes(header + struct.pack('<II', 4096, 1_080_000_000) + bytes(4096))
    raw = repr({'descr': '<f8', 'fortran_order': False, 'shape': (1000000, 1000000, 3)}).encode()
    raw += b' ' * (-(len(raw) + 11) % 64) + b'\n'
    (folder / 'claims_1e12.npy').write_bytes(b'\x93NUMPY\x01\x00' + struct.pack('<H', len(raw)) + raw)
    return sorted(folder.iterdir())


def _check_scan(scan, path: Path) -> None:
    rows, cols = scan.shape
    assert rows >= 2 and cols >= 1, path
    assert scan.points.dtype == np.float64 and scan.points.shape == (rows, cols, 3), path
    assert scan.labels is None or scan.labels.shape == (rows, cols), path
    assert scan.origins is None or np.shape(scan.origins) in ((3,), (rows, cols, 3)), path


def test_loader_gives_a_scan_or_a_scan_file_error_for_every_mutated_file(tmp_path: Path) -> None:
    cases = fuzz_cases(tmp_path)
    assert len(cases) >= 350
    outcomes: dict[str, int] = {}
    tracemalloc.start()
    try:
        for kind, how, path, kwargs in cases:
            tracemalloc.reset_peak()
            try:
                scan = load_scan(path, **kwargs)
            except ScanFileError as exc:
                message = str(exc)
                assert '\n' not in message, (kind, how, path, message)
                named = {path, kwargs.get('gt'), path.parent / 'os.json'}
                assert any(message.startswith(f'{name}: ') for name in named if name is not None), (kind, how, message)
                outcomes['error'] = outcomes.get('error', 0) + 1
            else:
                _check_scan(scan, path)
                outcomes['read'] = outcomes.get('read', 0) + 1
            peak = tracemalloc.get_traced_memory()[1]
            assert peak < IN_PROCESS_PEAK_BYTES, (kind, how, path, peak)
    finally:
        tracemalloc.stop()
    # the mutations are not all harmless, nor all fatal
    assert outcomes.get('error', 0) >= 100 and outcomes.get('read', 0) >= 30, outcomes


def _run_ppe(runs: list[list[str]], cwd: Path, parallel: int = 3) -> list[tuple[int, str, int]]:
    """Run ``python -m ppe_ros.cli ARGS`` for each ARGS, ``parallel`` at a time.

    Returns:
        (exit code, stderr, peak resident memory in KB of that very command) per run: measured by the
        launcher of test/child_memory.py (a child's own ``os.wait4`` figure would include this process's memory).
    """
    results = []
    env = {**os.environ, 'PYTHONPATH': os.pathsep.join(sys.path)}
    for first in range(0, len(runs), parallel):
        started = []
        for index, args in enumerate(runs[first : first + parallel], start=first):
            err_path = cwd / f'.stderr_{index}.txt'
            report = cwd / f'.peak_kib_{index}.txt'
            with open(err_path, 'wb') as err:
                process = subprocess.Popen(
                    measured([sys.executable, '-m', 'ppe_ros.cli', *args], report),
                    cwd=cwd,
                    stdout=subprocess.DEVNULL,
                    stderr=err,
                    env=env,
                )
            started.append((process, err_path, report))
        for process, err_path, report in started:
            process.wait()
            results.append((process.returncode, err_path.read_text(), peak_kib(report)))
            err_path.unlink()
            report.unlink()
    return results


def _check_cli_outcome(command: str, code: int, err: str, rss_kb: int, what) -> None:
    assert 'Traceback' not in err, (what, err)
    assert code in (0, 2), (what, code, err)
    if code == 2:
        assert err.startswith(f'ppe {command}: error: ') and err.count('\n') == 1, (what, err)
    assert rss_kb < SUBPROCESS_MAX_RSS_KB, (what, rss_kb)


@pytest.mark.timeout(300)
def test_ppe_info_and_extract_on_mutated_files_exit_0_or_2_in_bounded_memory(tmp_path: Path) -> None:
    cases = fuzz_cases(tmp_path / 'cases')
    rng = np.random.default_rng(SEED + 1)
    sample = [cases[int(i)] for i in rng.choice(len(cases), size=INFO_SAMPLE, replace=False)]
    runs, expectations = [], []
    for path in issue_bombs(tmp_path):
        extra = ['--intrinsics', *map(str, INTRINSICS), '--units', 'mm'] if path.suffix == '.png' else []
        runs.append(['info', str(path), *extra])
        expectations.append(path)
    for kind, how, path, kwargs in sample:
        extra = ['--intrinsics', *map(str, INTRINSICS), '--units', 'mm'] if kind == 'png' else []
        extra += ['--gt', str(kwargs['gt'])] if 'gt' in kwargs else []
        runs.append(['info', str(path), *extra])
        expectations.append((kind, how, path))
    # extract: one mutated file that loads and one that does not, each with two snapshots and pictures
    loadable, broken = None, None
    for kind, _, path, _ in cases:
        if kind != 'pcd_binary':
            continue
        try:
            scan = load_scan(path)
        except ScanFileError:
            broken = broken or path
        else:  # coordinates of everyday size: extreme ones are issue 17 item 2 (the extractor's, not the files')
            if np.nanmax(np.abs(scan.points), initial=0.0) < 100.0:
                loadable = loadable or path
    extract_runs = []
    for path, expected in ((loadable, 0), (broken, 2)):
        out = path.parent / 'out'
        out.mkdir()
        runs.append(['extract', str(path), '-o', str(out / 'p.npz'), '--png', str(out / 'p.png'), '-e', '0.01', '0.1'])
        extract_runs.append((out, expected))
    results = _run_ppe(runs, tmp_path)
    peak_kb = max(rss_kb for _, _, rss_kb in results)
    for (code, err, rss_kb), what in zip(results, expectations, strict=False):
        _check_cli_outcome('info', code, err, rss_kb, what)
        if isinstance(what, Path):  # the issue's bombs
            assert code == 2 and 'at most 50000000 points' in err, err
    for (code, err, rss_kb), (out, expected) in zip(results[len(expectations) :], extract_runs, strict=True):
        _check_cli_outcome('extract', code, err, rss_kb, out)
        assert code == expected, err
        names = sorted(p.name for p in out.iterdir())
        if code == 2:
            assert names == []
            continue
        assert names == ['p_e0.01.npz', 'p_e0.01.png', 'p_e0.1.npz', 'p_e0.1.png']  # no temporary file left
        from PIL import Image

        for name in names:
            if name.endswith('.npz'):
                with np.load(out / name) as data:
                    assert data['labels'].shape == (6, 8)
            else:
                with Image.open(out / name) as image:
                    image.verify()
    print(
        f'peak resident memory of a ppe subprocess: {peak_kb / 1024:.0f} MB (bound {SUBPROCESS_MAX_RSS_KB // 1024} MB)'
    )
