"""Deterministic synthetic organized laser scans of rooms with polyhedral objects (SynPEB style).

A scene is a list of planar convex polygon faces in a *world* frame (metres, z up), each with its
own face label (10, 11, 12, ...). A sensor with a spherical scan grid is placed in the scene by a
:class:`SensorPose`; rays are cast with a numba kernel and the result is an organized
``(H, W, 3)`` cloud in the *sensor* frame (x forward, y left, z up, azimuth ``atan2(y, x)``,
row 0 = top), like SynPEB's PCD files.

Ground truth follows SynPEB's conventions (see :func:`label_regions`): every label >= 10 is one
4-connected image region, so a face seen in separate pieces (a wall above and below a table) gets
one label per piece, and coplanar but separate faces get different labels; pieces smaller than
``min_region_pixels`` are label 3 ("visible, no plane"), like SynPEB's label-3 border pixels.

Noise model (what SynPEB's files look like): the beam direction used for ray casting is jittered
by ``angular_sigma_deg``, the true range along it gets Gaussian ``radial_sigma`` noise, and the
stored point is ``origin + nominal_direction * measured_range``. Rays that hit nothing (or only
beyond ``max_range``) are no-returns: NaN points with label 0.

Everything is deterministic for a given seed: the scene from ``default_rng(seed)``, the noise from
``default_rng([seed, 1])``; the standard normal draws do not depend on the sigmas, so the same seed
with different noise levels gives the same underlying noise pattern, scaled.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numba import njit

FIRST_LABEL = 10
"""The label of a scene's first face; SynPEB's ground-truth planes are the labels >= 10."""

DEFAULT_ROOM_SIZE = (7.0, 6.0, 3.0)
"""Default room extent (x, y, z) in metres: the room spans ``[0, x] x [0, y] x [0, z]``."""

DEFAULT_N_OBJECTS = 8
"""Default number of objects in :func:`make_room_scene`; not all find a place. With the defaults a
500 x 500 scan has 44 ground-truth regions on average (seeds 0..29: range 25-74, SD 12; SynPEB: 42.6)."""

UNLABELLED_LABEL = 3
"""Label of visible pixels that belong to no ground-truth plane (SynPEB's label 3: border slivers)."""

DEFAULT_MIN_REGION_PIXELS = 50
"""Smaller 4-connected regions of a face get :data:`UNLABELLED_LABEL` instead of a plane label.
SynPEB's smallest labelled regions are 65, 66 and 87 pixels (test_500, pc_02, pc_01)."""

SYNPEB_ROWS = 500
SYNPEB_COLS = 500

_INSIDE_TOLERANCE = 1e-9  # metres: a hit this far outside a face edge still counts (no cracks)
_MIN_HIT_DISTANCE = 1e-9  # metres: hits closer to the ray start are ignored


# --------------------------------------------------------------------------------------------
# Scene model
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Face:
    """A planar convex polygon with a ground-truth label.

    Attributes:
        vertices: ``(K, 3)`` float64 corner points in cyclic order (either orientation), metres.
        label: ground-truth label (>= 1; scenes built here number faces from 10).
        name: what the face is, e.g. ``'room.floor'`` or ``'box2.top'``.
    """

    vertices: np.ndarray
    label: int
    name: str = ''

    @property
    def normal(self) -> np.ndarray:
        """Unit normal by Newell's method (right-handed with the vertex order)."""
        return _newell_normal(self.vertices)

    @property
    def offset(self) -> float:
        """``d`` with ``normal . x = d`` for points x on the face (metres)."""
        return float(self.normal @ self.vertices.mean(axis=0))


@dataclass(frozen=True)
class Scene:
    """A set of labelled convex faces in the world frame (metres, z up)."""

    faces: tuple[Face, ...]
    room_size: tuple[float, float, float] | None = None
    description: str = ''

    @classmethod
    def from_polygons(
        cls,
        polygons: Sequence[tuple[str, np.ndarray]],
        *,
        first_label: int = FIRST_LABEL,
        room_size: tuple[float, float, float] | None = None,
        description: str = '',
    ) -> Scene:
        """Build a scene from ``(name, (K, 3) vertices)`` polygons, labelled ``first_label, +1, ...``.

        Raises:
            ValueError: a polygon with fewer than 3 vertices, non-finite, degenerate, non-planar
                or non-convex.
        """
        if first_label < 1:
            raise ValueError(f'first_label must be >= 1 (0 means "no plane"); got {first_label}')
        faces = []
        for index, (name, vertices) in enumerate(polygons):
            checked = _validate_polygon(vertices, f'polygon {index} ({name!r})')
            faces.append(Face(vertices=checked, label=first_label + index, name=name))
        return cls(faces=tuple(faces), room_size=room_size, description=description)

    @property
    def labels(self) -> np.ndarray:
        """``(F,)`` int64 labels of the faces, in face order."""
        return np.array([face.label for face in self.faces], dtype=np.int64)

    def face(self, label: int) -> Face:
        """The face with ``label``.

        Raises:
            KeyError: no face has that label.
        """
        for face in self.faces:
            if face.label == label:
                return face
        known = f'labels {self.labels.min()}..{self.labels.max()}' if self.faces else 'no faces'
        raise KeyError(f'no face with label {label} in the scene ({known})')


def _newell_normal(vertices: np.ndarray) -> np.ndarray:
    nxt = np.roll(vertices, -1, axis=0)
    normal = np.array(
        [
            np.sum((vertices[:, 1] - nxt[:, 1]) * (vertices[:, 2] + nxt[:, 2])),
            np.sum((vertices[:, 2] - nxt[:, 2]) * (vertices[:, 0] + nxt[:, 0])),
            np.sum((vertices[:, 0] - nxt[:, 0]) * (vertices[:, 1] + nxt[:, 1])),
        ]
    )
    length = np.linalg.norm(normal)
    if not length > 0.0:
        raise ValueError('degenerate polygon: zero area')
    return normal / length


def _validate_polygon(vertices: np.ndarray, what: str) -> np.ndarray:
    array = np.array(vertices, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3 or array.shape[0] < 3:
        raise ValueError(f'{what}: vertices must be a (K, 3) array with K >= 3; got shape {array.shape}')
    if not np.all(np.isfinite(array)):
        raise ValueError(f'{what}: vertices must be finite')
    try:
        normal = _newell_normal(array)
    except ValueError as error:
        raise ValueError(f'{what}: {error}') from None
    scale = max(1.0, float(np.abs(array).max()))
    distances = (array - array.mean(axis=0)) @ normal
    if np.abs(distances).max() > 1e-9 * scale:
        raise ValueError(f'{what}: vertices are not coplanar (max deviation {np.abs(distances).max():.3g} m)')
    edges = np.roll(array, -1, axis=0) - array
    turns = np.cross(edges, np.roll(edges, -1, axis=0)) @ normal
    if np.any(turns < -1e-12 * scale**2):
        raise ValueError(f'{what}: polygon is not convex (or its vertices are not in cyclic order)')
    array.setflags(write=False)
    return array


# --------------------------------------------------------------------------------------------
# Primitives: lists of (name, vertices) polygons in the world frame
# --------------------------------------------------------------------------------------------


def _rotation_z(yaw_deg: float) -> np.ndarray:
    angle = math.radians(yaw_deg)
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _place(local: np.ndarray, position: Sequence[float], yaw_deg: float) -> np.ndarray:
    """Rotate local vertices about z by yaw and translate by position."""
    return np.asarray(local, dtype=np.float64) @ _rotation_z(yaw_deg).T + np.asarray(position, dtype=np.float64)


_BOX_SIDES = ('top', 'bottom', '+x', '-x', '+y', '-y')


def _box_local(center: Sequence[float], size: Sequence[float], sides: Sequence[str]) -> list[tuple[str, np.ndarray]]:
    """Outward-oriented quads of an axis-aligned box given by its centre and size (local frame)."""
    cx, cy, cz = center
    hx, hy, hz = (0.5 * s for s in size)
    x0, x1, y0, y1, z0, z1 = cx - hx, cx + hx, cy - hy, cy + hy, cz - hz, cz + hz
    quads = {
        'top': [(x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)],
        'bottom': [(x0, y0, z0), (x0, y1, z0), (x1, y1, z0), (x1, y0, z0)],
        '+x': [(x1, y0, z0), (x1, y1, z0), (x1, y1, z1), (x1, y0, z1)],
        '-x': [(x0, y0, z0), (x0, y0, z1), (x0, y1, z1), (x0, y1, z0)],
        '+y': [(x0, y1, z0), (x0, y1, z1), (x1, y1, z1), (x1, y1, z0)],
        '-y': [(x0, y0, z0), (x1, y0, z0), (x1, y0, z1), (x0, y0, z1)],
    }
    for side in sides:
        if side not in quads:
            raise ValueError(f'unknown box side {side!r}; expected some of {_BOX_SIDES}')
    return [(side, np.array(quads[side], dtype=np.float64)) for side in sides]


def _check_size(size: Sequence[float], what: str) -> tuple[float, float, float]:
    values = tuple(float(v) for v in size)
    if len(values) != 3 or not all(math.isfinite(v) and v > 0.0 for v in values):
        raise ValueError(f'{what} size must be three positive finite lengths in metres; got {size}')
    return values  # type: ignore[return-value]


def room_polygons(size: Sequence[float] = DEFAULT_ROOM_SIZE, *, name: str = 'room') -> list[tuple[str, np.ndarray]]:
    """The 6 faces of an axis-aligned room ``[0, sx] x [0, sy] x [0, sz]`` (normals point inward).

    Order: floor, ceiling, walls x=0, x=sx, y=0, y=sy.
    """
    sx, sy, sz = _check_size(size, 'room')
    inward = _box_local((sx / 2, sy / 2, sz / 2), (sx, sy, sz), ('bottom', 'top', '-x', '+x', '-y', '+y'))
    names = ('floor', 'ceiling', 'wall_x0', 'wall_x1', 'wall_y0', 'wall_y1')
    return [(f'{name}.{label}', vertices[::-1].copy()) for label, (_, vertices) in zip(names, inward, strict=True)]


def box_polygons(
    position: Sequence[float],
    size: Sequence[float],
    *,
    yaw_deg: float = 0.0,
    bottom: bool = False,
    name: str = 'box',
) -> list[tuple[str, np.ndarray]]:
    """A box standing at ``position`` = (x, y, z of its bottom), ``size`` = (sx, sy, sz) in metres.

    The box is rotated by ``yaw_deg`` about the vertical axis through its centre. The bottom face
    is left out unless ``bottom`` (it is hidden when the box stands on the floor).
    """
    sx, sy, sz = _check_size(size, 'box')
    sides = ('top', '+x', '-x', '+y', '-y', *(('bottom',) if bottom else ()))
    local = _box_local((0.0, 0.0, sz / 2), (sx, sy, sz), sides)
    return [(f'{name}.{side}', _place(vertices, position, yaw_deg)) for side, vertices in local]


def wedge_polygons(
    position: Sequence[float],
    size: Sequence[float],
    *,
    yaw_deg: float = 0.0,
    bottom: bool = False,
    name: str = 'wedge',
) -> list[tuple[str, np.ndarray]]:
    """A ramp-shaped triangular prism: a right triangle in the local x-z plane extruded along y.

    ``position`` = (x, y, z of the bottom) of the footprint centre, ``size`` = (sx, sy, sz): the
    vertical back face is at local x = -sx/2 and the slope descends to the floor at x = +sx/2.
    """
    sx, sy, sz = _check_size(size, 'wedge')
    hx, hy = sx / 2, sy / 2
    polygons = [
        ('slope', [(hx, -hy, 0.0), (hx, hy, 0.0), (-hx, hy, sz), (-hx, -hy, sz)]),
        ('back', [(-hx, -hy, 0.0), (-hx, -hy, sz), (-hx, hy, sz), (-hx, hy, 0.0)]),
        ('-y', [(-hx, -hy, 0.0), (hx, -hy, 0.0), (-hx, -hy, sz)]),
        ('+y', [(-hx, hy, 0.0), (-hx, hy, sz), (hx, hy, 0.0)]),
    ]
    if bottom:
        polygons.append(('bottom', [(-hx, -hy, 0.0), (-hx, hy, 0.0), (hx, hy, 0.0), (hx, -hy, 0.0)]))
    return [(f'{name}.{side}', _place(np.array(v, dtype=np.float64), position, yaw_deg)) for side, v in polygons]


def shelf_polygons(
    position: Sequence[float],
    size: Sequence[float],
    *,
    yaw_deg: float = 0.0,
    n_boards: int = 4,
    thickness: float = 0.04,
    name: str = 'shelf',
) -> list[tuple[str, np.ndarray]]:
    """An open shelf: two vertical side panels and ``n_boards`` horizontal boards between them.

    ``size`` = (width along local x, depth along local y, height) in metres; boards are evenly
    spaced from 0.1 m up to the top. Faces hidden by construction (ends of the boards against the
    panels, panel bottoms on the floor) are left out.
    """
    sx, sy, sz = _check_size(size, 'shelf')
    if n_boards < 1:
        raise ValueError(f'a shelf needs n_boards >= 1; got {n_boards}')
    if not (0.0 < thickness < min(sx / 3, sz / (n_boards + 1))):
        raise ValueError(f'shelf board thickness {thickness} m does not fit the size {size}')
    polygons: list[tuple[str, np.ndarray]] = []
    for side, sign in (('left', 1.0), ('right', -1.0)):
        center = (sign * (sx - thickness) / 2, 0.0, sz / 2)
        for face, vertices in _box_local(center, (thickness, sy, sz), ('top', '+x', '-x', '+y', '-y')):
            polygons.append((f'{name}.panel_{side}.{face}', vertices))
    inner = sx - 2 * thickness
    heights = np.linspace(0.1, sz - thickness, n_boards) if n_boards > 1 else np.array([sz - thickness])
    for index, z_bottom in enumerate(heights):
        center = (0.0, 0.0, float(z_bottom) + thickness / 2)
        for face, vertices in _box_local(center, (inner, sy, thickness), ('top', 'bottom', '+y', '-y')):
            polygons.append((f'{name}.board{index}.{face}', vertices))
    return [(label, _place(vertices, position, yaw_deg)) for label, vertices in polygons]


def table_polygons(
    position: Sequence[float],
    size: Sequence[float],
    *,
    yaw_deg: float = 0.0,
    top_thickness: float = 0.05,
    leg_width: float = 0.08,
    name: str = 'table',
) -> list[tuple[str, np.ndarray]]:
    """A table: a slab top (6 faces) on four square legs (4 side faces each).

    ``size`` = (length along local x, width along local y, height) in metres.
    """
    sx, sy, sz = _check_size(size, 'table')
    if not (0.0 < top_thickness < sz) or not (0.0 < leg_width < min(sx, sy) / 3):
        raise ValueError(f'table top thickness {top_thickness} m / leg width {leg_width} m do not fit size {size}')
    polygons: list[tuple[str, np.ndarray]] = []
    top_center = (0.0, 0.0, sz - top_thickness / 2)
    for face, vertices in _box_local(top_center, (sx, sy, top_thickness), _BOX_SIDES):
        polygons.append((f'{name}.top.{face}', vertices))
    leg_height = sz - top_thickness
    inset_x, inset_y = sx / 2 - leg_width, sy / 2 - leg_width
    for index, (ux, uy) in enumerate(((1, 1), (-1, 1), (-1, -1), (1, -1))):
        center = (ux * inset_x, uy * inset_y, leg_height / 2)
        for face, vertices in _box_local(center, (leg_width, leg_width, leg_height), ('+x', '-x', '+y', '-y')):
            polygons.append((f'{name}.leg{index}.{face}', vertices))
    return [(label, _place(vertices, position, yaw_deg)) for label, vertices in polygons]


def _regular_polygon(n_sides: int, size_x: float, size_y: float, z: float) -> np.ndarray:
    """``(n, 3)`` corners of a regular n-gon scaled to ``size_x`` x ``size_y`` (counter-clockwise seen from +z)."""
    angles = 2.0 * np.pi * np.arange(n_sides) / n_sides
    return np.stack([0.5 * size_x * np.cos(angles), 0.5 * size_y * np.sin(angles), np.full(n_sides, z)], axis=-1)


def _check_sides(n_sides: int, what: str) -> int:
    if isinstance(n_sides, bool) or int(n_sides) != n_sides or n_sides < 3:
        raise ValueError(f'{what} needs an integer n_sides >= 3; got {n_sides}')
    return int(n_sides)


def prism_polygons(
    position: Sequence[float],
    size: Sequence[float],
    *,
    n_sides: int = 6,
    yaw_deg: float = 0.0,
    bottom: bool = False,
    name: str = 'prism',
) -> list[tuple[str, np.ndarray]]:
    """An upright prism over a regular ``n_sides``-gon (scaled to the footprint ``size[:2]``).

    ``position`` = (x, y, z of the bottom) of the axis, ``size`` = (sx, sy, height) in metres.
    Faces: the top polygon and ``n_sides`` vertical quads (the bottom only if ``bottom``).
    """
    sx, sy, sz = _check_size(size, 'prism')
    n_sides = _check_sides(n_sides, 'a prism')
    base = _regular_polygon(n_sides, sx, sy, 0.0)
    top = base + np.array([0.0, 0.0, sz])
    polygons = [('top', top)]
    for index in range(n_sides):
        following = (index + 1) % n_sides
        polygons.append((f'side{index}', np.array([base[index], base[following], top[following], top[index]])))
    if bottom:
        polygons.append(('bottom', base[::-1].copy()))
    return [(f'{name}.{side}', _place(vertices, position, yaw_deg)) for side, vertices in polygons]


def pyramid_polygons(
    position: Sequence[float],
    size: Sequence[float],
    *,
    n_sides: int = 4,
    yaw_deg: float = 0.0,
    bottom: bool = False,
    name: str = 'pyramid',
) -> list[tuple[str, np.ndarray]]:
    """A pyramid over a regular ``n_sides``-gon base (scaled to ``size[:2]``) with its apex above the centre.

    ``position`` = (x, y, z of the base), ``size`` = (sx, sy, height) in metres. Faces: ``n_sides``
    triangles (the base only if ``bottom``).
    """
    sx, sy, sz = _check_size(size, 'pyramid')
    n_sides = _check_sides(n_sides, 'a pyramid')
    base = _regular_polygon(n_sides, sx, sy, 0.0)
    apex = np.array([0.0, 0.0, sz])
    polygons = [
        (f'side{index}', np.array([base[index], base[(index + 1) % n_sides], apex])) for index in range(n_sides)
    ]
    if bottom:
        polygons.append(('bottom', base[::-1].copy()))
    return [(f'{name}.{side}', _place(vertices, position, yaw_deg)) for side, vertices in polygons]


def _icosahedron_triangles() -> np.ndarray:
    """``(20, 3, 3)`` outward-oriented triangles of the icosahedron with circumradius 1."""
    golden = (1.0 + math.sqrt(5.0)) / 2.0
    corners = []
    for a in (-1.0, 1.0):
        for b in (-golden, golden):
            corners += [(0.0, a, b), (a, b, 0.0), (b, 0.0, a)]
    vertices = np.array(corners) / math.hypot(1.0, golden)
    edge = float(np.linalg.norm(vertices[0] - vertices[1:], axis=1).min())
    triangles = []
    count = len(vertices)
    for i in range(count):
        for j in range(i + 1, count):
            for k in range(j + 1, count):
                sides = (vertices[i] - vertices[j], vertices[j] - vertices[k], vertices[k] - vertices[i])
                if all(abs(np.linalg.norm(side) - edge) < 1e-9 for side in sides):
                    triangle = vertices[[i, j, k]]
                    if np.cross(triangle[1] - triangle[0], triangle[2] - triangle[0]) @ triangle.mean(axis=0) < 0:
                        triangle = triangle[::-1]
                    triangles.append(triangle)
    return np.array(triangles)


_ICOSAHEDRON = _icosahedron_triangles()


def icosahedron_polygons(
    center: Sequence[float],
    radius: float,
    *,
    yaw_deg: float = 0.0,
    tilt_deg: float = 0.0,
    name: str = 'icosahedron',
) -> list[tuple[str, np.ndarray]]:
    """A regular icosahedron (20 triangles) with circumradius ``radius`` metres around ``center``.

    It is tilted by ``tilt_deg`` about its local x axis, then turned by ``yaw_deg`` about the vertical.
    """
    if not (math.isfinite(radius) and radius > 0.0):
        raise ValueError(f'icosahedron radius must be a positive length in metres; got {radius}')
    tilt = math.radians(tilt_deg)
    rotation_x = np.array(
        [[1.0, 0.0, 0.0], [0.0, math.cos(tilt), -math.sin(tilt)], [0.0, math.sin(tilt), math.cos(tilt)]]
    )
    return [
        (f'{name}.face{index}', _place(radius * triangle @ rotation_x.T, center, yaw_deg))
        for index, triangle in enumerate(_ICOSAHEDRON)
    ]


def stairs_polygons(
    position: Sequence[float],
    size: Sequence[float],
    *,
    n_steps: int = 5,
    yaw_deg: float = 0.0,
    name: str = 'stairs',
) -> list[tuple[str, np.ndarray]]:
    """A solid staircase rising along local +x: ``n_steps`` equal steps, each its own tread, riser and sides.

    ``position`` = (x, y, z of the bottom) of the footprint centre, ``size`` = (run along x, width
    along y, total height) in metres. Each step is a block from the floor to its tread, so its two
    side faces are separate rectangles (coplanar with, and touching, the next step's sides, as in
    SynPEB's staircases); the back is one rectangle of the full height.
    """
    sx, sy, sz = _check_size(size, 'stairs')
    if isinstance(n_steps, bool) or int(n_steps) != n_steps or n_steps < 1:
        raise ValueError(f'stairs need an integer n_steps >= 1; got {n_steps}')
    run, rise, hy = sx / n_steps, sz / n_steps, sy / 2
    polygons: list[tuple[str, np.ndarray]] = []
    for step in range(int(n_steps)):
        x0, x1 = -sx / 2 + step * run, -sx / 2 + (step + 1) * run
        z0, z1 = step * rise, (step + 1) * rise
        center = ((x0 + x1) / 2, 0.0, z1 / 2)
        faces = dict(_box_local(center, (run, sy, z1), ('top', '+y', '-y')))
        polygons.append((f'step{step}.tread', faces['top']))
        polygons.append((f'step{step}.riser', np.array([(x0, -hy, z0), (x0, -hy, z1), (x0, hy, z1), (x0, hy, z0)])))
        polygons.append((f'step{step}.+y', faces['+y']))
        polygons.append((f'step{step}.-y', faces['-y']))
    back = np.array([(sx / 2, -hy, 0.0), (sx / 2, hy, 0.0), (sx / 2, hy, sz), (sx / 2, -hy, sz)])
    polygons.append(('back', back))
    return [(f'{name}.{side}', _place(vertices, position, yaw_deg)) for side, vertices in polygons]


# --------------------------------------------------------------------------------------------
# Sensor: pose and scan grid
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SensorPose:
    """Pose of the sensor frame in the world frame.

    ``rotation = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (ROS fixed-axis roll-pitch-yaw) maps sensor
    axes to world axes; a positive pitch points the sensor's x axis (forward) *down*.
    """

    position: tuple[float, float, float] = (2.0, 2.8, 1.2)
    roll_deg: float = 0.0
    pitch_deg: float = 10.8
    yaw_deg: float = 12.0

    def __post_init__(self) -> None:
        position = tuple(float(v) for v in self.position)
        if len(position) != 3 or not all(math.isfinite(v) for v in position):
            raise ValueError(f'sensor position must be three finite coordinates in metres; got {self.position}')
        object.__setattr__(self, 'position', position)
        for angle_name in ('roll_deg', 'pitch_deg', 'yaw_deg'):
            if not math.isfinite(getattr(self, angle_name)):
                raise ValueError(f'sensor {angle_name} must be finite; got {getattr(self, angle_name)}')

    def rotation(self) -> np.ndarray:
        """``(3, 3)`` rotation from sensor to world coordinates."""
        r, p, y = (math.radians(a) for a in (self.roll_deg, self.pitch_deg, self.yaw_deg))
        rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(r), -math.sin(r)], [0.0, math.sin(r), math.cos(r)]])
        ry = np.array([[math.cos(p), 0.0, math.sin(p)], [0.0, 1.0, 0.0], [-math.sin(p), 0.0, math.cos(p)]])
        return _rotation_z(math.degrees(y)) @ ry @ rx

    def world_to_sensor(self, points: np.ndarray) -> np.ndarray:
        """Transform ``(..., 3)`` world points into the sensor frame."""
        return (np.asarray(points, dtype=np.float64) - np.asarray(self.position)) @ self.rotation()

    def to_dict(self) -> dict:
        """Plain-Python form (for JSON)."""
        return {
            'position': list(self.position),
            'roll_deg': self.roll_deg,
            'pitch_deg': self.pitch_deg,
            'yaw_deg': self.yaw_deg,
        }


