"""Unorganized lidar clouds -> an organized range image, and planes back to every input point.

Pure numpy/numba; no ROS import. PPE needs a grid (its 4-neighbourhood and tetromino seeds); a
spinning lidar's unorganized cloud (Hesai, Velodyne with ``organize_cloud: false``, KITTI ``.bin``
files) is put on one like this (all angles from each point's own ray, in the input frame, which
must be the sensor frame with z along the spin axis):

* **row** = the beam. With ``rings`` (a driver's ``ring`` field), one row per ring value, ordered
  from the highest to the lowest beam (ring numbers rising or falling with the rings' mean elevation). Without
  rings, the beams are found in the points' elevation angles: a laser's beam origin sits off the
  sensor origin (Ouster: 36 mm up and 15-28 mm out), which smears one beam's elevation seen from
  the origin by more than the gap to the next beam at short range; the vertical and radial offset
  (h, n) that make the elevation histogram sharpest are fitted first (a grid search), then every
  run of occupied 0.01 deg histogram bins is a beam and the bin edges are the midpoints between
  neighbouring beams' mean elevations. Uneven beam spacing (HDL-64E: 1/3 deg above, 1/2 deg
  below -8.33 deg) needs nothing special.
* **column** = the azimuth bin. Bins per revolution: given, or 2 pi over the median azimuth step
  between consecutive returns of one beam. Each beam's bins are shifted by its own phase (the
  circular mean of its points' azimuths modulo the step), so every return sits at a bin centre.
  The grid is cut (its seam, where planes are split) in the middle of the widest run of empty
  azimuth bins, if there is one (a field of view under 360 deg, the vehicle behind the sensor);
  a full circle is cut at ``azimuth_start`` (default 180 deg: behind the sensor, where Ouster's
  and Velodyne's organized clouds start). Empty columns at both ends are dropped.
* **cell**: the nearest return wins (ties: the first point); the image holds the winner itself, so
  the rays' directions come from the points and the projection changes the neighbourhood, not the
  geometry.
* **labels back** (:meth:`RangeImageProjection.point_labels`): a point that won its cell gets the
  cell's plane; a point that lost its cell to a nearer return gets that plane if it lies on it
  (perpendicular distance at most the tolerance), else 0. Invalid points get 0.

A non-repetitive scanner (Livox) has no beams: ``rows='angular_grid'`` bins elevation and azimuth
on a fixed grid of ``angular_resolution`` degrees over the field of view the points cover.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from ppe_ros.core.scan import MAX_RANGE, MIN_RANGE

#: How rows are made: from rings, from elevation bins, on a fixed angular grid, or chosen (auto:
#: rings if given, else elevation bins).
ROW_METHODS = ('auto', 'rings', 'elevation', 'angular_grid')
#: Width (deg) of the elevation histogram bins beams are found in.
ELEVATION_BIN_DEG = 0.01
#: Azimuth (deg) where a full circle is cut by default: behind the sensor (x forward).
DEFAULT_AZIMUTH_START_DEG = 180.0
#: Beams (the fullest) whose returns give the azimuth step.
STEP_ROWS = 8
#: Elevation runs closer than this fraction of the median spacing of the runs are one beam.
MERGE_FRACTION = 0.3
#: Default cell size (deg) of the fixed angular grid (Livox).
DEFAULT_ANGULAR_RESOLUTION_DEG = 0.8
#: Lost points within this distance (m) of their cell's plane join it when no sensor tolerance is given.
DEFAULT_LOST_POINT_TOLERANCE = 0.05
#: Points drawn (deterministically) to fit the beam-origin offset.
_OFFSET_SAMPLE = 4096
#: The offset grid search: (half range, step) of the vertical h and the radial n, coarse then fine (m);
#: real beams start up to ~0.2 m above or below the sensor origin (HDL-64E) but < 0.1 m out (Ouster: 14-28 mm).
_OFFSET_COARSE = ((0.3, 0.01), (0.1, 0.01))
_OFFSET_FINE = ((0.01, 0.001), (0.01, 0.001))
#: Largest grid the projection builds (cells), against a degenerate azimuth step.
MAX_CELLS = 50_000_000


@dataclass(frozen=True)
class RangeImageProjection:
    """Where every input point went in the range image.

    Attributes:
        rows, columns: the image size.
        point_cells: ``(N,)`` int64 cell ``row * columns + column`` of each input point; -1 for a
            point without a valid return (non-finite, or a ray shorter than MIN_RANGE).
        cell_points: ``(rows * columns,)`` int64 index of the input point that holds each cell
            (the nearest return), -1 for an empty cell.
        method: ``'rings'``, ``'elevation'`` or ``'angular_grid'``.
        azimuth_bins: azimuth bins per revolution (the angular grid: per 360 deg).
        row_elevations: ``(rows,)`` mean elevation (rad) of the points holding a row's cells (NaN if none).
        beam_origin_offset: ``(h, n)`` the vertical and radial beam-origin offset (m) fitted for the
            elevation bins ((0, 0) otherwise).
    """

    rows: int
    columns: int
    point_cells: np.ndarray
    cell_points: np.ndarray
    method: str
    azimuth_bins: int
    row_elevations: np.ndarray
    beam_origin_offset: tuple[float, float] = (0.0, 0.0)

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, columns)``."""
        return (self.rows, self.columns)

    @property
    def lost_points(self) -> int:
        """Valid points that lost their cell to a nearer return."""
        return int(np.count_nonzero(self.point_cells >= 0)) - int(np.count_nonzero(self.cell_points >= 0))

    def image(self, values: np.ndarray, fill: float = np.nan) -> np.ndarray:
        """``(rows, columns, k)`` float64 image of per-point ``values`` ``(N, k)`` (empty cells: ``fill``)."""
        values = np.asarray(values, dtype=np.float64)
        if values.ndim != 2 or len(values) != len(self.point_cells):
            raise ValueError(f'values must be (N, k) with N = {len(self.point_cells)}; got shape {values.shape}')
        out = np.empty((self.rows * self.columns, values.shape[1]))
        _gather_cells(np.ascontiguousarray(values), self.cell_points, float(fill), out)
        return out.reshape(self.rows, self.columns, values.shape[1])

    def point_labels(
        self, cell_labels: np.ndarray, points: np.ndarray, normals: np.ndarray, offsets: np.ndarray, tolerance: float
    ) -> np.ndarray:
        """``(N,)`` int32 plane label of every input point (0 = no plane), in the input order.

        Args:
            cell_labels: ``(rows, columns)`` labels of the image (0 = no plane, planes 1..J).
            points: ``(N, 3)`` the input points (m, input frame).
            normals, offsets: ``(J, 3)``, ``(J,)`` the planes ``n . x = d`` (input frame, m).
            tolerance: largest perpendicular distance (m) of a point that lost its cell from its
                cell's plane to get that plane.
        """
        labels = np.ascontiguousarray(cell_labels, dtype=np.int64).reshape(-1)
        if labels.size != self.rows * self.columns:
            raise ValueError(f'cell_labels must be {self.shape}; got {np.shape(cell_labels)}')
        if not (np.isfinite(tolerance) and tolerance >= 0):
            raise ValueError(f'tolerance must be a finite length >= 0 m; got {tolerance!r}')
        return _point_labels_kernel(
            self.point_cells,
            self.cell_points,
            labels,
            _as_points(points),
            np.ascontiguousarray(normals, dtype=np.float64).reshape(-1, 3),
            np.ascontiguousarray(offsets, dtype=np.float64).reshape(-1),
            float(tolerance),
        )


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _gather_cells(values, cell_points, fill, out):
    """out[c] = values[cell_points[c]], or ``fill`` where the cell is empty (cell_points[c] < 0), in parallel."""
    for c in nb.prange(cell_points.shape[0]):
        k = cell_points[c]
        for j in range(values.shape[1]):
            out[c, j] = values[k, j] if k >= 0 else fill


