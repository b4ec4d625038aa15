"""Small ray-cast scenes and an independent plane fit for the extraction and fitting tests.

Self-contained (numpy only, no ``ppe_ros`` import) so that the tests do not share code with what
they test. Frames: a scene lives in a *world* frame (metres, z up); a sensor at ``position`` with
rotation ``R`` (sensor -> world) casts rays whose directions are given in the *sensor* frame
(x forward, y left, z up). A :class:`Scan` holds the measured endpoints and ray starts in both
frames.

The scan grids are deliberately *not* separable: every row has its own azimuth stagger and every
column its own elevation stagger. With a separable grid each scan column is a plane through the
sensor, so any three endpoints of one column on a planar surface are collinear and every seed
containing them fits with the same error (exact ties decided by round-off), and a row at zero
elevation is a planar fan too (see the reference notes, section 9).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Face:
    """A plane ``normal . x = offset`` (world frame), optionally bounded by a convex polygon.

    ``polygon`` is ``(K, 3)`` vertices in cyclic order lying on the plane, or None for an
    unbounded plane.
    """

    normal: np.ndarray
    offset: float
    polygon: np.ndarray | None = None


def face_from_polygon(vertices) -> Face:
    """A bounded face from its convex polygon's vertices (metres, cyclic order)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    normal = np.cross(vertices[1] - vertices[0], vertices[2] - vertices[0])
    normal /= np.linalg.norm(normal)
    return Face(normal=normal, offset=float(normal @ vertices[0]), polygon=vertices)


def plane(normal, offset: float) -> Face:
    """An unbounded face ``normal . x = offset`` (the normal is normalised)."""
    normal = np.asarray(normal, dtype=np.float64)
    length = np.linalg.norm(normal)
    return Face(normal=normal / length, offset=float(offset) / length)


def rotation(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """Sensor-to-world rotation ``Rz(yaw) Ry(pitch) Rx(roll)``; a positive pitch looks down."""
    yaw, pitch, roll = np.radians([yaw_deg, pitch_deg, roll_deg])
    rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    ry = np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0], [-np.sin(pitch), 0, np.cos(pitch)]])
    rx = np.array([[1, 0, 0], [0, np.cos(roll), -np.sin(roll)], [0, np.sin(roll), np.cos(roll)]])
    return rz @ ry @ rx


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A random proper rotation (QR of a Gaussian matrix, sign-fixed)."""
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def staggered_directions(
    rows: int, cols: int, *, azimuth_fov_deg: float = 60.0, elevation_fov_deg: float = 40.0, seed: int = 0
) -> np.ndarray:
    """``(rows, cols, 3)`` unit ray directions (sensor frame) of a non-separable spherical grid.

    Row 0 is the top, column 0 the left (largest azimuth). Each row gets an azimuth stagger and
    each column an elevation stagger of up to a third of the grid spacing, so no scan row or
    column is a plane through the sensor.
    """
    rng = np.random.default_rng([seed, 17])
    az_step = azimuth_fov_deg / max(cols - 1, 1)
    el_step = elevation_fov_deg / max(rows - 1, 1)
    azimuth = (
        np.linspace(azimuth_fov_deg / 2, -azimuth_fov_deg / 2, cols)[None, :]
        + (rng.uniform(-az_step / 3, az_step / 3, rows)[:, None])
    )
    elevation = (
        np.linspace(elevation_fov_deg / 2, -elevation_fov_deg / 2, rows)[:, None]
        + (rng.uniform(-el_step / 3, el_step / 3, cols)[None, :])
    )
    azimuth, elevation = np.radians(azimuth), np.radians(elevation)
    return np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation) + 0.0 * azimuth],
        axis=-1,
    )


def beam_origins(directions: np.ndarray, radius: float = 0.04, height_step: float = 0.002) -> np.ndarray:
    """``(H, W, 3)`` per-ray starts (sensor frame): on a ring of ``radius`` m in each ray's azimuth,
    each row ``height_step`` m higher than the row below (like the beams of a spinning lidar)."""
    rows = directions.shape[0]
    horizontal = directions[..., :2] / np.linalg.norm(directions[..., :2], axis=-1, keepdims=True)
    heights = height_step * (rows - 1 - np.arange(rows))[:, None] * np.ones(directions.shape[1])
    return np.concatenate([radius * horizontal, heights[..., None]], axis=-1)


def cast(faces: list[Face], origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of each ray: ``(distances (N,), face index (N,))``; NaN / -1 where nothing is hit."""
    best = np.full(len(origins), np.inf)
    index = np.full(len(origins), -1, np.int64)
    for f, face in enumerate(faces):
        with np.errstate(divide='ignore', invalid='ignore'):
            t = (face.offset - origins @ face.normal) / (directions @ face.normal)
        hit = np.isfinite(t) & (t > 1e-9) & (t < best)
        if face.polygon is not None:
            x = origins + t[:, None] * directions
            poly = face.polygon
            for k in range(len(poly)):
                edge = poly[(k + 1) % len(poly)] - poly[k]
                side = np.cross(edge, x - poly[k]) @ face.normal
                hit &= side >= 0
        best[hit] = t[hit]
        index[hit] = f
    return np.where(index >= 0, best, np.nan), index


