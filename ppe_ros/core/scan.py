"""The ray model of an organized scan: ray starts s_k, unit directions v_k and lengths r_k.

A scan is an organized ``(H, W, 3)`` array of measured endpoints (metres, NaN = no return) plus
the start point of every ray: ``None`` (all rays start at the coordinate origin), a ``(3,)``
point, or an ``(H, W, 3)`` array (per-ray starts, e.g. Ouster beam origins). Internally the
extractor works in a frame translated by the mean ray start (``center``) so that no plane seen by
the sensor passes through the internal origin, which the ``w = n / d`` plane parameterisation needs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

#: Shortest ray (m) the extractor uses: a shorter one (a point on or next to its ray start) is a no-return.
MIN_RANGE = 1e-3
#: Longest ray (m) the extractor uses: a longer one (garbage such as a misread cloud) is a no-return.
MAX_RANGE = 1e5


@dataclass(frozen=True)
class RayScan:
    """Flattened rays of an organized scan, row-major (pixel id = row * width + col).

    Attributes:
        height, width: grid size (rows, columns).
        endpoints: ``(H*W, 3)`` measured endpoints in the internal frame (input frame minus
            ``center``), metres; rows of invalid rays are 0.
        directions: ``(H*W, 3)`` unit ray directions (0 for invalid rays).
        ranges: ``(H*W,)`` measured ray lengths ``r_k = |p_k - s_k|`` in metres (NaN if invalid).
        valid: ``(H*W,)`` bool: finite endpoint and start, and ``MIN_RANGE <= r_k <= MAX_RANGE``.
        center: ``(3,)`` the internal frame origin in input coordinates (mean valid ray start).
    """

    height: int
    width: int
    endpoints: np.ndarray
    directions: np.ndarray
    ranges: np.ndarray
    valid: np.ndarray
    center: np.ndarray

    @property
    def size(self) -> int:
        """Number of pixels H*W."""
        return self.height * self.width

    def ray_starts(self) -> np.ndarray:
        """``(H*W, 3)`` ray starts in the internal frame."""
        starts = self.endpoints - self.ranges[:, None] * self.directions
        starts[~self.valid] = 0.0
        return starts


def as_points_array(points: np.ndarray, *, name: str = 'points') -> np.ndarray:
    """Validate an organized ``(H, W, 3)`` cloud and return it as C-contiguous float64."""
    array = np.asarray(points)
    if array.ndim != 3 or array.shape[2] != 3:
        raise ValueError(f'{name} must be an organized (H, W, 3) array of x, y, z in metres; got shape {array.shape}')
    if array.shape[0] < 1 or array.shape[1] < 1:
        raise ValueError(f'{name} is empty: shape {array.shape}')
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise ValueError(f'{name} must be numeric (real floats or integers); got dtype {array.dtype}')
    return np.ascontiguousarray(array, dtype=np.float64)


def make_ray_scan(points: np.ndarray, origins: np.ndarray | None = None) -> RayScan:
    """Build the ray model of an organized scan.

    Args:
        points: ``(H, W, 3)`` measured endpoints in metres, NaN = no return.
        origins: ray starts in the same frame: None (coordinate origin), ``(3,)`` or ``(H, W, 3)``.

    Raises:
        ValueError: wrong shapes or dtypes.
    """
    pts = as_points_array(points)
    height, width, _ = pts.shape
    flat_points = pts.reshape(-1, 3)
    if origins is None:
        flat_starts = np.zeros((1, 3))  # one start for every ray
    else:
        starts = np.asarray(origins, dtype=np.float64)
        if starts.shape == (3,):
            if not np.all(np.isfinite(starts)):
                raise ValueError(f'origins must be finite; got {starts}')
            flat_starts = starts.reshape(1, 3)
        elif starts.shape == pts.shape:
            flat_starts = np.ascontiguousarray(starts).reshape(-1, 3)
        else:
            raise ValueError(
                f'origins must be None, a (3,) ray start or an (H, W, 3) array like points {pts.shape}; '
                f'got shape {starts.shape}'
            )
    ranges = np.empty(len(flat_points))
    valid = np.empty(len(flat_points), np.bool_)
    _ranges(flat_points, flat_starts, ranges, valid)
    n_valid = int(np.count_nonzero(valid))
    if n_valid == 0 or origins is None:
        center = np.zeros(3)
    else:
        center = _valid_mean(flat_starts, valid, n_valid)
    endpoints = np.empty_like(flat_points)
    directions = np.empty_like(flat_points)
    _rays(flat_points, flat_starts, ranges, valid, center, endpoints, directions)
    return RayScan(
        height=height,
        width=width,
        endpoints=endpoints,
        directions=directions,
        ranges=ranges,
        valid=valid,
        center=center,
    )


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _ranges(points, starts, ranges, valid):
    """Ray lengths |p - s| (m; NaN when invalid) and validity (MIN_RANGE <= r <= MAX_RANGE) of (n, 3) endpoints.

    ``starts`` is ``(n, 3)`` or ``(1, 3)`` (one start for every ray).
    """
    step = 0 if starts.shape[0] == 1 else 1  # start row of ray k: k * step
    for k in nb.prange(points.shape[0]):
        s = k * step
        d0 = points[k, 0] - starts[s, 0]
        d1 = points[k, 1] - starts[s, 1]
        d2 = points[k, 2] - starts[s, 2]
        r = np.sqrt((d0 * d0 + d2 * d2) + d1 * d1)  # numpy's einsum order: equal to it bit for bit
        ok = r >= MIN_RANGE and r <= MAX_RANGE  # False for NaN
        valid[k] = ok
        ranges[k] = r if ok else np.nan


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _valid_mean(starts, valid, n_valid):
    """The mean start of the valid rays, bit for bit ``starts[valid].mean(axis=0)`` of (n, 3) starts (numpy
    adds the rows of an (n, 3) array in order, then divides by the count), without copying the valid
    rows (numpy's reduction over the rows costs a loop call per row: 5 ms for an OS-1-128 sweep).
    ``starts`` is ``(n, 3)`` or ``(1, 3)`` (one start for every ray: its value added once per valid ray)."""
    step = 0 if starts.shape[0] == 1 else 1  # start row of ray k: k * step
    total = np.zeros(3)
    for k in range(valid.shape[0]):
        if valid[k]:
            for c in range(3):
                total[c] += starts[k * step, c]
    for c in range(3):
        total[c] /= n_valid
    return total


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _rays(points, starts, ranges, valid, center, endpoints, directions):
    """Endpoints relative to ``center`` and unit directions (p - s) / r; rows of invalid rays 0."""
    step = 0 if starts.shape[0] == 1 else 1  # start row of ray k: k * step
    for k in nb.prange(points.shape[0]):
        s = k * step
        for c in range(3):
            if valid[k]:
                endpoints[k, c] = points[k, c] - center[c]
                directions[k, c] = (points[k, c] - starts[s, c]) / ranges[k]
            else:
                endpoints[k, c] = 0.0
                directions[k, c] = 0.0


#: ray_spacing_deg samples about this many neighbour pairs in each direction at most.
SPACING_SAMPLES = 8192
#: ray_spacing_deg needs at least this many pairs of valid neighbours in each direction.
MIN_SPACING_PAIRS = 100


def ray_spacing_deg(points: np.ndarray, origins: np.ndarray | None = None) -> tuple[float, float]:
    """The angular spacing (degrees) of an organized scan's rays: the median angle between the ray
    directions (endpoint minus start) of 4-neighbouring valid rays along a row and along a column.

    Args:
        points: organized ``(H, W, 3)`` endpoints (any frame, metres), NaN = no return.
        origins: ray starts: None (the frame origin), ``(3,)`` or ``(H, W, 3)``.

    Returns:
        ``(along rows, along columns)``: for a spinning lidar's sweep (rows = beams) the azimuth step and
        the beam spacing, for a depth image the angle of a pixel. The median is taken over the pairs at
        every s-th row and column (s chosen for at most about SPACING_SAMPLES pairs a direction): well
        under a millisecond for a 128 x 1024 sweep. NaN in a direction with fewer than
        MIN_SPACING_PAIRS pairs of valid rays (finite, non-zero).
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 3 or points.shape[-1] != 3:
        raise ValueError(f'points must be an organized (H, W, 3) array; got shape {points.shape}')
    height, width = points.shape[:2]
    starts = np.zeros(3) if origins is None else np.asarray(origins, dtype=np.float64)
    if starts.shape not in ((3,), points.shape):
        raise ValueError(f'origins must be None, (3,) or {points.shape}; got shape {starts.shape}')
    step = max(1, int(np.ceil(np.sqrt(height * width / SPACING_SAMPLES))))
    along_rows, along_columns = _neighbour_angles(
        np.ascontiguousarray(points).reshape(-1, 3),
        np.ascontiguousarray(starts).reshape(-1, 3),
        height,
        width,
        step,
    )
    return _median_deg(along_rows), _median_deg(along_columns)


def _median_deg(angles: np.ndarray) -> float:
    """Median (degrees) of the finite angles (radians; NaN = no pair), NaN with fewer than MIN_SPACING_PAIRS."""
    finite = angles[np.isfinite(angles)]
    return float(np.degrees(np.median(finite))) if len(finite) >= MIN_SPACING_PAIRS else float('nan')


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _ray_angle(points, starts, a, b):
    """Angle (radians) between the rays of pixels a and b (atan2 of |cross| and dot); NaN if either is
    not finite or of zero length."""
    sa = 0 if starts.shape[0] == 1 else a
    sb = 0 if starts.shape[0] == 1 else b
    a0, a1, a2 = points[a, 0] - starts[sa, 0], points[a, 1] - starts[sa, 1], points[a, 2] - starts[sa, 2]
    b0, b1, b2 = points[b, 0] - starts[sb, 0], points[b, 1] - starts[sb, 1], points[b, 2] - starts[sb, 2]
    c0, c1, c2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
    length_a = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    length_b = np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
    if not (length_a > 0.0 and length_b > 0.0 and np.isfinite(length_a) and np.isfinite(length_b)):
        return np.nan
    return np.arctan2(np.sqrt(c0 * c0 + c1 * c1 + c2 * c2), a0 * b0 + a1 * b1 + a2 * b2)


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _neighbour_angles(points, starts, height, width, step):
    """Angles (radians; NaN: not a valid pair) between pixel (i, j) and its right and lower neighbours,
    for i and j every step-th row and column of an (H * W, 3) grid; starts (1, 3) or (H * W, 3)."""
    rows = (height - 2) // step + 1 if height > 1 else 0
    columns = (width - 2) // step + 1 if width > 1 else 0
    along_rows = np.full(rows * columns, np.nan)
    along_columns = np.full(rows * columns, np.nan)
    n = 0
    for i in range(0, height - 1, step):
        for j in range(0, width - 1, step):
            k = i * width + j
            along_rows[n] = _ray_angle(points, starts, k, k + 1)
            along_columns[n] = _ray_angle(points, starts, k, k + width)
            n += 1
    return along_rows, along_columns
