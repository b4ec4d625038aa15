"""Metrics of the real-data benchmark (``benchmarks/bench_real.py``): pure numpy (+ one numba kernel), no ROS.

The benchmark runs plane extractors on the real scans of ``../shared/data`` (Ouster sweeps, a TLS
scan, a Kinect frame, ICL-NUIM frames) and measures what a mapping user needs from planes:

* how many planes a scan is cut into (:func:`count_planes`) and how much of it lies in large planes
  (:func:`share_in_large_planes`);
* for lidar sweeps, how whole the ground is: a RANSAC ground plane within 25 m
  (:func:`fit_ground_plane`), then the largest plane's share of it and the number of planes that
  cover 80 % of it (:func:`ground_cover`);
* repeatability over consecutive sweeps: planes of sweep A are moved into sweep B's frame by the
  registration ``p_B = R p_A + t``, their points projected into B's range image
  (:class:`RangeImageProjector`) and matched to B's labels (:func:`match_planes`);
* covariance calibration: the Mahalanobis² of the difference of matched planes' closest points
  ``d n`` under the sum of their reported covariances (:func:`mahalanobis_squared`); a calibrated
  covariance gives the chi²(3) median :data:`CHI2_3_MEDIAN`.
* whether neighbouring large planes are flat strips of one curved surface: plane and quadric fits of
  their union (:func:`surface_shape`, :func:`smooth_surfaces`; ``benchmarks/bench_surface_shape.py``).

Frames: every point is in its scan's sensor frame (metres); a registration maps A's frame into B's.
The scans themselves and which of them were used to choose defaults are :data:`REAL_SCANS` and
:data:`SCAN_SPLIT`.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numba as nb
import numpy as np

from ppe_ros.core.sensor import SensorProfile, sensor_profile

CHI2_3_MEDIAN = 2.365973884375338
"""Median of the chi-squared distribution with 3 degrees of freedom: the Mahalanobis² median of a calibrated 3-D
covariance."""

SCAN_SPLIT: dict[str, str] = {
    'OS-0-128 1491': 'training',
    'OS-2-128 1259': 'training',
    'OS-2-32 5424': 'training',
    'OS-1-32 638': 'training',
    'ICL-NUIM 0': 'training',
    'OS-1-128 1795': 'reported',
    'OS-1-128 1796': 'reported',
    'OS-1-128 1797': 'reported',
    'TLS': 'reported',
    'Kinect': 'reported',
    'ICL-NUIM 1': 'reported',
    'ICL-NUIM 2': 'reported',
}
"""Which real scans may be used to choose defaults ('training') and which are only reported ('reported')."""


@dataclass(frozen=True)
class RealScan:
    """One real scan of the shared data.

    Attributes:
        name: short name (the key of :data:`SCAN_SPLIT`).
        path: file path relative to the shared data folder.
        kind: ``'lidar'`` (spinning lidar / TLS: range noise) or ``'depth_camera'`` (pinhole depth image).
        units: the ``units`` argument of :func:`ppe_ros.io.load_scan` (None = the loader's default).
        ground: measure the ground cover (Ouster sweeps: sensor frame z up).
        labelled: the scan has ground-truth plane labels (ICL-NUIM).
    """

    name: str
    path: str
    kind: str
    units: str | None = None
    ground: bool = False
    labelled: bool = False

    @property
    def split(self) -> str:
        """'training' or 'reported' (:data:`SCAN_SPLIT`)."""
        return SCAN_SPLIT[self.name]


REAL_SCANS: tuple[RealScan, ...] = (
    RealScan('OS-0-128 1491', 'ouster/OS-0-128-U1_v2.3.0_1024x10_frame1491_xyz_m.npy', 'lidar', ground=True),
    RealScan('OS-2-128 1259', 'ouster/OS-2-128-U1_v2.3.0_1024x10_frame1259_xyz_m.npy', 'lidar', ground=True),
    RealScan('OS-2-32 5424', 'ouster/OS-2-32-U0_v2.0.0_1024x10_frame5424_xyz_m.npy', 'lidar', ground=True),
    RealScan('OS-1-32 638', 'ouster/OS-1-32-G_v2.1.1_1024x10_frame638_xyz_m.npy', 'lidar', ground=True),
    RealScan('OS-1-128 1795', 'ouster/OS-1-128_v2.3.0_1024x10_lb_n3_frame1795_xyz_m.npy', 'lidar', ground=True),
    RealScan('OS-1-128 1796', 'ouster/OS-1-128_v2.3.0_1024x10_lb_n3_frame1796_xyz_m.npy', 'lidar', ground=True),
    RealScan('OS-1-128 1797', 'ouster/OS-1-128_v2.3.0_1024x10_lb_n3_frame1797_xyz_m.npy', 'lidar', ground=True),
    RealScan('TLS', 'tls/andreashaus_scan000.pcd', 'lidar', units='cm'),
    RealScan('Kinect', 'kinect/depth_0.png', 'depth_camera'),
    RealScan('ICL-NUIM 0', 'icl_nuim/icl_nuim_0.png', 'depth_camera', labelled=True),
    RealScan('ICL-NUIM 1', 'icl_nuim/icl_nuim_1.png', 'depth_camera', labelled=True),
    RealScan('ICL-NUIM 2', 'icl_nuim/icl_nuim_2.png', 'depth_camera', labelled=True),
)
"""The real scans of ``../shared/data`` in table order."""


def profile_with_settings(sensor: str, settings: Sequence[str] = ()) -> SensorProfile:
    """The sensor profile ``sensor`` with fields set by ``name=value`` strings (value: JSON, e.g.
    ``surface_tolerance=0.065``, ``flatness_length=null``): a variant to measure on training data.

    Raises:
        ValueError: an unknown profile or field, or a value that is not JSON or not accepted by the profile.
    """
    profile = sensor_profile(sensor)
    names = {f.name for f in dataclasses.fields(profile)}
    changes = {}
    for item in settings:
        name, sep, text = str(item).partition('=')
        if not sep or name.strip() not in names:
            raise ValueError(f'a setting must be name=value with a field of SensorProfile; got {item!r}')
        try:
            value = json.loads(text)
            changes[name.strip()] = tuple(value) if isinstance(value, list) else value
        except json.JSONDecodeError as exc:
            raise ValueError(
                f'the value of {name.strip()} must be JSON (0.065, true, null, "square"); got {text!r}'
            ) from exc
    try:
        return dataclasses.replace(profile, **changes)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'profile {profile.name!r} does not take {changes}: {exc}') from exc


SEQUENCE_PAIRS: tuple[tuple[str, str], ...] = (('OS-1-128 1795', 'OS-1-128 1796'), ('OS-1-128 1796', 'OS-1-128 1797'))
"""Consecutive sweeps (A, B) of the repeatability and covariance metrics."""


# --------------------------------------------------------------------------------------------- plane sizes


def plane_point_counts(labels: np.ndarray) -> np.ndarray:
    """Number of pixels of every plane label > 0 (ascending label order; labels without pixels are left out)."""
    lab = np.asarray(labels).ravel()
    _, counts = np.unique(lab[lab > 0], return_counts=True)
    return counts.astype(np.int64)


def count_planes(labels: np.ndarray, min_points: int = 20) -> int:
    """Number of planes (labels > 0) with at least ``min_points`` pixels."""
    return int(np.count_nonzero(plane_point_counts(labels) >= min_points))


def share_in_large_planes(labels: np.ndarray, valid: np.ndarray, min_points: int = 1000) -> float:
    """Fraction of the valid pixels that lie in planes of at least ``min_points`` pixels (NaN without valid pixels).

    Args:
        labels: ``(H, W)`` plane labels, 0 = no plane.
        valid: ``(H, W)`` bool, the pixel holds a measured point.
    """
    lab = np.asarray(labels)
    mask = np.asarray(valid, dtype=bool)
    if lab.shape != mask.shape:
        raise ValueError(f'labels {lab.shape} and valid {mask.shape} must have the same shape')
    n_valid = int(np.count_nonzero(mask))
    if n_valid == 0:
        return math.nan
    values, counts = np.unique(lab[mask & (lab > 0)], return_counts=True)
    large = values[counts >= min_points]
    return float(np.count_nonzero(mask & np.isin(lab, large))) / n_valid


# --------------------------------------------------------------------------------------------- ground


@dataclass(frozen=True)
class GroundPlane:
    """A ground plane ``normal . x = offset`` (normal up, metres) and its inlier pixels ``mask`` (H, W)."""

    normal: np.ndarray
    offset: float
    mask: np.ndarray

    @property
    def num_points(self) -> int:
        return int(np.count_nonzero(self.mask))


def _plane_through(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares (orthogonal) plane of ``(n, 3)`` points: unit normal with z >= 0 and offset."""
    centroid = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centroid, full_matrices=False)
    normal = vt[2]
    if normal[2] < 0:
        normal = -normal
    return normal, float(normal @ centroid)


