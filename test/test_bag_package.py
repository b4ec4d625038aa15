"""The shape of :mod:`ppe_ros.ros.bag`: the rosbags version its salvage readers are written for, the
public names and entry points, and functions of at most 120 lines."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from importlib import metadata
from pathlib import Path

from ppe_ros.ros import bag as bag_package
from ppe_ros.ros.bag import salvage

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / 'ppe_ros' / 'ros' / 'bag'


def pinned(name: str) -> str:
    """The version of ``name`` pinned in requirements.txt."""
    text = (REPO / 'requirements.txt').read_text()
    match = re.search(rf'^{re.escape(name)}(?:\[[^\]]*\])?==(\S+)', text, re.MULTILINE)
    assert match, f'{name} is not pinned in requirements.txt'
    return match.group(1)


def test_the_salvage_readers_are_written_for_the_pinned_rosbags():
    """The salvage readers use rosbags internals: a rosbags upgrade must go through them (see salvage/__init__)."""
    assert salvage.ROSBAGS_VERSION == pinned('rosbags') == metadata.version('rosbags')


def test_only_the_salvage_readers_import_rosbags_internals():
    public = {'rosbags.rosbag1', 'rosbags.rosbag2', 'rosbags.typesys', 'rosbags.highlevel'}
    for path in sorted(PACKAGE.rglob('*.py')):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or '').startswith('rosbags'):
                if path.parent.name != 'salvage':
                    assert node.module in public, (path.name, node.module)


def test_the_names_tests_and_entry_points_use_are_public():
    for name in (
        'BagOptions',
        'BagError',
        'FrameProcessor',
        'main',
        'run',
        'add_arguments',
        'output_topics',
        'open_input_bag',
        'process_bag',
        'format_report',
    ):
        assert callable(getattr(bag_package, name)), name
    setup = (REPO / 'setup.py').read_text()
    entry_points = re.findall(r"'process_bag = ([\w.]+):(\w+)'", setup)
    assert entry_points == [('ppe_ros.entry', 'process_bag')]  # imports the package inside, then calls its main
    from ppe_ros import entry

    assert entry.load_main('ppe_ros.ros.bag', 'process_bag') is bag_package.main
    result = subprocess.run(
        [sys.executable, '-m', 'ppe_ros.ros.bag', '--help'], capture_output=True, text=True, cwd=REPO, timeout=120
    )
    assert result.returncode == 0 and 'usage: process_bag' in result.stdout, result.stderr


def test_no_function_is_longer_than_120_lines():
    long = []
    for path in sorted(PACKAGE.rglob('*.py')):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.end_lineno - node.lineno >= 120:
                long.append(f'{path.relative_to(REPO)}:{node.lineno} {node.name}')
    assert long == []
