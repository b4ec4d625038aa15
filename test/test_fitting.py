"""Tests of the maximum-likelihood plane fits (ppe_ros.core.fitting) against an independent
Levenberg-Marquardt fit in a different parameterisation (test/scenes.py)."""

from __future__ import annotations

import numpy as np
import pytest
import scenes

from ppe_ros.core.fitting import LabeledPlanes, PlaneFit, fit_labeled_planes, fit_plane


def _plane_rays(n_rays: int, *, noise: float, seed: int, starts: str = 'origin'):
    """Rays towards the plane n . x = d with n = (-0.8, 0.3, -0.52)/|.|, d = -2.4 (2-4 m away).

    ``starts``: 'origin' (all at 0), 'point' (all at one point) or 'per-ray' (scattered by ~5 cm).
    Returns (points, origins or None, true normal facing the starts, true offset).
    """
    rng = np.random.default_rng(seed)
    normal = np.array([-0.8, 0.3, -0.52])
    normal /= np.linalg.norm(normal)
    offset = -2.4
    if starts == 'origin':
        origins = np.zeros((n_rays, 3))
    elif starts == 'point':
        origins = np.broadcast_to(np.array([0.4, -0.3, 0.2]), (n_rays, 3))
    else:
        origins = 0.05 * rng.standard_normal((n_rays, 3))
    # targets on the plane around the foot of the perpendicular from the mean start
    foot = origins.mean(axis=0) + (offset - normal @ origins.mean(axis=0)) * normal
    tangent_u = np.cross(normal, [0.0, 0.0, 1.0])
    tangent_u /= np.linalg.norm(tangent_u)
    tangent_v = np.cross(normal, tangent_u)
    uv = rng.uniform(-1.5, 1.5, size=(n_rays, 2))
    targets = foot + uv[:, :1] * tangent_u + uv[:, 1:] * tangent_v
    delta = targets - origins
    ranges = np.linalg.norm(delta, axis=1)
    directions = delta / ranges[:, None]
    measured = ranges + noise * rng.standard_normal(n_rays)
    points = origins + measured[:, None] * directions
    # the true normal faces the starts: n . s > d
    if normal @ origins.mean(axis=0) < offset:
        normal, offset = -normal, -offset
    return points, (None if starts == 'origin' else np.array(origins)), normal, offset


def _check_against_lm(fit: PlaneFit, points, origins) -> None:
    starts, directions, ranges = scenes.rays(points, origins)
    lm_sse, lm_normal, lm_offset = scenes.lm_plane_fit(starts, directions, ranges)
    assert fit.sse == pytest.approx(lm_sse, rel=1e-9, abs=1e-24)
    assert np.allclose(fit.normal, lm_normal, atol=1e-7)
    assert fit.offset == pytest.approx(lm_offset, abs=1e-7)
    # the reported plane attains the reported SSE, residuals and rmse by definition
    residuals = scenes.radial_residuals(fit.normal, fit.offset, starts, directions, ranges)
    assert np.allclose(fit.residuals, residuals, atol=1e-9)
    assert fit.sse == pytest.approx(float(residuals @ residuals), rel=1e-9, abs=1e-24)
    assert fit.rmse == pytest.approx(np.sqrt(fit.sse / len(points)), rel=1e-12, abs=1e-15)
    assert fit.count == len(points)
    assert np.linalg.norm(fit.normal) == pytest.approx(1.0, abs=1e-12)
    assert fit.normal @ starts.mean(axis=0) > fit.offset, 'the normal does not face the ray starts'


@pytest.mark.parametrize('starts', ['origin', 'point', 'per-ray'])
def test_noise_free_rays_give_the_true_plane(starts):
    points, origins, normal, offset = _plane_rays(50, noise=0.0, seed=1, starts=starts)
    fit = fit_plane(points, origins)
    assert fit.sse < 1e-24
    assert np.allclose(fit.normal, normal, atol=1e-10)
    assert fit.offset == pytest.approx(offset, abs=1e-10)
    assert np.all(np.abs(fit.residuals) < 1e-10)


