"""The package builds as a ROS 2 ament_python package with colcon, and the layout ROS users expect."""

from __future__ import annotations

import ast
import importlib.util
import shutil
import subprocess
import sys
import types
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE_FILES = (
    'package.xml',
    'setup.py',
    'setup.cfg',
    'resource',
    'ppe_ros',
    'config',
    'launch',
    'rviz',
    'README.md',
    'LICENSE',
)
LAUNCH_FILE = REPO / 'launch' / 'extractor.launch.py'
RVIZ_FILE = REPO / 'rviz' / 'ppe_ros.rviz'

#: Top-level module of every third-party import in ppe_ros/ and launch/ -> its rosdep key (None: not a
#: package of its own). A new import fails test_every_third_party_import_has_its_rosdep_key until it is here.
ROSDEP_KEYS = {
    'numpy': 'python3-numpy',
    'numba': 'python3-numba',
    'llvmlite': 'python3-numba',  # numba's code generator: installed with numba (apt and pip alike)
    'rosbags': 'python3-rosbags-pip',
    'lz4': 'python3-rosbags-pip',  # a requirement of rosbags (no rosdep key of its own)
    'backports': 'python3-rosbags-pip',  # backports.zstd, a requirement of rosbags on Python < 3.14
    'compression': None,  # compression.zstd: the standard library from Python 3.14 (backports.zstd before)
    'yaml': 'python3-yaml',
    'tqdm': 'python3-tqdm',
    'PIL': 'python3-pil',
    'matplotlib': 'python3-matplotlib',
    'rclpy': 'rclpy',
    'rcl_interfaces': 'rcl_interfaces',
    'sensor_msgs': 'sensor_msgs',
    'std_msgs': 'std_msgs',
    'visualization_msgs': 'visualization_msgs',
    'diagnostic_msgs': 'diagnostic_msgs',
    'launch': 'launch',
    'launch_ros': 'launch_ros',
    'ray': None,  # optional, for process_bag --executor ray only: pip (requirements-workspace.txt), no rosdep key
}
#: exec_depends without an import: message packages inside the outputs (MarkerArray holds geometry_msgs/Point,
#: every header builtin_interfaces/Time; the markers are serialized to CDR directly).
DEPENDS_WITHOUT_IMPORT = {'geometry_msgs', 'builtin_interfaces'}
#: pip name of every third-party package ppe_ros imports that is not ROS (what workspace users pip install).
PIP_NAMES = {
    'numba': 'numba',
    'llvmlite': 'llvmlite',
    'rosbags': 'rosbags',
    'yaml': 'pyyaml',
    'tqdm': 'tqdm',
    'PIL': 'pillow',
    'matplotlib': 'matplotlib',
}


def exec_depends() -> set[str]:
    return {e.text for e in ET.parse(REPO / 'package.xml').getroot().findall('exec_depend')}


def test_package_xml_declares_ament_python_and_dependencies():
    root = ET.parse(REPO / 'package.xml').getroot()
    assert root.get('format') == '3'
    assert root.findtext('name') == 'ppe_ros'
    assert root.find('export/build_type').text == 'ament_python'
    exec_deps = exec_depends()
    for dep in (
        'rclpy',
        'sensor_msgs',
        'visualization_msgs',
        'std_msgs',
        'geometry_msgs',
        'diagnostic_msgs',
        'python3-numpy',
        'python3-numba',
        'python3-rosbags-pip',
        'python3-yaml',
        'python3-tqdm',
        'python3-pil',
        'python3-matplotlib',
        'rcl_interfaces',
    ):
        assert dep in exec_deps, dep
    assert 'python3-pytest' in {e.text for e in root.findall('test_depend')}
    assert root.findtext('license') == 'Apache-2.0'


def third_party_imports() -> dict[str, list[str]]:
    """Top-level module -> files importing it, over ppe_ros/ and launch/ (standard library and ppe_ros left out)."""
    found: dict[str, list[str]] = {}
    for path in sorted([*(REPO / 'ppe_ros').rglob('*.py'), *(REPO / 'launch').glob('*.py')]):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split('.')[0]
                if top not in sys.stdlib_module_names and top not in ('ppe_ros', '__future__'):
                    found.setdefault(top, []).append(str(path.relative_to(REPO)))
    return found


