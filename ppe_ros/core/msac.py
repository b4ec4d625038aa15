"""The PPE paper's baseline: sequential MSAC plane detection (the reference's ``extrplnmsac.m``).

Repeat until at most ``min_remaining_fraction`` of all pixels (no-returns included, as in the
reference) remain unassigned: detect one plane among the remaining points with MSAC (random
3-point hypotheses scored by the truncated quadratic loss ``sum min(d^2, distance^2)`` of the
orthogonal point-plane distances d), give all its inliers (``|d| <= distance``) a new label and
remove them. There is no connectivity test and no minimum plane size, as in the reference; the
planes are numbered 1, 2, ... in detection order.

MSAC details (MATLAB ``pcfitplane`` defaults): at most ``max_trials`` non-degenerate hypotheses per
plane, adaptive stop once ``log(1 - confidence) / log(1 - w^3)`` trials were run for the best inlier
ratio w so far. Hypotheses are scored on a random subset of at most ``max_scored_points`` of the
remaining points (exact MSAC when fewer remain); the inliers of the winner are then taken from all
remaining points. Deterministic for a given ``seed``. Pure numpy/numba; float64 throughout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from ppe_ros.core.scan import as_points_array

DEFAULT_DISTANCE = 0.034
"""Inlier distance (m) tuned by the reference on SynPEB (``distopt``)."""

DEFAULT_MIN_REMAINING_FRACTION = 0.03
"""Stop once this fraction of the pixels is left (``percopt`` tuned by the reference on SynPEB)."""

DEFAULT_MAX_TRIALS = 1000
DEFAULT_CONFIDENCE = 0.99
DEFAULT_MAX_SCORED_POINTS = 20000

_MAX_DEGENERATE_FACTOR = 10  # give up after this many times max_trials degenerate samples in a row
_DEGENERATE_SINE = 1e-9  # samples whose two spanning vectors have a smaller sine are collinear


@dataclass(frozen=True)
class MsacPlanes:
    """Planes found by sequential MSAC.

    Attributes:
        labels: ``(H, W)`` int32; 0 = no plane, planes numbered ``1..J`` in detection order.
        normals: ``(J, 3)`` unit normals (input frame), oriented so that ``offsets >= 0``.
        offsets: ``(J,)`` d (m) with ``normals[j] . x = offsets[j]`` on plane j + 1.
        inlier_counts: ``(J,)`` number of pixels given to each plane.
        trials: ``(J,)`` number of hypotheses scored for each plane.
        seconds: wall time of the detection (s).
    """

    labels: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray
    inlier_counts: np.ndarray
    trials: np.ndarray
    seconds: float = 0.0

    @property
    def num_planes(self) -> int:
        """Number of planes J."""
        return len(self.offsets)


@njit(cache=True, nogil=True)
def _plane_through(p0x, p0y, p0z, p1x, p1y, p1z, p2x, p2y, p2z):
    """Unit normal and offset of the plane through three points; a zero normal if collinear."""
    ax, ay, az = p1x - p0x, p1y - p0y, p1z - p0z
    bx, by, bz = p2x - p0x, p2y - p0y, p2z - p0z
    nx = ay * bz - az * by
    ny = az * bx - ax * bz
    nz = ax * by - ay * bx
    length = math.sqrt(nx * nx + ny * ny + nz * nz)
    scale = math.sqrt(ax * ax + ay * ay + az * az) * math.sqrt(bx * bx + by * by + bz * bz)
    if not (length > _DEGENERATE_SINE * scale) or scale == 0.0:
        return 0.0, 0.0, 0.0, 0.0
    nx /= length
    ny /= length
    nz /= length
    return nx, ny, nz, nx * p0x + ny * p0y + nz * p0z


@njit(cache=True, nogil=True)
def _msac_kernel(xyz, valid, distance, stop_count, max_trials, confidence, max_scored, seed):
    """Sequential MSAC over the valid rows of ``xyz`` (N, 3); returns per-point labels and planes."""
    np.random.seed(seed)  # noqa: NPY002 (numba's per-thread generator; no Generator objects in kernels)
    n_points = xyz.shape[0]
    labels = np.zeros(n_points, np.int32)
    remaining = np.flatnonzero(valid)
    n_rem = remaining.shape[0]
    max_planes = n_rem // 3 + 1
    normals = np.zeros((max_planes, 3))
    offsets = np.zeros(max_planes)
    counts = np.zeros(max_planes, np.int64)
    trials_used = np.zeros(max_planes, np.int64)
    scored = np.empty(max_scored, np.int64)
    shuffle = np.empty(n_rem, np.int64)
    threshold2 = distance * distance
    log_failure = math.log(1.0 - confidence)
    n_planes = 0
    while n_rem > stop_count and n_rem >= 3:
        # the scoring subset: a random sample without replacement (partial Fisher-Yates)
        m = n_rem if n_rem <= max_scored else max_scored
        if m < n_rem:
            shuffle[:n_rem] = remaining[:n_rem]
            for i in range(m):
                j = i + np.random.randint(0, n_rem - i)  # noqa: NPY002
                shuffle[i], shuffle[j] = shuffle[j], shuffle[i]
                scored[i] = shuffle[i]
        else:
            scored[:m] = remaining[:m]
        best_score = np.inf
        bnx = bny = bnz = bd = 0.0
        required = max_trials
        trials = 0
        degenerate = 0
        while trials < required:
            i0 = remaining[np.random.randint(0, n_rem)]  # noqa: NPY002
            i1 = remaining[np.random.randint(0, n_rem)]  # noqa: NPY002
            i2 = remaining[np.random.randint(0, n_rem)]  # noqa: NPY002
            nx, ny, nz, d = _plane_through(
                xyz[i0, 0],
                xyz[i0, 1],
                xyz[i0, 2],
                xyz[i1, 0],
                xyz[i1, 1],
                xyz[i1, 2],
                xyz[i2, 0],
                xyz[i2, 1],
                xyz[i2, 2],
            )
            if nx == 0.0 and ny == 0.0 and nz == 0.0:
                degenerate += 1
                if degenerate > _MAX_DEGENERATE_FACTOR * max_trials:
                    break
                continue
            trials += 1
            score = 0.0
            inliers = 0
            for s in range(m):
                k = scored[s]
                dist = nx * xyz[k, 0] + ny * xyz[k, 1] + nz * xyz[k, 2] - d
                dist2 = dist * dist
                if dist2 <= threshold2:
                    score += dist2
                    inliers += 1
                else:
                    score += threshold2
            if score < best_score:
                best_score = score
                bnx, bny, bnz, bd = nx, ny, nz, d
                ratio = inliers / m
                if ratio >= 1.0:
                    required = trials
                elif ratio > 0.0:
                    needed = log_failure / math.log(1.0 - ratio * ratio * ratio)
                    if needed < required:
                        required = max(math.ceil(needed), 1)
        if best_score == np.inf:
            break
        if bd < 0.0:
            bnx, bny, bnz, bd = -bnx, -bny, -bnz, -bd
        label = n_planes + 1
        kept = 0
        taken = 0
        for s in range(n_rem):
            k = remaining[s]
            dist = bnx * xyz[k, 0] + bny * xyz[k, 1] + bnz * xyz[k, 2] - bd
            if abs(dist) <= distance:
                labels[k] = label
                taken += 1
            else:
                remaining[kept] = k
                kept += 1
        n_rem = kept
        normals[n_planes, 0] = bnx
        normals[n_planes, 1] = bny
        normals[n_planes, 2] = bnz
        offsets[n_planes] = bd
        counts[n_planes] = taken
        trials_used[n_planes] = trials
        n_planes += 1
        if taken == 0:  # cannot happen (the sample points are inliers); guards against an endless loop
            break
    return labels, normals[:n_planes], offsets[:n_planes], counts[:n_planes], trials_used[:n_planes]


def extract_planes_msac(
    points: np.ndarray,
    *,
    distance: float = DEFAULT_DISTANCE,
    min_remaining_fraction: float = DEFAULT_MIN_REMAINING_FRACTION,
    max_trials: int = DEFAULT_MAX_TRIALS,
    confidence: float = DEFAULT_CONFIDENCE,
    max_scored_points: int = DEFAULT_MAX_SCORED_POINTS,
    seed: int = 0,
) -> MsacPlanes:
    """Detect planes one after another with MSAC until few points are left (the paper's baseline).

    Args:
        points: organized ``(H, W, 3)`` endpoints (m, any frame); NaN = no return.
        distance: inlier distance (m) of the point-plane distance; also the MSAC loss truncation.
        min_remaining_fraction: stop once at most this fraction of the ``H * W`` pixels (no-returns
            included, as in the reference) is unassigned; in [0, 1).
        max_trials: at most this many non-degenerate hypotheses per plane.
        confidence: desired probability of drawing one all-inlier sample (adaptive stop), in (0, 1).
        max_scored_points: hypotheses are scored on a random subset of this many remaining points.
        seed: non-negative integer seed of the random sampling.

    Returns:
        The planes and their labels (:class:`MsacPlanes`).

    Raises:
        ValueError: bad shapes or parameter values.
    """
    import time

    cloud = as_points_array(points)
    if not (math.isfinite(distance) and distance > 0.0):
        raise ValueError(f'distance must be a positive finite length in metres; got {distance!r}')
    if not (0.0 <= min_remaining_fraction < 1.0):
        raise ValueError(f'min_remaining_fraction must be in [0, 1); got {min_remaining_fraction!r}')
    if isinstance(max_trials, bool) or int(max_trials) != max_trials or max_trials < 1:
        raise ValueError(f'max_trials must be a positive integer; got {max_trials!r}')
    if not (0.0 < confidence < 1.0):
        raise ValueError(f'confidence must be in (0, 1); got {confidence!r}')
    if isinstance(max_scored_points, bool) or int(max_scored_points) != max_scored_points or max_scored_points < 3:
        raise ValueError(f'max_scored_points must be an integer >= 3; got {max_scored_points!r}')
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f'seed must be a non-negative integer; got {seed!r}')
    height, width, _ = cloud.shape
    xyz = np.ascontiguousarray(cloud.reshape(-1, 3))
    valid = np.isfinite(xyz).all(axis=1)
    stop_count = max(min_remaining_fraction * xyz.shape[0], 2.0)
    start = time.perf_counter()
    labels, normals, offsets, counts, trials = _msac_kernel(
        xyz,
        valid,
        float(distance),
        float(stop_count),
        int(max_trials),
        float(confidence),
        int(max_scored_points),
        int(seed) % (2**32),
    )
    seconds = time.perf_counter() - start
    return MsacPlanes(
        labels=labels.reshape(height, width),
        normals=normals,
        offsets=offsets,
        inlier_counts=counts,
        trials=trials,
        seconds=seconds,
    )