@dataclass(frozen=True)
class Scan:
    """A cast scan.

    Attributes:
        sensor_points: ``(H, W, 3)`` endpoints in the sensor frame (m), NaN = no return.
        sensor_origins: ``(H, W, 3)`` ray starts in the sensor frame, or None (all at the origin).
        points: ``(H, W, 3)`` endpoints in the world frame.
        origins: ``(H, W, 3)`` ray starts in the world frame (never None).
        truth: ``(H, W)`` index of the face each ray hit, -1 = no return.
        faces: the world-frame faces.
        position, rotation: the sensor pose (sensor -> world: ``x_w = rotation @ x_s + position``).
    """

    sensor_points: np.ndarray
    sensor_origins: np.ndarray | None
    points: np.ndarray
    origins: np.ndarray
    truth: np.ndarray
    faces: list[Face]
    position: np.ndarray
    rotation: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.truth.shape


def cast_scan(
    faces: list[Face],
    *,
    rows: int,
    cols: int,
    position,
    yaw_deg: float = 0.0,
    pitch_deg: float = 0.0,
    roll_deg: float = 0.0,
    azimuth_fov_deg: float = 60.0,
    elevation_fov_deg: float = 40.0,
    noise: float = 0.0,
    seed: int = 0,
    beam_radius: float | None = None,
    nan_pixels=(),
) -> Scan:
    """Cast a scan of ``faces`` with Gaussian range noise of std ``noise`` m (seeded).

    ``beam_radius`` gives per-ray starts (:func:`beam_origins`); ``nan_pixels`` is a list of
    ``(row, col)`` that become no-returns.
    """
    directions = staggered_directions(
        rows, cols, azimuth_fov_deg=azimuth_fov_deg, elevation_fov_deg=elevation_fov_deg, seed=seed
    )
    sensor_origins = None if beam_radius is None else beam_origins(directions, beam_radius)
    starts = np.zeros_like(directions) if sensor_origins is None else sensor_origins
    rot = rotation(yaw_deg, pitch_deg, roll_deg)
    position = np.asarray(position, dtype=np.float64)
    world_starts = starts @ rot.T + position
    world_dirs = directions @ rot.T
    distances, index = cast(faces, world_starts.reshape(-1, 3), world_dirs.reshape(-1, 3))
    rng = np.random.default_rng([seed, 3])
    distances = distances + noise * rng.standard_normal(distances.shape)
    distances = distances.reshape(rows, cols)
    truth = index.reshape(rows, cols)
    for row, col in nan_pixels:
        distances[row, col] = np.nan
        truth[row, col] = -1
    sensor_points = starts + distances[..., None] * directions
    points = world_starts + distances[..., None] * world_dirs
    return Scan(
        sensor_points=sensor_points,
        sensor_origins=sensor_origins,
        points=points,
        origins=world_starts,
        truth=truth,
        faces=list(faces),
        position=position,
        rotation=rot,
    )


# --------------------------------------------------------------------------------------------
# Scenes
# --------------------------------------------------------------------------------------------

#: Floor z = 0 and two walls x = 3 and y = -1.2 meeting in a corner (world frame).
CORNER = (plane([0, 0, 1], 0.0), plane([-1, 0, 0], -3.0), plane([0, 1, 0], -1.2))