def fit_ground_plane(
    points: np.ndarray,
    *,
    max_horizontal_distance: float = 25.0,
    inlier_distance: float = 0.10,
    max_tilt_deg: float = 20.0,
    iterations: int = 500,
    sample_size: int = 20000,
    seed: int = 0,
) -> GroundPlane:
    """RANSAC ground plane of a lidar sweep whose frame has z up.

    Candidates are the valid points within ``max_horizontal_distance`` (m) of the z axis. RANSAC draws
    ``iterations`` point triples (deterministic for ``seed``), keeps planes whose normal is within
    ``max_tilt_deg`` of z and scores them by their inliers within ``inlier_distance`` (m) on a random
    subsample of ``sample_size`` candidates; the best plane is refitted (orthogonal least squares) to its
    inliers among all candidates twice. The ground is every candidate within ``inlier_distance`` of it.

    Raises:
        ValueError: fewer than 3 candidate points, or no admissible plane.
    """
    cloud = np.asarray(points, dtype=np.float64)
    if cloud.ndim != 3 or cloud.shape[2] != 3:
        raise ValueError(f'points must be an organized (H, W, 3) array; got shape {cloud.shape}')
    flat = cloud.reshape(-1, 3)
    with np.errstate(invalid='ignore'):
        candidate = np.isfinite(flat).all(axis=1) & (np.hypot(flat[:, 0], flat[:, 1]) <= max_horizontal_distance)
    index = np.flatnonzero(candidate)
    if len(index) < 3:
        raise ValueError(f'only {len(index)} valid points within {max_horizontal_distance} m; no ground plane')
    rng = np.random.default_rng(seed)
    sample = flat[index if len(index) <= sample_size else rng.choice(index, sample_size, replace=False)]
    triples = rng.integers(0, len(sample), size=(iterations, 3))
    p0, p1, p2 = sample[triples[:, 0]], sample[triples[:, 1]], sample[triples[:, 2]]
    normals = np.cross(p1 - p0, p2 - p0)
    lengths = np.linalg.norm(normals, axis=1)
    ok = lengths > 1e-9
    normals[ok] /= lengths[ok, None]
    normals *= np.where(normals[:, 2] < 0, -1.0, 1.0)[:, None]
    ok &= normals[:, 2] >= math.cos(math.radians(max_tilt_deg))
    if not np.any(ok):
        raise ValueError(f'no plane within {max_tilt_deg} deg of horizontal among {iterations} RANSAC samples')
    normals, offsets = normals[ok], np.einsum('ij,ij->i', normals[ok], p0[ok])
    scores = np.array(
        [np.count_nonzero(np.abs(sample @ n - d) <= inlier_distance) for n, d in zip(normals, offsets, strict=True)]
    )
    best = int(np.argmax(scores))
    normal, offset = normals[best], float(offsets[best])
    candidates = flat[index]
    for _ in range(2):
        inliers = np.abs(candidates @ normal - offset) <= inlier_distance
        if np.count_nonzero(inliers) < 3:
            break
        normal, offset = _plane_through(candidates[inliers])
    mask = np.zeros(len(flat), bool)
    mask[index[np.abs(candidates @ normal - offset) <= inlier_distance]] = True
    return GroundPlane(normal=normal, offset=offset, mask=mask.reshape(cloud.shape[:2]))