def _as_points(points: np.ndarray, name: str = 'points') -> np.ndarray:
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f'{name} must be an unorganized (N, 3) array of x, y, z in metres; got shape {array.shape}')
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise ValueError(f'{name} must be numeric; got dtype {array.dtype}')
    return np.ascontiguousarray(array, dtype=np.float64)


def _rays(points: np.ndarray, origins: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ray vectors p - s ``(N, 3)`` (0 where invalid), validity (finite, MIN_RANGE <= |p - s| <= MAX_RANGE),
    lengths |p - s| (m; 0 where invalid) and horizontal lengths hypot(x, y) of the rays (m)."""
    if origins is None:
        starts = np.zeros((1, 3))
    else:
        starts = np.asarray(origins, dtype=np.float64)
        if starts.shape not in ((3,), points.shape):
            raise ValueError(f'origins must be None, (3,) or (N, 3) like points {points.shape}; got {starts.shape}')
        starts = np.ascontiguousarray(starts).reshape(-1, 3)
    n = len(points)
    rays, valid, ranges, rho = np.empty((n, 3)), np.empty(n, np.bool_), np.empty(n), np.empty(n)
    _ray_geometry(points, starts, rays, valid, ranges, rho)
    return rays, valid, ranges, rho


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _ray_geometry(points, starts, rays, valid, ranges, rho):
    """rays, valid, ranges and rho of :func:`_rays` in one parallel pass; starts ``(1, 3)`` (one for every
    point) or ``(N, 3)``. Bit for bit numpy's ``p - s``, ``sqrt(einsum('ij,ij->i'))`` (which adds x^2 + z^2,
    then y^2) and ``hypot``."""
    step = 0 if starts.shape[0] == 1 else 1
    for k in nb.prange(points.shape[0]):
        s = k * step
        x = points[k, 0] - starts[s, 0]
        y = points[k, 1] - starts[s, 1]
        z = points[k, 2] - starts[s, 2]
        length = np.sqrt((x * x + z * z) + y * y)
        ok = length >= MIN_RANGE and length <= MAX_RANGE  # False for NaN
        valid[k] = ok
        if not ok:
            x = y = z = 0.0
        rays[k, 0] = x
        rays[k, 1] = y
        rays[k, 2] = z
        ranges[k] = length if ok else 0.0
        rho[k] = math.hypot(x, y)


def project_points(
    points: np.ndarray,
    rings: np.ndarray | None = None,
    *,
    origins: np.ndarray | None = None,
    rows: str = 'auto',
    azimuth_bins: int | None = None,
    angular_resolution: float = DEFAULT_ANGULAR_RESOLUTION_DEG,
    azimuth_start: float = DEFAULT_AZIMUTH_START_DEG,
) -> RangeImageProjection:
    """Put an unorganized cloud on a range image (see the module docstring for how).

    Args:
        points: ``(N, 3)`` endpoints in metres in the sensor frame (z = spin axis), NaN = no return.
        rings: ``(N,)`` integer beam (ring) number of each point, or None.
        origins: ray starts: None (the origin), ``(3,)`` or ``(N, 3)`` (m, the frame of ``points``).
        rows: ``'auto'`` (rings if given, else elevation bins), ``'rings'``, ``'elevation'`` or
            ``'angular_grid'``.
        azimuth_bins: azimuth bins per revolution; None = estimated from the points.
        angular_resolution: cell size (deg) of the angular grid.
        azimuth_start: azimuth (deg, counter-clockwise from x) where a full circle is cut.

    Raises:
        ValueError: bad shapes, values or settings (the message says which).
    """
    pts = _as_points(points)
    method = _row_method(rows, rings)
    ring_values = None if method != 'rings' else _as_rings(rings, len(pts))
    if azimuth_bins is not None and (int(azimuth_bins) != azimuth_bins or not 1 <= azimuth_bins <= 1_000_000):
        raise ValueError(f'azimuth_bins must be an integer in [1, 1000000] or None; got {azimuth_bins!r}')
    rays, valid, ranges, rho = _rays(pts, origins)
    offset = (0.0, 0.0)
    if method == 'angular_grid':
        if not (np.isfinite(angular_resolution) and 0.01 <= angular_resolution <= 10.0):
            raise ValueError(f'angular_resolution must be in [0.01, 10] deg; got {angular_resolution!r}')
        elevation = np.arctan2(rays[:, 2], rho)
        row_of, n_rows = _grid_rows(elevation, valid, math.radians(angular_resolution))
        bins = round(360.0 / angular_resolution)
    else:
        if method == 'rings':
            elevation = np.arctan2(rays[:, 2], rho)
            row_of, n_rows = _ring_rows(ring_values, elevation, valid)
        else:
            offset = fit_beam_origin_offset(rays, valid)
            elevation = np.arctan2(rays[:, 2] - offset[0], rho - offset[1])  # seen from the beam origin
            row_of, n_rows = _elevation_rows(elevation, valid)
        bins = None if azimuth_bins is None else int(azimuth_bins)
    azimuth = np.arctan2(rays[:, 1], rays[:, 0])
    if not np.isfinite(azimuth_start):
        raise ValueError(f'azimuth_start must be a finite angle in degrees; got {azimuth_start!r}')
    column_of, bins, step, centre = _azimuth_columns(azimuth, row_of, n_rows, bins, phased=method != 'angular_grid')
    start = math.radians(float(np.mod(azimuth_start + 180.0, 360.0)))
    start_bin = math.ceil((start - centre) / step - 1e-9) % bins  # the first bin centred at or after it
    column_of, n_columns = _crop_columns(column_of, row_of >= 0, bins, start_bin)
    if n_rows * n_columns > MAX_CELLS:
        raise ValueError(
            f'the range image would have {n_rows} x {n_columns} cells (more than {MAX_CELLS}); '
            'give azimuth_bins or a coarser angular_resolution'
        )
    cells = np.where(row_of >= 0, row_of * n_columns + column_of, -1).astype(np.int64)
    winners = _claim_cells(cells, ranges, n_rows * n_columns)
    held = winners[winners >= 0]
    row_elevations = _group_means(row_of[held], elevation[held], n_rows)
    return RangeImageProjection(
        rows=n_rows,
        columns=n_columns,
        point_cells=cells,
        cell_points=winners,
        method=method,
        azimuth_bins=int(bins),
        row_elevations=row_elevations,
        beam_origin_offset=(float(offset[0]), float(offset[1])),
    )


def _row_method(rows: str, rings: np.ndarray | None) -> str:
    if rows not in ROW_METHODS:
        raise ValueError(f'rows must be one of {", ".join(map(repr, ROW_METHODS))}; got {rows!r}')
    if rows == 'auto':
        return 'rings' if rings is not None else 'elevation'
    if rows == 'rings' and rings is None:
        raise ValueError("rows='rings' needs rings (the ring number of every point)")
    return rows


def _as_rings(rings: np.ndarray, n: int) -> np.ndarray:
    values = np.asarray(rings)
    if values.shape != (n,):
        raise ValueError(f'rings must be (N,) with N = {n} like points; got shape {values.shape}')
    if values.dtype.kind == 'f':
        finite = np.isfinite(values)
        if not np.all(values[finite] == np.round(values[finite])):
            raise ValueError('rings must be whole numbers (the beam number of each point)')
        values = np.where(finite, values, -1)
    elif values.dtype.kind not in 'iub':
        raise ValueError(f'rings must be integers; got dtype {values.dtype}')
    values = values.astype(np.int64)
    if values.size and (values.min() < -1 or values.max() > 65535):
        raise ValueError(f'rings must lie in 0 .. 65535 (a beam number); found {values.min()} .. {values.max()}')
    return values


def _ring_rows(rings: np.ndarray, elevation: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, int]:
    """Row of each point from its ring: every ring value from the smallest to the largest is a row (an
    absent one is an empty row), in ring order, top beam first (drivers number rings by elevation;
    whether upwards or downwards is read from the rings' mean elevations)."""
    row_of = np.full(len(rings), -1, np.int64)
    counts, sums = _ring_sums(rings, elevation, valid)
    present = np.flatnonzero(counts)
    if len(present) == 0:
        return row_of, 0
    means = (sums / np.maximum(counts, 1))[present]
    low, high = int(present[0]), int(present[-1])
    with np.errstate(invalid='ignore', divide='ignore'):  # rings of one elevation: no correlation (NaN)
        upwards = len(present) > 1 and np.corrcoef(present.astype(np.float64), means)[0, 1] > 0
    _rows_of_rings(rings, valid, low, high, upwards, row_of)
    return row_of, high - low + 1


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _ring_sums(rings, elevation, valid):
    """Per ring value 0 .. max, the count and the sum of the elevations (in the points' order) of the valid
    points with a ring (>= 0): np.bincount's counts and weighted sums of those points."""
    top = -1
    for k in range(rings.shape[0]):
        if valid[k] and rings[k] > top:
            top = rings[k]
    counts = np.zeros(top + 1, np.int64)
    sums = np.zeros(top + 1)
    for k in range(rings.shape[0]):
        if valid[k] and rings[k] >= 0:
            counts[rings[k]] += 1
            sums[rings[k]] += elevation[k]
    return counts, sums


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _rows_of_rings(rings, valid, low, high, upwards, row_of):
    """row_of[k] = the row of ring rings[k] (rings low .. high, the top beam's row 0) for valid points with a ring."""
    for k in nb.prange(rings.shape[0]):
        if valid[k] and rings[k] >= 0:
            row_of[k] = (high - rings[k]) if upwards else (rings[k] - low)


def _group_means(group: np.ndarray, values: np.ndarray, n_groups: int) -> np.ndarray:
    """Mean of ``values`` per group ``0 .. n_groups - 1`` (NaN for an empty group)."""
    counts = np.bincount(group, minlength=n_groups)
    sums = np.bincount(group, values, minlength=n_groups)
    with np.errstate(invalid='ignore', divide='ignore'):
        return np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)


