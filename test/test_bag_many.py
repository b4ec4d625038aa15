"""``process_bag IN [IN ...] OUT``: several inputs (or a directory of bags), one output bag each.

Each output must be, byte for byte, what a single run on that input writes; bad inputs and paths
follow the single-input rules (a clear error, nothing lost, the inputs never overwritten).
"""

from __future__ import annotations

import filecmp
from pathlib import Path

import pytest
from test_bag import JAZZY, NOETIC, bag_time, cloud, read_bag, serialized, write_ros1, write_rosbag2

from ppe_ros.core.synthetic import plane_scan
from ppe_ros.ros.bag import main
from ppe_ros.ros.bag.discovery import expand_inputs, output_name

LABELED = '/sensor/planes/labeled_points'


def run_cli(argv: list) -> int:
    return main([str(a) for a in argv] + ['--no-progress'])


def frames(count: int, seed: int, store=JAZZY) -> list[tuple[int, bytes]]:
    return [
        (
            bag_time(i),
            serialized(
                store, cloud(store, i, plane_scan(3, rows=24, cols=32, radial_sigma=0.005, seed=seed + i).points)
            ),
        )
        for i in range(count)
    ]


@pytest.fixture(scope='module')
def fleet(tmp_path_factory) -> Path:
    """A directory of three bags: rosbag2 mcap (3 frames), rosbag2 sqlite3 (2), ROS 1 (4)."""
    folder = tmp_path_factory.mktemp('fleet')
    write_rosbag2(folder / 'day1_front', frames(3, 10))
    write_rosbag2(folder / 'day1_rear', frames(2, 20), storage='sqlite3')
    write_ros1(folder / 'day2.bag', frames(4, 30, NOETIC))
    (folder / 'notes.txt').write_text('not a bag, not listed')
    return folder


@pytest.fixture(scope='module')
def singles(fleet, tmp_path_factory) -> Path:
    """What single runs write for each bag of the fleet (OUT named as the multi-input run names it)."""
    folder = tmp_path_factory.mktemp('singles')
    for source, name in (('day1_front', 'day1_front'), ('day1_rear', 'day1_rear'), ('day2.bag', 'day2')):
        assert run_cli([fleet / source, folder / name]) == 0
    return folder


def same_bag(a: Path, b: Path) -> bool:
    """Byte-identical bag directories (the same files with the same contents)."""
    names = sorted(p.name for p in a.iterdir())
    return names == sorted(p.name for p in b.iterdir()) and all(
        filecmp.cmp(a / name, b / name, shallow=False) for name in names
    )


def test_a_directory_of_bags_is_its_bags_in_name_order(fleet):
    bags, expanded = expand_inputs([fleet])
    assert expanded and [b.name for b in bags] == ['day1_front', 'day1_rear', 'day2.bag']
    assert [output_name(b) for b in bags] == ['day1_front', 'day1_rear', 'day2']
    assert expand_inputs([fleet / 'day1_front']) == ([fleet / 'day1_front'], False)  # a rosbag2 is one bag


def test_each_input_gets_the_bag_a_single_run_writes(tmp_path, fleet, singles, capsys):
    assert run_cli([fleet / 'day1_front', fleet / 'day1_rear', fleet / 'day2.bag', tmp_path / 'out']) == 0
    stdout = capsys.readouterr().out
    for name in ('day1_front', 'day1_rear', 'day2'):
        assert same_bag(tmp_path / 'out' / name, singles / name), name
    assert f'| {fleet / "day1_front"} | {tmp_path / "out" / "day1_front"} | 3 | 3 | 0 |' in stdout
    assert f'| {fleet / "day2.bag"} | {tmp_path / "out" / "day2"} | 4 | 4 | 0 |' in stdout
    assert '3 inputs, 3 complete: 9 frames in' in stdout
    assert sorted(p.name for p in (tmp_path / 'out').iterdir()) == ['day1_front', 'day1_rear', 'day2']


