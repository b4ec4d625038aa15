"""The fast kernels of the whole-surface pass against slow, obviously correct numpy references."""

from __future__ import annotations

import dataclasses
import heapq

import numpy as np
import pytest

from ppe_ros.core import consolidation
from ppe_ros.core.consolidation import (
    _candidate_pairs,
    _consolidate_kernel,
    _dense_ids,
    _heap_remove,
    _heap_set,
    _merge_pieces,
    _no_return_runs,
    _pair_costs,
    _parallel_candidate_pairs,
    _piece_planes,
    _touching_pairs,
    _unique_pairs,
    consolidate_pieces,
)
from ppe_ros.core.fitting import fit_pixel_groups
from ppe_ros.core.planes import PlaneSet
from ppe_ros.core.scan import make_ray_scan
from ppe_ros.core.sensor import LIDAR_NOISE
from ppe_ros.core.surfaces import _kept_planes, _plane_sums


def _scene(seed: int, rows: int = 48, cols: int = 160):
    """A noisy organized scan of a floor, two walls and a box, with gaps; piece ids of 8 x 8 blocks."""
    rng = np.random.default_rng(seed)
    az = np.linspace(-np.pi, np.pi, cols, endpoint=False)
    el = np.linspace(-0.4, 0.3, rows)
    v = np.stack([np.cos(el)[:, None] * np.cos(az), np.cos(el)[:, None] * np.sin(az), np.sin(el)[:, None] + 0 * az], -1)
    with np.errstate(divide='ignore'):
        floor = np.where(v[..., 2] < -1e-3, -1.5 / v[..., 2], np.inf)
        wall = np.where(np.abs(v[..., 0]) > 1e-3, 6.0 / np.abs(v[..., 0]), np.inf)
    r = np.minimum(floor, wall)
    box = (slice(20, 30), slice(40, 55))
    r[box] = np.minimum(r[box], 3.0)
    r = r + rng.normal(0.0, 0.01, r.shape)
    r[rng.random(r.shape) < 0.05] = np.nan
    r[r > 40] = np.nan
    points = v * r[..., None]
    scan = make_ray_scan(points)
    ids = (np.arange(rows)[:, None] // 8) * 1000 + np.arange(cols)[None, :] // 8
    ids = np.where(scan.valid.reshape(rows, cols), ids, -1).reshape(-1).astype(np.int64)
    ids[rng.random(ids.size) < 0.05] = -1
    sigmas = np.where(scan.valid, LIDAR_NOISE.sigmas(np.nan_to_num(scan.ranges, nan=1.0), scan.directions), np.nan)
    return scan, ids, sigmas


def _reference_sums(scan, planes: PlaneSet, ray_sigmas, count):
    """The numpy passes _plane_sums replaced (np.bincount in pixel order)."""
    labels = planes.labels.reshape(-1)
    on = np.flatnonzero(labels > 0)
    j = labels[on] - 1
    n = planes.num_planes
    points = scan.endpoints[on] + scan.center
    centroid = np.stack([np.bincount(j, weights=points[:, a], minlength=n) for a in range(3)], 1) / count[:, None]
    rel = points - centroid[j]
    scatter = np.empty((n, 3, 3))
    for a in range(3):
        for b in range(3):
            scatter[:, a, b] = np.bincount(j, weights=rel[:, a] * rel[:, b], minlength=n) / count
    distance = np.einsum('ij,ij->i', points, planes.normals[j]) - planes.offsets[j]
    along = np.einsum('ij,ij->i', scan.directions[on], planes.normals[j]) * ray_sigmas[on]
    mean = [np.bincount(j, weights=w, minlength=n) / count for w in (distance**2, along**2, ray_sigmas[on] ** 2)]
    return centroid, scatter, *mean


@pytest.mark.parametrize('seed', [0, 1])
def test_plane_sums_equal_the_numpy_passes(seed):
    scan, ids, sigmas = _scene(seed)
    planes, _ = fit_pixel_groups(scan, ids, min_plane_points=4, residuals=False)
    count = planes.point_counts.astype(np.float64)
    got = _plane_sums(scan, planes, sigmas, count)
    want = _reference_sums(scan, planes, sigmas, count)
    assert planes.num_planes > 20
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-15)