@pytest.mark.parametrize('starts', ['origin', 'point', 'per-ray'])
@pytest.mark.parametrize(('n_rays', 'noise'), [(4, 0.02), (30, 0.005), (500, 0.02), (200, 0.2)])
def test_noisy_fit_is_the_independent_least_squares_minimum(starts, n_rays, noise):
    points, origins, normal, _ = _plane_rays(n_rays, noise=noise, seed=n_rays, starts=starts)
    fit = fit_plane(points, origins)
    _check_against_lm(fit, points, origins)
    if n_rays >= 30:
        assert np.degrees(np.arccos(min(1.0, fit.normal @ normal))) < 10 * noise / 0.02


def test_origins_forms_agree():
    points, origins, _, _ = _plane_rays(40, noise=0.01, seed=3, starts='point')
    single = fit_plane(points, origins[0])
    per_ray = fit_plane(points, origins)
    assert single.sse == pytest.approx(per_ray.sse, rel=1e-12)
    assert np.allclose(single.normal, per_ray.normal, atol=1e-12)
    assert np.allclose(single.covariance, per_ray.covariance, rtol=1e-9, atol=1e-18)
    # None means every ray starts at the coordinate origin
    at_zero = fit_plane(points, np.zeros(3))
    default = fit_plane(points)
    assert default.sse == pytest.approx(at_zero.sse, rel=1e-12)
    assert np.allclose(default.normal, at_zero.normal, atol=1e-12)
    # rays from a different start are different rays: a different fit
    assert not np.isclose(default.sse, single.sse, rtol=1e-3)


def test_fit_is_invariant_to_rigid_motion():
    points, origins, _, _ = _plane_rays(60, noise=0.02, seed=4, starts='per-ray')
    rotation = scenes.random_rotation(np.random.default_rng(4))
    fit = fit_plane(points, origins)
    # the new coordinate origin lies on the fitted plane
    translation = -rotation @ (fit.offset * fit.normal)
    moved = fit_plane(points @ rotation.T + translation, origins @ rotation.T + translation)
    assert moved.sse == pytest.approx(fit.sse, rel=1e-9)
    assert np.allclose(moved.normal, rotation @ fit.normal, atol=1e-9)
    assert moved.offset == pytest.approx(fit.offset + (rotation @ fit.normal) @ translation, abs=1e-9)
    assert abs(moved.offset) < 1e-9
    assert np.allclose(moved.residuals, fit.residuals, atol=1e-9)


def test_covariance_is_symmetric_positive_semidefinite_and_scales_with_noise():
    fits = [fit_plane(*_plane_rays(300, noise=noise, seed=5, starts='origin')[:2]) for noise in (0.01, 0.04)]
    for fit in fits:
        assert fit.covariance.shape == (3, 3)
        assert np.allclose(fit.covariance, fit.covariance.T)
        assert np.linalg.eigvalsh(fit.covariance).min() > -1e-18
    # same noise pattern scaled 4x: variance 16x (to the accuracy of the linearisation)
    ratio = np.trace(fits[1].covariance) / np.trace(fits[0].covariance)
    assert 12 < ratio < 20


@pytest.mark.parametrize(
    ('points', 'origins', 'message'),
    [
        (np.zeros((5, 2)), None, r'\(N, 3\)'),
        (np.zeros((2, 3, 3)), None, r'\(N, 3\)'),
        (np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), None, 'at least 3'),
        (np.zeros((0, 3)), None, 'at least 3'),
        (np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [np.nan, 0.0, 1.0]]), None, 'not finite'),
        (np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]]), None, 'a length outside'),
        (np.eye(3), np.zeros((2, 3)), 'origins'),
        (np.eye(3), np.zeros(2), 'origins'),
    ],
)
def test_bad_input_raises(points, origins, message):
    with pytest.raises(ValueError, match=message):
        fit_plane(points, origins)


