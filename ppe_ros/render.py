"""Pictures of segmentations (PNG via Pillow): distinct colours per plane, no plane black.

Pure numpy + Pillow; no ROS import. Colours come from :func:`ppe_ros.core.colors.label_colors`,
the same stable colour per label that the node publishes for RViz.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ppe_ros.core.colors import label_colors
from ppe_ros.io.files import write_file_atomically


def label_image(labels: np.ndarray, *, background: tuple[int, int, int] = (0, 0, 0)) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB picture of an ``(H, W)`` label image; labels <= 0 get ``background``."""
    lab = np.asarray(labels)
    if lab.ndim != 2:
        raise ValueError(f'labels must be a 2-D (H, W) array; got shape {lab.shape}')
    packed = label_colors(lab.astype(np.int64))
    rgb = np.stack([(packed >> 16) & 0xFF, (packed >> 8) & 0xFF, packed & 0xFF], axis=-1).astype(np.uint8)
    rgb[lab <= 0] = background
    return rgb


def save_segmentation_png(
    path: str | os.PathLike[str],
    labels: np.ndarray,
    *,
    ground_truth: np.ndarray | None = None,
    gt_min_label: int = 1,
    overwrite: bool = True,
    scale: int | None = None,
) -> Path:
    """Write the segmentation (and the ground truth to its left, as in the paper's Figure 1).

    Args:
        path: output PNG.
        labels: ``(H, W)`` predicted plane labels (0 = no plane, drawn black).
        ground_truth: optional ``(H, W)`` ground-truth labels; labels below ``gt_min_label`` are black.
        scale: integer upscaling of small grids (default: so that the picture is at least 400 px high).
        overwrite: replace an existing file (else FileExistsError). Written to a temporary file in the same
            folder and renamed into place: never left truncated.
    """
    out = Path(path)
    writer = segmentation_png_writer(labels, ground_truth=ground_truth, gt_min_label=gt_min_label, scale=scale)
    return write_file_atomically(out, writer, overwrite=overwrite)


def segmentation_png_writer(
    labels: np.ndarray, *, ground_truth: np.ndarray | None = None, gt_min_label: int = 1, scale: int | None = None
):
    """A writer (for :func:`ppe_ros.io.files.write_files_atomically`) of :func:`save_segmentation_png`'s PNG."""
    from PIL import Image

    panels = []
    if ground_truth is not None:
        gt = np.asarray(ground_truth).astype(np.int64)
        if gt.shape != np.shape(labels):
            raise ValueError(f'ground truth shape {gt.shape} differs from the labels {np.shape(labels)}')
        panels.append(label_image(np.where(gt >= gt_min_label, gt, 0)))
    panels.append(label_image(labels))
    if len(panels) == 2:
        gap = np.full((panels[0].shape[0], 8, 3), 255, np.uint8)
        picture = np.concatenate([panels[0], gap, panels[1]], axis=1)
    else:
        picture = panels[0]
    if scale is None:
        scale = max(1, int(np.ceil(400 / max(picture.shape[0], 1))))
    if scale > 1:
        picture = np.repeat(np.repeat(picture, scale, axis=0), scale, axis=1)
    image = Image.fromarray(picture)
    return lambda stream: image.save(stream, format='PNG')