def fit_beam_origin_offset(rays: np.ndarray, valid: np.ndarray) -> tuple[float, float]:
    """The vertical and radial beam-origin offset ``(h, n)`` (m) that make the beams' elevations sharpest.

    A grid search (h in +-0.3 m, then n in +-0.1 m by 10 mm on up to 1024 points; then both again
    +-10 mm by 1 mm around the best on up to 4096; 20 mm steps miss OS-0-128's offsets) of the sum
    of squared counts of a 0.02 deg elevation histogram of evenly drawn points.
    """
    index = np.flatnonzero(valid)
    if index.size < 16:
        return (0.0, 0.0)
    sample = index[np.linspace(0, index.size - 1, min(index.size, _OFFSET_SAMPLE)).astype(np.int64)]
    rho = np.ascontiguousarray(np.hypot(rays[sample, 0], rays[sample, 1]))
    z = np.ascontiguousarray(rays[sample, 2])
    width = math.radians(2 * ELEVATION_BIN_DEG)
    h = n = 0.0
    for ((h_half, h_step), (n_half, n_step)), every in ((_OFFSET_COARSE, 4), (_OFFSET_FINE, 1)):
        r, height = rho[::every], z[::every]  # the coarse search on a quarter of the points
        grid = np.arange(-h_half, h_half + h_step / 2, h_step)
        h = h + grid[int(np.argmax(_sharpness_of_offsets(r, height, h + grid, np.full(len(grid), n), width)))]
        grid = np.arange(-n_half, n_half + n_step / 2, n_step)
        n = n + grid[int(np.argmax(_sharpness_of_offsets(r, height, np.full(len(grid), h), n + grid, width)))]
    return (float(h), float(n))


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _sharpness_of_offsets(rho, z, hs, ns, width):
    """:func:`_sharpness` at each offset (hs[i], ns[i]) (m), in parallel."""
    out = np.empty(len(hs))
    for i in nb.prange(len(hs)):
        out[i] = _sharpness(rho, z, hs[i], ns[i], width)
    return out


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _sharpness(rho, z, h, n, width):
    """Sum of squared counts of the histogram (bins ``width`` rad from -pi/2) of elevations atan2(z - h,
    rho - n); a point at rho < n (within the offset of the sensor's axis: its elevation beyond +-pi/2)
    is not counted."""
    counts = np.zeros(int(math.pi / width) + 2, np.int64)
    for k in range(rho.shape[0]):
        e = math.atan2(z[k] - h, rho[k] - n)
        if -math.pi / 2 <= e <= math.pi / 2:
            counts[int((e + math.pi / 2) / width)] += 1
    total = 0.0
    for c in counts:
        total += float(c) * float(c)
    return total


