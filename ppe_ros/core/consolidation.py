"""Whole surfaces: consolidate the greedy's planes into one plane per physical planar surface.

Pure numpy/numba; no ROS import.

The model. A physical planar surface is a plane up to a smooth deviation (flatness, the sensor's
systematic errors: per-beam range biases and angle errors, depth distortion) whose RMS distance
from the plane, measured along the normal, is at most the *surface tolerance* tau (metres). Two
pieces A and B are the same surface when

* they are *candidates*: they touch in the grid (4-neighbours), or, unless ``connected_only``,
  they are seen on either side of an occluder: along a grid row or column, every ray between a
  pixel of A and a pixel of B has no return or ends in front of the plane of the piece it leads
  to (by more than 2 tau plus 2 sigma of that ray), over at most ``max_gap`` pixels; and
* the orthogonal least-squares plane U of their union lies within tau RMS of each piece's own
  plane over that piece's points:
  ``dev(P, U)^2 = mean_P dist_U(p)^2 - s_P^2 <= t^2`` for P = A and P = B, with
  ``t^2 = tau^2 + lambda^2 min(max(s_A^2, s_B^2), max(sigma_A^2, sigma_B^2))``: ``s_P^2 =
  mean_P dist_P(p)^2`` is a piece's scatter about its own plane and ``sigma_P^2`` the mean range
  variance of its rays by the noise model. (lambda, ``noise_factor``: a deviation between two
  pieces' planes that is small against the noise their points show is not significant, so the
  tolerance grows with the noise, as a depth camera's does with depth; capped by the noise model,
  so that a merged surface does not widen its own tolerance; 0 for a constant tau); and
* the two pieces' own planes meet: along U's normal, measured at A's mean (B's plane there) or at
  B's mean (A's plane there), whichever is smaller, they are at most ``kappa t`` apart (kappa,
  ``step_factor`` >= 1; 1 by default). Without it a step between two side-by-side pieces (a kerb
  beside the road) would pass, the union's plane tilting to split it. A plane extrapolated to the
  other piece's mean also carries the pieces' tilt (two halves of a cambered road 2 deg apart, 5 m
  from each other, are 5 cm apart there), which kappa > 1 admits while a kerb's step stays above it.

``dev(A, U)^2 N_A + dev(B, U)^2 N_B`` is the union's increase of the sum of squared point-to-plane
distances, so the test is the paper's merge increment divided per point and per piece instead of
summed: a merge of two large, nearly coplanar pieces costs about ``N delta^2`` in the paper's error,
but only ``delta^2`` here, which is why large surfaces stay whole while a kerb (a 12 cm step), a
window recessed 10 cm, a ramp at 5 deg or two walls at 90 deg stay apart (their deviation is far
above a tau of a few cm).

*Large surfaces* (``large_surface_points``, 0: off; never with ``connected_only``): after the merges, a
second round takes the surfaces as pieces, finds their candidate pairs the same way but across
occluded gaps of any length along a row or column (a floor behind a wide piece of furniture, a wall
behind a cupboard), keeps the pairs of which at least one surface has ``large_surface_points`` rays or
more, and merges them cheapest first with the same test. A large surface is seen well enough that a
coplanar piece beyond an occluder is its continuation; small coplanar surfaces (two cushions at one
height) stay apart unless they are within ``max_gap``.

The pass merges candidate pairs greedily, cheapest first (cost: the largest of the three tests'
squared ratios to their tolerance, ties by
the smaller then the larger piece id), re-valuing a merged piece's pairs with all the neighbours of
both pieces, until no admissible pair is left. Candidate pairs are found once, from the greedy's
pieces. Moments (count, sums, sums of products) make every valuation O(1); a lower bound of the step
test without the union's eigen solve (:func:`_step_bound`) settles about nine in ten of the
inadmissible pairs of a lidar sweep.
:func:`consolidate_reference` (test/reference_consolidation.py) is the brute-force definition the
kernel is tested against.
"""

from __future__ import annotations

from collections.abc import Callable

import numba as nb
import numpy as np

from ppe_ros.core.scan import RayScan
from ppe_ros.core.sensor import check_step_factor, is_whole_number
from ppe_ros.core.thread_pool import SharedThreadPool, run_tasks
from ppe_ros.core.work_memory import WorkMemory

#: Largest gap (pixels along a row or column) an occluder may cover between two pieces of a surface.
DEFAULT_MAX_GAP = 64


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _add_ray(mom, g, endpoints, k, sigma):
    """Add ray k to row g of (K, 11) moments: count, x y z, xx xy xz yy yz zz of its endpoint, sigma^2."""
    x = endpoints[k, 0]
    y = endpoints[k, 1]
    z = endpoints[k, 2]
    mom[g, 0] += 1.0
    mom[g, 1] += x
    mom[g, 2] += y
    mom[g, 3] += z
    mom[g, 4] += x * x
    mom[g, 5] += x * y
    mom[g, 6] += x * z
    mom[g, 7] += y * y
    mom[g, 8] += y * z
    mom[g, 9] += z * z
    mom[g, 10] += sigma * sigma


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _piece_moments(ids, endpoints, sigmas, n_pieces):
    """(K, 11) moments of each piece: count, sum x y z, sum xx xy xz yy yz zz (internal frame, m), sum sigma^2."""
    mom = np.zeros((n_pieces, 11))
    for k in range(len(ids)):
        g = ids[k]
        if g < 0:
            continue
        _add_ray(mom, g, endpoints, k, sigmas[k])
    return mom