DEFAULT_SENSOR_POSE = SensorPose()
"""Default pose in the default room: 2 m from wall x=0, 1.2 m high, yaw 12 deg, pitched 10.8 deg down
(SynPEB's test_500 is pitched 10.8 deg *up* from 0.44 m; its pc_01/pc_02 look 18-23 deg down)."""


@dataclass(frozen=True)
class ScanGrid:
    """A spherical scan grid: one elevation per row, one azimuth per column (degrees).

    The nominal direction of pixel (row, col) in the sensor frame is
    ``(cos el cos az, cos el sin az, sin el)``: x forward, y left, z up, ``az = atan2(y, x)``.
    """

    elevation_deg: np.ndarray
    azimuth_deg: np.ndarray

    def __post_init__(self) -> None:
        for attribute in ('elevation_deg', 'azimuth_deg'):
            values = np.array(getattr(self, attribute), dtype=np.float64)
            if values.ndim != 1 or values.size < 1:
                raise ValueError(f'{attribute} must be a non-empty 1-D array of angles; got shape {values.shape}')
            if not np.all(np.isfinite(values)):
                raise ValueError(f'{attribute} must be finite')
            values.setflags(write=False)
            object.__setattr__(self, attribute, values)
        if np.any(np.abs(self.elevation_deg) >= 90.0):
            raise ValueError('elevation_deg must lie strictly between -90 and +90 degrees')

    @classmethod
    def synpeb(cls) -> ScanGrid:
        """SynPEB's grid: 500 x 500, azimuth ``-35 + 0.14 col``, elevation ``linspace(+30, -30, 500)``."""
        return cls(
            elevation_deg=np.linspace(30.0, -30.0, SYNPEB_ROWS),
            azimuth_deg=-35.0 + 0.14 * np.arange(SYNPEB_COLS),
        )

    @classmethod
    def uniform(
        cls,
        rows: int,
        cols: int,
        *,
        azimuth_fov_deg: float,
        elevation_fov_deg: float,
        azimuth_center_deg: float = 0.0,
        elevation_center_deg: float = 0.0,
    ) -> ScanGrid:
        """An evenly spaced grid; column 0 is the rightmost azimuth and row 0 the top, as in SynPEB.

        A single row or column sits at the centre angle.
        """
        if int(rows) != rows or int(cols) != cols or rows < 1 or cols < 1:
            raise ValueError(f'rows and cols must be positive integers; got rows={rows}, cols={cols}')
        if not (0.0 <= azimuth_fov_deg <= 360.0) or not (0.0 <= elevation_fov_deg < 180.0):
            raise ValueError(
                f'field of view must be 0..360 deg in azimuth and 0..<180 deg in elevation; '
                f'got {azimuth_fov_deg}, {elevation_fov_deg}'
            )
        half_az, half_el = azimuth_fov_deg / 2, elevation_fov_deg / 2
        azimuth = np.linspace(azimuth_center_deg - half_az, azimuth_center_deg + half_az, int(cols))
        elevation = np.linspace(elevation_center_deg + half_el, elevation_center_deg - half_el, int(rows))
        if cols == 1:
            azimuth = np.array([float(azimuth_center_deg)])
        if rows == 1:
            elevation = np.array([float(elevation_center_deg)])
        return cls(elevation_deg=elevation, azimuth_deg=azimuth)

    @property
    def rows(self) -> int:
        """Number of rows H."""
        return int(self.elevation_deg.size)

    @property
    def cols(self) -> int:
        """Number of columns W."""
        return int(self.azimuth_deg.size)

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return (self.rows, self.cols)

    def directions(self) -> np.ndarray:
        """``(H, W, 3)`` unit nominal ray directions in the sensor frame."""
        elevation = np.radians(self.elevation_deg)[:, None]
        azimuth = np.radians(self.azimuth_deg)[None, :]
        cos_el = np.cos(elevation)
        return np.stack(
            np.broadcast_arrays(cos_el * np.cos(azimuth), cos_el * np.sin(azimuth), np.sin(elevation)),
            axis=-1,
        )

    def to_dict(self) -> dict:
        """Plain-Python form (for JSON)."""
        return {'elevation_deg': self.elevation_deg.tolist(), 'azimuth_deg': self.azimuth_deg.tolist()}


