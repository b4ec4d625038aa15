"""Fuzzing ``process_bag``: cut and byte-flipped bags of every storage kind (issue 17).

Seeded and bounded: per storage kind, cuts at fixed and random lengths and random byte flips of a
clean bag of small organized clouds written with rosbags' writers, run in-process through
``main`` (and a few through a real process, for exit codes, stderr and memory). What must hold:

* the exit code is the documented one: 0 done, 1 damaged input (OUT holds the frames before the
  damage), 2 unusable input (nothing written); a cut bag is never 0;
* never a traceback; a failed run says why in exactly one ``process_bag: error:`` line;
* OUT, whenever it exists, is a valid bag (rosbags' AnyReader reads it all) with the three
  outputs of each frame, frames in input order, and each frame whose input message is intact
  equal, byte for byte, to what the clean run gives; no staging directory is left behind.

SQLite and zstd keep no checksums of the data (rosbags writes none), so a flipped byte inside a
point may go unnoticed: such a frame is processed as the bytes say; only frames whose input
message reads back unchanged are compared with the clean run.
"""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from child_memory import measured, peak_kib
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from ppe_ros.core.synthetic import plane_scan
from ppe_ros.ros.bag import main, open_input_bag, select_topics
from ppe_ros.ros.pointcloud2 import xyz_to_pointcloud2

REPO = Path(__file__).resolve().parents[1]
JAZZY = get_typestore(Stores.ROS2_JAZZY)
NOETIC = get_typestore(Stores.ROS1_NOETIC)
POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
TOPIC = '/lidar/points'
OUTPUT_TOPICS = ('/lidar/planes/labeled_points', '/lidar/planes/markers', '/lidar/planes')
FRAMES = 10
#: The mutations' seed (PPE_FUZZ_SEED to explore others; the suite runs with 17).
SEED = int(os.environ.get('PPE_FUZZ_SEED', '17'))
#: Cuts as fractions of the storage file, plus RANDOM_CUTS random lengths.
CUT_FRACTIONS = (0.0, 0.03, 0.3, 0.6, 0.97, 0.9995)
RANDOM_CUTS = 2
#: Byte-flip mutations (1 to 3 bytes each) per kind: near the start, near the end, anywhere.
FLIPS = 6
KINDS = ('rosbag2 mcap', 'rosbag2 sqlite3', 'zstd file', 'zstd message', 'bare mcap', 'ros1')
#: Peak memory (max RSS) of one process_bag process on these inputs.
MEMORY_BOUND_BYTES = 1 << 30


def _cloud(store, index: int):
    points = plane_scan(3, rows=24, cols=32, radial_sigma=0.005, seed=500 + index).points
    types = store.types
    stamp = types['builtin_interfaces/msg/Time'](sec=1_700_000_000 + index, nanosec=1000 * index)
    if store is NOETIC:
        header = types['std_msgs/msg/Header'](seq=index, stamp=stamp, frame_id='lidar')
    else:
        header = types['std_msgs/msg/Header'](stamp=stamp, frame_id='lidar')
    return xyz_to_pointcloud2(
        points, header=header, msg_class=types[POINTCLOUD2], field_class=types['sensor_msgs/msg/PointField']
    )


def _bag_time(index: int) -> int:
    return (1_700_000_000 + index) * 10**9 + 1000 * index + 5_000_000


def write_bag(kind: str, folder: Path) -> tuple[Path, Path]:
    """A clean bag of ``kind`` in ``folder``: (the path to give process_bag, the storage file to damage)."""
    if kind == 'ros1':
        path = folder / 'in.bag'
        writer = Ros1Writer(path)
        writer.chunk_threshold = 40_000  # several frames per chunk, several chunks
        writer.open()
        connection = writer.add_connection(TOPIC, POINTCLOUD2, typestore=NOETIC)
        for i in range(FRAMES):
            writer.write(connection, _bag_time(i), bytes(NOETIC.serialize_ros1(_cloud(NOETIC, i), POINTCLOUD2)))
        writer.close()
        return path, path
    storage = StoragePlugin.SQLITE3 if kind == 'rosbag2 sqlite3' else StoragePlugin.MCAP
    path = folder / 'in'
    writer = Writer(path, version=9, storage_plugin=storage)
    if kind == 'zstd file':
        writer.set_compression(CompressionMode.FILE, CompressionFormat.ZSTD)
    elif kind == 'zstd message':
        writer.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
    writer.open()
    connection = writer.add_connection(TOPIC, POINTCLOUD2, typestore=JAZZY)
    for i in range(FRAMES):
        writer.write(connection, _bag_time(i), bytes(JAZZY.serialize_cdr(_cloud(JAZZY, i), POINTCLOUD2)))
    writer.close()
    storage_file = next(p for p in path.iterdir() if p.name != 'metadata.yaml')
    if kind == 'bare mcap':
        bare = folder / 'in.mcap'
        shutil.move(storage_file, bare)
        shutil.rmtree(path)
        return bare, bare
    return path, storage_file


