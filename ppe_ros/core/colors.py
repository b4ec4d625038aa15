"""Label colours shared by the pictures (ppe_ros.render) and the ROS outputs (labelled cloud, markers).

Pure numpy; no ROS import.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: Colour of label ids <= 0 (unassigned / unlabelled) in :func:`label_colors`: mid grey.
UNLABELLED_COLOR = 0x808080


def _hsv_colors(ids: np.ndarray) -> np.ndarray:
    """Packed colours of int64 ids (no special case for ids <= 0)."""
    k = np.maximum(ids, 1)
    hue = np.mod(k * 0.6180339887498949, 1.0) * 6.0
    saturation = np.array([0.95, 0.7, 0.5])[k % 3]
    value = np.array([1.0, 0.8])[(k // 3) % 2]
    sector = np.floor(hue).astype(np.int64) % 6
    fraction = hue - np.floor(hue)
    p = value * (1.0 - saturation)
    q = value * (1.0 - saturation * fraction)
    t = value * (1.0 - saturation * (1.0 - fraction))
    red = np.choose(sector, [value, q, p, p, t, value])
    green = np.choose(sector, [t, value, value, q, p, p])
    blue = np.choose(sector, [p, p, t, value, value, q])
    channels = np.clip(np.rint(np.stack([red, green, blue], axis=-1) * 255.0), 0, 255).astype(np.uint32)
    return (channels[..., 0] << 16) | (channels[..., 1] << 8) | channels[..., 2]


def label_colors(labels: np.ndarray | Sequence[int]) -> np.ndarray:
    """A stable, distinct ``0x00RRGGBB`` colour (uint32) per integer label id; ids <= 0 are grey.

    Hues step by the golden angle (consecutive ids far apart on the colour wheel); saturation and
    value cycle with periods 3 and 2 so that ids with nearby hues still differ. The colour of an id
    never depends on which other ids are present. Returns an array of the shape of ``labels``.
    """
    ids = np.asarray(labels)
    if not (np.issubdtype(ids.dtype, np.integer) or ids.dtype == np.bool_):
        raise ValueError(f'labels must be integers; got dtype {ids.dtype}')
    ids = ids.astype(np.int64)
    if ids.size == 0:
        return np.zeros(ids.shape, dtype=np.uint32)
    low = max(int(ids.min()), 0)
    high = int(ids.max())
    if 0 <= high - low < 1 << 20 and high - low < 4 * ids.size:
        # few distinct ids (the usual case): colour a table once and index it
        table = _hsv_colors(np.arange(low, high + 1, dtype=np.int64))
        packed = table[np.clip(ids, low, high) - low]
    else:
        packed = _hsv_colors(ids)
    return np.where(ids <= 0, np.uint32(UNLABELLED_COLOR), packed).astype(np.uint32)