def beam_offset_origins(grid: ScanGrid, radius: float) -> np.ndarray:
    """``(H, W, 3)`` ray starts on a horizontal circle of ``radius`` metres around the sensor origin,
    in each column's azimuth direction (like a spinning lidar whose beams leave the housing a few
    centimetres off its axis)."""
    if not math.isfinite(radius):
        raise ValueError(f'radius must be finite; got {radius}')
    azimuth = np.radians(grid.azimuth_deg)
    ring = np.stack([radius * np.cos(azimuth), radius * np.sin(azimuth), np.zeros_like(azimuth)], axis=-1)
    return np.ascontiguousarray(np.broadcast_to(ring[None, :, :], (grid.rows, grid.cols, 3)))


# --------------------------------------------------------------------------------------------
# Random room scenes
# --------------------------------------------------------------------------------------------

_OBJECT_KINDS = ('box', 'wedge', 'shelf', 'table', 'prism', 'pyramid', 'icosahedron', 'stairs')
"""Object kinds of :func:`make_room_scene`: the furniture-like boxes, wedges, shelves and tables, and
the polyhedra seen in SynPEB's scans (n-gonal prisms, pyramids, floating icosahedra, staircases)."""

_PlacedBuilder = Callable[[float, float, float, str], list[tuple[str, np.ndarray]]]


