"""The greedy's two-level priority queue (heap + far key buckets) against a plain sorted list; the prefetch hint."""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import pytest

from ppe_ros.core.ppe.intrinsics import _prefetch
from ppe_ros.core.ppe.layout import (
    _G_EXTEND,
    _G_MERGE_EXACT,
    _G_MERGE_MODEL,
    _G_SEED,
    _NPI,
    _PALIVE,
    _PSTAMP,
    _PVER,
    _Q_BUCKETS,
    _Q_CHUNK,
    _Q_PER_OCTAVE,
    _QCOUNT,
)
from ppe_ros.core.ppe.queue import _g_pop, _q_bucket, _q_load, _q_new, _q_push
from ppe_ros.core.ppe.seeds import _sort_seed_keys


@nb.njit
def _live(kind, a, b, va, vb, pi):
    """The kernel's test of a popped entry: proxies need their plane's stamp, merges both versions."""
    if kind == _G_EXTEND:
        return pi[a, _PALIVE] != 0 and va == pi[a, _PSTAMP]
    if kind == _G_MERGE_MODEL or kind == _G_MERGE_EXACT:
        return pi[a, _PALIVE] != 0 and pi[b, _PALIVE] != 0 and va == pi[a, _PVER] and vb == pi[b, _PVER]
    return True


@nb.njit
def _drive(ops, keys, ints, pi):
    """Run pushes (op 0: entry t) and pops (op 1) through the queue; returns the popped entries.

    A pop discards stale entries until it finds a live one, as the kernel does.
    """
    gkey, gint, fkey, fint, fnext, bhead, qstate = _q_new(len(ops) + 8)
    gsize = 0
    out_keys = np.empty(len(ops))
    out_ints = np.empty((len(ops), 5), np.int64)
    n_out = 0
    for t in range(len(ops)):
        if ops[t] == 0:
            gsize = _q_push(
                gkey,
                gint,
                gsize,
                fkey,
                fint,
                fnext,
                bhead,
                qstate,
                keys[t],
                ints[t, 0],
                ints[t, 1],
                ints[t, 2],
                ints[t, 3],
                ints[t, 4],
            )
        else:
            while True:
                if gsize == 0 and qstate[_QCOUNT] > 0:
                    gsize = _q_load(gkey, gint, fkey, fint, fnext, bhead, qstate, pi)
                if gsize == 0:
                    break
                gsize = _g_pop(gkey, gint, gsize)
                if _live(gint[gsize, 0], gint[gsize, 1], gint[gsize, 2], gint[gsize, 3], gint[gsize, 4], pi):
                    out_keys[n_out] = gkey[gsize]
                    for c in range(5):
                        out_ints[n_out, c] = gint[gsize, c]
                    n_out += 1
                    break
    return out_keys[:n_out], out_ints[:n_out]


def _reference(ops, keys, ints, pi):
    """The same operations on a Python list: each pop takes the least live (key, kind, a, b)."""
    pending, out = [], []
    for t, op in enumerate(ops):
        if op == 0:
            pending.append((keys[t], *(int(x) for x in ints[t])))
            continue
        while pending:
            best = min(pending, key=lambda e: e[:4])
            pending.remove(best)
            if _live(*best[1:], pi):
                out.append(best)
                break
    return out


def _operations(rng, n, kinds):
    """n pushes with keys spread over 12 decades (with exact ties and zeros), pops interleaved."""
    keys = 10.0 ** rng.uniform(-12, 0, n)
    keys[rng.random(n) < 0.1] = 0.0
    ties = rng.random(n) < 0.2
    keys[ties] = rng.choice(keys[~ties], ties.sum())
    # later pushes drift upwards like the greedy's increments, with many far below the front
    keys *= np.where(rng.random(n) < 0.5, 1.0, np.linspace(1e-6, 1.0, n))
    ints = np.zeros((n, 5), np.int64)
    ints[:, 0] = rng.choice(kinds, n)
    ints[:, 1] = rng.integers(0, 50, n)
    ints[:, 2] = rng.integers(0, 50, n)
    ints[:, 3] = rng.integers(0, 3, n)
    ints[:, 4] = rng.integers(0, 3, n)
    ops = np.zeros(2 * n, np.int64)
    all_keys = np.zeros(2 * n)
    all_ints = np.zeros((2 * n, 5), np.int64)
    slots = np.sort(rng.choice(2 * n, n, replace=False))
    # a pop of an empty queue pops nothing in both implementations
    ops[:] = 1
    ops[slots] = 0
    all_keys[slots] = keys
    all_ints[slots] = ints
    return ops, all_keys, all_ints