def test_a_directory_of_bags_and_jobs_2_give_the_same_bags(tmp_path, fleet, singles):
    assert run_cli([fleet, tmp_path / 'out', '--jobs', '2']) == 0
    for name in ('day1_front', 'day1_rear', 'day2'):
        assert same_bag(tmp_path / 'out' / name, singles / name), name


def test_an_unusable_input_is_reported_and_the_others_are_written(tmp_path, fleet, singles, capsys):
    bad = tmp_path / 'broken.mcap'
    bad.write_bytes(b'\x89MCAP0\r\n' + b'\x00' * 40)
    missing = tmp_path / 'missing.bag'
    code = run_cli([fleet / 'day1_front', bad, missing, fleet / 'day1_rear', tmp_path / 'out'])
    captured = capsys.readouterr()
    assert code == 1
    assert 'Traceback' not in captured.err
    assert f'process_bag: error: {bad}: {bad} is damaged' in captured.err
    assert f'process_bag: error: {missing}: no such file or directory: {missing}' in captured.err
    assert same_bag(tmp_path / 'out' / 'day1_front', singles / 'day1_front')
    assert same_bag(tmp_path / 'out' / 'day1_rear', singles / 'day1_rear')
    assert sorted(p.name for p in (tmp_path / 'out').iterdir()) == ['day1_front', 'day1_rear']
    assert '4 inputs, 2 complete' in captured.out


@pytest.mark.parametrize(
    ('case', 'message'),
    [
        ('same name', 'would all write'),
        ('same bag twice', 'is given twice'),
        ('out is a file', 'is not a directory'),
        ('out inside an input', 'refusing to write in'),
        ('an output exists', 'exists; use --force to replace it'),
        ('ray address without ray', '--ray-address needs --executor ray'),
    ],
)
def test_bad_paths_are_refused_before_anything_is_written(tmp_path, fleet, capsys, case, message):
    inputs: list = [fleet / 'day1_front', fleet / 'day1_rear']
    out = tmp_path / 'out'
    extra: list = []
    if case == 'same name':
        write_rosbag2(tmp_path / 'other' / 'day1_front', frames(1, 40))
        inputs.append(tmp_path / 'other' / 'day1_front')
    elif case == 'same bag twice':
        inputs.append(fleet / 'day1_front')
    elif case == 'out is a file':
        out.write_text('mine')
    elif case == 'out inside an input':
        out = fleet / 'day1_front' / 'out'
    elif case == 'an output exists':
        (out / 'day1_rear').mkdir(parents=True)
        (out / 'day1_rear' / 'keep.txt').write_text('mine')
    else:
        extra = ['--ray-address', '127.0.0.1:1']
    before = sorted(str(p.relative_to(fleet)) for p in fleet.rglob('*'))
    assert run_cli([*inputs, out, *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith('process_bag: error: ') and message in err, err
    assert sorted(str(p.relative_to(fleet)) for p in fleet.rglob('*')) == before  # the inputs untouched
    if case == 'out is a file':
        assert out.read_text() == 'mine'
    elif case == 'an output exists':
        assert sorted(p.name for p in out.rglob('*')) == ['day1_rear', 'keep.txt']
    else:
        assert not out.exists()


def test_force_replaces_only_the_outputs(tmp_path, fleet, singles):
    out = tmp_path / 'out'
    (out / 'day1_rear').mkdir(parents=True)
    (out / 'day1_rear' / 'old.txt').write_text('old')
    (out / 'unrelated.txt').write_text('mine')
    assert run_cli([fleet / 'day1_front', fleet / 'day1_rear', out, '--force']) == 0
    assert same_bag(out / 'day1_rear', singles / 'day1_rear')
    assert (out / 'unrelated.txt').read_text() == 'mine'
    assert len(read_bag(out / 'day1_front')[LABELED]) == 3