def _random_object(kind: str, rng: np.random.Generator, room_height: float) -> tuple[float, _PlacedBuilder]:
    """A random object of ``kind``: its footprint radius (metres) and a builder ``(x, y, yaw_deg, name)``.

    Sizes are SynPEB-like (objects of 0.3-1.8 m) and no part is thinner than 4 cm (shelf boards
    and panels 4 cm, table tops 5 cm, table legs 8 cm), so every face is several pixels wide at the
    ranges of a 500 x 500 scan.
    """
    extra: dict = {}
    if kind == 'box':
        size = (rng.uniform(0.4, 1.2), rng.uniform(0.4, 1.2), rng.uniform(0.4, 1.2))
    elif kind == 'wedge':
        size = (rng.uniform(0.5, 1.3), rng.uniform(0.4, 1.0), rng.uniform(0.3, 0.9))
    elif kind == 'shelf':
        size = (rng.uniform(0.6, 1.2), rng.uniform(0.25, 0.45), rng.uniform(0.8, 1.8))
        extra = {'n_boards': int(rng.integers(3, 6))}
    elif kind == 'table':
        size = (rng.uniform(0.8, 1.6), rng.uniform(0.6, 1.0), rng.uniform(0.7, 0.8))
    elif kind in ('prism', 'pyramid'):
        diameter = rng.uniform(0.6, 1.2) if kind == 'prism' else rng.uniform(0.8, 1.4)
        height = rng.uniform(0.8, 1.8) if kind == 'prism' else rng.uniform(0.7, 1.4)
        size = (diameter, diameter, height)
        extra = {'n_sides': int(rng.integers(5, 9)) if kind == 'prism' else int(rng.integers(3, 7))}
    elif kind == 'icosahedron':
        radius = float(rng.uniform(0.4, 0.7))
        z_center = float(rng.uniform(radius + 0.3, max(radius + 0.3, min(2.2, room_height - radius - 0.1))))
        tilt = float(rng.uniform(0.0, 360.0))

        def build_icosahedron(x: float, y: float, yaw: float, name: str) -> list[tuple[str, np.ndarray]]:
            return icosahedron_polygons((x, y, z_center), radius, yaw_deg=yaw, tilt_deg=tilt, name=name)

        return radius, build_icosahedron
    elif kind == 'stairs':
        n_steps = int(rng.integers(4, 9))
        size = (n_steps * rng.uniform(0.25, 0.3), rng.uniform(1.0, 1.6), n_steps * rng.uniform(0.15, 0.2))
        extra = {'n_steps': n_steps}
    else:
        raise ValueError(f'unknown object kind {kind!r}; expected one of {_OBJECT_KINDS}')
    builder = _BUILDERS[kind]
    size = tuple(float(v) for v in size)
    radius = 0.5 * (math.hypot(size[0], size[1]) if kind in ('box', 'wedge', 'shelf', 'table', 'stairs') else size[0])

    def build(x: float, y: float, yaw: float, name: str) -> list[tuple[str, np.ndarray]]:
        return builder((x, y, 0.0), size, yaw_deg=yaw, name=name, **extra)

    return radius, build


_BUILDERS = {
    'box': box_polygons,
    'wedge': wedge_polygons,
    'shelf': shelf_polygons,
    'table': table_polygons,
    'prism': prism_polygons,
    'pyramid': pyramid_polygons,
    'stairs': stairs_polygons,
}

DEFAULT_VIEW_HALF_ANGLE_DEG = 40.0
"""Objects are placed within this bearing of the view direction (SynPEB's grid spans +-35 deg)."""

DEFAULT_MAX_OBJECT_DISTANCE = 4.5
"""Farthest horizontal distance (metres) of an object centre from the sensor in :func:`make_room_scene`."""