def _elevation_rows(elevation: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, int]:
    """Row of each point from elevation bins: a beam per run of occupied 0.01 deg histogram bins;
    row 0 is the highest beam."""
    row_of = np.full(len(elevation), -1, np.int64)
    if not valid.any():
        return row_of, 0
    centres = beam_elevations(elevation[valid])
    edges = (centres[1:] + centres[:-1]) / 2  # descending
    _rows_below_edges(-edges, elevation, valid, row_of)
    return row_of, len(centres)


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _rows_below_edges(negated_edges, elevation, valid, row_of):
    """row_of[k] = np.searchsorted(negated_edges, -elevation[k], side='left') for the valid points (the
    number of edges above the point's elevation; negated_edges ascending, NaN-free), in parallel. A table
    over 8 buckets per edge gives each point a start next to its answer, from which it steps to it."""
    n = negated_edges.shape[0]
    low = negated_edges[0] if n > 0 else 0.0
    buckets = 8 * n
    width = (negated_edges[n - 1] - low) / buckets if n > 1 else 0.0  # 0: every point starts at bucket 0
    start = np.empty(buckets + 1, np.int64)  # start[b]: about the answer at low + b * width
    i = 0
    for bucket in range(buckets + 1):
        while i < n and negated_edges[i] < low + bucket * width:
            i += 1
        start[bucket] = i
    for k in nb.prange(elevation.shape[0]):
        if valid[k]:
            value = -elevation[k]
            bucket = (value - low) / width if width > 0.0 else 0.0
            at = start[min(max(int(bucket), 0), buckets)] if bucket == bucket else 0
            while at > 0 and negated_edges[at - 1] >= value:  # exact whatever the start
                at -= 1
            while at < n and negated_edges[at] < value:
                at += 1
            row_of[k] = at


