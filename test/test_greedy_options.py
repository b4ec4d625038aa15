"""GreedyOptions: the greedy's seven tuning knobs as one checked, frozen object passed as ``options=``."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ppe_ros.core.extraction import DEFAULT_OPTIONS, GreedyOptions, extract_plane_hierarchy
from ppe_ros.core.ppe.layout import DEFAULT_EXACT_PLANE_SIZE, MERGE_LOOP_GROWTH, REFINED_MERGE_GROWTH
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
        'seed_shapes': 'all',
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