def make_room_scene(
    seed: int = 0,
    *,
    n_objects: int = DEFAULT_N_OBJECTS,
    room_size: Sequence[float] = DEFAULT_ROOM_SIZE,
    object_kinds: Sequence[str] = _OBJECT_KINDS,
    keep_clear: Sequence[float] | None = None,
    keep_clear_radius: float = 1.0,
    region: Sequence[float] | None = None,
    view_yaw_deg: float | None = None,
    view_half_angle_deg: float = DEFAULT_VIEW_HALF_ANGLE_DEG,
    max_distance: float = DEFAULT_MAX_OBJECT_DISTANCE,
) -> Scene:
    """A room ``[0, sx] x [0, sy] x [0, sz]`` with random, non-overlapping objects.

    Faces are labelled from 10: the 6 room faces first (floor, ceiling, walls), then each object's
    faces. Objects (see :data:`_OBJECT_KINDS`; random sizes and yaw; icosahedra float, everything
    else stands on the floor) are placed by rejection sampling so that their footprint circles do
    not overlap each other, stay inside the room and stay ``keep_clear_radius`` metres away from
    ``keep_clear`` = (x, y) (default: the position of :data:`DEFAULT_SENSOR_POSE`).

    Where: with ``region`` = (x_min, x_max, y_min, y_max) the centres are uniform in that
    rectangle. Without it (the default) they are in the sensor's view, like SynPEB's scans, which
    are filled with objects: bearing (seen from ``keep_clear``) within ``view_half_angle_deg`` of
    ``view_yaw_deg`` (default: the yaw of :data:`DEFAULT_SENSOR_POSE`), horizontal distance uniform up
    to ``max_distance`` metres. An object that finds no place in 200 tries is left out, so fewer
    than ``n_objects`` may appear in a crowded room. Deterministic in ``seed``.
    """
    seed = _check_seed(seed)
    if int(n_objects) != n_objects or n_objects < 0:
        raise ValueError(f'n_objects must be a non-negative integer; got {n_objects}')
    room = _check_size(room_size, 'room')
    kinds = tuple(object_kinds)
    if n_objects > 0 and (not kinds or any(kind not in _OBJECT_KINDS for kind in kinds)):
        raise ValueError(f'object_kinds must be a non-empty subset of {_OBJECT_KINDS}; got {object_kinds}')
    clear_xy = np.asarray(DEFAULT_SENSOR_POSE.position[:2] if keep_clear is None else keep_clear, dtype=np.float64)
    if clear_xy.shape != (2,) or not np.all(np.isfinite(clear_xy)):
        raise ValueError(f'keep_clear must be a finite (x, y) position; got {keep_clear}')
    if region is not None:
        x_min, x_max, y_min, y_max = (float(v) for v in region)
        if not (0.0 <= x_min < x_max <= room[0] and 0.0 <= y_min < y_max <= room[1]):
            raise ValueError(f'region must be (x_min, x_max, y_min, y_max) inside the room {room[:2]}; got {region}')
    view_yaw = DEFAULT_SENSOR_POSE.yaw_deg if view_yaw_deg is None else float(view_yaw_deg)
    if not (math.isfinite(view_yaw) and 0.0 < view_half_angle_deg <= 180.0 and max_distance > 0.0):
        raise ValueError(
            f'need a finite view_yaw_deg, 0 < view_half_angle_deg <= 180 and max_distance > 0; '
            f'got {view_yaw_deg}, {view_half_angle_deg}, {max_distance}'
        )
    rng = np.random.default_rng(seed)
    polygons = room_polygons(room)
    placed: list[tuple[float, float, float]] = []  # (x, y, footprint radius)
    margin = 0.05
    for index in range(int(n_objects)):
        kind = kinds[int(rng.integers(len(kinds)))]
        radius, build = _random_object(kind, rng, room[2])
        yaw = float(rng.uniform(0.0, 360.0))
        low_x, high_x = radius + margin, room[0] - radius - margin
        low_y, high_y = radius + margin, room[1] - radius - margin
        if region is not None:
            low_x, high_x = max(x_min, low_x), min(x_max, high_x)
            low_y, high_y = max(y_min, low_y), min(y_max, high_y)
        nearest = radius + keep_clear_radius
        if low_x >= high_x or low_y >= high_y or (region is None and nearest >= max_distance):
            continue
        for _ in range(200):
            if region is None:
                bearing = math.radians(view_yaw + rng.uniform(-view_half_angle_deg, view_half_angle_deg))
                distance = float(rng.uniform(nearest, max_distance))
                x, y = clear_xy[0] + distance * math.cos(bearing), clear_xy[1] + distance * math.sin(bearing)
                if not (low_x <= x <= high_x and low_y <= y <= high_y):
                    continue
            else:
                x, y = float(rng.uniform(low_x, high_x)), float(rng.uniform(low_y, high_y))
            if math.hypot(x - clear_xy[0], y - clear_xy[1]) < nearest:
                continue
            if all(math.hypot(x - px, y - py) >= radius + pr + 0.1 for px, py, pr in placed):
                placed.append((x, y, radius))
                polygons += build(x, y, yaw, f'{kind}{index}')
                break
    return Scene.from_polygons(
        polygons, room_size=room, description=f'room {room} with {len(placed)} objects, seed {seed}'
    )


def plane_scene(n_planes: int = 3, *, wall_height: float = 4.0) -> Scene:
    """A few large planes meeting at creases: floor z=0, front wall x=4, left wall y=3.

    ``n_planes`` = 1: front wall only; 2: floor and front wall; 3: floor and both walls (a
    corner). Labels 10, 11, 12 in that order (floor first when present). Each face is a large
    rectangle (floor x in [-1, 4], y in [-6, 3]; walls ``wall_height`` m tall).
    """
    if n_planes not in (1, 2, 3):
        raise ValueError(f'n_planes must be 1, 2 or 3; got {n_planes}')
    if not (math.isfinite(wall_height) and wall_height > 0):
        raise ValueError(f'wall_height must be positive; got {wall_height}')
    h = float(wall_height)
    floor = ('floor', np.array([[-1.0, -6.0, 0.0], [4.0, -6.0, 0.0], [4.0, 3.0, 0.0], [-1.0, 3.0, 0.0]]))
    front = ('wall_front', np.array([[4.0, -6.0, 0.0], [4.0, 3.0, 0.0], [4.0, 3.0, h], [4.0, -6.0, h]]))
    left = ('wall_left', np.array([[-1.0, 3.0, 0.0], [-1.0, 3.0, h], [4.0, 3.0, h], [4.0, 3.0, 0.0]]))
    polygons = {1: [front], 2: [floor, front], 3: [floor, front, left]}[n_planes]
    return Scene.from_polygons(polygons, description=f'{n_planes} large plane(s)')


PLANE_SCENE_POSE = SensorPose(position=(0.5, 0.0, 1.2), roll_deg=5.0, pitch_deg=10.0, yaw_deg=25.0)
"""Sensor pose used by :func:`plane_scan`: sees the floor, front wall and left wall of :func:`plane_scene`."""


# --------------------------------------------------------------------------------------------
# Ray casting
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _PackedFaces:
    normals: np.ndarray  # (F, 3)
    offsets: np.ndarray  # (F,)
    edge_normals: np.ndarray  # (F, E, 3) in-plane inward edge normals
    edge_offsets: np.ndarray  # (F, E)
    edge_counts: np.ndarray  # (F,) int64
    centers: np.ndarray  # (F, 3) bounding-sphere centres
    radii: np.ndarray  # (F,)


def _pack_faces(polygons: Sequence[np.ndarray]) -> _PackedFaces:
    count = len(polygons)
    max_edges = max((len(vertices) for vertices in polygons), default=3)
    packed = _PackedFaces(
        normals=np.zeros((count, 3)),
        offsets=np.zeros(count),
        edge_normals=np.zeros((count, max_edges, 3)),
        edge_offsets=np.zeros((count, max_edges)),
        edge_counts=np.zeros(count, dtype=np.int64),
        centers=np.zeros((count, 3)),
        radii=np.zeros(count),
    )
    for index, vertices in enumerate(polygons):
        normal = _newell_normal(vertices)
        centroid = vertices.mean(axis=0)
        packed.normals[index] = normal
        packed.offsets[index] = normal @ centroid
        packed.centers[index] = centroid
        packed.radii[index] = np.linalg.norm(vertices - centroid, axis=1).max() * (1 + 1e-12) + 1e-9
        packed.edge_counts[index] = len(vertices)
        for edge in range(len(vertices)):
            start, end = vertices[edge], vertices[(edge + 1) % len(vertices)]
            inward = np.cross(normal, end - start)
            inward /= np.linalg.norm(inward)
            if inward @ (centroid - start) < 0:
                inward = -inward
            packed.edge_normals[index, edge] = inward
            packed.edge_offsets[index, edge] = inward @ start
    return packed