#: Newton steps :func:`_smallest_root_newton` takes at most before it gives up (a nearly repeated root).
_NEWTON_STEPS = 8


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _smallest_root_newton(a00, a01, a02, a11, a12, a22):
    """Smallest root of det(A - x I) = 0 for a symmetric positive semi-definite 3x3 A, by Newton steps
    from x = 0 on x^3 - c2 x^2 + c1 x - c0 (below its inflection point c2 / 3, where the smallest root
    lies, the cubic is increasing and concave, so from below the root the steps approach it without
    overshooting; a root that rounding put just below 0 is passed once, then approached from below);
    NaN if _NEWTON_STEPS steps do not settle to 1e-15 of the trace."""
    c2 = a00 + a11 + a22
    c1 = a00 * a11 + a00 * a22 + a11 * a22 - a01 * a01 - a02 * a02 - a12 * a12
    c0 = a00 * (a11 * a22 - a12 * a12) - a01 * (a01 * a22 - a12 * a02) + a02 * (a01 * a12 - a11 * a02)
    x = 0.0
    for _ in range(_NEWTON_STEPS):
        slope = (3.0 * x - 2.0 * c2) * x + c1
        if not slope > 0.0:
            return np.nan
        step = (((x - c2) * x + c1) * x - c0) / slope
        x -= step
        if abs(step) <= 1e-15 * c2:
            return x
    return np.nan


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _smallest_eigen(a00, a01, a02, a11, a12, a22):
    """Smallest eigenvalue and its unit eigenvector (value, n0, n1, n2) of a symmetric 3x3 matrix.

    The eigenvalue by :func:`_smallest_root_newton` (the scatter of a piece of a plane: a well separated
    smallest value, 2-3 steps), else by the trigonometric solution (a repeated smallest value); the
    eigenvector is the largest cross product of two rows of A - value I (they span its orthogonal
    complement). A repeated smallest eigenvalue gives one of its eigenvectors.
    """
    q = (a00 + a11 + a22) / 3.0
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    if p2 <= 1e-300:
        return q, 0.0, 0.0, 1.0
    value = _smallest_root_newton(a00, a01, a02, a11, a12, a22)
    if not np.isfinite(value):
        p = np.sqrt(p2 / 6.0)
        b00, b11, b22 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p
        b01, b02, b12 = a01 / p, a02 / p, a12 / p
        det = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
        phi = np.arccos(min(max(det / 2.0, -1.0), 1.0)) / 3.0
        value = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)  # the smallest of the three
    r00, r11, r22 = a00 - value, a11 - value, a22 - value
    # rows (r00 a01 a02), (a01 r11 a12), (a02 a12 r22): their three cross products
    x0, x1, x2 = a01 * a12 - a02 * r11, a02 * a01 - r00 * a12, r00 * r11 - a01 * a01
    y0, y1, y2 = a01 * r22 - a02 * a12, a02 * a02 - r00 * r22, r00 * a12 - a01 * a02
    z0, z1, z2 = r11 * r22 - a12 * a12, a12 * a02 - a01 * r22, a01 * a12 - r11 * a02
    nx = x0 * x0 + x1 * x1 + x2 * x2
    ny = y0 * y0 + y1 * y1 + y2 * y2
    nz = z0 * z0 + z1 * z1 + z2 * z2
    if nx >= ny and nx >= nz:
        c0, c1, c2, norm2 = x0, x1, x2, nx
    elif ny >= nz:
        c0, c1, c2, norm2 = y0, y1, y2, ny
    else:
        c0, c1, c2, norm2 = z0, z1, z2, nz
    if not norm2 > 0.0:
        return value, 0.0, 0.0, 1.0
    inv = 1.0 / np.sqrt(norm2)
    return value, c0 * inv, c1 * inv, c2 * inv


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _scatter(m):
    """Mean (3) and per-point scatter (6: xx xy xz yy yz zz) of moments m (count, sums, sums of products)."""
    inv = 1.0 / m[0]
    m0, m1, m2 = m[1] * inv, m[2] * inv, m[3] * inv
    return (m0, m1, m2), (
        m[4] * inv - m0 * m0,
        m[5] * inv - m0 * m1,
        m[6] * inv - m0 * m2,
        m[7] * inv - m1 * m1,
        m[8] * inv - m1 * m2,
        m[9] * inv - m2 * m2,
    )


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _union_scatter(mom, a, b):
    """:func:`_scatter` of the moments mom[a] + mom[b] (rows of (K, 11) moments), without allocating their sum."""
    m_a, m_b = mom[a], mom[b]
    inv = 1.0 / (m_a[0] + m_b[0])
    m0, m1, m2 = (m_a[1] + m_b[1]) * inv, (m_a[2] + m_b[2]) * inv, (m_a[3] + m_b[3]) * inv
    return (m0, m1, m2), (
        (m_a[4] + m_b[4]) * inv - m0 * m0,
        (m_a[5] + m_b[5]) * inv - m0 * m1,
        (m_a[6] + m_b[6]) * inv - m0 * m2,
        (m_a[7] + m_b[7]) * inv - m1 * m1,
        (m_a[8] + m_b[8]) * inv - m1 * m2,
        (m_a[9] + m_b[9]) * inv - m2 * m2,
    )


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _plane_of(m, out):
    """The orthogonal LS plane of moments m into out (13): mean (3), scatter (6), own (the smallest
    eigenvalue, >= 0: the mean squared distance from the plane), unit normal (3); normal returned."""
    mean, sc = _scatter(m)
    value, n0, n1, n2 = _smallest_eigen(sc[0], sc[1], sc[2], sc[3], sc[4], sc[5])
    out[0], out[1], out[2] = mean
    out[3], out[4], out[5], out[6], out[7], out[8] = sc
    out[9] = max(value, 0.0)
    out[10], out[11], out[12] = n0, n1, n2
    return n0, n1, n2


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _mean_square_distance(m0, m1, m2, s00, s01, s02, s11, s12, s22, n0, n1, n2, c0, c1, c2):
    """Mean squared distance (m^2) of points with mean m and per-point scatter s (xx xy xz yy yz zz)
    from the plane with unit normal n through c."""
    q = n0 * n0 * s00 + n1 * n1 * s11 + n2 * n2 * s22 + 2.0 * (n0 * n1 * s01 + n0 * n2 * s02 + n1 * n2 * s12)
    offset = n0 * (m0 - c0) + n1 * (m1 - c1) + n2 * (m2 - c2)
    return q + offset * offset


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _deviation(piece, n0, n1, n2, c0, c1, c2):
    """dev^2 (m^2) of a piece (its _plane_of row) from the plane with unit normal n through c: the mean
    squared distance of its points from that plane less that from its own plane."""
    square = _mean_square_distance(
        piece[0], piece[1], piece[2], piece[3], piece[4], piece[5], piece[6], piece[7], piece[8], n0, n1, n2, c0, c1, c2
    )
    return max(square - piece[9], 0.0)


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _union_deviation(mom, plane, a, b, tau2, noise_factor2):
    """The deviation test of pieces A and B (rows a, b of moments and _plane_of rows): (max dev(P, U)^2 over
    P = A, B, t^2, and U's unit normal u0, u1, u2), U the union's LS plane, t^2 = tau^2 + lambda^2
    min(max(s_A^2, s_B^2), max(sigma_A^2, sigma_B^2))."""
    mean_u, sc = _union_scatter(mom, a, b)
    _, u0, u1, u2 = _smallest_eigen(sc[0], sc[1], sc[2], sc[3], sc[4], sc[5])
    plane_a, plane_b = plane[a], plane[b]
    deviation = max(
        _deviation(plane_a, u0, u1, u2, mean_u[0], mean_u[1], mean_u[2]),
        _deviation(plane_b, u0, u1, u2, mean_u[0], mean_u[1], mean_u[2]),
    )
    return deviation, _tolerance2(mom, plane, a, b, tau2, noise_factor2), u0, u1, u2


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _tolerance2(mom, plane, a, b, tau2, noise_factor2):
    """t^2 (m^2) of pieces A and B: tau^2 + lambda^2 min(max(s_A^2, s_B^2), max(sigma_A^2, sigma_B^2))."""
    scatter = min(max(plane[a, 9], plane[b, 9]), max(mom[a, 10] / mom[a, 0], mom[b, 10] / mom[b, 0]))
    return tau2 + noise_factor2 * scatter


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _merge_cost(mom, plane, a, b, tau2, noise_factor2, step_factor2):
    """Cost of joining pieces A and B (admissible: <= 1): the largest of dev(P, U)^2 / t_P^2 for P = A, B
    and step^2 / (kappa t)^2 (kappa^2: step_factor2), with
    t^2 = tau^2 + lambda^2 min(max(s_A^2, s_B^2), max(sigma_A^2, sigma_B^2))
    (s_P^2: P's mean squared distance from its own plane; sigma_P^2: the mean range variance of its rays).

    U is the union's LS plane; step is the smaller of the two distances along U's normal between the
    planes of A and B measured at A's mean and at B's mean (each piece's own plane is best known at
    its mean). mom: (K, 11) moments; plane: their _plane_of rows (K, 13); a, b: the pieces' rows (indices,
    not row views: a view of a row per call costs a reference count increment and decrement).
    """
    deviation, allowed, u0, u1, u2 = _union_deviation(mom, plane, a, b, tau2, noise_factor2)
    plane_a, plane_b = plane[a], plane[b]
    # at each piece's mean its own plane is at 0: the step there is the other plane's distance
    step_at_a = _along_normal(plane_b, plane_a[0], plane_a[1], plane_a[2], u0, u1, u2)
    step_at_b = _along_normal(plane_a, plane_b[0], plane_b[1], plane_b[2], u0, u1, u2)
    step2 = min(step_at_a * step_at_a, step_at_b * step_at_b)
    return max(deviation / allowed, step2 / (step_factor2 * allowed))