def run_in_process(source: Path, out: Path) -> tuple[int, str]:
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = main([str(source), str(out), '--no-progress'])
    return code, stderr.getvalue()


def output_messages(out: Path) -> dict[str, list[tuple[int, bytes]]]:
    """Topic -> [(time, raw)] of a bag, every message read (and deserialized, to prove it is valid)."""
    messages: dict[str, list[tuple[int, bytes]]] = {}
    with AnyReader([out], default_typestore=JAZZY) as reader:
        for connection, timestamp, raw in reader.messages():
            reader.deserialize(raw, connection.msgtype)
            messages.setdefault(connection.topic, []).append((timestamp, bytes(raw)))
    return messages


def input_messages(source: Path) -> dict[int, bytes]:
    """Bag time -> raw input message, as process_bag's reader reads them, up to any damage: of every
    PointCloud2 topic it selects (a flipped byte may change the topic's name in an MCAP summary)."""
    found: dict[int, bytes] = {}
    with contextlib.suppress(Exception):
        bag = open_input_bag(source)
        try:
            for _, timestamp, raw in bag.messages(select_topics(bag, None)):
                found[timestamp] = bytes(raw)
        finally:
            bag.close()
    return found


@pytest.fixture(scope='module')
def clean(tmp_path_factory):
    """Per kind: the clean bag's folder, its input messages and the outputs of a clean run."""
    result = {}
    for kind in KINDS:
        folder = tmp_path_factory.mktemp(kind.replace(' ', '_'))
        source, storage = write_bag(kind, folder)
        code, err = run_in_process(source, folder / 'clean_out')
        assert code == 0, err
        outputs = output_messages(folder / 'clean_out')
        assert [t for t, _ in outputs[OUTPUT_TOPICS[0]]] == [_bag_time(i) for i in range(FRAMES)]
        result[kind] = (folder, source, storage, input_messages(source), outputs)
    return result


def mutations(kind: str, size: int) -> list[tuple[str, object]]:
    """('cut', length) and ('flip', [(offset, xor mask)]) mutations of a storage file of ``size`` bytes."""
    rng = np.random.default_rng([SEED, KINDS.index(kind)])
    cuts = {int(size * fraction) for fraction in CUT_FRACTIONS} | {8}
    cuts |= {int(n) for n in rng.integers(9, size, RANDOM_CUTS)}
    found: list[tuple[str, object]] = [('cut', n) for n in sorted(cuts) if n < size]
    for i in range(FLIPS):
        region = (0, min(size, 256)) if i % 4 == 0 else (max(0, size - 512), size) if i % 4 == 1 else (0, size)
        count = int(rng.integers(1, 4))
        offsets = rng.integers(region[0], region[1], count)
        found.append(('flip', [(int(o), int(rng.integers(1, 256))) for o in offsets]))
    return found


def damaged_copy(folder: Path, source: Path, storage: Path, mutation: tuple[str, object], name: str) -> Path:
    """A copy of the clean bag with ``mutation`` applied to its storage file."""
    target_root = folder / name
    shutil.rmtree(target_root, ignore_errors=True)
    target_root.mkdir()
    if source.is_dir():
        copy = target_root / source.name
        shutil.copytree(source, copy)
        damaged = copy / storage.name
    else:
        copy = damaged = target_root / source.name
        shutil.copy(source, copy)
    what, how = mutation
    if what == 'cut':
        with damaged.open('r+b') as handle:
            handle.truncate(how)
    else:
        content = bytearray(damaged.read_bytes())
        for offset, mask in how:
            content[offset] ^= mask
        damaged.write_bytes(bytes(content))
    return copy