def test_dropping_planes_from_a_fit_equals_refitting_the_kept_ones():
    scan, ids, _ = _scene(2)
    planes, _ = fit_pixel_groups(scan, ids, min_plane_points=4, residuals=False, actions=7)
    keep = np.random.default_rng(0).random(planes.num_planes) < 0.6
    kept = _kept_planes(planes, keep)
    ids_kept = np.where(np.r_[False, keep][planes.labels.reshape(-1)], planes.labels.reshape(-1), -1)
    refit, _ = fit_pixel_groups(scan, ids_kept, min_plane_points=4, residuals=False, actions=7)
    assert 0 < kept.num_planes == keep.sum() < planes.num_planes
    for name in ('labels', 'normals', 'offsets', 'centroids', 'point_counts', 'sse', 'rmse', 'covariances'):
        np.testing.assert_array_equal(getattr(kept, name), getattr(refit, name), err_msg=name)
    assert kept.labels.dtype == refit.labels.dtype and kept.actions == refit.actions


@pytest.mark.parametrize('seed', [0, 3])
def test_weighted_group_fits_sum_the_sse_as_the_residual_image_does(seed):
    """With sigmas and no residual image, fit_pixel_groups sums the sse in metres per plane
    (_metric_sse, in the fits' kernel); with the image, from the image (the numpy reference): the same planes."""
    scan0, ids, sigmas = _scene(seed)
    scan = dataclasses.replace(scan0, directions=scan0.directions * np.nan_to_num(sigmas)[:, None])
    want, image = fit_pixel_groups(
        scan, ids, min_plane_points=5, residuals=True, sigmas=sigmas, max_error_increment=2.0
    )
    got, no_image = fit_pixel_groups(
        scan, ids, min_plane_points=5, residuals=False, sigmas=sigmas, max_error_increment=2.0
    )
    assert image is not None and no_image is None
    assert got.num_planes > 20 and got.max_error_increment == 2.0
    for name in ('labels', 'normals', 'offsets', 'centroids', 'point_counts', 'covariances'):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
    np.testing.assert_allclose(got.sse, want.sse, rtol=1e-12)  # bit for bit where np.einsum sums as assumed
    np.testing.assert_allclose(got.rmse, want.rmse, rtol=1e-12)
    empty, _ = fit_pixel_groups(scan, np.full(scan.size, -1), min_plane_points=5, residuals=False, sigmas=sigmas)
    assert empty.num_planes == 0 and empty.labels.shape == (scan.height, scan.width)


@pytest.mark.parametrize('scale', [1, 10**9])  # ids below the pixel count (the kernel) and far beyond (np.unique)
def test_dense_ids_equal_numpy_unique(scale):
    rng = np.random.default_rng(4)
    ids = rng.integers(-3, 500, 4000) * scale
    ids[ids < 0] = rng.integers(-5, 0, (ids < 0).sum())
    labels, dense = _dense_ids(ids)
    uniq = np.unique(ids[ids >= 0])
    np.testing.assert_array_equal(labels, uniq)
    np.testing.assert_array_equal(dense, np.where(ids >= 0, np.searchsorted(uniq, ids), -1))
    assert _dense_ids(np.full(5, -1, np.int64))[0].size == 0


def test_unique_pairs_equal_numpy_unique_rows():
    rng = np.random.default_rng(5)
    a = rng.integers(0, 300, 5000)
    pairs = np.stack([a, a + rng.integers(1, 40, 5000)], 1).astype(np.int64)
    want = np.unique(pairs, axis=0)
    np.testing.assert_array_equal(_unique_pairs(pairs, 340), want)
    assert _unique_pairs(np.zeros((0, 2), np.int64), 3).shape == (0, 2)