def beam_elevations(elevation: np.ndarray) -> np.ndarray:
    """Mean elevation (rad) of every beam found in ``elevation`` (finite, rad), highest first.

    A beam is a run of 0.01 deg histogram bins holding a point each, separated from the next by at
    least one empty bin; runs with fewer than 2 % of the median run's points (stray returns between
    beams) are not beams, and two runs closer than 0.3 times the median spacing are one beam (their
    count-weighted mean elevation).
    """
    width = math.radians(ELEVATION_BIN_DEG)
    low = float(elevation.min())
    index = np.floor((elevation - low) / width).astype(np.int64)
    counts = np.bincount(index)
    occupied = counts > 0
    starts = np.flatnonzero(occupied & ~np.r_[False, occupied[:-1]])
    run_counts = np.add.reduceat(counts, starts)
    keep = run_counts >= max(1.0, 0.02 * float(np.median(run_counts)))
    run_of_bin = np.searchsorted(starts, np.arange(len(counts)), side='right') - 1
    means = _group_means(run_of_bin[index], elevation, len(starts))
    order = np.argsort(-means[keep], kind='stable')
    centres, weights = means[keep][order], run_counts[keep][order].astype(np.float64)
    # one beam split by a hole in its histogram: runs much closer than the beams' spacing are merged
    while len(centres) > 2:
        gaps = centres[:-1] - centres[1:]
        k = int(np.argmin(gaps))
        if gaps[k] >= MERGE_FRACTION * float(np.median(gaps)):
            break
        total = weights[k] + weights[k + 1]
        centres[k] = (centres[k] * weights[k] + centres[k + 1] * weights[k + 1]) / total
        weights[k] = total
        centres, weights = np.delete(centres, k + 1), np.delete(weights, k + 1)
    return centres


