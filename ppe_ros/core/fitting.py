"""Maximum-likelihood plane fits under the radial (ray-length) noise model of PPE.

A plane explains ray k (start s_k, unit direction v_k, measured length r_k) by the length at
which the ray meets it. With the plane written as ``w . x = 1`` (``w = n / d``) in a frame whose
origin is not on the plane, the residual of ray k is exactly

    r_k - rhat_k = (w . p_k - 1) / (w . v_k),      p_k = s_k + r_k v_k,

and the fit minimises the sum of squared residuals (SSE, m^2) by Gauss-Newton with step halving.
Internally every computation runs in the frame of :class:`ppe_ros.core.scan.RayScan` (the input
frame translated by the mean ray start); results are returned in the input frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from ppe_ros.core.chunks import group_chunks
from ppe_ros.core.planes import PlaneSet
from ppe_ros.core.scan import MAX_RANGE, MIN_RANGE, RayScan, make_ray_scan

#: Gauss-Newton stops when the SSE decreases by less than this fraction (or the step is tiny).
FIT_RELATIVE_TOLERANCE = 1e-13
FIT_MAX_ITERATIONS = 50


# --------------------------------------------------------------------------------------------
# numba kernels
# --------------------------------------------------------------------------------------------


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def solve_sym3(a00, a01, a02, a11, a12, a22, b0, b1, b2):
    """Solve the symmetric positive definite 3x3 system A x = b (adjugate, one division).

    Positive definiteness is tested on the Jacobi-scaled matrix D^-1/2 A D^-1/2 (unit diagonal):
    its leading 2x2 minor and its determinant must exceed 1e-15 (the squared pivots of its
    Cholesky factor), so the test does not depend on the units of A.
    Returns (x0, x1, x2, ok); ok is False when A is not numerically positive definite (x is then
    meaningless). Branch-free, so that loops calling it can be vectorised.
    """
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    # scaled minor c22 / (a00 a11) > 1e-15 and scaled det / scaled minor = det / (a22 c22) > 1e-15
    ok = (a00 > 0.0) & (a11 > 0.0) & (a22 > 0.0) & (c22 > 1e-15 * a00 * a11) & (det > 1e-15 * a22 * c22)
    inv = 1.0 / det if ok else 0.0
    return (
        (c00 * b0 + c01 * b1 + c02 * b2) * inv,
        (c01 * b0 + c11 * b1 + c12 * b2) * inv,
        (c02 * b0 + c12 * b1 + c22 * b2) * inv,
        ok,
    )


_ZERO9 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
_ZERO10 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _init_add(acc, x, y, z):
    """Add the point (x, y, z) to the normal equations (a00 a01 a02 a11 a12 a22 b0 b1 b2) of _linear_init."""
    a00, a01, a02, a11, a12, a22, b0, b1, b2 = acc
    wt = x * x + y * y + z * z
    return (
        a00 + wt * x * x,
        a01 + wt * x * y,
        a02 + wt * x * z,
        a11 + wt * y * y,
        a12 + wt * y * z,
        a22 + wt * z * z,
        b0 + wt * x,
        b1 + wt * y,
        b2 + wt * z,
    )


# Fits called in the greedy's loops allocate nothing and are compiled with _nrt=False (no atomic
# reference counting of their array arguments on each call; see ppe_ros.core.ppe.queue).


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _linear_init(endpoints, idx, count):
    """Initial plane w: minimises sum |p|^2 (w . p - 1)^2, a range-weighted algebraic fit."""
    acc = _ZERO9
    for t in range(count):
        k = idx[t]
        acc = _init_add(acc, endpoints[k, 0], endpoints[k, 1], endpoints[k, 2])
    return solve_sym3(acc[0], acc[1], acc[2], acc[3], acc[4], acc[5], acc[6], acc[7], acc[8])


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _ray_terms_at(px, py, pz, vx, vy, vz, w0, w1, w2):
    """Radial residual f = (w . p - 1) / (w . v) of the ray (p, v) at w (m), gradient df/dw = (p - f v) / (w . v)."""
    inv_den = 1.0 / (w0 * vx + w1 * vy + w2 * vz)
    f = (w0 * px + w1 * py + w2 * pz - 1.0) * inv_den
    return f, (px - f * vx) * inv_den, (py - f * vy) * inv_den, (pz - f * vz) * inv_den


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def ray_terms(endpoints, directions, k, w0, w1, w2):
    """:func:`_ray_terms_at` of ray k."""
    return _ray_terms_at(
        endpoints[k, 0],
        endpoints[k, 1],
        endpoints[k, 2],
        directions[k, 0],
        directions[k, 1],
        directions[k, 2],
        w0,
        w1,
        w2,
    )


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _gn_add(acc, res, g0, g1, g2):
    """Add a ray's residual and gradient to (SSE, J^T J (6), J^T r (3))."""
    sse, a00, a01, a02, a11, a12, a22, b0, b1, b2 = acc
    return (
        sse + res * res,
        a00 + g0 * g0,
        a01 + g0 * g1,
        a02 + g0 * g2,
        a11 + g1 * g1,
        a12 + g1 * g2,
        a22 + g2 * g2,
        b0 + g0 * res,
        b1 + g1 * res,
        b2 + g2 * res,
    )


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def gn_pass(endpoints, directions, idx, count, w0, w1, w2):
    """One pass over rays idx[:count] at w: SSE, Gauss-Newton information J^T J (6) and J^T r (3)."""
    acc = _ZERO10
    for t in range(count):
        res, g0, g1, g2 = ray_terms(endpoints, directions, idx[t], w0, w1, w2)
        acc = _gn_add(acc, res, g0, g1, g2)
    return acc


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _gauss_newton(endpoints, directions, idx, count, w0, w1, w2, max_iterations, relative_tolerance):
    """Minimise the radial SSE over w from the start (w0, w1, w2).

    Each iteration is one pass over the rays: the pass at a trial point gives its SSE (accept or
    halve the step) and, when accepted, the next Gauss-Newton system. Converged when the
    Gauss-Newton predicted decrease b^T H^-1 b (the decrease of the linearised SSE, which bounds
    how far the SSE is above its minimum to second order) is at most ``relative_tolerance * sse``.

    Returns (sse, w0, w1, w2, converged, information): information is the Gauss-Newton J^T J
    (a00 a01 a02 a11 a12 a22) at the returned w, from the pass that accepted it. sse is inf when
    the fit is degenerate.
    """
    sse, a00, a01, a02, a11, a12, a22, b0, b1, b2 = gn_pass(endpoints, directions, idx, count, w0, w1, w2)
    if not np.isfinite(sse):
        return np.inf, w0, w1, w2, False, (a00, a01, a02, a11, a12, a22)
    for _ in range(max_iterations):
        d0, d1, d2, ok = solve_sym3(a00, a01, a02, a11, a12, a22, b0, b1, b2)
        if not ok:
            return sse, w0, w1, w2, False, (a00, a01, a02, a11, a12, a22)
        predicted = d0 * b0 + d1 * b1 + d2 * b2
        if not predicted > relative_tolerance * sse:
            return sse, w0, w1, w2, True, (a00, a01, a02, a11, a12, a22)
        step = 1.0
        improved = False
        for _halving in range(30):
            n0 = w0 - step * d0
            n1 = w1 - step * d1
            n2 = w2 - step * d2
            trial = gn_pass(endpoints, directions, idx, count, n0, n1, n2)
            if trial[0] <= sse:
                improved = True
                break
            step *= 0.5
        if not improved:
            return sse, w0, w1, w2, True, (a00, a01, a02, a11, a12, a22)
        w0, w1, w2 = n0, n1, n2
        sse, a00, a01, a02, a11, a12, a22, b0, b1, b2 = trial
        wn = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        dn = step * np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if dn <= 1e-15 * wn:
            return sse, w0, w1, w2, True, (a00, a01, a02, a11, a12, a22)
    return sse, w0, w1, w2, False, (a00, a01, a02, a11, a12, a22)


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def fit_with_information(endpoints, directions, idx, count, w0, w1, w2, max_iterations, relative_tolerance):
    """Exact fit of rays idx[:count]; starts from (w0, w1, w2) if finite, else the algebraic fit.

    Returns (sse, w0, w1, w2, information) with the Gauss-Newton information J^T J
    (a00 a01 a02 a11 a12 a22) at the returned w; sse = inf (and w, information NaN when there is
    no plane to start from) for a degenerate set (fewer than 3 independent rays).
    """
    nan6 = (np.nan, np.nan, np.nan, np.nan, np.nan, np.nan)
    if count < 3:
        return np.inf, np.nan, np.nan, np.nan, nan6
    if not (np.isfinite(w0) and np.isfinite(w1) and np.isfinite(w2)):
        w0, w1, w2, ok = _linear_init(endpoints, idx, count)
        if not ok:
            return np.inf, np.nan, np.nan, np.nan, nan6
    sse, w0, w1, w2, _, information = _gauss_newton(
        endpoints, directions, idx, count, w0, w1, w2, max_iterations, relative_tolerance
    )
    return sse, w0, w1, w2, information


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def fit_rays(endpoints, directions, idx, count, w0, w1, w2, max_iterations, relative_tolerance):
    """:func:`fit_with_information` without the information: (sse, w0, w1, w2)."""
    sse, w0, w1, w2, _ = fit_with_information(
        endpoints, directions, idx, count, w0, w1, w2, max_iterations, relative_tolerance
    )
    return sse, w0, w1, w2


