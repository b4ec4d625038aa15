"""Tests of ppe_ros.core.evaluation: Hoover metrics exactly as the reference segcompeval.m.

Label images are hand-made; every expected count is derived by hand in the comments. Notation:
G_m = GT region m, S_n = extracted region n, fms = O_mn / |S_n|, fgt = O_mn / |G_m|, T = 0.8, all
tests strict ">".
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from ppe_ros.core.evaluation import SegmentationScore, aggregate_scores, score_segmentation


def counts(score: SegmentationScore) -> tuple[int, int, int, int, int]:
    """(correct, over, under, missed, noise)."""
    return score.n_correct, score.n_over, score.n_under, score.n_missed, score.n_noise


def segcompeval_dense(pred: np.ndarray, gt: np.ndarray, t: float = 0.8) -> tuple[int, int, int, int, int, float]:
    """Line-by-line dense transcription of the reference segcompeval.m, for cross-checking."""
    gti = np.unique(gt[gt >= 10])
    msi = np.unique(pred[pred > 0])
    o = np.array([[np.sum((gt == g) & (pred == p)) for p in msi] for g in gti], dtype=float).reshape(len(gti), len(msi))
    pms = np.array([np.sum(pred == p) for p in msi], dtype=float)
    pgt = np.array([np.sum(gt == g) for g in gti], dtype=float)
    fms = o / pms[None, :]
    fgt = o / pgt[:, None]
    foverseg = np.sum((fms > t) * fgt, axis=1) * (np.sum(fms > t, axis=1) >= 2)
    fundrseg = np.sum((fgt > t) * fms, axis=0) * (np.sum(fgt > t, axis=0) >= 2)
    corrseg = (fms > t) & (fgt > t)
    overseg = foverseg > t
    undrseg = fundrseg > t
    avgcorrseg = (fms * corrseg + fgt * corrseg) / 2
    avgoverseg = (np.sum(fms * (fms > t), axis=1) + foverseg * overseg) / (np.sum(fms > t, axis=1) + 1) * overseg
    avgundrseg = (np.sum(fgt * (fgt > t), axis=0) + fundrseg * undrseg) / (np.sum(fgt > t, axis=0) + 1) * undrseg
    avgoversegcause = np.sum((fms > t) * overseg[:, None] * fms, axis=0)
    avgundrsegcause = np.sum((fgt > t) * undrseg[None, :] * fgt, axis=1)
    corrseg = (avgcorrseg > avgoverseg[:, None]) & (avgcorrseg > avgundrseg[None, :])
    overseg = (avgoverseg > np.sum(avgcorrseg, axis=1)) & (avgoverseg > avgundrsegcause)
    undrseg = (avgundrseg > np.sum(avgcorrseg, axis=0)) & (avgundrseg > avgoversegcause)
    oversegcause = np.sum((fms > t) * overseg[:, None], axis=0)
    undrsegcause = np.sum((fgt > t) * undrseg[None, :], axis=1)
    missseg = (np.sum(corrseg, axis=1) + overseg + undrsegcause) == 0
    noisseg = (np.sum(corrseg, axis=0) + undrseg + oversegcause) == 0
    gtcorr = np.sum(corrseg, axis=1)
    fcorrseg = np.sum(pgt * gtcorr) / np.sum(pgt)
    return (
        int(corrseg.sum()),
        int(overseg.sum()),
        int(undrseg.sum()),
        int(missseg.sum()),
        int(noisseg.sum()),
        float(fcorrseg),
    )


# ---------------------------------------------------------------------------------------------
# Single classes
# ---------------------------------------------------------------------------------------------


def test_correct_pairs_perfect_segmentation():
    # GT 10 = left half (24 px), GT 11 = right half (24 px); predictions 1, 2 identical.
    # fms = fgt = 1 for both pairs -> 2 correct, nothing else; f = k = 1.
    gt = np.zeros((6, 8), np.int64)
    gt[:, :4], gt[:, 4:] = 10, 11
    pred = np.where(gt == 10, 1, 2)
    score = score_segmentation(pred, gt)
    assert counts(score) == (2, 0, 0, 0, 0)
    assert (score.n_gt, score.n_pred) == (2, 2)
    assert score.f == 1.0 and score.k == 1.0 and score.k_all_rays == 1.0
    assert score.gt_classes == ('correct', 'correct')
    assert score.pred_classes == ('correct', 'correct')
    assert score.correct_pairs.tolist() == [[10, 1], [11, 2]]
    assert score.consistent
    assert math.isnan(score.rmse) and math.isnan(score.alpha)


def test_over_segmentation_into_two_and_three():
    # GT 10 = whole 6x8 (48 px). Two predictions of 24 px each: fms = 1, fgt = 0.5 for both.
    # #{n: fms > T} = 2, fover = 0.5 + 0.5 = 1 > T -> raw over; no pair has fgt > T -> no correct.
    # aover = (1 + 1 + 1) / 3 = 1 > sum acorr = 0 and > aundercause = 0 -> over.
    # Both predictions have fms > T with an over GT -> overcause -> class 'over', not noise.
    gt = np.full((6, 8), 10)
    pred = np.where(np.arange(8)[None, :] < 4, 1, 2) * np.ones((6, 1), np.int64)
    score = score_segmentation(pred, gt)
    assert counts(score) == (0, 1, 0, 0, 0)
    assert score.gt_classes == ('over',) and score.pred_classes == ('over', 'over')
    assert score.f == 0.0 and score.k == 0.0
    # Three parts: cols 0-2 (18 px), 3-5 (18 px), 6-7 (12 px); fgt 0.375 + 0.375 + 0.25 = 1 > T.
    pred3 = np.digitize(np.arange(8), [3, 6])[None, :] + 1 + np.zeros((6, 1), np.int64)
    score3 = score_segmentation(pred3, gt)
    assert counts(score3) == (0, 1, 0, 0, 0)
    assert score3.pred_classes == ('over', 'over', 'over')


def test_under_segmentation_of_two_and_three_gt_regions():
    # GT 10 = cols 0-3 (24 px), GT 11 = cols 4-7 (24 px); one prediction covers all 48 px.
    # fgt = 1 (> T) for both GT, fms = 0.5 each: #{m: fgt > T} = 2, funder = 1 > T -> raw under;
    # no correct pair (fms 0.5). aunder = (1 + 1 + 1) / 3 = 1 > 0 -> under; both GT 'under'.
    gt = np.where(np.arange(8)[None, :] < 4, 10, 11) + np.zeros((6, 1), np.int64)
    pred = np.ones((6, 8), np.int64)
    score = score_segmentation(pred, gt)
    assert counts(score) == (0, 0, 1, 0, 0)
    assert score.gt_classes == ('under', 'under') and score.pred_classes == ('under',)
    # Three GT regions (cols 0-2, 3-5, 6-7) under one prediction: still one under-segmentation.
    gt3 = np.digitize(np.arange(8), [3, 6])[None, :] + 10 + np.zeros((6, 1), np.int64)
    score3 = score_segmentation(pred, gt3)
    assert counts(score3) == (0, 0, 1, 0, 0)
    assert score3.gt_classes == ('under', 'under', 'under')


def test_missed_and_noise():
    # GT 10 = rows 0-2 (24 px), GT 11 = rows 3-5 (24 px).
    # Prediction 1 = rows 0-2 exactly -> correct with GT 10.
    # GT 11 has no prediction at all -> missed.
    # Prediction 2 lies only on pixels with GT label 3 (non-GT): it overlaps no GT region -> noise.
    gt = np.zeros((6, 8), np.int64)
    gt[:3], gt[3:] = 10, 11
    gt[5, 4:] = 3  # 4 px of unlabelled points; GT 11 keeps 20 px
    pred = np.zeros_like(gt)
    pred[:3] = 1
    pred[5, 4:] = 2  # 4 px, all label 3
    score = score_segmentation(pred, gt)
    assert counts(score) == (1, 0, 0, 1, 1)
    assert score.gt_classes == ('correct', 'missed')
    assert score.pred_classes == ('correct', 'noise')
    # k = 24 / (24 + 20) labelled points; k_all_rays = 24 / 48 pixels.
    assert score.k == pytest.approx(24 / 44, abs=1e-15)
    assert score.k_all_rays == pytest.approx(24 / 48, abs=1e-15)


def test_partial_overlap_gives_missed_and_noise():
    # GT 10 = 24 px (rows 0-2); prediction 1 covers 12 of them only: fms = 1, fgt = 0.5.
    # Not correct (fgt), no over (only 1 prediction with fms > T) -> GT missed;
    # prediction: not correct, not under (1 GT with fgt > T? fgt 0.5: none), no overcause -> noise.
    gt = np.zeros((6, 8), np.int64)
    gt[:3] = 10
    pred = np.zeros_like(gt)
    pred[:3, :4] = 1
    assert counts(score_segmentation(pred, gt)) == (0, 0, 0, 1, 1)


# ---------------------------------------------------------------------------------------------
# Corner cases
# ---------------------------------------------------------------------------------------------


def test_exactly_80_percent_is_not_correct():
    # GT 10 = 5 px (row 0, cols 0-4). Prediction covers 4 of them and nothing else:
    # fgt = 4/5 = 0.8, which is NOT > 0.8 -> not correct: GT missed, prediction noise.
    gt = np.zeros((2, 8), np.int64)
    gt[0, :5] = 10
    pred = np.zeros_like(gt)
    pred[0, :4] = 1
    assert counts(score_segmentation(pred, gt)) == (0, 0, 0, 1, 1)
    # One more GT pixel covered: fgt = 5/5 = 1 -> correct.
    pred[0, 4] = 1
    assert counts(score_segmentation(pred, gt)) == (1, 0, 0, 0, 0)
    # The same threshold on the prediction side: 4 of 5 prediction pixels in GT 10 (fms = 0.8).
    gt2 = np.zeros((2, 8), np.int64)
    gt2[0, :4] = 10
    pred2 = np.zeros_like(gt2)
    pred2[0, :5] = 1  # pixel (0, 4) has GT label 0
    assert counts(score_segmentation(pred2, gt2)) == (0, 0, 0, 1, 1)
    # With a lower tolerance T = 0.75 the same pair is correct (0.8 > 0.75).
    assert counts(score_segmentation(pred2, gt2, threshold=0.75)) == (1, 0, 0, 0, 0)


def _tie_scene(extra_pixels_of_second: int) -> tuple[np.ndarray, np.ndarray]:
    """GT 10 = 112 px. Prediction 1 = 98 px inside GT 10 (fms = 1, fgt = 98/112 = 0.875).
    Prediction 2 = 7 px of GT 10 plus ``extra`` px of GT label 3 (fgt = 7/112 = 0.0625).
    The remaining 7 px of GT 10 are in no prediction. Image 8 x 15 = 120 px."""
    gt = np.full(120, 10, np.int64)
    pred = np.zeros(120, np.int64)
    pred[:98] = 1
    pred[98:105] = 2
    gt[112:] = 0  # 8 px outside GT 10 -> GT 10 has 112 px
    gt[112 : 112 + extra_pixels_of_second] = 3
    pred[112 : 112 + extra_pixels_of_second] = 2
    return pred.reshape(8, 15), gt.reshape(8, 15)


def test_tie_between_correct_and_over_is_neither():
    # extra = 1: fms2 = 7/8 = 0.875 > T, so #{n: fms > T} = 2 and fover = 0.875 + 0.0625 = 0.9375 > T.
    # acorr(10, 1) = (1 + 0.875) / 2 = 0.9375;  aover = (1 + 0.875 + 0.9375) / 3 = 2.8125 / 3 = 0.9375.
    # All values are exact binary fractions: an exact tie. Strict '>' both ways ->
    # not correct (acorr > aover fails), not over (aover > sum acorr fails) -> GT 10 missed;
    # prediction 1 and 2: not correct, not under, no overcause (over is false) -> 2 noise.
    pred, gt = _tie_scene(1)
    score = score_segmentation(pred, gt)
    assert counts(score) == (0, 0, 0, 1, 2)
    assert score.consistent
    assert counts(score) == segcompeval_dense(pred, gt)[:5]


def test_tie_neighbours_resolve_to_correct_or_over():
    # extra = 2: fms2 = 7/9 = 0.78 <= T -> only prediction 1 has fms > T -> no over;
    # (10, 1) correct with acorr 0.9375 > 0; prediction 2 (fgt 0.0625) -> noise.
    pred, gt = _tie_scene(2)
    assert counts(score_segmentation(pred, gt)) == (1, 0, 0, 0, 1)
    # extra = 0: fms2 = 1, aover = (1 + 1 + 0.9375) / 3 = 0.979 > acorr 0.9375 -> over wins;
    # both predictions are part of the over-segmentation -> no noise.
    pred, gt = _tie_scene(0)
    score = score_segmentation(pred, gt)
    assert counts(score) == (0, 1, 0, 0, 0)
    assert score.pred_classes == ('over', 'over')


def test_correct_pair_beside_small_pure_fragment_counts_as_over():
    # Reference semantics (not intuitive): GT 10 = 20 px; prediction 1 = 18 px of it (fgt 0.9),
    # prediction 2 = the other 2 px (fms = 1). #{fms > T} = 2, fover = 0.9 + 0.1 = 1.0 > T.
    # acorr = (1 + 0.9) / 2 = 0.95 < aover = (1 + 1 + 1.0) / 3 = 1 -> over, not correct.
    gt = np.zeros((4, 5), np.int64) + 10
    pred = np.ones_like(gt)
    pred[3, 3:] = 2
    score = score_segmentation(pred, gt)
    assert counts(score) == (0, 1, 0, 0, 0)
    # The reference removes 1-point planes first (min_pred_points=2): with a 1 px fragment the
    # remaining prediction (19 of 20 px, fgt 0.95) is correct...
    pred[3, 3] = 1
    assert counts(score_segmentation(pred, gt)) == (1, 0, 0, 0, 0)
    # ...unless the 1 px fragment is kept (min_pred_points=1): over again.
    assert counts(score_segmentation(pred, gt, min_pred_points=1)) == (0, 1, 0, 0, 0)


def test_labels_below_gt_min_count_towards_prediction_size():
    # GT 10 = 20 px (rows 0-3, cols 0-4 of a 6x5 image); label 3 = non-GT points.
    # Prediction 1 = GT 10 plus 4 px of label 3: |S| = 24, fms = 20/24 = 0.833 > T -> correct.
    gt = np.zeros((6, 5), np.int64)
    gt[:4] = 10
    gt[4:] = 3
    pred = np.zeros_like(gt)
    pred[:4] = 1
    pred[4, :4] = 1
    score = score_segmentation(pred, gt)
    assert counts(score) == (1, 0, 0, 0, 0)
    assert score.n_gt == 1  # label 3 is no GT region
    assert score.pred_sizes.tolist() == [24]
    # 6 px of label 3: |S| = 26, fms = 20/26 = 0.769 -> not correct: missed + noise.
    pred[4, 4] = 1
    pred[5, 0] = 1
    assert counts(score_segmentation(pred, gt)) == (0, 0, 0, 1, 1)
    # With gt_min_label=3, label 3 (10 px) is a GT region too: GT 10 fgt = 1, fms = 20/26;
    # GT 3 fgt = 6/10. Neither pair is correct; prediction 1 has only GT 10 with fgt > T.
    assert counts(score_segmentation(pred, gt, gt_min_label=3)) == (0, 0, 0, 2, 1)


def test_k_denominators():
    # 6x8 = 48 px. GT 10 = 20 px (rows 0-1 + row 2 cols 0-3), GT 11 = 12 px (row 3 + row 4 cols 0-3),
    # label 3 = 4 px (row 4 cols 4-7), label 0 = 12 px (row 5 and row 2 cols 4-7).
    gt = np.zeros((6, 8), np.int64)
    gt[:2] = 10
    gt[2, :4] = 10
    gt[3] = 11
    gt[4, :4] = 11
    gt[4, 4:] = 3
    pred = np.where(gt == 10, 1, 0)  # only GT 10 found
    score = score_segmentation(pred, gt)
    assert counts(score) == (1, 0, 0, 1, 0)
    assert score.k == 20 / 32  # labelled points (>= 10): 20 + 12
    assert score.k_all_rays == 20 / 48  # all rays
    valid = np.ones(gt.shape, bool)
    valid[5] = False  # 8 no-returns -> 40 valid rays
    assert score_segmentation(pred, gt, valid=valid).k_all_rays == 20 / 40
    assert score.f == 0.5


# ---------------------------------------------------------------------------------------------
# RMSE and alpha
# ---------------------------------------------------------------------------------------------


def test_rmse_pooled_over_planes_below_10_m():
    # Three predictions of 8 px each on a 4x6 image (rows 0-1 cols 0-3 = plane 1, etc.).
    pred = np.zeros((4, 6), np.int64)
    pred[:2, :4] = 1
    pred[2:, :4] = 2
    pred[:, 4:] = 3
    gt = pred + 9
    residuals = np.full(pred.shape, 1e6)  # values outside planes would be ignored (none here)
    # Plane 1: 4 x 0.03 and 4 x -0.04 -> SSE = 4 * 0.0009 + 4 * 0.0016 = 0.01; RMSE 0.035 < 10: kept.
    residuals[:2, :4] = [[0.03, 0.03, 0.03, 0.03], [-0.04, -0.04, -0.04, -0.04]]
    # Plane 2: +-10 m -> RMSE exactly 10, not < 10: dropped.
    residuals[2:, :4] = [[10.0, -10.0, 10.0, -10.0], [10.0, -10.0, 10.0, -10.0]]
    # Plane 3: one NaN residual -> RMSE NaN -> dropped (NaN < 10 is false in the reference).
    residuals[:, 4:] = 0.001
    residuals[0, 4] = np.nan
    score = score_segmentation(pred, gt, residuals=residuals)
    assert score.n_rmse_dropped == 2
    assert score.rmse_points == 8
    assert score.rmse_sse == pytest.approx(0.01, abs=1e-15)
    assert score.rmse == pytest.approx(math.sqrt(0.01 / 8), abs=1e-15)
    # Plane 2 at 9.99 m is kept and dominates the pooled RMSE: sqrt((0.01 + 8 * 9.99^2) / 16).
    residuals[2:, :4] = 9.99
    score = score_segmentation(pred, gt, residuals=residuals)
    assert score.n_rmse_dropped == 1
    assert score.rmse == pytest.approx(math.sqrt((0.01 + 8 * 9.99**2) / 16), rel=1e-14)
    # Residuals on "no plane" pixels are ignored.
    pred[:, 4:] = 0
    residuals[:, 4:] = np.nan
    assert score_segmentation(pred, gt, residuals=residuals).n_rmse_dropped == 0


def test_alpha_folds_angles_to_90_degrees():
    # Four GT rows (10..13), predictions 1..3 match 10..12 exactly; GT 13 has no prediction (missed).
    gt = np.repeat(np.arange(10, 14), 4).reshape(4, 4)
    pred = np.where(gt < 13, gt - 9, 0)
    normals = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [-1.0, 0.0, 1.0]])  # planes 1, 2, 3
    gt_angles = [
        (10, 11, 90.0),  # measured 90 -> |90 - 90| = 0
        (10, 12, 135.0),  # measured 45; GT folded 180 - 135 = 45 -> 0
        (11, 12, 40.0),  # measured angle((-1,0,0), (-1,0,1)) = 45 -> |45 - 40| = 5
        (10, 13, 90.0),  # GT 13 not correctly segmented -> skipped
    ]
    score = score_segmentation(pred, gt, gt_angles=gt_angles, pred_normals=normals)
    assert score.angle_count == 3
    assert score.angle_diff_sum == pytest.approx(5.0, abs=1e-12)
    assert score.alpha == pytest.approx(5.0 / 3.0, abs=1e-12)
    # A flipped normal gives 135 deg, folded to 45: same result; also via a mapping of normals.
    flipped = {1: -normals[0], 2: normals[1], 3: normals[2]}
    score2 = score_segmentation(pred, gt, gt_angles=gt_angles, pred_normals=flipped)
    assert score2.alpha == pytest.approx(5.0 / 3.0, abs=1e-12)
    with pytest.raises(ValueError, match='pred_normals'):
        score_segmentation(pred, gt, gt_angles=gt_angles)


# ---------------------------------------------------------------------------------------------
# Cross-check, aggregation, JSON, input validation, speed
# ---------------------------------------------------------------------------------------------


def _random_case(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    height, width = 12, 14
    # GT: a few rectangles of labels 10+ on a background of 0 and 3.
    gt = rng.choice([0, 3], size=(height, width))
    for label in range(10, 10 + int(rng.integers(1, 7))):
        r0, c0 = rng.integers(0, height - 2), rng.integers(0, width - 2)
        gt[r0 : r0 + rng.integers(2, 9), c0 : c0 + rng.integers(2, 9)] = label
    # Prediction: each GT label maps to a random plane id (equal ids merge regions), background to 0
    # or to one background plane; some regions are split at a random column; sparse noise pixels.
    mapping = np.concatenate([[0], rng.integers(1, 8, size=19)])
    if rng.random() < 0.3:
        mapping[0] = 7
    pred = mapping[np.clip(gt - 9, 0, 19)]
    cut = rng.integers(0, width)
    split = (np.arange(width)[None, :] >= cut) & (rng.random(20)[np.clip(gt - 9, 0, 19)] < 0.3)
    pred = np.where(split & (pred > 0), pred + 10, pred)
    pred = np.where(rng.random(gt.shape) < 0.02, rng.integers(0, 30, size=gt.shape), pred)
    if rng.random() < 0.5:
        pred = np.roll(pred, int(rng.integers(-1, 2)), axis=int(rng.integers(0, 2)))
    return pred, gt


def test_matches_dense_transcription_of_reference_on_random_segmentations():
    rng = np.random.default_rng(1234)
    totals = np.zeros(5, np.int64)
    for trial in range(60):
        pred, gt = _random_case(rng)
        score = score_segmentation(pred, gt, min_pred_points=1)
        expected = segcompeval_dense(pred, gt)
        assert counts(score) == expected[:5], f'trial {trial}'
        assert score.k == pytest.approx(expected[5], abs=1e-15), f'trial {trial}'
        totals += counts(score)
    # The random cases exercise every class (correct, over, under, missed, noise).
    assert np.all(totals > 0), totals


def test_aggregate_scores_like_the_paper_table():
    # Scan A: 2 GT, both correct (k = 1). Scan B: 2 GT (24 + 24 px), one correct, one missed, one noise.
    gt = np.zeros((6, 8), np.int64)
    gt[:3], gt[3:] = 10, 11
    perfect = np.where(gt == 10, 1, 2)
    partial = np.zeros_like(gt)
    partial[:3] = 1
    partial[3, :2] = 2  # 2 px of GT 11: fms = 1, fgt = 2/24 -> GT 11 missed, prediction 2 noise
    res_a = np.full(gt.shape, 0.01)
    res_b = np.full(gt.shape, 0.03)
    a = score_segmentation(perfect, gt, residuals=res_a)
    b = score_segmentation(partial, gt, residuals=res_b)
    assert counts(a) == (2, 0, 0, 0, 0) and counts(b) == (1, 0, 0, 1, 1)
    table = aggregate_scores([a, b])
    assert table['n_scans'] == 2
    assert table['f'] == 3 / 4  # sum correct / sum GT
    assert table['k'] == pytest.approx((1.0 + 0.5) / 2)
    assert table['n_m'] == 0.5 and table['n_s'] == 0.5 and table['n_o'] == 0 and table['n_u'] == 0
    assert table['rmse'] == pytest.approx((0.01 + 0.03) / 2)  # mean of per-scan RMSE
    # pooled: a has 48 points at 0.01, b has 26 points (24 + 2) at 0.03.
    assert table['rmse_pooled'] == pytest.approx(math.sqrt((48 * 0.01**2 + 26 * 0.03**2) / 74))
    assert table['rmse_filtered'] == pytest.approx(0.01)  # scans above 0.02 m dropped
    assert math.isnan(table['alpha'])
    with pytest.raises(ValueError, match='at least one'):
        aggregate_scores([])


def test_to_dict_is_json_ready():
    gt = np.full((3, 4), 10)
    score = score_segmentation(np.ones((3, 4), np.int64), gt)
    data = json.loads(json.dumps(score.to_dict(), allow_nan=False))
    assert data['n_correct'] == 1 and data['rmse'] is None and data['gt_classes'] == ['correct']
    assert data['correct_pairs'] == [[10, 1]]


def test_empty_prediction_and_empty_ground_truth():
    gt = np.full((3, 4), 10)
    score = score_segmentation(np.zeros((3, 4), np.int64), gt)
    assert counts(score) == (0, 0, 0, 1, 0) and score.n_pred == 0 and score.f == 0.0
    score = score_segmentation(np.ones((3, 4), np.int64), np.zeros((3, 4), np.int64))
    assert counts(score) == (0, 0, 0, 0, 1) and math.isnan(score.f) and math.isnan(score.k)


def test_input_validation():
    gt = np.full((3, 4), 10)
    with pytest.raises(ValueError, match='same shape'):
        score_segmentation(np.zeros((4, 3), np.int64), gt)
    with pytest.raises(ValueError, match='>= 0'):
        score_segmentation(-np.ones((3, 4), np.int64), gt)
    with pytest.raises(ValueError, match='2-D'):
        score_segmentation(np.zeros(12, np.int64), gt)
    with pytest.raises(ValueError, match='integer'):
        score_segmentation(np.full((3, 4), 0.5), gt)
    with pytest.raises(ValueError, match='threshold'):
        score_segmentation(gt, gt, threshold=1.0)
    with pytest.raises(ValueError, match='residuals'):
        score_segmentation(gt, gt, residuals=np.zeros((2, 2)))
    with pytest.raises(ValueError, match='valid'):
        score_segmentation(gt, gt, valid=np.ones((3, 4)))


def test_scores_a_500_by_500_block_image():
    rng = np.random.default_rng(5)
    gt = (np.arange(500)[:, None] // 50 * 10 + np.arange(500)[None, :] // 50) + 10  # 100 blocks
    pred = np.where(rng.random(gt.shape) < 0.05, rng.integers(1, 5000, size=gt.shape), gt - 9)
    residuals = rng.normal(0.0, 0.01, size=gt.shape)
    score = score_segmentation(pred, gt, residuals=residuals)
    assert score.n_gt == 100 and score.consistent
    # 5 % of the pixels scattered over other labels leave every block above T = 0.8; a block that
    # also holds all pixels of one small noise label counts as over-segmented (Hoover)
    assert score.n_correct + score.n_over == 100 and score.n_correct >= 80
    assert score.n_missed == 0 and score.n_under == 0