def _grid_rows(elevation: np.ndarray, valid: np.ndarray, step: float) -> tuple[np.ndarray, int]:
    """Rows of a fixed angular grid of ``step`` rad from the highest point down."""
    row_of = np.full(len(elevation), -1, np.int64)
    if not valid.any():
        return row_of, 0
    top = float(elevation[valid].max())
    row_of[valid] = np.floor((top - elevation[valid]) / step).astype(np.int64)
    return row_of, int(row_of.max()) + 1


def _azimuth_columns(
    azimuth: np.ndarray, row_of: np.ndarray, n_rows: int, bins: int | None, *, phased: bool
) -> tuple[np.ndarray, int, float, float]:
    """Azimuth bin (0 .. bins - 1, periodic) of every point, the bins per revolution, the step (rad)
    and the common offset (rad, in [0, step)) of the bins' centres from -pi + k step.

    Without ``bins`` the step is estimated (:func:`estimate_azimuth_step`); a revolution then holds
    ``ceil(2 pi / step)`` bins, the last one narrower unless 2 pi is a whole number of steps.
    """
    ok = row_of >= 0
    column_of = np.full(len(azimuth), -1, np.int64)
    if not ok.any():
        return column_of, bins or 1, 2 * math.pi / (bins or 1), 0.0
    if bins is None:
        step = estimate_azimuth_step(azimuth[ok], row_of[ok])
        bins = min(math.ceil(2 * math.pi / step - 1e-9), 1_000_000)
    else:
        step = 2 * math.pi / bins
    if phased:
        sin, cos = _phase_sums(azimuth, row_of, n_rows, step)
        # each beam's phase as a deviation from the common one, so that beams whose returns sit on a
        # bin edge all fall on the same side of it
        common = math.atan2(float(sin.sum()), float(cos.sum())) % (2 * math.pi)
        beam_phase = common + np.angle(np.exp(1j * (np.arctan2(sin, cos) - common)))
        _phased_columns(azimuth, row_of, beam_phase / (2 * math.pi) * step, step, bins, column_of)
        return column_of, bins, step, common / (2 * math.pi) * step
    shifted = azimuth[ok] + math.pi
    column_of[ok] = np.mod(np.floor(shifted / step).astype(np.int64), bins)
    return column_of, bins, step, step / 2