@dataclass(frozen=True)
class GroundCover:
    """How the planes of a segmentation cover a ground mask.

    Attributes:
        ground_points: pixels of the ground.
        largest_share: the largest share of the ground that one plane holds (0..1).
        planes_for_share: the fewest planes that together hold at least ``share`` of the ground, or None
            if all planes together hold less.
        covered_share: the share of the ground in any plane.
        planes_touching: planes that hold at least one ground pixel.
        share: the target share (0.8).
    """

    ground_points: int
    largest_share: float
    planes_for_share: int | None
    covered_share: float
    planes_touching: int
    share: float


def ground_cover(labels: np.ndarray, ground: np.ndarray, share: float = 0.8) -> GroundCover:
    """Largest plane's share of the ``ground`` pixels and the number of planes needed to cover ``share`` of them.

    The fewest planes are the largest ones (by ground pixels) first: a prefix of the sorted overlaps.
    """
    lab = np.asarray(labels)
    mask = np.asarray(ground, dtype=bool)
    if lab.shape != mask.shape:
        raise ValueError(f'labels {lab.shape} and ground {mask.shape} must have the same shape')
    if not 0.0 < share <= 1.0:
        raise ValueError(f'share must be in (0, 1]; got {share}')
    n_ground = int(np.count_nonzero(mask))
    if n_ground == 0:
        return GroundCover(0, math.nan, None, math.nan, 0, share)
    _, overlaps = np.unique(lab[mask & (lab > 0)], return_counts=True)
    overlaps = np.sort(overlaps)[::-1]
    cumulative = np.cumsum(overlaps)
    reached = np.flatnonzero(cumulative >= share * n_ground)
    return GroundCover(
        ground_points=n_ground,
        largest_share=float(overlaps[0]) / n_ground if len(overlaps) else 0.0,
        planes_for_share=int(reached[0]) + 1 if len(reached) else None,
        covered_share=float(cumulative[-1]) / n_ground if len(overlaps) else 0.0,
        planes_touching=len(overlaps),
        share=share,
    )


# --------------------------------------------------------------------------------------------- connected parts


@nb.njit(cache=True)
def _find_root(parent, x):
    while parent[x] != x:
        parent[x] = parent[parent[x]]
        x = parent[x]
    return x


@nb.njit(cache=True)
def _connected_parts_kernel(labels, height, width, out):
    n = height * width
    parent = np.arange(n)
    for r in range(height):
        for c in range(width):
            k = r * width + c
            if labels[k] <= 0:
                continue
            for nb_k in (k - 1 if c > 0 else -1, k - width if r > 0 else -1):
                if nb_k >= 0 and labels[nb_k] == labels[k]:
                    a = _find_root(parent, k)
                    b = _find_root(parent, nb_k)
                    if a != b:
                        if a < b:
                            parent[b] = a
                        else:
                            parent[a] = b
    for k in range(n):
        out[k] = _find_root(parent, k) if labels[k] > 0 else -1


def connected_parts(labels: np.ndarray, min_points: int = 20) -> np.ndarray:
    """Split every label into its 4-connected parts on the grid; keep parts of at least ``min_points`` pixels.

    Returns:
        ``(H, W)`` int64 labels ``1..J`` by decreasing part size (ties: first pixel in row-major order);
        0 = no plane or a part that is too small.
    """
    lab = np.asarray(labels)
    if lab.ndim != 2:
        raise ValueError(f'labels must be a 2-D (H, W) array; got shape {lab.shape}')
    height, width = lab.shape
    roots = np.empty(height * width, np.int64)
    _connected_parts_kernel(np.ascontiguousarray(lab, dtype=np.int64).ravel(), height, width, roots)
    out = np.zeros(height * width, np.int64)
    inside = roots >= 0
    values, first, inverse, counts = np.unique(
        roots[inside], return_index=True, return_inverse=True, return_counts=True
    )
    order = np.lexsort((first, -counts))  # by size, then by first pixel (roots are the smallest pixel id)
    rank = np.empty(len(values), np.int64)
    rank[order] = np.arange(1, len(values) + 1)
    new = np.where(counts[inverse] >= min_points, rank[inverse], 0)
    kept = np.unique(new[new > 0])
    remap = np.zeros(len(values) + 1, np.int64)
    remap[kept] = np.arange(1, len(kept) + 1)
    out[inside] = remap[new]
    return out.reshape(height, width)


# --------------------------------------------------------------------------------------------- motion


