"""GreedyOptions: the greedy's tuning knobs as one checked, frozen object passed as ``options=``."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scenes import room_scan

from ppe_ros.core.extraction import DEFAULT_OPTIONS, GreedyOptions, extract_plane_hierarchy
from ppe_ros.core.fitting import fit_with_information
from ppe_ros.core.ppe.api import _profile_greedy_options
from ppe_ros.core.ppe.layout import (
    _NPF,
    _PE,
    _PH,
    _PW,
    DEFAULT_EXACT_PLANE_SIZE,
    MERGE_LOOP_GROWTH,
    REFINED_MERGE_GROWTH,
    TETROMINO_OFFSETS,
)
from ppe_ros.core.ppe.state import _candidate_increment, _hybrid_merge, _one_step_sse, _set_exact_state, _union_fit
from ppe_ros.core.sensor import LIDAR_NOISE, PROFILES, SensorProfile
from ppe_ros.core.synthetic import plane_scan


def test_the_defaults_are_the_documented_ones():
    assert DEFAULT_OPTIONS == GreedyOptions()
    assert dataclasses.asdict(DEFAULT_OPTIONS) == {
        'exact_plane_size': DEFAULT_EXACT_PLANE_SIZE,
        'exact_merge_size': 0,
        'relinearisation_drift': 1e-2,
        'refined_merge_growth': REFINED_MERGE_GROWTH,
        'merge_loop_growth': MERGE_LOOP_GROWTH,
        'defer_merges': True,
        'candidate_fits': 'exact',
        'fit_tolerance': 1e-13,
        'seed_shapes': 'all',
        'block_seeds': False,
        'pool_capacity': None,
    }
    assert (DEFAULT_EXACT_PLANE_SIZE, REFINED_MERGE_GROWTH, MERGE_LOOP_GROWTH) == (32, 0.125, 1 / 512)


def test_options_are_frozen_and_normalised():
    options = GreedyOptions(exact_plane_size=np.int64(40), exact_merge_size=8.0, defer_merges=0, pool_capacity=3.0)
    assert (options.exact_plane_size, options.exact_merge_size, options.defer_merges, options.pool_capacity) == (
        40,
        8,
        False,
        3,
    )
    assert type(options.exact_plane_size) is int and type(options.pool_capacity) is int
    with pytest.raises(dataclasses.FrozenInstanceError):
        options.exact_plane_size = 5


@pytest.mark.parametrize(
    ('field', 'value', 'message'),
    [
        ('exact_plane_size', 3, 'exact_plane_size must be >= 4'),
        ('exact_plane_size', 4.5, 'exact_plane_size must be a whole number'),
        ('exact_merge_size', True, 'exact_merge_size must be a whole number'),
        ('pool_capacity', 0, 'pool_capacity must be >= 1'),
        ('pool_capacity', 2.5, 'pool_capacity must be a whole number'),
        ('relinearisation_drift', -1e-3, 'relinearisation_drift must be >= 0'),
        ('relinearisation_drift', np.nan, 'relinearisation_drift must be >= 0'),
        ('refined_merge_growth', np.inf, 'refined_merge_growth must be a finite fraction'),
        ('merge_loop_growth', -0.5, 'merge_loop_growth must be a finite fraction'),
        ('candidate_fits', 'approximate', "candidate_fits must be 'exact' or 'one_step'"),
        ('candidate_fits', ['exact'], "candidate_fits must be 'exact' or 'one_step'"),
        ('fit_tolerance', 0.0, 'fit_tolerance must be a number in'),
        ('fit_tolerance', 1.0, 'fit_tolerance must be a number in'),
        ('fit_tolerance', np.nan, 'fit_tolerance must be a number in'),
        ('fit_tolerance', True, 'fit_tolerance must be a number in'),
    ],
)
def test_bad_options_raise_an_error_naming_the_field(field, value, message):
    with pytest.raises(ValueError, match=message):
        GreedyOptions(**{field: value})


def test_options_reach_the_greedy_and_only_a_greedy_options_is_accepted():
    points = plane_scan(3, radial_sigma=0.01).points
    default = extract_plane_hierarchy(points)
    assert np.array_equal(extract_plane_hierarchy(points, options=DEFAULT_OPTIONS).actions, default.actions)
    # every evaluation exact: more exact fits than with the model for planes above 32 rays
    exact = extract_plane_hierarchy(points, options=GreedyOptions(exact_plane_size=10**9, exact_merge_size=10**9))
    assert exact.stats['relinearisations'] == 0 < default.stats['relinearisations']
    with pytest.raises(TypeError, match='options must be a GreedyOptions'):
        extract_plane_hierarchy(points, options={'exact_plane_size': 64})
    with pytest.raises(TypeError):
        extract_plane_hierarchy(points, exact_plane_size=64)  # the knobs are no keywords any more


def _small_plane(seed: int, count: int = 12):
    """A plane row (pf) fitted exactly to ``count`` noisy rays of a tilted plane, and one more ray."""
    rng = np.random.default_rng(seed)
    directions = rng.normal([0.3, 0.2, 1.0], 0.15, size=(count + 1, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    normal = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])
    ranges = 3.0 / (directions @ normal) + rng.normal(0.0, 0.01, count + 1)
    endpoints = directions * ranges[:, None]
    pf = np.zeros((1, _NPF))
    idx = np.arange(count + 1, dtype=np.int64)
    _set_exact_state(endpoints, directions, pf, idx, count, 0, np.nan, np.nan, np.nan)
    return endpoints, directions, pf, idx


def _one_step_reference(endpoints, directions, pf, count):
    """One Gauss-Newton step from the plane's fit with the last ray added, in plain numpy."""
    w = pf[0, _PW : _PW + 3]
    a00, a01, a02, a11, a12, a22 = pf[0, _PH : _PH + 6]
    information = np.array([[a00, a01, a02], [a01, a11, a12], [a02, a12, a22]])
    p, v = endpoints[count], directions[count]
    f = (w @ p - 1.0) / (w @ v)
    g = (p - f * v) / (w @ v)
    step = np.linalg.solve(information + np.outer(g, g), f * g)
    moved = w - step
    residuals = (endpoints[: count + 1] @ moved - 1.0) / (directions[: count + 1] @ moved)
    return float(residuals @ residuals), moved


