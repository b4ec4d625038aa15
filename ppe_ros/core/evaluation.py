"""Segmentation metrics of the PPE paper's evaluation (Hoover et al. 1996, as in ``segcompeval.m``).

Ground truth (GT) regions are the labels ``>= gt_min_label`` (10 for SynPEB and SegComp); smaller
labels are unlabelled/edge pixels: they are no GT region but still count towards the size of an
extracted plane that contains them. Predicted label 0 means "no plane".

With ``O_mn`` the overlap of GT region m and extracted region n, ``fms = O_mn / |S_n|`` and
``fgt = O_mn / |G_m|``, every test is a *strict* ``> T`` (T = 0.8):

* raw classes: correct pair ``fms > T and fgt > T``; over-segmented GT m if ``>= 2`` extracted n
  have ``fms > T`` and their ``fgt`` sum exceeds T; under-segmented extracted n likewise with the
  roles swapped;
* average scores ``acorr``, ``aover``, ``aunder``, ``aovercause``, ``aundercause`` and the
  exclusive classification exactly as in the reference code (see the notes, section 3.1);
* missed GT regions and noise (spurious) extracted regions are those left over.

Also: ``f = correct / #GT``, ``k`` = fraction of labelled points (label >= gt_min_label) in
correctly segmented GT regions, ``k_all_rays`` the paper's variant over all valid rays, the RMSE of
radial residuals pooled over the points of extracted planes whose own RMSE is < 10 m, and the angle
metric alpha. Pure numpy.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields

import numpy as np

DEFAULT_THRESHOLD = 0.8
"""Hoover tolerance T of the reference evaluation (``tcomp``)."""

RMSE_PLANE_LIMIT = 10.0
"""Extracted planes whose own RMSE is not below this (metres) are left out of the scan RMSE."""

GT_CLASSES = ('correct', 'over', 'under', 'missed')
"""Classes of a GT region: correctly segmented, over-segmented, part of an under-segmentation, missed."""

PRED_CLASSES = ('correct', 'under', 'over', 'noise')
"""Classes of an extracted region: correct, under-segmented, part of an over-segmentation, noise."""


@dataclass(frozen=True)
class SegmentationScore:
    """Scores of one segmentation against its ground truth.

    Attributes:
        f: ``n_correct / n_gt`` (NaN without GT regions).
        k: labelled points (label >= gt_min_label) in correctly segmented GT regions divided by
            all labelled points (the reference code's ``fcorrseg``; NaN without labelled points).
        k_all_rays: the same numerator divided by the number of valid rays (the paper's formula).
        rmse: radial residual RMSE (m) pooled over the points of extracted planes whose own RMSE
            is < 10 m; NaN if no residuals were given or no plane qualifies.
        n_gt, n_pred: number of GT regions and of extracted regions (planes).
        n_correct, n_over, n_under, n_missed, n_noise: Hoover counts (n_over counts GT regions,
            n_under extracted regions, n_noise extracted regions).
        alpha: mean absolute difference (degrees) between extracted and GT angles of GT plane
            pairs whose both planes are correctly segmented; NaN if there is none.
        angle_diff_sum, angle_count: the sum and count behind alpha (for aggregation).
        rmse_sse, rmse_points: sum of squared residuals (m^2) and point count behind rmse.
        n_rmse_dropped: extracted planes left out of rmse (own RMSE >= 10 m or NaN residuals).
        gt_labels, gt_sizes, gt_classes: per GT region (ascending label): its label, pixel count
            and class (one of GT_CLASSES; several joined by '+' if the classification is
            inconsistent, which the reference only warns about).
        pred_labels, pred_sizes, pred_classes: the same per extracted region (PRED_CLASSES).
        correct_pairs: ``(n_correct, 2)`` int64 rows (gt label, predicted label).
        consistent: every region got exactly one class.
        threshold: the tolerance T used.
    """

    f: float
    k: float
    k_all_rays: float
    rmse: float
    n_gt: int
    n_pred: int
    n_correct: int
    n_over: int
    n_under: int
    n_missed: int
    n_noise: int
    alpha: float
    angle_diff_sum: float
    angle_count: int
    rmse_sse: float
    rmse_points: int
    n_rmse_dropped: int
    gt_labels: np.ndarray
    gt_sizes: np.ndarray
    gt_classes: tuple[str, ...]
    pred_labels: np.ndarray
    pred_sizes: np.ndarray
    pred_classes: tuple[str, ...]
    correct_pairs: np.ndarray
    consistent: bool
    threshold: float

    def to_dict(self) -> dict:
        """JSON-ready dict: arrays become lists, NaN becomes None."""
        out = {}
        for item in fields(self):
            out[item.name] = _jsonable(getattr(self, item.name))
        return out


def _jsonable(value):
    if isinstance(value, np.ndarray):
        return [_jsonable(v) for v in value.tolist()]
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _as_label_image(labels: np.ndarray, name: str) -> np.ndarray:
    array = np.asarray(labels)
    if array.ndim != 2:
        raise ValueError(f'{name} must be a 2-D (H, W) label image; got shape {array.shape}')
    if array.dtype.kind == 'f':
        if not np.all(np.isfinite(array)) or np.any(array != np.round(array)):
            raise ValueError(f'{name} must hold integer labels; got non-integer or non-finite values')
    elif array.dtype.kind not in 'iub':
        raise ValueError(f'{name} must be an integer label image; got dtype {array.dtype}')
    return array.astype(np.int64)


def _group_sum(index: np.ndarray, weights: np.ndarray, size: int) -> np.ndarray:
    """Per-group sums, accumulated in input order (as MATLAB's sum along a dimension)."""
    return np.bincount(index, weights=weights, minlength=size).astype(np.float64)


def _check_score_inputs(
    pred_labels: np.ndarray,
    gt_labels: np.ndarray,
    residuals: np.ndarray | None,
    valid: np.ndarray | None,
    threshold: float,
    gt_angles: Sequence[tuple[int, int, float]] | None,
    pred_normals,
    min_pred_points: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Validated ``(pred, gt, residuals, valid)``: int64 label images, float64 residuals, bool mask."""
    pred = _as_label_image(pred_labels, 'pred_labels')
    gt = _as_label_image(gt_labels, 'gt_labels')
    if pred.shape != gt.shape:
        raise ValueError(f'pred_labels {pred.shape} and gt_labels {gt.shape} must have the same shape')
    if np.any(pred < 0):
        raise ValueError('pred_labels must be >= 0 (0 = no plane)')
    if not (0.0 <= threshold < 1.0):
        raise ValueError(f'threshold must be in [0, 1); got {threshold}')
    if int(min_pred_points) != min_pred_points or min_pred_points < 1:
        raise ValueError(f'min_pred_points must be a positive integer; got {min_pred_points}')
    if valid is not None:
        valid = np.asarray(valid)
        if valid.shape != gt.shape or valid.dtype != np.bool_:
            raise ValueError(f'valid must be a bool array of shape {gt.shape}; got {valid.dtype} {valid.shape}')
    if residuals is not None:
        residuals = np.asarray(residuals, dtype=np.float64)
        if residuals.shape != gt.shape:
            raise ValueError(f'residuals must have shape {gt.shape}; got {residuals.shape}')
    if gt_angles and pred_normals is None:
        raise ValueError('gt_angles need pred_normals (the normals of the extracted planes)')
    return pred, gt, residuals, valid


@dataclass(frozen=True)
class _Regions:
    """The scored regions: sorted labels and pixel counts of the GT and the kept extracted regions."""

    pred_flat: np.ndarray  # flattened predicted labels, regions below min_pred_points set to 0
    pred_values: np.ndarray
    pred_counts: np.ndarray
    gt_values: np.ndarray
    gt_counts: np.ndarray


def _find_regions(pred_flat: np.ndarray, gt_flat: np.ndarray, gt_min_label: int, min_pred_points: int) -> _Regions:
    """GT regions (labels >= gt_min_label) and extracted regions (dropping those below min_pred_points)."""
    pred_values, pred_counts = np.unique(pred_flat[pred_flat > 0], return_counts=True)
    keep = pred_counts >= min_pred_points
    if not np.all(keep):
        pred_flat = np.where(np.isin(pred_flat, pred_values[~keep]), 0, pred_flat)
        pred_values, pred_counts = pred_values[keep], pred_counts[keep]
    gt_values, gt_counts = np.unique(gt_flat[gt_flat >= gt_min_label], return_counts=True)
    return _Regions(pred_flat, pred_values, pred_counts, gt_values, gt_counts)


@dataclass(frozen=True)
class _OverlapTable:
    """Sparse Hoover overlap table over the (GT m, extracted n) pairs that share pixels, sorted by (m, n)."""

    pair_m: np.ndarray  # GT region index of each pair
    pair_n: np.ndarray  # extracted region index of each pair
    fms: np.ndarray  # O_mn / |S_n|
    fgt: np.ndarray  # O_mn / |G_m|


def _overlap_table(gt_flat: np.ndarray, gt_min_label: int, regions: _Regions) -> _OverlapTable:
    """Overlaps O_mn of the GT and extracted regions as the fractions fms and fgt of each pair."""
    n_pred = len(regions.pred_values)
    both = (gt_flat >= gt_min_label) & (regions.pred_flat > 0)
    gt_index = np.searchsorted(regions.gt_values, gt_flat[both])
    pred_index = np.searchsorted(regions.pred_values, regions.pred_flat[both])
    codes, overlaps = np.unique(gt_index * max(n_pred, 1) + pred_index, return_counts=True)
    pair_m = codes // max(n_pred, 1)
    pair_n = codes % max(n_pred, 1)
    overlap = overlaps.astype(np.float64)
    fms = overlap / regions.pred_counts[pair_n]
    fgt = overlap / regions.gt_counts[pair_m]
    return _OverlapTable(pair_m, pair_n, fms, fgt)


@dataclass(frozen=True)
class _Classification:
    """Exclusive Hoover classes: per pair (correct), per GT region and per extracted region."""

    correct: np.ndarray  # per pair: a correct detection
    over: np.ndarray  # per GT region: over-segmented
    under: np.ndarray  # per extracted region: under-segmented
    missed: np.ndarray  # per GT region
    noise: np.ndarray  # per extracted region
    correct_per_m: np.ndarray  # per GT region: number of correct pairs
    correct_per_n: np.ndarray  # per extracted region: number of correct pairs
    overcause: np.ndarray  # per extracted region: over-segmented GT regions it is part of
    undercause: np.ndarray  # per GT region: under-segmented extracted regions it is part of


def _classify(table: _OverlapTable, n_gt: int, n_pred: int, t: float) -> _Classification:
    """Raw classes, average scores and the exclusive classification, exactly as ``segcompeval.m``."""
    pair_m, pair_n, fms, fgt = table.pair_m, table.pair_n, table.fms, table.fgt
    in_ms = fms > t  # [fms_mn > T]
    in_gt = fgt > t  # [fgt_mn > T]

    count_ms_per_m = np.bincount(pair_m[in_ms], minlength=n_gt)
    count_gt_per_n = np.bincount(pair_n[in_gt], minlength=n_pred)
    f_over = _group_sum(pair_m, fgt * in_ms, n_gt) * (count_ms_per_m >= 2)
    f_under = _group_sum(pair_n, fms * in_gt, n_pred) * (count_gt_per_n >= 2)
    correct_raw = in_ms & in_gt
    over_raw = f_over > t
    under_raw = f_under > t

    acorr = (fms * correct_raw + fgt * correct_raw) / 2
    aover = (_group_sum(pair_m, fms * in_ms, n_gt) + f_over * over_raw) / (count_ms_per_m + 1) * over_raw
    aunder = (_group_sum(pair_n, fgt * in_gt, n_pred) + f_under * under_raw) / (count_gt_per_n + 1) * under_raw
    aovercause = _group_sum(pair_n, in_ms * over_raw[pair_m] * fms, n_pred)
    aundercause = _group_sum(pair_m, in_gt * under_raw[pair_n] * fgt, n_gt)

    # Exclusive classification (uses the pre-exclusion acorr, as the reference does).
    correct = (acorr > aover[pair_m]) & (acorr > aunder[pair_n])
    over = (aover > _group_sum(pair_m, acorr, n_gt)) & (aover > aundercause)
    under = (aunder > _group_sum(pair_n, acorr, n_pred)) & (aunder > aovercause)
    overcause = np.bincount(pair_n[in_ms & over[pair_m]], minlength=n_pred)  # counts, as the reference
    undercause = np.bincount(pair_m[in_gt & under[pair_n]], minlength=n_gt)
    correct_per_m = np.bincount(pair_m[correct], minlength=n_gt)
    correct_per_n = np.bincount(pair_n[correct], minlength=n_pred)
    missed = (correct_per_m == 0) & ~over & (undercause == 0)
    noise = (correct_per_n == 0) & ~under & (overcause == 0)
    return _Classification(correct, over, under, missed, noise, correct_per_m, correct_per_n, overcause, undercause)


def _class_names(classes: _Classification) -> tuple[tuple[str, ...], tuple[str, ...], bool]:
    """Class names per GT region and per extracted region ('+'-joined if several), and consistency."""
    gt_flags = np.stack([classes.correct_per_m > 0, classes.over, classes.undercause > 0, classes.missed], axis=1)
    pred_flags = np.stack([classes.correct_per_n > 0, classes.under, classes.overcause > 0, classes.noise], axis=1)
    gt_classes = tuple('+'.join(n for n, flag in zip(GT_CLASSES, row, strict=True) if flag) for row in gt_flags)
    pred_classes = tuple('+'.join(n for n, flag in zip(PRED_CLASSES, row, strict=True) if flag) for row in pred_flags)
    consistent = bool(
        np.all(classes.correct_per_m + classes.over + classes.undercause + classes.missed == 1)
        and np.all(classes.correct_per_n + classes.under + classes.overcause + classes.noise == 1)
    )
    return gt_classes, pred_classes, consistent


def _score_result(
    gt: np.ndarray,
    valid: np.ndarray | None,
    residuals: np.ndarray | None,
    regions: _Regions,
    table: _OverlapTable,
    classes: _Classification,
    gt_angles: Sequence[tuple[int, int, float]] | None,
    pred_normals,
    t: float,
) -> SegmentationScore:
    """The :class:`SegmentationScore` of a classified segmentation (f, k, rmse, alpha and the counts)."""
    gt_values, gt_counts = regions.gt_values, regions.gt_counts
    pred_values, pred_counts = regions.pred_values, regions.pred_counts
    n_gt, n_pred = len(gt_values), len(pred_values)
    gt_classes, pred_classes, consistent = _class_names(classes)
    correct = classes.correct

    n_correct = int(np.count_nonzero(correct))
    correct_pairs = np.stack([gt_values[table.pair_m[correct]], pred_values[table.pair_n[correct]]], axis=1).astype(
        np.int64
    )
    correct_points = float(np.sum(gt_counts * (classes.correct_per_m > 0)))
    labelled_points = float(np.sum(gt_counts))
    n_valid = gt.size if valid is None else int(np.count_nonzero(valid))

    rmse, rmse_sse, rmse_points, n_dropped = _pooled_rmse(regions.pred_flat, pred_values, residuals)
    angle_sum, angle_count = _angle_differences(correct_pairs, gt_angles, pred_normals)

    return SegmentationScore(
        f=n_correct / n_gt if n_gt else math.nan,
        k=correct_points / labelled_points if labelled_points else math.nan,
        k_all_rays=correct_points / n_valid if n_valid else math.nan,
        rmse=rmse,
        n_gt=n_gt,
        n_pred=n_pred,
        n_correct=n_correct,
        n_over=int(np.count_nonzero(classes.over)),
        n_under=int(np.count_nonzero(classes.under)),
        n_missed=int(np.count_nonzero(classes.missed)),
        n_noise=int(np.count_nonzero(classes.noise)),
        alpha=angle_sum / angle_count if angle_count else math.nan,
        angle_diff_sum=angle_sum,
        angle_count=angle_count,
        rmse_sse=rmse_sse,
        rmse_points=rmse_points,
        n_rmse_dropped=n_dropped,
        gt_labels=gt_values.astype(np.int64),
        gt_sizes=gt_counts.astype(np.int64),
        gt_classes=gt_classes,
        pred_labels=pred_values.astype(np.int64),
        pred_sizes=pred_counts.astype(np.int64),
        pred_classes=pred_classes,
        correct_pairs=correct_pairs.reshape(-1, 2),
        consistent=consistent,
        threshold=t,
    )


def score_segmentation(
    pred_labels: np.ndarray,
    gt_labels: np.ndarray,
    *,
    gt_min_label: int = 10,
    residuals: np.ndarray | None = None,
    valid: np.ndarray | None = None,
    threshold: float = DEFAULT_THRESHOLD,
    gt_angles: Sequence[tuple[int, int, float]] | None = None,
    pred_normals: np.ndarray | Mapping[int, np.ndarray] | None = None,
    min_pred_points: int = 2,
) -> SegmentationScore:
    """Score an extracted segmentation against ground truth with the reference evaluation.

    Args:
        pred_labels: ``(H, W)`` integer labels of extracted planes; 0 = no plane.
        gt_labels: ``(H, W)`` integer ground truth; labels >= ``gt_min_label`` are GT regions.
        gt_min_label: smallest GT region label (10 for SynPEB and SegComp).
        residuals: ``(H, W)`` radial residuals (measured minus predicted range along each ray,
            metres) of each point w.r.t. its own extracted plane; values outside planes are
            ignored. A plane whose residuals include NaN has a NaN RMSE and is left out (as in
            the reference, where ``NaN < 10`` is false). None: rmse is NaN.
        valid: ``(H, W)`` bool mask of valid rays (the denominator of ``k_all_rays``); None = all
            pixels.
        threshold: Hoover tolerance T (strict ``>``).
        gt_angles: ``(label1, label2, angle_deg)`` GT angles between plane pairs (SegComp's
            ``.gt-ang``); None or empty: alpha is NaN.
        pred_normals: normals of the extracted planes, needed with ``gt_angles``: an ``(J, 3)``
            array whose row j belongs to label j + 1 (``PlaneSet.normals``), or a mapping
            label -> normal.
        min_pred_points: extracted regions with fewer pixels are removed before scoring (the
            reference drops atomic 1-point planes, ``rmatompln``); 1 keeps everything.

    Returns:
        The scores; see :class:`SegmentationScore`.

    Raises:
        ValueError: mismatched shapes, negative predicted labels, bad threshold, or gt_angles
            without pred_normals.
    """
    pred, gt, residuals, valid = _check_score_inputs(
        pred_labels, gt_labels, residuals, valid, threshold, gt_angles, pred_normals, min_pred_points
    )
    gt_flat = gt.ravel()
    regions = _find_regions(pred.ravel(), gt_flat, gt_min_label, min_pred_points)
    table = _overlap_table(gt_flat, gt_min_label, regions)
    t = float(threshold)
    classes = _classify(table, len(regions.gt_values), len(regions.pred_values), t)
    return _score_result(gt, valid, residuals, regions, table, classes, gt_angles, pred_normals, t)


def _pooled_rmse(
    pred_flat: np.ndarray, pred_values: np.ndarray, residuals: np.ndarray | None
) -> tuple[float, float, int, int]:
    """(rmse, sse, points, planes dropped) pooled over planes whose own RMSE < 10 m."""
    if residuals is None or len(pred_values) == 0:
        return math.nan, 0.0, 0, 0
    in_plane = pred_flat > 0
    plane_index = np.searchsorted(pred_values, pred_flat[in_plane])
    values = residuals.ravel()[in_plane]
    squared = values * values
    n_planes = len(pred_values)
    bad = np.bincount(plane_index, weights=~np.isfinite(squared), minlength=n_planes) > 0
    sse = np.bincount(plane_index, weights=np.where(np.isfinite(squared), squared, 0.0), minlength=n_planes)
    counts = np.bincount(plane_index, minlength=n_planes)
    with np.errstate(invalid='ignore', divide='ignore'):
        plane_rmse = np.sqrt(sse / counts)
    plane_rmse[bad] = np.nan
    kept = plane_rmse < RMSE_PLANE_LIMIT
    total_sse = float(np.sum(sse[kept]))
    total_points = int(np.sum(counts[kept]))
    rmse = math.sqrt(total_sse / total_points) if total_points else math.nan
    return rmse, total_sse, total_points, int(n_planes - np.count_nonzero(kept))


def _fold_angle(angle_deg: float) -> float:
    return 180.0 - angle_deg if angle_deg > 90.0 else angle_deg


def _normal_of(pred_normals, label: int) -> np.ndarray:
    if isinstance(pred_normals, Mapping):
        if label not in pred_normals:
            raise ValueError(f'pred_normals has no normal for extracted plane {label}')
        normal = np.asarray(pred_normals[label], dtype=np.float64)
    else:
        array = np.asarray(pred_normals, dtype=np.float64)
        if array.ndim != 2 or array.shape[1] != 3:
            raise ValueError(f'pred_normals must be (J, 3) (row j = label j + 1) or a mapping; got {array.shape}')
        if not 1 <= label <= len(array):
            raise ValueError(f'pred_normals has {len(array)} rows; no row for extracted plane {label}')
        normal = array[label - 1]
    if normal.shape != (3,) or not np.all(np.isfinite(normal)) or not np.any(normal):
        raise ValueError(f'normal of extracted plane {label} must be a finite non-zero 3-vector; got {normal}')
    return normal


def _angle_differences(
    correct_pairs: np.ndarray,
    gt_angles: Sequence[tuple[int, int, float]] | None,
    pred_normals,
) -> tuple[float, int]:
    """Sum and count of |angle(extracted) - angle(GT)| over GT pairs with both planes correct."""
    if not gt_angles:
        return 0.0, 0
    match = {int(g): int(p) for g, p in correct_pairs}
    total, count = 0.0, 0
    for entry in gt_angles:
        if len(entry) != 3:
            raise ValueError(f'gt_angles entries must be (label1, label2, angle_deg); got {entry}')
        label1, label2, gt_angle = int(entry[0]), int(entry[1]), float(entry[2])
        if label1 not in match or label2 not in match:
            continue
        n1 = _normal_of(pred_normals, match[label1])
        n2 = _normal_of(pred_normals, match[label2])
        angle = math.degrees(math.atan2(float(np.linalg.norm(np.cross(n1, n2))), float(n1 @ n2)))
        total += abs(_fold_angle(angle) - _fold_angle(gt_angle))
        count += 1
    return total, count


def aggregate_scores(scores: Sequence[SegmentationScore], *, rmse_outlier_limit: float = 0.02) -> dict:
    """The paper's table row over many scans (as ``ploteval.m`` aggregates them).

    Returns a dict with:
        ``n_scans``; ``f`` = sum correct / sum GT regions; ``k`` and ``k_all_rays`` = means over
        scans; ``n_o``, ``n_u``, ``n_m``, ``n_s`` = mean over-, under-segmented, missed and noise
        (spurious) counts per scan; ``n_gt``, ``n_pred`` = mean counts per scan; ``rmse`` = mean of
        the per-scan RMSEs (finite ones); ``rmse_filtered`` = the same without scans above
        ``rmse_outlier_limit`` metres (the reference plot drops those); ``rmse_pooled`` = RMSE
        pooled over all points of all scans; ``alpha`` = sum angle differences / sum angle
        counts. Undefined values are NaN.
    """
    scores = list(scores)
    if not scores:
        raise ValueError('aggregate_scores needs at least one SegmentationScore')

    def mean(values) -> float:
        array = np.asarray(values, dtype=np.float64)
        array = array[np.isfinite(array)]
        return float(array.mean()) if array.size else math.nan

    total_gt = sum(s.n_gt for s in scores)
    rmses = [s.rmse for s in scores]
    total_points = sum(s.rmse_points for s in scores)
    total_angles = sum(s.angle_count for s in scores)
    return {
        'n_scans': len(scores),
        'f': sum(s.n_correct for s in scores) / total_gt if total_gt else math.nan,
        'k': mean([s.k for s in scores]),
        'k_all_rays': mean([s.k_all_rays for s in scores]),
        'n_o': mean([s.n_over for s in scores]),
        'n_u': mean([s.n_under for s in scores]),
        'n_m': mean([s.n_missed for s in scores]),
        'n_s': mean([s.n_noise for s in scores]),
        'n_gt': mean([s.n_gt for s in scores]),
        'n_pred': mean([s.n_pred for s in scores]),
        'rmse': mean(rmses),
        'rmse_filtered': mean([r for r in rmses if r <= rmse_outlier_limit]),
        'rmse_pooled': math.sqrt(sum(s.rmse_sse for s in scores) / total_points) if total_points else math.nan,
        'alpha': sum(s.angle_diff_sum for s in scores) / total_angles if total_angles else math.nan,
    }