# Four-ray fits in straight-line code (the tetromino seeds). Loops over anchors that call fit4
# are vectorised by LLVM (no data-dependent branches); P and V are the endpoints and directions
# as (3, n) arrays so that neighbouring anchors read neighbouring memory.


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _fit4_pass(P, V, rays, w0, w1, w2):
    """:func:`gn_pass` of the four rays (same operations in the same order)."""
    acc = _ZERO10
    for t in range(4):
        k = rays[t]
        res, g0, g1, g2 = _ray_terms_at(P[0, k], P[1, k], P[2, k], V[0, k], V[1, k], V[2, k], w0, w1, w2)
        acc = _gn_add(acc, res, g0, g1, g2)
    return acc


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _fit4_step(P, V, rays, state, tolerance):
    """One iteration of :func:`_gauss_newton` (relative_tolerance ``tolerance``) with a full step, as selects
    instead of returns.

    state = (w, system, stopped, fallback) with w = (w0, w1, w2) and system = gn_pass at w;
    stopped when _gauss_newton would have returned, fallback when it would have halved the step.
    """
    w, system, stopped, fallback = state
    sse, a00, a01, a02, a11, a12, a22, b0, b1, b2 = system
    d0, d1, d2, ok = solve_sym3(a00, a01, a02, a11, a12, a22, b0, b1, b2)
    stop_now = (not ok) | (not (d0 * b0 + d1 * b1 + d2 * b2 > tolerance * sse))
    trial_w = (w[0] - d0, w[1] - d1, w[2] - d2)
    trial = _fit4_pass(P, V, rays, trial_w[0], trial_w[1], trial_w[2])
    active = (not stopped) & (not stop_now)
    fallback = fallback | (active & (not (trial[0] <= sse)))
    accept = active & (trial[0] <= sse)
    w = trial_w if accept else w
    system = trial if accept else system
    tiny = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) <= 1e-15 * np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    return w, system, stopped | stop_now | fallback | (accept & tiny), fallback


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def fit4(P, V, k0, k1, k2, k3, tolerance=FIT_RELATIVE_TOLERANCE):
    """:func:`fit_rays` of the rays k0..k3 from the algebraic start, in straight-line code (relative_tolerance
    ``tolerance``).

    Runs the algebraic start and up to three Gauss-Newton iterations exactly as :func:`fit_with_information` would
    (most seed fits converge within three; the rest go to the general fit, which a fourth
    vectorised iteration would not save).
    Returns (sse, done): when done, sse is bit-identical to fit_rays's; done is False when fit_with_information
    would go on (more iterations, a halved step) or the set is degenerate: call fit_rays then.
    """
    rays = (k0, k1, k2, k3)
    acc = _ZERO9  # _linear_init: range-weighted algebraic fit
    for t in range(4):
        acc = _init_add(acc, P[0, rays[t]], P[1, rays[t]], P[2, rays[t]])
    w0, w1, w2, ok = solve_sym3(acc[0], acc[1], acc[2], acc[3], acc[4], acc[5], acc[6], acc[7], acc[8])
    system = _fit4_pass(P, V, rays, w0, w1, w2)
    good = ok & np.isfinite(system[0])
    state = ((w0, w1, w2), system, False, False)
    state = _fit4_step(P, V, rays, state, tolerance)  # written out three times: LLVM vectorises the
    state = _fit4_step(P, V, rays, state, tolerance)  # caller's loop over anchors only when no loop is left
    state = _fit4_step(P, V, rays, state, tolerance)
    return state[1][0], good & state[2] & (not state[3])


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _fit_groups(
    endpoints,
    directions,
    members,
    starts,
    bounds,
    max_iterations,
    relative_tolerance,
    out_w,
    out_sse,
    out_info,
    sigmas,
    out_metric_sse,
):
    """Fit every group g = members[starts[g]:starts[g+1]] exactly; the groups' runs ``bounds``
    (chunks.group_chunks) in parallel. With ``sigmas`` (one per ray; an empty array: none), also each
    fitted group's SSE in metres (:func:`_metric_sse`) into out_metric_sse (an unfitted one keeps its sse)."""
    for c in nb.prange(len(bounds) - 1):
        for g in range(bounds[c], bounds[c + 1]):
            idx = members[starts[g] : starts[g + 1]]
            sse, w0, w1, w2, information = fit_with_information(
                endpoints, directions, idx, len(idx), np.nan, np.nan, np.nan, max_iterations, relative_tolerance
            )
            out_sse[g] = sse
            out_w[g, 0] = w0
            out_w[g, 1] = w1
            out_w[g, 2] = w2
            for i in range(6):
                out_info[g, i] = information[i]
            if len(sigmas):
                fitted = np.isfinite(w0) and np.isfinite(w1) and np.isfinite(w2)
                out_metric_sse[g] = _metric_sse(endpoints, directions, sigmas, idx, w0, w1, w2) if fitted else sse


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _metric_sse(endpoints, directions, sigmas, idx, w0, w1, w2):
    """SSE (m^2) of the plane w of the rays idx from their residuals times sigma_k, summed in idx's order.

    The dot products are summed as (0 + 2) + 1, the order of the np.einsum that fit_pixel_groups's
    residual image uses, so that both give the same sse bit for bit.
    """
    total = 0.0
    for k in idx:
        along_p = (endpoints[k, 0] * w0 + endpoints[k, 2] * w2) + endpoints[k, 1] * w1
        along_v = (directions[k, 0] * w0 + directions[k, 2] * w2) + directions[k, 1] * w1
        residual = (along_p - 1.0) / along_v * sigmas[k]
        total += residual * residual
    return total


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PlaneFit:
    """One maximum-likelihood plane fit, in the input frame.

    Attributes:
        normal: unit normal facing the mean ray start. offset: d with ``normal . x = d`` (m).
        sse: radial SSE (m^2). rmse: sqrt(sse / count) (m). count: number of rays.
        covariance: 3x3 covariance of the closest-point vector ``offset * normal`` (m^2).
        residuals: ``(count,)`` radial residuals ``r_k - rhat_k`` (m).
    """

    normal: np.ndarray
    offset: float
    sse: float
    rmse: float
    count: int
    covariance: np.ndarray
    residuals: np.ndarray