def _assert_same_order(got, expected):
    """Same order of (key, kind, a, b); entries equal in all four (versions aside) may come in any order."""
    assert [e[:4] for e in got] == [e[:4] for e in expected]
    assert sorted(got) == sorted(expected)


@pytest.mark.parametrize('seed', range(5))
def test_queue_pops_in_the_order_of_key_kind_and_ids(seed):
    rng = np.random.default_rng(seed)
    ops, keys, ints = _operations(rng, 3000, [_G_SEED])
    pi = np.zeros((64, _NPI), np.int64)
    out_keys, out_ints = _drive(ops, keys, ints, pi)
    expected = _reference(ops, keys, ints, pi)
    assert len(out_keys) == len(expected) > 1000
    _assert_same_order([(k, *map(int, i)) for k, i in zip(out_keys, out_ints, strict=True)], expected)


@pytest.mark.parametrize('seed', range(3))
def test_queue_drops_only_stale_entries_and_keeps_the_order_of_the_rest(seed):
    """Proxies with an old stamp and merges of changed or gone planes are dropped, nothing else."""
    rng = np.random.default_rng(100 + seed)
    ops, keys, ints = _operations(rng, 3000, [_G_SEED, _G_EXTEND, _G_MERGE_MODEL, _G_MERGE_EXACT])
    pi = np.zeros((64, _NPI), np.int64)
    pi[:, _PALIVE] = rng.random(64) < 0.8
    pi[:, _PSTAMP] = rng.integers(0, 3, 64)
    pi[:, _PVER] = rng.integers(0, 3, 64)
    out_keys, out_ints = _drive(ops, keys, ints, pi)
    got = [(k, *map(int, i)) for k, i in zip(out_keys, out_ints, strict=True)]
    expected = _reference(ops, keys, ints, pi)
    assert len(expected) > 500
    _assert_same_order(got, expected)


@pytest.mark.parametrize('n', [1, _Q_CHUNK - 1, _Q_CHUNK, _Q_CHUNK + 1, 10 * _Q_CHUNK + 3])
def test_a_far_bucket_of_several_chunks_pops_in_order_and_its_chunks_are_reused(n):
    """n entries in one far bucket (keys within a quarter octave), a key in a later bucket, then a
    second round that pushes into buckets emptied before (their chunks come off the free stack)."""
    rng = np.random.default_rng(n)
    ops, keys, ints = [], [], []
    for base in (1.0, 4.0, 1e-3):
        for t in range(n):
            ops.append(0)
            keys.append(base * (1.0 + 0.15 * rng.random()))
            ints.append((_G_SEED, t, rng.integers(0, 17), 0, 0))
        ops.append(0)
        keys.append(base * 3.0)
        ints.append((_G_SEED, n, 0, 0, 0))
        ops.extend([1] * (n + 1))
        keys.extend([0.0] * (n + 1))
        ints.extend([(0, 0, 0, 0, 0)] * (n + 1))
    ops, keys, ints = np.array(ops), np.array(keys), np.array(ints, np.int64)
    pi = np.zeros((64, _NPI), np.int64)
    out_keys, out_ints = _drive(ops, keys, ints, pi)
    expected = _reference(ops, keys, ints, pi)
    assert len(out_keys) == len(expected) == 3 * (n + 1)
    _assert_same_order([(k, *map(int, i)) for k, i in zip(out_keys, out_ints, strict=True)], expected)