def corner_scan(
    *,
    rows: int = 8,
    cols: int = 10,
    n_planes: int = 3,
    noise: float = 0.0,
    seed: int = 0,
    beam_radius: float | None = None,
    nan_pixels=(),
) -> Scan:
    """A small scan of the floor and one or two walls by a pitched and rolled sensor 1 m above the floor.

    With ``n_planes=2`` the second wall is left out (the first wall is then hit where it was).
    """
    faces = list(CORNER[:n_planes])
    return cast_scan(
        faces,
        rows=rows,
        cols=cols,
        position=(0.0, 0.0, 1.0),
        yaw_deg=-15.0,
        pitch_deg=15.0,
        roll_deg=12.0,
        azimuth_fov_deg=60.0,
        elevation_fov_deg=50.0,
        noise=noise,
        seed=seed,
        beam_radius=beam_radius,
        nan_pixels=nan_pixels,
    )


def depth_jump_scan(*, rows: int = 8, cols: int = 10, noise: float = 0.003, seed: int = 0) -> Scan:
    """A near wall panel (x = 2, y > 0) in front of a far wall (x = 3.5): a depth jump of 1.5 m
    between the left and the right part of the scan, plus the floor."""
    near = face_from_polygon([[2.0, 0.05, -0.1], [2.0, 0.05, 3.0], [2.0, 5.0, 3.0], [2.0, 5.0, -0.1]])
    faces = [plane([0, 0, 1], 0.0), plane([-1, 0, 0], -3.5), near]
    return cast_scan(
        faces,
        rows=rows,
        cols=cols,
        position=(0.0, 0.0, 1.0),
        yaw_deg=3.0,
        pitch_deg=12.0,
        roll_deg=8.0,
        azimuth_fov_deg=60.0,
        elevation_fov_deg=50.0,
        noise=noise,
        seed=seed,
    )


def box_faces(lo, hi) -> list[Face]:
    """The top and four side faces of an axis-aligned box [lo, hi] (outward normals)."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    quads = [
        [(x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)],  # top
        [(x1, y0, z0), (x1, y1, z0), (x1, y1, z1), (x1, y0, z1)],  # +x
        [(x0, y0, z0), (x0, y0, z1), (x0, y1, z1), (x0, y1, z0)],  # -x
        [(x0, y1, z0), (x0, y1, z1), (x1, y1, z1), (x1, y1, z0)],  # +y
        [(x0, y0, z0), (x1, y0, z0), (x1, y0, z1), (x0, y0, z1)],  # -y
    ]
    return [face_from_polygon(q) for q in quads]


def room_scan(*, rows: int = 60, cols: int = 80, noise: float = 0.02, seed: int = 0) -> Scan:
    """A room-like scene: floor, ceiling, three walls and two boxes, seen from 1.2 m height.

    Every face shows at least ~100 pixels on the 60 x 80 grid.
    """
    room = [
        plane([0, 0, 1], 0.0),
        plane([0, 0, -1], -2.6),
        plane([-1, 0, 0], -5.0),
        plane([0, -1, 0], -2.5),
        plane([0, 1, 0], -2.5),
    ]
    boxes = box_faces((1.6, -0.4, 0.0), (2.4, 0.6, 0.6)) + box_faces((2.2, -2.2, 0.0), (3.0, -1.3, 1.4))
    return cast_scan(
        room + boxes,
        rows=rows,
        cols=cols,
        position=(0.0, 0.0, 1.2),
        yaw_deg=4.0,
        pitch_deg=8.0,
        roll_deg=5.0,
        azimuth_fov_deg=100.0,
        elevation_fov_deg=70.0,
        noise=noise,
        seed=seed,
    )


def plane_patch(
    *, rows: int = 10, cols: int = 10, noise: float = 0.01, seed: int = 0, beam_radius: float | None = None
) -> Scan:
    """A single tilted plane filling the whole grid (world frame = sensor at the origin, rotated)."""
    faces = [plane([-1.0, 0.2, -0.3], -2.5)]
    return cast_scan(
        faces,
        rows=rows,
        cols=cols,
        position=(0.3, -0.2, 0.1),
        yaw_deg=10.0,
        pitch_deg=-5.0,
        roll_deg=20.0,
        azimuth_fov_deg=40.0,
        elevation_fov_deg=30.0,
        noise=noise,
        seed=seed,
        beam_radius=beam_radius,
    )


# --------------------------------------------------------------------------------------------
# Rays and an independent plane fit
# --------------------------------------------------------------------------------------------


def rays(points: np.ndarray, origins: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(starts, unit directions, ranges)`` of ``(N, 3)`` endpoints and ``(N, 3)``/``(3,)``/None starts."""
    points = np.asarray(points, dtype=np.float64)
    starts = (
        np.zeros_like(points)
        if origins is None
        else np.broadcast_to(np.asarray(origins, dtype=np.float64), points.shape)
    )
    delta = points - starts
    ranges = np.linalg.norm(delta, axis=1)
    return np.array(starts), delta / ranges[:, None], ranges


