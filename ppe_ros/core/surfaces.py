"""Whole surfaces: a snapshot of the greedy consolidated into one plane per physical surface.

After the greedy (ppe_ros.core.extraction) with a sensor profile, the pieces of one surface are
merged (ppe_ros.core.consolidation), planes that are not planar within the sensor's tolerance are
reported as no plane, and each plane's covariance gets the share of the errors that do not average
out (systematic_covariances). Frames: the scan's; lengths in metres.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import numba as nb
import numpy as np

from ppe_ros.core.boundary_join import BOUNDARY_GAP, join_at_boundaries
from ppe_ros.core.chunks import group_chunks, plane_members
from ppe_ros.core.consolidation import _reusable, columns_wrap, consolidated_surfaces, rows_wrap
from ppe_ros.core.fitting import fit_pixel_groups_with_members
from ppe_ros.core.planes import PlaneSet
from ppe_ros.core.quadrants import jackknife_of_members
from ppe_ros.core.scan import RayScan
from ppe_ros.core.sensor import SensorProfile

if TYPE_CHECKING:
    from ppe_ros.core.extraction import PlaneHierarchy


def whole_surfaces(
    hierarchy: PlaneHierarchy,
    cut: dict,
    profile: SensorProfile | None,
    min_plane_points: int,
    surface_tolerance: float | None,
    connected_only: bool,
) -> PlaneSet:
    """One snapshot of the greedy, consolidated into whole surfaces and filtered for planarity."""
    if 'max_error_increment' in cut:
        steps = hierarchy.steps_for_error(cut['max_error_increment'])
        ids = hierarchy.plane_ids_for_error(cut['max_error_increment'])
    else:
        steps = hierarchy.steps_for_count(cut['max_planes'])
        ids = hierarchy.plane_ids(steps)
    scan = hierarchy.scan
    sigmas = hierarchy.sigmas
    unit_scan = scan if sigmas is None else replace(scan, directions=_unit_directions(scan, sigmas))
    ray_sigmas = np.where(scan.valid, 1.0, np.nan) if sigmas is None else sigmas
    if surface_tolerance is not None:
        noise_factor = 0.0 if profile is None else profile.noise_factor
        share = None if profile is None else profile.large_surface_share
        large_points = 0 if share is None else max(1, math.ceil(share * int(np.count_nonzero(scan.valid))))
        step_factor = 1.0 if profile is None else profile.step_factor
        boundary_points = None if profile is None else profile.boundary_join_points
        ids = _consolidate(
            unit_scan,
            ids,
            ray_sigmas,
            surface_tolerance,
            connected_only,
            noise_factor,
            min_plane_points,
            large_points,
            step_factor,
            boundary_points,
        )
    planes, _, fitted_members = fit_pixel_groups_with_members(
        scan, ids, min_plane_points=min_plane_points, residuals=False, sigmas=sigmas, actions=steps, **cut
    )
    factor = np.inf if profile is None else profile.max_plane_rmse_factor
    curvature_factor = np.inf if profile is None else profile.max_plane_curvature_factor
    min_width = None if profile is None else profile.min_plane_width
    min_breadth = None if profile is None else profile.min_plane_breadth
    sums = members = None  # the planes' _plane_sums with ray_sigmas and their _members, when computed
    tested = np.isfinite(factor) or np.isfinite(curvature_factor) or min_width is not None or min_breadth is not None
    if tested and planes.num_planes:
        planes, sums, members = _drop_non_planar(
            unit_scan,
            planes,
            ray_sigmas,
            surface_tolerance or 0.0,
            profile.noise_factor,
            factor,
            profile.flatness_length,
            curvature_factor,
            min_width,
            profile.curvature_max_size,
            fitted_members,
            min_breadth,
        )
    if profile is not None and profile.correlation_length is not None and planes.num_planes:
        independent = _independent_sigmas(unit_scan, ray_sigmas, profile)
        planes = replace(
            planes,
            covariances=planes.covariances
            + systematic_covariances(
                unit_scan,
                planes,
                independent,
                profile.correlation_length,
                quadrant_jackknife=profile.quadrant_jackknife,
                row_jackknife=profile.row_jackknife,
                sums=sums if independent is ray_sigmas else None,
                members=members,
            ),
        )
    return planes


def _unit_directions(scan: RayScan, sigmas: np.ndarray) -> np.ndarray:
    """``scan.directions / sigma_k`` (the greedy's scaled directions made unit again; invalid rays as
    they are), in the consolidation's work memory (valid until this thread's next whole_surfaces)."""
    out = _reusable('unit_directions', 3 * scan.size, np.float64).reshape(scan.size, 3)
    _unit_directions_kernel(scan.directions, scan.valid, np.ascontiguousarray(sigmas, dtype=np.float64), out)
    return out


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _unit_directions_kernel(directions, valid, sigmas, out):
    for k in nb.prange(len(valid)):
        scale = sigmas[k] if valid[k] else 1.0
        for c in range(3):
            out[k, c] = directions[k, c] / scale


def _consolidate(
    unit_scan: RayScan,
    ids: np.ndarray,
    ray_sigmas: np.ndarray,
    tau: float,
    connected_only: bool,
    noise_factor: float,
    min_points: int,
    large_surface_points: int = 0,
    step_factor: float = 1.0,
    boundary_join_points: int | None = None,
) -> np.ndarray:
    """consolidate_pieces then absorb_rays (then join_at_boundaries with boundary_join_points), across
    the seam of a full revolution: in the columns (a sweep with one row per beam) or in the rows (a
    transposed sweep, one column per beam), so that a transposed grid gives the same surfaces."""
    scan, order = unit_scan, None
    wrap = columns_wrap(unit_scan)
    if not wrap and rows_wrap(unit_scan):  # consolidate the transposed grid, whose columns wrap
        order = np.arange(unit_scan.size).reshape(unit_scan.height, unit_scan.width).T.reshape(-1)
        scan = replace(
            unit_scan,
            height=unit_scan.width,
            width=unit_scan.height,
            endpoints=unit_scan.endpoints[order],
            directions=unit_scan.directions[order],
            ranges=unit_scan.ranges[order],
            valid=unit_scan.valid[order],
        )
        ids, ray_sigmas, wrap = ids[order], ray_sigmas[order], True
    # consolidate_pieces then absorb_rays, the surfaces numbered 0..S-1 (fit_pixel_groups numbers
    # planes by size and first pixel: the ids' values do not matter), in work memory
    ids = consolidated_surfaces(
        scan,
        ids,
        ray_sigmas,
        tau,
        connected_only=connected_only,
        noise_factor=noise_factor,
        min_points=min_points,
        wrap_columns=wrap,
        large_surface_points=large_surface_points,
        step_factor=step_factor,
    )
    if boundary_join_points is not None:
        ids = join_at_boundaries(
            scan,
            ids,
            ray_sigmas,
            tau,
            boundary_join_points,
            noise_factor=noise_factor,
            step_factor=step_factor,
            wrap_columns=wrap,
            max_gap=0 if connected_only else BOUNDARY_GAP,
        )
    if order is None:
        return ids
    back = np.empty_like(ids)
    back[order] = ids
    return back


def _independent_sigmas(unit_scan: RayScan, ray_sigmas: np.ndarray, profile: SensorProfile) -> np.ndarray:
    """The rays' independent noise (m) that the systematic covariance does not count: the sigmas the
    greedy used, but at most the profile's unscaled model's. A scan measured noisier than the model
    (noise_scale_bounds) keeps the excess as systematic error: the second differences that measure
    the scale also see structured errors (lateral jitter on slanted surfaces, disparity steps)."""
    if profile.noise is None or profile.noise_scale_bounds is None:
        return ray_sigmas  # the greedy's sigmas are the model's
    model = profile.noise.ray_sigmas(unit_scan.ranges, unit_scan.directions, unit_scan.valid)
    return np.fmin(ray_sigmas, model, out=model)


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _plane_sums_kernel(members, starts, bounds, endpoints, center, directions, ray_sigmas, normals, offsets, count):
    """Per-plane sums over the rays of every plane j (``members[starts[j]:starts[j + 1]]``, chunks.plane_members:
    pixel order, as np.bincount adds).

    Returns (J, 12): centroid (3, m; endpoints + center), per-point scatter xx xy xz yy yz zz about it
    (6, m^2), mean squared distance from the plane (m^2), mean (sigma_k n . v_k)^2 (m^2), mean sigma_k^2
    (m^2), each divided by count[j]. The planes' runs ``bounds`` (chunks.group_chunks) are summed in
    parallel, each plane by one thread in pixel order.
    """
    out = np.zeros((len(count), 12))
    for c in nb.prange(len(bounds) - 1):
        for g in range(bounds[c], bounds[c + 1]):
            _plane_sums_of(
                members[starts[g] : starts[g + 1]],
                g,
                endpoints,
                center,
                directions,
                ray_sigmas,
                normals,
                offsets,
                count,
                out,
            )
    return out


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _plane_sums_of(pixels, g, endpoints, center, directions, ray_sigmas, normals, offsets, count, out):
    """_plane_sums_kernel's row g from the plane's pixels. Two passes: the sums of the points, then of
    the products of their offsets from the centroid."""
    for k in pixels:
        x = endpoints[k, 0] + center[0]
        y = endpoints[k, 1] + center[1]
        z = endpoints[k, 2] + center[2]
        out[g, 0] += x
        out[g, 1] += y
        out[g, 2] += z
        # dot products summed as (0 + 2) + 1, the order of np.einsum's two-lane sum of three terms,
        # which the numpy passes this kernel replaces used
        distance = (x * normals[g, 0] + z * normals[g, 2]) + y * normals[g, 1] - offsets[g]
        along = (
            (directions[k, 0] * normals[g, 0] + directions[k, 2] * normals[g, 2]) + directions[k, 1] * normals[g, 1]
        ) * ray_sigmas[k]
        out[g, 9] += distance * distance
        out[g, 10] += along * along
        out[g, 11] += ray_sigmas[k] * ray_sigmas[k]
    for a in (0, 1, 2, 9, 10, 11):
        out[g, a] /= count[g]
    for k in pixels:
        rx = endpoints[k, 0] + center[0] - out[g, 0]
        ry = endpoints[k, 1] + center[1] - out[g, 1]
        rz = endpoints[k, 2] + center[2] - out[g, 2]
        out[g, 3] += rx * rx
        out[g, 4] += rx * ry
        out[g, 5] += rx * rz
        out[g, 6] += ry * ry
        out[g, 7] += ry * rz
        out[g, 8] += rz * rz
    for a in range(3, 9):
        out[g, a] /= count[g]


def _plane_sums(scan: RayScan, planes: PlaneSet, ray_sigmas: np.ndarray, count: np.ndarray, members=None):
    """Per-plane means over each plane's rays (see _plane_sums_kernel): centroid (J, 3), scatter
    (J, 3, 3), mean squared distance from the plane, mean (sigma_k n . v_k)^2 and mean sigma_k^2 (J,).
    ``members``: the planes' :func:`_members`, if already computed."""
    members, starts = _members(planes) if members is None else members
    sums = _plane_sums_kernel(
        members,
        starts,
        group_chunks(planes.point_counts),
        np.ascontiguousarray(scan.endpoints, dtype=np.float64),
        np.ascontiguousarray(scan.center, dtype=np.float64),
        np.ascontiguousarray(scan.directions, dtype=np.float64),
        np.ascontiguousarray(ray_sigmas, dtype=np.float64),
        np.ascontiguousarray(planes.normals, dtype=np.float64),
        np.ascontiguousarray(planes.offsets, dtype=np.float64),
        np.ascontiguousarray(count, dtype=np.float64),
    )
    scatter = sums[:, _SCATTER_INDEX]
    return sums[:, :3], scatter, sums[:, 9], sums[:, 10], sums[:, 11]


