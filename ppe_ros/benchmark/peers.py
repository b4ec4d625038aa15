"""Peers a user might pick instead of PPE, as optional extras (imported lazily, skipped when absent).

* ``open3d``: Open3D's ``PointCloud.segment_plane`` (RANSAC) applied iteratively, the common user
  recipe: detect a plane, remove its inliers, repeat until ``fraction`` of the pixels is left.
  Install: ``make peers`` (the open3d pinned in requirements.txt; CPython 3.8-3.12 wheels, about
  400 MB; on Debian/Ubuntu it also needs ``apt-get install libusb-1.0-0``).
* ``open3d-patches``: Open3D's ``detect_planar_patches`` (robust planar patch detection on
  estimated normals); every point is given to the nearest returned patch within ``distance``
  of its plane and inside its oriented box.
* ``polylidar``: Polylidar3D (PyPI ``polylidar``) on its organized-point-cloud path (a triangle
  mesh from the grid, dominant normals from the triangle normals, then plane extraction); PyPI
  has wheels up to CPython 3.10 only.
"""

from __future__ import annotations

import importlib
import sys
import time
from typing import Any

import numpy as np

from ppe_ros.benchmark.methods import MethodUnavailable, PlaneMethod, Segmentation, _check_positive


def _import(module: str, install: str):
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MethodUnavailable(f'{module} is not installed ({exc}); {install}') from None


def _polylidar_hint() -> str:
    version = f'{sys.version_info.major}.{sys.version_info.minor}'
    return (
        f'no wheel for this Python {version} (PyPI has polylidar wheels for CPython <= 3.10 only; this project '
        f'needs >= 3.11); where it is installed the adapter runs it'
    )


class _Open3dMethod(PlaneMethod):
    """What both Open3D adapters share: the optional import and the valid points of the grid."""

    install = 'install it with: make peers  (Debian/Ubuntu also: apt-get install libusb-1.0-0)'

    def check_available(self) -> None:
        _import('open3d', self.install)

    def _open3d_and_points(self, points: np.ndarray) -> tuple[Any, int, int, np.ndarray, np.ndarray]:
        """(open3d module, height, width, (H*W, 3) points, flat indices of the finite ones)."""
        o3d = _import('open3d', self.install)
        cloud = np.asarray(points, dtype=np.float64)
        height, width = cloud.shape[:2]
        flat = cloud.reshape(-1, 3)
        return o3d, height, width, flat, np.flatnonzero(np.isfinite(flat).all(axis=1))


class Open3dSegmentPlane(_Open3dMethod):
    """Open3D ``segment_plane`` in a loop (RANSAC, remove inliers, repeat).

    Args:
        distance: RANSAC inlier distance (m). fraction: stop once this fraction of the pixels is left.
        iterations: RANSAC iterations per plane. seed: Open3D's random seed. max_planes: optional cap.
    """

    name = 'open3d'
    description = 'Open3D segment_plane applied iteratively (RANSAC)'

    def __init__(
        self,
        distance: float = 0.034,
        fraction: float = 0.03,
        *,
        iterations: int = 1000,
        seed: int = 0,
        max_planes: int | None = None,
    ) -> None:
        self.distance = _check_positive(distance, 'distance (m)')
        self.fraction = float(fraction)
        if not 0.0 <= self.fraction < 1.0:
            raise ValueError(f'fraction must be in [0, 1); got {fraction!r}')
        self.iterations = int(iterations)
        self.seed = int(seed)
        self.max_planes = max_planes

    def parameters(self) -> dict[str, Any]:
        return {'distance': self.distance, 'fraction': self.fraction, 'iterations': self.iterations, 'seed': self.seed}

    def segment(self, points: np.ndarray, origins: np.ndarray | None = None) -> Segmentation:
        o3d, height, width, flat, remaining = self._open3d_and_points(points)
        labels = np.zeros(height * width, np.int64)
        stop = max(self.fraction * height * width, 2)
        start = time.perf_counter()
        o3d.utility.random.seed(self.seed)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(flat[remaining]))
        label = 0
        while len(remaining) > stop and len(remaining) >= 3:
            if self.max_planes is not None and label >= self.max_planes:
                break
            _, inliers = pcd.segment_plane(distance_threshold=self.distance, ransac_n=3, num_iterations=self.iterations)
            inliers = np.asarray(inliers, dtype=np.int64)
            if len(inliers) == 0:
                break
            label += 1
            labels[remaining[inliers]] = label
            pcd = pcd.select_by_index(inliers.tolist(), invert=True)
            remaining = np.delete(remaining, inliers)
        seconds = time.perf_counter() - start
        return Segmentation(labels=labels.reshape(height, width), seconds=seconds, info={'planes': label})


