"""A slow, obviously correct reference implementation of Probabilistic Plane Extraction (PPE).

It exists to test the fast numba extractor (``ppe_ros.core.extraction``): it implements the same
semantics (Schaefer et al., ICRA 2019, Algorithm 1, with this project's choices) in the most
direct way possible. Every step recomputes every candidate action from scratch, and every error
is an exact maximum-likelihood fit. The only shortcut is a cache of plane fits keyed by the set
of pixel ids, which cannot change a result because a fit depends only on its set of rays.

Semantics (frames and units: everything is in the frame of the input points, lengths in metres,
errors in m^2):

* **Rays.** Pixel ``(row, col)`` of an ``(H, W, 3)`` organized scan has linear id
  ``row * W + col``. It is valid iff its point and ray origin are finite and the range
  ``r = ||p - s||`` is positive; its unit direction is ``v = (p - s) / r``.
* **Error of a set of rays Q.** ``SSE(Q) = min over planes of sum_k (r_k - rhat_k)^2``, with
  ``rhat_k`` the signed distance along ray k from its origin to the plane.
* **Adjacency.** 4-neighbourhood; an edge between two 4-adjacent pixels is admissible iff both
  are valid and their points are at most ``max_neighbor_distance`` apart.
* **State.** Every valid pixel starts as an atomic plane. A regular plane created from a seed
  gets the linear id of the seed's anchor pixel; a merge keeps the smaller id.
* **Candidates.** create (anchor, config): a tetromino seed of 4 valid atomic pixels whose
  internal 4-adjacent pairs are admissible edges, increment ``SSE(seed)``; extend (plane, pixel):
  an atomic valid pixel with an admissible edge to the plane, increment
  ``SSE(Q + k) - SSE(Q)``; merge (a, b), a < b: two regular planes joined by an admissible edge,
  increment ``SSE(Qa + Qb) - SSE(Qa) - SSE(Qb)``.
* **Greedy.** Each step executes the candidate with the least increment; exact ties go to the
  smallest ``(kind, a, b)`` with kinds ordered create < extend < merge.
* **Snapshots.** ``J`` = valid pixels not in a regular plane + regular planes. The snapshot for
  an error threshold e is the state before the first executed action whose increment exceeds e;
  the snapshot for a plane count n is the state when first ``J <= n``; either is the final
  state if that never happens. The run continues while a candidate exists and some e has not
  been exceeded yet or ``J > min(n)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

# (drow, dcol) offsets from the anchor pixel for the 17 seed configurations, in config order
# (config index 0..16). They are the 17 fixed non-I tetrominoes; each contains the anchor (0, 0).
TETROMINO_OFFSETS: tuple[tuple[tuple[int, int], ...], ...] = (
    ((0, 0), (1, 0), (0, 1), (1, 1)),  # O
    ((-1, 0), (0, 0), (1, 0), (0, 1)),  # T
    ((0, -1), (-1, 0), (0, 0), (1, 0)),  # T
    ((0, -1), (0, 0), (1, 0), (0, 1)),  # T
    ((0, -1), (-1, 0), (0, 0), (0, 1)),  # T
    ((0, 0), (1, 0), (-1, 1), (0, 1)),  # S/Z
    ((-1, -1), (0, -1), (0, 0), (1, 0)),  # S/Z
    ((0, -1), (0, 0), (1, 0), (1, 1)),  # S/Z
    ((0, -1), (-1, 0), (0, 0), (-1, 1)),  # S/Z
    ((-1, 0), (0, 0), (1, 0), (-1, 1)),  # L/J
    ((-1, -1), (-1, 0), (0, 0), (1, 0)),  # L/J
    ((0, -1), (1, -1), (0, 0), (0, 1)),  # L/J
    ((0, -1), (0, 0), (0, 1), (1, 1)),  # L/J
    ((-1, -1), (0, -1), (0, 0), (0, 1)),  # L/J
    ((0, -1), (0, 0), (-1, 1), (0, 1)),  # L/J
    ((-1, 0), (0, 0), (1, 0), (1, 1)),  # L/J
    ((1, -1), (-1, 0), (0, 0), (1, 0)),  # L/J
)

CREATE, EXTEND, MERGE = 0, 1, 2
ACTION_KIND_NAMES: tuple[str, str, str] = ('create', 'extend', 'merge')
# The dtype of ``ReferenceResult.actions_array()``; the fast extractor's ``.actions`` uses it too.
ACTION_DTYPE = np.dtype([('kind', np.int8), ('a', np.int64), ('b', np.int64), ('increment', np.float64)])
DEFAULT_MAX_ERROR_INCREMENT = 0.01

# Plane fit: stop when an accepted Gauss-Newton step lowers the SSE by less than this fraction.
_FIT_RELATIVE_TOLERANCE = 1e-13
_FIT_MAX_ITERATIONS = 100
_FIT_MAX_STEP_HALVINGS = 40
# ... or when the Gauss-Newton step would change w by less than this fraction (round-off level).
_FIT_NEGLIGIBLE_STEP = 1e-13


# --------------------------------------------------------------------------------------------
# Exact plane fit
# --------------------------------------------------------------------------------------------


def _sse_in_w(w: np.ndarray, points: np.ndarray, directions: np.ndarray) -> float:
    """SSE of the plane ``w . x = 1`` (translated frame); inf if a ray is parallel to it."""
    if not np.all(np.isfinite(w)):
        return math.inf
    cosines = directions @ w
    if np.any(cosines == 0.0):
        return math.inf
    residuals = (points @ w - 1.0) / cosines
    sse = float(residuals @ residuals)
    return sse if math.isfinite(sse) else math.inf


def _gauss_newton(w: np.ndarray, points: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, float]:
    """Minimise the SSE over w from the start w by Gauss-Newton with step halving.

    The residual of ray k is ``f_k(w) = (w . p_k - 1) / (w . v_k)`` (exactly ``r_k - rhat_k``),
    its gradient ``p_k / (w . v_k) - f_k v_k / (w . v_k)``.
    """
    sse = _sse_in_w(w, points, directions)
    if not math.isfinite(sse):
        return w, sse
    for _ in range(_FIT_MAX_ITERATIONS):
        if sse == 0.0:
            break
        cosines = directions @ w
        residuals = (points @ w - 1.0) / cosines
        jacobian = (points - residuals[:, None] * directions) / cosines[:, None]
        step = np.linalg.lstsq(jacobian, -residuals, rcond=None)[0]
        if not np.all(np.isfinite(step)) or np.linalg.norm(step) <= _FIT_NEGLIGIBLE_STEP * np.linalg.norm(w):
            break
        fraction = 1.0
        for _ in range(_FIT_MAX_STEP_HALVINGS):
            w_trial = w + fraction * step
            sse_trial = _sse_in_w(w_trial, points, directions)
            if sse_trial < sse:
                break
            fraction *= 0.5
        else:
            break  # no step along the Gauss-Newton direction lowers the SSE: converged
        decrease = sse - sse_trial
        w, sse_old, sse = w_trial, sse, sse_trial
        if decrease < _FIT_RELATIVE_TOLERANCE * sse_old:
            break
    return w, sse


def _initial_guesses(points: np.ndarray, ranges: np.ndarray) -> list[np.ndarray]:
    """Starting values of w for the fit (translated frame)."""
    guesses = []
    # min sum_k (r_k (w . p_k - 1))^2: the residual linearised at w . v_k = 1 / r_k.
    guesses.append(np.linalg.lstsq(ranges[:, None] * points, ranges, rcond=None)[0])
    # min sum_k (w . p_k - 1)^2: the algebraic fit.
    guesses.append(np.linalg.lstsq(points, np.ones(len(points)), rcond=None)[0])
    # The PCA (orthogonal least squares) plane of the endpoints.
    centroid = points.mean(axis=0)
    normal = np.linalg.svd(points - centroid)[2][-1]
    offset = float(normal @ centroid)
    if abs(offset) > 1e-12 * (1.0 + float(np.linalg.norm(centroid))):
        guesses.append(normal / offset)
    return guesses


def _fit_translated(points: np.ndarray, directions: np.ndarray, ranges: np.ndarray) -> tuple[float, np.ndarray]:
    """The best (sse, w) over all starts; ``points`` are endpoints relative to the mean origin."""
    best_sse, best_w = math.inf, np.full(3, np.nan)
    for guess in _initial_guesses(points, ranges):
        w, sse = _gauss_newton(guess, points, directions)
        if sse < best_sse:
            best_sse, best_w = sse, w
    return best_sse, best_w


def reference_fit(origins: np.ndarray, directions: np.ndarray, ranges: np.ndarray) -> tuple[float, np.ndarray, float]:
    """Exact maximum-likelihood plane of N >= 3 rays under the radial (ray-length) noise model.

    Args:
        origins: ``(N, 3)`` ray start points s_k (metres).
        directions: ``(N, 3)`` unit ray directions v_k.
        ranges: ``(N,)`` measured ray lengths r_k > 0 (metres).

    Returns:
        ``(sse, normal, offset)``: the least sum of squared range residuals
        ``sum_k (r_k - rhat_k)^2`` (m^2), with ``rhat_k = (offset - normal . s_k) / (normal . v_k)``,
        and the plane ``normal . x = offset`` attaining it (unit normal facing the mean ray
        origin; offset in metres, in the frame of the input). The plane is searched among planes
        not through the mean ray origin (parameter ``w = normal / distance`` relative to it),
        from three starts (weighted linear, algebraic and PCA plane) with Gauss-Newton and step
        halving until the SSE drops by a relative 1e-13 or less per step; the best is returned.
        The SSE is inf and the plane NaN if no start gives a finite SSE.
    """
    origins = np.asarray(origins, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    ranges = np.asarray(ranges, dtype=np.float64)
    if origins.ndim != 2 or origins.shape[1] != 3:
        raise ValueError(f'origins must have shape (N, 3), got {origins.shape}')
    if directions.shape != origins.shape:
        raise ValueError(f'directions must have shape {origins.shape} like origins, got {directions.shape}')
    if ranges.shape != (origins.shape[0],):
        raise ValueError(f'ranges must have shape ({origins.shape[0]},), got {ranges.shape}')
    if origins.shape[0] < 3:
        raise ValueError(f'a plane fit needs at least 3 rays, got {origins.shape[0]}')
    if not (np.all(np.isfinite(origins)) and np.all(np.isfinite(directions)) and np.all(np.isfinite(ranges))):
        raise ValueError('origins, directions and ranges must be finite')
    if np.any(ranges <= 0.0):
        raise ValueError('ranges must be positive')
    if np.max(np.abs(np.linalg.norm(directions, axis=1) - 1.0)) > 1e-9:
        raise ValueError('directions must be unit vectors')

    mean_origin = origins.mean(axis=0)
    endpoints = origins - mean_origin + ranges[:, None] * directions
    sse, w = _fit_translated(endpoints, directions, ranges)
    if not math.isfinite(sse):
        return math.inf, np.full(3, np.nan), math.nan
    inverse_distance = float(np.linalg.norm(w))
    normal = w / inverse_distance
    # Translated frame: normal . (x - mean_origin) = 1 / |w| > 0, so the normal points away
    # from the mean origin; flip it to face the origin.
    normal = -normal
    offset = -1.0 / inverse_distance + float(normal @ mean_origin)
    return sse, normal, offset


# --------------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------------


class Action(NamedTuple):
    """One executed greedy action.

    create: ``a`` = anchor pixel id (the new plane's id), ``b`` = config index 0..16;
    extend: ``a`` = plane id, ``b`` = pixel id; merge: ``a`` = surviving (smaller) plane id,
    ``b`` = removed plane id. ``increment`` is the error increment in m^2.
    """

    kind: str
    a: int
    b: int
    increment: float


class Snapshot(NamedTuple):
    """The state at a stopping threshold.

    ``description`` is ``f'e={float(e)!r}'`` (e.g. ``'e=0.01'``) or ``f'n={n}'``;
    ``plane_id_image`` is ``(H, W)`` int64 holding each pixel's regular plane id, -1 for atomic
    and invalid pixels; ``steps`` is the number of actions executed before this state.
    """

    description: str
    plane_id_image: np.ndarray
    steps: int


def plane_sets(snapshot: Snapshot | np.ndarray) -> dict[int, tuple[int, ...]]:
    """Map plane id -> sorted linear pixel ids, from a snapshot or a plane-id image."""
    image = snapshot.plane_id_image if isinstance(snapshot, Snapshot) else np.asarray(snapshot)
    flat = image.reshape(-1)
    return {int(plane): tuple(int(k) for k in np.flatnonzero(flat == plane)) for plane in np.unique(flat[flat >= 0])}


def tetromino_pixels(anchor: int, config: int, width: int) -> tuple[int, ...]:
    """Linear ids of the 4 cells of seed ``(anchor, config)`` on a grid of ``width`` columns.

    The seed must lie inside the grid (true for every executed create).
    """
    row, col = divmod(anchor, width)
    return tuple((row + drow) * width + col + dcol for drow, dcol in TETROMINO_OFFSETS[config])


@dataclass(frozen=True)
class ReferenceResult:
    """Output of ``reference_extract``.

    Attributes:
        shape: ``(H, W)`` of the scan.
        actions: executed actions in order.
        snapshots: one per threshold: e thresholds ascending, then n counts descending.
        final_plane_id_image: the ``(H, W)`` plane ids (-1 = atomic or invalid) when the run ended.
        valid: ``(H, W)`` bool mask of valid pixels.
    """

    shape: tuple[int, int]
    actions: list[Action]
    snapshots: list[Snapshot]
    final_plane_id_image: np.ndarray
    valid: np.ndarray

    def actions_array(self) -> np.ndarray:
        """The actions as a structured array of dtype ``ACTION_DTYPE`` (kind 0/1/2 = create/extend/merge)."""
        out = np.zeros(len(self.actions), dtype=ACTION_DTYPE)
        for i, action in enumerate(self.actions):
            out[i] = (ACTION_KIND_NAMES.index(action.kind), action.a, action.b, action.increment)
        return out

    def plane_sets(self, snapshot: Snapshot | np.ndarray) -> dict[int, tuple[int, ...]]:
        """Map plane id -> sorted linear pixel ids of a snapshot (or plane-id image)."""
        return plane_sets(snapshot)

    def snapshot(self, description: str) -> Snapshot:
        """The snapshot labelled ``description`` (e.g. ``'e=0.01'`` or ``'n=3'``)."""
        for snap in self.snapshots:
            if snap.description == description:
                return snap
        raise KeyError(f'no snapshot {description!r}; have {[s.description for s in self.snapshots]}')

    def state_after(self, steps: int) -> np.ndarray:
        """The ``(H, W)`` plane-id image after replaying the first ``steps`` actions from scratch."""
        height, width = self.shape
        labels = np.full(height * width, -1, dtype=np.int64)
        for action in self.actions[:steps]:
            if action.kind == 'create':
                labels[list(tetromino_pixels(action.a, action.b, width))] = action.a
            elif action.kind == 'extend':
                labels[action.b] = action.a
            else:
                labels[labels == action.b] = action.a
        return labels.reshape(height, width)


# --------------------------------------------------------------------------------------------
# Extraction
# --------------------------------------------------------------------------------------------


class _Scan:
    """Per-pixel rays of a scan and its admissible edges (flattened row-major)."""

    def __init__(self, points: np.ndarray, origins: np.ndarray, max_neighbor_distance: float):
        self.height, self.width = points.shape[:2]
        self.size = self.height * self.width
        points = points.reshape(-1, 3)
        origins = origins.reshape(-1, 3)
        finite = np.all(np.isfinite(points), axis=1) & np.all(np.isfinite(origins), axis=1)
        with np.errstate(invalid='ignore'):
            ranges = np.linalg.norm(points - origins, axis=1)
        self.valid = finite & (ranges > 0.0)
        self.points = points
        self.origins = origins
        self.ranges = np.where(self.valid, ranges, np.nan)
        with np.errstate(invalid='ignore', divide='ignore'):
            self.directions = (points - origins) / self.ranges[:, None]
        self.max_neighbor_distance = max_neighbor_distance
        # neighbors[k]: pixels joined to k by an admissible edge.
        self.neighbors: list[list[int]] = [[] for _ in range(self.size)]
        for k in range(self.size):
            row, col = divmod(k, self.width)
            for m_row, m_col in ((row - 1, col), (row + 1, col), (row, col - 1), (row, col + 1)):
                if 0 <= m_row < self.height and 0 <= m_col < self.width:
                    m = m_row * self.width + m_col
                    if self.is_admissible_edge(k, m):
                        self.neighbors[k].append(m)

    def is_admissible_edge(self, a: int, b: int) -> bool:
        """Both pixels valid and their points at most max_neighbor_distance apart (adjacency not checked)."""
        if not (self.valid[a] and self.valid[b]):
            return False
        return float(np.linalg.norm(self.points[a] - self.points[b])) <= self.max_neighbor_distance

    def seeds(self) -> list[tuple[int, int, tuple[int, ...]]]:
        """(anchor, config, pixels) of every seed inside the grid with valid cells and admissible edges.

        Whether its cells are still atomic is checked by the caller at every step.
        """
        out = []
        for anchor in range(self.size):
            row, col = divmod(anchor, self.width)
            for config, offsets in enumerate(TETROMINO_OFFSETS):
                cells = [(row + drow, col + dcol) for drow, dcol in offsets]
                if not all(0 <= r < self.height and 0 <= c < self.width for r, c in cells):
                    continue
                pixels = tuple(r * self.width + c for r, c in cells)
                if not all(self.valid[k] for k in pixels):
                    continue
                internal_edges = [
                    (pixels[i], pixels[j])
                    for i in range(4)
                    for j in range(i + 1, 4)
                    if abs(cells[i][0] - cells[j][0]) + abs(cells[i][1] - cells[j][1]) == 1
                ]
                assert len(internal_edges) == (4 if config == 0 else 3)
                if all(self.is_admissible_edge(a, b) for a, b in internal_edges):
                    out.append((anchor, config, pixels))
        return out


class _Extractor:
    """The greedy agglomeration, recomputing every candidate every step."""

    def __init__(self, scan: _Scan):
        self.scan = scan
        self.labels = np.full(scan.size, -1, dtype=np.int64)  # regular plane id per pixel
        self.planes: dict[int, frozenset[int]] = {}
        self._sse_cache: dict[frozenset[int], float] = {}
        self._seeds = scan.seeds()

    def sse(self, pixels: frozenset[int]) -> float:
        """Exact SSE of the rays of a set of pixels (cached: it depends on the set only)."""
        if pixels not in self._sse_cache:
            ids = np.array(sorted(pixels))
            scan = self.scan
            self._sse_cache[pixels] = reference_fit(scan.origins[ids], scan.directions[ids], scan.ranges[ids])[0]
        return self._sse_cache[pixels]

    def plane_count(self) -> int:
        """J: valid pixels not in a regular plane plus regular planes."""
        in_planes = sum(len(pixels) for pixels in self.planes.values())
        return int(self.scan.valid.sum()) - in_planes + len(self.planes)

    def is_atomic(self, k: int) -> bool:
        return bool(self.scan.valid[k]) and self.labels[k] < 0

    def candidates(self) -> list[tuple[float, int, int, int]]:
        """Every candidate action as ``(increment, kind, a, b)``; the tuple order is the greedy order."""
        out = []
        for anchor, config, pixels in self._seeds:
            if all(self.is_atomic(k) for k in pixels):
                out.append((self.sse(frozenset(pixels)), CREATE, anchor, config))
        for plane, pixels in self.planes.items():
            plane_sse = self.sse(pixels)
            reachable_atomic = {m for k in pixels for m in self.scan.neighbors[k] if self.is_atomic(m)}
            for k in reachable_atomic:
                out.append((self.sse(pixels | {k}) - plane_sse, EXTEND, plane, k))
        merge_pairs = set()
        for plane, pixels in self.planes.items():
            for k in pixels:
                for m in self.scan.neighbors[k]:
                    other = int(self.labels[m])
                    if other >= 0 and other != plane:
                        merge_pairs.add((min(plane, other), max(plane, other)))
        for a, b in merge_pairs:
            increment = self.sse(self.planes[a] | self.planes[b]) - self.sse(self.planes[a]) - self.sse(self.planes[b])
            out.append((increment, MERGE, a, b))
        # A NaN increment (a fit that failed) can never be chosen.
        return [candidate for candidate in out if not math.isnan(candidate[0])]

    def execute(self, kind: int, a: int, b: int) -> None:
        if kind == CREATE:
            pixels = frozenset(tetromino_pixels(a, b, self.scan.width))
            self.planes[a] = pixels
            self.labels[list(pixels)] = a
        elif kind == EXTEND:
            self.planes[a] = self.planes[a] | {b}
            self.labels[b] = a
        else:
            self.planes[a] = self.planes[a] | self.planes.pop(b)
            self.labels[self.labels == b] = a

    def image(self) -> np.ndarray:
        return self.labels.reshape(self.scan.height, self.scan.width).copy()


def _as_thresholds(value: float | Sequence[float] | None, name: str) -> list[float]:
    if value is None:
        return []
    values = [value] if np.ndim(value) == 0 else list(np.asarray(value).reshape(-1))
    out = []
    for v in values:
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise ValueError(f'{name} must be numbers, got {v!r}')
        if math.isnan(float(v)):
            raise ValueError(f'{name} must not be NaN')
        out.append(float(v))
    return sorted(set(out))


def _as_counts(value: int | Sequence[int] | None) -> list[int]:
    if value is None:
        return []
    values = [value] if np.ndim(value) == 0 else list(np.asarray(value).reshape(-1))
    out = []
    for v in values:
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or v < 0:
            raise ValueError(f'max_planes must be non-negative integers, got {v!r}')
        out.append(int(v))
    return sorted(set(out), reverse=True)


def reference_extract(
    points: np.ndarray,
    *,
    origins: np.ndarray | None = None,
    max_error_increment: float | Sequence[float] | None = DEFAULT_MAX_ERROR_INCREMENT,
    max_planes: int | Sequence[int] | None = None,
    max_neighbor_distance: float = np.inf,
) -> ReferenceResult:
    """Run PPE on an organized scan by brute force (see the module docstring for the semantics).

    Args:
        points: ``(H, W, 3)`` ray endpoints in metres; NaN = no return.
        origins: ``(H, W, 3)`` ray start points in metres, same frame; default all zeros.
        max_error_increment: error threshold(s) e in m^2 (one snapshot each); None for none.
            If both this and ``max_planes`` are None, e = [0.01].
        max_planes: plane-count threshold(s) n (one snapshot each); None for none.
        max_neighbor_distance: lmax in metres; longer 4-neighbour edges are not admissible.

    Returns:
        The executed actions and the snapshots.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 3 or points.shape[2] != 3:
        raise ValueError(f'points must have shape (H, W, 3), got {points.shape}')
    if origins is None:
        origins = np.zeros_like(points)
    origins = np.asarray(origins, dtype=np.float64)
    if origins.shape != points.shape:
        raise ValueError(f'origins must have the shape of points {points.shape}, got {origins.shape}')
    max_neighbor_distance = float(max_neighbor_distance)
    if not max_neighbor_distance > 0.0:
        raise ValueError(f'max_neighbor_distance must be positive, got {max_neighbor_distance}')
    error_thresholds = _as_thresholds(max_error_increment, 'max_error_increment')
    plane_counts = _as_counts(max_planes)
    if not error_thresholds and not plane_counts:
        error_thresholds = [DEFAULT_MAX_ERROR_INCREMENT]

    scan = _Scan(points, origins, max_neighbor_distance)
    extractor = _Extractor(scan)
    pending_errors = list(error_thresholds)  # ascending
    pending_counts = list(plane_counts)  # descending
    taken: dict[str, Snapshot] = {}
    actions: list[Action] = []

    while True:
        plane_count = extractor.plane_count()
        for n in [n for n in pending_counts if plane_count <= n]:
            taken[f'n={n}'] = Snapshot(f'n={n}', extractor.image(), len(actions))
            pending_counts.remove(n)
        candidates = extractor.candidates()
        if not candidates:
            break
        increment, kind, a, b = min(candidates)
        for e in [e for e in pending_errors if increment > e]:
            taken[f'e={e!r}'] = Snapshot(f'e={e!r}', extractor.image(), len(actions))
            pending_errors.remove(e)
        if not pending_errors and not pending_counts:
            break
        extractor.execute(kind, a, b)
        actions.append(Action(ACTION_KIND_NAMES[kind], a, b, increment))

    for e in pending_errors:
        taken[f'e={e!r}'] = Snapshot(f'e={e!r}', extractor.image(), len(actions))
    for n in pending_counts:
        taken[f'n={n}'] = Snapshot(f'n={n}', extractor.image(), len(actions))
    order = [f'e={e!r}' for e in error_thresholds] + [f'n={n}' for n in plane_counts]
    return ReferenceResult(
        shape=(scan.height, scan.width),
        actions=actions,
        snapshots=[taken[d] for d in order],
        final_plane_id_image=extractor.image(),
        valid=scan.valid.reshape(scan.height, scan.width).copy(),
    )