def _members(planes: PlaneSet) -> tuple[np.ndarray, np.ndarray]:
    """The planes' pixels grouped by plane (chunks.plane_members of their labels)."""
    return plane_members(planes.labels.reshape(-1), planes.num_planes)


#: Columns of _plane_sums_kernel's xx xy xz yy yz zz as a symmetric (3, 3) matrix.
_SCATTER_INDEX = np.array([[3, 4, 5], [4, 6, 7], [5, 7, 8]])


def systematic_covariances(
    scan: RayScan,
    planes: PlaneSet,
    ray_sigmas: np.ndarray,
    correlation_length: float,
    quadrant_jackknife: bool = False,
    *,
    row_jackknife: bool = False,
    sums: tuple | None = None,
    members: tuple | None = None,
) -> np.ndarray:
    """``(J, 3, 3)`` covariance (m^2) of each plane's closest point d n from errors that do not average out.

    The model: a plane's points deviate from it by the sensor's independent noise (already in the
    fit's covariance) plus a systematic part (surface flatness, per-beam biases, depth distortion)
    that is correlated over ``correlation_length`` (m). Its variance is estimated per plane from the
    data: the mean squared point-to-plane distance less the noise model's share along the normal,
    s_sys^2 = max(mean dist^2 - mean (sigma_k n . v_k)^2, 0). Over a plane of area A it averages out
    only over N_eff = clamp(A / L^2, 1, N) independent patches, so the plane's offset at its
    centroid has variance s_sys^2 / N_eff and its tilt about each in-plane axis e_i
    s_sys^2 / (N_eff lambda_i) (lambda_i: the points' variance along e_i; A = 12 sqrt(lambda_1 lambda_2),
    a rectangle's). With ``quadrant_jackknife`` the spread of the plane's fit over its four
    quadrants (ppe_ros.core.quadrants: errors correlated over the whole plane, which move the plane
    when a different part of the surface is seen) is used too, with ``row_jackknife`` its spread over
    the grid rows it spans (a spinning lidar's beams, each with its own range bias and angle error),
    with both the one of larger trace (each jackknife sees only the errors that differ between the
    parts of its partition): a covariance of offset and tilts whose variances are raised to the
    independent-patch model's where that is larger. The result is
    mapped to d n to first order. ``sums``: the planes' :func:`_plane_sums` with these ``ray_sigmas``, if
    already computed; ``members``: their :func:`_members`, if already computed.
    """
    count = planes.point_counts.astype(np.float64)
    n_planes = planes.num_planes
    if members is None and (sums is None or quadrant_jackknife or row_jackknife):
        members = _members(planes)
    if sums is None:
        sums = _plane_sums(scan, planes, ray_sigmas, count, members)
    centroid, scatter, residual2, noise2, _ = sums
    normals, offsets = planes.normals, planes.offsets
    systematic2 = np.maximum(residual2 - noise2, 0.0)
    values, vectors = np.linalg.eigh(scatter)  # ascending: the two largest span the plane
    lam1, lam2 = np.maximum(values[:, 2], 1e-12), np.maximum(values[:, 1], 1e-12)
    area = 12.0 * np.sqrt(lam1 * lam2)
    n_eff = np.clip(area / float(correlation_length) ** 2, 1.0, count)
    # local parameters: offset at the centroid, tilts about the long (u) and short (v) in-plane axes
    model = np.stack([systematic2 / n_eff, systematic2 / (n_eff * lam1), systematic2 / (n_eff * lam2)], axis=1)
    u_axis, v_axis = vectors[:, :, 2], vectors[:, :, 1]
    local = np.zeros((n_planes, 3, 3))
    axes = np.stack([u_axis, v_axis, normals], axis=1)
    if quadrant_jackknife:
        local = jackknife_of_members(scan.endpoints, scan.center, *members, centroid, axes)
    if row_jackknife:
        rows = jackknife_of_members(scan.endpoints, scan.center, *members, centroid, axes, row_width=scan.width)
        # with both, each plane takes the partition that moves it more (larger trace)
        wider = np.trace(rows, axis1=1, axis2=2) > np.trace(local, axis1=1, axis2=2)
        local = np.where(wider[:, None, None], rows, local)
    diagonal = np.arange(3)
    local[:, diagonal, diagonal] = np.maximum(local[:, diagonal, diagonal], model)
    # d n of the plane w = a + b u + c v (w along the normal from the centroid), to first order
    jacobian = np.stack(
        [
            normals,
            -np.einsum('ij,ij->i', u_axis, centroid)[:, None] * normals - offsets[:, None] * u_axis,
            -np.einsum('ij,ij->i', v_axis, centroid)[:, None] * normals - offsets[:, None] * v_axis,
        ],
        axis=2,
    )
    out = np.einsum('jab,jbc,jdc->jad', jacobian, local, jacobian)
    return np.where(np.isfinite(out), out, 0.0)


