"""The spread of a plane's fit over parts of it: delete-one-quadrant and delete-one-row (beam) jackknives.

A plane fitted to a surface that is not exactly flat, or to a sensor's errors that are correlated
over metres, moves when a different part of the surface is seen: the next sweep's extent differs
by a few metres, an occluder hides a corner. The fit's covariance (independent residuals) does not
see that. The jackknife measures it from the plane's own points: split the plane at the median of
its long in-plane axis u and each half at the median of the other axis v, refit the plane without
each quadrant in turn, and take the spread of the four refits,
Cov = (K - 1) / K sum_k (theta_-k - mean theta)(theta_-k - mean theta)^T with K = 4.
theta = (a, b, c) of the local plane w = a + b u + c v, with u, v, w the coordinates of a point
relative to the centroid along the two in-plane axes and the normal (metres, the scan's frame);
a is the offset at the centroid (m), b and c the tilts about the two in-plane axes (rad, to first
order). ppe_ros.core.surfaces.systematic_covariances maps them to the closest point d n.

The row jackknife (:func:`jackknife_of_members` with ``row_width``) leaves out one grid row at a time
instead: the rows of a spinning lidar's sweep are its beams, and each beam's range bias and angle
error is one error shared by all the beam's points on the plane, so a plane seen by few beams moves
with them. Its groups are the rows holding at least MIN_QUADRANT_POINTS of the plane's points (points
of sparser rows stay in every refit); K is their number (at least MIN_ROWS, else the spread is 0).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ppe_ros.core.chunks import group_chunks, plane_members

#: Quadrants of the jackknife (2 x 2 blocks in the plane).
NUM_QUADRANTS = 4
#: A quadrant needs this many points, else the plane's jackknife is 0 (a tiny plane's spread is noise).
MIN_QUADRANT_POINTS = 3
#: The row jackknife needs a plane's points on at least this many rows (of MIN_QUADRANT_POINTS points each).
MIN_ROWS = 3


def quadrant_jackknife(
    points: np.ndarray, plane_index: np.ndarray, centroids: np.ndarray, axes: np.ndarray
) -> np.ndarray:
    """``(J, 3, 3)`` jackknife covariance of each plane's local parameters (a m, b rad, c rad).

    Args:
        points: ``(N, 3)`` points (m) of all planes, in the scan's frame.
        plane_index: ``(N,)`` plane index 0..J-1 of each point.
        centroids: ``(J, 3)`` each plane's centroid (m).
        axes: ``(J, 3, 3)``: ``axes[j, 0]`` the long in-plane axis u, ``axes[j, 1]`` the short
            in-plane axis v, ``axes[j, 2]`` the normal (unit vectors).
    Planes with a quadrant of fewer than MIN_QUADRANT_POINTS points get 0.
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    plane_index = np.ascontiguousarray(plane_index, dtype=np.int64)
    centroids = np.ascontiguousarray(centroids, dtype=np.float64)
    axes = np.ascontiguousarray(axes, dtype=np.float64)
    n_planes = len(centroids)
    if points.ndim != 2 or points.shape[1] != 3 or plane_index.shape != (len(points),):
        raise ValueError('points must be (N, 3) and plane_index (N,)')
    if centroids.shape != (n_planes, 3) or axes.shape != (n_planes, 3, 3):
        raise ValueError('centroids must be (J, 3) and axes (J, 3, 3)')
    if len(plane_index) and (plane_index.min() < 0 or plane_index.max() >= n_planes):
        raise ValueError(f'plane_index must be in 0..{n_planes - 1}')
    members, starts = plane_members(plane_index + 1, n_planes)  # labels 1..J: every point is on a plane
    return jackknife_of_members(points, np.zeros(3), members, starts, centroids, axes)


