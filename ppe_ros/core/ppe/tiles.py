"""The tiled greedy: vertical strips of the grid (azimuth sectors of a sweep) run independently and in parallel."""

from __future__ import annotations

import itertools

import numba as nb
import numpy as np

from ppe_ros.core.ppe.greedy import _greedy
from ppe_ros.core.ppe.layout import _ST_HEAP_PEAK, KIND_CREATE
from ppe_ros.core.ppe.memory import _reusable
from ppe_ros.core.thread_pool import SharedThreadPool, run_tasks

#: Columns per tile of tiles='auto' on a sweep (a grid at least 4 times as wide as high: 45 deg sectors
#: of a 1024-column spinning lidar); images get twice as wide strips (measured: 128-column strips of
#: ICL-NUIM's 640 x 480 frames lost 6-8 points of k in the depth-camera profile's consolidation,
#: 320-column ones none).
AUTO_TILE_COLUMNS = 128


def _tile_bounds(width: int, tiles: int | str, height: int = 1) -> list[int]:
    """Column bounds [0, c1, ..., width] of ``tiles`` vertical strips of near-equal width.

    'auto': one strip per AUTO_TILE_COLUMNS columns on a grid at least 4 times as wide as high, per
    2 AUTO_TILE_COLUMNS otherwise (at least 1). Strips are at least 8 columns wide.
    """
    if isinstance(tiles, str):
        if tiles != 'auto':
            raise ValueError(f"tiles must be a count >= 1 or 'auto'; got {tiles!r}")
        columns = AUTO_TILE_COLUMNS if width >= 4 * height else 2 * AUTO_TILE_COLUMNS
        count = max(1, round(width / columns))
    else:
        if isinstance(tiles, bool) or int(tiles) != tiles or int(tiles) < 1:
            raise ValueError(f"tiles must be a count >= 1 or 'auto'; got {tiles!r}")
        count = int(tiles)
    count = max(1, min(count, width // 8))
    return [round(i * width / count) for i in range(count + 1)]


#: A tile border may move by this fraction of the strip width to where the fewest grid edges cross it.
TILE_BORDER_SLACK = 0.25


def _placed_borders(bounds: list[int], ok_right: np.ndarray, height: int, width: int) -> list[int]:
    """The inner borders moved (each within TILE_BORDER_SLACK of a strip's width) to the column between c - 1
    and c that the fewest admissible grid edges cross (ties: the nearest to the nominal border, then the
    left one): a border there cuts fewest surfaces (it falls on depth jumps, no-returns, edges of objects).
    """
    if len(bounds) <= 2:
        return bounds
    crossing = ok_right.reshape(height, width).sum(axis=0)  # crossing[c - 1]: edges between columns c - 1, c
    slack = int(TILE_BORDER_SLACK * width / (len(bounds) - 1))
    placed = [0]
    for nominal in bounds[1:-1]:
        candidates = np.arange(max(nominal - slack, placed[-1] + 8), min(nominal + slack, width - 8) + 1)
        if len(candidates) == 0:
            placed.append(nominal)
            continue
        order = np.lexsort((candidates, np.abs(candidates - nominal), crossing[candidates - 1]))
        placed.append(int(candidates[order[0]]))
    return [*placed, width]


#: Its threads keep their work memory (ppe.memory) from tile to tile and call to call.
_tile_pool = SharedThreadPool('ppe-tile')


def _tile_inputs(inputs: tuple, height: int, width: int, c0: int, c1: int) -> tuple:
    """The inputs of _greedy for columns c0:c1, copied (row-major, tile-local pixel ids) into work memory."""
    out = []
    for index, array in enumerate(inputs):
        trailing = array.shape[1:]
        tile = array.reshape((height, width, *trailing))[:, c0:c1]
        buffer = _reusable(f'tile{index}_{array.dtype.str}', tile.size, array.dtype).reshape(tile.shape)
        np.copyto(buffer, tile)
        out.append(buffer.reshape((-1, *trailing)))
    return tuple(out)


def _largest_first(seed_key: np.ndarray, height: int, width: int, bounds: list[int]) -> list[int]:
    """Strip indices by decreasing number of seeds the greedy may create (finite keys); ties by index."""
    finite = np.isfinite(seed_key.reshape(height, width))
    seeds = [int(np.count_nonzero(finite[:, bounds[t] : bounds[t + 1]])) for t in range(len(bounds) - 1)]
    return sorted(range(len(seeds)), key=lambda t: (-seeds[t], t))


def _tiled_greedy(
    inputs: tuple,
    height: int,
    width: int,
    bounds: list[int],
    options,
    stop_increment: float,
    stop_count: int,
    threads: int | None,
) -> tuple:
    """The greedy on each column strip separately (up to ``threads`` at once): the strips' action logs
    one after another in strip order (kinds, a, b, increments), the start of each strip's run in them
    (``(T + 1,)``) and the summed stats.

    The strips' grid edges across a border were cut before the seeds, so each strip is an independent
    problem; its log is translated to the whole grid's pixel ids (a tile's row-major order is the
    grid's, so "a merge keeps the smaller id" still holds). :func:`joint_order` interleaves the runs
    into one log whose cut at every e is the union of every strip's own cut at e. The result does
    not depend on threads.
    """
    n_tiles = len(bounds) - 1

    def run(t: int) -> tuple:
        c0, c1 = bounds[t], bounds[t + 1]
        local = _tile_inputs(inputs, height, width, c0, c1)
        kinds, a_ids, b_ids, incs, stats = _greedy(local, height, c1 - c0, options, stop_increment, stop_count)
        tile_width = c1 - c0
        a_ids = (a_ids // tile_width) * width + c0 + a_ids % tile_width
        b_global = (b_ids // tile_width) * width + c0 + b_ids % tile_width
        b_ids = np.where(kinds == KIND_CREATE, b_ids, b_global)
        return kinds, a_ids, b_ids, incs, stats

    threads = min(nb.get_num_threads() if threads is None else int(threads), n_tiles)
    # the strips with the most valid seeds first (about the most work), so that no large strip is
    # left for one thread at the end
    strip_order = _largest_first(inputs[7], height, width, bounds) if threads > 1 else range(n_tiles)
    results = run_tasks(run, strip_order, threads, _tile_pool)
    run_starts = np.cumsum([0] + [len(r[3]) for r in results])
    stats = np.sum([r[4] for r in results], axis=0)
    stats[_ST_HEAP_PEAK] = max(int(r[4][_ST_HEAP_PEAK]) for r in results)
    log = tuple(np.concatenate([r[column] for r in results]) for column in range(4))
    return log, run_starts, stats


def joint_order(increments: np.ndarray, run_starts: np.ndarray) -> np.ndarray:
    """The order of the actions of the runs (strip logs one after another) in the joint log: by each
    strip's running maximum increment, stable (strip order breaks ties), so that for every e the joint
    log's cut at e is the union of every strip's own cut at e."""
    running_max = np.concatenate([np.maximum.accumulate(increments[a:b]) for a, b in itertools.pairwise(run_starts)])
    return _merged_runs_order(running_max, np.asarray(run_starts, np.int64))


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _merged_runs_order(keys, run_starts):
    """``np.argsort(keys, kind='stable')`` of keys made of ascending runs ``keys[run_starts[i]:run_starts[i + 1]]``
    (NaN-free): a merge of the runs, ties taken from the earlier run first (O(n * runs))."""
    n_runs = len(run_starts) - 1
    head = run_starts[:-1].copy()
    order = np.empty(len(keys), np.int64)
    for out in range(len(keys)):
        best = -1
        for run in range(n_runs):
            if head[run] < run_starts[run + 1] and (best < 0 or keys[head[run]] < keys[head[best]]):
                best = run
        order[out] = head[best]
        head[best] += 1
    return order
