"""A slow, obviously correct consolidation (ppe_ros.core.consolidation's model), for tests.

Pieces are sets of pixels; every valuation fits the union's plane from its points with numpy's
eigh; candidate pairs follow the module docstring's rule pixel by pixel in plain Python; the
agglomeration re-values every candidate pair of the current surfaces before each merge.
"""

from __future__ import annotations

import itertools

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


def _boundary_pixel_pairs(ids, large, height, width, wrap, max_gap):
    """Pixel pairs (k, l) of two large surfaces: l the first pixel with a surface to the right of k (across
    the seam when wrap) or below it, past at most max_gap pixels without one."""
    pairs = []
    for k in range(height * width):
        if ids[k] < 0 or not large[ids[k]]:
            continue
        i, j = divmod(k, width)
        walks = [
            [i * width + (j + s) % width for s in range(1, max_gap + 2) if wrap or j + s < width],
            [(i + s) * width + j for s in range(1, max_gap + 2) if i + s < height],
        ]
        for walk in walks:
            walk = list(itertools.takewhile(lambda x, k=k: x != k, walk))  # not past k, once around
            hit = next((x for x in walk if ids[x] >= 0), None)
            if hit is not None and ids[hit] != ids[k] and large[ids[hit]]:
                pairs.append((k, hit))
    return pairs


def _mean_square_distance(points, normal, mean):
    return float(np.mean(((points - mean) @ normal) ** 2))


def boundary_cost_reference(pa, pb, at_a, at_b, sigmas_a, sigmas_b, tau, noise_factor, step_factor, max_bend_deg):
    """The boundary round's cost of surfaces with points pa, pb whose boundary points are at_a, at_b (one row
    per boundary pixel pair); inf if their normals bend by more than max_bend_deg."""
    normal, mean, _ = _plane(np.concatenate([pa, pb]))
    na, ca, own_a = _plane(pa)
    nb, cb, own_b = _plane(pb)
    if np.degrees(np.arccos(min(abs(float(na @ nb)), 1.0))) > max_bend_deg:
        return np.inf
    scatter = min(max(own_a, own_b), max(np.mean(sigmas_a**2), np.mean(sigmas_b**2)))
    allowed = tau**2 + noise_factor**2 * scatter
    deviation = max(_deviation(pa, normal, mean), _deviation(pb, normal, mean))
    excess_a = max(_mean_square_distance(at_a, nb, cb) - _mean_square_distance(at_a, na, ca), 0.0)
    excess_b = max(_mean_square_distance(at_b, na, ca) - _mean_square_distance(at_b, nb, cb), 0.0)
    return max(deviation, max(excess_a, excess_b) / step_factor**2) / allowed


def boundary_join_reference(
    scan,
    ids,
    sigmas,
    tau,
    min_points,
    noise_factor=0.0,
    step_factor=1.0,
    wrap=False,
    max_gap=3,
    min_pairs=10,
    max_bend_deg=4.0,
):
    """ppe_ros.core.boundary_join.join_at_boundaries by brute force: every pair of current surfaces is
    valued again from its points before each merge (its boundary: the pixel pairs between its parts)."""
    ids = np.asarray(ids)
    counts = np.bincount(ids[ids >= 0]) if np.any(ids >= 0) else np.zeros(0, int)
    large = counts >= min_points
    pixel_pairs = _boundary_pixel_pairs(ids, large, scan.height, scan.width, wrap, max_gap)
    group = {g: g for g in range(len(counts))}  # surface -> its current surface (the smallest id)
    points = scan.endpoints
    while True:
        best = None
        current = sorted({group[g] for g in range(len(counts)) if large[g]})
        for a_index, a in enumerate(current):
            for b in current[a_index + 1 :]:
                sides = [(k, m) if group[ids[k]] == a else (m, k) for k, m in pixel_pairs]
                sides = [(k, m) for k, m in sides if group[ids[k]] == a and group[ids[m]] == b]
                if len(sides) < min_pairs:
                    continue
                members_a = np.flatnonzero([g >= 0 and group[g] == a for g in ids])
                members_b = np.flatnonzero([g >= 0 and group[g] == b for g in ids])
                sig = np.where(np.isfinite(sigmas), sigmas, 0.0)
                value = boundary_cost_reference(
                    points[members_a],
                    points[members_b],
                    points[[k for k, _ in sides]],
                    points[[m for _, m in sides]],
                    sig[members_a],
                    sig[members_b],
                    tau,
                    noise_factor,
                    step_factor,
                    max_bend_deg,
                )
                if value <= 1.0 and (best is None or (value, a, b) < best):
                    best = (value, a, b)
        if best is None:
            break
        _, a, b = best
        for g in group:
            if group[g] == b:
                group[g] = a
    return np.array([group[g] if g >= 0 else -1 for g in ids])