def check_run(code: int, err: str, damaged: Path, out: Path, mutation, clean_inputs, clean_outputs) -> None:
    what = mutation[0]
    context = f'{mutation}: exit {code}\n{err[-1500:]}'
    assert 'Traceback' not in err, context
    errors = [line for line in err.splitlines() if line.startswith('process_bag: error: ')]
    if what == 'cut':
        assert code in (1, 2), context
    else:
        assert code in (0, 1, 2), context
    assert len(errors) == (0 if code == 0 else 1), context
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f'.{out.name}.')], context
    if code == 2:
        assert not out.exists(), context
        return
    assert out.is_dir(), context
    outputs = output_messages(out)
    times = [t for t, _ in outputs.get(OUTPUT_TOPICS[0], [])]
    for topic in OUTPUT_TOPICS:
        assert [t for t, _ in outputs.get(topic, [])] == times, context  # all three outputs of each frame
    assert times == sorted(set(times)), context  # input order, each frame once
    clean_times = [t for t, _ in clean_outputs[OUTPUT_TOPICS[0]]]
    damaged_inputs = input_messages(damaged)
    if what == 'cut':  # the frames before the damage, every one of them
        assert times == clean_times[: len(times)], context
    else:  # a flipped byte may change a time stamp too (no checksum): frames of the bag as it reads
        assert set(times) <= set(damaged_inputs), context
    intact = {t for t, raw in damaged_inputs.items() if clean_inputs.get(t) == raw}
    for topic in OUTPUT_TOPICS:
        expected = dict(clean_outputs[topic])
        for timestamp, raw in outputs.get(topic, []):
            if timestamp in intact:
                assert raw == expected[timestamp], f'{context}\n{topic} at {timestamp} differs from the clean run'


@pytest.mark.timeout(120)
@pytest.mark.parametrize('kind', KINDS)
def test_damaged_bags_give_the_documented_outcome(clean, kind):
    folder, source, storage, clean_inputs, clean_outputs = clean[kind]
    outcomes = {0: 0, 1: 0, 2: 0}
    recovered = 0
    for index, mutation in enumerate(mutations(kind, storage.stat().st_size)):
        damaged = damaged_copy(folder, source, storage, mutation, f'case{index}')
        out = damaged.parent / 'out'
        code, err = run_in_process(damaged, out)
        check_run(code, err, damaged, out, mutation, clean_inputs, clean_outputs)
        outcomes[code] += 1
        if code == 1 and mutation[0] == 'cut':
            recovered += len(output_messages(out).get(OUTPUT_TOPICS[0], []))
        shutil.rmtree(damaged.parent)
    if kind != 'zstd file':  # (a cut zstd stream loses its last 128 KiB block: here the whole file)
        assert outcomes[1] > 0, outcomes  # some damage is read up to the cut, not everything refused
        assert recovered > 0, outcomes


@pytest.mark.timeout(180)
@pytest.mark.parametrize(
    ('kind', 'mutation'),
    [
        ('rosbag2 sqlite3', ('cut', 0.6)),
        ('zstd file', ('cut', 0.5)),
        ('bare mcap', ('cut', 8)),
    ],
)
def test_damaged_bags_in_a_real_process(clean, tmp_path, kind, mutation):
    """Exit code, stderr (one line, no traceback) and peak memory of the real command."""
    _, source, storage, clean_inputs, clean_outputs = clean[kind]
    what, amount = mutation
    length = amount if isinstance(amount, int) else int(storage.stat().st_size * amount)
    damaged = damaged_copy(tmp_path, source, storage, (what, length), 'case')
    out = damaged.parent / 'out'
    report = tmp_path / 'peak_kib.txt'  # the command's own peak, not this process's (child_memory)
    result = subprocess.run(
        measured([sys.executable, '-m', 'ppe_ros.ros.bag', str(damaged), str(out), '--no-progress'], report),
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=150,
    )
    check_run(result.returncode, result.stderr, damaged, out, (what, length), clean_inputs, clean_outputs)
    assert result.returncode == {'rosbag2 sqlite3': 1, 'zstd file': 2, 'bare mcap': 2}[kind], result.stderr
    assert peak_kib(report) * 1024 < MEMORY_BOUND_BYTES, peak_kib(report)
