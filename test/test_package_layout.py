"""The package builds as a ROS 2 ament_python package with colcon, and the layout ROS users expect."""

from __future__ import annotations

import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE_FILES = ('package.xml', 'setup.py', 'setup.cfg', 'resource', 'ppe_ros', 'config', 'README.md', 'LICENSE')


def test_package_xml_declares_ament_python_and_dependencies():
    root = ET.parse(REPO / 'package.xml').getroot()
    assert root.get('format') == '3'
    assert root.findtext('name') == 'ppe_ros'
    assert root.find('export/build_type').text == 'ament_python'
    exec_deps = {e.text for e in root.findall('exec_depend')}
    for dep in ('rclpy', 'sensor_msgs', 'visualization_msgs', 'std_msgs', 'geometry_msgs', 'diagnostic_msgs',
                'python3-numpy'):
        assert dep in exec_deps, dep
    assert 'python3-pytest' in {e.text for e in root.findall('test_depend')}
    assert root.findtext('license') == 'Apache-2.0'


def test_import_has_no_ros_dependency():
    """``import ppe_ros`` and the core API must work without rclpy (plain numpy + numba users)."""
    code = (
        'import sys; import ppe_ros; from ppe_ros import extract_planes, PlaneSet; '
        'import ppe_ros.core.extraction, ppe_ros.io; '
        'bad = [m for m in sys.modules if m.startswith(("rclpy", "rosbags", "sensor_msgs"))]; '
        'assert not bad, bad'
    )
    subprocess.run([sys.executable, '-c', code], check=True, timeout=120)


@pytest.mark.timeout(300)
def test_colcon_build_installs_executables_and_config(tmp_path):
    colcon = Path(sys.executable).parent / 'colcon'
    if not colcon.exists():
        colcon_path = shutil.which('colcon')
        assert colcon_path, 'colcon is a pinned dependency (colcon-common-extensions); make venv installs it'
        colcon = Path(colcon_path)
    src = tmp_path / 'ws' / 'src' / 'ppe_ros'
    src.mkdir(parents=True)
    for name in PACKAGE_FILES:
        source = REPO / name
        if source.is_dir():
            shutil.copytree(source, src / name, ignore=shutil.ignore_patterns('__pycache__', '*.nbi', '*.nbc'))
        else:
            shutil.copy2(source, src / name)
    result = subprocess.run([str(colcon), 'build'], cwd=tmp_path / 'ws', capture_output=True, text=True, timeout=280)
    assert result.returncode == 0, result.stdout + result.stderr
    install = tmp_path / 'ws' / 'install' / 'ppe_ros'
    for executable in ('extractor', 'process_bag', 'ppe'):
        path = install / 'lib' / 'ppe_ros' / executable
        assert path.is_file(), f'missing {path}'
    assert (install / 'share' / 'ppe_ros' / 'config' / 'extractor.yaml').is_file()
    assert (install / 'share' / 'ppe_ros' / 'package.xml').is_file()
    assert (install / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'ppe_ros').is_file()
