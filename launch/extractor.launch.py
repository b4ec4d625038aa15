"""``ros2 launch ppe_ros extractor.launch.py``: the plane-extraction node, optionally with RViz.

Arguments (``name:=value``):

* ``sensor``: ``none`` (default), ``lidar`` or ``depth_camera``: picks the params file
  ``config/extractor.yaml``, ``config/lidar.yaml`` or ``config/depth_camera.yaml`` of the package;
* ``params_file``: a params file of your own instead (its ``extractor:`` section);
* ``points``: the input cloud topic (default ``/points``), e.g. ``/ouster/points`` or
  ``/camera/depth/points``;
* ``depth_image``, ``camera_info``: a depth camera's depth image and camera info topics (default
  ``/camera/depth/image_rect_raw`` and ``/camera/depth/camera_info``, the RealSense driver's);
* ``metadata``: the Ouster driver's metadata topic (default ``/ouster/metadata``; per-beam ray
  starts while ``ray_origin`` is [0, 0, 0]);
* ``namespace``: the node's namespace (default none; the packaged params files name the node
  ``extractor`` in the root namespace: with a namespace use a file whose key is ``/<ns>/extractor:``
  or ``/**:``);
* ``use_sim_time``: ``true`` for bag replays with ``--clock`` (default ``false``);
* ``rviz``: ``true`` also starts ``rviz2`` with ``rviz/ppe_ros.rviz`` (needs the rviz2 package);
* ``frame``: RViz's fixed frame (default ``os_lidar``): the input cloud's frame_id, or any frame
  TF connects to it.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution, PythonExpression
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

PACKAGE = 'ppe_ros'
#: sensor argument -> params file in share/ppe_ros/config
PARAMS_FILES = {'none': 'extractor.yaml', 'lidar': 'lidar.yaml', 'depth_camera': 'depth_camera.yaml'}


def generate_launch_description() -> LaunchDescription:
    share = FindPackageShare(PACKAGE)
    sensor = LaunchConfiguration('sensor')
    params_file_of_sensor = PathJoinSubstitution(
        [
            share,
            'config',
            PythonExpression([repr(PARAMS_FILES), ".get('", sensor, "', 'extractor.yaml')"]),
        ]
    )
    arguments = [
        DeclareLaunchArgument(
            'sensor',
            default_value='none',
            choices=list(PARAMS_FILES),
            description='sensor profile: picks config/<profile>.yaml',
        ),
        DeclareLaunchArgument(
            'params_file',
            default_value=params_file_of_sensor,
            description="params file of the extractor (default: the sensor profile's)",
        ),
        DeclareLaunchArgument('points', default_value='/points', description='input PointCloud2 topic'),
        DeclareLaunchArgument(
            'depth_image',
            default_value='/camera/depth/image_rect_raw',
            description='input depth image topic (sensor_msgs/Image, 16UC1 mm or 32FC1 m)',
        ),
        DeclareLaunchArgument(
            'camera_info',
            default_value='/camera/depth/camera_info',
            description="the depth image's sensor_msgs/CameraInfo topic",
        ),
        DeclareLaunchArgument(
            'metadata',
            default_value='/ouster/metadata',
            description="the Ouster driver's metadata topic (std_msgs/String)",
        ),
        DeclareLaunchArgument('namespace', default_value='', description='namespace of the node'),
        DeclareLaunchArgument(
            'use_sim_time', default_value='false', choices=['true', 'false'], description='use /clock (bag replays)'
        ),
        DeclareLaunchArgument(
            'rviz',
            default_value='false',
            choices=['true', 'false'],
            description='also start rviz2 with rviz/ppe_ros.rviz',
        ),
        DeclareLaunchArgument('frame', default_value='os_lidar', description="RViz's fixed frame"),
    ]
    extractor = Node(
        package=PACKAGE,
        executable='extractor',
        name='extractor',
        namespace=LaunchConfiguration('namespace'),
        parameters=[LaunchConfiguration('params_file'), {'use_sim_time': LaunchConfiguration('use_sim_time')}],
        remappings=[
            ('points', LaunchConfiguration('points')),
            ('depth/image', LaunchConfiguration('depth_image')),
            ('depth/camera_info', LaunchConfiguration('camera_info')),
            ('metadata', LaunchConfiguration('metadata')),
        ],
        output='screen',
        emulate_tty=True,
    )
    rviz = Node(
        package='rviz2',
        executable='rviz2',
        name='rviz2',
        arguments=['-d', PathJoinSubstitution([share, 'rviz', 'ppe_ros.rviz']), '-f', LaunchConfiguration('frame')],
        parameters=[{'use_sim_time': LaunchConfiguration('use_sim_time')}],
        condition=IfCondition(LaunchConfiguration('rviz')),
        output='screen',
    )
    return LaunchDescription([*arguments, extractor, rviz])
