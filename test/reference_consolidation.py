"""A slow, obviously correct consolidation (ppe_ros.core.consolidation's model), for tests.

Pieces are sets of pixels; every valuation fits the union's plane from its points with numpy's
eigh; candidate pairs follow the module docstring's rule pixel by pixel in plain Python; the
agglomeration re-values every candidate pair of the current surfaces before each merge.
"""

from __future__ import annotations

import numpy as np


def _plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    mean = points.mean(axis=0)
    values, vectors = np.linalg.eigh(np.cov((points - mean).T, bias=True))
    return vectors[:, 0], mean, max(values[0], 0.0)


def _deviation(points: np.ndarray, normal: np.ndarray, mean: np.ndarray) -> float:
    _, _, own = _plane(points)
    return max(float(np.mean(((points - mean) @ normal) ** 2)) - own, 0.0)


def cost(points_a, points_b, sigmas_a, sigmas_b, tau, noise_factor, step_factor=1.0):
    normal, mean, _ = _plane(np.concatenate([points_a, points_b]))
    scatter = min(max(_plane(points_a)[2], _plane(points_b)[2]), max(np.mean(sigmas_a**2), np.mean(sigmas_b**2)))
    allowed_a = allowed_b = tau**2 + noise_factor**2 * scatter
    value = max(_deviation(points_a, normal, mean) / allowed_a, _deviation(points_b, normal, mean) / allowed_b)
    # the step at each piece's mean: where the line from it along the union's normal meets the other's plane
    na, ca, _ = _plane(points_a)
    nb, cb, _ = _plane(points_b)
    step_at_a = nb @ (cb - ca) / (nb @ normal)
    step_at_b = na @ (ca - cb) / (na @ normal)
    return max(value, min(step_at_a**2, step_at_b**2) / (step_factor**2 * min(allowed_a, allowed_b)))


def _bridges(scan, sigmas, ids, k, normal, mean, tau, connected_only):
    if not np.isfinite(scan.ranges[k]):
        return not connected_only
    along = normal @ scan.directions[k]
    margin = 2 * tau + 2 * sigmas[k] * abs(along)
    height = normal @ (scan.endpoints[k] - mean)
    if abs(height) <= margin:
        return ids[k] < 0
    if connected_only:
        return False
    start_height = height - scan.ranges[k] * along
    return height * start_height > 0 and abs(start_height) > abs(height)


def candidate_pairs(scan, sigmas, ids, tau, max_gap, connected_only, wrap_columns=False):
    planes = {}
    for g in np.unique(ids[ids >= 0]):
        members = np.flatnonzero(ids == g)
        if len(members) >= 3:
            normal, mean, _ = _plane(scan.endpoints[members])
            planes[g] = (normal, mean)
    usable = np.array([g in planes if g >= 0 else False for g in ids])
    work = np.where(usable, ids, -1)
    pairs = set()
    width = scan.width
    for step, along_rows in ((1, True), (width, False)):
        for k in range(len(work)):
            b = work[k]
            if b < 0:
                continue
            position = k % width if along_rows else k // width
            if position == 0 or work[k - step] == b:
                continue
            for g in range(1, min(max_gap, position) + 1):
                q = k - g * step
                if work[q] == b:
                    break
                if _bridges(scan, sigmas, work, q, *planes[b], tau, connected_only):
                    continue
                a = work[q]
                if a >= 0 and (
                    g == 1
                    or all(
                        _bridges(scan, sigmas, work, r, *planes[a], tau, connected_only)
                        for r in range(q + step, k, step)
                    )
                ):
                    pairs.add((min(a, b), max(a, b)))
                break
            else:
                continue
    # pieces that touch directly are always candidates
    for k in range(len(work)):
        for q in ((k + 1) if (k + 1) % width else None, k + width if k + width < len(work) else None):
            if q is not None and work[k] >= 0 and work[q] >= 0 and work[k] != work[q]:
                pairs.add((min(work[k], work[q]), max(work[k], work[q])))
    if wrap_columns:  # the last column touches the first
        for row in range(scan.height):
            a, b = work[row * width + width - 1], work[row * width]
            if a >= 0 and b >= 0 and a != b:
                pairs.add((min(a, b), max(a, b)))
    return pairs


def _merge_cheapest_first(scan, ids, sigmas, pairs, root, tau, noise_factor, step_factor):
    """Merge the current surfaces (union-find root over piece ids) along the pieces' candidate pairs, the
    cheapest admissible pair first, every pair re-valued from the pixels before each merge."""

    def find(g):
        while root[g] != g:
            g = root[g]
        return g

    while True:
        best = None
        for a, b in sorted({(min(find(a), find(b)), max(find(a), find(b))) for a, b in pairs}):
            if a == b:
                continue
            ma = np.isin(ids, [g for g in root if find(g) == a])
            mb = np.isin(ids, [g for g in root if find(g) == b])
            value = cost(scan.endpoints[ma], scan.endpoints[mb], sigmas[ma], sigmas[mb], tau, noise_factor, step_factor)
            if value <= 1.0 and (best is None or value < best[0]):
                best = (value, a, b)
        if best is None:
            return find
        root[best[2]] = best[1]


def consolidate_reference(
    scan,
    ids,
    sigmas,
    tau,
    *,
    noise_factor=0.0,
    connected_only=False,
    max_gap=64,
    wrap_columns=False,
    large_surface_points=0,
    step_factor=1.0,
):
    """Surface id (the smallest piece id) of each pixel, -1 for none. large_surface_points > 0 (not with
    connected_only): then the surfaces (their pixels of pieces of >= 3 pixels) are found candidates
    across gaps of any length, and the pairs with a surface of at least that many pixels merge the same way."""
    ids = np.asarray(ids, np.int64)
    pairs = candidate_pairs(scan, sigmas, ids, tau, max_gap, connected_only, wrap_columns)
    root = {g: g for g in np.unique(ids[ids >= 0])}
    find = _merge_cheapest_first(scan, ids, sigmas, pairs, root, tau, noise_factor, step_factor)
    if large_surface_points and not connected_only:
        sizes = {g: int(np.count_nonzero(ids == g)) for g in root}
        surfaces = np.array([find(g) if g >= 0 and sizes[g] >= 3 else -1 for g in ids])
        surface_size = {s: int(np.count_nonzero(surfaces == s)) for s in np.unique(surfaces[surfaces >= 0])}
        wide = candidate_pairs(scan, sigmas, surfaces, tau, max(scan.height, scan.width), False, wrap_columns)
        wide = {(a, b) for a, b in wide if max(surface_size[a], surface_size[b]) >= large_surface_points}
        find = _merge_cheapest_first(scan, ids, sigmas, wide, root, tau, noise_factor, step_factor)
    return np.array([find(g) if g >= 0 else -1 for g in ids])