def _planes_from_w(w: np.ndarray, center: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normals facing the internal origin and offsets in the input frame, from internal ``(J, 3)`` w."""
    norm = np.linalg.norm(w, axis=1)
    normals = -w / norm[:, None]
    return normals, normals @ center - 1.0 / norm


def _closest_point_covariances(
    w: np.ndarray, center: np.ndarray, info6: np.ndarray, sse: np.ndarray, counts: np.ndarray
) -> np.ndarray:
    """Covariances ``(J, 3, 3)`` of d*n (input frame) from Cov(w) = sigma^2 (sum g g^T)^-1, sigma^2 = sse/(count-3).

    NaN for a plane whose information matrix is singular.
    """
    info = info6[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(-1, 3, 3)
    dof = np.maximum(counts - 3, 1)
    inv_info = np.full_like(info, np.nan)
    try:
        inv_info[:] = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        for j in range(len(info)):
            try:
                inv_info[j] = np.linalg.inv(info[j])
            except np.linalg.LinAlgError:
                pass
    cov_w = (sse / dof)[:, None, None] * inv_info
    norm = np.linalg.norm(w, axis=1)
    normal, offset = _planes_from_w(w, center)
    # d n / d w (symmetric), gradient of d w.r.t. w (d/dw of -1/|w| is -n/|w|^2), d (d n) / d w
    d_normal = -(np.eye(3) - normal[:, :, None] * normal[:, None, :]) / norm[:, None, None]
    d_offset = d_normal @ center - normal / norm[:, None] ** 2
    jac = normal[:, :, None] * d_offset[:, None, :] + offset[:, None, None] * d_normal
    cov = jac @ cov_w @ jac.transpose(0, 2, 1)
    return 0.5 * (cov + cov.transpose(0, 2, 1))


def fit_plane(points: np.ndarray, origins: np.ndarray | None = None) -> PlaneFit:
    """Maximum-likelihood plane through measured endpoints under radial noise.

    Args:
        points: ``(N, 3)`` measured endpoints (m), N >= 3, all finite.
        origins: ray starts: None (the coordinate origin), ``(3,)`` or ``(N, 3)``.

    Returns:
        The exact minimiser of the sum of squared ray-length residuals, with its covariance.

    Raises:
        ValueError: bad shapes, non-finite points, fewer than 3 rays or a degenerate (collinear) set.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f'points must be (N, 3); got shape {pts.shape}')
    if len(pts) < 3:
        raise ValueError(f'a plane needs at least 3 rays; got {len(pts)}')
    if origins is not None:
        org = np.asarray(origins, dtype=np.float64)
        if org.shape == (3,):
            org = np.broadcast_to(org, pts.shape)
        if org.shape != pts.shape:
            raise ValueError(f'origins must be None, (3,) or (N, 3) like points; got shape {org.shape}')
        org = org[:, None, :]
    else:
        org = None
    scan = make_ray_scan(pts[:, None, :], org)
    if not scan.valid.all():
        raise ValueError(
            f'{int((~scan.valid).sum())} of {len(pts)} rays are not finite or have a length outside '
            f'{MIN_RANGE:g}..{MAX_RANGE:g} m'
        )
    planes, residuals = fit_pixel_groups(scan, np.zeros(len(pts), np.int64), min_plane_points=3)
    if planes.num_planes != 1 or not np.isfinite(planes.sse[0]):
        raise ValueError('degenerate ray set: the rays do not determine a plane (collinear endpoints?)')
    return PlaneFit(
        normal=planes.normals[0],
        offset=float(planes.offsets[0]),
        sse=float(planes.sse[0]),
        rmse=float(planes.rmse[0]),
        count=int(planes.point_counts[0]),
        covariance=planes.covariances[0],
        residuals=residuals[:, 0].copy(),
    )


