"""Message types and the output topics of each input topic (the node's names)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence

from ppe_ros.ros.bag.errors import BagError

POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
IMAGE = 'sensor_msgs/msg/Image'
COMPRESSED_IMAGE = 'sensor_msgs/msg/CompressedImage'
CAMERA_INFO = 'sensor_msgs/msg/CameraInfo'
#: The last name of image_transport's compressedDepth topic of an image topic.
COMPRESSED_DEPTH = 'compressedDepth'
MARKER_ARRAY = 'visualization_msgs/msg/MarkerArray'

#: Output kinds in writing order: topic suffix (relative to the namespace) and message type.
OUTPUT_SUFFIXES: dict[str, str] = {
    'labeled_points': 'planes/labeled_points',
    'markers': 'planes/markers',
    'plane_table': 'planes',
}
OUTPUT_MSGTYPES: dict[str, str] = {
    'labeled_points': POINTCLOUD2,
    'markers': MARKER_ARRAY,
    'plane_table': POINTCLOUD2,
}


def base_image_topic(topic: str) -> str:
    """The image topic of an image_transport topic: ``/camera/depth/image_rect_raw/compressedDepth`` ->
    ``/camera/depth/image_rect_raw``; any other topic is its own."""
    base, _, last = topic.rpartition('/')
    return base if last == COMPRESSED_DEPTH and base else topic


def camera_info_topic(image_topic: str) -> str:
    """The camera info topic beside an image topic (image_transport's convention):
    ``/camera/depth/image_rect_raw`` (and its ``/compressedDepth``) -> ``/camera/depth/camera_info``."""
    return f'{base_image_topic(image_topic).rsplit("/", 1)[0]}/camera_info'


def output_topics(
    input_topics: Sequence[str], *, kinds: Sequence[str] = tuple(OUTPUT_SUFFIXES), reserved: Sequence[str] = ()
) -> dict[str, dict[str, str]]:
    """Output topic of each output kind for each input topic.

    ``/ns/points`` -> ``/ns/planes/labeled_points``, ``/ns/planes/markers``, ``/ns/planes`` (the
    node's relative names in the input's namespace). An input whose outputs another input would
    also get, or that would coincide with a ``reserved`` topic (a copied input), uses
    ``<input topic>/planes/...`` instead.

    Raises:
        BagError: two outputs still coincide (only with contrived topic names).
    """

    def beside(topic: str) -> dict[str, str]:
        namespace = topic.rsplit('/', 1)[0]
        return {kind: f'{namespace}/{OUTPUT_SUFFIXES[kind]}' for kind in kinds}

    def under(topic: str) -> dict[str, str]:
        return {kind: f'{topic.rstrip("/")}/{OUTPUT_SUFFIXES[kind]}' for kind in kinds}

    names = {topic: beside(topic) for topic in input_topics}
    uses = Counter(name for outputs in names.values() for name in outputs.values())
    taken = set(reserved)
    for topic in input_topics:
        if any(uses[name] > 1 or name in taken for name in names[topic].values()):
            names[topic] = under(topic)
    everything = [name for outputs in names.values() for name in outputs.values()]
    clashes = sorted({name for name in everything if everything.count(name) > 1 or name in taken})
    if clashes:
        raise BagError(f'output topics {clashes} would be written twice; process these input topics separately')
    return names