def jackknife_of_members(
    endpoints: np.ndarray,
    shift: np.ndarray,
    members: np.ndarray,
    starts: np.ndarray,
    centroids: np.ndarray,
    axes: np.ndarray,
    *,
    row_width: int | None = None,
) -> np.ndarray:
    """:func:`quadrant_jackknife` of plane j's points ``endpoints[members[starts[j]:starts[j + 1]]] + shift``
    (m; ``shift`` (3,): a scan's center), with ``centroids`` and ``axes`` as there; members as
    chunks.plane_members gives them (no checks). With ``row_width``, the delete-one-row jackknife instead
    (module docstring): members are pixel ids of a grid that many columns wide (row = id // row_width), and a
    plane on fewer than MIN_ROWS rows of MIN_QUADRANT_POINTS points gets 0."""
    return _jackknife_kernel(
        np.ascontiguousarray(endpoints, dtype=np.float64),
        np.ascontiguousarray(shift, dtype=np.float64),
        0 if row_width is None else int(row_width),
        members,
        starts,
        group_chunks(np.diff(starts)),
        np.ascontiguousarray(centroids, dtype=np.float64),
        np.ascontiguousarray(axes, dtype=np.float64),
    )


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _jackknife_kernel(points, shift, row_width, order, starts, bounds, centroids, axes):
    """jackknife_of_members of the planes' members (points + shift): over quadrants (row_width 0) or over the
    rows of a grid row_width columns wide; the planes' runs ``bounds`` (chunks.group_chunks) in parallel."""
    out = np.zeros((len(centroids), 3, 3))
    for c in nb.prange(len(bounds) - 1):
        for j in range(bounds[c], bounds[c + 1]):
            members = order[starts[j] : starts[j + 1]]
            if row_width == 0:
                if len(members) >= NUM_QUADRANTS * MIN_QUADRANT_POINTS:
                    local = _local_coordinates(points, shift, members, centroids[j], axes[j])
                    out[j] = _plane_jackknife(local, _quadrants(local), NUM_QUADRANTS)
            elif len(members) >= MIN_ROWS * MIN_QUADRANT_POINTS:
                group, n_groups = _row_groups(members, row_width)
                if n_groups >= MIN_ROWS:
                    local = _local_coordinates(points, shift, members, centroids[j], axes[j])
                    out[j] = _plane_jackknife(local, group, n_groups)
    return out


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _local_coordinates(points, shift, members, centroid, axes):
    """(n, 3) coordinates u, v, w of the members (points + shift) relative to the centroid along axes."""
    local = np.empty((len(members), 3))
    for i in range(len(members)):
        for a in range(3):
            local[i, a] = (
                (points[members[i], 0] + shift[0] - centroid[0]) * axes[a, 0]
                + (points[members[i], 1] + shift[1] - centroid[1]) * axes[a, 1]
                + (points[members[i], 2] + shift[2] - centroid[2]) * axes[a, 2]
            )
    return local


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _quadrants(local):
    """Quadrant 0..3 of each point: 2 * (u > median u) + (v > median v of its half)."""
    u_high = local[:, 0] > np.median(local[:, 0])
    quadrant = np.empty(len(local), dtype=np.int64)
    for half in range(2):
        in_half = np.flatnonzero(u_high == (half == 1))
        v_median = np.median(local[in_half, 1]) if len(in_half) else 0.0
        for i in in_half:
            quadrant[i] = 2 * half + (1 if local[i, 1] > v_median else 0)
    return quadrant


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _plane_jackknife(local, group, n_groups):
    """Delete-one-group jackknife covariance (3, 3) of the least-squares (a, b, c) of w = a + b u + c v;
    group: 0..n_groups - 1 of each point, -1 = in every refit. Zero if a group has fewer than
    MIN_QUADRANT_POINTS points, or a refit is singular (what is left has no extent in u or v)."""
    normal = np.zeros((n_groups + 1, 3, 3))  # per group (the last: -1): sum of x x^T, x = (1, u, v)
    rhs = np.zeros((n_groups + 1, 3))  # per group: sum of x w
    counts = np.zeros(n_groups + 1, dtype=np.int64)
    x = np.empty(3)
    for i in range(len(local)):
        g = group[i] if group[i] >= 0 else n_groups
        x[0], x[1], x[2] = 1.0, local[i, 0], local[i, 1]
        counts[g] += 1
        for a in range(3):
            rhs[g, a] += x[a] * local[i, 2]
            for b in range(3):
                normal[g, a, b] += x[a] * x[b]
    if counts[:n_groups].min() < MIN_QUADRANT_POINTS:
        return np.zeros((3, 3))
    total_normal, total_rhs = normal.sum(axis=0), rhs.sum(axis=0)
    thetas = np.empty((n_groups, 3))
    for q in range(n_groups):
        thetas[q] = _solve3(total_normal - normal[q], total_rhs - rhs[q])
    if not np.all(np.isfinite(thetas)):
        return np.zeros((3, 3))
    spread = thetas - thetas.sum(axis=0) / n_groups
    out = np.zeros((3, 3))
    for q in range(n_groups):
        for a in range(3):
            for b in range(3):
                out[a, b] += spread[q, a] * spread[q, b]
    return (n_groups - 1) / n_groups * out


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _solve3(m, r):
    """x with m x = r for a symmetric positive definite 3 x 3 m (Cramer's rule); NaN when m is singular
    (its determinant below 1e-12 of its diagonal's product)."""
    c00 = m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]
    c01 = m[1, 2] * m[2, 0] - m[1, 0] * m[2, 2]
    c02 = m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]
    det = m[0, 0] * c00 + m[0, 1] * c01 + m[0, 2] * c02
    if not abs(det) > 1e-12 * abs(m[0, 0] * m[1, 1] * m[2, 2]):  # no extent in u or v left: no solution
        return np.full(3, np.nan)
    c11 = m[0, 0] * m[2, 2] - m[0, 2] * m[2, 0]
    c12 = m[0, 2] * m[1, 0] - m[0, 0] * m[1, 2]
    c22 = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    x = np.empty(3)
    x[0] = (c00 * r[0] + c01 * r[1] + c02 * r[2]) / det
    x[1] = (c01 * r[0] + c11 * r[1] + c12 * r[2]) / det
    x[2] = (c02 * r[0] + c12 * r[1] + c22 * r[2]) / det
    return x


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _row_groups(members, width):
    """Group 0..K-1 of each member pixel: its row's rank among the rows holding at least MIN_QUADRANT_POINTS
    members (-1: a sparser row), and K."""
    rows = members // width
    low, high = rows.min(), rows.max()
    counts = np.zeros(high - low + 1, dtype=np.int64)
    for r in rows:
        counts[r - low] += 1
    rank = np.full(high - low + 1, -1, dtype=np.int64)
    n_groups = 0
    for r in range(high - low + 1):
        if counts[r] >= MIN_QUADRANT_POINTS:
            rank[r] = n_groups
            n_groups += 1
    group = np.empty(len(members), dtype=np.int64)
    for i in range(len(members)):
        group[i] = rank[rows[i] - low]
    return group, n_groups