def fit_pixel_groups(
    scan: RayScan,
    plane_ids: np.ndarray,
    *,
    min_plane_points: int,
    residuals: bool = True,
    sigmas: np.ndarray | None = None,
    **meta,
) -> tuple[PlaneSet, np.ndarray | None]:
    """Fit every group of pixels sharing a plane id >= 0 (ids < 0: no plane).

    Groups smaller than ``min_plane_points`` become no plane. Planes are numbered 1..J by
    decreasing size (ties: first pixel in row-major order). Returns the PlaneSet and an
    ``(H, W)`` image of radial residuals (NaN where no plane; None when ``residuals`` is False).

    With ``sigmas`` (the rays' range noise, m), the scan's directions are scaled by them (a sensor
    model): the fits minimise the normalised residuals, the covariances follow from that weighted
    fit, and sse, rmse and the residual image are in metres again.
    """
    planes, residual_image, _ = fit_pixel_groups_with_members(
        scan, plane_ids, min_plane_points=min_plane_points, residuals=residuals, sigmas=sigmas, **meta
    )
    return planes, residual_image


def fit_pixel_groups_with_members(
    scan: RayScan,
    plane_ids: np.ndarray,
    *,
    min_plane_points: int,
    residuals: bool,
    sigmas: np.ndarray | None,
    **meta,
) -> tuple[PlaneSet, np.ndarray | None, tuple[np.ndarray, np.ndarray]]:
    """:func:`fit_pixel_groups`, and the planes' pixels grouped by plane in pixel order (members, starts
    (J + 1,)): what chunks.plane_members of the labels gives, from the fits' own grouping."""
    height, width = scan.height, scan.width
    ids = np.where(scan.valid, plane_ids, -1).astype(np.int64)
    if ids.size and ids.max() >= scan.size:  # ids beyond the pixel count (labels): renumber them
        labelled = ids >= 0
        ids[labelled] = np.unique(ids[labelled], return_inverse=True)[1]
    counts, first_pixel = _id_counts(ids)
    kept = np.flatnonzero(counts >= max(int(min_plane_points), 1))
    order = kept[np.lexsort((first_pixel[kept], -counts[kept]))]  # size desc, then first pixel asc
    n_planes = len(order)
    if n_planes == 0:
        empty_residuals = np.full((height, width), np.nan) if residuals else None
        return PlaneSet.empty((height, width), **meta), empty_residuals, (np.empty(0, np.int64), np.zeros(1, np.int64))
    rank = np.full(scan.size, -1, np.int64)
    rank[order] = np.arange(n_planes)
    point_counts = counts[order]
    starts = np.zeros(n_planes + 1, np.int64)
    starts[1:] = np.cumsum(point_counts)
    members = np.empty(starts[-1], np.int64)
    labels = np.empty(scan.size, np.int32)
    sums = np.empty((n_planes, 3))
    _group_members(ids, rank, starts, scan.endpoints, members, labels, sums)
    out_w = np.empty((n_planes, 3))
    out_sse = np.empty(n_planes)
    out_info = np.empty((n_planes, 6))
    metric_in_fits = sigmas is not None and not residuals  # the sse in metres again, in the fits' pass
    out_metric_sse = np.empty(n_planes if metric_in_fits else 0)
    _fit_groups(
        scan.endpoints,
        scan.directions,
        members,
        starts,
        group_chunks(point_counts),
        FIT_MAX_ITERATIONS,
        FIT_RELATIVE_TOLERANCE,
        out_w,
        out_sse,
        out_info,
        np.ascontiguousarray(sigmas, dtype=np.float64) if metric_in_fits else np.empty(0),
        out_metric_sse,
    )
    centroids = sums / point_counts[:, None] + scan.center
    normals = np.full((n_planes, 3), np.nan)
    offsets = np.full(n_planes, np.nan)
    covariances = np.full((n_planes, 3, 3), np.nan)
    plane_fitted = np.isfinite(out_w).all(axis=1)
    fitted = np.flatnonzero(plane_fitted)
    residual_image = np.full(scan.size, np.nan) if residuals else None
    if len(fitted):
        w = out_w[fitted]
        normals[fitted], offsets[fitted] = _planes_from_w(w, scan.center)
        covariances[fitted] = _closest_point_covariances(
            w, scan.center, out_info[fitted], out_sse[fitted], point_counts[fitted]
        )
        if residual_image is not None:
            member_plane = np.repeat(np.arange(n_planes), point_counts)
            on_fitted = plane_fitted[member_plane]
            idx = members[on_fitted]
            w_of_pixel = out_w[member_plane[on_fitted]]
            residual_image[idx] = (np.einsum('ij,ij->i', scan.endpoints[idx], w_of_pixel) - 1.0) / np.einsum(
                'ij,ij->i', scan.directions[idx], w_of_pixel
            )
    sse = out_metric_sse if metric_in_fits else out_sse.copy()
    if sigmas is not None and residual_image is not None:  # residuals in metres again
        residual_image *= sigmas
        on_plane = np.flatnonzero(labels > 0)
        metric = np.bincount(labels[on_plane] - 1, weights=residual_image[on_plane] ** 2, minlength=n_planes)
        sse = np.where(plane_fitted, metric, out_sse)
    planes = PlaneSet(
        labels=labels.reshape(height, width),
        normals=normals,
        offsets=offsets,
        centroids=centroids,
        point_counts=point_counts,
        sse=sse,
        rmse=np.sqrt(sse / point_counts),
        covariances=covariances,
        **meta,
    )
    residual_image = None if residual_image is None else residual_image.reshape(height, width)
    return planes, residual_image, (members, starts)


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _id_counts(ids):
    """Pixel count and first pixel (row-major) of every id in 0..len(ids)-1 (ids < 0 ignored)."""
    n = len(ids)
    counts = np.zeros(n, np.int64)
    first = np.full(n, n, np.int64)
    for k in range(n):
        g = ids[k]
        if g >= 0:
            if counts[g] == 0:
                first[g] = k
            counts[g] += 1
    return counts, first


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _group_members(ids, rank, starts, endpoints, members, labels, sums):
    """Members of plane r in members[starts[r]:starts[r+1]] (row-major order), labels (r + 1; 0 for
    no plane) and the sum of each plane's endpoints, for the plane ranks ``rank[id]`` (-1: none)."""
    fill = starts[:-1].copy()
    sums[:] = 0.0
    for k in range(len(ids)):
        r = rank[ids[k]] if ids[k] >= 0 else -1
        labels[k] = r + 1
        if r >= 0:
            members[fill[r]] = k
            fill[r] += 1
            for c in range(3):
                sums[r, c] += endpoints[k, c]


