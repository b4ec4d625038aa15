"""Tests of the brute-force reference PPE (test/reference_ppe.py), the oracle for the fast extractor."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import reference_ppe
from reference_ppe import (
    ACTION_DTYPE,
    TETROMINO_OFFSETS,
    plane_sets,
    reference_extract,
    reference_fit,
    tetromino_pixels,
)

# --------------------------------------------------------------------------------------------
# Synthetic scans by ray casting
# --------------------------------------------------------------------------------------------

# World planes n . x = d: the floor and two walls meeting in a corner.
FLOOR_AND_TWO_WALLS = (
    (np.array([0.0, 0.0, 1.0]), 0.0),
    (np.array([1.0, 0.0, 0.0]), 3.0),
    (np.array([0.0, 1.0, 0.0]), -1.2),
)
SENSOR_POSITION = np.array([0.0, 0.0, 1.0])  # metres above the floor
# Beam elevations (deg) avoid 0: a zero-elevation row is a planar fan whose points on any plane are
# collinear, which makes every seed with three cells in that row fit exactly. The per-row azimuth
# stagger (deg, like a real multi-beam lidar) keeps columns from being planar fans for the same reason.
ELEVATIONS_DEG = np.array([28.0, 20.0, 12.0, 5.0, -8.0, -16.0, -24.0, -32.0])
AZIMUTH_STAGGER_DEG = np.array([0.0, 1.7, -1.1, 2.3, -0.6, 1.2, -2.0, 0.5])


def rotation(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """Sensor-to-world rotation Rz(yaw) Ry(pitch) Rx(roll); positive pitch looks down."""
    yaw, pitch, roll = np.radians([yaw_deg, pitch_deg, roll_deg])
    rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    ry = np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0], [-np.sin(pitch), 0, np.cos(pitch)]])
    rx = np.array([[1, 0, 0], [0, np.cos(roll), -np.sin(roll)], [0, np.sin(roll), np.cos(roll)]])
    return rz @ ry @ rx


def cast_scan(
    planes=FLOOR_AND_TWO_WALLS,
    *,
    noise: float = 0.0,
    seed: int = 0,
    yaw_deg: float = -15.0,
    pitch_deg: float = 15.0,
    roll_deg: float = 30.0,
    width: int = 10,
    origin_step: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """An 8 x width scan of infinite planes by a rolled and pitched spinning sensor.

    Returns sensor-frame points (origins at zero), world-frame points and per-pixel origins
    (column j starts at ``SENSOR_POSITION + j * origin_step``; directions are the same), and the
    index of the plane each ray hit. Range noise is Gaussian with std ``noise`` metres.
    """
    rotation_matrix = rotation(yaw_deg, pitch_deg, roll_deg)
    origin_step = np.zeros(3) if origin_step is None else np.asarray(origin_step, dtype=float)
    height = len(ELEVATIONS_DEG)
    azimuths_deg = np.linspace(30.0, -30.0, width)
    rng = np.random.default_rng(seed)
    sensor_points = np.empty((height, width, 3))
    world_points = np.empty((height, width, 3))
    world_origins = np.empty((height, width, 3))
    truth = np.empty((height, width), dtype=np.int64)
    for row, col in itertools.product(range(height), range(width)):
        elevation = np.radians(ELEVATIONS_DEG[row])
        azimuth = np.radians(azimuths_deg[col] + AZIMUTH_STAGGER_DEG[row])
        direction = np.array(
            [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
        )
        world_direction = rotation_matrix @ direction
        origin = SENSOR_POSITION + col * origin_step
        hits = []
        for index, (normal, offset) in enumerate(planes):
            cosine = normal @ world_direction
            if cosine != 0.0 and (offset - normal @ origin) / cosine > 0.0:
                hits.append(((offset - normal @ origin) / cosine, index))
        distance, truth[row, col] = min(hits)
        distance += noise * rng.standard_normal()
        sensor_points[row, col] = distance * direction
        world_points[row, col] = origin + distance * world_direction
        world_origins[row, col] = origin
    return {'sensor_points': sensor_points, 'points': world_points, 'origins': world_origins, 'truth': truth}


def truth_partition(truth: np.ndarray) -> list[tuple[int, ...]]:
    """The pixel sets (sorted linear ids) of the true planes, sorted."""
    flat = truth.reshape(-1)
    return sorted(tuple(int(k) for k in np.flatnonzero(flat == label)) for label in np.unique(flat[flat >= 0]))


def plane_count_of(image: np.ndarray, valid: np.ndarray) -> int:
    """J of a plane-id image: valid pixels outside regular planes plus regular planes."""
    labels = image[image >= 0]
    return int(valid.sum()) - labels.size + len(np.unique(labels))


# --------------------------------------------------------------------------------------------
# Tetromino seeds
# --------------------------------------------------------------------------------------------


def _normalized(cells) -> frozenset[tuple[int, int]]:
    min_row = min(r for r, _ in cells)
    min_col = min(c for _, c in cells)
    return frozenset((r - min_row, c - min_col) for r, c in cells)


def _is_connected(cells: frozenset[tuple[int, int]]) -> bool:
    start = next(iter(cells))
    seen, stack = {start}, [start]
    while stack:
        r, c = stack.pop()
        for neighbour in ((r + 1, c), (r - 1, c), (r, c + 1), (r, c - 1)):
            if neighbour in cells and neighbour not in seen:
                seen.add(neighbour)
                stack.append(neighbour)
    return len(seen) == len(cells)


def _fixed_non_i_tetrominoes() -> set[frozenset[tuple[int, int]]]:
    """All fixed tetrominoes (translation classes) by enumerating 4-cell subsets of a 4x4 box, minus I."""
    box = list(itertools.product(range(4), range(4)))
    shapes = {_normalized(cells) for cells in itertools.combinations(box, 4) if _is_connected(frozenset(cells))}
    assert len(shapes) == 19  # 2 I + 1 O + 4 T + 4 S/Z + 8 L/J
    straight = {frozenset((0, c) for c in range(4)), frozenset((r, 0) for r in range(4))}
    return shapes - straight


def test_seed_configs_are_the_17_fixed_non_i_tetrominoes_each_placement_once():
    configs = [frozenset(offsets) for offsets in TETROMINO_OFFSETS]
    assert len(configs) == 17
    assert all(len(cells) == 4 and (0, 0) in cells for cells in configs)
    assert {_normalized(cells) for cells in configs} == _fixed_non_i_tetrominoes()

    height, width = 5, 6
    placements_from_seeds = []
    for anchor, config in itertools.product(range(height * width), range(17)):
        row, col = divmod(anchor, width)
        cells = [(row + dr, col + dc) for dr, dc in TETROMINO_OFFSETS[config]]
        if all(0 <= r < height and 0 <= c < width for r, c in cells):
            placements_from_seeds.append(frozenset(cells))
            assert tetromino_pixels(anchor, config, width) == tuple(r * width + c for r, c in cells)
    all_placements = {
        frozenset((r + dr, c + dc) for dr, dc in shape)
        for shape in _fixed_non_i_tetrominoes()
        for r, c in itertools.product(range(height), range(width))
        if all(r + dr < height and c + dc < width for dr, dc in shape)
    }
    assert len(placements_from_seeds) == len(set(placements_from_seeds))  # each placement once
    assert set(placements_from_seeds) == all_placements


# --------------------------------------------------------------------------------------------
# Exact plane fit
# --------------------------------------------------------------------------------------------


def _rays_to_plane(normal, offset, origins, rng, noise):
    """Rays from ``origins`` in random directions towards the plane normal . x = offset, with range noise."""
    normal = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    targets = []
    for origin in origins:
        # A point on the plane near the foot of the origin's perpendicular.
        foot = origin + (offset - normal @ origin) * normal
        tangent = rng.normal(size=3)
        tangent -= (tangent @ normal) * normal
        targets.append(foot + rng.uniform(0.2, 1.5) * tangent / np.linalg.norm(tangent))
    targets = np.array(targets)
    ranges = np.linalg.norm(targets - origins, axis=1)
    directions = (targets - origins) / ranges[:, None]
    return directions, ranges + noise * rng.standard_normal(len(ranges))


def _sse_of_plane(normal, offset, origins, directions, ranges) -> np.ndarray:
    """SSE of (many) planes computed directly from the definition rhat = (d - n.s) / (n.v)."""
    normal = np.asarray(normal)
    offset = np.asarray(offset)
    predicted = (offset[..., None] - normal @ origins.T) / (normal @ directions.T)
    return np.sum((ranges - predicted) ** 2, axis=-1)


def _unit(theta, phi):
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)


def test_fit_of_noise_free_rays_recovers_the_plane():
    rng = np.random.default_rng(1)
    normal, offset = np.array([0.3, -0.4, 0.866]), 2.0
    normal /= np.linalg.norm(normal)
    origins = rng.normal(scale=0.3, size=(7, 3))
    directions, ranges = _rays_to_plane(normal, offset, origins, rng, noise=0.0)
    sse, fitted_normal, fitted_offset = reference_fit(origins, directions, ranges)
    assert sse < 1e-24
    # The normal faces the mean ray origin, which lies on the negative side of normal . x = offset.
    assert np.allclose(fitted_normal, -normal, atol=1e-10)
    assert fitted_offset == pytest.approx(-offset, abs=1e-10)
    assert fitted_normal @ origins.mean(axis=0) > fitted_offset


def test_fit_of_noisy_rays_is_the_minimum():
    rng = np.random.default_rng(2)
    origins = rng.normal(scale=0.2, size=(6, 3))
    directions, ranges = _rays_to_plane([0.2, 0.1, 1.0], 1.5, origins, rng, noise=0.03)
    sse, normal, offset = reference_fit(origins, directions, ranges)
    assert 1e-5 < sse < 1e-1
    assert np.linalg.norm(normal) == pytest.approx(1.0)
    # The reported plane attains the reported SSE under the definition of rhat.
    assert _sse_of_plane(normal, offset, origins, directions, ranges) == pytest.approx(sse, rel=1e-9)

    # Gradient over (theta, phi, offset) vanishes (central differences, independent parameterisation).
    theta, phi = math.acos(normal[2]), math.atan2(normal[1], normal[0])

    def sse_at(params):
        return float(_sse_of_plane(_unit(params[0], params[1]), params[2], origins, directions, ranges))

    center = np.array([theta, phi, offset])
    step = 1e-6
    gradient = [(sse_at(center + step * e) - sse_at(center - step * e)) / (2 * step) for e in np.eye(3)]
    assert np.max(np.abs(gradient)) < 1e-6 * max(sse, 1.0)

    # Dense grid around the optimum never beats it.
    deltas = np.linspace(-0.05, 0.05, 21)
    d_theta, d_phi, d_offset = np.meshgrid(deltas, deltas, deltas, indexing='ij')
    grid_sse = _sse_of_plane(_unit(theta + d_theta, phi + d_phi), offset + d_offset, origins, directions, ranges)
    assert grid_sse.min() >= sse * (1 - 1e-12)

    # Random perturbations at every scale never lower the SSE.
    for scale in (1e-7, 1e-5, 1e-3, 1e-1):
        params = center + scale * rng.normal(size=(500, 3))
        perturbed = _sse_of_plane(_unit(params[:, 0], params[:, 1]), params[:, 2], origins, directions, ranges)
        assert perturbed.min() >= sse * (1 - 1e-12)

    # A coarse global search over all normal directions and offsets finds nothing better either.
    count = 4000
    golden = np.pi * (3 - np.sqrt(5))
    z = 1 - 2 * (np.arange(count) + 0.5) / count
    sphere = np.stack(
        [
            np.sqrt(1 - z**2) * np.cos(golden * np.arange(count)),
            np.sqrt(1 - z**2) * np.sin(golden * np.arange(count)),
            z,
        ],
        axis=1,
    )
    offsets = np.linspace(-4.0, 4.0, 161)
    global_sse = _sse_of_plane(sphere[:, None, :], offsets[None, :], origins, directions, ranges)
    assert np.nanmin(global_sse) >= sse * (1 - 1e-12)


def test_fit_from_four_rays_of_a_seed_matches_the_definition():
    # Four rays from one origin (a seed), noisy: the reported plane attains the SSE and is a minimum.
    rng = np.random.default_rng(3)
    origins = np.zeros((4, 3))
    directions, ranges = _rays_to_plane([1.0, 0.2, -0.1], 4.0, origins, rng, noise=0.05)
    sse, normal, offset = reference_fit(origins, directions, ranges)
    assert _sse_of_plane(normal, offset, origins, directions, ranges) == pytest.approx(sse, rel=1e-9, abs=1e-20)
    theta, phi = math.acos(normal[2]), math.atan2(normal[1], normal[0])
    params = np.array([theta, phi, offset]) + 1e-3 * rng.normal(size=(2000, 3))
    perturbed = _sse_of_plane(_unit(params[:, 0], params[:, 1]), params[:, 2], origins, directions, ranges)
    assert perturbed.min() >= sse * (1 - 1e-12)


def test_fit_keeps_the_lowest_of_several_local_minima():
    # An L seed of a noisy scan across the floor-wall crease: its SSE has two local minima and
    # one of the starts (the PCA plane) falls into the worse one.
    points = cast_scan(noise=0.05, seed=3)['sensor_points']
    cells = [(4, 1), (4, 2), (5, 2), (6, 2)]
    endpoints = np.array([points[row, col] for row, col in cells])
    ranges = np.linalg.norm(endpoints, axis=1)
    directions = endpoints / ranges[:, None]
    local_minima = [
        reference_ppe._gauss_newton(start, endpoints, directions)[1]
        for start in reference_ppe._initial_guesses(endpoints, ranges)
    ]
    assert max(local_minima) > 10 * min(local_minima)
    sse, normal, offset = reference_fit(np.zeros((4, 3)), directions, ranges)
    assert sse == pytest.approx(min(local_minima), rel=1e-12)
    assert _sse_of_plane(normal, offset, np.zeros((4, 3)), directions, ranges) == pytest.approx(sse, rel=1e-9)
    # A global grid over normal directions and offsets finds nothing lower.
    count = 20000
    golden = np.pi * (3 - np.sqrt(5))
    z = 1 - 2 * (np.arange(count) + 0.5) / count
    radius = np.sqrt(1 - z**2)
    sphere = np.stack([radius * np.cos(golden * np.arange(count)), radius * np.sin(golden * np.arange(count)), z], 1)
    grid_minimum = min(
        float(np.min(_sse_of_plane(sphere, np.full(count, d), np.zeros((4, 3)), directions, ranges)))
        for d in np.linspace(-8.0, 8.0, 801)
    )
    assert sse <= grid_minimum


@pytest.mark.parametrize(
    ('origins', 'directions', 'ranges', 'message'),
    [
        (np.zeros((4, 2)), np.zeros((4, 2)), np.ones(4), 'origins must have shape'),
        (np.zeros((4, 3)), np.zeros((3, 3)), np.ones(4), 'directions must have shape'),
        (np.zeros((4, 3)), np.eye(3)[[0, 1, 2, 0]], np.ones(3), 'ranges must have shape'),
        (np.zeros((2, 3)), np.eye(3)[[0, 1]], np.ones(2), 'at least 3 rays'),
        (np.zeros((3, 3)), np.eye(3), np.array([1.0, np.nan, 1.0]), 'must be finite'),
        (np.zeros((3, 3)), np.eye(3), np.array([1.0, 0.0, 1.0]), 'ranges must be positive'),
        (np.zeros((3, 3)), 2 * np.eye(3), np.ones(3), 'unit vectors'),
    ],
)
def test_fit_rejects_bad_input(origins, directions, ranges, message):
    with pytest.raises(ValueError, match=message):
        reference_fit(origins, directions, ranges)


# --------------------------------------------------------------------------------------------
# Extraction
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize('frame', ['sensor', 'world_moving_origins'])
def test_noise_free_floor_and_two_walls_split_exactly(frame):
    if frame == 'sensor':
        scan = cast_scan()
        result = reference_extract(scan['sensor_points'], max_error_increment=[1e-6, 0.01])
    else:
        # World frame; each column's rays start 3 cm further along the track.
        scan = cast_scan(origin_step=np.array([0.01, 0.03, 0.0]))
        result = reference_extract(scan['points'], origins=scan['origins'], max_error_increment=[1e-6, 0.01])
    truth = scan['truth']
    assert len(np.unique(truth)) == 3
    assert [s.description for s in result.snapshots] == ['e=1e-06', 'e=0.01']
    for snapshot in result.snapshots:
        assert sorted(plane_sets(snapshot).values()) == truth_partition(truth)
        assert np.array_equal(snapshot.plane_id_image, result.state_after(snapshot.steps))
    # Every executed action was exact (noise-free), and the run stopped before a cross-plane merge.
    assert all(abs(action.increment) < 1e-20 for action in result.actions)
    assert result.snapshots[-1].steps == len(result.actions)
    assert np.array_equal(result.final_plane_id_image, result.snapshots[-1].plane_id_image)
    # Plane ids are anchor pixels of the plane.
    for plane_id, pixels in plane_sets(result.final_plane_id_image).items():
        assert plane_id in pixels


def _assert_same_actions(first, second, rtol=1e-6):
    a, b = first.actions_array(), second.actions_array()
    assert len(a) == len(b)
    for field in ('kind', 'a', 'b'):
        assert np.array_equal(a[field], b[field])
    assert np.allclose(a['increment'], b['increment'], rtol=rtol, atol=1e-14)


def test_noisy_scan_gives_the_same_actions_in_sensor_and_world_frames():
    # The fit is invariant to rigid motion: sensor frame with zero origins versus the world frame
    # with the sensor position as every ray's origin.
    scan = cast_scan(noise=0.01, seed=4)
    in_sensor = reference_extract(scan['sensor_points'], max_error_increment=0.01)
    in_world = reference_extract(scan['points'], origins=scan['origins'], max_error_increment=0.01)
    assert len(in_sensor.actions) > 20
    _assert_same_actions(in_sensor, in_world)


def test_actions_array_has_the_shared_dtype():
    scan = cast_scan(noise=0.01, seed=5)
    result = reference_extract(scan['sensor_points'])
    array = result.actions_array()
    assert array.dtype == ACTION_DTYPE
    assert array.dtype.names == ('kind', 'a', 'b', 'increment')
    assert array.dtype['kind'] == np.int8 and array.dtype['a'] == np.int64 and array.dtype['increment'] == np.float64
    kinds = {'create': 0, 'extend': 1, 'merge': 2}
    assert [kinds[action.kind] for action in result.actions] == array['kind'].tolist()
    assert [action.a for action in result.actions] == array['a'].tolist()
    assert [action.b for action in result.actions] == array['b'].tolist()
    assert [action.increment for action in result.actions] == array['increment'].tolist()
    assert array['kind'][0] == 0  # the first action always creates a plane
    # Merges keep the smaller id.
    merges = array[array['kind'] == 2]
    assert np.all(merges['a'] < merges['b'])


def _mirrored_blocks_scan():
    """5 x 9 scan: columns 0-3 and 5-8 hold bit-identical noisy rays of a tilted plane, column 4 is NaN.

    Pixel (row, 2) of the left block is NaN as well, mirrored to (row, 7), so every candidate of the
    left block has an exact twin with an identical increment in the right block.
    """
    rng = np.random.default_rng(6)
    left = np.empty((5, 4, 3))
    for row, col in itertools.product(range(5), range(4)):
        direction = np.array([1.0, 0.15 * (col - 1.5), 0.12 * (row - 2)])
        direction /= np.linalg.norm(direction)
        distance = (2.5 - 0.3 * direction[1]) / (direction[0] + 0.2 * direction[2])
        left[row, col] = (distance + 0.01 * rng.standard_normal()) * direction
    left[2, 2] = np.nan
    points = np.full((5, 9, 3), np.nan)
    points[:, :4] = left
    points[:, 5:] = left
    return points


def test_exact_ties_go_to_the_smaller_ids():
    points = _mirrored_blocks_scan()
    result = reference_extract(points, max_error_increment=None, max_planes=2)
    shift = 5  # right-block pixel id = left-block pixel id + 5 (same row)

    def side(action):
        return 'left' if action.a % 9 < 4 else 'right'

    left = [(i, a) for i, a in enumerate(result.actions) if side(a) == 'left']
    right = [(i, a) for i, a in enumerate(result.actions) if side(a) == 'right']
    assert len(left) == len(right) > 5
    for (i_left, a_left), (i_right, a_right) in zip(left, right, strict=True):
        # The right block repeats the left block exactly, and each twin comes after its left original.
        assert (a_right.kind, a_right.a - shift, a_right.increment) == (
            a_left.kind,
            a_left.a,
            a_left.increment,
        )
        assert a_right.b == (a_left.b if a_left.kind == 'create' else a_left.b + shift)
        assert i_left < i_right
    # Each block ends as one plane of all its valid pixels; the NaN pixels are in no plane.
    final = result.snapshot('n=2')
    valid = np.isfinite(points).all(axis=2)
    left_pixels = tuple(int(k) for k in np.flatnonzero(valid.reshape(-1)) if k % 9 < 4)
    right_pixels = tuple(k + shift for k in left_pixels)
    assert sorted(plane_sets(final).values()) == [left_pixels, right_pixels]
    assert np.array_equal(result.valid, valid)


def _least_key_action(labels: np.ndarray, valid: np.ndarray) -> tuple[int, int, int] | None:
    """The least (kind, a, b) candidate of a state, scanning the rules in key order (lmax = inf)."""
    height, width = labels.shape
    flat = labels.reshape(-1)
    atomic = valid.reshape(-1) & (flat < 0)

    def neighbours(k):
        row, col = divmod(k, width)
        for r, c in ((row - 1, col), (row + 1, col), (row, col - 1), (row, col + 1)):
            if 0 <= r < height and 0 <= c < width and valid.reshape(-1)[r * width + c]:
                yield r * width + c

    for anchor in range(height * width):
        row, col = divmod(anchor, width)
        for config, offsets in enumerate(TETROMINO_OFFSETS):
            cells = [(row + dr, col + dc) for dr, dc in offsets]
            if all(0 <= r < height and 0 <= c < width and atomic[r * width + c] for r, c in cells):
                return (0, anchor, config)
    planes = sorted(set(flat[flat >= 0].tolist()))
    for plane in planes:
        for k in range(height * width):
            if atomic[k] and any(flat[m] == plane for m in neighbours(k)):
                return (1, plane, k)
    for a, b in itertools.combinations(planes, 2):
        if any(flat[m] == b for k in np.flatnonzero(flat == a) for m in neighbours(k)):
            return (2, a, b)
    return None


def test_equal_increments_order_create_extend_merge_then_ids(monkeypatch):
    # With every fit error exactly zero, every increment ties and only the tie-break decides.
    monkeypatch.setattr(reference_ppe, 'reference_fit', lambda origins, directions, ranges: (0.0, None, None))
    rng = np.random.default_rng(7)
    points = rng.uniform(1.0, 2.0, size=(5, 6, 3))
    points[1, 3] = np.nan
    points[3, 0] = np.nan
    valid = np.isfinite(points).all(axis=2)
    result = reference_extract(points, max_error_increment=None, max_planes=1)
    assert len(result.actions) > 5
    kinds = [action.kind for action in result.actions]
    assert kinds == sorted(kinds, key=['create', 'extend', 'merge'].index)
    assert {'create', 'extend', 'merge'} <= set(kinds)
    for step, action in enumerate(result.actions):
        assert action.increment == 0.0
        expected = _least_key_action(result.state_after(step), valid)
        assert (['create', 'extend', 'merge'].index(action.kind), action.a, action.b) == expected
    assert _least_key_action(result.final_plane_id_image, valid) is None
    assert np.all(result.final_plane_id_image[~valid] == -1)


def test_invalid_pixels_never_join_a_plane():
    scan = cast_scan(noise=0.005, seed=8)
    points = scan['points'].copy()
    origins = scan['origins'].copy()
    points[2, 3] = np.nan  # no return
    points[5, 6] = origins[5, 6]  # zero range
    origins[4, 1, 0] = np.inf  # broken origin
    points[6, 8, 2] = np.nan  # partly NaN point
    invalid = [(2, 3), (5, 6), (4, 1), (6, 8)]
    result = reference_extract(points, origins=origins, max_error_increment=0.01)
    assert sorted(zip(*np.nonzero(~result.valid), strict=True)) == sorted(invalid)
    width = points.shape[1]
    invalid_ids = {row * width + col for row, col in invalid}
    for action in result.actions:
        if action.kind == 'create':
            assert not invalid_ids & set(tetromino_pixels(action.a, action.b, width))
        elif action.kind == 'extend':
            assert action.b not in invalid_ids
    assert all(result.final_plane_id_image[row, col] == -1 for row, col in invalid)
    # All valid pixels end up in planes (the noise is small against the thresholds).
    assert np.all(result.final_plane_id_image[result.valid] >= 0)


def _two_walls_with_a_depth_jump():
    """A wall 2 m away on the left columns and one 3.5 m away on the right (the same orientation)."""
    points = np.empty((6, 8, 3))
    rng = np.random.default_rng(9)
    for row, col in itertools.product(range(6), range(8)):
        elevation = np.radians(-20.0 + 7.0 * row + 0.9 * col)
        azimuth = np.radians(25.0 - 7.0 * col + 1.3 * row)
        direction = np.array(
            [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
        )
        depth = 2.0 if col < 4 else 3.5
        distance = depth / direction[0] + 0.005 * rng.standard_normal()
        points[row, col] = distance * direction
    return points


def test_max_neighbor_distance_stops_joining_across_a_depth_jump():
    points = _two_walls_with_a_depth_jump()
    width = points.shape[1]
    # Without lmax, running down to one plane merges across the jump.
    unlimited = reference_extract(points, max_error_increment=None, max_planes=1)
    assert len(plane_sets(unlimited.snapshot('n=1'))) == 1
    # Neighbours on a wall are < 0.5 m apart, across the jump > 1.4 m.
    sides = {k: (k % width < 4) for k in range(points.shape[0] * width)}
    limited = reference_extract(points, max_error_increment=None, max_planes=1, max_neighbor_distance=0.6)
    final = plane_sets(limited.snapshot('n=1'))
    assert sorted(final.values()) == sorted(tuple(k for k in sides if sides[k] == left) for left in (True, False))
    for action in limited.actions:
        if action.kind == 'create':
            assert len({sides[k] for k in tetromino_pixels(action.a, action.b, width)}) == 1
        else:
            assert sides[action.a] == sides[action.b]
    # An lmax below every neighbour distance leaves no candidate: nothing happens.
    none = reference_extract(points, max_neighbor_distance=0.01)
    assert none.actions == []
    assert np.all(none.snapshots[0].plane_id_image == -1) and none.snapshots[0].steps == 0


def test_error_and_count_snapshots_follow_their_definitions():
    scan = cast_scan(noise=0.01, seed=10)
    errors = [0.1, 1e-5, 1e-3, 1e-4, 0.01]
    counts = [3, 40, 10]
    result = reference_extract(scan['sensor_points'], max_error_increment=errors, max_planes=counts)
    increments = [action.increment for action in result.actions]
    assert [s.description for s in result.snapshots] == (
        ['e=1e-05', 'e=0.0001', 'e=0.001', 'e=0.01', 'e=0.1', 'n=40', 'n=10', 'n=3']
    )
    # Increments are not monotone, so "first action above e" differs from "all actions <= e".
    assert any(later < earlier for earlier, later in itertools.pairwise(increments))
    for e in sorted(errors):
        snapshot = result.snapshot(f'e={e!r}')
        first_above = next((i for i, inc in enumerate(increments) if inc > e), len(increments))
        assert snapshot.steps == first_above
        assert np.array_equal(snapshot.plane_id_image, result.state_after(first_above))
    for n in counts:
        snapshot = result.snapshot(f'n={n}')
        reached = next(
            (k for k in range(len(increments) + 1) if plane_count_of(result.state_after(k), result.valid) <= n),
            len(increments),
        )
        assert snapshot.steps == reached
        assert np.array_equal(snapshot.plane_id_image, result.state_after(reached))
    # The run ends as soon as the last threshold is met.
    assert len(result.actions) == max(s.steps for s in result.snapshots)
    assert plane_count_of(result.final_plane_id_image, result.valid) <= 3


def test_thresholds_met_at_the_start_snapshot_the_atomic_state():
    scan = cast_scan(noise=0.01, seed=11)
    result = reference_extract(scan['sensor_points'], max_error_increment=[-1.0, 0.01], max_planes=1000)
    for description in ('e=-1.0', 'n=1000'):
        snapshot = result.snapshot(description)
        assert snapshot.steps == 0 and np.all(snapshot.plane_id_image == -1)
    # The default threshold is e = 0.01 when neither e nor n is given.
    default = reference_extract(scan['sensor_points'])
    assert [s.description for s in default.snapshots] == ['e=0.01']
    _assert_same_actions(default, reference_extract(scan['sensor_points'], max_error_increment=None), rtol=0)
    assert default.snapshots[0].steps == result.snapshot('e=0.01').steps


@pytest.mark.parametrize(
    ('kwargs', 'message'),
    [
        ({'points': np.zeros((4, 3))}, 'points must have shape'),
        ({'points': np.ones((2, 2, 3)), 'origins': np.zeros((2, 3, 3))}, 'origins must have the shape'),
        (
            {'points': np.ones((2, 2, 3)), 'max_neighbor_distance': 0.0},
            'max_neighbor_distance must be positive',
        ),
        ({'points': np.ones((2, 2, 3)), 'max_error_increment': [np.nan]}, 'must not be NaN'),
        ({'points': np.ones((2, 2, 3)), 'max_planes': [-1]}, 'non-negative integers'),
        ({'points': np.ones((2, 2, 3)), 'max_planes': 2.5}, 'non-negative integers'),
    ],
)
def test_extract_rejects_bad_input(kwargs, message):
    points = kwargs.pop('points')
    with pytest.raises(ValueError, match=message):
        reference_extract(points, **kwargs)