@pytest.mark.parametrize('seed', range(5))
def test_a_one_step_candidate_is_one_gauss_newton_step_and_bounds_the_exact_fit(seed):
    """state._one_step_sse against plain numpy: the SSE at w - (H + g g^T)^-1 f g; at least the exact fit's
    SSE of the same rays (a minimum), and within 1e-3 of it (relative) for a ray on the plane."""
    count = 12
    endpoints, directions, pf, idx = _small_plane(seed, count)
    sse, w0, w1, w2 = _one_step_sse(endpoints, directions, pf, 0, idx, count + 1, count)
    expected, moved = _one_step_reference(endpoints, directions, pf, count)
    assert sse == pytest.approx(expected, rel=1e-10)
    np.testing.assert_allclose([w0, w1, w2], moved, rtol=1e-10)
    exact, _, _, _, _ = fit_with_information(endpoints, directions, idx, count + 1, w0, w1, w2, 50, 1e-15)
    assert exact <= sse * (1 + 1e-12)
    increment = sse - pf[0, _PE]
    assert increment == pytest.approx(exact - pf[0, _PE], rel=1e-3)


def test_candidate_increment_one_step_keeps_its_w_for_the_exact_fit_of_the_execution():
    """_candidate_increment with one_step: the one-step SSE and w in the plane's candidate cache with NaN
    information (the execution fits from there); exact: the converged fit, with its information."""
    count = 12
    endpoints, directions, pf, idx = _small_plane(7, count)
    ecache_i = np.full((1, 2), -1, np.int32)
    ecache_f = np.zeros((1, 10))
    one_step = _candidate_increment(
        endpoints, directions, pf, 0, True, idx, count, count, 3, ecache_i, ecache_f, True, 1e-6
    )
    expected, moved = _one_step_reference(endpoints, directions, pf, count)
    assert one_step == pytest.approx(expected - pf[0, _PE], rel=1e-10)
    assert tuple(ecache_i[0]) == (count, 3)
    np.testing.assert_allclose(ecache_f[0, 1:4], moved, rtol=1e-10)
    assert np.isnan(ecache_f[0, 4:]).all()
    exact = _candidate_increment(
        endpoints, directions, pf, 0, True, idx, count, count, 4, ecache_i, ecache_f, False, 1e-13
    )
    assert exact <= one_step and exact == pytest.approx(one_step, rel=1e-3)
    assert np.isfinite(ecache_f[0, 4:]).all()


@pytest.mark.parametrize('seed', range(3))
def test_the_one_step_greedy_follows_the_exact_one_until_increments_this_close_reorder_it(seed):
    """A room scan with and without the lidar noise model: GreedyOptions(candidate_fits='one_step') takes the
    same actions as the exact greedy for at least the first 40 % of the log, with increments at or above
    the exact ones by at most 1e-3 (relative), and its cut has as many planes."""
    scan = room_scan(rows=60, cols=80, noise=0.02, seed=seed)
    for noise, e in ((None, 0.01), (LIDAR_NOISE, 16.0)):
        runs = {
            fits: extract_plane_hierarchy(
                scan.points,
                origins=scan.origins,
                max_error_increment=e,
                noise=noise,
                options=GreedyOptions(candidate_fits=fits),
            )
            for fits in ('exact', 'one_step')
        }
        exact, one_step = runs['exact'].actions, runs['one_step'].actions
        n = min(len(exact), len(one_step))
        same = np.ones(n, bool)
        for field in ('kind', 'a', 'b'):
            same &= exact[field][:n] == one_step[field][:n]
        common = int(np.argmin(same)) if not same.all() else n
        assert common >= 0.4 * len(exact)
        relative = (one_step['increment'][:common] - exact['increment'][:common]) / np.maximum(
            exact['increment'][:common], 1e-300
        )
        assert relative.min() >= -1e-9 and relative.max() <= 1e-3
        assert relative.max() > 0.0  # the one-step values are not the exact ones
        planes = [runs[f].cut(max_error_increment=e, min_plane_points=20).num_planes for f in ('exact', 'one_step')]
        assert planes[0] == planes[1]


