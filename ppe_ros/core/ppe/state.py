"""Plane state and fits: exact states, the quadratic models of extensions and merges, hybrid (model + exact)
merges, union fits, re-linearisation and the caches of refined merges and candidate fits."""

from __future__ import annotations

import numba as nb
import numpy as np

from ppe_ros.core.fitting import fit_rays, fit_with_information, gn_pass, ray_terms, solve_sym3
from ppe_ros.core.ppe.intrinsics import _prefetch

# --------------------------------------------------------------------------------------------
from ppe_ros.core.ppe.layout import (
    _EC_RAY,
    _EC_VER,
    _FIT_INFO,
    _FIT_ITERATIONS,
    _FIT_TOLERANCE,
    _FIT_VALUE,
    _FIT_W,
    _MC_PARTNER,
    _MC_VA,
    _MC_VB,
    _PCOUNT,
    _PE,
    _PH,
    _PHEAD,
    _PRPARTNER,
    _PVER,
    _PW,
    _PWL,
    _RC_COUNT,
    _RC_EXCESS,
    _RC_GRAD,
    _RC_INFO,
    _RC_VER,
    _RC_W,
    UNION_MODEL_AGREEMENT,
)


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _find(parent, x):
    root = x
    while parent[root] != root:
        root = parent[root]
    while parent[x] != root:
        nxt = parent[x]
        parent[x] = root
        x = nxt
    return root


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _gather(pi, nextpix, p, buf, endpoints, directions, start=0):
    """Write plane p's pixel ids into buf from index start on; returns their count.

    Prefetch hints request each ray's endpoint and direction, which the fit that follows reads:
    the pixel list is a chain of dependent loads, the rays' rows are independent of each other, so
    requesting them during the walk overlaps their cache misses with it.
    """
    n = 0
    k = pi[p, _PHEAD]
    while k >= 0:
        _prefetch(endpoints, k, 0)
        _prefetch(directions, k, 0)
        buf[start + n] = k
        n += 1
        k = nextpix[k]
    return n


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _store_state(pf, p, sse, w0, w1, w2, information):
    """Store plane p's E, w (also as its linearisation point) and information."""
    pf[p, _PE] = sse
    pf[p, _PW] = w0
    pf[p, _PW + 1] = w1
    pf[p, _PW + 2] = w2
    pf[p, _PWL] = w0
    pf[p, _PWL + 1] = w1
    pf[p, _PWL + 2] = w2
    for i in range(6):
        pf[p, _PH + i] = information[i]


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _set_exact_state(endpoints, directions, pf, idx, count, p, w0, w1, w2, tolerance=_FIT_TOLERANCE):
    """Fit plane p exactly on idx[:count] from (w0, w1, w2) and store E, w, information, w_lin
    (tolerance: the fit's relative convergence tolerance, GreedyOptions.fit_tolerance)."""
    sse, w0, w1, w2, information = fit_with_information(
        endpoints, directions, idx, count, w0, w1, w2, _FIT_ITERATIONS, tolerance
    )
    _store_state(pf, p, sse, w0, w1, w2, information)


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _put_fit(fits, r, value, w0, w1, w2, information):
    """Write a fit into row r of an (n, 10) fit table: value (SSE, m^2), w (3) and information (6)."""
    fits[r, _FIT_VALUE] = value
    fits[r, _FIT_W] = w0
    fits[r, _FIT_W + 1] = w1
    fits[r, _FIT_W + 2] = w2
    for t in range(6):
        fits[r, _FIT_INFO + t] = information[t]


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _get_fit(fits, r):
    """Row r of an (n, 10) fit table: (value, w0, w1, w2, information)."""
    return (
        fits[r, _FIT_VALUE],
        fits[r, _FIT_W],
        fits[r, _FIT_W + 1],
        fits[r, _FIT_W + 2],
        (
            fits[r, _FIT_INFO],
            fits[r, _FIT_INFO + 1],
            fits[r, _FIT_INFO + 2],
            fits[r, _FIT_INFO + 3],
            fits[r, _FIT_INFO + 4],
            fits[r, _FIT_INFO + 5],
        ),
    )


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _candidate_increment(
    endpoints, directions, pf, p, small, idx, n, k, version, ecache_i, ecache_f, one_step, tolerance
):
    """Increment (m^2) of extending plane p (at its current version) by ray k.

    A small plane (small: it has at most exact_plane_size rays with k) is fitted on its rays idx[:n]
    (the caller gathers them) plus k, written to idx[n]; the least-SSE candidate fit of p's current
    version is kept in (ecache_i, ecache_f)[p] (ray, version; SSE, w, information). Exactly (one_step
    False; tolerance: the fit's relative convergence tolerance): executing that extension needs no fit,
    it is the same fit (same rays in the same order, same start) that _set_exact_state would make. With
    one_step, :func:`_one_step_sse` instead (its w kept, information NaN: the execution fits from
    there). A large plane uses its model.
    """
    if not small:
        return _model_extension(endpoints, directions, pf, p, k)[0]
    idx[n] = k
    sse = np.inf
    if one_step:
        sse, w0, w1, w2 = _one_step_sse(endpoints, directions, pf, p, idx, n + 1, k)
        information = (np.nan, np.nan, np.nan, np.nan, np.nan, np.nan)
    if not np.isfinite(sse):  # exact, or the one-step model is singular
        sse, w0, w1, w2, information = fit_with_information(
            endpoints, directions, idx, n + 1, pf[p, _PW], pf[p, _PW + 1], pf[p, _PW + 2], _FIT_ITERATIONS, tolerance
        )
    if ecache_i[p, _EC_VER] != version or sse < ecache_f[p, _FIT_VALUE]:
        ecache_i[p, _EC_RAY] = k
        ecache_i[p, _EC_VER] = version
        _put_fit(ecache_f, p, sse, w0, w1, w2, information)
    return sse - pf[p, _PE]


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _one_step_sse(endpoints, directions, pf, p, idx, count, k):
    """The SSE (m^2) of rays idx[:count] (plane p's rays and ray k) at w' = w - H'^-1 f g: one Gauss-Newton
    step from p's fit (w, information H, a minimum: zero gradient) with k's residual f and gradient g
    added (H' = H + g g^T). An upper bound of their exact fit's SSE, and close to it: the step is the
    one the rank-one model of a large plane takes, the SSE is exact at w'. Returns (sse, w'); sse inf
    when H' is singular or a residual is not finite."""
    inc, x0, x1, x2, f, g0, g1, g2 = _model_extension(endpoints, directions, pf, p, k)
    if not np.isfinite(inc):
        return np.inf, np.nan, np.nan, np.nan
    scale = f / (1.0 + g0 * x0 + g1 * x1 + g2 * x2)
    w0 = pf[p, _PW] - x0 * scale
    w1 = pf[p, _PW + 1] - x1 * scale
    w2 = pf[p, _PW + 2] - x2 * scale
    sse = 0.0
    for t in range(count):
        residual = ray_terms(endpoints, directions, idx[t], w0, w1, w2)[0]
        sse += residual * residual
    if not np.isfinite(sse):
        return np.inf, np.nan, np.nan, np.nan
    return sse, w0, w1, w2


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _relinearise(endpoints, directions, pf, idx, count, p):
    """Re-linearise large plane p on its rays idx[:count]: one Gauss-Newton step from its current w.

    The model's w is already close to the minimiser (rank-one updates), so one step brings it to
    within the Gauss-Newton rate of convergence; E becomes the SSE at the new w predicted by the
    linearisation and the information is the Gauss-Newton J^T J at the current w.
    """
    w0 = pf[p, _PW]
    w1 = pf[p, _PW + 1]
    w2 = pf[p, _PW + 2]
    sse, a00, a01, a02, a11, a12, a22, b0, b1, b2 = gn_pass(endpoints, directions, idx, count, w0, w1, w2)
    d0, d1, d2, ok = solve_sym3(a00, a01, a02, a11, a12, a22, b0, b1, b2)
    if not (ok and np.isfinite(sse)):
        _set_exact_state(endpoints, directions, pf, idx, count, p, w0, w1, w2)
        return
    _store_state(
        pf, p, max(sse - (d0 * b0 + d1 * b1 + d2 * b2), 0.0), w0 - d0, w1 - d1, w2 - d2, (a00, a01, a02, a11, a12, a22)
    )


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _model_extension(endpoints, directions, pf, p, k):
    """Increment of adding ray k to plane p under p's quadratic model (rank-one update).

    Returns (increment, x0, x1, x2, f, g0, g1, g2) with x = H^-1 g.
    """
    w0 = pf[p, _PW]
    w1 = pf[p, _PW + 1]
    w2 = pf[p, _PW + 2]
    f, g0, g1, g2 = ray_terms(endpoints, directions, k, w0, w1, w2)
    x0, x1, x2, ok = solve_sym3(
        pf[p, _PH], pf[p, _PH + 1], pf[p, _PH + 2], pf[p, _PH + 3], pf[p, _PH + 4], pf[p, _PH + 5], g0, g1, g2
    )
    if not ok or not np.isfinite(f):
        return np.inf, 0.0, 0.0, 0.0, f, g0, g1, g2
    denom = 1.0 + g0 * x0 + g1 * x1 + g2 * x2
    return f * f / denom, x0, x1, x2, f, g0, g1, g2


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _model_merge_terms(pf, a, b):
    """Ha (w_a - w_b), Hb (w_a - w_b) and S = Ha + Hb (6) of planes a, b: the merge model's system."""
    # scalar reads (no array views: a view costs reference counting in the hot loop)
    ha0, ha1, ha2, ha3, ha4, ha5 = (
        pf[a, _PH],
        pf[a, _PH + 1],
        pf[a, _PH + 2],
        pf[a, _PH + 3],
        pf[a, _PH + 4],
        pf[a, _PH + 5],
    )
    hb0, hb1, hb2, hb3, hb4, hb5 = (
        pf[b, _PH],
        pf[b, _PH + 1],
        pf[b, _PH + 2],
        pf[b, _PH + 3],
        pf[b, _PH + 4],
        pf[b, _PH + 5],
    )
    d0 = pf[a, _PW] - pf[b, _PW]
    d1 = pf[a, _PW + 1] - pf[b, _PW + 1]
    d2 = pf[a, _PW + 2] - pf[b, _PW + 2]
    # Ha d, Hb d
    ad0 = ha0 * d0 + ha1 * d1 + ha2 * d2
    ad1 = ha1 * d0 + ha3 * d1 + ha4 * d2
    ad2 = ha2 * d0 + ha4 * d1 + ha5 * d2
    bd0 = hb0 * d0 + hb1 * d1 + hb2 * d2
    bd1 = hb1 * d0 + hb3 * d1 + hb4 * d2
    bd2 = hb2 * d0 + hb4 * d1 + hb5 * d2
    return (ad0, ad1, ad2), (bd0, bd1, bd2), (ha0 + hb0, ha1 + hb1, ha2 + hb2, ha3 + hb3, ha4 + hb4, ha5 + hb5)


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _model_merge_increment_of(ad, bd, s):
    """Merge increment (ad^T S^-1 bd, at least 0; inf when S is singular) of the terms of _model_merge_terms."""
    y0, y1, y2, ok = solve_sym3(s[0], s[1], s[2], s[3], s[4], s[5], bd[0], bd[1], bd[2])
    if not ok:
        return np.inf
    inc = ad[0] * y0 + ad[1] * y1 + ad[2] * y2
    if inc < 0.0:
        inc = 0.0
    return inc


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _model_merge_increment(pf, a, b):
    """Merge increment of planes a, b under their quadratic models (inf when the models are singular)."""
    ad, bd, s = _model_merge_terms(pf, a, b)
    return _model_merge_increment_of(ad, bd, s)


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _model_merge(pf, a, b):
    """Merge increment of planes a, b under their quadratic models and the merged w."""
    ad, bd, s = _model_merge_terms(pf, a, b)
    inc = _model_merge_increment_of(ad, bd, s)
    if not inc < np.inf:
        return np.inf, np.nan, np.nan, np.nan
    # merged w = w_b + S^-1 Ha (w_a - w_b)
    z0, z1, z2, _ = solve_sym3(s[0], s[1], s[2], s[3], s[4], s[5], ad[0], ad[1], ad[2])
    return inc, pf[b, _PW] + z0, pf[b, _PW + 1] + z1, pf[b, _PW + 2] + z2


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _model_offset(pf, big, w0, w1, w2):
    """Plane big's information H (6), e = w - w_big (3) and H e (3): its quadratic model at w is
    E_big + e^T H e, with half gradient H e."""
    h0, h1, h2, h3, h4, h5 = (
        pf[big, _PH],
        pf[big, _PH + 1],
        pf[big, _PH + 2],
        pf[big, _PH + 3],
        pf[big, _PH + 4],
        pf[big, _PH + 5],
    )
    e0 = w0 - pf[big, _PW]
    e1 = w1 - pf[big, _PW + 1]
    e2 = w2 - pf[big, _PW + 2]
    he = (h0 * e0 + h1 * e1 + h2 * e2, h1 * e0 + h3 * e1 + h4 * e2, h2 * e0 + h4 * e1 + h5 * e2)
    return (h0, h1, h2, h3, h4, h5), (e0, e1, e2), he


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _hybrid_pass(endpoints, directions, pf, big, idx, count, w0, w1, w2):
    """model_big(w) + exact radial SSE of rays idx[:count] at w, with its Gauss-Newton system.

    Returns (value, info6, r0, r1, r2): info6 = H_big + J^T J (a tuple a00 a01 a02 a11 a12 a22) and
    r = H_big (w - w_big) + J^T f.
    """
    (h0, h1, h2, h3, h4, h5), (e0, e1, e2), (r0, r1, r2) = _model_offset(pf, big, w0, w1, w2)
    value = pf[big, _PE] + e0 * r0 + e1 * r1 + e2 * r2
    for t in range(count):
        f, g0, g1, g2 = ray_terms(endpoints, directions, idx[t], w0, w1, w2)
        value += f * f
        h0 += g0 * g0
        h1 += g0 * g1
        h2 += g0 * g2
        h3 += g1 * g1
        h4 += g1 * g2
        h5 += g2 * g2
        r0 += g0 * f
        r1 += g1 * f
        r2 += g2 * f
    return value, (h0, h1, h2, h3, h4, h5), r0, r1, r2


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _hybrid_merge(endpoints, directions, pf, big, idx, count, w0, w1, w2, tolerance=_FIT_TOLERANCE):
    """min over w of model_big(w) + exact SSE of rays idx[:count] (Gauss-Newton with step halving, to the
    relative tolerance GreedyOptions.fit_tolerance).

    One pass over the rays per iteration (the pass at a trial point gives its value and, when
    accepted, the next system). Returns (value, w0, w1, w2, info6, r3) where info6 is the information
    matrix and r3 the half gradient H_big (w - w_big) + J^T f at the returned w.
    """
    value, info, r0, r1, r2 = _hybrid_pass(endpoints, directions, pf, big, idx, count, w0, w1, w2)
    for _ in range(_FIT_ITERATIONS):
        d0, d1, d2, ok = solve_sym3(info[0], info[1], info[2], info[3], info[4], info[5], r0, r1, r2)
        if not ok:
            break
        if not (d0 * r0 + d1 * r1 + d2 * r2) > tolerance * value:
            break
        step = 1.0
        improved = False
        for _h in range(30):
            n0 = w0 - step * d0
            n1 = w1 - step * d1
            n2 = w2 - step * d2
            trial = _hybrid_pass(endpoints, directions, pf, big, idx, count, n0, n1, n2)
            if trial[0] <= value:
                improved = True
                break
            step *= 0.5
        if not improved:
            break
        decrease = value - trial[0]
        w0, w1, w2 = n0, n1, n2
        value, info, r0, r1, r2 = trial
        if decrease <= tolerance * value:
            break
    return value, w0, w1, w2, info, (r0, r1, r2)


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _keep_refined_merge(rcache_i, rcache_f, pf, pi, big, small, e_small, value, w0, w1, w2, info, r):
    """Keep the small plane's exact residuals of a refined hybrid merge as a quadratic model at its w.

    value, info, r: _hybrid_merge's result at w; e_small: the small plane's exact E (m^2). Stored on
    the small plane: the partner (pf's _PRPARTNER); its own version and the partner's ray count
    (rcache_i); its SSE at w minus e_small, its half gradient J^T f (3) and Gauss-Newton information
    J^T J (6) at w, and w (3) (rcache_f).
    """
    (h0, h1, h2, h3, h4, h5), (e0, e1, e2), (he0, he1, he2) = _model_offset(pf, big, w0, w1, w2)
    pf[small, _PRPARTNER] = big
    rcache_i[small, _RC_VER] = pi[small, _PVER]
    rcache_i[small, _RC_COUNT] = pi[big, _PCOUNT]
    rcache_f[small, _RC_EXCESS] = value - (pf[big, _PE] + e0 * he0 + e1 * he1 + e2 * he2) - e_small
    rcache_f[small, _RC_GRAD] = r[0] - he0
    rcache_f[small, _RC_GRAD + 1] = r[1] - he1
    rcache_f[small, _RC_GRAD + 2] = r[2] - he2
    rcache_f[small, _RC_INFO] = info[0] - h0
    rcache_f[small, _RC_INFO + 1] = info[1] - h1
    rcache_f[small, _RC_INFO + 2] = info[2] - h2
    rcache_f[small, _RC_INFO + 3] = info[3] - h3
    rcache_f[small, _RC_INFO + 4] = info[4] - h4
    rcache_f[small, _RC_INFO + 5] = info[5] - h5
    rcache_f[small, _RC_W] = w0
    rcache_f[small, _RC_W + 1] = w1
    rcache_f[small, _RC_W + 2] = w2


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _refined_merge_increment(pf, big, rcache_f, small):
    """Merge increment (m^2) of big's current model plus small's residual model kept by _keep_refined_merge.

    min over w of E_big + (w - w_big)^T H_big (w - w_big) + s + 2 r^T u + u^T H_s u (u = w - w*),
    minus E_big and small's exact E: excess + e^T H_big e - c^T S^-1 c with e = w* - w_big,
    c = H_big e + r, S = H_big + H_s (the minimiser is u = -S^-1 c). Equals the refined increment
    while big is unchanged.
    """
    (h0, h1, h2, h3, h4, h5), (e0, e1, e2), (he0, he1, he2) = _model_offset(
        pf, big, rcache_f[small, _RC_W], rcache_f[small, _RC_W + 1], rcache_f[small, _RC_W + 2]
    )
    c0 = he0 + rcache_f[small, _RC_GRAD]
    c1 = he1 + rcache_f[small, _RC_GRAD + 1]
    c2 = he2 + rcache_f[small, _RC_GRAD + 2]
    y0, y1, y2, ok = solve_sym3(
        h0 + rcache_f[small, _RC_INFO],
        h1 + rcache_f[small, _RC_INFO + 1],
        h2 + rcache_f[small, _RC_INFO + 2],
        h3 + rcache_f[small, _RC_INFO + 3],
        h4 + rcache_f[small, _RC_INFO + 4],
        h5 + rcache_f[small, _RC_INFO + 5],
        c0,
        c1,
        c2,
    )
    if not ok:
        return np.inf
    inc = rcache_f[small, _RC_EXCESS] + e0 * he0 + e1 * he1 + e2 * he2 - (c0 * y0 + c1 * y1 + c2 * y2)
    if inc < 0.0:
        inc = 0.0
    return inc


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _union_fit(endpoints, directions, pf, idx, count, a, b, tolerance=_FIT_TOLERANCE):
    """Exact fit of the union of planes a and b (rays idx[:count]; relative tolerance
    GreedyOptions.fit_tolerance); both planes' states are exact fits.

    Starts from the merged w of the two planes' quadratic models. The radial SSE of rays on two
    different surfaces can have several local minima, so when the increment found there disagrees
    with the models' by more than UNION_MODEL_AGREEMENT (relative), the fit also starts from a's
    plane, b's plane and the algebraic fit and keeps the least SSE (on the SynPEB and Ouster scans
    the models agree within 5 % and all four starts reach the same minimum).
    Returns (sse, w0, w1, w2).
    """
    model_inc, m0, m1, m2 = _model_merge(pf, a, b)
    best = np.inf
    b0 = np.nan
    b1 = np.nan
    b2 = np.nan
    if model_inc < np.inf:
        best, b0, b1, b2 = fit_rays(endpoints, directions, idx, count, m0, m1, m2, _FIT_ITERATIONS, tolerance)
        inc = best - pf[a, _PE] - pf[b, _PE]
        if best < np.inf and abs(inc - model_inc) <= UNION_MODEL_AGREEMENT * max(inc, model_inc):
            return best, b0, b1, b2
    sse, w0, w1, w2 = fit_rays(
        endpoints, directions, idx, count, pf[a, _PW], pf[a, _PW + 1], pf[a, _PW + 2], _FIT_ITERATIONS, tolerance
    )
    if sse < best:
        best, b0, b1, b2 = sse, w0, w1, w2
    sse, w0, w1, w2 = fit_rays(
        endpoints, directions, idx, count, pf[b, _PW], pf[b, _PW + 1], pf[b, _PW + 2], _FIT_ITERATIONS, tolerance
    )
    if sse < best:
        best, b0, b1, b2 = sse, w0, w1, w2
    sse, w0, w1, w2 = fit_rays(endpoints, directions, idx, count, np.nan, np.nan, np.nan, _FIT_ITERATIONS, tolerance)
    if sse < best:
        best, b0, b1, b2 = sse, w0, w1, w2
    return best, b0, b1, b2


@nb.njit(cache=True, error_model='numpy', nogil=True, _nrt=False)
def _cache_merge(mcache_i, mcache_f, a, b, va, vb, value, w0, w1, w2, info):
    """Remember the refined merge of planes a < b at versions (va, vb): its value, merged w and information."""
    mcache_i[a, _MC_PARTNER] = b
    mcache_i[a, _MC_VA] = va
    mcache_i[a, _MC_VB] = vb
    _put_fit(mcache_f, a, value, w0, w1, w2, info)