def test_the_indexed_heap_keeps_one_entry_per_edge_and_its_first_is_the_least():
    """_heap_set / _heap_remove against a dict of edge -> (cost, a, b) whose least value is the first;
    few distinct costs, so that ties are decided by the pieces; positions stay consistent."""
    rng = np.random.default_rng(6)
    m = 400
    hkey, hpair, hedge, where = np.empty(m), np.empty((m, 2), np.int64), np.empty(m, np.int64), np.full(m, -1)
    size, reference, popped = 0, {}, 0
    for _ in range(20000):
        e = int(rng.integers(0, m))
        action = rng.random()
        if action < 0.55:
            key = (float(rng.integers(0, 5)) / 4, e % 7, e)  # (cost, a, b): b = e keeps (a, b) unique
            size = _heap_set(hkey, hpair, hedge, where, size, e, *key)
            reference[e] = key
        elif action < 0.8:
            size = _heap_remove(hkey, hpair, hedge, where, size, e)
            reference.pop(e, None)
        elif size:
            first = int(hedge[0])
            assert reference[first] == min(reference.values())
            assert (hkey[0], hpair[0, 0], hpair[0, 1]) == reference.pop(first)
            size = _heap_remove(hkey, hpair, hedge, where, size, first)
            popped += 1
        assert size == len(reference)
        queued = {int(hedge[i]): (hkey[i], hpair[i, 0], hpair[i, 1]) for i in range(size)}
        assert queued == reference
        assert all(where[hedge[i]] == i for i in range(size)) and np.sum(where >= 0) == size
    assert popped > 2000


def _lazy_heap_merges(moments, pairs, tau2, noise_factor2):
    """The merge loop with Python's heapq and lazy deletion (versions): the definition the kernel's
    indexed heap must reproduce."""
    mom = [row.copy() for row in moments]
    parent, version = list(range(len(mom))), [0] * len(mom)
    neighbours = [set() for _ in mom]
    heap = []

    def find(x):
        while parent[x] != x:
            x = parent[x]
        return x

    def push(a, b):
        lo, hi = min(a, b), max(a, b)
        cost = consolidation.merge_cost(mom[lo], mom[hi], np.sqrt(tau2), np.sqrt(noise_factor2))
        if cost <= 1.0:
            heapq.heappush(heap, (cost, lo, hi, version[lo], version[hi]))

    for a, b in pairs:
        neighbours[a].add(int(b))
        neighbours[b].add(int(a))
        push(int(a), int(b))
    while heap:
        _, a, b, va, vb = heapq.heappop(heap)
        if parent[a] != a or parent[b] != b or (version[a], version[b]) != (va, vb):
            continue
        parent[b] = a
        mom[a] = mom[a] + mom[b]
        version[a] += 1
        neighbours[a] = {find(c) for c in neighbours[a] | neighbours[b]} - {a}
        for c in sorted(neighbours[a]):
            push(a, c)
    return np.array([find(x) for x in range(len(mom))])


def test_the_merge_loop_equals_a_lazy_heapq_loop_on_a_scene_of_many_pieces():
    scan, ids, sigmas = _scene(9, rows=64)
    labels, dense = _dense_ids(ids)
    sig = np.ascontiguousarray(np.nan_to_num(sigmas))
    moments = consolidation._piece_moments(dense, scan.endpoints, sig, len(labels))
    normals, means, _ = _piece_planes(moments)
    no_return = _no_return_runs(scan.ranges, dense, scan.height, scan.width)
    found = _candidate_pairs(
        dense, scan.endpoints, scan.directions, scan.ranges, sig, no_return, scan.height, scan.width,
        normals, means, 0.05, 16, False, 0, scan.size,
    )  # fmt: skip
    pairs = _unique_pairs(found, len(labels))
    roots = _merge_pieces(moments, pairs, 0.05**2, 1.0)
    np.testing.assert_array_equal(roots, _lazy_heap_merges(moments, pairs, 0.05**2, 1.0))
    plane_rows, costs = _pair_costs(moments, pairs, 0.05**2, 1.0, 1.0)
    np.testing.assert_array_equal(_consolidate_kernel(moments, pairs, plane_rows, costs, 0.05**2, 1.0, 1.0), roots)
    assert len(np.unique(roots)) < len(labels) / 2  # the scene's blocks merge into surfaces


