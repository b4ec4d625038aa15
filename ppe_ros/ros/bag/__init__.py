"""``ros2 run ppe_ros process_bag IN OUT``: a bag of point clouds or depth images in, a bag of planes out.

Offline twin of the live node (:mod:`ppe_ros.ros.node`): every frame goes through the same
:func:`ppe_ros.ros.processing.process_cloud` (or :func:`~ppe_ros.ros.processing.process_depth_image`)
with the same parameters (the node's params file, ``--params``), using rosbags message classes
instead of rclpy (no ROS installation needed). Inputs are the PointCloud2 topics and the depth image
topics (an Image topic with ``camera_info`` beside it and ``depth`` in its name; ``--topic`` names any
Image topic with its camera info); each depth image goes with the camera info read last before it.

Input (read with rosbags): a rosbag2 directory (sqlite3 or mcap, compressed or not), a bare
``.mcap`` / ``.db3`` file, or a ROS 1 ``.bag``. Damaged inputs are read as far as they go: a
rosbag2 directory without ``metadata.yaml`` (recorder killed) is read from its storage files, an
MCAP file without footer and a ROS 1 bag without index are scanned record by record (a chunk cut
short gives the records complete in it), a ``.db3`` that SQLite refuses is read page by page
(:class:`SalvageSqliteReader`), and a cut or corrupt ``.zstd`` storage file (``compression_mode:
file``) is decompressed up to the damage.

Output: a rosbag2 (``--storage mcap`` default, or ``sqlite3``) with, for every input topic, the
node's three outputs at the input message's bag timestamp, each with the input's header:

* ``<ns>/planes/labeled_points`` (``sensor_msgs/msg/PointCloud2``: x y z label rgb),
* ``<ns>/planes/markers`` (``visualization_msgs/msg/MarkerArray``),
* ``<ns>/planes`` (``sensor_msgs/msg/PointCloud2``, one point per plane),

where ``<ns>`` is the input topic without its last element, as for the node, which subscribes to
``points`` and publishes ``planes/...`` in its namespace: ``/ouster/points`` gives
``/ouster/planes/labeled_points`` and so on. Input topics that would share outputs (``/ns/a`` and
``/ns/b``), or an output that would coincide with a copied input topic, use
``<input topic>/planes/...`` instead. ``publish_*: false`` in the params file leaves that output
out. ``--copy-input`` also copies the input topics (ROS 1 messages converted to ROS 2).

Several inputs (``process_bag IN [IN ...] OUT``, or a directory of bags as IN): OUT is a
directory with one output bag per input, named after it (``runs/a.mcap`` -> ``OUT/a``), each
byte for byte what a single run on that input writes, and a summary table over all inputs at the
end; an input that cannot be used is reported and the others go on. ``--executor ray`` sends the
frames, ``--task-frames`` at a time, to Ray tasks (a local Ray of ``--jobs`` CPUs, or the cluster
at ``--ray-address``); this process still reads the inputs and writes the outputs, in input
order, so the outputs are the local run's bytes. A task whose worker dies is retried
(``--task-retries``), then that input is reported incomplete.

Safety: the input is only read. The output is written to a hidden staging directory next to OUT
and renamed to OUT when complete; an existing OUT is replaced only with ``--force``. A message that
does not decode or a frame the extractor cannot use is skipped, logged and counted. A read error in
the middle of the input, a dying worker or Ctrl-C (SIGINT/SIGTERM: the frames in flight are
finished first; a second Ctrl-C drops them) still closes the output as a valid bag holding every
frame processed before it.

Exit codes: 0 done; 1 the input is damaged or processing stopped on an error (OUT holds the frames
before it); 2 bad command line or input (no output written); 128 + signal number when interrupted.

Modules, one concern each: :mod:`.inputs` (opening any input kind), :mod:`.salvage` (damaged
storage files; the one place that uses rosbags internals), :mod:`.compression`, :mod:`.frames`
(one frame), :mod:`.executors` (inline or worker processes), :mod:`.signals` (Ctrl-C),
:mod:`.output` (the output bag and path checks), :mod:`.report` (options, counts, summary),
:mod:`.runner` (:func:`process_bag`, :func:`process_bags`), :mod:`.discovery` (several inputs),
:mod:`.ray_executor` (``--executor ray``), :mod:`.cli` (the command line).
"""

from __future__ import annotations

from ppe_ros.ros.bag.cli import (
    add_arguments,
    build_parser,
    main,
    options_from_args,
    read_params_file,
    run,
    runs_from_args,
)
from ppe_ros.ros.bag.discovery import expand_inputs, output_paths
from ppe_ros.ros.bag.errors import EXIT_DAMAGED, EXIT_OK, EXIT_USAGE, BagError, describe_read_error
from ppe_ros.ros.bag.executors import FrameExecutor, InlineExecutor, PoolExecutor, TaskFailed, default_numba_threads
from ppe_ros.ros.bag.frames import FrameProcessor, FrameResult, ros1_as_ros2, ros1_cloud_as_ros2
from ppe_ros.ros.bag.inputs import InputBag, InputTopic, open_input_bag, select_topics
from ppe_ros.ros.bag.output import DEFAULT_STORAGE, STORAGES, OutputBag, check_paths
from ppe_ros.ros.bag.ray_executor import RayExecutor
from ppe_ros.ros.bag.report import (
    BagOptions,
    BagReport,
    BagsReport,
    TopicReport,
    describe_completion,
    format_report,
    format_summary,
    report_problems,
)
from ppe_ros.ros.bag.runner import process_bag, process_bags
from ppe_ros.ros.bag.salvage import SalvageMcapReader, SalvageRos1Reader, SalvageSqliteReader
from ppe_ros.ros.bag.signals import StopRequests
from ppe_ros.ros.bag.topics import MARKER_ARRAY, OUTPUT_MSGTYPES, OUTPUT_SUFFIXES, POINTCLOUD2, output_topics

__all__ = [
    'DEFAULT_STORAGE',
    'EXIT_DAMAGED',
    'EXIT_OK',
    'EXIT_USAGE',
    'MARKER_ARRAY',
    'OUTPUT_MSGTYPES',
    'OUTPUT_SUFFIXES',
    'POINTCLOUD2',
    'STORAGES',
    'BagError',
    'BagOptions',
    'BagReport',
    'BagsReport',
    'FrameExecutor',
    'FrameProcessor',
    'FrameResult',
    'InlineExecutor',
    'InputBag',
    'InputTopic',
    'OutputBag',
    'PoolExecutor',
    'RayExecutor',
    'SalvageMcapReader',
    'SalvageRos1Reader',
    'SalvageSqliteReader',
    'StopRequests',
    'TaskFailed',
    'TopicReport',
    'add_arguments',
    'build_parser',
    'check_paths',
    'default_numba_threads',
    'describe_completion',
    'describe_read_error',
    'expand_inputs',
    'format_report',
    'format_summary',
    'main',
    'open_input_bag',
    'options_from_args',
    'output_paths',
    'output_topics',
    'process_bag',
    'process_bags',
    'read_params_file',
    'report_problems',
    'ros1_as_ros2',
    'ros1_cloud_as_ros2',
    'run',
    'runs_from_args',
    'select_topics',
]