@dataclass(frozen=True)
class LabeledPlanes:
    """Exact plane fits of a given labelling.

    Attributes:
        planes: the PlaneSet (labels renumbered 1..J by size).
        label_ids: ``(J,)`` the original label of each plane.
        residuals: ``(H, W)`` radial residual of every pixel of a plane (m), NaN elsewhere.
    """

    planes: PlaneSet
    label_ids: np.ndarray
    residuals: np.ndarray


def fit_labeled_planes(
    points: np.ndarray,
    labels: np.ndarray,
    *,
    origins: np.ndarray | None = None,
    min_plane_points: int = 4,
    ignore_labels_below: int = 1,
) -> LabeledPlanes:
    """Fit one maximum-likelihood plane per label of an organized scan.

    Args:
        points: ``(H, W, 3)`` endpoints (m), NaN = no return.
        labels: ``(H, W)`` integer labels; labels below ``ignore_labels_below`` are not planes.
        origins: ray starts (None, ``(3,)`` or ``(H, W, 3)``).
        min_plane_points: smaller labels are reported as no plane.
    """
    scan = make_ray_scan(points, origins)
    lab = np.asarray(labels)
    if lab.shape != (scan.height, scan.width):
        raise ValueError(f'labels must have the grid shape {(scan.height, scan.width)}; got {lab.shape}')
    if not np.issubdtype(lab.dtype, np.integer):
        if not np.all(np.isfinite(lab)) or not np.all(lab == np.round(lab)):
            raise ValueError('labels must be integers')
        lab = lab.astype(np.int64)
    flat = lab.reshape(-1).astype(np.int64)
    ids = np.where(flat >= ignore_labels_below, flat, -1)
    planes, residuals = fit_pixel_groups(scan, ids, min_plane_points=min_plane_points)
    label_ids = np.zeros(planes.num_planes, np.int64)
    plane_labels = planes.labels.reshape(-1)
    mask = plane_labels > 0
    label_ids[plane_labels[mask] - 1] = flat[mask]
    return LabeledPlanes(planes=planes, label_ids=label_ids, residuals=residuals)