@njit(cache=True, nogil=True, inline='always')
def _face_hit(
    f,
    ox,
    oy,
    oz,
    dx,
    dy,
    dz,
    best,
    normals,
    offsets,
    edge_normals,
    edge_offsets,
    edge_counts,
    centers,
    radii,
    inside_tolerance,
    min_distance,
):
    """Distance t along the ray (o, d) at which it meets face f inside its polygon, if min_distance < t < best;
    else inf. The face's bounding sphere (centers, radii) is tested first."""
    cx = centers[f, 0] - ox
    cy = centers[f, 1] - oy
    cz = centers[f, 2] - oz
    along = cx * dx + cy * dy + cz * dz
    radius = radii[f]
    if along + radius < 0.0 or along - radius > best:
        return np.inf
    if cx * cx + cy * cy + cz * cz - along * along > radius * radius:
        return np.inf
    nx, ny, nz = normals[f, 0], normals[f, 1], normals[f, 2]
    denominator = nx * dx + ny * dy + nz * dz
    if denominator == 0.0:
        return np.inf
    t = (offsets[f] - (nx * ox + ny * oy + nz * oz)) / denominator
    if not (t > min_distance and t < best):
        return np.inf
    px = ox + t * dx
    py = oy + t * dy
    pz = oz + t * dz
    for e in range(edge_counts[f]):
        value = (edge_normals[f, e, 0] * px + edge_normals[f, e, 1] * py + edge_normals[f, e, 2] * pz) - edge_offsets[
            f, e
        ]
        if value < -inside_tolerance:
            return np.inf
    return t


@njit(cache=True, nogil=True)
def _cast_rays_kernel(
    origins: np.ndarray,
    directions: np.ndarray,
    normals: np.ndarray,
    offsets: np.ndarray,
    edge_normals: np.ndarray,
    edge_offsets: np.ndarray,
    edge_counts: np.ndarray,
    centers: np.ndarray,
    radii: np.ndarray,
    inside_tolerance: float,
    min_distance: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest face hit per ray: (distance along the unit direction or NaN, face index or -1).

    On exactly equal distances the face with the lower index wins.
    """
    n_rays = directions.shape[0]
    n_faces = normals.shape[0]
    distances = np.full(n_rays, np.nan)
    hit_faces = np.full(n_rays, -1, dtype=np.int64)
    for k in range(n_rays):
        ox, oy, oz = origins[k, 0], origins[k, 1], origins[k, 2]
        dx, dy, dz = directions[k, 0], directions[k, 1], directions[k, 2]
        best = np.inf
        best_face = -1
        for f in range(n_faces):
            t = _face_hit(
                f,
                ox,
                oy,
                oz,
                dx,
                dy,
                dz,
                best,
                normals,
                offsets,
                edge_normals,
                edge_offsets,
                edge_counts,
                centers,
                radii,
                inside_tolerance,
                min_distance,
            )
            if t < best:
                best = t
                best_face = f
        if best_face >= 0:
            distances[k] = best
            hit_faces[k] = best_face
    return distances, hit_faces


def cast_rays(scene: Scene, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cast rays against a scene (all in one frame).

    Args:
        scene: the faces.
        origins: ``(N, 3)`` ray starts, metres.
        directions: ``(N, 3)`` unit ray directions.

    Returns:
        ``(distances (N,), labels (N,))``: distance to the nearest face (NaN if none) and that
        face's label (0 if none).
    """
    origins = np.ascontiguousarray(origins, dtype=np.float64)
    directions = np.ascontiguousarray(directions, dtype=np.float64)
    if origins.ndim != 2 or origins.shape[1] != 3 or directions.shape != origins.shape:
        raise ValueError(f'origins and directions must both be (N, 3); got {origins.shape} and {directions.shape}')
    if not (np.all(np.isfinite(origins)) and np.all(np.isfinite(directions))):
        raise ValueError('ray origins and directions must be finite')
    if len(scene.faces) == 0:
        return np.full(len(origins), np.nan), np.zeros(len(origins), dtype=np.int64)
    packed = _pack_faces([face.vertices for face in scene.faces])
    distances, faces = _cast_rays_kernel(
        origins,
        directions,
        packed.normals,
        packed.offsets,
        packed.edge_normals,
        packed.edge_offsets,
        packed.edge_counts,
        packed.centers,
        packed.radii,
        _INSIDE_TOLERANCE,
        _MIN_HIT_DISTANCE,
    )
    labels = np.where(faces >= 0, scene.labels[np.maximum(faces, 0)], 0)
    return distances, labels


# --------------------------------------------------------------------------------------------
# Ground-truth regions (SynPEB conventions)
# --------------------------------------------------------------------------------------------


@njit(cache=True, nogil=True)
def _find_root(parents: np.ndarray, index: int) -> int:
    while parents[index] != index:
        parents[index] = parents[parents[index]]  # path halving
        index = parents[index]
    return index


@njit(cache=True, nogil=True)
def _union(parents: np.ndarray, first: int, second: int) -> None:
    """Join the sets of two pixels; the smaller root becomes the root of both."""
    first = _find_root(parents, first)
    second = _find_root(parents, second)
    if first < second:
        parents[second] = first
    elif second < first:
        parents[first] = second


@njit(cache=True, nogil=True)
def _component_roots_kernel(face_labels: np.ndarray) -> np.ndarray:
    """4-connected components of equal positive labels in an ``(H, W)`` image, by union-find.

    Returns ``(H * W,)`` int64: per pixel (row-major) the row-major index of its component's first
    pixel (the union keeps the smaller root), or -1 where the label is <= 0.
    """
    height, width = face_labels.shape
    parents = np.arange(height * width)
    for row in range(height):
        for col in range(width):
            label = face_labels[row, col]
            if label <= 0:
                continue
            here = row * width + col
            if row > 0 and face_labels[row - 1, col] == label:
                _union(parents, here, here - width)
            if col > 0 and face_labels[row, col - 1] == label:
                _union(parents, here, here - 1)
    roots = np.full(height * width, -1, dtype=np.int64)
    for index in range(height * width):
        if face_labels[index // width, index % width] > 0:
            roots[index] = _find_root(parents, index)
    return roots


def label_regions(
    face_labels: np.ndarray,
    *,
    min_region_pixels: int = DEFAULT_MIN_REGION_PIXELS,
    first_label: int = FIRST_LABEL,
    small_label: int = UNLABELLED_LABEL,
) -> tuple[np.ndarray, dict[int, int]]:
    """Turn a per-pixel face image into SynPEB-style ground truth: one label per 4-connected region.

    Every 4-connected region of pixels with the same positive face label gets its own label, so a
    face seen in separate pieces (a wall above and below a table) gets one label per piece.
    Regions are numbered ``first_label, first_label + 1, ...`` in order of (face label, row-major
    index of the region's first pixel), which keeps the numbering deterministic and keeps the face
    order when every face is one region. Regions with fewer than ``min_region_pixels`` pixels get
    ``small_label`` instead: visible, but not a ground-truth plane (like SynPEB's label 3 pixels).
    Labels <= 0 (no return) stay 0.

    Args:
        face_labels: ``(H, W)`` integer face label per pixel; <= 0 = no face.
        min_region_pixels: smallest region (pixels) that becomes a ground-truth plane, >= 1.
        first_label: label of the first region, > ``small_label``.
        small_label: label of the pixels of too-small regions, >= 1.

    Returns:
        ``(regions, region_faces)``: the ``(H, W)`` int64 label image and, per region label, the
        face label it came from.
    """
    faces = np.asarray(face_labels)
    if faces.ndim != 2 or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f'face_labels must be a 2-D integer array; got {faces.dtype} with shape {faces.shape}')
    for name, value, lowest in (('min_region_pixels', min_region_pixels, 1), ('small_label', small_label, 1)):
        if isinstance(value, bool) or int(value) != value or value < lowest:
            raise ValueError(f'{name} must be an integer >= {lowest}; got {value!r}')
    if isinstance(first_label, bool) or int(first_label) != first_label or first_label <= small_label:
        raise ValueError(f'first_label must be an integer > small_label ({small_label}); got {first_label!r}')
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    roots = _component_roots_kernel(faces)
    flat_faces = faces.reshape(-1)
    regions = np.zeros(faces.size, dtype=np.int64)
    visible = roots >= 0
    if not visible.any():
        return regions.reshape(faces.shape), {}
    first_pixels, component_of_pixel, sizes = np.unique(roots[visible], return_inverse=True, return_counts=True)
    component_faces = flat_faces[first_pixels]
    component_labels = np.full(first_pixels.size, int(small_label), dtype=np.int64)
    order = np.lexsort((first_pixels, component_faces))
    kept = order[sizes[order] >= min_region_pixels]
    component_labels[kept] = int(first_label) + np.arange(kept.size)
    regions[visible] = component_labels[component_of_pixel]
    region_faces = {int(first_label) + rank: int(component_faces[c]) for rank, c in enumerate(kept)}
    return regions.reshape(faces.shape), region_faces


# --------------------------------------------------------------------------------------------
# Scans
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SyntheticScan:
    """A generated organized scan with per-pixel ground truth.

    The ground truth follows SynPEB: ``labels`` numbers the 4-connected regions of visible faces
    (a face seen in two pieces is two regions), regions too small to be planes are
    :data:`UNLABELLED_LABEL`, and ``face_labels`` keeps the face each pixel belongs to.

    Attributes:
        points: ``(H, W, 3)`` float64 measured endpoints in the sensor frame, metres; NaN = no return.
        labels: ``(H, W)`` int64 ground-truth region label per pixel: >= 10 a plane region (one
            4-connected piece of one face), 3 = visible but in a region below the minimum size,
            0 = no return.
        origins: ``(H, W, 3)`` ray starts in the sensor frame when any is non-zero, else None
            (every ray starts at the sensor origin).
        scene: the scene, in the world frame.
        grid: the scan grid.
        params: generation parameters (seed, noise sigmas, max range, sensor pose), JSON-ready.
        sensor_pose: pose of the sensor frame in the world frame.
        true_ranges: ``(H, W)`` noise-free distance along the (jittered) cast ray, NaN = no return.
        face_labels: ``(H, W)`` int64 label of the scene face hit by each ray, 0 = no return
            (None: same as ``labels``).
        region_faces: region label -> face label (empty: region labels are face labels).
    """

    points: np.ndarray
    labels: np.ndarray
    origins: np.ndarray | None
    scene: Scene
    grid: ScanGrid
    params: dict
    sensor_pose: SensorPose = field(default_factory=SensorPose)
    true_ranges: np.ndarray | None = None
    face_labels: np.ndarray | None = None
    region_faces: dict[int, int] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return self.labels.shape

    def ray_starts(self) -> np.ndarray:
        """``(H, W, 3)`` ray starts (zeros when ``origins`` is None)."""
        return np.zeros(self.points.shape) if self.origins is None else self.origins

    def ranges(self) -> np.ndarray:
        """``(H, W)`` measured ray lengths ``|point - origin|`` (NaN = no return), metres."""
        return np.linalg.norm(self.points - self.ray_starts(), axis=-1)

    def label_counts(self) -> dict[int, int]:
        """Pixels per ground-truth plane region (labels >= 10; no-returns and label 3 excluded)."""
        values, counts = np.unique(self.labels[self.labels >= FIRST_LABEL], return_counts=True)
        return {int(v): int(c) for v, c in zip(values, counts, strict=True)}

    def visible_labels(self, min_points: int = 1) -> np.ndarray:
        """Sorted ground-truth region labels with at least ``min_points`` pixels."""
        return np.array(sorted(k for k, v in self.label_counts().items() if v >= min_points), dtype=np.int64)

    def face_of_label(self, label: int) -> Face:
        """The scene face (world frame) of ground-truth region ``label``.

        Raises:
            KeyError: no region has that label.
        """
        if not self.region_faces:
            return self.scene.face(label)
        if label not in self.region_faces:
            known = f'{min(self.region_faces)}..{max(self.region_faces)}'
            raise KeyError(f'no ground-truth region with label {label} in the scan (regions {known})')
        return self.scene.face(self.region_faces[label])

    def plane_of_label(self, label: int) -> tuple[np.ndarray, float]:
        """``(normal, offset)`` of a region's plane in the sensor frame: ``normal . x = offset``.

        The unit normal faces the sensor origin (so ``offset <= 0``), as in ``PlaneSet``.
        """
        face = self.face_of_label(label)
        vertices = self.sensor_pose.world_to_sensor(face.vertices)
        normal = _newell_normal(vertices)
        offset = float(normal @ vertices.mean(axis=0))
        if offset > 0.0:
            normal, offset = -normal, -offset
        return normal, offset


def _check_seed(seed: int) -> int:
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f'seed must be a non-negative integer; got {seed!r}')
    return int(seed)