def test_the_pairs_first_costs_are_merge_cost_of_each_pair_in_every_block():
    """_pair_costs values pieces and pairs in parallel blocks: each row and cost equals the serial
    _plane_of and merge_cost of that piece or pair (more pieces and pairs than one block)."""
    rng = np.random.default_rng(11)
    n_pieces = 2 * consolidation._COST_BLOCK + 37
    points = rng.normal(0.0, 1.0, (n_pieces, 20, 3)) * np.array([2.0, 1.0, 0.01]) + rng.normal(
        0.0, 3.0, (n_pieces, 1, 3)
    )
    moments = np.zeros((n_pieces, 11))
    for g in range(n_pieces):
        moments[g] = consolidation._piece_moments(np.zeros(20, np.int64), points[g], np.full(20, 0.02), 1)[0]
    a = rng.integers(0, n_pieces, 3 * consolidation._COST_BLOCK + 5)
    b = (a + rng.integers(1, n_pieces, len(a))) % n_pieces
    pairs = np.ascontiguousarray(np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1))
    plane_rows, costs = _pair_costs(moments, pairs, 0.05**2, 1.0, 1.0)
    expected_rows = np.empty((n_pieces, 13))
    for g in range(n_pieces):
        consolidation._plane_of(moments[g], expected_rows[g])
    np.testing.assert_array_equal(plane_rows, expected_rows)
    expected = np.array([consolidation.merge_cost(moments[i], moments[j], 0.05, 1.0) for i, j in pairs])
    admissible = expected <= 1.0
    assert 0 < np.count_nonzero(admissible) < len(costs)  # both kinds of pairs
    # an admissible pair gets its cost; an inadmissible one a value above 1 (the cost or a bound of it)
    np.testing.assert_array_equal(costs[admissible], expected[admissible])
    assert np.all(costs[~admissible] > 1.0)
    assert np.all(costs[~admissible] <= expected[~admissible] * (1 + 1e-9))


def _piece_pair_moments(rng, n_pairs: int) -> tuple[np.ndarray, np.ndarray]:
    """Moments of random pairs of planar pieces side by side (20-400 points each, 1 cm noise, up to 60 m
    out): the second tilted against the first by up to 3 deg (half of the pairs) or 10-90 deg, and
    raised by up to 15 cm along the first's normal."""
    moments = np.zeros((2, n_pairs, 11))
    for p in range(n_pairs):
        center = rng.uniform(-60.0, 60.0, 3)
        normal = rng.normal(size=3)
        normal /= np.linalg.norm(normal)
        along = np.cross(normal, rng.normal(size=3))
        along /= np.linalg.norm(along)
        tilt = np.radians(rng.uniform(0.0, 3.0) if p % 2 else rng.uniform(10.0, 90.0))
        for side in (0, 1):
            n_side = np.cos(side * tilt) * normal + np.sin(side * tilt) * along
            u = np.cross(n_side, along if side == 0 else normal)
            u /= np.linalg.norm(u)
            w = np.cross(n_side, u)
            count = int(rng.integers(20, 400))
            extent = rng.uniform(0.2, 3.0)
            s, t = rng.uniform(-extent, extent, (2, count))
            origin = center + (side - 0.5) * 2.0 * extent * along + side * rng.uniform(0.0, 0.15) * normal
            points = origin + np.outer(s, u) + np.outer(t, w) + np.outer(rng.normal(0.0, 0.01, count), n_side)
            one_piece = np.zeros(count, np.int64)
            moments[side, p] = consolidation._piece_moments(one_piece, points, np.full(count, 0.02), 1)[0]
    return moments[0], moments[1]