@pytest.mark.parametrize('count', [3, 10])
def test_collinear_endpoints_raise(count):
    # endpoints on one line (not through the origin): no unique plane
    t = np.linspace(-1.0, 1.0, count)
    points = np.array([2.0, 0.5, 0.3]) + t[:, None] * np.array([0.1, 1.0, -0.2])
    with pytest.raises(ValueError, match='degenerate'):
        fit_plane(points)


def test_three_rays_fit_exactly():
    points = np.array([[2.0, 0.1, 0.3], [2.2, -0.5, 0.1], [1.9, 0.2, -0.6]])
    fit = fit_plane(points)
    assert fit.sse < 1e-24 and fit.count == 3
    assert np.allclose(points @ fit.normal, fit.offset, atol=1e-10)


# --------------------------------------------------------------------------------------------
# fit_labeled_planes
# --------------------------------------------------------------------------------------------


def _labeled_scan():
    """The 8 x 10 corner scan (noise 3 mm) with its ground-truth faces as labels 5, 9, 7, a
    3-pixel label 2 carved out of the floor, one no-return pixel, and -1/0 labels ignored."""
    scan = scenes.corner_scan(noise=0.003, seed=6, nan_pixels=[(1, 1)])
    labels = np.select([scan.truth == 0, scan.truth == 1, scan.truth == 2], [5, 9, 7], default=0)
    labels[7, :3] = 2  # three floor pixels: too small for a plane
    labels[0, 0] = -1
    return scan, labels


def test_fit_labeled_planes_bookkeeping():
    scan, labels = _labeled_scan()
    result = fit_labeled_planes(scan.points, labels, origins=scan.origins)
    assert isinstance(result, LabeledPlanes)
    planes = result.planes
    valid = np.isfinite(scan.points).all(axis=2)
    sizes = {label: int(((labels == label) & valid).sum()) for label in (5, 9, 7)}
    firsts = {label: int(np.flatnonzero(((labels == label) & valid).reshape(-1))[0]) for label in sizes}
    # planes numbered by decreasing size (ties: first pixel in row-major order); label_ids maps them back
    expected_order = sorted(sizes, key=lambda label: (-sizes[label], firsts[label]))
    assert result.label_ids.tolist() == expected_order
    assert planes.point_counts.tolist() == [sizes[label] for label in expected_order]
    for j, label in enumerate(result.label_ids):
        mask = (labels == label) & valid
        assert np.array_equal(planes.labels == j + 1, mask)
        pixels = np.flatnonzero(mask.reshape(-1))
        fit = fit_plane(scan.points.reshape(-1, 3)[pixels], scan.origins.reshape(-1, 3)[pixels])
        assert planes.sse[j] == pytest.approx(fit.sse, rel=1e-9)
        assert np.allclose(planes.normals[j], fit.normal, atol=1e-9)
        assert np.allclose(result.residuals[mask], fit.residuals, atol=1e-9)
        assert np.allclose(planes.covariances[j], fit.covariance, rtol=1e-6, atol=1e-15)
        assert np.allclose(planes.centroids[j], scan.points.reshape(-1, 3)[pixels].mean(axis=0), atol=1e-12)
    # no plane: the small label, ignored labels, the no-return pixel
    outside = planes.labels == 0
    assert np.array_equal(outside, ~np.isin(labels, [5, 9, 7]) | ~valid)
    assert np.all(np.isnan(result.residuals[outside]))
    assert np.all(np.isfinite(result.residuals[~outside]))


def test_a_degenerate_group_gets_nan_parameters_without_spoiling_the_others():
    scan, labels = _labeled_scan()
    labels = labels.copy()
    valid = np.isfinite(scan.points).all(axis=2)
    row = int(np.flatnonzero(valid.all(axis=1))[0])
    labels[row, :2] = 42  # two rays: no plane to fit
    result = fit_labeled_planes(scan.points, labels, origins=scan.origins, min_plane_points=2)
    planes = result.planes
    bad = np.flatnonzero(result.label_ids == 42)
    assert len(bad) == 1
    j = int(bad[0])
    assert np.all(np.isnan(planes.normals[j])) and np.isnan(planes.offsets[j])
    assert np.all(np.isnan(planes.covariances[j])) and np.all(np.isnan(result.residuals[row, :2]))
    others = np.arange(planes.num_planes) != j
    assert np.all(np.isfinite(planes.normals[others])) and np.all(np.isfinite(planes.covariances[others]))


