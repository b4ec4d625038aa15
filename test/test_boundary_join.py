"""The boundary round (ppe_ros.core.boundary_join): large surfaces that meet where they touch become one."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
from reference_consolidation import boundary_cost_reference, boundary_join_reference, cost

from ppe_ros.core.boundary_join import (
    BOUNDARY_GAP,
    MIN_BOUNDARY_PAIRS,
    _boundary_cost,
    _boundary_pixel_pairs,
    _side_moments,
    join_at_boundaries,
)
from ppe_ros.core.consolidation import _piece_moments, _plane_rows
from ppe_ros.core.scan import make_ray_scan
from ppe_ros.core.sensor import PROFILES, SensorProfile
from ppe_ros.core.surfaces import _consolidate

TAU = 0.05
ROWS, COLS, STEP = 20, 60, 0.1  # a 2 m x 6 m patch of ground, 10 cm between rays


def _ground(height_of_x, *, noise: float = 0.005, seed: int = 0) -> np.ndarray:
    """(ROWS, COLS, 3) points on z = height_of_x(x) (x along the columns, y along the rows), with noise."""
    x, y = np.meshgrid(np.arange(COLS) * STEP, np.arange(ROWS) * STEP)
    z = height_of_x(x) + np.random.default_rng(seed).normal(0.0, noise, x.shape)
    return np.stack([x, y, z], axis=-1)


def _halves(points: np.ndarray, *, gap: int = 0):
    """The scan of ``points`` seen from 2 m above, its left half surface 0 and its right half surface 1,
    with ``gap`` columns between them in no surface."""
    scan = make_ray_scan(points, np.array([3.0, 1.0, 2.0]))
    ids = np.zeros((ROWS, COLS), np.int64)
    ids[:, COLS // 2 :] = 1
    ids[:, COLS // 2 : COLS // 2 + gap] = -1
    return scan, ids.reshape(-1), np.full(scan.size, 0.02)


def _crown(slope: float = np.tan(np.radians(1.1))):
    return lambda x: -slope * np.abs(x - STEP * COLS / 2)  # each half falls 1.1 deg to its side


def _join(scan, ids, sigmas, **options):
    return join_at_boundaries(scan, ids, sigmas, TAU, options.pop('min_points', 300), **options)


def test_the_halves_of_a_cambered_road_join_although_their_means_are_a_step_apart():
    scan, ids, sigmas = _halves(_ground(_crown()))
    left, right = scan.endpoints[ids == 0], scan.endpoints[ids == 1]
    # the consolidation's own pairwise test: the planes 6 cm apart at the other half's mean
    assert cost(left, right, sigmas[ids == 0], sigmas[ids == 1], TAU, 0.0) > 1.0
    out = _join(scan, ids, sigmas)
    assert np.array_equal(out, np.zeros_like(ids))


@pytest.mark.parametrize(
    'height_of_x',
    [
        lambda x: np.where(x >= STEP * COLS / 2, 0.12, 0.0),  # a 12 cm kerb
        lambda x: np.where(x >= STEP * COLS / 2, -0.10, 0.0),  # a window recessed by 10 cm
        lambda x: np.where(x >= STEP * COLS / 2, (x - STEP * COLS / 2) * np.tan(np.radians(5)), 0.0),  # a 5 deg ramp
    ],
    ids=['kerb', 'recess', 'ramp'],
)
def test_a_step_or_a_ramp_between_two_flat_surfaces_keeps_them_apart(height_of_x):
    scan, ids, sigmas = _halves(_ground(height_of_x))
    assert np.array_equal(_join(scan, ids, sigmas), ids)


def test_a_kerb_stays_apart_when_rays_of_the_road_joined_the_pavement_next_to_it():
    """The pavement's side of the boundary then lies on the road's plane; the road's side still lies the
    kerb's height off the pavement's: each side is tested on its own (a mean of both would pass 6.5 cm)."""
    scan, ids, sigmas = _halves(_ground(lambda x: np.where(x >= STEP * COLS / 2, 0.065, 0.0)))
    grid = ids.reshape(ROWS, COLS)
    grid[grid == 0], grid[grid == 1] = 2, 0  # the pavement (right) is surface 0, the road (left) surface 1
    grid[grid == 2] = 1
    grid[:, COLS // 2 - 2 : COLS // 2] = 0  # two columns of road rays in the pavement's surface
    out = _join(scan, grid.reshape(-1), sigmas)
    assert np.array_equal(out, grid.reshape(-1))


def test_two_walls_at_ninety_degrees_stay_apart():
    points = _ground(lambda x: np.zeros_like(x))
    right = points[:, COLS // 2 :]
    right[..., 2] = right[..., 0] - STEP * COLS / 2  # the right half rises as a vertical wall
    right[..., 0] = STEP * COLS / 2
    scan, ids, sigmas = _halves(points)
    assert np.array_equal(_join(scan, ids, sigmas), ids)


@pytest.mark.parametrize(
    ('gap', 'max_gap', 'joined'), [(BOUNDARY_GAP, BOUNDARY_GAP, True), (4, 3, False), (1, 0, False)]
)
def test_a_boundary_crosses_at_most_max_gap_rays_without_a_surface(gap, max_gap, joined):
    scan, ids, sigmas = _halves(_ground(_crown()), gap=gap)
    out = _join(scan, ids, sigmas, max_gap=max_gap)
    assert np.array_equal(out, np.where(ids >= 0, 0, -1) if joined else ids)


def test_any_non_negative_ids_give_the_same_surfaces_with_their_own_ids():
    scan, ids, sigmas = _halves(_ground(_crown()), gap=1)
    sparse = np.where(ids >= 0, 10**12 + 7 * ids, -1)  # far beyond the pixel count
    out = _join(scan, sparse, sigmas)
    assert np.array_equal(out, np.where(ids >= 0, 10**12, -1))


def test_surfaces_below_min_points_and_short_boundaries_take_no_part():
    scan, ids, sigmas = _halves(_ground(_crown()))
    assert np.array_equal(_join(scan, ids, sigmas, min_points=601), ids)  # each half holds 600 rays
    short = ids.reshape(ROWS, COLS).copy()
    short[MIN_BOUNDARY_PAIRS - 1 :, COLS // 2 - 4 : COLS // 2 + 4] = -1  # 9 rows still touch
    assert np.array_equal(_join(scan, short.reshape(-1), sigmas), short.reshape(-1))


def test_the_halves_join_across_the_seam_of_a_full_revolution_only_when_the_columns_wrap():
    points = np.roll(_ground(_crown()), COLS // 2, axis=1)  # the crown now lies between the last and first column
    scan, ids, sigmas = _halves(points, gap=BOUNDARY_GAP + 1)  # the grid's middle (6 m apart in the scene): no boundary
    joined = _join(scan, ids, sigmas, wrap_columns=True)
    assert np.array_equal(joined, np.where(ids >= 0, 0, -1))
    assert np.array_equal(_join(scan, ids, sigmas, wrap_columns=False), ids)


def _bent_blocks(seed: int):
    """A gently bent ground in 3 x 4 blocks (surfaces 0-11), with a kerb along one side, some rays in
    no surface and one small block: a chain of merges that folds boundaries."""
    rng = np.random.default_rng(seed)
    bend = rng.uniform(0.004, 0.012)
    points = _ground(lambda x: bend * (x - 3.0) ** 2 + np.where(x > 5.0, 0.13, 0.0), seed=seed)
    rows = np.minimum(np.arange(ROWS) * 3 // ROWS, 2)
    cols = np.minimum(np.arange(COLS) * 4 // COLS, 3)
    ids = (rows[:, None] * 4 + cols[None, :]).astype(np.int64)
    ids[:, 50:] = 12  # the kerb's top, one surface
    ids[rng.random(ids.shape) < 0.05] = -1
    ids[ids == 5] = 13  # ids need not be dense
    sigmas = np.full(ROWS * COLS, 0.02)
    return make_ray_scan(points, np.array([3.0, 1.0, 2.0])), ids.reshape(-1), sigmas


@pytest.mark.parametrize('seed', [0, 1, 2, 3])
@pytest.mark.parametrize('wrap', [False, True])
def test_the_boundary_round_equals_the_brute_force_reference(seed, wrap):
    scan, ids, sigmas = _bent_blocks(seed)
    out = _join(scan, ids, sigmas, min_points=60, wrap_columns=wrap)
    expected = boundary_join_reference(scan, ids, sigmas, TAU, 60, wrap=wrap)
    assert np.array_equal(out, expected)
    assert len(np.unique(out[out >= 0])) < len(np.unique(ids[ids >= 0]))  # some merges happened
    assert len(np.unique(out[out >= 0])) >= 2  # the kerb's top stays apart


def test_noise_factor_and_step_factor_widen_the_tolerance_as_in_the_reference():
    scan, ids, sigmas = _halves(_ground(lambda x: np.where(x >= STEP * COLS / 2, 0.07, 0.0), noise=0.02))
    assert np.array_equal(_join(scan, ids, sigmas), ids)  # a 7 cm step: apart at kappa 1 and lambda 0
    for options in ({'step_factor': 1.6}, {'noise_factor': 3.0}):
        out = _join(scan, ids, sigmas, **options)
        expected = boundary_join_reference(scan, ids, sigmas, TAU, 300, **options)
        assert np.array_equal(out, expected)
        assert np.array_equal(out, np.zeros_like(ids))


def test_bad_arguments_are_clear_errors():
    scan, ids, sigmas = _halves(_ground(_crown()))
    with pytest.raises(ValueError, match='surface_tolerance'):
        join_at_boundaries(scan, ids, sigmas, 0.0, 300)
    with pytest.raises(ValueError, match='boundary_join_points'):
        join_at_boundaries(scan, ids, sigmas, TAU, 0)
    with pytest.raises(ValueError, match='max_gap'):
        join_at_boundaries(scan, ids, sigmas, TAU, 300, max_gap=-1)
    with pytest.raises(ValueError, match='one entry per pixel'):
        join_at_boundaries(scan, ids[:-1], sigmas, TAU, 300)
    with pytest.raises(ValueError, match='sigmas must have one entry per pixel'):
        join_at_boundaries(scan, ids, sigmas[:-1], TAU, 300)
    for bend in (-1.0, 91.0, 'steep', True):
        with pytest.raises(ValueError, match='max_bend_deg'):
            join_at_boundaries(scan, ids, sigmas, TAU, 300, max_bend_deg=bend)
    for bad in (0, 2.5, True, 'many'):
        with pytest.raises(ValueError, match='boundary_join_points'):
            SensorProfile(name='x', boundary_join_points=bad)


def test_the_lidar_profile_runs_the_round_after_the_consolidation():
    assert PROFILES['lidar'].boundary_join_points == 300
    assert all(PROFILES[name].boundary_join_points is None for name in ('none', 'paper', 'depth_camera'))
    scan, ids, sigmas = _halves(_ground(_crown()))
    profile = PROFILES['lidar']
    args = (scan, ids, sigmas, TAU, False, 0.0, profile.min_plane_points)
    apart = _consolidate(*args).copy()
    assert len(np.unique(apart[apart >= 0])) == 2  # the consolidation alone keeps the halves apart
    joined = _consolidate(*args, boundary_join_points=profile.boundary_join_points)
    assert len(np.unique(joined[joined >= 0])) == 1
    without = dataclasses.replace(profile, boundary_join_points=None)
    assert without.boundary_join_points is None


@pytest.mark.parametrize('wrap', [False, True])
def test_the_boundary_pixel_pairs_of_row_blocks_are_those_of_one_pass(wrap, monkeypatch):
    """The kernel over all pixels equals the reference (the smaller surface id's pixel first); any split
    into pixel ranges, and the row blocks on 2 threads (_parallel_boundary_pixel_pairs), give the same
    pairs in the same order."""
    import numba
    import reference_consolidation as reference

    from ppe_ros.core import boundary_join, consolidation

    rng = np.random.default_rng(7)
    height, width = 64, 300
    ids = np.where(rng.random(height * width) < 0.2, -1, rng.integers(0, 9, height * width)).astype(np.int64)
    large = np.arange(9) != 4  # surface 4 is too small
    whole = _boundary_pixel_pairs(ids, large, height, width, wrap, 3, 0, height * width)
    want = [
        (k, x) if ids[k] < ids[x] else (x, k)
        for k, x in reference._boundary_pixel_pairs(ids, large, height, width, wrap, 3)
    ]
    assert len(whole) > 1000
    np.testing.assert_array_equal(whole, np.array(want))
    cuts = [0, 1, 7 * width, 7 * width + 5, height * width - 3, height * width]
    blocks = [_boundary_pixel_pairs(ids, large, height, width, wrap, 3, a, b) for a, b in itertools.pairwise(cuts)]
    np.testing.assert_array_equal(np.concatenate(blocks), whole)
    calls = []
    run_tasks = consolidation.run_tasks

    def recording_run_tasks(run, order, threads, pool):
        calls.append((len(order), threads))
        return run_tasks(run, order, threads, pool)

    monkeypatch.setattr(boundary_join, 'PARALLEL_PAIRS_MIN_PIXELS', 1000)
    monkeypatch.setattr(consolidation, 'run_tasks', recording_run_tasks)
    before = numba.get_num_threads()
    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    try:
        got = boundary_join._parallel_boundary_pixel_pairs(ids, large, height, width, wrap, 3)
    finally:
        numba.set_num_threads(before)
    np.testing.assert_array_equal(got, whole)
    if numba.config.NUMBA_NUM_THREADS >= 2:
        assert calls == [(2 * consolidation.BLOCKS_PER_THREAD, 2)]


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_the_cost_of_a_pair_is_the_reference_cost_from_its_points(seed):
    """Unequal sides: a 4 cm step under a 2 deg tilt of one side, boundary pairs across a gap of 2 rays."""
    rng = np.random.default_rng(seed)
    tilt = np.tan(np.radians(rng.uniform(0.5, 2.0)))
    points = _ground(lambda x: np.where(x >= 3.0, 0.04 + tilt * (x - 3.0), 0.0), noise=0.01, seed=seed)
    scan, ids, sigmas = _halves(points, gap=2)
    sigmas = sigmas * rng.uniform(0.5, 2.0, sigmas.shape)
    moments = _piece_moments(ids, scan.endpoints, sigmas, 2)
    plane = np.empty((2, 13))
    _plane_rows(moments, plane, 0, 2)
    pixel_pairs = _boundary_pixel_pairs(ids, np.array([True, True]), ROWS, COLS, False, 2, 0, ROWS * COLS)
    side = _side_moments(scan.endpoints, sigmas, pixel_pairs, np.zeros(len(pixel_pairs), np.int64), 1)
    for noise_factor, step_factor in ((0.0, 1.0), (2.0, 1.3)):
        value = _boundary_cost(moments, plane, side, 0, 0, 1, TAU**2, noise_factor**2, step_factor**2, 0.0)
        expected = boundary_cost_reference(
            scan.endpoints[ids == 0],
            scan.endpoints[ids == 1],
            scan.endpoints[pixel_pairs[:, 0]],
            scan.endpoints[pixel_pairs[:, 1]],
            sigmas[ids == 0],
            sigmas[ids == 1],
            TAU,
            noise_factor,
            step_factor,
            90.0,
        )
        assert np.isfinite(value) and value == pytest.approx(expected, rel=1e-7)