def test_the_step_bound_is_below_the_merge_cost_and_decides_the_offset_pairs():
    """_step_bound (no eigen solve) never exceeds _merge_cost, so a pair it puts above 1 is inadmissible;
    _merge_cost_or_bound returns the cost where that is at most 1 and a value above 1 otherwise. The bound
    must decide a share of the inadmissible pairs (else it saves nothing): those whose planes are apart."""
    rng = np.random.default_rng(3)
    first, second = _piece_pair_moments(rng, 400)
    decided = inadmissible = 0
    tau2, kappa2 = 0.05**2, 1.5**2
    for lam2 in (0.0, 9.0):
        for m_a, m_b in zip(first, second, strict=True):
            mom = np.stack([m_a, m_b])
            plane = np.empty((2, 13))
            consolidation._plane_of(mom[0], plane[0])
            consolidation._plane_of(mom[1], plane[1])
            cost = consolidation._merge_cost(mom, plane, 0, 1, tau2, lam2, kappa2)
            bound = consolidation._step_bound(mom, plane, 0, 1, tau2, lam2, kappa2)
            assert bound <= cost * (1 + 1e-9) + 1e-12
            value = consolidation._merge_cost_or_bound(mom, plane, 0, 1, tau2, lam2, kappa2)
            if cost <= 1.0:
                assert value == cost
                continue
            assert value > 1.0
            inadmissible += 1
            decided += bound > 1.0 + consolidation._BOUND_MARGIN
    assert inadmissible > 200
    assert decided > 0.3 * inadmissible


@pytest.mark.parametrize('seed', [0, 1])
def test_touching_pairs_are_the_distinct_4_neighbour_pairs(seed):
    rng = np.random.default_rng(seed)
    height, width = 23, 31
    ids = rng.integers(0, 12, (height, width)).repeat(2, axis=1)[:, :width]  # runs: repeated pairs
    ids[rng.random(ids.shape) < 0.2] = -1
    flat = np.ascontiguousarray(ids.ravel(), dtype=np.int64)
    want = set()
    for i in range(height):
        for j in range(width):
            for di, dj in ((0, 1), (1, 0)):
                if i + di < height and j + dj < width:
                    a, b = ids[i, j], ids[i + di, j + dj]
                    if a >= 0 and b >= 0 and a != b:
                        want.add((min(a, b), max(a, b)))
    found = _touching_pairs(flat, width, 0, flat.size)
    assert {tuple(p) for p in found.tolist()} == want and len(want) > 30
    assert (found[:, 0] < found[:, 1]).all()
    assert len(found) < 2 * flat.size
    # row blocks find the same pairs, repeats included: a block starts a row
    cut = 9 * width
    blocks = np.concatenate([_touching_pairs(flat, width, 0, cut), _touching_pairs(flat, width, cut, flat.size)])
    np.testing.assert_array_equal(np.sort(blocks, axis=0), np.sort(found, axis=0))


@pytest.mark.parametrize('connected_only', [False, True])
def test_candidate_pairs_in_row_blocks_equal_one_pass(monkeypatch, connected_only):
    import numba

    scan, ids, sigmas = _scene(7, rows=64)
    labels, dense = _dense_ids(ids)
    moments = consolidation._piece_moments(dense, scan.endpoints, np.nan_to_num(sigmas), len(labels))
    normals, means, _ = _piece_planes(moments)
    args = (np.ascontiguousarray(sigmas), normals, means, 0.05, 16, connected_only)
    no_return = _no_return_runs(scan.ranges, dense, scan.height, scan.width)
    whole = _candidate_pairs(
        dense,
        scan.endpoints,
        scan.directions,
        scan.ranges,
        args[0],
        no_return,
        scan.height,
        scan.width,
        *args[1:],
        0,
        scan.size,
    )
    monkeypatch.setattr(consolidation, 'PARALLEL_MIN_PIXELS', 1)
    previous = numba.get_num_threads()
    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    try:
        blocks = _parallel_candidate_pairs(dense, scan, *args)
    finally:
        numba.set_num_threads(previous)
    assert len(whole) > 100
    np.testing.assert_array_equal(np.unique(blocks, axis=0), np.unique(whole, axis=0))
    np.testing.assert_array_equal(np.sort(blocks, axis=0), np.sort(whole, axis=0))  # the same repeats too