def _drop_non_planar(
    scan: RayScan,
    planes: PlaneSet,
    ray_sigmas: np.ndarray,
    tau: float,
    noise_factor: float,
    factor: float,
    flatness_length: float | None = None,
    curvature_factor: float = np.inf,
    min_width: float | None = None,
    curvature_max_size: float | None = None,
    members: tuple[np.ndarray, np.ndarray] | None = None,
    min_breadth: float | None = None,
) -> tuple[PlaneSet, tuple, tuple]:
    """Report as no plane every plane whose RMS point-to-plane distance exceeds
    factor * sqrt(tau_D^2 + lambda^2 mean sigma_k^2 + mean (sigma_k n . v_k)^2): the surface tolerance
    plus the sensor's noise along the normal (lambda: noise_factor), or whose best quadric surface
    departs from its plane by an RMS of more than curvature_factor * tau_D (:func:`curvature_rms`: a
    wheel, a car body, a pole). tau_D = tau min(1, D / flatness_length) for a plane of size D (the
    square root of its area, 12 sqrt(l1 l2) from the scatter's two largest eigenvalues): a
    surface's deviation from flatness grows with its size, so a small patch must be flat to the
    noise, which a tree's or a car's pieces are not; None: tau_D = tau. With ``curvature_max_size`` the
    curvature test judges only planes of a size D below it; ``min_width``: a plane whose points span less
    than that across (sqrt(12 l2), l2 the scatter's middle eigenvalue) is no plane; ``min_breadth``: a plane
    whose :func:`plane_breadth` is below it is no plane. scan has unit directions;
    ``members``: the planes' :func:`_members`, if already known (the fits group them).
    Returns the kept planes, renumbered (:func:`_kept_planes`: what a refit of their pixels gives), their
    :func:`_plane_sums` with ``ray_sigmas`` (for :func:`systematic_covariances` with the same sigmas) and their
    :func:`_members`.
    """
    members = _members(planes) if members is None else members
    sums = _plane_sums(scan, planes, ray_sigmas, np.maximum(planes.point_counts, 1), members)
    centroid, scatter, mean_d2, noise2, sigma2 = sums
    tau2 = np.full(planes.num_planes, tau**2)
    values = np.linalg.eigvalsh(scatter)  # ascending: the two largest span the plane
    size = np.sqrt(12.0 * np.sqrt(np.maximum(values[:, 2], 0.0) * np.maximum(values[:, 1], 0.0)))
    if flatness_length is not None:
        tau2 *= np.minimum(1.0, size / float(flatness_length)) ** 2
    planar = mean_d2 <= factor**2 * (tau2 + noise_factor**2 * sigma2 + noise2)
    if np.isfinite(curvature_factor):
        curvature = curvature_rms(scan, planes, centroid, scatter, members=members)
        bent = ~(curvature**2 <= float(curvature_factor) ** 2 * tau2)  # NaN: bent, as a failed test
        if curvature_max_size is not None:
            bent &= size < float(curvature_max_size)
        planar &= ~bent
    if min_width is not None:
        planar &= 12.0 * np.maximum(values[:, 1], 0.0) >= float(min_width) ** 2
    if min_breadth is not None:
        planar &= plane_breadth(scan, planes, members=members) >= float(min_breadth)
    if planar.all():
        return planes, sums, members
    return _kept_planes(planes, planar), tuple(column[planar] for column in sums), _kept_members(members, planar)


