"""ppe_ros: Probabilistic Plane Extraction (Schaefer et al., ICRA 2019) for organized 3-D scans.

The public API needs only numpy and numba (no ROS import here)::

    from ppe_ros import extract_planes
    planes = extract_planes(points, max_error_increment=0.0484, max_neighbor_distance=0.18)
    planes = extract_planes(points, origins=origins, sensor='lidar')   # a real sensor's profile

Names are resolved lazily so that ``import ppe_ros`` stays fast.
"""

from __future__ import annotations

import importlib

__version__ = '0.1.0'

_EXPORTS = {
    'PlaneSet': 'ppe_ros.core.planes',
    'extract_planes': 'ppe_ros.core.extraction',
    'extract_plane_hierarchy': 'ppe_ros.core.extraction',
    'PlaneHierarchy': 'ppe_ros.core.extraction',
    'GreedyOptions': 'ppe_ros.core.extraction',
    'release_work_memory': 'ppe_ros.core.extraction',
    'fit_plane': 'ppe_ros.core.fitting',
    'fit_labeled_planes': 'ppe_ros.core.fitting',
    'NoiseModel': 'ppe_ros.core.sensor',
    'SensorProfile': 'ppe_ros.core.sensor',
    'PROFILES': 'ppe_ros.core.sensor',
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    return getattr(importlib.import_module(module), name)