def _check_sigma(value: float, name: str) -> float:
    value = float(value)
    if not (math.isfinite(value) and value >= 0.0):
        raise ValueError(f'{name} must be a finite value >= 0; got {value}')
    return value


def _check_scan_setup(
    scene: Scene | None,
    seed: int,
    grid: ScanGrid | None,
    sensor_pose: SensorPose | None,
    radial_sigma: float,
    angular_sigma_deg: float,
    max_range: float | None,
    n_objects: int,
    min_region_pixels: int,
) -> tuple[Scene, int, ScanGrid, SensorPose, float, float]:
    """Validated ``(scene, seed, grid, pose, radial_sigma, angular_sigma_deg)`` of :func:`generate_scan`.

    Fills in the defaults; builds the random room (world frame) when ``scene`` is None.
    """
    seed = _check_seed(seed)
    radial_sigma = _check_sigma(radial_sigma, 'radial_sigma')
    angular_sigma_deg = _check_sigma(angular_sigma_deg, 'angular_sigma_deg')
    if max_range is not None and not (float(max_range) > 0.0):
        raise ValueError(f'max_range must be positive (metres) or None; got {max_range}')
    if isinstance(min_region_pixels, bool) or int(min_region_pixels) != min_region_pixels or min_region_pixels < 1:
        raise ValueError(f'min_region_pixels must be an integer >= 1; got {min_region_pixels!r}')
    grid = ScanGrid.synpeb() if grid is None else grid
    if not isinstance(grid, ScanGrid):
        raise ValueError(f'grid must be a ScanGrid; got {type(grid).__name__}')
    pose = DEFAULT_SENSOR_POSE if sensor_pose is None else sensor_pose
    if not isinstance(pose, SensorPose):
        raise ValueError(f'sensor_pose must be a SensorPose; got {type(pose).__name__}')
    if scene is None:
        scene = make_room_scene(seed, n_objects=n_objects, keep_clear=pose.position[:2], view_yaw_deg=pose.yaw_deg)
    elif not isinstance(scene, Scene):
        raise ValueError(f'scene must be a Scene or None; got {type(scene).__name__}')
    return scene, seed, grid, pose, radial_sigma, angular_sigma_deg


def _ray_starts(ray_origins: np.ndarray | None, height: int, width: int) -> np.ndarray:
    """``(H, W, 3)`` ray starts in the sensor frame (metres) from None, ``(3,)`` or ``(H, W, 3)``."""
    if ray_origins is None:
        return np.zeros((height, width, 3))
    starts = np.asarray(ray_origins, dtype=np.float64)
    if starts.shape == (3,):
        starts = np.broadcast_to(starts, (height, width, 3))
    elif starts.shape != (height, width, 3):
        raise ValueError(f'ray_origins must be None, (3,) or {(height, width, 3)}; got shape {starts.shape}')
    if not np.all(np.isfinite(starts)):
        raise ValueError('ray_origins must be finite')
    return np.array(starts)


def _jittered_directions(
    grid: ScanGrid, nominal: np.ndarray, angular_noise: np.ndarray, angular_sigma_deg: float
) -> np.ndarray:
    """``(H, W, 3)`` unit cast directions: the nominal ones jittered in their tangent plane.

    ``angular_noise`` ``(H, W, 2)`` holds standard normal draws along the unit azimuth and
    elevation directions, scaled by ``angular_sigma_deg`` (degrees).
    """
    azimuth = np.radians(grid.azimuth_deg)[None, :]
    elevation = np.radians(grid.elevation_deg)[:, None]
    east = np.stack(np.broadcast_arrays(-np.sin(azimuth), np.cos(azimuth), np.zeros_like(azimuth + elevation)), -1)
    up = np.stack(
        np.broadcast_arrays(
            -np.sin(elevation) * np.cos(azimuth), -np.sin(elevation) * np.sin(azimuth), np.cos(elevation)
        ),
        -1,
    )
    sigma_rad = math.radians(angular_sigma_deg)
    cast_directions = nominal + sigma_rad * (angular_noise[..., :1] * east + angular_noise[..., 1:] * up)
    cast_directions /= np.linalg.norm(cast_directions, axis=-1, keepdims=True)
    return cast_directions