def test_every_third_party_import_has_its_rosdep_key_in_package_xml():
    """`rosdep install --from-paths src` must bring everything ppe_ros imports (issue 19 item 2)."""
    imports = third_party_imports()
    unmapped = {name: files for name, files in imports.items() if name not in ROSDEP_KEYS}
    assert not unmapped, f'imports without a rosdep key (add it to ROSDEP_KEYS and package.xml): {unmapped}'
    declared = exec_depends()
    missing = {name: ROSDEP_KEYS[name] for name in imports if ROSDEP_KEYS[name] and ROSDEP_KEYS[name] not in declared}
    assert not missing, f'package.xml lacks <exec_depend> for {missing}'
    used = {ROSDEP_KEYS[name] for name in imports} | DEPENDS_WITHOUT_IMPORT
    assert declared <= used, f'exec_depends nothing imports: {sorted(declared - used)}'
    for name in ('numba', 'rosbags', 'yaml', 'rclpy', 'launch_ros'):  # the scan itself sees the imports
        assert name in imports, name


def requirement_lines(path: Path) -> list[str]:
    return [line.strip() for line in path.read_text().splitlines() if line.strip() and not line.startswith('#')]


def test_workspace_requirements_hold_only_the_non_ros_packages_with_the_pinned_versions():
    """A colcon workspace on an apt ROS install must not get the ros-jazzy wheels, colcon, setuptools or numpy."""
    workspace = requirement_lines(REPO / 'requirements-workspace.txt')
    pinned = requirement_lines(REPO / 'requirements.txt')
    assert set(workspace) <= set(pinned), sorted(set(workspace) - set(pinned))
    names = {line.split('==')[0].lower() for line in workspace}
    for forbidden in ('ros-jazzy-', 'colcon', 'setuptools', 'numpy', 'pytest', 'ruff', 'pip'):
        assert not any(name.startswith(forbidden) for name in names), (forbidden, names)
    imported = third_party_imports()
    for module, pip_name in PIP_NAMES.items():
        assert module in imported and pip_name in names, (module, pip_name, names)


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
def test_colcon_build_installs_executables_config_launch_and_rviz(tmp_path, monkeypatch):
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
    share = install / 'share' / 'ppe_ros'
    assert (share / 'package.xml').is_file()
    assert (install / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'ppe_ros').is_file()
    from ppe_ros.ros.processing import ExtractorParams

    for name in ('extractor.yaml', 'lidar.yaml', 'depth_camera.yaml'):  # the installed params files load
        assert (share / 'config' / name).read_text() == (REPO / 'config' / name).read_text()
        ExtractorParams.from_yaml(share / 'config' / name)
    assert (share / 'rviz' / 'ppe_ros.rviz').read_text() == RVIZ_FILE.read_text()
    assert rviz_displays(share / 'rviz' / 'ppe_ros.rviz')
    # the installed launch file, against the installed share (what `ros2 launch ppe_ros extractor.launch.py` finds)
    check_launch_file(share / 'launch' / 'extractor.launch.py', share, monkeypatch)


# ------------------------------------------------------------------ the launch file, with launch stubbed
# launch and launch_ros have no PyPI wheels (ros-jazzy-launch, ros-jazzy-launch-ros: "No matching
# distribution"): the launch file runs here against stand-ins that record what it builds and evaluate its
# substitutions the way launch does (LaunchConfiguration, PathJoinSubstitution, PythonExpression,
# FindPackageShare, IfCondition).


class _Recorded:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


class _LaunchConfiguration:
    def __init__(self, name):
        self.name = name

    def perform(self, context):
        return context['configurations'][self.name]


class _FindPackageShare:
    def __init__(self, package):
        self.package = package

    def perform(self, context):
        return str(context['shares'][self.package])


def perform(value, context) -> str:
    """A substitution (or a list of them, or text) as launch evaluates it: the parts' texts joined."""
    if isinstance(value, str):
        return value
    if isinstance(value, list):
        return ''.join(perform(part, context) for part in value)
    return value.perform(context)


class _PathJoinSubstitution:
    def __init__(self, parts):
        self.parts = parts

    def perform(self, context):
        return str(Path(*(perform(part, context) for part in self.parts)))


class _PythonExpression:
    def __init__(self, parts):
        self.parts = parts

    def perform(self, context):
        return str(eval(perform(self.parts, context), {}))