def _kept_members(members: tuple, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_members` of ``_kept_planes(planes, keep)`` from the planes' own: the kept planes' runs, in
    their order (the renumbering keeps the planes' order and each plane's pixel order)."""
    pixels, starts = members
    counts = np.diff(starts)
    kept_starts = np.zeros(np.count_nonzero(keep) + 1, np.int64)
    np.cumsum(counts[keep], out=kept_starts[1:])
    return pixels[np.repeat(keep, counts)], kept_starts


def plane_breadth(
    scan: RayScan, planes: PlaneSet, *, members: tuple[np.ndarray, np.ndarray] | None = None
) -> np.ndarray:
    """``(J,)`` breadth (m) of each plane across the scan's grid: how wide a strip of points it is.

    On every grid row that holds points of plane j, the row's extent is the largest distance of those
    points from the one in the row's least column; on every grid column, from the one in the column's
    least row. The breadth is the smaller of the two medians: over the plane's rows of their extents
    and over its columns of theirs. A wall, a road or a window is as broad as it is wide or tall (a
    ring of ground around the sensor: about its diameter); a pole, a trunk or a branch, seen from one
    side, is a strip of its diameter; a plane of points on one grid row (one beam) has breadth 0
    across it. Frame-free (distances between ``scan.endpoints``). ``members``: the planes'
    :func:`_members`, if already computed.

    Raises:
        ValueError: the planes' label grid does not have one pixel per ray of the scan.
    """
    height, width = planes.labels.shape
    if height * width != len(scan.endpoints):
        raise ValueError(f'planes of a {height} x {width} grid for a scan of {len(scan.endpoints)} rays')
    members, starts = _members(planes) if members is None else members
    return _breadth_kernel(
        members,
        starts,
        group_chunks(planes.point_counts),
        np.ascontiguousarray(scan.endpoints, dtype=np.float64),
        height,
        width,
    )


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _breadth_kernel(members, starts, bounds, endpoints, height, width):
    """plane_breadth of each plane g (pixels ``members[starts[g]:starts[g + 1]]`` in pixel order); the planes'
    runs ``bounds`` (chunks.group_chunks) in parallel, with a row and a column scratch per run."""
    out = np.zeros(len(starts) - 1)
    for c in nb.prange(len(bounds) - 1):
        row_first = np.full(height, -1, np.int64)
        row_extent = np.zeros(height)
        column_first = np.full(width, -1, np.int64)
        column_extent = np.zeros(width)
        for g in range(bounds[c], bounds[c + 1]):
            out[g] = _breadth_of(
                members[starts[g] : starts[g + 1]], endpoints, width, row_first, row_extent, column_first, column_extent
            )
    return out


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _breadth_of(pixels, endpoints, width, row_first, row_extent, column_first, column_extent):
    """plane_breadth of one plane's pixels (in pixel order, so a row's first pixel is its least column's and
    a column's its least row's). The first and extent arrays (a slot per row or column, first -1) are
    scratch, left as found."""
    n_rows = 0
    n_columns = 0
    for k in pixels:
        i = k // width
        j = k - i * width
        n_rows += _extend_line(endpoints, k, i, row_first, row_extent)
        n_columns += _extend_line(endpoints, k, j, column_first, column_extent)
    rows = np.empty(n_rows)
    columns = np.empty(n_columns)
    n_rows = 0
    n_columns = 0
    for k in pixels:
        i = k // width
        j = k - i * width
        if row_first[i] >= 0:
            rows[n_rows] = np.sqrt(row_extent[i])
            n_rows += 1
            row_first[i] = -1
        if column_first[j] >= 0:
            columns[n_columns] = np.sqrt(column_extent[j])
            n_columns += 1
            column_first[j] = -1
    if n_rows == 0:
        return 0.0
    return min(np.median(rows), np.median(columns))


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _extend_line(endpoints, k, line, first, extent):
    """Pixel k on grid line ``line``: its first pixel (returns 1) or the line's squared extent from its first
    pixel grown to reach k (returns 0)."""
    f = first[line]
    if f < 0:
        first[line] = k
        extent[line] = 0.0
        return 1
    dx = endpoints[k, 0] - endpoints[f, 0]
    dy = endpoints[k, 1] - endpoints[f, 1]
    dz = endpoints[k, 2] - endpoints[f, 2]
    extent[line] = max(extent[line], dx * dx + dy * dy + dz * dz)
    return 0


def curvature_rms(
    scan: RayScan, planes: PlaneSet, centroid: np.ndarray, scatter: np.ndarray, *, members=None
) -> np.ndarray:
    """``(J,)`` RMS (m) by which each plane's best quadric surface departs from its best plane.

    In the frame of the plane's points (centroid; u, v along the scatter's two largest axes, w along
    the smallest), w is fitted by least squares once as a + b u + c v and once as the quadric
    a + b u + c v + d u^2 + e u v + f v^2; the result is sqrt((SSE_plane - SSE_quadric) / N), the
    RMS of the quadric's bend over the plane's points (a flat surface: only the noise's share, about
    sigma sqrt(3 / N); half a cylinder of radius R: about R / 4). ``centroid`` (J, 3) and ``scatter``
    (J, 3, 3, per point) are :func:`_plane_sums`'; points are ``scan.endpoints + scan.center``.
    ``members``: the planes' :func:`_members`, if already computed.
    """
    members, starts = _members(planes) if members is None else members
    values, vectors = np.linalg.eigh(scatter)  # ascending: w, v, u
    scales = np.sqrt(np.where(values > 0.0, values, 1.0))  # u, v in units of their spread
    reduction = _quadric_reduction_kernel(
        members,
        starts,
        group_chunks(planes.point_counts),
        np.ascontiguousarray(scan.endpoints, dtype=np.float64),
        np.ascontiguousarray(scan.center, dtype=np.float64),
        np.ascontiguousarray(centroid, dtype=np.float64),
        np.ascontiguousarray(vectors, dtype=np.float64),
        np.ascontiguousarray(scales, dtype=np.float64),
    )
    count = np.maximum(planes.point_counts, 1).astype(np.float64)
    return np.sqrt(reduction / count)


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _quadric_reduction_kernel(members, starts, bounds, endpoints, center, centroid, vectors, scales):
    """Per plane j (pixels ``members[starts[j]:starts[j + 1]]``, chunks.plane_members), SSE_plane - SSE_quadric
    (m^2) of curvature_rms; the planes' runs ``bounds`` (chunks.group_chunks) in parallel, each plane by one
    thread in pixel order."""
    out = np.zeros(len(centroid))
    for c in nb.prange(len(bounds) - 1):
        for g in range(bounds[c], bounds[c + 1]):
            out[g] = _quadric_reduction_of(
                members[starts[g] : starts[g + 1]], g, endpoints, center, centroid, vectors, scales
            )
    return out


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _quadric_reduction_of(pixels, g, endpoints, center, centroid, vectors, scales):
    """_quadric_reduction_kernel's value of plane g from its pixels.

    The normal equations A^T A x = A^T w in the basis (1, u, v, u^2, u v, v^2) (u, v divided by
    scales[g, 2], scales[g, 1]) are summed in pixel order. With the Cholesky factor L L^T = A^T A and
    z = L^-1 A^T w, a fit on the first m basis functions has SSE = w^T w - (z_0^2 + ... + z_{m-1}^2)
    (L's leading block factors the leading block), so the reduction is z_3^2 + z_4^2 + z_5^2. A basis
    function that depends on the earlier ones (a pivot of at most 1e-12 of its diagonal: points on
    two lines) adds nothing and is skipped.
    """
    normal = np.zeros((6, 6))
    rhs = np.zeros(6)
    basis = np.empty(6)
    for k in pixels:
        dx = endpoints[k, 0] + center[0] - centroid[g, 0]
        dy = endpoints[k, 1] + center[1] - centroid[g, 1]
        dz = endpoints[k, 2] + center[2] - centroid[g, 2]
        u = (dx * vectors[g, 0, 2] + dy * vectors[g, 1, 2] + dz * vectors[g, 2, 2]) / scales[g, 2]
        v = (dx * vectors[g, 0, 1] + dy * vectors[g, 1, 1] + dz * vectors[g, 2, 1]) / scales[g, 1]
        w = dx * vectors[g, 0, 0] + dy * vectors[g, 1, 0] + dz * vectors[g, 2, 0]
        basis[0], basis[1], basis[2] = 1.0, u, v
        basis[3], basis[4], basis[5] = u * u, u * v, v * v
        for a in range(6):
            rhs[a] += basis[a] * w
            for b in range(a + 1):
                normal[a, b] += basis[a] * basis[b]
    lower = np.zeros((6, 6))
    z = np.zeros(6)
    for a in range(6):  # Cholesky, row by row, and forward substitution of z
        for b in range(a + 1):
            total = normal[a, b]
            for c in range(b):
                total -= lower[a, c] * lower[b, c]
            if b < a:
                lower[a, b] = total / lower[b, b] if lower[b, b] > 0.0 else 0.0
            elif total > 1e-12 * normal[a, a]:
                lower[a, a] = np.sqrt(total)
            else:
                lower[a, a] = 0.0  # dependent: skipped
        total = rhs[a]
        for c in range(a):
            total -= lower[a, c] * z[c]
        z[a] = total / lower[a, a] if lower[a, a] > 0.0 else 0.0
    return z[3] * z[3] + z[4] * z[4] + z[5] * z[5]


def _kept_planes(planes: PlaneSet, keep: np.ndarray) -> PlaneSet:
    """The planes with keep[j] True, renumbered 1..J' in their order, the others no plane.

    It is what fit_pixel_groups gives for the kept planes' pixels: each group is fitted on its own
    rays in pixel order, and the order by size, then first pixel, is kept by any subset.
    """
    kept = np.flatnonzero(keep)
    relabel = np.zeros(planes.num_planes + 1, np.int32)
    relabel[kept + 1] = np.arange(1, len(kept) + 1, dtype=np.int32)
    return replace(
        planes,
        labels=relabel[planes.labels],
        normals=planes.normals[kept],
        offsets=planes.offsets[kept],
        centroids=planes.centroids[kept],
        point_counts=planes.point_counts[kept],
        sse=planes.sse[kept],
        rmse=planes.rmse[kept],
        covariances=planes.covariances[kept],
    )
