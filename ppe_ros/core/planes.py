"""The result type of plane extraction: a segmentation of an organized scan into finite planes.

Pure numpy; no ROS import. Frames: every vector is in the frame of the input points (for a
sensor message, its ``header.frame_id``); lengths are metres, errors m^2.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class PlaneSet:
    """Finite planes extracted from one organized scan.

    Attributes:
        labels: ``(H, W)`` int32; 0 = no plane, planes are numbered ``1..J`` by decreasing
            point count (ties: the plane whose first pixel in row-major order comes first).
        normals: ``(J, 3)`` unit normals; each faces the sensor (the mean ray origin of its rays).
        offsets: ``(J,)`` plane offsets ``d`` with ``normals[j] . x = offsets[j]`` for points x
            on plane j+1, in metres.
        centroids: ``(J, 3)`` mean of each plane's measured endpoints, metres.
        point_counts: ``(J,)`` int64 number of rays (pixels) of each plane.
        sse: ``(J,)`` sum of squared radial (ray-length) residuals of the maximum-likelihood fit, m^2.
        rmse: ``(J,)`` ``sqrt(sse / point_counts)``, metres.
        covariances: ``(J, 3, 3)`` covariance of the closest-point vector ``offsets * normals``
            (m^2), from the Gauss-Newton information matrix of the fit, with the noise variance
            estimated from the plane's own residuals (``sse / (count - 3)``); with a sensor profile
            the fit is weighted by the noise model and a systematic part is added (errors
            correlated over the surface, see docs/algorithm.md).
        max_error_increment: the threshold e (m^2) this snapshot was cut at, or None.
        max_planes: the plane-count threshold this snapshot was cut at, or None.
        actions: number of greedy actions executed to reach this snapshot.
    """

    labels: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray
    centroids: np.ndarray
    point_counts: np.ndarray
    sse: np.ndarray
    rmse: np.ndarray
    covariances: np.ndarray
    max_error_increment: float | None = None
    max_planes: int | None = None
    actions: int = 0
    meta: dict = field(default_factory=dict)

    @property
    def num_planes(self) -> int:
        """Number of planes J."""
        return len(self.offsets)

    def closest_points(self) -> np.ndarray:
        """``(J, 3)`` closest-point vectors ``d * n`` (metres)."""
        return self.offsets[:, None] * self.normals

    @classmethod
    def empty(cls, shape: tuple[int, int], **kwargs) -> PlaneSet:
        """A segmentation of a ``shape`` grid with no plane."""
        return cls(
            labels=np.zeros(shape, np.int32),
            normals=np.zeros((0, 3)),
            offsets=np.zeros(0),
            centroids=np.zeros((0, 3)),
            point_counts=np.zeros(0, np.int64),
            sse=np.zeros(0),
            rmse=np.zeros(0),
            covariances=np.zeros((0, 3, 3)),
            **kwargs,
        )

    def to_npz_dict(self) -> dict[str, np.ndarray]:
        """Arrays for ``np.savez`` (the format ``ppe extract`` writes and ``ppe score`` reads)."""
        out = {
            'labels': self.labels,
            'normals': self.normals,
            'offsets': self.offsets,
            'centroids': self.centroids,
            'point_counts': self.point_counts,
            'sse': self.sse,
            'rmse': self.rmse,
            'covariances': self.covariances,
            'actions': np.int64(self.actions),
        }
        if self.max_error_increment is not None:
            out['max_error_increment'] = np.float64(self.max_error_increment)
        if self.max_planes is not None:
            out['max_planes'] = np.int64(self.max_planes)
        return out