def _cast_in_sensor_frame(
    scene: Scene, pose: SensorPose, starts: np.ndarray, cast_directions: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(H, W)`` hit distances (metres, NaN = no hit) and int64 face labels (0 = no hit).

    Casts in the sensor frame: transforms the faces, not the rays.
    """
    height, width = starts.shape[:2]
    sensor_scene = Scene(
        faces=tuple(
            Face(vertices=pose.world_to_sensor(face.vertices), label=face.label, name=face.name) for face in scene.faces
        )
    )
    distances, labels = cast_rays(sensor_scene, starts.reshape(-1, 3), cast_directions.reshape(-1, 3))
    return distances.reshape(height, width), labels.reshape(height, width).astype(np.int64)


def _measure_ranges(
    distances: np.ndarray,
    labels: np.ndarray,
    radial_noise: np.ndarray,
    radial_sigma: float,
    max_range: float | None,
) -> np.ndarray:
    """The range error model: ``(H, W)`` measured ranges (metres, NaN = no return).

    Hits beyond ``max_range`` become no-returns (in place: their ``distances`` NaN, ``labels`` 0),
    then the radial noise is added; a measured range that is not positive is a no-return too.
    """
    if max_range is not None:
        beyond = distances > float(max_range)
        distances[beyond] = np.nan
        labels[beyond] = 0
    measured = distances + radial_sigma * radial_noise
    negative = ~(measured > 0.0)
    measured[negative] = np.nan
    labels[negative] = 0
    return measured


def generate_scan(
    scene: Scene | None = None,
    *,
    seed: int = 0,
    grid: ScanGrid | None = None,
    sensor_pose: SensorPose | None = None,
    radial_sigma: float = 0.02,
    angular_sigma_deg: float = 0.001,
    ray_origins: np.ndarray | None = None,
    max_range: float | None = None,
    n_objects: int = DEFAULT_N_OBJECTS,
    min_region_pixels: int = DEFAULT_MIN_REGION_PIXELS,
) -> SyntheticScan:
    """Generate an organized scan of ``scene`` (default: ``make_room_scene(seed)``).

    Args:
        scene: faces in the world frame; None builds a random room from ``seed`` with ``n_objects``
            objects, kept clear of the sensor position.
        seed: non-negative integer; the scene (if built) and the noise are deterministic in it.
        grid: scan grid; default SynPEB's 500 x 500 grid.
        sensor_pose: sensor pose in the world frame; default :data:`DEFAULT_SENSOR_POSE`.
        radial_sigma: standard deviation of the range noise, metres.
        angular_sigma_deg: standard deviation of the beam-direction jitter per axis (azimuthal and
            elevational), degrees. The jittered direction is used for casting; the stored point
            uses the nominal direction.
        ray_origins: ray starts in the sensor frame: None (all at the origin), ``(3,)`` or
            ``(H, W, 3)`` metres; see :func:`beam_offset_origins`.
        max_range: rays whose true hit distance exceeds this (metres) are no-returns; None = no limit.
        n_objects: objects in the random room (only when ``scene`` is None).
        min_region_pixels: 4-connected pieces of a face with fewer pixels are labelled
            :data:`UNLABELLED_LABEL` instead of getting a plane label (see :func:`label_regions`).

    Returns:
        The scan; ``origins`` is the ``(H, W, 3)`` array of ray starts if any is non-zero.
    """
    scene, seed, grid, pose, radial_sigma, angular_sigma_deg = _check_scan_setup(
        scene, seed, grid, sensor_pose, radial_sigma, angular_sigma_deg, max_range, n_objects, min_region_pixels
    )
    height, width = grid.shape
    starts = _ray_starts(ray_origins, height, width)

    nominal = grid.directions()
    rng = np.random.default_rng([seed, 1])
    radial_noise = rng.standard_normal((height, width))
    angular_noise = rng.standard_normal((height, width, 2))
    cast_directions = _jittered_directions(grid, nominal, angular_noise, angular_sigma_deg)

    distances, labels = _cast_in_sensor_frame(scene, pose, starts, cast_directions)
    measured = _measure_ranges(distances, labels, radial_noise, radial_sigma, max_range)
    points = starts + nominal * measured[..., None]
    origins = starts if np.any(starts != 0.0) else None
    regions, region_faces = label_regions(labels, min_region_pixels=int(min_region_pixels))
    params = {
        'seed': seed,
        'radial_sigma': radial_sigma,
        'angular_sigma_deg': angular_sigma_deg,
        'max_range': None if max_range is None else float(max_range),
        'sensor_pose': pose.to_dict(),
        'rows': height,
        'cols': width,
        'n_faces': len(scene.faces),
        'min_region_pixels': int(min_region_pixels),
        'n_regions': len(region_faces),
        'scene': scene.description,
    }
    return SyntheticScan(
        points=points,
        labels=regions,
        origins=origins,
        scene=scene,
        grid=grid,
        params=params,
        sensor_pose=pose,
        true_ranges=distances,
        face_labels=labels,
        region_faces=region_faces,
    )


def plane_scan(
    n_planes: int = 3,
    *,
    rows: int = 24,
    cols: int = 32,
    azimuth_fov_deg: float = 60.0,
    elevation_fov_deg: float = 40.0,
    radial_sigma: float = 0.0,
    angular_sigma_deg: float = 0.0,
    seed: int = 0,
    sensor_pose: SensorPose | None = None,
    ray_origins: np.ndarray | None = None,
    min_region_pixels: int = 1,
) -> SyntheticScan:
    """A small scan of :func:`plane_scene` for tests: noise-free by default, every ray hits a plane.

    With the default pose (:data:`PLANE_SCENE_POSE`: 1.2 m high, yaw 25 deg, pitched 10 deg down,
    rolled 5 deg) and field of view, ``n_planes=3`` shows the floor (label 10), the front wall (11)
    and the left wall (12) meeting at two creases and a corner; the sensor's pitch and roll keep the
    vertical crease out of every scan-column plane. ``n_planes=1`` (a wall alone) has no-returns
    below and beside the wall. Use ``radial_sigma=0.02`` for the "20 mm noise" variant. Every
    visible piece of a face is a ground-truth region by default (``min_region_pixels=1``: the grids
    are tiny), and each face of :func:`plane_scene` is one piece, so region labels are face labels.
    """
    grid = ScanGrid.uniform(rows, cols, azimuth_fov_deg=azimuth_fov_deg, elevation_fov_deg=elevation_fov_deg)
    return generate_scan(
        plane_scene(n_planes),
        seed=seed,
        grid=grid,
        sensor_pose=PLANE_SCENE_POSE if sensor_pose is None else sensor_pose,
        radial_sigma=radial_sigma,
        angular_sigma_deg=angular_sigma_deg,
        ray_origins=ray_origins,
        min_region_pixels=min_region_pixels,
    )


def polygon_room_lidar_scan(
    height: int = 128,
    width: int = 1024,
    *,
    sides: int = 28,
    radius: float = 8.0,
    ceiling: float = 2.5,
    floor: float = 1.5,
    noise: float = 0.01,
    no_return_fraction: float = 0.02,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A spinning-lidar scan (sensor at the origin, elevation +22.5..-22.5 deg, full turn) of a
    ``sides``-gon room: walls ``radius`` m from the sensor, ceiling ``ceiling`` m above, floor
    ``floor`` m below. Fast, for node and marker workloads of lidar size.

    Returns:
        ``(points, labels, normals, offsets)``: ``(H, W, 3)`` points in metres with radial noise
        ``noise`` (m) and NaN for the dropped ``no_return_fraction`` of the rays; ``(H, W)`` int32
        true faces (0 = no return, walls 1..sides, then ceiling and floor); ``(sides + 2, 3)``
        unit normals facing the sensor and offsets with ``normal . x = offset``.
    """
    if sides < 3:
        raise ValueError(f'a polygon room needs sides >= 3; got {sides}')
    rng = np.random.default_rng(seed)
    elevation = np.radians(np.linspace(22.5, -22.5, height))[:, None]
    azimuth = np.linspace(0.0, 2 * np.pi, width, endpoint=False)[None, :]
    directions = np.stack(
        np.broadcast_arrays(
            np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)
        ),
        -1,
    )
    angles = (np.arange(sides) + 0.5) * 2 * np.pi / sides
    outward = np.concatenate(
        [np.stack([np.cos(angles), np.sin(angles), np.zeros(sides)], 1), [[0, 0, 1.0], [0, 0, -1.0]]]
    )
    distances = np.concatenate([np.full(sides, float(radius)), [float(ceiling), float(floor)]])
    along = directions @ outward.T
    with np.errstate(divide='ignore'):
        hit = np.where(along > 1e-9, distances / along, np.inf)
    labels = np.argmin(hit, axis=-1).astype(np.int32) + 1
    ranges = hit.min(axis=-1) + rng.normal(0.0, noise, labels.shape)
    points = directions * ranges[..., None]
    dropped = rng.random(labels.shape) < no_return_fraction
    points[dropped] = np.nan
    labels[dropped] = 0
    return points, labels, -outward, -distances