def test_consolidation_of_the_scene_is_independent_of_the_thread_count(monkeypatch):
    import numba

    scan, ids, sigmas = _scene(8, rows=64)
    one = consolidate_pieces(scan, ids, sigmas, 0.05, noise_factor=1.0, wrap_columns=True)
    monkeypatch.setattr(consolidation, 'PARALLEL_MIN_PIXELS', 1)
    previous = numba.get_num_threads()
    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    try:
        two = consolidate_pieces(scan, ids, sigmas, 0.05, noise_factor=1.0, wrap_columns=True)
    finally:
        numba.set_num_threads(previous)
    assert len(np.unique(one[one >= 0])) < len(np.unique(ids[ids >= 0]))
    np.testing.assert_array_equal(one, two)


def _groups(ids: np.ndarray) -> np.ndarray:
    """Each pixel's group numbered by its first pixel (-1: none): equal for equal partitions."""
    out = np.full(ids.shape, -1, np.int64)
    on = ids >= 0
    _, first, inverse = np.unique(ids[on], return_index=True, return_inverse=True)
    out[on] = np.flatnonzero(on)[first][inverse]
    return out


@pytest.mark.parametrize(('seed', 'connected_only', 'wrap'), [(9, False, True), (10, True, False), (11, False, False)])
def test_consolidated_surfaces_group_the_rays_as_consolidate_then_absorb(seed, connected_only, wrap):
    scan, ids, sigmas = _scene(seed, rows=40)
    ids = ids.copy()
    ids[::97] = np.where(ids[::97] >= 0, 10**6 + np.arange(len(ids[::97])), -1)  # pieces of one ray
    kw = {'noise_factor': 1.0, 'connected_only': connected_only, 'wrap_columns': wrap}
    merged = consolidation.consolidate_pieces(scan, ids, sigmas, 0.05, **kw)
    want = consolidation.absorb_rays(scan, merged, sigmas, 0.05, noise_factor=1.0, min_points=6, wrap_columns=wrap)
    got = consolidation.consolidated_surfaces(scan, ids, sigmas, 0.05, min_points=6, **kw).copy()
    assert 3 < len(np.unique(want[want >= 0])) < len(np.unique(ids[ids >= 0]))
    np.testing.assert_array_equal(_groups(got), _groups(want))
    big = consolidation.consolidated_surfaces(
        scan, np.where(ids >= 0, ids * 10**9, -1), sigmas, 0.05, min_points=6, **kw
    )
    np.testing.assert_array_equal(_groups(big), _groups(want))  # ids far beyond the pixel count (np.unique)
    none = consolidation.consolidated_surfaces(scan, np.full(scan.size, -1), sigmas, 0.05)
    assert (none == -1).all()


def _reference_columns_wrap(valid: np.ndarray, directions: np.ndarray) -> bool:
    """The numpy test that _last_next_to_first replaced."""
    both = valid[:, 1:] & valid[:, :-1]
    seam_both = valid[:, -1] & valid[:, 0]
    if np.count_nonzero(both) < 4 or not seam_both.any():
        return False
    steps = np.einsum('ijk,ijk->ij', directions[:, 1:], directions[:, :-1])[both]
    seam = np.einsum('ik,ik->i', directions[:, -1], directions[:, 0])[seam_both]
    step_angle = np.median(np.arccos(np.clip(steps, -1.0, 1.0)))
    return float(np.median(np.arccos(np.clip(seam, -1.0, 1.0)))) <= 2.0 * float(step_angle)