def test_the_profiles_greedy_options():
    """The lidar profile runs the greedy with squares and one-step candidates at a 1e-6 fit tolerance (block
    seeds when its copy asks for them); the depth camera profile with the exact greedy's candidates at a 1e-9
    fit tolerance, the paper's profile with the exact greedy."""
    assert _profile_greedy_options(PROFILES['lidar']) == GreedyOptions(
        seed_shapes='square', candidate_fits='one_step', fit_tolerance=1e-6
    )
    with_blocks = dataclasses.replace(PROFILES['lidar'], block_seeds=True)
    assert _profile_greedy_options(with_blocks) == GreedyOptions(
        seed_shapes='square', candidate_fits='one_step', fit_tolerance=1e-6, block_seeds=True
    )
    assert _profile_greedy_options(PROFILES['depth_camera']) == GreedyOptions(fit_tolerance=1e-9)
    assert _profile_greedy_options(PROFILES['paper']) == GreedyOptions()
    with pytest.raises(ValueError, match='candidate_fits'):
        SensorProfile(name='mine', candidate_fits='fast')
    with pytest.raises(ValueError, match='fit_tolerance'):
        SensorProfile(name='mine', fit_tolerance=-1.0)


def test_fit_tolerance_reaches_the_union_fit_and_the_hybrid_merge():
    """A loose tolerance stops the union fit and the hybrid merge earlier: a higher (not lower) SSE than at
    the exact greedy's 1e-13, and already close to it."""
    endpoints, directions, pf, idx = _small_plane(11, count=24)
    pf = np.vstack([pf, pf])
    first = np.arange(12, dtype=np.int64)
    _set_exact_state(endpoints, directions, pf, first, 12, 0, np.nan, np.nan, np.nan)
    _set_exact_state(endpoints, directions, pf, np.arange(12, 24, dtype=np.int64), 12, 1, np.nan, np.nan, np.nan)
    tight = _union_fit(endpoints, directions, pf, idx, 24, 0, 1, 1e-13)
    loose = _union_fit(endpoints, directions, pf, idx, 24, 0, 1, 0.5)
    assert tight[0] < loose[0] <= tight[0] * 1.01
    start = pf[0, _PW : _PW + 3] * 1.01
    rays = np.arange(12, 24, dtype=np.int64)
    tight = _hybrid_merge(endpoints, directions, pf, 0, rays, 12, *start, 1e-13)
    loose = _hybrid_merge(endpoints, directions, pf, 0, rays, 12, *start, 0.5)
    assert tight[0] < loose[0] <= tight[0] * 1.01


@pytest.mark.parametrize('seed_shapes', ['all', 'square'])
def test_fit_tolerance_reaches_the_seeds(seed_shapes):
    """Every create's increment is its tetromino's fit at the options' fit_tolerance (bit for bit), and with
    a loose tolerance some creates differ from the exact greedy's seed fits."""
    scan_in = room_scan(rows=30, cols=40, noise=0.02, seed=3)
    increments = {}
    for tolerance in (1e-13, 1e-6):
        options = GreedyOptions(seed_shapes=seed_shapes, fit_tolerance=tolerance)
        hierarchy = extract_plane_hierarchy(scan_in.points, origins=scan_in.origins, options=options)
        creates = hierarchy.actions[hierarchy.actions['kind'] == 0]
        assert len(creates) > 50
        scan = hierarchy.scan
        for anchor, config, increment in zip(creates['a'], creates['b'], creates['increment'], strict=True):
            i, j = divmod(int(anchor), scan.width)
            idx = ((i + TETROMINO_OFFSETS[config, :, 0]) * scan.width + j + TETROMINO_OFFSETS[config, :, 1]).astype(
                np.int64
            )
            sse = fit_with_information(scan.endpoints, scan.directions, idx, 4, np.nan, np.nan, np.nan, 50, tolerance)[
                0
            ]
            assert increment == sse, (tolerance, anchor, config)
            increments[tolerance, int(anchor), int(config)] = increment
    loose = [key for key in increments if key[0] == 1e-6 and (1e-13, *key[1:]) in increments]
    assert len(loose) > 50
    assert sum(increments[key] != increments[(1e-13, *key[1:])] for key in loose) > 0