#: A pair whose step bound (:func:`_step_bound`) exceeds 1 by more than this is inadmissible without its
#: exact cost; the margin covers rounding (the bound and the cost are computed differently).
_BOUND_MARGIN = 1e-6


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _step_bound(mom, plane, a, b, tau2, noise_factor2, step_factor2):
    """A lower bound of the step part of :func:`_merge_cost` (step^2 / (kappa t)^2) without the union's
    normal u: the step at A's mean is ``n_B . (c_B - c_A) / (n_B . u)`` and ``|n_B . u| <= 1`` (and so at
    B's mean), so each step is at least the other plane's distance from the piece's mean."""
    plane_a, plane_b = plane[a], plane[b]
    d0, d1, d2 = plane_b[0] - plane_a[0], plane_b[1] - plane_a[1], plane_b[2] - plane_a[2]
    at_a = plane_b[10] * d0 + plane_b[11] * d1 + plane_b[12] * d2
    at_b = plane_a[10] * d0 + plane_a[11] * d1 + plane_a[12] * d2
    return min(at_a * at_a, at_b * at_b) / (step_factor2 * _tolerance2(mom, plane, a, b, tau2, noise_factor2))


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _merge_cost_or_bound(mom, plane, a, b, tau2, noise_factor2, step_factor2):
    """:func:`_merge_cost` where it may be admissible (<= 1); a value above 1 (a lower bound of it) where
    :func:`_step_bound` already shows that it is not. The merge loops only compare a cost with 1 and order
    the admissible ones, so they take the same merges with either."""
    bound = _step_bound(mom, plane, a, b, tau2, noise_factor2, step_factor2)
    if bound > 1.0 + _BOUND_MARGIN:
        return bound
    return _merge_cost(mom, plane, a, b, tau2, noise_factor2, step_factor2)


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _along_normal(piece, x0, x1, x2, u0, u1, u2):
    """Where the line x + t u meets the piece's plane: t (m); inf if parallel."""
    n0, n1, n2 = piece[10], piece[11], piece[12]
    return (n0 * (piece[0] - x0) + n1 * (piece[1] - x1) + n2 * (piece[2] - x2)) / (n0 * u0 + n1 * u1 + n2 * u2)


def merge_cost(
    m_a: np.ndarray, m_b: np.ndarray, surface_tolerance: float, noise_factor: float = 0.0, step_factor: float = 1.0
) -> float:
    """:func:`_merge_cost` of two pieces given by their (11,) moments (see _piece_moments); <= 1: admissible."""
    mom = np.stack([np.asarray(m_a, np.float64), np.asarray(m_b, np.float64)])
    plane = np.empty((2, 13))
    _plane_of(mom[0], plane[0])
    _plane_of(mom[1], plane[1])
    return float(
        _merge_cost(mom, plane, 0, 1, float(surface_tolerance) ** 2, float(noise_factor) ** 2, float(step_factor) ** 2)
    )


# not inline='always': numba's IR inlining of a function whose arrays stay live across its early
# returns leaves a reference count increment and decrement of every array argument per call (5x slower)
@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _bridges(ids, endpoints, directions, ranges, sigmas, k, normals, means, g, tau, connected_only):
    """True if ray k may lie between two pieces of the surface of piece g (plane normals[g], means[g]).

    It may if it has no plane and ends on the plane (within 2 tau + 2 sigma_k |n . v_k| along the
    normal), or, unless connected_only, if it has no return or ends in front of the plane (on the
    sensor's side) by more than that: an occluder.
    """
    if not np.isfinite(ranges[k]):
        return not connected_only
    r = ranges[k]
    n0, n1, n2 = normals[g, 0], normals[g, 1], normals[g, 2]
    along = n0 * directions[k, 0] + n1 * directions[k, 1] + n2 * directions[k, 2]
    margin = 2.0 * tau + 2.0 * sigmas[k] * abs(along)
    height = (
        n0 * (endpoints[k, 0] - means[g, 0])
        + n1 * (endpoints[k, 1] - means[g, 1])
        + n2 * (endpoints[k, 2] - means[g, 2])
    )
    if abs(height) <= margin:
        return ids[k] < 0
    if connected_only:
        return False
    # the sensor's side: the ray start's side of the plane (the endpoint minus the ray)
    start_height = height - r * along
    return height * start_height > 0.0 and abs(start_height) > abs(height)


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _candidate_pairs(
    ids,
    endpoints,
    directions,
    ranges,
    sigmas,
    no_return,
    height,
    width,
    normals,
    means,
    tau,
    max_gap,
    connected_only,
    first,
    last,
):
    """Candidate pairs (a < b) found from the pixels first..last-1 (the later piece b of a pair is on
    one of them), as an (m, 2) array, possibly with repeats (see the module docstring). no_return is
    :func:`_no_return_runs` of the grid."""
    touching = _touching_pairs(ids, width, first, last)
    out = np.empty((len(touching) + 16, 2), np.int64)
    out[: len(touching)] = touching
    n_out = len(touching)
    for direction in range(2):  # 0: along rows (left), 1: along columns (up)
        step = 1 if direction == 0 else width
        i = first // width
        j = first - i * width - 1
        for k in range(first, last):
            j += 1  # (i, j): the row and column of pixel k
            if j == width:
                j = 0
                i += 1
            b = ids[k]
            if b < 0:
                continue
            position = j if direction == 0 else i
            if position == 0:
                continue
            back = ids[k - step]
            if back == b:
                continue
            if back >= 0 and not _bridges(
                ids, endpoints, directions, ranges, sigmas, k - step, normals, means, b, tau, connected_only
            ):
                continue
            a = _across_gap(
                ids,
                endpoints,
                directions,
                ranges,
                sigmas,
                no_return[direction],
                k,
                step,
                1 if back < 0 else 2,  # back bridges: tested
                min(max_gap, position),
                normals,
                means,
                tau,
                connected_only,
            )
            if a >= 0:
                out, n_out = _add_pair(out, n_out, a, b)
    return out[:n_out]


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _touching_pairs(ids, width, first, last):
    """(m, 2) pairs (a < b) of distinct pieces that are 4-neighbours, b on one of the pixels first..last-1
    and a left of it or above it; a pair that the previous pixel of the same row found is not repeated."""
    out = np.empty((2 * (last - first), 2), np.int64)
    n_out = 0
    for direction in range(2):  # 0: along rows (left), 1: along columns (up)
        step = 1 if direction == 0 else width
        i = first // width
        j = first - i * width - 1
        last_a = last_b = -1
        for k in range(first, last):
            j += 1  # (i, j): the row and column of pixel k
            if j == width:
                j = 0
                i += 1
            if j == 0:
                last_a = last_b = -1
            if (j if direction == 0 else i) == 0:
                continue
            b = ids[k]
            back = ids[k - step]
            if b < 0 or back < 0 or back == b:
                continue
            a, b = min(back, b), max(back, b)
            if a != last_a or b != last_b:
                out[n_out, 0] = a
                out[n_out, 1] = b
                n_out += 1
                last_a, last_b = a, b
    return out[:n_out]


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _across_gap(
    ids, endpoints, directions, ranges, sigmas, no_return, k, step, g, reach, normals, means, tau, connected_only
):
    """The piece that pixel k's piece b is a candidate with across a gap, or -1: walking back from k by
    step, from the g-th ray back and at most reach rays back, over rays that bridge to b's plane, the
    first ray that does not bridge, if it is on a piece and every ray between bridges to that piece's
    plane too. no_return: the runs of rays without a return and a piece along the line (skipped)."""
    b = ids[k]
    while g <= reach:
        q = k - g * step
        if not connected_only and no_return[q] > 0:
            g += no_return[q]  # rays without a return bridge: skip their run
            continue
        if ids[q] == b:
            return -1
        if _bridges(ids, endpoints, directions, ranges, sigmas, q, normals, means, b, tau, connected_only):
            g += 1
            continue
        a = ids[q]
        if a >= 0 and _gap_bridges(
            ids, endpoints, directions, ranges, sigmas, no_return, q, k, step, normals, means, a, tau, connected_only
        ):
            return a
        return -1
    return -1


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _add_pair(out, n_out, a, b):
    """Append the pair (min, max) to out[:n_out] (grown when full); returns (out, n_out)."""
    if n_out == len(out):
        grown = np.empty((2 * len(out), 2), np.int64)
        grown[:n_out] = out[:n_out]
        out = grown
    out[n_out, 0] = min(a, b)
    out[n_out, 1] = max(a, b)
    return out, n_out + 1


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _gap_bridges(
    ids, endpoints, directions, ranges, sigmas, no_return, first, last, step, normals, means, g, tau, connected_only
):
    """True if every ray strictly between pixels first and last (a line of the grid) bridges to piece g's
    plane; no_return: the runs of rays without a return and a piece along that line
    (:func:`_no_return_runs`), which bridge unless connected_only, are skipped."""
    q = last - step
    while q > first:
        if not connected_only and no_return[q] > 0:
            q -= no_return[q] * step
            continue
        if not _bridges(ids, endpoints, directions, ranges, sigmas, q, normals, means, g, tau, connected_only):
            return False
        q -= step
    return True


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _no_return_runs(ranges, ids, height, width):
    """``(2, H*W)`` lengths of the runs of rays without a return (range not finite) and without a piece
    (id < 0) that end at each ray: [0] along its row (it and the rays left of it), [1] along its column
    (it and the rays above it); 0 for any other ray. Such a ray bridges any two pieces (_bridges)
    unless connected_only."""
    runs = np.zeros((2, height * width), np.int32)
    for k in range(height * width):
        if np.isfinite(ranges[k]) or ids[k] >= 0:
            continue
        runs[0, k] = 1 + (runs[0, k - 1] if k % width > 0 else 0)
        runs[1, k] = 1 + (runs[1, k - width] if k >= width else 0)
    return runs


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _find(parent, x):
    while parent[x] != x:
        parent[x] = parent[parent[x]]
        x = parent[x]
    return x