def test_the_seam_test_equals_the_numpy_medians():
    rng = np.random.default_rng(12)
    for trial in range(40):
        rows, cols = int(rng.integers(1, 6)), int(rng.integers(8, 40))
        span = rng.uniform(1.5, 2.2) * np.pi  # around a full revolution: the seam step near the others
        az = np.linspace(0.0, span, cols, endpoint=False) + rng.normal(0, 0.01, cols)
        el = rng.uniform(-0.3, 0.3, (rows, 1))
        d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) + 0 * az], -1)
        valid = rng.random((rows, cols)) < (0.5 if trial % 3 else 0.95)
        want = _reference_columns_wrap(valid, d)
        assert consolidation._last_next_to_first(valid, d) == want
        steps = consolidation._reusable('t', rows * (cols - 1), np.float64)
        seam = consolidation._reusable('u', rows, np.float64)
        n_steps, n_seam = consolidation._neighbour_dots(valid, d, steps, seam)
        both = valid[:, 1:] & valid[:, :-1]
        assert n_seam == np.count_nonzero(valid[:, -1] & valid[:, 0])
        np.testing.assert_allclose(steps[:n_steps], np.einsum('ijk,ijk->ij', d[:, 1:], d[:, :-1])[both], rtol=1e-15)
        if n_steps:
            want_median = np.median(np.arccos(np.clip(steps[:n_steps], -1.0, 1.0)))
            assert consolidation._median_angle(steps[:n_steps].copy()) == want_median


def test_the_median_angle_test_counts_as_the_sorted_median_decides():
    """_median_angle_at_least (no sort) against np.median of the angles, with repeated angles, both
    parities, cosines rounded beyond 1, and thresholds on either side of the median and between the two
    middle angles of an even count (not on a tie itself: there the arccos of numba and numpy may
    differ in the last bit)."""
    from ppe_ros.core.consolidation import _median_angle_at_least

    rng = np.random.default_rng(5)
    decided = {True: 0, False: 0}
    for _ in range(3000):
        n = int(rng.integers(1, 12))
        cosines = np.cos(rng.choice(rng.uniform(0.0, 3.0, 5), n))
        cosines[rng.random(n) < 0.1] = 1.0 + 1e-15  # a dot product of unit vectors rounded up
        angles = np.sort(np.arccos(np.clip(cosines, -1.0, 1.0)))
        median = float(np.median(angles))
        middle = angles[n // 2 - 1 : n // 2 + 1] if n % 2 == 0 else angles[n // 2 : n // 2 + 1]
        thresholds = [median * (1 + 1e-9), median * (1 - 1e-9), 0.5 * (middle[0] + median), rng.uniform(0, 3), 0.0]
        for threshold in thresholds:
            if abs(threshold - median) <= 1e-12 * max(median, 1.0):
                continue
            want = median >= threshold
            assert _median_angle_at_least(cosines, threshold) == want, (cosines, threshold)
            decided[want] += 1
    assert min(decided.values()) > 1000
    assert not _median_angle_at_least(np.zeros(0), 0.0)


def test_the_public_release_frees_the_whole_surface_work_memory_too():
    from scenes import cast_scan, plane

    from ppe_ros import extract_planes, release_work_memory

    scan = cast_scan(
        [plane([-1, 0, 0], -4.0)], rows=30, cols=40, position=(0, 0, 0), azimuth_fov_deg=40, elevation_fov_deg=30,
        noise=0.01, seed=0,
    )  # fmt: skip
    extract_planes(scan.points, sensor='lidar')
    assert getattr(consolidation._work_memory, 'buffers', {})  # the pass kept its arrays
    release_work_memory()
    assert consolidation._work_memory.buffers == {}


def test_no_return_runs_count_the_rays_without_a_return_and_a_piece_back_along_rows_and_columns():
    rng = np.random.default_rng(3)
    height, width = 9, 13
    ranges = np.where(rng.random(height * width) < 0.5, np.nan, 1.0)
    ids = np.where(rng.random(height * width) < 0.2, 4, -1)
    runs = _no_return_runs(ranges, ids, height, width)
    empty = (~np.isfinite(ranges) & (ids < 0)).reshape(height, width)
    for i in range(height):
        for j in range(width):
            left = 0
            while j - left >= 0 and empty[i, j - left]:
                left += 1
            up = 0
            while i - up >= 0 and empty[i - up, j]:
                up += 1
            assert (runs[0, i * width + j], runs[1, i * width + j]) == (left, up)
    assert runs.max() >= 3