class _IfCondition:
    def __init__(self, predicate):
        self.predicate = predicate

    def evaluate(self, context):
        return perform(self.predicate, context).lower() in ('true', '1')


class _LaunchDescription:
    def __init__(self, entities):
        self.entities = entities


def stubbed_launch_modules() -> dict[str, types.ModuleType]:
    modules = {}
    for name, members in {
        'launch': {'LaunchDescription': _LaunchDescription},
        'launch.actions': {'DeclareLaunchArgument': type('DeclareLaunchArgument', (_Recorded,), {})},
        'launch.conditions': {'IfCondition': _IfCondition},
        'launch.substitutions': {
            'LaunchConfiguration': _LaunchConfiguration,
            'PathJoinSubstitution': _PathJoinSubstitution,
            'PythonExpression': _PythonExpression,
        },
        'launch_ros': {},
        'launch_ros.actions': {'Node': type('Node', (_Recorded,), {})},
        'launch_ros.substitutions': {'FindPackageShare': _FindPackageShare},
    }.items():
        module = types.ModuleType(name)
        module.__dict__.update(members)
        modules[name] = module
    return modules


def load_launch_description(path: Path, monkeypatch):
    for name, module in stubbed_launch_modules().items():
        monkeypatch.setitem(sys.modules, name, module)
    spec = importlib.util.spec_from_file_location('extractor_launch', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.generate_launch_description()


def launch_context(description, share: Path, **given: str) -> dict:
    """The launch configurations of ``given`` arguments over the declared defaults (in declaration order)."""
    context = {'configurations': {}, 'shares': {'ppe_ros': share}}
    for entity in description.entities:
        if type(entity).__name__ == 'DeclareLaunchArgument':
            name = entity.args[0]
            value = given.get(name, entity.kwargs.get('default_value'))
            assert value is not None, f'launch argument {name} has no default'
            choices = entity.kwargs.get('choices')
            value = perform(value, context)
            assert choices is None or value in choices, (name, value, choices)
            context['configurations'][name] = value
    return context


def launch_nodes(description) -> dict[str, _Recorded]:
    return {node.kwargs['executable']: node for node in description.entities if type(node).__name__ == 'Node'}


def check_launch_file(path: Path, share: Path, monkeypatch) -> None:
    """The launch file starts the extractor with the sensor's params file, remaps its inputs, and RViz on request."""
    from ppe_ros.ros.node import CAMERA_INFO_TOPIC, DEPTH_IMAGE_TOPIC, INPUT_TOPIC, METADATA_TOPIC
    from ppe_ros.ros.processing import SENSOR_CHOICES

    description = load_launch_description(path, monkeypatch)
    declared = {e.args[0]: e for e in description.entities if type(e).__name__ == 'DeclareLaunchArgument'}
    assert {
        'sensor',
        'params_file',
        'points',
        'depth_image',
        'camera_info',
        'metadata',
        'namespace',
        'rviz',
        'frame',
    } <= set(declared)
    assert set(declared['sensor'].kwargs['choices']) <= set(SENSOR_CHOICES)
    nodes = launch_nodes(description)
    assert set(nodes) == {'extractor', 'rviz2'}
    extractor = nodes['extractor']
    assert (extractor.kwargs['package'], extractor.kwargs['name']) == ('ppe_ros', 'extractor')
    expected_files = {'none': 'extractor.yaml', 'lidar': 'lidar.yaml', 'depth_camera': 'depth_camera.yaml'}
    assert set(declared['sensor'].kwargs['choices']) == set(expected_files)
    for sensor, file_name in expected_files.items():
        context = launch_context(description, share, sensor=sensor)
        params_file, overrides = extractor.kwargs['parameters']
        resolved = Path(perform(params_file, context))
        assert resolved == share / 'config' / file_name and resolved.is_file(), resolved
        assert {key: perform(value, context) for key, value in overrides.items()} == {'use_sim_time': 'false'}
        if sensor != 'none':
            from ppe_ros.ros.processing import ExtractorParams

            assert ExtractorParams.from_yaml(resolved).sensor == sensor
    context = launch_context(description, share, points='/ouster/points', params_file='/tmp/mine.yaml')
    assert perform(extractor.kwargs['parameters'][0], context) == '/tmp/mine.yaml'
    remappings = {source: perform(target, context) for source, target in extractor.kwargs['remappings']}
    assert remappings == {
        INPUT_TOPIC: '/ouster/points',
        DEPTH_IMAGE_TOPIC: '/camera/depth/image_rect_raw',
        CAMERA_INFO_TOPIC: '/camera/depth/camera_info',
        METADATA_TOPIC: '/ouster/metadata',
    }
    context = launch_context(
        description, share, depth_image='/k4a/depth/image_raw', camera_info='/k4a/depth/camera_info'
    )
    remappings = {source: perform(target, context) for source, target in extractor.kwargs['remappings']}
    assert (remappings[DEPTH_IMAGE_TOPIC], remappings[CAMERA_INFO_TOPIC]) == (
        '/k4a/depth/image_raw',
        '/k4a/depth/camera_info',
    )
    rviz = nodes['rviz2']
    assert not rviz.kwargs['condition'].evaluate(launch_context(description, share))
    context = launch_context(description, share, rviz='true', frame='camera_depth_optical_frame')
    assert rviz.kwargs['condition'].evaluate(context)
    arguments = [perform(argument, context) for argument in rviz.kwargs['arguments']]
    assert arguments[:2] == ['-d', str(share / 'rviz' / 'ppe_ros.rviz')] and Path(arguments[1]).is_file()
    assert arguments[2:] == ['-f', 'camera_depth_optical_frame']


def test_launch_file_starts_the_extractor_with_the_sensors_params_and_remappings(monkeypatch):
    check_launch_file(LAUNCH_FILE, REPO, monkeypatch)


def test_launch_file_is_valid_python_for_ros2_launch():
    """ros2 launch imports the file and calls generate_launch_description(); it imports only launch and launch_ros."""
    tree = ast.parse(LAUNCH_FILE.read_text())
    functions = {node.name for node in tree.body if isinstance(node, ast.FunctionDef)}
    assert 'generate_launch_description' in functions
    imported = {node.module.split('.')[0] for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    assert imported == {'launch', 'launch_ros'}


# ------------------------------------------------------------------ the RViz config


def rviz_displays(path: Path) -> dict[str, dict]:
    import yaml

    config = yaml.safe_load(path.read_text())
    displays = config['Visualization Manager']['Displays']
    return {display['Topic']['Value']: display for display in displays if 'Topic' in display}


def test_rviz_config_shows_the_labelled_cloud_the_markers_and_the_plane_centroids():
    from ppe_ros.ros.markers import MESH_NAMESPACE, NORMAL_NAMESPACE, OUTLINE_NAMESPACE
    from ppe_ros.ros.node import LABELED_POINTS_TOPIC, MARKERS_TOPIC, PLANE_TABLE_TOPIC
    from ppe_ros.ros.processing import LABELED_POINTS_FIELDS, PLANE_TABLE_DTYPE

    displays = rviz_displays(RVIZ_FILE)
    assert set(displays) == {f'/{LABELED_POINTS_TOPIC}', f'/{MARKERS_TOPIC}', f'/{PLANE_TABLE_TOPIC}'}
    labeled, markers, table = (
        displays[f'/{topic}'] for topic in (LABELED_POINTS_TOPIC, MARKERS_TOPIC, PLANE_TABLE_TOPIC)
    )
    assert labeled['Class'] == table['Class'] == 'rviz_default_plugins/PointCloud2'
    assert markers['Class'] == 'rviz_default_plugins/MarkerArray'
    assert set(markers['Namespaces']) == {MESH_NAMESPACE, OUTLINE_NAMESPACE, NORMAL_NAMESPACE}
    for display in displays.values():  # the node publishes reliable, volatile
        assert display['Enabled'] is True
        assert (display['Topic']['Reliability Policy'], display['Topic']['Durability Policy']) == (
            'Reliable',
            'Volatile',
        )
    # RViz's XYZ transformer reads float32 x y z only; RGB8 reads a 4-byte 'rgb' field
    for display, fields in ((labeled, LABELED_POINTS_FIELDS), (table, PLANE_TABLE_DTYPE.names)):
        assert (display['Position Transformer'], display['Color Transformer']) == ('XYZ', 'RGB8')
        assert {'x', 'y', 'z', 'rgb'} <= set(fields)
    for axis, offset in zip('xyz', (0, 4, 8), strict=True):
        assert PLANE_TABLE_DTYPE.fields[axis] == (np.dtype('<f4'), offset)
    assert PLANE_TABLE_DTYPE.fields['rgb'][0].itemsize == 4