def test_fit_labeled_planes_options():
    scan, labels = _labeled_scan()
    # min_plane_points 3 keeps the 3-pixel label
    small = fit_labeled_planes(scan.points, labels, origins=scan.origins, min_plane_points=3)
    assert sorted(small.label_ids.tolist()) == [2, 5, 7, 9]
    # ignore_labels_below 6: only 7 and 9 are planes
    high = fit_labeled_planes(scan.points, labels, origins=scan.origins, ignore_labels_below=6)
    assert sorted(high.label_ids.tolist()) == [7, 9]
    # integral float labels are accepted
    as_float = fit_labeled_planes(scan.points, labels.astype(float), origins=scan.origins)
    assert np.array_equal(
        as_float.planes.labels, fit_labeled_planes(scan.points, labels, origins=scan.origins).planes.labels
    )
    # labels far beyond the pixel count group the same pixels
    base = fit_labeled_planes(scan.points, labels, origins=scan.origins)
    huge = fit_labeled_planes(scan.points, labels * 10**12, origins=scan.origins)
    assert np.array_equal(huge.planes.labels, base.planes.labels)
    assert np.array_equal(huge.label_ids, base.label_ids * 10**12)
    assert np.array_equal(huge.planes.sse, base.planes.sse)
    # no labels at all: an empty set
    empty = fit_labeled_planes(scan.points, np.zeros(labels.shape, int), origins=scan.origins)
    assert empty.planes.num_planes == 0 and len(empty.label_ids) == 0 and np.all(np.isnan(empty.residuals))


@pytest.mark.parametrize(
    ('labels', 'message'),
    [
        (np.zeros((8, 9), int), 'grid shape'),
        (np.full((8, 10), 0.5), 'integers'),
        (np.full((8, 10), np.nan), 'integers'),
    ],
)
def test_fit_labeled_planes_rejects_bad_labels(labels, message):
    scan, _ = _labeled_scan()
    with pytest.raises(ValueError, match=message):
        fit_labeled_planes(scan.points, labels, origins=scan.origins)


def _delta_method_covariance(points, origins, normal, offset, sse):
    """Covariance of offset * normal by the delta method in an independent parameterisation:
    n(alpha, beta) = unit(normal + alpha u + beta v), d; central-difference Jacobians."""
    starts, directions, ranges = scenes.rays(points, origins)
    u = np.cross(normal, [0.3, -0.5, 0.8])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)

    def plane(params):
        n = normal + params[0] * u + params[1] * v
        return n / np.linalg.norm(n), params[2]

    def residuals(params):
        return scenes.radial_residuals(*plane(params), starts, directions, ranges)

    def closest(params):
        n, d = plane(params)
        return d * n

    x0 = np.array([0.0, 0.0, offset])
    h = 1e-6
    steps = np.eye(3) * h
    jac = np.column_stack([(residuals(x0 + s) - residuals(x0 - s)) / (2 * h) for s in steps])
    cov_params = sse / (len(points) - 3) * np.linalg.inv(jac.T @ jac)
    jac_c = np.column_stack([(closest(x0 + s) - closest(x0 - s)) / (2 * h) for s in steps])
    return jac_c @ cov_params @ jac_c.T


@pytest.mark.parametrize('starts', ['origin', 'point', 'per-ray'])
def test_covariance_is_the_delta_method_covariance_of_the_closest_point(starts):
    points, origins, _, _ = _plane_rays(80, noise=0.01, seed=7, starts=starts)
    fit = fit_plane(points, origins)
    expected = _delta_method_covariance(points, origins, fit.normal, fit.offset, fit.sse)
    assert np.allclose(fit.covariance, expected, rtol=1e-4, atol=1e-6 * np.abs(expected).max()), (
        f'reported\n{fit.covariance}\ndelta method\n{expected}'
    )