def radial_residuals(normal, offset, starts, directions, ranges) -> np.ndarray:
    """``r_k - rhat_k`` with ``rhat_k = (offset - normal . s_k) / (normal . v_k)``."""
    return ranges - (offset - starts @ normal) / (directions @ normal)


def radial_sse(normal, offset, starts, directions, ranges) -> float:
    res = radial_residuals(normal, offset, starts, directions, ranges)
    return float(res @ res)


def lm_plane_fit(starts, directions, ranges, *, max_iterations: int = 500) -> tuple[float, np.ndarray, float]:
    """Levenberg-Marquardt fit of a plane under radial noise, parameterised by (theta, phi, d).

    The normal is ``n = Q (sin theta cos phi, sin theta sin phi, cos theta)`` with a fixed
    rotation Q that puts the starting normal on the equator (away from the poles), and the
    plane is ``n . x = d``. Starts from the PCA plane of the endpoints; accepts only steps that
    lower the SSE and stops when no damping gives a decrease. Returns
    ``(sse, unit normal facing the mean ray start, offset)``.
    """
    starts = np.asarray(starts, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    ranges = np.asarray(ranges, dtype=np.float64)
    endpoints = starts + ranges[:, None] * directions
    centroid = endpoints.mean(axis=0)
    normal0 = np.linalg.svd(endpoints - centroid)[2][-1]
    # Q: first column = normal0 (theta = pi/2, phi = 0 maps to normal0)
    basis = np.linalg.svd(normal0[None, :])[2]
    q = np.stack([normal0, basis[1], basis[2]], axis=1)

    def unpack(params):
        theta, phi, d = params
        local = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
        dlocal = np.array(
            [
                [np.cos(theta) * np.cos(phi), -np.sin(theta) * np.sin(phi)],
                [np.cos(theta) * np.sin(phi), np.sin(theta) * np.cos(phi)],
                [-np.sin(theta), 0.0],
            ]
        )
        return q @ local, q @ dlocal, d

    def residuals_and_jacobian(params):
        n, dn, d = unpack(params)
        cos = directions @ n
        rhat = (d - starts @ n) / cos
        res = ranges - rhat
        # d res / d n = (s + rhat v) / (n . v); d res / d d = -1 / (n . v)
        grad_n = (starts + rhat[:, None] * directions) / cos[:, None]
        jac = np.column_stack([grad_n @ dn, -1.0 / cos])
        return res, jac

    params = np.array([np.pi / 2, 0.0, float(normal0 @ centroid)])
    res, jac = residuals_and_jacobian(params)
    sse = float(res @ res)
    damping = 1e-3
    for _ in range(max_iterations):
        jtj = jac.T @ jac
        grad = jac.T @ res
        improved = False
        for _ in range(60):
            step = np.linalg.solve(jtj + damping * np.diag(np.diag(jtj)), -grad)
            trial = params + step
            trial_res, trial_jac = residuals_and_jacobian(trial)
            trial_sse = float(trial_res @ trial_res)
            if np.isfinite(trial_sse) and trial_sse < sse:
                improved = True
                break
            damping *= 10.0
        if not improved:
            break
        params, res, jac, sse = trial, trial_res, trial_jac, trial_sse
        damping = max(damping / 10.0, 1e-12)
        if np.linalg.norm(step) < 1e-15 * (1.0 + np.linalg.norm(params)):
            break
    n, _, d = unpack(params)
    mean_start = starts.mean(axis=0)
    if n @ mean_start - d > 0:  # already facing the mean start: n . s > d on the sensor side
        return sse, n, float(d)
    return sse, -n, float(-d)
