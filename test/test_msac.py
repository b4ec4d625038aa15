"""Sequential MSAC baseline: finds the planes of a simple scene, follows the stop rule, is deterministic."""

from __future__ import annotations

import numpy as np
import pytest

from ppe_ros.core.evaluation import score_segmentation
from ppe_ros.core.msac import extract_planes_msac
from ppe_ros.core.synthetic import plane_scan


@pytest.fixture(scope='module')
def three_planes():
    return plane_scan(3, rows=30, cols=40)


def test_finds_the_three_planes_of_a_noise_free_scene(three_planes):
    result = extract_planes_msac(three_planes.points, distance=0.01, min_remaining_fraction=0.0, seed=3)
    assert result.num_planes == 3
    assert np.all(result.labels > 0)  # every ray hits one of the planes, and each is within 1 cm of its plane
    score = score_segmentation(result.labels, three_planes.labels)
    assert score.n_gt == 3 and score.n_correct == 3 and score.f == 1.0
    # each detected plane is the ground-truth plane it covers: same normal (up to sign) and offset
    for label in range(1, 4):
        gt_label = np.bincount(three_planes.labels[result.labels == label]).argmax()
        normal, offset = three_planes.plane_of_label(int(gt_label))
        sign = np.sign(result.normals[label - 1] @ normal)
        assert np.allclose(sign * result.normals[label - 1], normal, atol=1e-6)
        assert abs(sign * result.offsets[label - 1] - offset) < 1e-6
    assert result.inlier_counts.sum() == three_planes.labels.size
    assert np.all(result.offsets >= 0)


def test_planes_are_found_largest_first(three_planes):
    result = extract_planes_msac(three_planes.points, distance=0.01, min_remaining_fraction=0.0, seed=0)
    sizes = np.bincount(three_planes.labels.ravel(), minlength=13)
    found = [np.bincount(three_planes.labels[result.labels == label]).argmax() for label in (1, 2, 3)]
    assert list(sizes[found]) == sorted(sizes[10:13], reverse=True)
    # inliers within 1 cm of a plane include a few rays of its neighbours next to the creases
    assert np.allclose(result.inlier_counts, sizes[found], rtol=0.03)


def test_deterministic_for_a_seed():
    scan = plane_scan(3, rows=30, cols=40, radial_sigma=0.02, seed=5)
    first = extract_planes_msac(scan.points, seed=11)
    second = extract_planes_msac(scan.points, seed=11)
    assert np.array_equal(first.labels, second.labels)
    assert np.array_equal(first.normals, second.normals)
    assert np.array_equal(first.trials, second.trials)
    other = extract_planes_msac(scan.points, seed=12)
    assert not np.array_equal(first.normals, other.normals)  # the seed is used


def test_stops_once_the_fraction_is_left(three_planes):
    fraction = 0.3
    result = extract_planes_msac(three_planes.points, distance=0.01, min_remaining_fraction=fraction, seed=0)
    n = three_planes.labels.size
    left = np.count_nonzero(result.labels == 0)
    assert left <= fraction * n
    assert left + result.inlier_counts[-1] > fraction * n  # the loop did not go on after reaching the fraction
    assert result.num_planes < 3


def test_no_returns_stay_unlabelled_and_count_in_the_fraction(three_planes):
    points = three_planes.points.copy()
    points[:, :20] = np.nan  # half the pixels are no-returns
    result = extract_planes_msac(points, distance=0.01, min_remaining_fraction=0.5, seed=0)
    assert np.all(result.labels[:, :20] == 0)
    assert result.num_planes == 0  # 50 % left already: nothing to do, as the reference (N counts NaN pixels)
    result = extract_planes_msac(points, distance=0.01, min_remaining_fraction=0.0, seed=0)
    assert np.all(result.labels[:, 20:] > 0)


@pytest.mark.parametrize(
    ('kwargs', 'message'),
    [
        ({'distance': 0.0}, 'distance'),
        ({'distance': float('nan')}, 'distance'),
        ({'min_remaining_fraction': 1.0}, 'min_remaining_fraction'),
        ({'max_trials': 0}, 'max_trials'),
        ({'confidence': 1.0}, 'confidence'),
        ({'seed': -1}, 'seed'),
        ({'max_scored_points': 2}, 'max_scored_points'),
    ],
)
def test_bad_parameters_are_rejected(three_planes, kwargs, message):
    with pytest.raises(ValueError, match=message):
        extract_planes_msac(three_planes.points, **kwargs)


def test_bad_points_are_rejected():
    with pytest.raises(ValueError, match=r'\(H, W, 3\)'):
        extract_planes_msac(np.zeros((10, 3)))