# The merge loop's queue: a binary min-heap of candidate pairs (edges) in lexicographic order of
# (cost, a, b), indexed by edge: where[e] is edge e's position (-1: not queued), so that a re-valued
# pair's entry is re-keyed in place and an inadmissible or dead one removed. Each live pair of pieces
# then has at most one entry and the loop pops merges only (no stale entries). Arrays: hkey (costs),
# hpair (m, 2) (a, b), hedge (edge ids), where (m,).


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _heap_before(hkey, hpair, i, key, a, b):
    """Heap entry i before the entry (key, a, b): (cost, a, b) in lexicographic order."""
    if hkey[i] != key:
        return hkey[i] < key
    if hpair[i, 0] != a:
        return hpair[i, 0] < a
    return hpair[i, 1] < b


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _heap_put(hkey, hpair, hedge, where, i, key, a, b, e):
    hkey[i] = key
    hpair[i, 0], hpair[i, 1] = a, b
    hedge[i] = e
    where[e] = i


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _heap_sift_up(hkey, hpair, hedge, where, i, key, a, b, e):
    """Put the entry (key, a, b) of edge e into the hole at i, moving the parents after it down."""
    while i > 0:
        parent = (i - 1) // 2
        if _heap_before(hkey, hpair, parent, key, a, b):
            break
        _heap_put(hkey, hpair, hedge, where, i, hkey[parent], hpair[parent, 0], hpair[parent, 1], hedge[parent])
        i = parent
    _heap_put(hkey, hpair, hedge, where, i, key, a, b, e)


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _heap_sift_down(hkey, hpair, hedge, where, size, i, key, a, b, e):
    """Put the entry (key, a, b) of edge e into the hole at i of heap[:size], moving the children before it up."""
    while True:
        child = 2 * i + 1
        if child >= size:
            break
        right = child + 1
        if right < size and _heap_before(hkey, hpair, right, hkey[child], hpair[child, 0], hpair[child, 1]):
            child = right
        if not _heap_before(hkey, hpair, child, key, a, b):
            break
        _heap_put(hkey, hpair, hedge, where, i, hkey[child], hpair[child, 0], hpair[child, 1], hedge[child])
        i = child
    _heap_put(hkey, hpair, hedge, where, i, key, a, b, e)


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _heap_fill(hkey, hpair, hedge, where, size, i, key, a, b, e):
    """Put the entry of edge e into the hole at i of heap[:size], up or down to its place."""
    if i > 0 and not _heap_before(hkey, hpair, (i - 1) // 2, key, a, b):
        _heap_sift_up(hkey, hpair, hedge, where, i, key, a, b, e)
    else:
        _heap_sift_down(hkey, hpair, hedge, where, size, i, key, a, b, e)


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _heap_set(hkey, hpair, hedge, where, size, e, key, a, b):
    """Queue edge e as (key, a, b), or re-key its entry; returns the heap's new size (room for every edge)."""
    if where[e] < 0:
        _heap_sift_up(hkey, hpair, hedge, where, size, key, a, b, e)
        return size + 1
    _heap_fill(hkey, hpair, hedge, where, size, where[e], key, a, b, e)
    return size


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _heap_remove(hkey, hpair, hedge, where, size, e):
    """Take edge e's entry (if queued) out of heap[:size]; returns the new size."""
    i = where[e]
    if i < 0:
        return size
    where[e] = -1
    size -= 1
    if i < size:  # the last entry fills the hole
        _heap_fill(hkey, hpair, hedge, where, size, i, hkey[size], hpair[size, 0], hpair[size, 1], hedge[size])
    return size


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _pair_costs(moments, pairs, tau2, noise_factor2, step_factor2):
    """_plane_of rows (K, 13) of the pieces and the _merge_cost_or_bound of every pair (m,), in blocks of
    _COST_BLOCK in parallel (each value on its own: the same for any thread count)."""
    n = moments.shape[0]
    m = pairs.shape[0]
    plane = np.empty((n, 13))
    costs = np.empty(m)
    for block in nb.prange((n + _COST_BLOCK - 1) // _COST_BLOCK):
        _plane_rows(moments, plane, block * _COST_BLOCK, min(n, (block + 1) * _COST_BLOCK))
    for block in nb.prange((m + _COST_BLOCK - 1) // _COST_BLOCK):
        _pair_cost_rows(
            moments,
            plane,
            pairs,
            block * _COST_BLOCK,
            min(m, (block + 1) * _COST_BLOCK),
            tau2,
            noise_factor2,
            step_factor2,
            costs,
        )
    return plane, costs


#: Pieces or pairs per task of _pair_costs' parallel loops.
_COST_BLOCK = 1024


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _plane_rows(moments, plane, first, stop):
    """_plane_of rows first..stop-1 of the pieces' moments into plane."""
    for x in range(first, stop):
        _plane_of(moments[x], plane[x])


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _pair_cost_rows(moments, plane, pairs, first, stop, tau2, noise_factor2, step_factor2, costs):
    """_merge_cost_or_bound of the pairs first..stop-1 into costs."""
    for e in range(first, stop):
        costs[e] = _merge_cost_or_bound(moments, plane, pairs[e, 0], pairs[e, 1], tau2, noise_factor2, step_factor2)


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _neighbour_lists(pairs, n):
    """Half-edges of the candidate pairs (m, 2) of n pieces: a linked list of neighbours per piece
    (head, tail (n,), next, other (2 m,)); half-edge 2 e + side of edge e belongs to pairs[e, side]."""
    m = pairs.shape[0]
    other = np.empty(2 * m, np.int64)
    nxt = np.full(2 * m, -1, np.int64)
    head = np.full(n, -1, np.int64)
    tail = np.full(n, -1, np.int64)
    for e in range(m):
        for side in range(2):
            h = 2 * e + side
            u = pairs[e, side]
            other[h] = pairs[e, 1 - side]
            if head[u] < 0:
                head[u] = h
            else:
                nxt[tail[u]] = h
            tail[u] = h
    return head, tail, nxt, other


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _consolidate_kernel(moments, pairs, plane_rows, costs, tau2, noise_factor2, step_factor2):
    """Greedy agglomeration of pieces (moments (K, 11), candidate pairs (m, 2) unique) -> root of each piece.

    A pair is admissible when its :func:`_merge_cost` is at most 1 (tau2 = tau^2, noise_factor2 = lambda^2,
    step_factor2 = kappa^2).
    plane_rows, costs: the pieces' _plane_of rows and the pairs' costs (:func:`_pair_costs`). The queue
    is the indexed heap above, ordered by (cost, a, b): every live pair of pieces has at most one
    candidate edge (dead[e]: a duplicate of another edge between the same two pieces, or inside one),
    which holds its latest admissible cost, so the first entry is always the next merge.
    """
    n = moments.shape[0]
    m = pairs.shape[0]
    mom = moments.copy()
    plane = plane_rows.copy()
    parent = np.arange(n)
    head, tail, nxt, other = _neighbour_lists(pairs, n)
    dead = np.zeros(m, np.bool_)
    hkey = np.empty(m)
    hpair = np.empty((m, 2), np.int64)
    hedge = np.empty(m, np.int64)
    where = np.full(m, -1, np.int64)
    size = 0
    for e in range(m):
        if costs[e] <= 1.0:
            _heap_put(hkey, hpair, hedge, where, size, costs[e], pairs[e, 0], pairs[e, 1], e)
            size += 1
    for i in range(size // 2 - 1, -1, -1):
        _heap_sift_down(hkey, hpair, hedge, where, size, i, hkey[i], hpair[i, 0], hpair[i, 1], hedge[i])
    stamp = np.full(n, -1, np.int64)
    n_merges = 0
    while size > 0:
        a, b, first = hpair[0, 0], hpair[0, 1], hedge[0]
        size = _heap_remove(hkey, hpair, hedge, where, size, first)
        dead[first] = True
        # merge b into a (a < b: the smaller id survives)
        parent[b] = a
        mom[a] += mom[b]
        _plane_of(mom[a], plane[a])
        n_merges += 1
        if head[b] >= 0:
            if head[a] < 0:
                head[a] = head[b]
            else:
                nxt[tail[a]] = head[b]
            tail[a] = tail[b]
        # re-value a's pairs with every distinct neighbour root; the list keeps one half-edge per
        # distinct neighbour (dead edges, self-loops and repeats dropped), so its length stays the degree
        h = head[a]
        head[a] = -1
        tail[a] = -1
        while h >= 0:
            following = nxt[h]
            e = h >> 1
            c = -1 if dead[e] else _find(parent, other[h])
            if c >= 0 and c != a and stamp[c] != n_merges:
                stamp[c] = n_merges
                other[h] = c
                nxt[h] = -1
                if head[a] < 0:
                    head[a] = h
                else:
                    nxt[tail[a]] = h
                tail[a] = h
                lo = min(a, c)
                hi = max(a, c)
                value = _merge_cost_or_bound(mom, plane, lo, hi, tau2, noise_factor2, step_factor2)
                if value <= 1.0:
                    size = _heap_set(hkey, hpair, hedge, where, size, e, value, lo, hi)
                else:
                    size = _heap_remove(hkey, hpair, hedge, where, size, e)
            elif c >= 0:  # a self-loop or a second edge to c: dead (its other half-edge is dropped later)
                dead[e] = True
                size = _heap_remove(hkey, hpair, hedge, where, size, e)
            h = following
    roots = np.empty(n, np.int64)
    for x in range(n):
        roots[x] = _find(parent, x)
    return roots


def _merge_pieces(
    moments: np.ndarray, pairs: np.ndarray, tau2: float, noise_factor2: float, step_factor2: float = 1.0
) -> np.ndarray:
    """The root of each piece after :func:`_consolidate_kernel` merged the pieces (moments (K, 11)) along
    their unique candidate pairs (m, 2), valued by :func:`_pair_costs`."""
    plane_rows, costs = _pair_costs(moments, pairs, tau2, noise_factor2, step_factor2)
    return _consolidate_kernel(moments, pairs, plane_rows, costs, tau2, noise_factor2, step_factor2)


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _unique_pairs(pairs, n):
    """The distinct rows of pairs (m, 2) of ids in 0..n-1, sorted by (first, second): two stable
    counting sorts (by the second id, then the first) and a pass over equal neighbours."""
    m = pairs.shape[0]
    by_second = np.empty(m, np.int64)
    order = np.empty(m, np.int64)
    start = np.zeros(n + 1, np.int64)
    for column, source, target in ((1, np.arange(m), by_second), (0, by_second, order)):
        start[:] = 0
        for e in range(m):
            start[pairs[e, column] + 1] += 1
        for g in range(n):
            start[g + 1] += start[g]
        for e in source:
            g = pairs[e, column]
            target[start[g]] = e
            start[g] += 1
    out = np.empty((m, 2), np.int64)
    n_out = 0
    for e in order:
        a = pairs[e, 0]
        b = pairs[e, 1]
        if n_out == 0 or out[n_out - 1, 0] != a or out[n_out - 1, 1] != b:
            out[n_out, 0] = a
            out[n_out, 1] = b
            n_out += 1
    return out[:n_out].copy()


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _piece_planes(moments):
    """Unit normals, means (internal frame) and scatter about the plane (m^2) of the LS planes of pieces
    given by (K, 11) moments."""
    normals = np.empty((len(moments), 3))
    means = np.empty((len(moments), 3))
    own = np.empty(len(moments))
    row = np.empty(13)
    for g in range(len(moments)):
        normals[g, 0], normals[g, 1], normals[g, 2] = _plane_of(moments[g], row)
        means[g, 0], means[g, 1], means[g, 2] = row[0], row[1], row[2]
        own[g] = row[9]
    return normals, means, own


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _dense_ids_kernel(ids, bound):
    """Dense ids of ids in -1..bound-1: (labels (K,) the present ids ascending, dense (N,) the rank of
    each pixel's id among them, -1 for -1)."""
    rank = np.full(bound, -1, np.int64)
    for k in range(len(ids)):
        if ids[k] >= 0:
            rank[ids[k]] = 0
    n_labels = 0
    for g in range(bound):
        if rank[g] == 0:
            rank[g] = n_labels
            n_labels += 1
    labels = np.empty(n_labels, np.int64)
    for g in range(bound):
        if rank[g] >= 0:
            labels[rank[g]] = g
    dense = np.empty(len(ids), np.int64)
    for k in range(len(ids)):
        dense[k] = rank[ids[k]] if ids[k] >= 0 else -1
    return labels, dense


def _dense_ids(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(labels: the distinct ids >= 0 ascending, dense: (N,) each entry's index in labels, -1 where ids < 0)."""
    bound = int(ids.max()) + 1 if ids.size else 0
    if bound <= 4 * ids.size + 16:  # ids bounded by the pixel count (the greedy's plane ids): no sort
        return _dense_ids_kernel(ids, max(bound, 0))
    uniq, dense = np.unique(ids, return_inverse=True)
    negative = int(np.searchsorted(uniq, 0))
    return uniq[negative:], np.where(ids >= 0, dense.reshape(-1) - negative, -1).astype(np.int64)


def _dense_pieces(scan: RayScan, ids: np.ndarray, sigmas: np.ndarray, min_points: int):
    """The pieces of ``ids`` (int64 >= 0; -1: none) as dense ids 0..K-1 with their moments.

    Returns (labels: (K,) the original id of each dense id, dense: (H*W,) dense id of each pixel or -1,
    moments: (K, 11), small: (K,) pieces of fewer than min_points rays, planes: _piece_planes of the
    moments, with small pieces' rows computed from a placeholder).
    """
    labels, dense = _dense_ids(ids)
    ray_sigmas = np.ascontiguousarray(np.where(np.isfinite(sigmas), sigmas, 0.0), dtype=np.float64)
    moments = _piece_moments(dense, scan.endpoints, ray_sigmas, len(labels))
    small = moments[:, 0] < min_points
    planes = _piece_planes(np.where(small[:, None], np.ones(11), moments))
    return labels, dense, moments, small, planes


def columns_wrap(scan: RayScan) -> bool:
    """True if the scan's last column is next to its first: a full revolution of a spinning lidar.

    Along each row, the angle between the rays of the last and the first column (the median over
    the rows where both returned) must be at most twice the median angle between neighbouring
    columns (a camera's or a cropped scan's first and last columns are its field of view apart;
    so are the first and last beams of a transposed sweep).
    """
    grid = (scan.height, scan.width)
    return _last_next_to_first(scan.valid.reshape(grid), scan.directions.reshape(*grid, 3))


def rows_wrap(scan: RayScan) -> bool:
    """True if the scan's last row is next to its first: a transposed revolution (one column per beam),
    by the test of :func:`columns_wrap` on the rows."""
    grid = (scan.height, scan.width)
    return _last_next_to_first(scan.valid.reshape(grid).T, scan.directions.reshape(*grid, 3).transpose(1, 0, 2))


def _last_next_to_first(valid: np.ndarray, directions: np.ndarray) -> bool:
    """:func:`columns_wrap` on a ``(rows, columns)`` validity grid and its ``(rows, columns, 3)`` unit directions."""
    if valid.shape[1] < 8 or valid.shape[0] < 1:
        return False
    steps = _reusable('neighbour_dots', valid.shape[0] * (valid.shape[1] - 1), np.float64)
    seam = _reusable('seam_dots', valid.shape[0], np.float64)
    n_steps, n_seam = _neighbour_dots(valid, directions, steps, seam)
    if n_steps < 4 or n_seam == 0:
        return False
    return _median_angle_at_least(steps[:n_steps], 0.5 * _median_angle(seam[:n_seam]))


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _neighbour_dots(valid, directions, steps, seam):
    """Cosines of the angles between the rays of neighbouring columns (both valid; row-major order)
    into steps, and between the last and the first column into seam; returns their counts. The dot
    products are summed as (0 + 2) + 1, the order of np.einsum's two-lane sum of three terms."""
    rows, columns = valid.shape
    n_steps = 0
    n_seam = 0
    for i in range(rows):
        for j in range(columns):
            if j + 1 < columns:
                if not (valid[i, j + 1] and valid[i, j]):
                    continue
                a, b = j + 1, j
            elif valid[i, columns - 1] and valid[i, 0]:
                a, b = columns - 1, 0
            else:
                continue
            cosine = (
                directions[i, a, 0] * directions[i, b, 0] + directions[i, a, 2] * directions[i, b, 2]
            ) + directions[i, a, 1] * directions[i, b, 1]
            if j + 1 < columns:
                steps[n_steps] = cosine
                n_steps += 1
            else:
                seam[n_seam] = cosine
                n_seam += 1
    return n_steps, n_seam


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _median_angle_at_least(cosines, angle):
    """``np.median(np.arccos(np.clip(cosines, -1, 1))) >= angle`` (rad) without sorting: by counting the
    angles of at least ``angle`` (cosines below cos(angle); within 1e-9 of it, by the angle itself); for an
    even count with exactly half of them counted, from the two middle angles (the largest angle not
    counted, the smallest counted)."""
    n = len(cosines)
    if n == 0:
        return False
    limit = np.cos(angle) if angle > 0.0 else 2.0  # angle <= 0: every angle counts
    at_least = 0
    counted_max = -2.0  # the largest cosine <= limit: the smallest angle counted
    uncounted_min = 2.0  # the smallest cosine > limit: the largest angle not counted
    for c in cosines:
        c = min(max(c, -1.0), 1.0)
        if c < limit - 1e-9 or (c <= limit + 1e-9 and np.arccos(c) >= angle):  # near the limit: the angle
            at_least += 1
            counted_max = max(counted_max, c)
        else:
            uncounted_min = min(uncounted_min, c)
    if n % 2 or 2 * at_least != n:
        return 2 * at_least > n
    return 0.5 * (np.arccos(uncounted_min) + np.arccos(counted_max)) >= angle


def _median_angle(cosines: np.ndarray) -> float:
    """``np.median(np.arccos(np.clip(cosines, -1, 1)))`` from the middle cosines alone (arccos decreases:
    the middle angles are those of the middle cosines); cosines (work memory) is partitioned in place."""
    n = len(cosines)
    middle = [n // 2] if n % 2 else [n // 2 - 1, n // 2]
    cosines.partition(middle)
    return float(np.median(np.arccos(np.clip(cosines[middle], -1.0, 1.0))))


#: Pixels per thread below which the candidate pairs are found in the calling thread alone.
PARALLEL_MIN_PIXELS = 8192
#: Row blocks per thread of the candidate pairs (the cost per row varies: no returns, occluders).
BLOCKS_PER_THREAD = 4

_pool = SharedThreadPool('ppe-surfaces')


def in_row_blocks(
    pairs_of_pixels: Callable[[int, int], np.ndarray], height: int, width: int, min_pixels_per_thread: int
) -> np.ndarray:
    """``pairs_of_pixels(0, height * width)``, computed as row blocks (BLOCKS_PER_THREAD per thread) taken in
    turn by numba's thread count of threads (at most one per min_pixels_per_thread pixels) and concatenated
    in block order: ``pairs_of_pixels(first, last)`` gives the (m, 2) rows found from pixels first..last-1
    (a kernel that releases the GIL), in pixel order."""
    threads = max(1, min(nb.get_num_threads(), height * width // min_pixels_per_thread))
    n_blocks = min(threads * BLOCKS_PER_THREAD, height) if threads > 1 else 1
    if n_blocks == 1:
        return pairs_of_pixels(0, height * width)
    bounds = [width * round(i * height / n_blocks) for i in range(n_blocks + 1)]
    blocks = run_tasks(lambda i: pairs_of_pixels(bounds[i], bounds[i + 1]), range(n_blocks), threads, _pool)
    return np.concatenate(blocks)


def _parallel_candidate_pairs(ids, scan: RayScan, sigmas, normals, means, tau, max_gap, connected_only) -> np.ndarray:
    """_candidate_pairs of all pixels in row blocks (:func:`in_row_blocks`; consolidate_pieces sorts and
    dedupes them)."""
    no_return = _no_return_runs(scan.ranges, ids, scan.height, scan.width)

    def block(first: int, last: int) -> np.ndarray:
        return _candidate_pairs(
            ids,
            scan.endpoints,
            scan.directions,
            scan.ranges,
            sigmas,
            no_return,
            scan.height,
            scan.width,
            normals,
            means,
            tau,
            max_gap,
            connected_only,
            first,
            last,
        )

    return in_row_blocks(block, scan.height, scan.width, PARALLEL_MIN_PIXELS)


def _unique_candidate_pairs(
    ids: np.ndarray,
    scan: RayScan,
    sigmas: np.ndarray,
    normals: np.ndarray,
    means: np.ndarray,
    tau: float,
    max_gap: int,
    connected_only: bool,
    wrap_columns: bool,
) -> np.ndarray:
    """The candidate pairs (m, 2) of the pieces ids (rows of normals and means; -1: none), with those
    across the seam of a full revolution when wrap_columns: each pair once, sorted by (a, b)."""
    pairs = _parallel_candidate_pairs(ids, scan, sigmas, normals, means, tau, max_gap, connected_only)
    if wrap_columns:
        pairs = np.concatenate([pairs, _seam_pairs(ids, scan.height, scan.width)])
    return _unique_pairs(np.ascontiguousarray(pairs), len(normals))


def _seam_pairs(ids: np.ndarray, height: int, width: int) -> np.ndarray:
    """(m, 2) pairs (a < b) of distinct pieces that touch across the seam (last column, first column)."""
    grid = ids.reshape(height, width)
    a, b = grid[:, -1], grid[:, 0]
    both = (a >= 0) & (b >= 0) & (a != b)
    return np.stack([np.minimum(a[both], b[both]), np.maximum(a[both], b[both])], axis=1).astype(np.int64)


def consolidate_pieces(
    scan: RayScan,
    piece_ids: np.ndarray,
    sigmas: np.ndarray,
    surface_tolerance: float,
    *,
    noise_factor: float = 0.0,
    connected_only: bool = False,
    max_gap: int = DEFAULT_MAX_GAP,
    wrap_columns: bool = False,
    large_surface_points: int = 0,
    step_factor: float = 1.0,
) -> np.ndarray:
    """Merge the pieces of one physical surface (see the module docstring).

    Args:
        scan: the ray model (unit directions).
        piece_ids: ``(H*W,)`` piece of each pixel (>= 0), -1 for none; pieces of fewer than 3
            pixels are left as they are.
        sigmas: ``(H*W,)`` range noise of each ray (m); NaN for invalid rays.
        surface_tolerance: tau (m), > 0.
        noise_factor: lambda: a piece may deviate by sqrt(tau^2 + lambda^2 s^2), s its RMS distance from
            its own plane (the noise the data show; a depth camera's grows with depth).
        connected_only: consider only pieces that touch in the grid.
        max_gap: the largest occluded gap (pixels) between two pieces of a surface.
        wrap_columns: the last column is next to the first (a full revolution, :func:`columns_wrap`):
            pieces that touch across that seam are candidates too.
        large_surface_points: a surface of at least this many rays also joins a coplanar surface
            across an occluded gap of any length (the second round of the module docstring); 0: off.
        step_factor: kappa >= 1: the two pieces' planes may be kappa t apart at the nearer mean (the step
            test of the module docstring); 1: t.

    Returns:
        ``(H*W,)`` surface id of each pixel (the smallest piece id of its surface), -1 for none.
    """
    tau, factor = checked_tolerances(surface_tolerance, noise_factor)
    if int(max_gap) < 1:
        raise ValueError(f'max_gap must be >= 1 pixel; got {max_gap!r}')
    large = _check_large_surface_points(large_surface_points)
    step2 = check_step_factor(step_factor) ** 2
    ids = np.ascontiguousarray(piece_ids, dtype=np.int64)
    if ids.shape != (scan.size,):
        raise ValueError(f'piece_ids must have one entry per pixel ({scan.size}); got shape {ids.shape}')
    labels, dense, moments, small, (normals, means, _) = _dense_pieces(scan, ids, sigmas, 3)
    if len(labels) < 2:
        return ids.copy()
    dense_for_pairs = np.where(small[np.maximum(dense, 0)] & (dense >= 0), -1, dense)
    sigmas = np.ascontiguousarray(sigmas, dtype=np.float64)
    pairs = _unique_candidate_pairs(
        dense_for_pairs, scan, sigmas, normals, means, tau, int(max_gap), bool(connected_only), wrap_columns
    )
    roots = _merge_pieces(moments, pairs, tau * tau, factor * factor, step2)
    if large and not connected_only:
        roots = _join_large_surfaces(
            scan, dense_for_pairs, roots, moments, sigmas, tau, factor, large, wrap_columns, step2
        )
    return np.where(dense >= 0, labels[roots[np.maximum(dense, 0)]], -1)


def _check_large_surface_points(large_surface_points: int) -> int:
    value = large_surface_points
    if not (is_whole_number(value) and value >= 0):
        raise ValueError(f'large_surface_points must be a whole number of rays >= 0 (0: off); got {value!r}')
    return int(value)


def _join_large_surfaces(
    scan: RayScan,
    dense: np.ndarray,
    roots: np.ndarray,
    moments: np.ndarray,
    sigmas: np.ndarray,
    tau: float,
    factor: float,
    large_points: int,
    wrap_columns: bool,
    step_factor2: float = 1.0,
) -> np.ndarray:
    """The second round (module docstring): the surfaces (root rows of the merged pieces; dense: (H*W,)
    piece row of each pixel, -1 for none or a piece left out of the pairs) as pieces, their candidate
    pairs across occluded gaps of any length along a row or column, those with a surface of at least
    large_points rays merged cheapest first. Returns the new root of each piece row."""
    surface_moments = np.zeros_like(moments)
    np.add.at(surface_moments, roots, moments)  # (a root's row sums its pieces; the other rows stay 0)
    counts = surface_moments[:, 0]
    large = counts >= large_points
    if not np.any(large) or np.count_nonzero(counts) < 2:
        return roots
    surface_of_pixel = np.where(dense >= 0, roots[np.maximum(dense, 0)], -1)
    normals, means, _ = _piece_planes(np.where(counts[:, None] >= 3, surface_moments, np.ones(moments.shape[1])))
    pairs = _unique_candidate_pairs(
        surface_of_pixel, scan, sigmas, normals, means, tau, max(scan.height, scan.width), False, wrap_columns
    )
    pairs = pairs[large[pairs[:, 0]] | large[pairs[:, 1]]]
    if len(pairs) == 0:
        return roots
    return _merge_pieces(surface_moments, pairs, tau * tau, factor * factor, step_factor2)[roots]


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _absorb_kernel(
    ids, endpoints, directions, sigmas, valid, height, width, normals, means, tolerances, wrap_columns, queue
):
    """Grow every surface into 4-neighbouring rays without one that lie on its plane (breadth first,
    in pixel order); ids is updated in place. A ray k lies on surface P when its distance from P's
    plane is at most tolerances[P] + 2 sigma_k |n . v_k| (a non-finite sigma_k counts as 0).
    wrap_columns: the first and the last column are neighbours. queue: work memory of len(ids)."""
    n = len(ids)
    head = 0
    tail = 0
    for k in range(n):
        if ids[k] >= 0:
            queue[tail] = k
            tail += 1
    while head < tail:
        k = queue[head]
        head += 1
        p = ids[k]
        i = k // width
        j = k - i * width
        for side in range(4):
            if side == 0:
                if j == 0 and not wrap_columns:
                    continue
                q = k - 1 if j > 0 else k + width - 1
            elif side == 1:
                if j + 1 == width and not wrap_columns:
                    continue
                q = k + 1 if j + 1 < width else k - width + 1
            elif side == 2:
                if i == 0:
                    continue
                q = k - width
            else:
                if i + 1 == height:
                    continue
                q = k + width
            if ids[q] >= 0 or not valid[q]:
                continue
            along = (
                normals[p, 0] * directions[q, 0] + normals[p, 1] * directions[q, 1] + normals[p, 2] * directions[q, 2]
            )
            distance = (
                normals[p, 0] * (endpoints[q, 0] - means[p, 0])
                + normals[p, 1] * (endpoints[q, 1] - means[p, 1])
                + normals[p, 2] * (endpoints[q, 2] - means[p, 2])
            )
            sigma = sigmas[q] if np.isfinite(sigmas[q]) else 0.0
            if abs(distance) <= tolerances[p] + 2.0 * sigma * abs(along):
                ids[q] = p
                queue[tail] = q
                tail += 1


def absorb_rays(
    scan: RayScan,
    surface_ids: np.ndarray,
    sigmas: np.ndarray,
    surface_tolerance: float,
    *,
    noise_factor: float = 0.0,
    min_points: int = 1,
    wrap_columns: bool = False,
) -> np.ndarray:
    """Give rays without a surface (and surfaces of fewer than ``min_points`` rays) to a neighbouring
    surface whose plane they lie on (see :func:`_absorb_kernel`; tolerance sqrt(tau^2 + lambda^2 s_P^2)).
    wrap_columns: the first and the last column are neighbours (:func:`columns_wrap`).

    Returns the new ``(H*W,)`` surface ids (-1: none).
    """
    ids = np.ascontiguousarray(surface_ids, dtype=np.int64).copy()
    if ids.size == 0 or ids.max() < 0:
        return ids
    labels, dense, _, small, (normals, means, own) = _dense_pieces(scan, ids, sigmas, max(int(min_points), 3))
    dense = np.where((dense >= 0) & ~small[np.maximum(dense, 0)], dense, -1)
    tolerances = np.sqrt(float(surface_tolerance) ** 2 + float(noise_factor) ** 2 * own)
    _absorb_kernel(
        dense,
        scan.endpoints,
        scan.directions,
        np.ascontiguousarray(sigmas, dtype=np.float64),
        scan.valid,
        scan.height,
        scan.width,
        normals,
        means,
        tolerances,
        bool(wrap_columns),
        np.empty(len(dense), np.int64),
    )
    return np.where(dense >= 0, labels[np.maximum(dense, 0)], -1)


#: The whole-surface pass's work memory (consolidated_surfaces, the seam test, unit directions).
_work_memory = WorkMemory()
_reusable = _work_memory.array


def release_work_memory() -> None:
    """Free the work memory :func:`consolidated_surfaces` keeps between calls in the calling thread
    (about 40 bytes per ray of the largest scan so far)."""
    _work_memory.release()


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _dense_moments_kernel(ids, rank, dense, endpoints, sigmas):
    """_dense_ids_kernel and _piece_moments in one: rank (len > ids.max()) and dense (len(ids)) are
    filled in place; returns (labels (K,), moments (K, 11)). Non-finite sigmas count as 0."""
    rank[:] = -1
    for k in range(len(ids)):
        if ids[k] >= 0:
            rank[ids[k]] = 0
    n_labels = 0
    for g in range(len(rank)):
        if rank[g] == 0:
            rank[g] = n_labels
            n_labels += 1
    labels = np.empty(n_labels, np.int64)
    for g in range(len(rank)):
        if rank[g] >= 0:
            labels[rank[g]] = g
    mom = np.zeros((n_labels, 11))
    for k in range(len(ids)):
        g = rank[ids[k]] if ids[k] >= 0 else -1
        dense[k] = g
        if g < 0:
            continue
        _add_ray(mom, g, endpoints, k, sigmas[k] if np.isfinite(sigmas[k]) else 0.0)
    return labels, mom


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _without_small(dense, small, out):
    """out[k] = dense[k], or -1 where it is a small piece's (small[dense[k]])."""
    for k in range(len(dense)):
        out[k] = -1 if dense[k] >= 0 and small[dense[k]] else dense[k]


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _surface_moments_kernel(dense, roots, endpoints, sigmas, min_points, surface):
    """Each pixel's surface (the consolidation's root of its piece), numbered 0..S-1 by ascending root,
    into surface (-1: none, or a surface of fewer than min_points rays); returns the surfaces' (S, 11)
    moments, summed over their pixels in pixel order (non-finite sigmas count as 0)."""
    index = np.full(len(roots), -1, np.int64)
    for k in range(len(dense)):
        if dense[k] >= 0:
            index[roots[dense[k]]] = 0
    n_surfaces = 0
    for r in range(len(roots)):
        if index[r] == 0:
            index[r] = n_surfaces
            n_surfaces += 1
    mom = np.zeros((n_surfaces, 11))
    for k in range(len(dense)):
        if dense[k] < 0:
            surface[k] = -1
            continue
        g = index[roots[dense[k]]]
        surface[k] = g
        _add_ray(mom, g, endpoints, k, sigmas[k] if np.isfinite(sigmas[k]) else 0.0)
    for k in range(len(dense)):
        if surface[k] >= 0 and mom[surface[k], 0] < min_points:
            surface[k] = -1
    return mom


def checked_tolerances(surface_tolerance: float, noise_factor: float) -> tuple[float, float]:
    """(tau, lambda) as floats; ValueError unless tau is a finite length > 0 m and lambda finite and >= 0."""
    tau = float(surface_tolerance)
    factor = float(noise_factor)
    if not (np.isfinite(tau) and tau > 0.0):
        raise ValueError(f'surface_tolerance must be a finite length > 0 m; got {surface_tolerance!r}')
    if not (np.isfinite(factor) and factor >= 0.0):
        raise ValueError(f'noise_factor must be finite and >= 0; got {noise_factor!r}')
    return tau, factor


def consolidated_surfaces(
    scan: RayScan,
    piece_ids: np.ndarray,
    sigmas: np.ndarray,
    surface_tolerance: float,
    *,
    noise_factor: float = 0.0,
    connected_only: bool = False,
    min_points: int = 1,
    wrap_columns: bool = False,
    large_surface_points: int = 0,
    step_factor: float = 1.0,
) -> np.ndarray:
    """``absorb_rays(scan, consolidate_pieces(scan, piece_ids, ...), ...)`` with the surfaces numbered
    0..S-1 (by their smallest piece id) instead of by that id: the same rays in the same surfaces,
    with the work arrays in this thread's work memory (:func:`release_work_memory`).

    Returns ``(H*W,)`` surface of each pixel (-1: none); the array is work memory, overwritten by
    this thread's next call (copy it to keep it).
    """
    tau, factor = checked_tolerances(surface_tolerance, noise_factor)
    large = _check_large_surface_points(large_surface_points)
    step2 = check_step_factor(step_factor) ** 2
    ids = np.ascontiguousarray(piece_ids, dtype=np.int64)
    if ids.shape != (scan.size,):
        raise ValueError(f'piece_ids must have one entry per pixel ({scan.size}); got shape {ids.shape}')
    sigmas = np.ascontiguousarray(sigmas, dtype=np.float64)
    surface = _reusable('surface', scan.size, np.int64)
    if ids.size == 0 or ids.max() < 0:
        surface[:] = -1
        return surface
    bound = int(ids.max()) + 1
    dense = _reusable('dense', scan.size, np.int64)
    if bound <= 4 * ids.size + 16:
        labels, moments = _dense_moments_kernel(ids, _reusable('rank', bound, np.int64), dense, scan.endpoints, sigmas)
    else:
        labels, dense[:] = _dense_ids(ids)
        moments = _piece_moments(dense, scan.endpoints, np.where(np.isfinite(sigmas), sigmas, 0.0), len(labels))
    roots = np.arange(len(labels))
    if len(labels) >= 2:
        small = moments[:, 0] < 3
        normals, means, _ = _piece_planes(np.where(small[:, None], np.ones(11), moments))
        pair_ids = _reusable('pair_ids', scan.size, np.int64)
        _without_small(dense, small, pair_ids)
        pairs = _unique_candidate_pairs(
            pair_ids, scan, sigmas, normals, means, tau, DEFAULT_MAX_GAP, connected_only, wrap_columns
        )
        roots = _merge_pieces(moments, pairs, tau * tau, factor * factor, step2)
        if large and not connected_only:
            roots = _join_large_surfaces(
                scan, pair_ids, roots, moments, sigmas, tau, factor, large, wrap_columns, step2
            )
    surface_moments = _surface_moments_kernel(dense, roots, scan.endpoints, sigmas, max(int(min_points), 3), surface)
    small = surface_moments[:, 0] < max(int(min_points), 3)
    normals, means, own = _piece_planes(np.where(small[:, None], np.ones(11), surface_moments))
    _absorb_kernel(
        surface,
        scan.endpoints,
        scan.directions,
        sigmas,
        scan.valid,
        scan.height,
        scan.width,
        normals,
        means,
        np.sqrt(tau**2 + factor**2 * own),
        bool(wrap_columns),
        dense,  # the queue: dense is no longer needed
    )
    return surface