def rigid_fit_from_planes(
    normals_a: np.ndarray,
    offsets_a: np.ndarray,
    normals_b: np.ndarray,
    offsets_b: np.ndarray,
    weights: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Rigid motion ``p_B = R p_A + t`` that maps matched planes of A onto those of B.

    Plane j is ``n . x = d`` in each frame; a motion maps it to ``n' = R n_A``, ``d' = d_A + n' . t``. R
    is the weighted Kabsch rotation of the normals, t the weighted least squares of ``n'_j . t = d_B - d_A``.
    Needs at least three planes whose normals span 3-D space.

    Raises:
        ValueError: fewer than 3 pairs or normals that do not constrain t.
    """
    na, nb_ = np.asarray(normals_a, float), np.asarray(normals_b, float)
    da, db = np.asarray(offsets_a, float), np.asarray(offsets_b, float)
    if na.shape != nb_.shape or na.ndim != 2 or na.shape[1] != 3 or da.shape != (len(na),) or db.shape != da.shape:
        raise ValueError('normals must be (J, 3) and offsets (J,) in both frames')
    if len(na) < 3:
        raise ValueError(f'a rigid fit from planes needs >= 3 matched planes; got {len(na)}')
    w = np.ones(len(na)) if weights is None else np.asarray(weights, float)
    h = (w[:, None] * na).T @ nb_
    u, _, vt = np.linalg.svd(h)
    sign = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rotation = vt.T @ np.diag([1.0, 1.0, sign]) @ u.T
    moved = na @ rotation.T
    a = (w[:, None] * moved).T @ moved
    if np.linalg.cond(a) > 1e8:
        raise ValueError("the matched planes' normals do not span 3-D space; translation undetermined")
    translation = np.linalg.solve(a, (w[:, None] * moved).T @ (db - da))
    return rotation, translation


def transform_planes(
    normals: np.ndarray, offsets: np.ndarray, rotation: np.ndarray, translation: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Planes ``n . x = d`` of frame A in frame B (``p_B = R p_A + t``): ``(R n, d + (R n) . t)``."""
    moved = np.asarray(normals, float) @ np.asarray(rotation, float).T
    return moved, np.asarray(offsets, float) + moved @ np.asarray(translation, float)


def closest_point_jacobian(closest_point: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """``(3, 3)`` derivative of B's closest point ``d' n'`` with respect to A's closest point ``c = d n``.

    With ``u = R c``, ``n' = u / |u|``, ``d' = |u| + n' . t``: ``c' = u + (n' . t) n'`` and
    ``dc'/du = I + (n' t^T + (n' . t) I)(I - n' n'^T) / |u|``.
    """
    u = np.asarray(rotation, float) @ np.asarray(closest_point, float)
    length = float(np.linalg.norm(u))
    normal = u / length
    t = np.asarray(translation, float)
    projector = np.eye(3) - np.outer(normal, normal)
    du = np.eye(3) + (np.outer(normal, t) + (normal @ t) * np.eye(3)) @ projector / length
    return du @ rotation


def registration_covariance(
    normal: np.ndarray, offset: float, sigma_translation: float, sigma_rotation: float
) -> np.ndarray:
    """``(3, 3)`` covariance that a registration error adds to a plane's closest point ``c = d n`` in B's frame.

    A small extra motion (rotation vector ``w`` about B's origin, translation ``u``) moves the plane to
    ``n + w x n`` and ``d + n . u``, so ``dc = n n^T u - d [n]x w``. With isotropic independent errors of
    ``sigma_translation`` (m) and ``sigma_rotation`` (rad) per axis:
    ``C = sigma_t^2 n n^T + d^2 sigma_r^2 [n]x [n]x^T``.
    """
    n = np.asarray(normal, float)
    cross = np.array([[0.0, -n[2], n[1]], [n[2], 0.0, -n[0]], [-n[1], n[0], 0.0]])
    return sigma_translation**2 * np.outer(n, n) + (offset * sigma_rotation) ** 2 * cross @ cross.T


def mahalanobis_squared(delta: np.ndarray, covariance: np.ndarray) -> float:
    """``delta^T C^-1 delta`` (NaN when C is not positive definite or not finite)."""
    cov = np.asarray(covariance, float)
    vec = np.asarray(delta, float)
    if not (np.all(np.isfinite(cov)) and np.all(np.isfinite(vec))):
        return math.nan
    try:
        factor = np.linalg.cholesky(0.5 * (cov + cov.T))
    except np.linalg.LinAlgError:
        return math.nan
    solved = np.linalg.solve(factor, vec)
    return float(solved @ solved)


def truth_mahalanobis(
    labels: np.ndarray,
    offsets: np.ndarray,
    normals: np.ndarray,
    covariances: np.ndarray,
    truth_labels: np.ndarray,
    true_plane,
    min_points: int = 1000,
    min_truth_label: int = 10,
) -> np.ndarray:
    """Covariance calibration against known planes (generated scans): for every plane of at least
    ``min_points`` points whose points lie mostly (more than half) on one ground-truth surface, the
    Mahalanobis² of the difference of its closest point ``offsets[j] * normals[j]`` from that surface's
    (``true_plane(label) -> (normal, offset)``, the same frame) under ``covariances[j]``.

    ``labels``: the planes' label image (plane j is label j + 1, 0 = none); ``truth_labels`` the same
    shape, surfaces labelled >= ``min_truth_label``. Returns the values, in plane order.
    """
    flat = np.asarray(labels).reshape(-1)
    truth = np.asarray(truth_labels).reshape(-1)
    if flat.shape != truth.shape:
        raise ValueError(
            f'labels and truth_labels must have one shape; got {np.shape(labels)} and {np.shape(truth_labels)}'
        )
    values = []
    for j in range(len(offsets)):
        on_plane = truth[flat == j + 1]
        if len(on_plane) < min_points:
            continue
        surfaces, counts = np.unique(on_plane[on_plane >= min_truth_label], return_counts=True)
        if not len(counts) or 2 * counts.max() <= len(on_plane):
            continue
        normal, offset = true_plane(int(surfaces[np.argmax(counts)]))
        delta = float(offsets[j]) * np.asarray(normals[j], float) - float(offset) * np.asarray(normal, float)
        values.append(mahalanobis_squared(delta, covariances[j]))
    return np.asarray(values, dtype=np.float64)


# --------------------------------------------------------------------------------------------- matching


class RangeImageProjector:
    """Projects points into the pixel grid of a spinning-lidar sweep (row = beam elevation, column = azimuth).

    Built from the sweep's own organized points: every row's elevation and a linear column -> azimuth model
    are the medians over its valid points, measured from the ray starts (``origins``; the Ouster beams start
    on a circle of about 15 mm around the axis, which matters at short range). A query point is given the
    row of the nearest elevation and the nearest column, measured from the mean ray start height and circle.
    """

    def __init__(self, points: np.ndarray, origins: np.ndarray | None = None) -> None:
        cloud = np.asarray(points, dtype=np.float64)
        if cloud.ndim != 3 or cloud.shape[2] != 3:
            raise ValueError(f'points must be an organized (H, W, 3) array; got shape {cloud.shape}')
        self.height, self.width = cloud.shape[:2]
        self.points = cloud
        self.valid = np.isfinite(cloud).all(axis=2)
        starts = np.zeros_like(cloud) if origins is None else np.broadcast_to(np.asarray(origins, float), cloud.shape)
        rays = cloud - starts
        with np.errstate(invalid='ignore'):
            elevation = np.arctan2(rays[..., 2], np.hypot(rays[..., 0], rays[..., 1]))
            azimuth = np.arctan2(rays[..., 1], rays[..., 0])
        self.start_height = float(np.mean(starts[..., 2][self.valid])) if self.valid.any() else 0.0
        start_xy = starts[..., :2][self.valid]
        self.start_center = start_xy.mean(axis=0) if len(start_xy) else np.zeros(2)
        self.start_radius = (
            float(np.median(np.linalg.norm(start_xy - self.start_center, axis=1))) if len(start_xy) else 0.0
        )
        rows = np.array(
            [np.median(elevation[r][self.valid[r]]) if self.valid[r].any() else np.nan for r in range(self.height)]
        )
        known = np.isfinite(rows)
        if np.count_nonzero(known) < 1:
            raise ValueError('the sweep has no valid point')
        if not np.all(known):
            rows = np.interp(np.arange(self.height), np.flatnonzero(known), rows[known])
        self.row_elevation = rows
        self.row_order = np.argsort(rows)
        # column j has azimuth a0 + s * 2 pi j / W (s = +-1): pick the sign and a0 by circular means
        columns = np.broadcast_to(np.arange(self.width), (self.height, self.width))[self.valid]
        angles = azimuth[self.valid]
        best = None
        for sign in (-1.0, 1.0):
            phase = angles - sign * 2 * np.pi * columns / self.width
            mean = np.exp(1j * phase).mean()
            if best is None or abs(mean) > best[0]:
                best = (abs(mean), sign, float(np.angle(mean)))
        self.column_sign, self.azimuth0 = best[1], best[2]
        self.pixel_angle = max(
            2 * np.pi / self.width, float(np.median(np.abs(np.diff(np.sort(rows))))) if self.height > 1 else 0.0
        )

    def project(self, query: np.ndarray) -> np.ndarray:
        """Flat pixel index (row * W + column) of each ``(n, 3)`` point, -1 where the pixel holds no point."""
        pixel, offset = self._grid_pixels(query)
        inside = offset <= 1.5 * self.pixel_angle + 1e-9
        pixel[~inside | ~self.valid.ravel()[pixel]] = -1
        return pixel

    def grid_pixels(self, query: np.ndarray) -> np.ndarray:
        """Flat pixel index of each ``(n, 3)`` point whose elevation is within half a beam spacing of its row's
        (-1: between or beyond the beams), whether or not the sweep has a return there: where this sensor's
        beams would see the point."""
        pixel, offset = self._grid_pixels(query)
        pixel[offset > 0.5 * self.pixel_angle] = -1
        return pixel

    def _grid_pixels(self, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The nearest row and column's flat pixel index of each point and its elevation's distance (rad) from
        that row's elevation, measured from the mean ray start height and circle."""
        q = np.asarray(query, dtype=np.float64).reshape(-1, 3)
        xy = q[:, :2] - self.start_center
        rho = np.linalg.norm(xy, axis=1) - self.start_radius
        elevation = np.arctan2(q[:, 2] - self.start_height, rho)
        azimuth = np.arctan2(xy[:, 1], xy[:, 0])
        sorted_rows = self.row_elevation[self.row_order]
        pos = (
            np.clip(np.searchsorted(sorted_rows, elevation), 1, len(sorted_rows) - 1)
            if len(sorted_rows) > 1
            else np.zeros(len(q), np.int64)
        )
        if len(sorted_rows) > 1:
            pos = np.where(
                np.abs(elevation - sorted_rows[pos - 1]) <= np.abs(elevation - sorted_rows[pos]), pos - 1, pos
            )
        row = self.row_order[pos]
        column = np.round(self.column_sign * (azimuth - self.azimuth0) * self.width / (2 * np.pi)).astype(np.int64)
        column %= self.width
        return row * self.width + column, np.abs(elevation - self.row_elevation[row])


def resweep(
    points: np.ndarray,
    origins: np.ndarray | None,
    rotation: np.ndarray,
    translation: np.ndarray,
    *,
    range_sigma: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """The sweep the same sensor would take of sweep A's scene after the motion ``x_B = R x_A + t``.

    A's returns (``(H, W, 3)`` points, m, A's frame; ``origins`` their ray starts, as for extract_planes) are
    moved into B's frame and put on A's own beam grid (:meth:`RangeImageProjector.grid_pixels` of A: the same
    beams and columns): in each pixel the point nearest to the ray start stays (what would hide the others),
    pixels no point falls into have no return. With ``range_sigma`` > 0 (m) each kept point also moves along its
    new ray by Gaussian noise of that standard deviation (a new measurement of it; seeded by ``seed``). Returns
    ``(H, W, 3)`` points in B's frame, NaN where there is no return. A training sequence of real sweeps: the
    same surfaces sampled by rays that fall elsewhere on them, to measure whether planes are found again.
    """
    cloud = np.asarray(points, dtype=np.float64)
    if cloud.ndim != 3 or cloud.shape[2] != 3:
        raise ValueError(f'points must be an organized (H, W, 3) array; got shape {cloud.shape}')
    height, width = cloud.shape[:2]
    projector = RangeImageProjector(cloud, origins)
    flat = cloud.reshape(-1, 3)
    moved = flat[np.isfinite(flat).all(axis=1)] @ np.asarray(rotation, float).T + np.asarray(translation, float)
    pixel = projector.grid_pixels(moved)
    moved, pixel = moved[pixel >= 0], pixel[pixel >= 0]
    starts = np.broadcast_to(np.zeros(3) if origins is None else np.asarray(origins, float), cloud.shape)
    starts = starts.reshape(-1, 3)[pixel]
    length = np.linalg.norm(moved - starts, axis=1)
    order = np.lexsort((length, pixel))  # by pixel, the nearest first
    pixel, moved, starts, length = pixel[order], moved[order], starts[order], length[order]
    nearest = np.ones(len(pixel), dtype=bool)
    nearest[1:] = pixel[1:] != pixel[:-1]
    kept, start, length = moved[nearest], starts[nearest], length[nearest]
    if range_sigma > 0.0:
        noise = np.random.default_rng(seed).normal(0.0, float(range_sigma), len(kept))
        kept = start + (kept - start) * ((length + noise) / length)[:, None]
    out = np.full((height * width, 3), np.nan)
    out[pixel[nearest]] = kept
    return out.reshape(height, width, 3)


@dataclass(frozen=True)
class PlaneMatch:
    """A plane of sweep A (>= the size limit) and its best match in sweep B.

    Attributes:
        label_a, label_b: labels in A and B (label_b 0: no B plane under A's projected points).
        points_a: pixels of A's plane. projected: distinct B pixels with a point that A's plane projects to.
        iou: ``|P & B_k| / |P | B_k|`` of the projected pixels P and B's plane k (0 without a match).
        angle_deg: angle between A's normal moved into B's frame and B's normal.
        offset_diff: ``|d'_A - d_B|`` (m) of A's moved plane and B's plane: their gap at B's sensor,
            which an angle between them times the distance to the planes dominates.
        gap_at_planes: the planes' gap where they are (m): the mean of the distance of A's moved
            centroid from B's plane and of B's centroid from A's moved plane (NaN without a match).
        mahalanobis2: Mahalanobis² of ``c'_A - c_B`` (closest points ``d n`` in B's frame) under
            ``J cov_A J^T + cov_B`` (J: :func:`closest_point_jacobian`); NaN without covariances.
        sigma_d_predicted: ``sqrt(n_B^T (J cov_A J^T + cov_B) n_B)`` (m), the predicted spread of the offset.
        found: ``angle_deg < 2``, ``offset_diff < 0.05`` and ``iou >= 0.7`` (the issue's targets).
        mahalanobis2_with_registration: the same with :func:`registration_covariance` added (NaN without an
            estimate of the registration error).
    """

    label_a: int
    label_b: int
    points_a: int
    projected: int
    iou: float
    angle_deg: float
    offset_diff: float
    mahalanobis2: float
    sigma_d_predicted: float
    found: bool
    mahalanobis2_with_registration: float = math.nan
    gap_at_planes: float = math.nan


#: Thresholds of a plane "found again" in the next sweep.
MAX_MATCH_ANGLE_DEG = 2.0
MAX_MATCH_OFFSET = 0.05
MIN_MATCH_IOU = 0.7


def match_planes(
    labels_a: np.ndarray,
    points_a: np.ndarray,
    normals_a: np.ndarray,
    offsets_a: np.ndarray,
    covariances_a: np.ndarray | None,
    labels_b: np.ndarray,
    projector_b: RangeImageProjector,
    normals_b: np.ndarray,
    offsets_b: np.ndarray,
    covariances_b: np.ndarray | None,
    rotation: np.ndarray,
    translation: np.ndarray,
    *,
    min_points: int = 1000,
    registration_sigma: tuple[float, float] | None = None,
) -> list[PlaneMatch]:
    """Match every plane of A with at least ``min_points`` pixels to a plane of B after the motion ``(R, t)``.

    Plane arrays are indexed by label - 1 (PlaneSet layout: label j is row j - 1). A's plane points are moved
    into B's frame and projected into B's range image; P is the set of distinct valid B pixels hit; the match
    is the B label (> 0) that holds most of P. Parts of A's plane that B does not see (no return, outside
    the grid) do not count against it; parts of B's plane that A's plane does not reach do.
    ``registration_sigma`` = (m, rad) per axis: an estimate of the registration error, added to the
    covariance by :func:`registration_covariance` for :attr:`PlaneMatch.mahalanobis2_with_registration`.
    """
    lab_a = np.asarray(labels_a)
    lab_b = np.asarray(labels_b).ravel()
    flat_a = np.asarray(points_a, float).reshape(-1, 3)
    rotation = np.asarray(rotation, float)
    translation = np.asarray(translation, float)
    sizes_b = np.bincount(lab_b[lab_b > 0], minlength=len(offsets_b) + 1)
    values, counts = np.unique(lab_a[lab_a > 0], return_counts=True)
    moved_normals, moved_offsets = transform_planes(normals_a, offsets_a, rotation, translation)
    matches = []
    for label, count in zip(values, counts, strict=True):
        if count < min_points:
            continue
        moved = flat_a[(lab_a == label).ravel()] @ rotation.T + translation
        pixels = np.unique(projector_b.project(moved))
        pixels = pixels[pixels >= 0]
        hit = lab_b[pixels]
        if not np.any(hit > 0):
            matches.append(
                PlaneMatch(int(label), 0, int(count), len(pixels), 0.0, math.nan, math.nan, math.nan, math.nan, False)
            )
            continue
        hit_values, hit_counts = np.unique(hit[hit > 0], return_counts=True)
        best = int(hit_values[np.argmax(hit_counts)])
        inter = int(hit_counts.max())
        iou = inter / (len(pixels) + int(sizes_b[best]) - inter)
        n_a, d_a = moved_normals[label - 1], moved_offsets[label - 1]
        n_b, d_b = np.asarray(normals_b[best - 1], float), float(offsets_b[best - 1])
        if n_a @ n_b < 0:  # the same plane seen from its other side: compare with a consistent sign
            n_a, d_a = -n_a, -d_a
        angle = math.degrees(math.acos(min(1.0, abs(float(n_a @ n_b)))))
        offset_diff = abs(d_a - d_b)
        centroid_a = moved.mean(axis=0)
        centroid_b = projector_b.points.reshape(-1, 3)[lab_b == best].mean(axis=0)
        gap = 0.5 * (abs(float(centroid_a @ n_b) - d_b) + abs(float(centroid_b @ n_a) - d_a))
        md2 = sigma_d = md2_registered = math.nan
        if covariances_a is not None and covariances_b is not None:
            jac = closest_point_jacobian(
                offsets_a[label - 1] * np.asarray(normals_a[label - 1], float), rotation, translation
            )
            cov = jac @ covariances_a[label - 1] @ jac.T + covariances_b[best - 1]
            delta = d_a * n_a - d_b * n_b
            md2 = mahalanobis_squared(delta, cov)
            sigma_d = math.sqrt(max(float(n_b @ cov @ n_b), 0.0)) if np.all(np.isfinite(cov)) else math.nan
            if registration_sigma is not None:
                md2_registered = mahalanobis_squared(
                    delta, cov + registration_covariance(n_b, d_b, *registration_sigma)
                )
        found = angle < MAX_MATCH_ANGLE_DEG and offset_diff < MAX_MATCH_OFFSET and iou >= MIN_MATCH_IOU
        matches.append(
            PlaneMatch(
                int(label),
                best,
                int(count),
                len(pixels),
                float(iou),
                angle,
                offset_diff,
                md2,
                sigma_d,
                bool(found),
                md2_registered,
                gap,
            )
        )
    return matches


def match_plane_sets(
    points_a: np.ndarray,
    planes_a,
    points_b: np.ndarray,
    origins_b: np.ndarray | None,
    planes_b,
    rotation: np.ndarray,
    translation: np.ndarray,
    **options,
) -> list[PlaneMatch]:
    """:func:`match_planes` of two sweeps' PlaneSets (``(H, W, 3)`` points; B's ray starts for its range image);
    ``options``: ``min_points``, ``registration_sigma``."""
    return match_planes(
        planes_a.labels,
        points_a,
        planes_a.normals,
        planes_a.offsets,
        planes_a.covariances,
        planes_b.labels,
        RangeImageProjector(points_b, origins_b),
        planes_b.normals,
        planes_b.offsets,
        planes_b.covariances,
        rotation,
        translation,
        **options,
    )


@dataclass(frozen=True)
class RepeatabilitySummary:
    """Summary of :func:`match_planes` over one sweep pair.

    Attributes:
        planes: planes of A with >= the size limit. found: those found again (:attr:`PlaneMatch.found`).
        found_share: ``found / planes`` (NaN without planes).
        median_iou: median IoU over all of A's large planes (0 for a plane without any B plane under it).
        pairs: planes with a B match. median_mahalanobis2: median over pairs with finite covariances.
        median_sigma_d_predicted, median_offset_diff: median predicted offset spread and observed ``|d'_A - d_B|``
            (m) over the pairs.
        median_angle_deg: median normal angle over the pairs.
        median_mahalanobis2_with_registration: the median with the registration error estimate added.
        median_gap_at_planes: median :attr:`PlaneMatch.gap_at_planes` (m) over the pairs.
        missed_iou, missed_angle, missed_offset: of the planes not found again, how many miss each
            criterion (IoU below MIN_MATCH_IOU, angle of MAX_MATCH_ANGLE_DEG or more, offset gap of
            MAX_MATCH_OFFSET or more; a plane may miss several; a plane without a match misses all three).
    """

    planes: int
    found: int
    found_share: float
    median_iou: float
    pairs: int
    median_mahalanobis2: float
    median_sigma_d_predicted: float
    median_offset_diff: float
    median_angle_deg: float
    median_mahalanobis2_with_registration: float = math.nan
    median_gap_at_planes: float = math.nan
    missed_iou: int = 0
    missed_angle: int = 0
    missed_offset: int = 0


def _median(values) -> float:
    array = np.asarray([v for v in values if math.isfinite(v)], float)
    return float(np.median(array)) if len(array) else math.nan


def summarize_matches(matches: list[PlaneMatch]) -> RepeatabilitySummary:
    """Share found again, median IoU and the covariance calibration of a list of matches."""
    paired = [m for m in matches if m.label_b > 0]
    found = sum(m.found for m in matches)
    missed = [m for m in matches if not m.found]
    return RepeatabilitySummary(
        planes=len(matches),
        found=found,
        found_share=found / len(matches) if matches else math.nan,
        median_iou=_median([m.iou for m in matches]),
        pairs=len(paired),
        median_mahalanobis2=_median([m.mahalanobis2 for m in paired]),
        median_sigma_d_predicted=_median([m.sigma_d_predicted for m in paired]),
        median_offset_diff=_median([m.offset_diff for m in paired]),
        median_angle_deg=_median([m.angle_deg for m in paired]),
        median_mahalanobis2_with_registration=_median([m.mahalanobis2_with_registration for m in paired]),
        median_gap_at_planes=_median([m.gap_at_planes for m in paired]),
        missed_iou=sum(not m.iou >= MIN_MATCH_IOU for m in missed),
        missed_angle=sum(not m.angle_deg < MAX_MATCH_ANGLE_DEG for m in missed),
        missed_offset=sum(not m.offset_diff < MAX_MATCH_OFFSET for m in missed),
    )


def motion_difference(
    rotation_a: np.ndarray, translation_a: np.ndarray, rotation_b: np.ndarray, translation_b: np.ndarray
) -> tuple[float, float]:
    """(angle in degrees, translation distance in m) between two rigid motions."""
    relative = np.asarray(rotation_a, float).T @ np.asarray(rotation_b, float)
    cos_angle = np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0)
    return math.degrees(math.acos(cos_angle)), float(np.linalg.norm(np.asarray(translation_a) - translation_b))


# ------------------------------------------------------------------------------------------ surface shape


@dataclass(frozen=True)
class SurfaceShape:
    """How far a set of points (metres, any frame) is from a plane, and how well a smooth bend explains them.

    Attributes:
        points: number of points.
        plane_rms: RMS distance (m) of the points from their least-squares plane.
        quadric_rms: RMS residual (m) of the least-squares quadric height field
            ``w = a + b u + c v + d u^2 + e u v + f v^2`` over that plane (u, v along the two largest axes of
            the points' scatter, w along its normal, origin at the centroid).
        radii: the quadric's principal radii of curvature (m) at the centroid, smaller first (1 / the
            eigenvalues' magnitudes of its Hessian; inf where it is flat).
    """

    points: int
    plane_rms: float
    quadric_rms: float
    radii: tuple[float, float]


def surface_shape(points: np.ndarray) -> SurfaceShape:
    """:class:`SurfaceShape` of ``(N, 3)`` points (N >= 6, not all on one line)."""
    cloud = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(cloud) < 6:
        raise ValueError(f'surface_shape needs at least 6 points; got {len(cloud)}')
    centred = cloud - cloud.mean(axis=0)
    _, _, axes = np.linalg.svd(centred, full_matrices=False)
    u, v, w = (centred @ axes.T).T
    design = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=1)
    coefficients, *_ = np.linalg.lstsq(design, w, rcond=None)
    d, e, f = coefficients[3:]
    curvatures = np.abs(np.linalg.eigvalsh(np.array([[2.0 * d, e], [e, 2.0 * f]])))
    radii = sorted(1.0 / c if c > 0.0 else math.inf for c in curvatures)
    return SurfaceShape(
        points=len(cloud),
        plane_rms=float(np.sqrt(np.mean(w * w))),
        quadric_rms=float(np.sqrt(np.mean((w - design @ coefficients) ** 2))),
        radii=(float(radii[0]), float(radii[1])),
    )


def touching_pairs(labels: np.ndarray, min_pairs: int = 1) -> dict[tuple[int, int], int]:
    """``{(a, b): n}`` with a < b: labels a, b > 0 of an ``(H, W)`` grid that are 4-neighbours in n pixel pairs
    (n >= min_pairs)."""
    grid = np.asarray(labels)
    left, right = grid[:, :-1].ravel(), grid[:, 1:].ravel()
    up, down = grid[:-1].ravel(), grid[1:].ravel()
    first = np.concatenate([left, up])
    second = np.concatenate([right, down])
    keep = (first > 0) & (second > 0) & (first != second)
    low = np.minimum(first[keep], second[keep])
    high = np.maximum(first[keep], second[keep])
    pairs, counts = np.unique(np.stack([low, high], axis=1), axis=0, return_counts=True)
    return {(int(a), int(b)): int(n) for (a, b), n in zip(pairs, counts, strict=True) if n >= min_pairs}


def smooth_surfaces(
    points: np.ndarray,
    labels: np.ndarray,
    *,
    min_points: int = 10000,
    max_quadric_rms: float = 0.01,
    min_touching: int = 50,
) -> list[tuple[list[int], SurfaceShape]]:
    """Groups of large planes that together are one smooth surface, each with its :class:`SurfaceShape`.

    The planes of at least ``min_points`` points of an organized scan (``points`` (H, W, 3) metres,
    ``labels`` (H, W), 0 = no plane) start as groups of one; two groups are joined while their planes
    touch in at least ``min_touching`` pixel pairs and their union's ``quadric_rms`` is at most
    ``max_quadric_rms`` (m), the cheapest union first. A curved surface cut into flat planes (a cylinder
    into strips) comes out as one group whose ``plane_rms`` is far above its ``quadric_rms``; planes that
    meet at an edge (a wall and the floor) join only where the fold is shallow enough for a quadric to
    follow it within ``max_quadric_rms``. Largest group first.
    """
    cloud = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    flat = np.asarray(labels).ravel()
    values, counts = np.unique(flat[flat > 0], return_counts=True)
    large = [int(p) for p, n in zip(values, counts, strict=True) if n >= min_points]
    touching = {
        pair for pair, n in touching_pairs(labels, min_touching).items() if pair[0] in large and pair[1] in large
    }
    groups = [[p] for p in large]

    def shape(members):
        return surface_shape(cloud[np.isin(flat, members)])

    while True:
        best = None
        for i, a in enumerate(groups):
            for j in range(i + 1, len(groups)):
                b = groups[j]
                if not any((min(p, q), max(p, q)) in touching for p in a for q in b):
                    continue
                rms = shape(a + b).quadric_rms
                if rms <= max_quadric_rms and (best is None or rms < best[0]):
                    best = (rms, i, j)
        if best is None:
            break
        _, i, j = best
        groups[i] = sorted(groups[i] + groups.pop(j))
    result = [(members, shape(members)) for members in groups]
    return sorted(result, key=lambda item: -item[1].points)
