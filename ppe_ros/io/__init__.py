"""Scan files (PCD, NPY, depth PNG) -> organized clouds, and PCD writing. Pure numpy/numba (+ Pillow for PNG).

from ppe_ros.io import load_scan
scan = load_scan('../shared/data/synpeb/pc_01.pcd')   # scan.points (H, W, 3) metres, scan.labels
"""

from __future__ import annotations

from ppe_ros.io.depth import PinholeIntrinsics, backproject_depth
from ppe_ros.io.errors import ScanFileError
from ppe_ros.io.loading import FORMATS, UNIT_SCALES, Scan, load_scan
from ppe_ros.io.pcd import read_pcd, save_pcd

__all__ = [
    'FORMATS',
    'UNIT_SCALES',
    'PinholeIntrinsics',
    'Scan',
    'ScanFileError',
    'backproject_depth',
    'load_scan',
    'read_pcd',
    'save_pcd',
]
