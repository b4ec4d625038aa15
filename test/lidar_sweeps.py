"""Synthetic spinning-lidar sweeps for the tests of unorganized clouds (issue 20)."""

from __future__ import annotations

import math

import numpy as np

#: HDL-64E-like beam elevations (deg): 1/3 deg apart above -8.33, 1/2 deg below (uneven on purpose).
HDL_LIKE_ELEVATIONS = np.r_[2.0 - np.arange(32) / 3.0, -8.83 - 0.5 * np.arange(32)]


def room_sweep(
    elevations_deg: np.ndarray,
    columns: int,
    *,
    sigma: float = 0.003,
    seed: int = 0,
    beam_origin: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """An organized 360 deg sweep ``(rows, columns, 3)`` of a box room (walls, floor, ceiling) seen from
    inside; rows are beams from the top, columns run clockwise from the back (as Ouster's image). Each
    beam starts ``beam_origin = (h, n)`` above and out from the sensor origin."""
    h, n = beam_origin
    elevation = np.radians(np.asarray(elevations_deg, dtype=np.float64))[:, None]
    azimuth = math.pi - (np.arange(columns) + 0.5) * 2 * math.pi / columns  # clockwise, starting behind
    direction = np.stack(
        np.broadcast_arrays(
            np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)
        ),
        axis=-1,
    )
    start = np.stack(np.broadcast_arrays(n * np.cos(azimuth), n * np.sin(azimuth), h + 0 * elevation), axis=-1)
    low, high = np.array([-6.0, -5.0, -1.7]), np.array([8.0, 4.0, 2.5])
    with np.errstate(divide='ignore', invalid='ignore'):
        t = np.where(direction > 0, (high - start) / direction, (low - start) / direction)
    t = np.where(t > 0, t, np.inf).min(axis=-1)
    t = t + np.random.default_rng(seed).normal(0.0, sigma, t.shape)
    return start + t[..., None] * direction


def shuffled(points: np.ndarray, seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The valid points of an organized sweep in random order, their rings (rows) and their flat indices."""
    width = points.shape[1]
    flat = points.reshape(-1, 3)
    index = np.flatnonzero(np.isfinite(flat).all(axis=1))
    np.random.default_rng(seed).shuffle(index)
    return flat[index], index // width, index