def test_bucket_index_never_decreases_with_the_key():
    rng = np.random.default_rng(7)
    keys = np.sort(
        np.concatenate(
            [
                [
                    0.0,
                    5e-324,
                    1e-310,
                    2.2250738585072014e-308,
                    1e-300,
                    1e-12,
                    0.5,
                    1.0,
                    1.0 + 1e-16,
                    2.0,
                    1e300,
                    np.finfo(float).max,
                    np.inf,
                ],
                10.0 ** rng.uniform(-320, 300, 20000),
            ]
        )
    )
    buckets = np.array([_q_bucket(k) for k in keys])
    assert np.all(np.diff(buckets) >= 0)
    assert buckets.min() >= 0 and buckets.max() < _Q_BUCKETS
    # four buckets per octave: keys a factor 2 apart are four buckets apart
    assert _q_bucket(2e-5) - _q_bucket(1e-5) == 4


def test_bucket_index_from_float_bits_equals_the_frexp_formula():
    """_q_bucket reads a normal key's exponent and top fraction bits directly; it must give the
    bucket of the frexp formula (mantissa in [0.5, 1)) for every key, subnormals and edges included."""

    def by_frexp(key):
        if not key > 0.0:
            return 0
        if not key < np.inf:
            return _Q_BUCKETS - 1
        mantissa, exponent = math.frexp(key)
        return (exponent + 1100) * _Q_PER_OCTAVE + int((mantissa - 0.5) * (2 * _Q_PER_OCTAVE))

    rng = np.random.default_rng(11)
    keys = np.concatenate(
        [
            [
                0.0,
                -0.0,
                -1.0,
                np.nan,
                np.inf,
                5e-324,
                1e-310,
                np.nextafter(2.2250738585072014e-308, 0.0),
                2.2250738585072014e-308,
                0.5,
                np.nextafter(0.5, 1.0),
                0.625,
                np.nextafter(0.625, 0.0),
                0.75,
                0.875,
                np.nextafter(1.0, 0.0),
                1.0,
                np.finfo(float).max,
            ],
            10.0 ** rng.uniform(-323, 308, 50000),
        ]
    )
    assert [_q_bucket(k) for k in keys] == [by_frexp(k) for k in keys]


def test_seed_sort_equals_a_stable_argsort():
    """The radix sort of the seed keys gives the anchors in the order of a stable argsort (ties by
    anchor id), infinite keys (no seed) left out, on keys with ties, zeros, -0.0, subnormals and
    keys spread over many octaves (every digit used)."""
    rng = np.random.default_rng(5)
    cases = [
        np.array([], float),
        np.array([np.inf, np.inf]),
        np.array([3.0, -0.0, 0.0, 1e-310, 5e-324, np.inf, 3.0, 0.0, 2.0]),
        np.round(rng.uniform(0, 1e-3, 20000), 7),  # many ties
        10.0 ** rng.uniform(-300, 2, 20000),
        np.where(rng.random(20000) < 0.3, np.inf, rng.uniform(0, 0.05, 20000)),
        np.full(1000, 0.25),
    ]
    for keys in cases:
        order, sorted_keys = _sort_seed_keys(keys)
        finite = np.flatnonzero(keys < np.inf)
        expected = finite[np.argsort(keys[finite], kind='stable')]
        np.testing.assert_array_equal(order, expected)
        np.testing.assert_array_equal(sorted_keys, keys[expected])
        # keys above a cutoff are left out as well (seeds a run can never reach)
        if len(finite):
            cutoff = np.median(keys[finite])
            order, sorted_keys = _sort_seed_keys(keys, cutoff)
            np.testing.assert_array_equal(order, expected[keys[expected] <= cutoff])
            np.testing.assert_array_equal(sorted_keys, keys[order])


@nb.njit
def _sum_with_prefetch(values_1d, values_2d):
    total = 0.0
    for i in range(len(values_1d)):
        if i + 4 < len(values_1d):
            _prefetch(values_1d, i + 4, 0)
            _prefetch(values_2d, i + 4, 1)
        total += values_1d[i] + values_2d[i, 1]
    return total


def test_prefetch_hint_compiles_for_1d_and_2d_arrays_and_changes_nothing():
    rng = np.random.default_rng(0)
    values_1d, values_2d = rng.random(100), rng.random((100, 3))
    assert _sum_with_prefetch(values_1d, values_2d) == pytest.approx(values_1d.sum() + values_2d[:, 1].sum())
    with pytest.raises(nb.core.errors.TypingError):
        nb.njit(lambda a: _prefetch(a, 0, 0))(np.zeros((2, 2, 2)))
