"""Unorganized clouds -> range image -> planes per input point (ppe_ros.core.projection, issue 20)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from lidar_sweeps import HDL_LIKE_ELEVATIONS, room_sweep, shuffled

from ppe_ros.core.extraction import extract_planes
from ppe_ros.core.projection import (
    _beam_steps,
    _claim_cells,
    _gather_cells,
    _phase_sums,
    _point_labels_kernel,
    _rays,
    _ring_rows,
    _rows_below_edges,
    _sharpness,
    _sharpness_of_offsets,
    beam_elevations,
    estimate_azimuth_step,
    extract_planes_unorganized,
    fit_beam_origin_offset,
    matched_label_agreement,
    project_points,
)
from ppe_ros.core.scan import MAX_RANGE, MIN_RANGE

# ------------------------------------------------------------------ kernels against references


def slow_claim(cells, ranges, n_cells):
    winners = [-1] * n_cells
    for i, c in enumerate(cells):
        if c >= 0 and (winners[c] < 0 or ranges[i] < ranges[winners[c]]):
            winners[c] = i
    return np.array(winners)


def test_nearest_return_wins_its_cell_as_a_slow_reference_says():
    rng = np.random.default_rng(3)
    cells = rng.integers(-1, 50, 2000)
    ranges = np.round(rng.uniform(1, 3, 2000), 1)  # many ties: the first point wins them
    np.testing.assert_array_equal(_claim_cells(cells, ranges, 60), slow_claim(cells, ranges, 60))


def test_point_labels_kernel_matches_a_slow_reference():
    rng = np.random.default_rng(4)
    n, n_cells = 3000, 400
    cells = rng.integers(-1, n_cells, n)
    points = rng.normal(0, 2, (n, 3))
    ranges = np.linalg.norm(points, axis=1)
    winners = slow_claim(cells, ranges, n_cells)
    normals = rng.normal(size=(5, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    offsets = rng.uniform(-1, 1, 5)
    cell_labels = rng.integers(0, 6, n_cells)
    tolerance = 0.5
    expected = np.zeros(n, np.int32)
    for i in range(n):
        c = cells[i]
        if c < 0 or cell_labels[c] == 0:
            continue
        label = cell_labels[c]
        if winners[c] == i or abs(normals[label - 1] @ points[i] - offsets[label - 1]) <= tolerance:
            expected[i] = label
    got = _point_labels_kernel(cells, winners, cell_labels.astype(np.int64), points, normals, offsets, tolerance)
    np.testing.assert_array_equal(got, expected)
    assert 0 < np.count_nonzero(got) < n


def test_sharpness_is_the_sum_of_squared_histogram_counts():
    rng = np.random.default_rng(5)
    rho, z = rng.uniform(0.5, 30, 500), rng.uniform(-10, 10, 500)
    width = math.radians(0.02)
    elevation = np.arctan2(z - 0.1, rho - 0.02)
    counts = np.bincount(((elevation + math.pi / 2) / width).astype(np.int64))
    assert _sharpness(rho, z, 0.1, 0.02, width) == float((counts.astype(float) ** 2).sum())


def test_sharpness_counts_only_points_beyond_the_offset_from_the_axis():
    """Points nearer the sensor's axis than the radial offset n have elevations beyond +-pi/2 (atan2 of a
    negative rho - n): they are not counted (the kernel wrote them outside its histogram before, or
    wrapped a negative bin to the top of it)."""
    rng = np.random.default_rng(9)
    rho, z = rng.uniform(0.0, 0.2, 2000), rng.uniform(-1.0, 1.0, 2000)
    width = math.radians(0.02)
    for h, n in ((0.1, 0.05), (-0.3, 0.1), (0.0, 0.0), (0.05, -0.1)):
        elevation = np.arctan2(z - h, rho - n)
        inside = np.abs(elevation) <= math.pi / 2
        assert (not inside.all()) == (n > 0)
        counts = np.bincount(((elevation[inside] + math.pi / 2) / width).astype(np.int64))
        assert _sharpness(rho, z, h, n, width) == float((counts.astype(float) ** 2).sum()), (h, n)


def test_an_unorganized_cloud_around_the_sensor_axis_is_extracted():
    """A small unorganized cloud whose points are within centimetres of the z axis (a depth camera's
    centre, or a lidar cloud scaled to the wrong unit): the beam-origin search meets rho < n."""
    rng = np.random.default_rng(10)
    x, y = rng.uniform(-0.08, 0.08, (2, 3000))
    points = np.stack([x, y, 0.002 * x + 0.001 * rng.normal(size=3000) - 0.05], axis=1)
    planes = extract_planes(points, sensor='lidar')
    assert planes.labels.shape == (3000,)


@pytest.mark.parametrize('count', [0, 5])
def test_a_cloud_without_a_valid_point_and_per_point_origins_has_no_plane(count):
    """An empty cloud, or one of no-returns only, with (N, 3) ray starts: every point labelled 0, no error (the
    image of the starts had no cell while the image of the points has its one no-return cell)."""
    points = np.full((count, 3), np.nan)
    planes = extract_planes(points, origins=np.zeros((count, 3)), sensor='lidar')
    np.testing.assert_array_equal(planes.labels, np.zeros(count, np.int32))
    assert planes.num_planes == 0


def test_ray_geometry_is_numpys_bit_for_bit():
    """_rays (one parallel kernel) against the numpy it replaced: p - s, the lengths of sqrt(einsum) and hypot."""
    rng = np.random.default_rng(8)
    points = rng.normal(0, 20, (3000, 3))
    points[::50] = np.nan
    points[1::50] = 0.0  # below MIN_RANGE
    points[2::50] *= 1e6  # beyond MAX_RANGE
    for origins in (None, np.array([0.1, -0.2, 0.03]), rng.normal(0, 0.05, points.shape)):
        rays_in = points.copy() if origins is None else points - origins
        length = np.sqrt(np.einsum('ij,ij->i', rays_in, rays_in))
        with np.errstate(invalid='ignore'):
            valid = (length >= MIN_RANGE) & (length <= MAX_RANGE)
        rays_in[~valid] = 0.0
        rays, got_valid, ranges, rho = _rays(points, origins)
        np.testing.assert_array_equal(got_valid, valid)
        assert 0 < valid.sum() < len(points) - 100
        np.testing.assert_array_equal(rays, rays_in)
        np.testing.assert_array_equal(ranges, np.sqrt(np.einsum('ij,ij->i', rays_in, rays_in)))
        np.testing.assert_array_equal(rho, np.hypot(rays_in[:, 0], rays_in[:, 1]))


@pytest.mark.parametrize('n_edges', [0, 1, 2, 127, 300])
def test_rows_below_edges_are_searchsorted(n_edges):
    """The bucketed search against np.searchsorted(side='left'), with values on the edges, between, beyond."""
    rng = np.random.default_rng(n_edges)
    edges = np.sort(rng.uniform(-0.5, 0.3, n_edges))
    if n_edges >= 3:
        edges[n_edges // 3 : n_edges // 3 + 2] = edges[n_edges // 3]  # a repeated edge
    values = np.concatenate([rng.uniform(-0.7, 0.5, 4000), edges, np.nextafter(edges, np.inf), [np.inf, -np.inf]])
    elevation = -values  # the kernel takes the negated elevations' ascending edges
    valid = rng.random(len(values)) < 0.9
    row_of = np.full(len(values), -1, np.int64)
    _rows_below_edges(edges, elevation, valid, row_of)
    expected = np.where(valid, np.searchsorted(edges, values, side='left'), -1)
    np.testing.assert_array_equal(row_of, expected)


def test_phase_sums_are_a_loop_over_the_points_in_order():
    rng = np.random.default_rng(9)
    azimuth = rng.uniform(-math.pi, math.pi, 5000)
    row_of = rng.integers(-1, 40, 5000)
    step = 2 * math.pi / 1024
    sin, cos = np.zeros(40), np.zeros(40)
    for a, r in zip(azimuth, row_of, strict=True):
        if r >= 0:
            phase = 2 * math.pi / step * (a + math.pi)
            sin[r] += math.sin(phase)
            cos[r] += math.cos(phase)
    got_sin, got_cos = _phase_sums(azimuth, row_of, 40, step)
    np.testing.assert_array_equal(got_sin, sin)
    np.testing.assert_array_equal(got_cos, cos)


@pytest.mark.parametrize('upwards', [True, False])
def test_ring_rows_follow_numpys_bincount_of_the_rings(upwards):
    """Rows from rings against the numpy definition (bincount means, ring order flipped when rings count upwards)."""
    rng = np.random.default_rng(10)
    rings = rng.integers(-1, 64, 6000)
    rings[rings == 17] = 18  # an absent ring inside the range: an empty row
    elevation = (rings if upwards else -rings) * 0.01 + rng.normal(0, 0.001, len(rings))
    valid = rng.random(len(rings)) < 0.95
    ok = valid & (rings >= 0)
    counts = np.bincount(rings[ok])
    present = np.flatnonzero(counts)
    means = (np.bincount(rings[ok], elevation[ok]) / np.maximum(counts, 1))[present]
    low, high = int(present[0]), int(present[-1])
    assert (np.corrcoef(present.astype(float), means)[0, 1] > 0) == upwards
    expected = np.full(len(rings), -1, np.int64)
    expected[ok] = (high - rings[ok]) if upwards else (rings[ok] - low)
    row_of, n_rows = _ring_rows(rings, elevation, valid)
    np.testing.assert_array_equal(row_of, expected)
    assert n_rows == high - low + 1


def test_rings_of_one_elevation_count_downwards_without_a_warning():
    """Points all at one elevation (their rings' mean elevations do not correlate with the ring numbers: NaN)."""
    rings = np.array([3, 5, 3, 9])
    with np.errstate(all='raise'):
        row_of, n_rows = _ring_rows(rings, np.zeros(4), np.ones(4, bool))
    np.testing.assert_array_equal(row_of, [0, 2, 0, 6])
    assert n_rows == 7


def test_azimuth_step_of_a_beam_of_three_uneven_returns_is_their_median_step():
    """No step within 30 % of the median (steps of 0.1 and 2.2 rad): the median itself, not NaN."""
    azimuth = np.array([0.0, 0.1, 2.3, 1.0])
    row_of = np.array([0, 0, 0, 1])
    with np.errstate(all='raise'):
        step = estimate_azimuth_step(azimuth, row_of)
    assert step == pytest.approx(1.15)  # 5.46 steps a revolution: not snapped to a whole number
    cloud = np.array([[10 * math.cos(a), 10 * math.sin(a), 0.5] for a in azimuth])
    planes = extract_planes(cloud, rings=row_of)  # a cloud this small has no plane, but is processed
    assert planes.labels.shape == (4,)


def test_beam_steps_are_the_diffs_of_the_points_sorted_by_row_and_azimuth():
    """_beam_steps against the numpy definition it replaced (lexsort by row then azimuth, np.diff within rows,
    steps above 1e-7 rad), with repeated azimuths and rows left out."""
    rng = np.random.default_rng(12)
    row_of = rng.integers(0, 20, 6000)
    azimuth = rng.choice(np.linspace(-math.pi, math.pi, 2048, endpoint=False), 6000)  # many repeats
    counts = np.bincount(row_of)
    rows = np.array([2, 3, 7, 11, 19])
    chosen = np.isin(row_of, rows)
    order = np.lexsort((azimuth[chosen], row_of[chosen]))
    a, r = azimuth[chosen][order], row_of[chosen][order]
    steps = np.diff(a)
    expected = steps[(r[1:] == r[:-1]) & (steps > 1e-7)]
    got = _beam_steps(azimuth, row_of, rows, counts)
    assert len(expected) > 1000
    np.testing.assert_array_equal(got, expected)
    assert len(_beam_steps(azimuth, row_of, rows[:0], counts)) == 0


@pytest.mark.parametrize('fill', [np.nan, 0.0])
def test_gather_cells_is_numpys_fancy_indexing(fill):
    rng = np.random.default_rng(13)
    values = rng.normal(size=(500, 3))
    cell_points = np.where(rng.random(800) < 0.6, rng.integers(0, 500, 800), -1)
    expected = np.full((800, 3), fill)
    held = cell_points >= 0
    expected[held] = values[cell_points[held]]
    out = np.empty((800, 3))
    _gather_cells(values, cell_points, fill, out)
    np.testing.assert_array_equal(out, expected)
    assert 0 < held.sum() < 800


def test_sharpness_of_offsets_is_sharpness_at_each():
    rng = np.random.default_rng(11)
    rho, z = rng.uniform(0.5, 30, 700), rng.uniform(-10, 10, 700)
    hs, ns = rng.uniform(-0.3, 0.3, 25), rng.uniform(-0.1, 0.1, 25)
    width = math.radians(0.02)
    got = _sharpness_of_offsets(rho, z, hs, ns, width)
    np.testing.assert_array_equal(got, [_sharpness(rho, z, h, n, width) for h, n in zip(hs, ns, strict=True)])


# ------------------------------------------------------------------ the projection


def test_beams_are_found_at_uneven_hdl64e_like_elevations():
    rng = np.random.default_rng(6)
    beams = np.radians(HDL_LIKE_ELEVATIONS)
    elevation = np.repeat(beams, 500) + rng.normal(0, math.radians(0.01), 64 * 500)
    stray = rng.uniform(beams.min(), beams.max(), 20)  # a few returns between beams are not beams
    found = beam_elevations(np.r_[elevation, stray])
    assert found.shape == (64,)
    np.testing.assert_allclose(found, beams, atol=math.radians(0.005))


def test_beam_origin_offset_is_recovered():
    points = room_sweep(HDL_LIKE_ELEVATIONS, 720, sigma=0.0, beam_origin=(0.12, 0.03)).reshape(-1, 3)
    h, n = fit_beam_origin_offset(points, np.ones(len(points), bool))
    assert h == pytest.approx(0.12, abs=0.002) and n == pytest.approx(0.03, abs=0.002)


@pytest.mark.parametrize('with_rings', [True, False], ids=['rings', 'elevation_bins'])
def test_a_shuffled_sweep_is_put_back_on_its_grid(with_rings):
    """Mirrored (azimuth counter-clockwise), started at the same seam: row and column of every point."""
    sweep = room_sweep(HDL_LIKE_ELEVATIONS, 900, beam_origin=(0.1, 0.02))
    sweep[np.random.default_rng(2).random(sweep.shape[:2]) < 0.2] = np.nan  # no-returns, then dropped
    points, rings, index = shuffled(sweep)
    projection = project_points(points, rings if with_rings else None)
    assert projection.shape == (64, 900) and projection.azimuth_bins == 900 and projection.lost_points == 0
    assert projection.method == ('rings' if with_rings else 'elevation')
    row, column = np.divmod(projection.point_cells, projection.columns)
    np.testing.assert_array_equal(row, index // 900)
    np.testing.assert_array_equal(column, 899 - index % 900)
    image = projection.image(points)
    np.testing.assert_array_equal(image[:, ::-1], sweep)  # NaN where no return, as the sweep


def test_rings_counting_upwards_give_the_top_beam_first_and_absent_rings_empty_rows():
    sweep = room_sweep(HDL_LIKE_ELEVATIONS[::4], 360)
    points, rings, _ = shuffled(sweep)
    velodyne_rings = 15 - rings  # Velodyne numbers its rings from the bottom beam
    keep = velodyne_rings != 7
    projection = project_points(points[keep], velodyne_rings[keep])
    assert projection.shape == (16, 360)
    assert np.all(projection.cell_points.reshape(16, 360)[8] == -1)  # ring 7 is row 15 - 7 = 8: empty
    assert np.all(np.diff(projection.row_elevations[np.isfinite(projection.row_elevations)]) < 0)


def test_a_partial_field_of_view_is_cut_at_its_gap_and_cropped():
    sweep = room_sweep(HDL_LIKE_ELEVATIONS[::8], 720)
    azimuth = np.degrees(np.arctan2(sweep[..., 1], sweep[..., 0]))
    sweep[np.abs(azimuth) > 60] = np.nan  # a 120 deg field of view around +x: the gap is behind
    points, rings, _ = shuffled(sweep)
    projection = project_points(points, rings, azimuth_bins=720)
    assert projection.shape == (8, 240)
    assert projection.lost_points == 0


def test_invalid_points_get_no_cell_and_no_label():
    sweep = room_sweep(HDL_LIKE_ELEVATIONS[::4], 360)
    points, rings, _ = shuffled(sweep)
    points = np.r_[points, [[np.nan, 0, 0], [0, 0, 0], [np.inf, 1, 1]]]
    rings = np.r_[rings, 0, 0, 0]
    planes = extract_planes(points, rings=rings, sensor='lidar')
    assert planes.labels.shape == (len(points),)
    assert np.all(planes.meta['projection'].point_cells[-3:] == -1) and np.all(planes.labels[-3:] == 0)


def test_bad_arguments_are_refused_with_a_reason():
    points = np.zeros((10, 3))
    with pytest.raises(ValueError, match=r'rings must be \(N,\)'):
        project_points(points, np.zeros(3))
    with pytest.raises(ValueError, match='rows must be one of'):
        project_points(points, rows='columns')
    with pytest.raises(ValueError, match="rows='rings' needs rings"):
        project_points(points, rows='rings')
    with pytest.raises(ValueError, match='azimuth_bins must be'):
        project_points(points, azimuth_bins=0)
    with pytest.raises(ValueError, match=r'unorganized \(N, 3\)'):
        project_points(np.zeros((4, 2)))
    with pytest.raises(ValueError, match='whole numbers'):
        project_points(points, np.full(10, 0.5))


# ------------------------------------------------------------------ planes per point


def test_unorganized_cloud_gives_the_planes_of_the_organized_sweep():
    sweep = room_sweep(HDL_LIKE_ELEVATIONS[::2], 720, sigma=0.005)
    organized = extract_planes(sweep, sensor='lidar')
    points, rings, index = shuffled(sweep)
    for given in (rings, None):
        planes = extract_planes(points, rings=given, sensor='lidar')
        assert planes.labels.shape == (len(points),) and planes.labels.dtype == np.int32
        assert matched_label_agreement(organized.labels.reshape(-1)[index], planes.labels) >= 0.999
        assert planes.num_planes == organized.num_planes


def test_a_point_that_lost_its_cell_gets_the_plane_only_when_it_lies_on_it():
    """Second returns behind wall points: 1 cm behind (on the wall: its plane) or 30 cm behind (no plane)."""
    sweep = room_sweep(HDL_LIKE_ELEVATIONS[::2], 720, sigma=0.002)
    points, rings, _ = shuffled(sweep)
    first = extract_planes(points, rings=rings, sensor='lidar')
    wall_label = first.labels[np.argmax(points[:, 0])]
    wall = np.flatnonzero(first.labels == wall_label)[:80]
    unit = points[wall] / np.linalg.norm(points[wall], axis=1)[:, None]
    behind = points[wall] + np.r_[np.full(40, 0.01), np.full(40, 0.3)][:, None] * unit
    cloud = np.r_[points, behind]
    cloud_rings = np.r_[rings, rings[wall]]
    n = len(points)
    planes = extract_planes(cloud, rings=cloud_rings, sensor='lidar')
    assert planes.meta['projection'].lost_points == 80
    np.testing.assert_array_equal(planes.labels[:n], first.labels)  # the nearer returns kept their cells
    assert np.all(planes.labels[n : n + 40] == wall_label)  # within the lidar profile's 5 cm
    assert np.all(planes.labels[n + 40 :] == 0)
    strict = extract_planes_unorganized(cloud, cloud_rings, sensor='lidar', lost_point_tolerance=0.005)
    assert np.all(strict.labels[n:] == 0)
    loose = extract_planes_unorganized(cloud, cloud_rings, sensor='lidar', lost_point_tolerance=0.5)
    assert np.all(loose.labels[n:] == wall_label)


def test_several_thresholds_give_one_point_labelling_each():
    sweep = room_sweep(HDL_LIKE_ELEVATIONS[::4], 360)
    points, rings, _ = shuffled(sweep)
    cuts = extract_planes(points, rings=rings, max_error_increment=[0.01, 0.1], min_plane_points=4)
    assert isinstance(cuts, list) and len(cuts) == 2
    assert all(cut.labels.shape == (len(points),) for cut in cuts)


def test_transposed_grid_gives_the_same_planes():
    """The 4-neighbourhood and the 17 tetrominoes map onto themselves under transposition, so PPE on the
    transposed grid makes the same choices up to ties between equal increments (broken by pixel id)."""
    sweep = room_sweep(HDL_LIKE_ELEVATIONS[::2], 480, sigma=0.005)
    planes = extract_planes(sweep, sensor='lidar')
    transposed = extract_planes(np.ascontiguousarray(sweep.transpose(1, 0, 2)), sensor='lidar')
    assert matched_label_agreement(planes.labels, transposed.labels.T) >= 0.999
    assert planes.num_planes == transposed.num_planes


def test_a_livox_like_cloud_on_the_fixed_angular_grid_finds_its_wall():
    """A non-repetitive (rosette-like) pattern of 20000 rays over a 70 deg field of view onto a wall 5 m ahead
    and the floor: the default 0.8 deg grid is ~60 % filled, and the wall and floor come out as planes."""
    rng = np.random.default_rng(7)
    t = np.sort(rng.uniform(0, 1, 20000))
    radius = np.radians(35) * np.abs(np.sin(2 * math.pi * 37 * t)) * np.sqrt(rng.uniform(0.2, 1, t.size))
    angle = 2 * math.pi * 5.1 * t
    elevation, azimuth = radius * np.sin(angle), radius * np.cos(angle)
    direction = np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=1
    )
    with np.errstate(divide='ignore'):
        to_wall = np.where(direction[:, 0] > 0, 5.0 / direction[:, 0], np.inf)
        to_floor = np.where(direction[:, 2] < 0, -1.5 / direction[:, 2], np.inf)
    ranges = np.minimum(to_wall, to_floor) + rng.normal(0, 0.01, t.size)
    points = direction * ranges[:, None]
    planes = extract_planes_unorganized(points, rows='angular_grid', sensor='lidar')
    projection = planes.meta['projection']
    assert projection.method == 'angular_grid'
    on_wall = to_wall < to_floor
    wall_label = np.bincount(planes.labels[on_wall]).argmax()
    assert wall_label > 0 and np.mean(planes.labels[on_wall] == wall_label) > 0.8
    floor_label = np.bincount(planes.labels[~on_wall]).argmax()
    assert floor_label not in (0, wall_label)


def test_matched_label_agreement_matches_labels_one_to_one():
    a = np.array([0, 0, 1, 1, 1, 2, 2, 3])
    b = np.array([0, 5, 7, 7, 7, 7, 9, 0])
    # 0-0 (1), 1-7 (3), 2-9 (1): 5 of 8; 2's other point went to 7, which is taken
    assert matched_label_agreement(a, b) == 5 / 8
    assert matched_label_agreement(b, b) == 1.0


def test_a_cloud_without_a_valid_point_gives_no_plane_for_every_point():
    planes = extract_planes(np.zeros((100, 3)), sensor='lidar')  # every ray shorter than MIN_RANGE
    assert planes.num_planes == 0 and planes.labels.shape == (100,) and not planes.labels.any()
    assert planes.meta['projection'].shape == (0, 0)