class Open3dPlanarPatches(_Open3dMethod):
    """Open3D ``detect_planar_patches`` with every point assigned to its nearest patch.

    Args:
        distance: a point joins a patch when it is within this distance (m) of the patch's plane
            and inside its oriented box (grown by ``distance``).
        normal_radius, normal_neighbors: hybrid KD-tree search of the normal estimation.
    """

    name = 'open3d-patches'
    description = 'Open3D detect_planar_patches (points assigned to the nearest patch)'

    def __init__(self, distance: float = 0.03, *, normal_radius: float = 0.1, normal_neighbors: int = 30) -> None:
        self.distance = _check_positive(distance, 'distance (m)')
        self.normal_radius = _check_positive(normal_radius, 'normal_radius (m)')
        self.normal_neighbors = int(normal_neighbors)

    def parameters(self) -> dict[str, Any]:
        return {
            'distance': self.distance,
            'normal_radius': self.normal_radius,
            'normal_neighbors': self.normal_neighbors,
        }

    def segment(self, points: np.ndarray, origins: np.ndarray | None = None) -> Segmentation:
        o3d, height, width, flat, valid = self._open3d_and_points(points)
        xyz = flat[valid]
        start = time.perf_counter()
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
        pcd.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=self.normal_radius, max_nn=self.normal_neighbors)
        )
        patches = pcd.detect_planar_patches()
        best = np.full(len(xyz), np.inf)
        owner = np.zeros(len(xyz), np.int64)
        for index, box in enumerate(patches, start=1):
            rotation = np.asarray(box.R)
            local = (xyz - np.asarray(box.center)) @ rotation
            half = np.asarray(box.extent) / 2 + self.distance
            plane_distance = np.abs(local[:, 2])
            inside = np.all(np.abs(local[:, :2]) <= half[:2], axis=1) & (plane_distance <= self.distance)
            closer = inside & (plane_distance < best)
            best[closer] = plane_distance[closer]
            owner[closer] = index
        seconds = time.perf_counter() - start
        labels = np.zeros(height * width, np.int64)
        labels[valid] = owner
        return Segmentation(labels=labels.reshape(height, width), seconds=seconds, info={'planes': len(patches)})


class Polylidar3dOrganized(PlaneMethod):
    """Polylidar3D on an organized point cloud (triangle mesh of the grid).

    Dominant plane normals (which Polylidar3D needs as input) are found here by greedy clustering
    of the triangle normals: the most populated direction within ``normal_cluster_deg`` first,
    up to ``max_normals``. Planes are the triangle groups Polylidar3D returns; a pixel gets the
    plane of (one of) its triangles.
    """

    name = 'polylidar'
    description = 'Polylidar3D, organized point cloud path'

    def __init__(
        self,
        lmax: float = 0.1,
        *,
        min_triangles: int = 200,
        z_thresh: float = 0.05,
        norm_thresh: float = 0.96,
        max_normals: int = 8,
        normal_cluster_deg: float = 10.0,
    ) -> None:
        self.lmax = _check_positive(lmax, 'lmax (m)')
        self.min_triangles = int(min_triangles)
        self.z_thresh = float(z_thresh)
        self.norm_thresh = float(norm_thresh)
        self.max_normals = int(max_normals)
        self.normal_cluster_deg = float(normal_cluster_deg)

    def parameters(self) -> dict[str, Any]:
        return {
            'lmax': self.lmax,
            'min_triangles': self.min_triangles,
            'z_thresh': self.z_thresh,
            'norm_thresh': self.norm_thresh,
        }

    def check_available(self) -> None:
        _import('polylidar', _polylidar_hint())

    def _dominant_normals(self, normals: np.ndarray) -> np.ndarray:
        normals = normals[np.isfinite(normals).all(axis=1)]
        cos_limit = np.cos(np.radians(self.normal_cluster_deg))
        chosen = []
        left = normals
        rng = np.random.default_rng(0)
        for _ in range(self.max_normals):
            if len(left) < self.min_triangles:
                break
            candidates = left[rng.choice(len(left), size=min(len(left), 200), replace=False)]
            support = (np.abs(candidates @ left.T) >= cos_limit).sum(axis=1)
            best = candidates[int(np.argmax(support))]
            members = np.abs(left @ best) >= cos_limit
            mean = (left[members] * np.sign(left[members] @ best)[:, None]).mean(axis=0)
            chosen.append(mean / np.linalg.norm(mean))
            left = left[~members]
        return np.array(chosen).reshape(-1, 3)

    def segment(self, points: np.ndarray, origins: np.ndarray | None = None) -> Segmentation:
        polylidar = _import('polylidar', _polylidar_hint())
        cloud = np.ascontiguousarray(points, dtype=np.float64)
        height, width = cloud.shape[:2]
        start = time.perf_counter()
        flat = cloud.reshape(-1, 3)
        mesh, _ = polylidar.extract_tri_mesh_from_organized_point_cloud(
            polylidar.MatrixDouble(np.where(np.isfinite(flat), flat, np.nan)), height, width, 1, calc_normals=True
        )
        triangles = np.asarray(mesh.triangles)
        normals = self._dominant_normals(np.asarray(mesh.triangle_normals))
        labels = np.zeros(height * width, np.int64)
        planes = 0
        if len(normals):
            extractor = polylidar.Polylidar3D(
                alpha=0.0,
                lmax=self.lmax,
                min_triangles=self.min_triangles,
                z_thresh=self.z_thresh,
                norm_thresh=self.norm_thresh,
                norm_thresh_min=self.norm_thresh,
            )
            all_planes, _ = extractor.extract_planes_and_polygons_optimized(mesh, polylidar.MatrixDouble(normals))
            for planes_of_normal in all_planes:
                for triangle_ids in planes_of_normal:
                    planes += 1
                    labels[triangles[np.asarray(triangle_ids, dtype=np.int64)].ravel()] = planes
        seconds = time.perf_counter() - start
        return Segmentation(labels=labels.reshape(height, width), seconds=seconds, info={'planes': planes})


PEERS: dict[str, type[PlaneMethod]] = {
    Open3dSegmentPlane.name: Open3dSegmentPlane,
    Open3dPlanarPatches.name: Open3dPlanarPatches,
    Polylidar3dOrganized.name: Polylidar3dOrganized,
}
"""Peer methods by name (each optional)."""
