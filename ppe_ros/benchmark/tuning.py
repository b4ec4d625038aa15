"""Grid search of PPE's lmax x e on a train split (as the reference's ``trainppe.m``), and the params YAML.

Score of a grid point: the mean over scans of ``n_correct / n_gt`` (T = 0.8). One PPE run per
(scan, lmax) up to the largest e gives every e of the grid from the action log. The best point is
the highest score; ties go to the smaller lmax, then the smaller e.

The YAML written is a ROS 2 parameters file of the extractor node (``extractor: ros__parameters:``)
that ``ppe eval --params`` reads too.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ppe_ros.benchmark.methods import ERROR_GRID, hierarchy_labels
from ppe_ros.benchmark.runner import LabelledScan
from ppe_ros.core.evaluation import score_segmentation

FULL_LMAX_GRID = tuple(round(0.02 * i, 2) for i in range(1, 11))
"""The reference's lmax grid for SynPEB (m): 0.02:0.02:0.2."""

COARSE_LMAX_GRID = (0.06, 0.12, 0.18)
"""Every third value of the full grid: the cheap default of ``ppe tune``."""

NODE_NAME = 'extractor'


@dataclass(frozen=True)
class TuningResult:
    """Scores of the grid: ``scores[i, j]`` = mean f over the scans at ``lmax_grid[i]``, ``error_grid[j]``."""

    lmax_grid: tuple[float, ...]
    error_grid: tuple[float, ...]
    scores: np.ndarray
    n_scans: int
    seconds: float

    @property
    def best_index(self) -> tuple[int, int]:
        """``(i, j)`` of the best score (first in lmax-major order on ties)."""
        flat = int(np.nanargmax(self.scores))
        return flat // self.scores.shape[1], flat % self.scores.shape[1]

    @property
    def best_lmax(self) -> float:
        return self.lmax_grid[self.best_index[0]]

    @property
    def best_error(self) -> float:
        return self.error_grid[self.best_index[1]]

    @property
    def best_score(self) -> float:
        i, j = self.best_index
        return float(self.scores[i, j])


def tune_ppe(
    scans: Sequence[Callable[[], LabelledScan]],
    *,
    lmax_grid: Sequence[float] = COARSE_LMAX_GRID,
    error_grid: Sequence[float] = ERROR_GRID,
    progress: Callable[[str], None] | None = None,
) -> TuningResult:
    """Grid search of (lmax, e) maximising the mean f over ``scans`` (loaders of labelled scans).

    Raises:
        ValueError: an empty grid or no scans.
    """
    import time

    from ppe_ros.core.extraction import extract_plane_hierarchy

    lmaxes = tuple(float(v) for v in lmax_grid)
    errors = tuple(sorted(float(v) for v in error_grid))
    if not lmaxes or any(not v > 0 for v in lmaxes):
        raise ValueError(f'lmax grid must be non-empty and positive (m); got {lmax_grid}')
    if not errors or any(not (math.isfinite(v) and v >= 0) for v in errors):
        raise ValueError(f'e grid must be non-empty, finite and >= 0 (m^2); got {error_grid}')
    if not scans:
        raise ValueError('tuning needs at least one scan')
    start = time.perf_counter()
    totals = np.zeros((len(lmaxes), len(errors)))
    for load in scans:
        scan = load()
        for i, lmax in enumerate(lmaxes):
            hierarchy = extract_plane_hierarchy(
                scan.points, origins=scan.origins, max_neighbor_distance=lmax, max_error_increment=errors[-1]
            )
            cache: dict[int, float] = {}
            for j, e in enumerate(errors):
                steps = hierarchy.steps_for_error(e)
                if steps not in cache:
                    score = score_segmentation(
                        hierarchy_labels(hierarchy, e), scan.labels, gt_min_label=scan.gt_min_label
                    )
                    cache[steps] = score.n_correct / score.n_gt if score.n_gt else math.nan
                totals[i, j] += cache[steps]
            if progress is not None:
                progress(f'{scan.name} lmax {lmax:g}')
    return TuningResult(
        lmax_grid=lmaxes,
        error_grid=errors,
        scores=totals / len(scans),
        n_scans=len(scans),
        seconds=time.perf_counter() - start,
    )


def params_yaml(max_neighbor_distance: float, max_error_increment: float, *, comments: Sequence[str] = ()) -> str:
    """A ROS 2 parameters file of the extractor node with the two PPE parameters."""
    head = ''.join(f'# {line}\n' for line in comments)
    return (
        f'{head}{NODE_NAME}:\n  ros__parameters:\n'
        f'    max_error_increment: {float(max_error_increment)!r}\n'
        f'    max_neighbor_distance: {float(max_neighbor_distance)!r}\n'
    )


def write_params_yaml(
    path: str | os.PathLike[str],
    max_neighbor_distance: float,
    max_error_increment: float,
    *,
    comments: Sequence[str] = (),
    overwrite: bool = False,
) -> Path:
    """Write :func:`params_yaml`; an existing file is refused unless ``overwrite``."""
    out = Path(path)
    text = params_yaml(max_neighbor_distance, max_error_increment, comments=comments)
    try:
        with open(out, 'w' if overwrite else 'x') as stream:
            stream.write(text)
    except FileExistsError:
        raise FileExistsError(f'{out} exists; refusing to overwrite it (use --force)') from None
    return out


def _profile_value(params: dict, name: str, path) -> float:
    """A node parameter given as 0: the value of the file's sensor profile (``sensor``, default none)."""
    from ppe_ros.core.sensor import sensor_profile

    try:
        return float(getattr(sensor_profile(str(params.get('sensor', 'none'))), name))
    except ValueError as exc:
        raise ValueError(f'{path}: {exc}') from None


def read_params_yaml(path: str | os.PathLike[str]) -> dict[str, float]:
    """``{'max_neighbor_distance': ..., 'max_error_increment': ...}`` (those present) from a params file.

    Accepts the node's format (``extractor: ros__parameters: ...``, also under ``/**``) or a flat mapping.
    A value of 0 is the file's sensor profile's (the node's convention).

    Raises:
        ValueError: not a mapping, or no PPE parameter in it, or a value that is not a number.
    """
    import yaml

    text = Path(path).read_text()
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f'{path}: not valid YAML: {exc}') from None
    if not isinstance(data, dict):
        raise ValueError(f'{path}: expected a mapping of parameters')
    params = data
    for key in (NODE_NAME, f'/{NODE_NAME}', '/**'):
        if isinstance(data.get(key), dict) and isinstance(data[key].get('ros__parameters'), dict):
            params = data[key]['ros__parameters']
            break
    out = {}
    for name in ('max_neighbor_distance', 'max_error_increment'):
        if name in params:
            value = params[name]
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f'{path}: {name} must be a number; got {value!r}')
            out[name] = float(value) if value else _profile_value(params, name, path)
    if not out:
        raise ValueError(f'{path}: no max_neighbor_distance or max_error_increment found')
    return out