def _phase_sums(azimuth: np.ndarray, row_of: np.ndarray, n_rows: int, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Per row, the sums of sin and cos of 2 pi (azimuth + pi) / step over its points (row_of >= 0), each
    in the points' order (the sines and cosines in parallel, then the sums)."""
    sines, cosines = np.empty(len(azimuth)), np.empty(len(azimuth))
    _phases(azimuth, row_of, 2 * math.pi / step, sines, cosines)
    return _row_sums(row_of, n_rows, sines, cosines)


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _phases(azimuth, row_of, scale, sines, cosines):
    """sin and cos of scale (azimuth + pi) of the points with a row (row_of >= 0)."""
    for k in nb.prange(azimuth.shape[0]):
        if row_of[k] >= 0:
            phase = scale * (azimuth[k] + math.pi)
            sines[k] = math.sin(phase)
            cosines[k] = math.cos(phase)


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _row_sums(row_of, n_rows, sines, cosines):
    """Per row, the sums of sines and cosines over its points (row_of >= 0), in the points' order."""
    sin = np.zeros(n_rows)
    cos = np.zeros(n_rows)
    for k in range(row_of.shape[0]):
        r = row_of[k]
        if r >= 0:
            sin[r] += sines[k]
            cos[r] += cosines[k]
    return sin, cos


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _phased_columns(azimuth, row_of, row_offset, step, bins, column_of):
    """column_of[k] = rint((azimuth + pi - row_offset[row]) / step) mod bins for points with a row."""
    for k in range(azimuth.shape[0]):
        r = row_of[k]
        if r >= 0:
            c = np.int64(np.rint((azimuth[k] + math.pi - row_offset[r]) / step)) % bins
            column_of[k] = c


def estimate_azimuth_step(azimuth: np.ndarray, row_of: np.ndarray) -> float:
    """Azimuth step (rad) between consecutive returns of one beam.

    The mean of the steps within 30 % of their median (no-returns make steps of several bins; the median
    itself when none is) in the STEP_ROWS beams with the most returns;
    snapped to 2 pi / round(2 pi / step) when a revolution is within 0.05 steps of a whole number.

    Args:
        azimuth: ``(n,)`` azimuths (rad) of valid points; row_of: ``(n,)`` their beams (rows).
    """
    counts = np.bincount(row_of)
    fullest = np.argsort(-counts, kind='stable')[:STEP_ROWS]  # a few beams tell the step
    steps = _beam_steps(azimuth, row_of, np.sort(fullest[counts[fullest] > 1]), counts)
    if steps.size == 0:
        return 2 * math.pi
    median = float(np.median(steps))
    near = steps[np.abs(steps - median) <= 0.3 * median]
    step = float(np.mean(near)) if near.size else median  # a beam or two of a few points: no typical step
    step = max(step, 2 * math.pi / 1_000_000)
    per_revolution = 2 * math.pi / step
    if abs(per_revolution - round(per_revolution)) <= 0.05:  # a twentieth of a step in a revolution
        return 2 * math.pi / max(round(per_revolution), 1)
    return step


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _beam_steps(azimuth, row_of, rows, counts):
    """The steps of more than 1e-7 rad between consecutive azimuths of each beam in ``rows`` (ascending; counts:
    the points per row), beam after beam, each beam's in ascending azimuth: the order in which np.diff of the
    points sorted by (row, azimuth) has them."""
    slot = np.full(len(counts), -1, np.int64)
    start = np.zeros(len(rows) + 1, np.int64)
    for t in range(len(rows)):
        slot[rows[t]] = t
        start[t + 1] = start[t] + counts[rows[t]]
    values = np.empty(start[-1])
    fill = start[:-1].copy()
    for k in range(len(azimuth)):
        t = slot[row_of[k]]
        if t >= 0:
            values[fill[t]] = azimuth[k]
            fill[t] += 1
    steps = np.empty(start[-1])
    n = 0
    for t in range(len(rows)):
        beam = np.sort(values[start[t] : start[t + 1]])
        for i in range(1, len(beam)):
            step = beam[i] - beam[i - 1]
            if step > 1e-7:
                steps[n] = step
                n += 1
    return steps[:n].copy()


def _crop_columns(column_of: np.ndarray, ok: np.ndarray, bins: int, start_bin: int) -> tuple[np.ndarray, int]:
    """Columns rotated to start at the seam (the middle of the widest run of empty bins, else
    ``start_bin``), empty columns at both ends dropped."""
    if not ok.any():
        return column_of, 0
    empty = np.bincount(column_of[ok], minlength=bins) == 0
    seam = start_bin
    if empty.any() and not empty.all():
        # runs of empty bins on the circle: rotate so that bin 0 is occupied, then find the runs
        first_full = int(np.argmax(~empty))
        ring = np.roll(empty, -first_full)
        edges = np.diff(np.r_[0, ring.astype(np.int8), 0])
        starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
        widest = int(np.argmax(ends - starts))  # ties: the first
        seam = (first_full + (int(starts[widest]) + int(ends[widest])) // 2) % bins
    occupied = np.flatnonzero(~np.roll(empty, -seam))
    first, last = int(occupied[0]), int(occupied[-1])
    return np.where(ok, np.mod(column_of - (seam + first), bins), -1), last - first + 1


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _claim_cells(cells, ranges, n_cells):
    """Index of the nearest point of every cell (ties: the first), -1 for an empty cell."""
    winners = np.full(n_cells, -1, np.int64)
    for i in range(cells.shape[0]):
        c = cells[i]
        if c < 0:
            continue
        w = winners[c]
        if w < 0 or ranges[i] < ranges[w]:
            winners[c] = i
    return winners


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _point_labels_kernel(cells, winners, cell_labels, points, normals, offsets, tolerance):
    """Label of each point: its cell's if it holds the cell or lies within ``tolerance`` of that plane."""
    out = np.zeros(cells.shape[0], np.int32)
    for i in range(cells.shape[0]):
        c = cells[i]
        if c < 0:
            continue
        label = cell_labels[c]
        if label <= 0:
            continue
        if winners[c] == i:
            out[i] = label
            continue
        j = label - 1
        distance = abs(
            normals[j, 0] * points[i, 0] + normals[j, 1] * points[i, 1] + normals[j, 2] * points[i, 2] - offsets[j]
        )
        if distance <= tolerance:
            out[i] = label
    return out


def extract_planes_unorganized(
    points: np.ndarray,
    rings: np.ndarray | None = None,
    *,
    origins: np.ndarray | None = None,
    rows: str = 'auto',
    azimuth_bins: int | None = None,
    angular_resolution: float = DEFAULT_ANGULAR_RESOLUTION_DEG,
    azimuth_start: float = DEFAULT_AZIMUTH_START_DEG,
    lost_point_tolerance: float | None = None,
    **extract_options,
):
    """Extract planes from an unorganized lidar cloud: project it, run PPE on the image, label every point.

    Args:
        points: ``(N, 3)`` endpoints in metres in the sensor frame (z = spin axis), NaN = no return.
        rings: ``(N,)`` beam number of each point (a driver's ``ring`` field) or None.
        origins: ray starts: None, ``(3,)`` or ``(N, 3)`` (m).
        rows, azimuth_bins, angular_resolution, azimuth_start: the projection (:func:`project_points`).
        lost_point_tolerance: a point that lost its cell to a nearer return gets the cell's plane
            when within this distance (m) of it; None = the sensor profile's surface_tolerance
            (the ``sensor``/``surface_tolerance`` options), else DEFAULT_LOST_POINT_TOLERANCE.
        extract_options: :func:`ppe_ros.core.extraction.extract_planes`'s keyword arguments.

    Returns:
        What ``extract_planes`` returns, with ``labels`` of shape ``(N,)`` in the input order; the
        planes' fits, ``point_counts`` and ``rmse`` are those of the image's cells (one return per
        cell); ``meta['projection']`` is the :class:`RangeImageProjection` and ``meta['cell_labels']``
        the image's ``(rows, columns)`` labels.
    """
    from ppe_ros.core.extraction import PROFILE_DEFAULT, extract_planes
    from ppe_ros.core.sensor import sensor_profile

    pts = _as_points(points)
    projection = project_points(
        pts,
        rings,
        origins=origins,
        rows=rows,
        azimuth_bins=azimuth_bins,
        angular_resolution=angular_resolution,
        azimuth_start=azimuth_start,
    )
    tolerance = lost_point_tolerance
    if tolerance is None:
        tolerance = extract_options.get('surface_tolerance', PROFILE_DEFAULT)
        if tolerance is PROFILE_DEFAULT or tolerance is None:
            sensor = extract_options.get('sensor')
            tolerance = None if sensor is None else sensor_profile(sensor).surface_tolerance
        if tolerance is None:
            tolerance = DEFAULT_LOST_POINT_TOLERANCE
    image_origins = origins
    if origins is not None and np.shape(origins) == pts.shape:
        image_origins = image_or_empty(projection, np.asarray(origins, dtype=np.float64), fill=0.0)
    result = extract_planes(image_or_empty(projection, pts), origins=image_origins, **extract_options)
    cuts = result if isinstance(result, list) else [result]
    mapped = [planes_for_points(projection, cut, pts, float(tolerance)) for cut in cuts]
    return mapped if isinstance(result, list) else mapped[0]


def image_or_empty(projection: RangeImageProjection, values: np.ndarray, fill: float = np.nan) -> np.ndarray:
    """The range image ``(rows, columns, k)`` of per-point ``values`` ``(N, k)`` (the points, or their ray
    starts), empty cells ``fill``; one ``fill`` cell if no point is valid (a no-return)."""
    if projection.rows == 0 or projection.columns == 0:
        return np.full((1, 1, np.shape(values)[1]), fill)
    return projection.image(values, fill=fill)


def planes_for_points(projection: RangeImageProjection, planes, points: np.ndarray, tolerance: float):
    """The PlaneSet of the image with ``labels`` ``(N,)`` for the input points.

    See :func:`extract_planes_unorganized` for the labels and ``meta``.
    """
    if projection.rows == 0 or projection.columns == 0:
        point_labels = np.zeros(len(points), np.int32)
    else:
        point_labels = projection.point_labels(planes.labels, points, planes.normals, planes.offsets, tolerance)
    meta = {**planes.meta, 'projection': projection, 'cell_labels': planes.labels}
    return dataclasses.replace(planes, labels=point_labels, meta=meta)


def matched_label_agreement(first: np.ndarray, second: np.ndarray) -> float:
    """Fraction of points with the same label in two segmentations after matching their labels.

    Labels are matched one-to-one greedily by overlap (largest first; 0 = no plane matches only 0);
    a point agrees when both labels are 0 or its two labels are a matched pair.
    """
    a = np.asarray(first, dtype=np.int64).reshape(-1)
    b = np.asarray(second, dtype=np.int64).reshape(-1)
    if a.shape != b.shape:
        raise ValueError(f'the segmentations have different sizes: {a.size} and {b.size}')
    if a.size == 0:
        return 1.0
    pairs, counts = np.unique(np.stack([a, b], axis=1), axis=0, return_counts=True)
    agree = int(counts[(pairs[:, 0] == 0) & (pairs[:, 1] == 0)].sum())
    used_a: set[int] = set()
    used_b: set[int] = set()
    for k in np.lexsort((pairs[:, 1], pairs[:, 0], -counts)):
        x, y = int(pairs[k, 0]), int(pairs[k, 1])
        if x == 0 or y == 0 or x in used_a or y in used_b:
            continue
        used_a.add(x)
        used_b.add(y)
        agree += int(counts[k])
    return agree / a.size
