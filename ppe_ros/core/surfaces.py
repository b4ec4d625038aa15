"""Whole surfaces: a snapshot of the greedy consolidated into one plane per physical surface.

After the greedy (ppe_ros.core.extraction) with a sensor profile, the pieces of one surface are
merged (ppe_ros.core.consolidation), planes that are not planar within the sensor's tolerance are
reported as no plane, and each plane's covariance gets the share of the errors that do not average
out (systematic_covariances). Frames: the scan's; lengths in metres.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from ppe_ros.core.consolidation import absorb_rays, columns_wrap, consolidate_pieces, rows_wrap
from ppe_ros.core.fitting import fit_pixel_groups
from ppe_ros.core.planes import PlaneSet
from ppe_ros.core.quadrants import quadrant_jackknife as quadrant_jackknife_covariances
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
    else:
        steps = hierarchy.steps_for_count(cut['max_planes'])
    ids = hierarchy.plane_ids(steps)
    scan = hierarchy.scan
    sigmas = hierarchy.sigmas
    unit_scan = (
        scan
        if sigmas is None
        else replace(scan, directions=scan.directions / np.where(scan.valid, sigmas, 1.0)[:, None])
    )
    ray_sigmas = np.where(scan.valid, 1.0, np.nan) if sigmas is None else sigmas
    if surface_tolerance is not None:
        noise_factor = 0.0 if profile is None else profile.noise_factor
        ids = _consolidate(
            unit_scan, ids, ray_sigmas, surface_tolerance, connected_only, noise_factor, min_plane_points
        )
    planes, _ = fit_pixel_groups(
        scan, ids, min_plane_points=min_plane_points, residuals=False, sigmas=sigmas, actions=steps, **cut
    )
    factor = np.inf if profile is None else profile.max_plane_rmse_factor
    if np.isfinite(factor) and planes.num_planes:
        planes = _drop_non_planar(
            unit_scan,
            scan,
            planes,
            ray_sigmas,
            surface_tolerance or 0.0,
            profile.noise_factor,
            factor,
            sigmas,
            min_plane_points,
            steps,
            cut,
            profile.flatness_length,
        )
    if profile is not None and profile.correlation_length is not None and planes.num_planes:
        planes = replace(
            planes,
            covariances=planes.covariances
            + systematic_covariances(
                unit_scan,
                planes,
                _independent_sigmas(unit_scan, ray_sigmas, profile),
                profile.correlation_length,
                quadrant_jackknife=profile.quadrant_jackknife,
            ),
        )
    return planes


def _consolidate(
    unit_scan: RayScan,
    ids: np.ndarray,
    ray_sigmas: np.ndarray,
    tau: float,
    connected_only: bool,
    noise_factor: float,
    min_points: int,
) -> np.ndarray:
    """consolidate_pieces then absorb_rays, across the seam of a full revolution: in the columns (a
    sweep with one row per beam) or in the rows (a transposed sweep, one column per beam), so that a
    transposed grid gives the same surfaces."""
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
    ids = consolidate_pieces(
        scan, ids, ray_sigmas, tau, connected_only=connected_only, noise_factor=noise_factor, wrap_columns=wrap
    )
    ids = absorb_rays(scan, ids, ray_sigmas, tau, noise_factor=noise_factor, min_points=min_points, wrap_columns=wrap)
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
    model = np.full(unit_scan.size, np.nan)
    valid = unit_scan.valid
    model[valid] = profile.noise.sigmas(unit_scan.ranges[valid], unit_scan.directions[valid])
    return np.fmin(ray_sigmas, model)


def _plane_scatter(points: np.ndarray, j: np.ndarray, count: np.ndarray, n_planes: int):
    """Centroid (J, 3) and per-point scatter matrix (J, 3, 3) of each plane's points (plane j[i] of points[i])."""
    centroid = np.stack([np.bincount(j, weights=points[:, a], minlength=n_planes) for a in range(3)], 1)
    centroid /= count[:, None]
    rel = points - centroid[j]
    scatter = np.empty((n_planes, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            scatter[:, a, b] = scatter[:, b, a] = (
                np.bincount(j, weights=rel[:, a] * rel[:, b], minlength=n_planes) / count
            )
    return centroid, scatter


def systematic_covariances(
    scan: RayScan,
    planes: PlaneSet,
    ray_sigmas: np.ndarray,
    correlation_length: float,
    quadrant_jackknife: bool = False,
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
    when a different part of the surface is seen) is used too: its covariance of offset and tilts,
    with each variance raised to the independent-patch model's where that is larger. The result is
    mapped to d n to first order.
    """
    labels = planes.labels.reshape(-1)
    on = np.flatnonzero(labels > 0)
    j = labels[on] - 1
    count = planes.point_counts.astype(np.float64)
    points = scan.endpoints[on] + scan.center
    n_planes = planes.num_planes
    centroid, scatter = _plane_scatter(points, j, count, n_planes)
    normals, offsets = planes.normals, planes.offsets
    distance = np.einsum('ij,ij->i', points, normals[j]) - offsets[j]
    along = np.einsum('ij,ij->i', scan.directions[on], normals[j]) * ray_sigmas[on]
    residual2 = np.bincount(j, weights=distance**2, minlength=n_planes) / count
    noise2 = np.bincount(j, weights=along**2, minlength=n_planes) / count
    systematic2 = np.maximum(residual2 - noise2, 0.0)
    values, vectors = np.linalg.eigh(scatter)  # ascending: the two largest span the plane
    lam1, lam2 = np.maximum(values[:, 2], 1e-12), np.maximum(values[:, 1], 1e-12)
    area = 12.0 * np.sqrt(lam1 * lam2)
    n_eff = np.clip(area / float(correlation_length) ** 2, 1.0, count)
    # local parameters: offset at the centroid, tilts about the long (u) and short (v) in-plane axes
    model = np.stack([systematic2 / n_eff, systematic2 / (n_eff * lam1), systematic2 / (n_eff * lam2)], axis=1)
    u_axis, v_axis = vectors[:, :, 2], vectors[:, :, 1]
    local = np.zeros((n_planes, 3, 3))
    if quadrant_jackknife:
        axes = np.stack([u_axis, v_axis, normals], axis=1)
        local = quadrant_jackknife_covariances(points, j, centroid, axes)
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
    fit_scan: RayScan,
    planes: PlaneSet,
    ray_sigmas: np.ndarray,
    tau: float,
    noise_factor: float,
    factor: float,
    sigmas: np.ndarray | None,
    min_plane_points: int,
    steps: int,
    cut: dict,
    flatness_length: float | None = None,
) -> PlaneSet:
    """Report as no plane every plane whose RMS point-to-plane distance exceeds
    factor * sqrt(tau_D^2 + lambda^2 mean sigma_k^2 + mean (sigma_k n . v_k)^2): the surface tolerance
    plus the sensor's noise along the normal (lambda: noise_factor). tau_D = tau min(1, D /
    flatness_length) for a plane of size D (the square root of its area, 12 sqrt(l1 l2) from the
    scatter's two largest eigenvalues): a surface's deviation from flatness grows with its size, so
    a small patch must be flat to the noise, which a tree's or a car's pieces are not; None: tau_D =
    tau. scan has unit directions; the kept planes are refitted on fit_scan (the greedy's, directions
    scaled by sigmas).
    """
    labels = planes.labels.reshape(-1)
    on = np.flatnonzero(labels > 0)
    j = labels[on] - 1
    normals_internal = planes.normals[j]
    points = scan.endpoints[on] + scan.center
    distance = np.einsum('ij,ij->i', points, normals_internal) - planes.offsets[j]
    along = np.abs(np.einsum('ij,ij->i', scan.directions[on], normals_internal)) * ray_sigmas[on]
    count = np.maximum(planes.point_counts, 1)
    mean_d2 = np.bincount(j, weights=distance**2, minlength=planes.num_planes) / count
    noise2 = np.bincount(j, weights=along**2, minlength=planes.num_planes) / count
    sigma2 = np.bincount(j, weights=ray_sigmas[on] ** 2, minlength=planes.num_planes) / count
    tau2 = np.full(planes.num_planes, tau**2)
    if flatness_length is not None:
        _, scatter = _plane_scatter(points, j, count.astype(np.float64), planes.num_planes)
        values = np.linalg.eigvalsh(scatter)  # ascending: the two largest span the plane
        size = np.sqrt(12.0 * np.sqrt(np.maximum(values[:, 2], 0.0) * np.maximum(values[:, 1], 0.0)))
        tau2 *= np.minimum(1.0, size / float(flatness_length)) ** 2
    planar = mean_d2 <= factor**2 * (tau2 + noise_factor**2 * sigma2 + noise2)
    if planar.all():
        return planes
    keep = np.concatenate([[False], planar])
    ids = np.where(keep[labels], labels, -1).astype(np.int64)
    refit, _ = fit_pixel_groups(
        fit_scan, ids, min_plane_points=min_plane_points, residuals=False, sigmas=sigmas, actions=steps, **cut
    )
    return refit
