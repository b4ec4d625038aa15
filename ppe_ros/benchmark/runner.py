"""Run plane-extraction methods over labelled scans and score them with the paper's evaluation.

Per scan and method: segment (timed), fit every predicted segment exactly under the radial noise
model for the RMSE (unless the method already did), and score with
:func:`ppe_ros.core.evaluation.score_segmentation` (Hoover T = 0.8, GT labels >= ``gt_min_label``).
Per noise level and method the scans are aggregated as the paper's table
(:func:`ppe_ros.core.evaluation.aggregate_scores`). For PPE the f of every e of the sweep is kept
for the f-over-sqrt(e) curve.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from ppe_ros.benchmark.dataset import iter_scans
from ppe_ros.benchmark.methods import MethodUnavailable, PlaneMethod, Segmentation
from ppe_ros.core.evaluation import DEFAULT_THRESHOLD, SegmentationScore, aggregate_scores, score_segmentation


@dataclass(frozen=True)
class LabelledScan:
    """A scan with ground truth, ready for scoring.

    Attributes:
        name: how the scan is shown (``test/sigma_20mm/pc_01`` or a file name).
        points: ``(H, W, 3)`` metres, NaN = no return. origins: ray starts (None, ``(3,)`` or ``(H, W, 3)``).
        labels: ``(H, W)`` ground truth. gt_min_label: the smallest label that is a GT plane.
        group: the table the scan belongs to (a noise level name, or the scan's own name).
        radial_sigma: the scan's radial noise (m) if known.
    """

    name: str
    points: np.ndarray
    origins: np.ndarray | None
    labels: np.ndarray
    gt_min_label: int
    group: str
    radial_sigma: float | None = None


def load_labelled_scan(
    path: str | os.PathLike[str],
    *,
    group: str | None = None,
    radial_sigma: float | None = None,
    name: str | None = None,
    gt: str | os.PathLike[str] | None = None,
) -> LabelledScan:
    """Read a scan file that carries ground truth (SynPEB PCD, depth PNG with ``*_labels.npy``, ...).

    Raises:
        ValueError: the file has no ground-truth labels.
    """
    from ppe_ros.io import load_scan

    scan = load_scan(path, gt=gt)
    if scan.labels is None:
        raise ValueError(
            f'{path}: the scan carries no ground-truth labels (SynPEB PCD intensity, a label field, '
            f'a <name>_labels.npy next to it, or --gt)'
        )
    label = name or Path(path).name
    return LabelledScan(
        name=label,
        points=scan.points,
        origins=scan.origins,
        labels=scan.labels,
        gt_min_label=int(scan.meta.get('min_plane_label', 10)),
        group=group or label,
        radial_sigma=radial_sigma,
    )


def dataset_scans(
    directory: str | os.PathLike[str],
    *,
    split: str = 'test',
    noise_mm: Sequence[float] | None = None,
    max_scans: int | None = None,
) -> list[tuple[str, Callable[[], LabelledScan]]]:
    """Lazy loaders ``(name, load)`` of a data set's scans (one level after the other)."""
    loaders = []
    for entry in iter_scans(directory, split=split, noise_mm=noise_mm, max_scans=max_scans):

        def load(entry=entry) -> LabelledScan:
            return load_labelled_scan(entry.path, group=entry.level, radial_sigma=entry.radial_sigma, name=entry.name)

        loaders.append((entry.name, load))
    return loaders


@dataclass
class ScanResult:
    """One method on one scan."""

    scan: str
    group: str
    method: str
    score: SegmentationScore
    seconds: float
    radial_sigma: float | None = None
    sweep_correct: dict[float, int] | None = None  # e -> correct GT regions (PPE only)
    info: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-ready summary (scalars of the score, no per-region arrays)."""
        score = {k: v for k, v in self.score.to_dict().items() if not isinstance(v, list)}
        out = {
            'scan': self.scan,
            'group': self.group,
            'method': self.method,
            'seconds': self.seconds,
            'radial_sigma': self.radial_sigma,
            'score': score,
            'info': self.info,
        }
        if self.sweep_correct is not None:
            out['sweep_correct'] = {f'{e:.6g}': c for e, c in self.sweep_correct.items()}
        return out


def score_prediction(
    points: np.ndarray,
    origins: np.ndarray | None,
    gt_labels: np.ndarray,
    pred_labels: np.ndarray,
    *,
    gt_min_label: int = 10,
    residuals: np.ndarray | None = None,
    threshold: float = DEFAULT_THRESHOLD,
) -> SegmentationScore:
    """Score predicted labels against ground truth, with the RMSE of the exact radial fit of each segment.

    ``residuals`` (the radial residual image of the predicted planes) is computed with
    :func:`ppe_ros.core.fitting.fit_labeled_planes` when not given; segments of fewer than 3 points
    have no fit and are left out of the RMSE.
    """
    from ppe_ros.core.fitting import fit_labeled_planes

    pred = np.asarray(pred_labels)
    if residuals is None:
        residuals = fit_labeled_planes(points, pred, origins=origins, min_plane_points=3).residuals
    valid = np.isfinite(np.asarray(points, dtype=np.float64)).all(axis=2)
    return score_segmentation(
        pred, gt_labels, gt_min_label=gt_min_label, residuals=residuals, valid=valid, threshold=threshold
    )


def run_method_on_scan(method: PlaneMethod, scan: LabelledScan) -> ScanResult:
    """Segment one scan with one method (its parameters for the scan's noise level) and score it (and its sweep)."""
    segmentation: Segmentation = method.for_noise(scan.radial_sigma).segment(scan.points, scan.origins)
    score = score_prediction(
        scan.points,
        scan.origins,
        scan.labels,
        segmentation.labels,
        gt_min_label=scan.gt_min_label,
        residuals=segmentation.residuals,
    )
    sweep_correct = None
    if segmentation.sweep is not None:
        cache: dict[int, int] = {}
        sweep_correct = {}
        for e, labels in segmentation.sweep.items():
            key = id(labels)
            if key not in cache:
                cache[key] = score_segmentation(labels, scan.labels, gt_min_label=scan.gt_min_label).n_correct
            sweep_correct[e] = cache[key]
    return ScanResult(
        scan=scan.name,
        group=scan.group,
        method=method.name,
        score=score,
        seconds=segmentation.seconds,
        radial_sigma=scan.radial_sigma,
        sweep_correct=sweep_correct,
        info=dict(segmentation.info),
    )


@dataclass
class Evaluation:
    """Results of an evaluation run: per scan, aggregated per (group, method), skipped methods."""

    results: list[ScanResult]
    skipped: dict[str, str]
    methods: list[PlaneMethod]

    def groups(self) -> list[str]:
        """Group names in the order they were run."""
        seen: list[str] = []
        for result in self.results:
            if result.group not in seen:
                seen.append(result.group)
        return seen

    def rows(self, group: str) -> list[dict]:
        """The paper's table rows of one group: one per method (aggregate_scores + seconds per scan)."""
        rows = []
        for method in self.methods:
            mine = [r for r in self.results if r.group == group and r.method == method.name]
            if not mine:
                continue
            row = aggregate_scores([r.score for r in mine])
            row['method'] = method.name
            row['seconds'] = float(np.mean([r.seconds for r in mine]))
            sigmas = {r.radial_sigma for r in mine}
            row['radial_sigma'] = sigmas.pop() if len(sigmas) == 1 else None
            rows.append(row)
        return rows

    def sweep_curve(self, group: str, method: str = 'ppe') -> dict[float, float] | None:
        """e -> f (sum correct / sum GT regions) over the group's scans, for a method with a sweep."""
        mine = [r for r in self.results if r.group == group and r.method == method and r.sweep_correct]
        if not mine:
            return None
        total_gt = sum(r.score.n_gt for r in mine)
        errors = sorted(mine[0].sweep_correct)
        return {e: (sum(r.sweep_correct[e] for r in mine) / total_gt if total_gt else math.nan) for e in errors}

    def to_dict(self) -> dict:
        """JSON-ready: per-scan results, table rows per group, sweeps, skipped methods."""
        return {
            'methods': {m.name: m.parameters() for m in self.methods},
            'skipped': self.skipped,
            'groups': {
                g: {'rows': self.rows(g), 'sweep': {f'{e:.6g}': f for e, f in (self.sweep_curve(g) or {}).items()}}
                for g in self.groups()
            },
            'scans': [r.to_dict() for r in self.results],
        }


def _score_from_dict(data: dict) -> SegmentationScore:
    """A SegmentationScore from the scalars of ``to_dict`` (per-region arrays are left empty)."""
    values = {}
    for item in fields(SegmentationScore):
        value = data.get(item.name)
        if item.name in ('gt_labels', 'gt_sizes', 'pred_labels', 'pred_sizes'):
            value = np.zeros(0, np.int64)
        elif item.name == 'correct_pairs':
            value = np.zeros((0, 2), np.int64)
        elif item.name in ('gt_classes', 'pred_classes'):
            value = ()
        elif value is None:
            value = math.nan
        values[item.name] = value
    return SegmentationScore(**values)


def load_previous_results(path: str | os.PathLike[str]) -> dict[tuple[str, str, str], ScanResult]:
    """Per-scan results of an earlier run (``ppe eval --raw``), keyed by (method, its parameters, scan).

    Raises:
        ValueError: not a raw results file of ``ppe eval``.
    """
    try:
        data = json.loads(Path(path).read_text())
        params = data['methods']
        entries = data['scans']
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f'{path}: not a raw results file of `ppe eval --raw`: {exc}') from None
    out = {}
    for entry in entries:
        method = entry['method']
        if method not in params:
            continue
        sweep = entry.get('sweep_correct')
        result = ScanResult(
            scan=entry['scan'],
            group=entry['group'],
            method=method,
            score=_score_from_dict(entry['score']),
            seconds=float(entry['seconds']),
            radial_sigma=entry.get('radial_sigma'),
            sweep_correct=None if sweep is None else {float(e): int(c) for e, c in sweep.items()},
            info=entry.get('info', {}),
        )
        out[(method, _params_key(params[method]), entry['scan'])] = result
    return out


def _params_key(params: dict) -> str:
    return json.dumps(params, sort_keys=True, default=float)


def available_methods(methods: Iterable[PlaneMethod]) -> tuple[list[PlaneMethod], dict[str, str]]:
    """Split methods into those that can run here and ``{name: reason}`` for the others."""
    usable, skipped = [], {}
    for method in methods:
        try:
            method.check_available()
        except MethodUnavailable as exc:
            skipped[method.name] = str(exc)
            continue
        usable.append(method)
    return usable, skipped


def evaluate(
    scans: Sequence[tuple[str, Callable[[], LabelledScan]]],
    methods: Sequence[PlaneMethod],
    *,
    progress: Callable[[str], None] | None = None,
    warm_up: bool = True,
    previous: dict[tuple[str, str, str], ScanResult] | None = None,
    checkpoint: Callable[[Evaluation], None] | None = None,
) -> Evaluation:
    """Run every available method on every scan and score it.

    Args:
        scans: ``(name, loader)`` pairs; each loader returns a :class:`LabelledScan`.
        methods: the methods; unavailable ones are skipped and reported in ``Evaluation.skipped``.
        progress: called with a short description after each (scan, method) step.
        warm_up: run each method once on a tiny scan first so that JIT compilation is not timed.
        previous: results of an earlier run (:func:`load_previous_results`); a (method with the same
            parameters, scan) found there is taken from it instead of being run again (a method with a
            sweep only if the earlier result has one).
        checkpoint: called with the results so far after each scan (e.g. to save them for a resume).
    """
    usable, skipped = available_methods(methods)
    previous = previous or {}
    keys = {method.name: _params_key(method.parameters()) for method in usable}

    def reused(method: PlaneMethod, name: str) -> ScanResult | None:
        result = previous.get((method.name, keys[method.name], name))
        if result is None or (getattr(method, 'sweep_errors', None) is not None and result.sweep_correct is None):
            return None
        return result

    if warm_up:
        for method in usable:
            if any(reused(method, name) is None for name, _ in scans):
                method.warm_up()
    results = []
    for name, load in scans:
        scan = None
        for method in usable:
            result = reused(method, name)
            if result is None:
                scan = load() if scan is None else scan
                result = run_method_on_scan(method, scan)
            results.append(result)
            if progress is not None:
                progress(f'{name} {method.name}')
        if checkpoint is not None:
            checkpoint(Evaluation(results=list(results), skipped=skipped, methods=usable))
    return Evaluation(results=results, skipped=skipped, methods=usable)
