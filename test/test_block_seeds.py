"""Block seeds (GreedyOptions.block_seeds): the 4 x 4 blocks that fit one plane within the stop start the greedy."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scenes import room_scan

from ppe_ros import extract_planes
from ppe_ros.core.extraction import GreedyOptions, extract_plane_hierarchy
from ppe_ros.core.fitting import fit_rays
from ppe_ros.core.ppe.layout import _FIT_ITERATIONS, KIND_CREATE, KIND_EXTEND
from ppe_ros.core.ppe.seeds import BLOCK_SIDE, _block_seeds, _edge_masks, _seed_stage
from ppe_ros.core.scan import make_ray_scan
from ppe_ros.core.sensor import PROFILES
from ppe_ros.core.synthetic_real import generate_lidar_scan

STOP = 0.01  # m^2: the runs' max_error_increment (unit directions: increments in m^2)
TOLERANCE = 1e-6


def _scan(lmax: float = 0.3):
    """A noisy room with a hole, ray starts off the origin, and its admissible edges at lmax."""
    scene = room_scan(rows=40, cols=56, noise=0.01, seed=5)
    points = scene.points.copy()
    points[10:13, 20:27] = np.nan
    scan = make_ray_scan(points, scene.origins)
    ok_right, ok_down = _edge_masks(scan, lmax)
    return points, scene.origins, scan, ok_right, ok_down


def _blocks_one_by_one(scan, ok_right, ok_down, max_sse):
    """Slow reference: every aligned 4 x 4 block, its 24 internal edges checked one by one, fitted with fit_rays
    (no lower bound), kept when its SSE is at most max_sse; sorted by (SSE, anchor)."""
    h, w = scan.height, scan.width
    kept = []
    for i0 in range(0, h - BLOCK_SIDE + 1, BLOCK_SIDE):
        for j0 in range(0, w - BLOCK_SIDE + 1, BLOCK_SIDE):
            cells = [(i0 + di) * w + j0 + dj for di in range(BLOCK_SIDE) for dj in range(BLOCK_SIDE)]
            right = [k for k in cells if (k % w) - j0 < BLOCK_SIDE - 1]
            down = [k for k in cells if k // w - i0 < BLOCK_SIDE - 1]
            if not (all(ok_right[k] for k in right) and all(ok_down[k] for k in down)):
                continue
            idx = np.array(cells, dtype=np.int64)
            sse = fit_rays(
                scan.endpoints, scan.directions, idx, 16, np.nan, np.nan, np.nan, _FIT_ITERATIONS, TOLERANCE
            )[0]
            if sse <= max_sse:
                kept.append((sse, cells[0]))
    return np.array([anchor for _, anchor in sorted(kept)], dtype=np.int64)


@pytest.mark.parametrize('lmax', [0.3, np.inf])
def test_block_seeds_are_the_aligned_blocks_that_fit_within_the_stop(lmax):
    _, _, scan, ok_right, ok_down = _scan(lmax)
    square_sse = _seed_stage(scan, ok_right, ok_down, np.inf, 'square')[0][:, 0].copy()
    fast = _block_seeds(
        scan.endpoints, scan.directions, ok_right, ok_down, square_sse, scan.height, scan.width, STOP, TOLERANCE
    )
    slow = _blocks_one_by_one(scan, ok_right, ok_down, STOP)
    np.testing.assert_array_equal(fast, slow)
    # some blocks fit, others span an edge of the room or a hole, or fit worse than the stop
    joined = _blocks_one_by_one(scan, ok_right, ok_down, np.inf)
    assert 10 < len(slow) < len(joined) < (scan.height // 4) * (scan.width // 4)


def test_a_run_with_block_seeds_starts_with_its_blocks_as_paper_actions():
    """The log starts with each block's create of its top-left square and the extensions by its other 12 rays in
    row order, with the exact increments (summing to the block's fit), each at most the stop; the replay after
    them holds exactly the blocks; then the greedy goes on as usual."""
    points, origins, scan, ok_right, ok_down = _scan(np.inf)
    options = GreedyOptions(seed_shapes='square', block_seeds=True, fit_tolerance=TOLERANCE)
    hierarchy = extract_plane_hierarchy(points, origins=origins, max_error_increment=STOP, options=options)
    blocks = _blocks_one_by_one(scan, ok_right, ok_down, STOP)
    n_block_actions = len(blocks) * (BLOCK_SIDE * BLOCK_SIDE - 3)
    log = hierarchy.actions
    assert len(blocks) > 10 and len(log) > n_block_actions + 100
    w = scan.width
    for t, anchor in enumerate(blocks):
        rows = log[t * 13 : (t + 1) * 13]
        assert rows['kind'][0] == KIND_CREATE and rows['a'][0] == anchor and rows['b'][0] == 0
        others = [anchor + di * w + dj for di in range(4) for dj in range(4) if not (di < 2 and dj < 2)]
        assert (rows['kind'][1:] == KIND_EXTEND).all() and (rows['a'][1:] == anchor).all()
        np.testing.assert_array_equal(rows['b'][1:], others)
        assert (rows['increment'] >= 0.0).all() and (rows['increment'] <= STOP).all()
        cells = np.array([anchor + di * w + dj for di in range(4) for dj in range(4)], dtype=np.int64)
        sse = fit_rays(scan.endpoints, scan.directions, cells, 16, np.nan, np.nan, np.nan, _FIT_ITERATIONS, 1e-13)[0]
        assert rows['increment'].sum() == pytest.approx(sse, rel=1e-5)
    ids = hierarchy.plane_ids(n_block_actions)
    expected = np.full(scan.size, -1)
    for anchor in blocks:
        expected[[anchor + di * w + dj for di in range(4) for dj in range(4)]] = anchor
    np.testing.assert_array_equal(ids, expected)
    # the greedy after the blocks: creates, extensions and merges, none above the stop
    kinds = log['kind'][n_block_actions:]
    assert len(np.unique(kinds)) == 3 and (log['increment'] <= STOP).all()
    # the same run without blocks is another hierarchy of the same scan
    plain = extract_plane_hierarchy(
        points, origins=origins, max_error_increment=STOP, options=GreedyOptions(seed_shapes='square')
    )
    assert not np.array_equal(plain.actions['a'][:50], log['a'][:50])


def test_block_seeds_need_a_stop_increment():
    """A run stopped by a plane count (or run to the end) has no blocks: the same log as without the option."""
    scene = room_scan(rows=24, cols=32, noise=0.01, seed=5)
    runs = [
        extract_plane_hierarchy(
            scene.points, origins=scene.origins, max_planes=20, options=GreedyOptions(block_seeds=flag)
        ).actions
        for flag in (False, True)
    ]
    np.testing.assert_array_equal(runs[0], runs[1])


def test_a_profile_with_block_seeds_runs_them_and_the_built_in_ones_do_not():
    """extract_planes with a copy of the lidar profile asking for block seeds starts its greedy with blocks (a
    different segmentation of the same generated sweep, with as many points in planes within a few
    percent); the built-in profiles have none."""
    assert not any(profile.block_seeds for profile in PROFILES.values())
    sweep = generate_lidar_scan(seed=4, model='os1-32', cols=256)
    plain = extract_planes(sweep.points, origins=sweep.origins, sensor='lidar')
    blocks = extract_planes(
        sweep.points, origins=sweep.origins, sensor=dataclasses.replace(PROFILES['lidar'], block_seeds=True)
    )
    assert not np.array_equal(plain.labels, blocks.labels)
    assert blocks.num_planes > 5
    assert abs(int(blocks.point_counts.sum()) - int(plain.point_counts.sum())) < 0.05 * plain.point_counts.sum()
