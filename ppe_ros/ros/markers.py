"""RViz markers of finite planes: a mesh of each plane's own grid cells, its outline and its normal.

Geometry (pure numpy, vectorized over all planes at once):

* **Mesh** (``TRIANGLE_LIST``): every 2x2 cell of the (optionally strided) grid whose pixels
  belong to one plane gives two triangles if all 4 corners belong to it and one triangle if
  exactly 3 do. A vertex is the intersection of the pixel's ray (from ``ray_origin`` through the
  measured point) with the fitted plane, so the mesh is the finite plane with its holes, not a
  convex hull. Triangles are wound counter-clockwise seen from the side the plane normal points
  to (the sensor side).
* **Outline** (``LINE_LIST``): the mesh's boundary edges, i.e. edges used by exactly one triangle.
* **Normal** (``ARROW``): from the plane centroid along the unit normal.

The marker array is serialized directly to CDR bytes (see :mod:`ppe_ros.ros.messages`):
``DELETEALL`` first, then per plane its mesh, outline and arrow in the namespaces
:data:`MESH_NAMESPACE`, :data:`OUTLINE_NAMESPACE` and :data:`NORMAL_NAMESPACE` with
``id = plane id``. Every marker header, and the nested texture header, carries the input stamp and
frame_id. All coordinates are metres in the frame of the input cloud.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from ppe_ros.core.planes import PlaneSet
from ppe_ros.core.work_memory import WorkMemory
from ppe_ros.ros.messages import CDR_LE_HEADER, CdrWriter, StampedFrame

MESH_NAMESPACE = 'plane_mesh'
OUTLINE_NAMESPACE = 'plane_outline'
NORMAL_NAMESPACE = 'plane_normal'

# visualization_msgs/Marker constants
ARROW = 0
LINE_LIST = 5
TRIANGLE_LIST = 11
ADD = 0
DELETEALL = 3

#: Rays closer than this cosine to parallel to their plane are projected orthogonally instead of
#: intersected (the intersection would run off to infinity).
GRAZING_COSINE = 1e-3


@dataclass(frozen=True)
class PlaneGeometry:
    """Marker geometry of all planes of one scan, grouped by plane id (1..J in order).

    Attributes:
        triangles: ``(T, 3, 3)`` triangle vertices (m, cloud frame), plane 1's first.
        triangle_counts: ``(J,)`` triangles of each plane.
        segments: ``(S, 2, 3)`` outline segment end points (m), grouped like ``triangles``.
        segment_counts: ``(J,)`` outline segments of each plane.
        areas: ``(J,)`` mesh area of each plane (m^2).
    """

    triangles: np.ndarray
    triangle_counts: np.ndarray
    segments: np.ndarray
    segment_counts: np.ndarray
    areas: np.ndarray

    @property
    def num_planes(self) -> int:
        """Number of planes J."""
        return len(self.triangle_counts)


# --------------------------------------------------------------------------------------------
# numba kernels
# --------------------------------------------------------------------------------------------

# cell kinds (corners a=(r,c) b=(r,c+1) c=(r+1,c) d=(r+1,c+1) of the 2x2 cell at (r, c))
_NO_CELL, _FULL, _MISSING_A, _MISSING_B, _MISSING_C, _MISSING_D = 0, 1, 2, 3, 4, 5


@nb.njit(cache=True, parallel=True)
def _project_vertices(points, labels, normals, offsets, origins, grazing_cosine):
    """``(H, W, 3)``: each labelled pixel's ray (from ``origins[r, c]``) meets its plane here (0 elsewhere)."""
    height, width = labels.shape
    vertices = np.zeros((height, width, 3))
    for r in nb.prange(height):
        for c in range(width):
            label = labels[r, c]
            if label <= 0:
                continue
            j = label - 1
            o0, o1, o2 = origins[r, c, 0], origins[r, c, 1], origins[r, c, 2]
            n0, n1, n2 = normals[j, 0], normals[j, 1], normals[j, 2]
            p0, p1, p2 = points[r, c, 0], points[r, c, 1], points[r, c, 2]
            u0, u1, u2 = p0 - o0, p1 - o1, p2 - o2
            along = n0 * u0 + n1 * u1 + n2 * u2
            length = np.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
            if abs(along) > grazing_cosine * length:
                t = (offsets[j] - (n0 * o0 + n1 * o1 + n2 * o2)) / along
                vertices[r, c, 0] = o0 + t * u0
                vertices[r, c, 1] = o1 + t * u1
                vertices[r, c, 2] = o2 + t * u2
            else:  # grazing ray: orthogonal projection of the measured point
                off = n0 * p0 + n1 * p1 + n2 * p2 - offsets[j]
                vertices[r, c, 0] = p0 - off * n0
                vertices[r, c, 1] = p1 - off * n1
                vertices[r, c, 2] = p2 - off * n2
    return vertices


@nb.njit(cache=True, nogil=True, inline='always')
def _cell(labels, r, c):
    """(plane label, kind) of the cell at (r, c): a plane owning >= 3 of its 4 corners, else (0, 0)."""
    la, lb, lc, ld = labels[r, c], labels[r, c + 1], labels[r + 1, c], labels[r + 1, c + 1]
    if la > 0 and la == lb and la == lc and la == ld:
        return la, _FULL
    if lb > 0 and lb == lc and lb == ld:
        return lb, _MISSING_A
    if la > 0 and la == lc and la == ld:
        return la, _MISSING_B
    if la > 0 and la == lb and la == ld:
        return la, _MISSING_C
    if la > 0 and la == lb and la == lc:
        return la, _MISSING_D
    return 0, _NO_CELL


@nb.njit(cache=True, nogil=True, inline='always')
def _cell_label_at(cell_labels, r, c):
    """Label of cell (r, c), 0 outside the cell grid."""
    if r < 0 or c < 0 or r >= cell_labels.shape[0] or c >= cell_labels.shape[1]:
        return 0
    return cell_labels[r, c]


@nb.njit(cache=True, nogil=True, inline='always')
def _boundary_label(label_0, label_1, cell_label_0, cell_label_1):
    """Plane of a grid side between two pixels if exactly one adjacent cell's triangles use it, else 0."""
    if label_0 <= 0 or label_1 != label_0:
        return 0
    uses = (cell_label_0 == label_0) + (cell_label_1 == label_0)
    return label_0 if uses == 1 else 0


# The fill loops below read and write array elements, never rows: a row (an array view) costs
# numba an atomic reference-count increment and decrement, several per cell.


@nb.njit(cache=True, nogil=True, inline='always')
def _vertex(vertices, r, c):
    """Vertex (r, c) as a 3-tuple."""
    return vertices[r, c, 0], vertices[r, c, 1], vertices[r, c, 2]


@nb.njit(cache=True, nogil=True, inline='always')
def _put_segment(segments, s, vertices, r0, c0, r1, c1):
    """Write the segment from vertex (r0, c0) to vertex (r1, c1) into ``segments[s]``."""
    for k in range(3):
        segments[s, 0, k] = vertices[r0, c0, k]
        segments[s, 1, k] = vertices[r1, c1, k]


@nb.njit(cache=True, nogil=True, inline='always')
def _put_triangle(triangles, areas, slot, normal, label, va, vb, vc):
    """Write triangle (va, vb, vc) (3-tuples) into ``triangles[slot]``, wound counter-clockwise around ``normal``."""
    e10, e11, e12 = vb[0] - va[0], vb[1] - va[1], vb[2] - va[2]
    e20, e21, e22 = vc[0] - va[0], vc[1] - va[1], vc[2] - va[2]
    facing = (
        normal[0] * (e11 * e22 - e12 * e21) + normal[1] * (e12 * e20 - e10 * e22) + normal[2] * (e10 * e21 - e11 * e20)
    )
    first, second = (vb, vc) if facing >= 0.0 else (vc, vb)
    for k in range(3):
        triangles[slot, 0, k] = va[k]
        triangles[slot, 1, k] = first[k]
        triangles[slot, 2, k] = second[k]
    areas[label - 1] += 0.5 * abs(facing)


@nb.njit(cache=True, nogil=True)
def _mesh_kernel(vertices, labels, normals, num_planes):
    """Triangles, outline segments (grouped by plane) and areas of all planes; see plane_geometry."""
    height, width = labels.shape
    cell_labels = np.zeros((height - 1, width - 1), np.int64)
    cell_kinds = np.zeros((height - 1, width - 1), np.int8)
    triangle_counts = np.zeros(num_planes + 1, np.int64)
    segment_counts = np.zeros(num_planes + 1, np.int64)
    # pass 1: classify cells, count triangles and diagonal outline segments
    for r in range(height - 1):
        for c in range(width - 1):
            label, kind = _cell(labels, r, c)
            cell_labels[r, c] = label
            cell_kinds[r, c] = kind
            if kind == _FULL:
                triangle_counts[label] += 2
            elif kind != _NO_CELL:
                triangle_counts[label] += 1
                segment_counts[label] += 1  # the diagonal of a one-triangle cell is a boundary edge
    # side edges used by exactly one cell's triangles are boundary edges
    for r in range(height):
        for c in range(width - 1):  # horizontal edge (r, c)-(r, c+1): cells above and below
            label = _boundary_label(
                labels[r, c], labels[r, c + 1], _cell_label_at(cell_labels, r - 1, c), _cell_label_at(cell_labels, r, c)
            )
            if label > 0:
                segment_counts[label] += 1
    for r in range(height - 1):
        for c in range(width):  # vertical edge (r, c)-(r+1, c): cells left and right
            label = _boundary_label(
                labels[r, c], labels[r + 1, c], _cell_label_at(cell_labels, r, c - 1), _cell_label_at(cell_labels, r, c)
            )
            if label > 0:
                segment_counts[label] += 1
    triangle_next = np.zeros(num_planes + 1, np.int64)
    segment_next = np.zeros(num_planes + 1, np.int64)
    for j in range(1, num_planes + 1):
        triangle_next[j] = triangle_next[j - 1] + triangle_counts[j - 1]
        segment_next[j] = segment_next[j - 1] + segment_counts[j - 1]
    triangles = np.empty((triangle_next[num_planes] + triangle_counts[num_planes], 3, 3))
    segments = np.empty((segment_next[num_planes] + segment_counts[num_planes], 2, 3))
    areas = np.zeros(num_planes)
    # pass 2: fill, in row-major order within each plane
    for r in range(height - 1):
        for c in range(width - 1):
            kind = cell_kinds[r, c]
            if kind == _NO_CELL:
                continue
            label = cell_labels[r, c]
            normal = (normals[label - 1, 0], normals[label - 1, 1], normals[label - 1, 2])
            slot = triangle_next[label]
            a, b = _vertex(vertices, r, c), _vertex(vertices, r, c + 1)
            c_, d = _vertex(vertices, r + 1, c), _vertex(vertices, r + 1, c + 1)
            if kind == _FULL:
                _put_triangle(triangles, areas, slot, normal, label, a, b, d)
                _put_triangle(triangles, areas, slot + 1, normal, label, a, d, c_)
                triangle_next[label] = slot + 2
                continue
            if kind == _MISSING_A:
                _put_triangle(triangles, areas, slot, normal, label, b, d, c_)
            elif kind == _MISSING_B:
                _put_triangle(triangles, areas, slot, normal, label, a, d, c_)
            elif kind == _MISSING_C:
                _put_triangle(triangles, areas, slot, normal, label, a, b, d)
            else:
                _put_triangle(triangles, areas, slot, normal, label, a, b, c_)
            triangle_next[label] = slot + 1
            s = segment_next[label]
            if kind == _MISSING_A or kind == _MISSING_D:  # diagonal b-c
                _put_segment(segments, s, vertices, r, c + 1, r + 1, c)
            else:  # diagonal a-d
                _put_segment(segments, s, vertices, r, c, r + 1, c + 1)
            segment_next[label] = s + 1
    for r in range(height):
        for c in range(width - 1):
            label = _boundary_label(
                labels[r, c], labels[r, c + 1], _cell_label_at(cell_labels, r - 1, c), _cell_label_at(cell_labels, r, c)
            )
            if label > 0:
                s = segment_next[label]
                _put_segment(segments, s, vertices, r, c, r, c + 1)
                segment_next[label] = s + 1
    for r in range(height - 1):
        for c in range(width):
            label = _boundary_label(
                labels[r, c], labels[r + 1, c], _cell_label_at(cell_labels, r, c - 1), _cell_label_at(cell_labels, r, c)
            )
            if label > 0:
                s = segment_next[label]
                _put_segment(segments, s, vertices, r, c, r + 1, c)
                segment_next[label] = s + 1
    return triangles, triangle_counts[1:], segments, segment_counts[1:], areas


# --------------------------------------------------------------------------------------------
# public functions
# --------------------------------------------------------------------------------------------


def plane_geometry(
    points: np.ndarray, planes: PlaneSet, *, ray_origin: np.ndarray | None = None, stride: int = 1
) -> PlaneGeometry:
    """Mesh triangles, outline segments and areas of every plane of an organized scan.

    Args:
        points: ``(H, W, 3)`` measured endpoints (m, cloud frame), NaN = no return.
        planes: the planes of this scan (``planes.labels`` is ``(H, W)``).
        ray_origin: ``(3,)`` start point of every ray, or ``(H, W, 3)`` one per pixel (m, cloud frame);
            default the origin.
        stride: use every ``stride``-th row and column (a coarser mesh, ``stride**2`` fewer triangles).

    Raises:
        ValueError: shapes that do not match, labels outside ``0..J``, a bad ``stride`` or ``ray_origin``.
    """
    points = np.asarray(points, dtype=np.float64)
    labels = np.asarray(planes.labels)
    if points.ndim != 3 or points.shape[2] != 3 or points.shape[:2] != labels.shape:
        raise ValueError(f'points must be (H, W, 3) with the grid of planes.labels {labels.shape}; got {points.shape}')
    if int(stride) != stride or stride < 1:
        raise ValueError(f'stride must be an integer >= 1; got {stride}')
    origin = np.zeros(3) if ray_origin is None else np.asarray(ray_origin, dtype=np.float64)
    if origin.shape not in ((3,), points.shape) or not np.all(np.isfinite(origin)):
        shown = repr(ray_origin) if origin.size <= 3 else f'an array of shape {origin.shape}'
        raise ValueError(f'ray_origin must be a finite (3,) point or one per pixel {points.shape}; got {shown}')
    num_planes = planes.num_planes
    if labels.size and (labels.min() < 0 or labels.max() > num_planes):
        raise ValueError(f'planes.labels must lie in 0..{num_planes}; got {labels.min()}..{labels.max()}')
    stride = int(stride)
    points = np.ascontiguousarray(points[::stride, ::stride])
    labels = np.ascontiguousarray(labels[::stride, ::stride], dtype=np.int64)
    origins = np.ascontiguousarray(
        np.broadcast_to(origin, points.shape) if origin.shape == (3,) else origin[::stride, ::stride]
    )
    height, width = labels.shape
    if num_planes == 0 or height < 2 or width < 2:
        return PlaneGeometry(
            triangles=np.zeros((0, 3, 3)),
            triangle_counts=np.zeros(num_planes, np.int64),
            segments=np.zeros((0, 2, 3)),
            segment_counts=np.zeros(num_planes, np.int64),
            areas=np.zeros(num_planes),
        )
    normals = np.ascontiguousarray(planes.normals, dtype=np.float64)
    offsets = np.ascontiguousarray(planes.offsets, dtype=np.float64)
    vertices = _project_vertices(points, labels, normals, offsets, origins, GRAZING_COSINE)
    triangles, triangle_counts, segments, segment_counts, areas = _mesh_kernel(vertices, labels, normals, num_planes)
    return PlaneGeometry(
        triangles=triangles,
        triangle_counts=triangle_counts,
        segments=segments,
        segment_counts=segment_counts,
        areas=areas,
    )


def budgeted_plane_geometry(
    points: np.ndarray,
    planes: PlaneSet,
    *,
    ray_origin: np.ndarray | None = None,
    stride: int = 1,
    max_triangles: int = 0,
) -> tuple[PlaneGeometry, int]:
    """:func:`plane_geometry` within a mesh budget: ``(geometry, stride used)``.

    The stride starts at ``stride`` and grows until the meshes of all planes together have at most
    ``max_triangles`` triangles (0 = no limit). A stride s keeps about 1/s^2 of the triangles, so
    the next stride tried is ``ceil(s * sqrt(triangles / max_triangles))`` (at least s + 1). The
    triangles are first bounded without building the mesh (at most two per labelled pixel of the
    strided grid), so that a mesh over budget is not built only to be thrown away; at worst the loop
    ends at a stride no smaller than the grid, where no cell (and no triangle) is left.
    """
    if int(max_triangles) != max_triangles or max_triangles < 0:
        raise ValueError(f'max_triangles must be an integer >= 0; got {max_triangles}')

    def next_stride(current: int, triangles: int) -> int:
        return max(current + 1, math.ceil(current * math.sqrt(triangles / max_triangles)))

    def triangle_bound(labels: np.ndarray, current: int) -> int:
        strided = labels[::current, ::current]
        return 0 if min(strided.shape) < 2 else 2 * int(np.count_nonzero(strided > 0))

    labels = np.asarray(planes.labels)
    if max_triangles and labels.ndim == 2:
        while (bound := triangle_bound(labels, stride)) > max_triangles:
            stride = next_stride(stride, bound)
    geometry = plane_geometry(points, planes, ray_origin=ray_origin, stride=stride)
    while max_triangles and len(geometry.triangles) > max_triangles:
        stride = next_stride(stride, len(geometry.triangles))
        geometry = plane_geometry(points, planes, ray_origin=ray_origin, stride=stride)
    return geometry, int(stride)


def rgb_floats(colors: np.ndarray) -> np.ndarray:
    """``(J, 3)`` float r, g, b in [0, 1] of ``0x00RRGGBB`` colours."""
    packed = np.asarray(colors, dtype=np.uint32)
    return np.stack([(packed >> 16) & 0xFF, (packed >> 8) & 0xFF, packed & 0xFF], axis=-1) / 255.0


def arrow_lengths(areas: np.ndarray) -> np.ndarray:
    """Normal-arrow length per plane (m): half the side of a square of the mesh area, in [0.1, 1]."""
    return np.clip(0.5 * np.sqrt(np.asarray(areas, dtype=np.float64)), 0.1, 1.0)


def _write_marker_tail(writer: CdrWriter, stamped: StampedFrame) -> None:
    """The fields of a Marker after ``points[]``: all empty, except the texture's header."""
    writer.uint32(0)  # colors[]
    writer.string('')  # texture_resource
    writer.header(stamped)  # texture: sensor_msgs/CompressedImage
    writer.string('')  # texture.format
    writer.uint32(0)  # texture.data[]
    writer.uint32(0)  # uv_coordinates[]
    writer.string('')  # text
    writer.string('')  # mesh_resource
    writer.string('')  # mesh_file.filename
    writer.uint32(0)  # mesh_file.data[]
    writer.boolean(False)  # mesh_use_embedded_materials


def _write_marker(
    writer: CdrWriter,
    stamped: StampedFrame,
    *,
    ns: str,
    marker_id: int,
    marker_type: int,
    action: int,
    scale: tuple[float, float, float],
    rgba: tuple[float, float, float, float],
    points: np.ndarray | None,
) -> None:
    """One ``visualization_msgs/Marker`` (identity pose, lifetime 0 = until replaced), field by field."""
    writer.header(stamped)
    writer.string(ns)
    writer.int32(marker_id)
    writer.int32(marker_type)
    writer.int32(action)
    writer.float64s(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)  # pose: position, orientation (x y z w)
    writer.float64s(*scale)
    writer.float32s(*rgba)
    writer.int32(0)  # lifetime.sec
    writer.uint32(0)  # lifetime.nanosec
    writer.boolean(False)  # frame_locked
    count = 0 if points is None else len(points)
    writer.uint32(count)  # points[]
    if count:
        writer.float64_block(points)
    _write_marker_tail(writer, stamped)


class _MarkerEncoder:
    """Serializes the planes' ADD markers (thousands per frame) in one numba kernel.

    Everything after a marker's vertices is the same bytes for every marker of the frame, because a
    vertex block (24 bytes per point) starts and ends 8-byte aligned. Produces exactly the bytes of
    :func:`_write_marker`. Chunks collect here and go to the writer in :meth:`flush`.
    """

    def __init__(self, writer: CdrWriter, stamped: StampedFrame) -> None:
        self._writer = writer
        self._size = writer.size
        self._chunks: list[bytes | memoryview] = []
        self._head = (stamped.sec, stamped.nanosec, stamped.frame_id.encode('utf-8') + b'\x00')
        tail = CdrWriter()
        _write_marker_tail(tail, stamped)
        self._tail = tail.getvalue()[len(CDR_LE_HEADER) :]

    def write_planes(
        self,
        namespaces: tuple[bytes, bytes, bytes],
        rgb: np.ndarray,
        alphas: tuple[float, float],
        line_width: float,
        lengths: np.ndarray,
        blocks: tuple[np.ndarray, np.ndarray, np.ndarray],
        ends: tuple[np.ndarray, np.ndarray],
    ) -> None:
        """Per plane j (id j + 1): its mesh if it has triangles, its outline if it has segments, its
        arrow; each byte for byte what :func:`_write_marker` writes for an ADD marker, written by one
        numba kernel (:func:`_plane_markers_kernel`; thousands of markers per frame)."""
        mesh_ns, outline_ns, normal_ns = (np.frombuffer(ns, np.uint8) for ns in namespaces)
        triangle_bytes, segment_bytes, arrow_bytes = blocks
        triangle_ends, segment_ends = ends
        sec, nanosec, frame_id = self._head
        tail = np.frombuffer(self._tail, np.uint8)
        # the fixed fields, the strings and all padding of a marker take less than 200 bytes more than its strings
        per_marker = 200 + len(frame_id) + max(len(mesh_ns), len(outline_ns), len(normal_ns)) + len(tail)
        bound = 3 * len(lengths) * per_marker + sum(len(block) for block in blocks)
        # work memory: fresh memory would cost a page fault per 4 KiB (the bytes are joined before the next call)
        out = _work_memory.array('markers', bound, np.uint8)
        breaks = _work_memory.array('marker_breaks', 4 * (2 * len(lengths) + 1), np.int64).reshape(-1, 4)
        used, n_breaks = _plane_markers_kernel(
            out,
            breaks,
            self._size,
            sec,
            nanosec,
            np.frombuffer(frame_id, np.uint8),
            mesh_ns,
            outline_ns,
            normal_ns,
            tail,
            np.ascontiguousarray(rgb, dtype=np.float64),
            float(alphas[0]),
            float(alphas[1]),
            float(line_width),
            np.ascontiguousarray(lengths, dtype=np.float64),
            triangle_bytes,
            segment_bytes,
            arrow_bytes,
            np.ascontiguousarray(triangle_ends, dtype=np.int64),
            np.ascontiguousarray(segment_ends, dtype=np.int64),
        )
        # the bytes between large vertex blocks, and the blocks themselves without a copy
        view, block_views, written = memoryview(out), (memoryview(triangle_bytes), memoryview(segment_bytes)), 0
        for pos, which, first, stop in breaks[:n_breaks].tolist():
            self._chunks += (view[written:pos], block_views[which][first:stop])
            self._size += pos - written + stop - first
            written = pos
        self._chunks.append(view[written:used])
        self._size += used - written

    def flush(self) -> None:
        """Hand the collected chunks to the writer."""
        self._writer.raw(*self._chunks)
        self._chunks = []


def _byte_view(values: np.ndarray) -> np.ndarray:
    """The bytes of ``values`` as little-endian float64 (a uint8 array), without a copy when already so."""
    return np.ascontiguousarray(values, dtype='<f8').reshape(-1).view(np.uint8)


#: The marker bytes' buffer, one per thread (the markers of a 128 x 1024 sweep take up to about 20 MB).
_work_memory = WorkMemory()


# The plane markers in one kernel. CDR aligns every primitive to its size counted from the start of the
# payload (after the 4-byte encapsulation header): ``size`` is the payload's length before the first
# marker, so a field at buffer position pos is aligned when (size + pos) is. The message is little-endian
# (CDR_LE_HEADER): integers are written byte by byte, the pose, scale and colour as the host's float bytes,
# which are little-endian on every platform ROS 2 runs on (x86-64, arm64).


@nb.njit(cache=True, nogil=True, inline='always')
def _pad(out, pos, size, alignment):
    """Zero bytes up to the next multiple of ``alignment`` of the payload offset; the new position."""
    while (size + pos) % alignment:
        out[pos] = 0
        pos += 1
    return pos


@nb.njit(cache=True, nogil=True, inline='always')
def _put_u32(out, pos, value):
    """The low 32 bits of the integer ``value``, little-endian (two's complement for a negative one)."""
    value = np.int64(value)
    for k in range(4):
        out[pos + k] = (value >> (8 * k)) & 0xFF
    return pos + 4


@nb.njit(cache=True, nogil=True, inline='always')
def _put_bytes(out, pos, data, first, stop):
    out[pos : pos + stop - first] = data[first:stop]
    return pos + stop - first


@nb.njit(cache=True, nogil=True)
def _marker_head(out, pos, size, sec, nanosec, frame_id, ns, marker_id, marker_type, doubles, floats, count):
    """An ADD marker up to its points (lifetime 0, not frame-locked, ``count`` points), aligned for the
    8-byte vertex block that follows: doubles (10,) the pose (identity) and the scale, floats (4,) float32
    the colour; the new position."""
    pos = _pad(out, pos, size, 4)
    pos = _put_u32(out, pos, sec)
    pos = _put_u32(out, pos, nanosec)
    pos = _put_u32(out, pos, len(frame_id))
    pos = _put_bytes(out, pos, frame_id, 0, len(frame_id))
    pos = _pad(out, pos, size, 4)
    pos = _put_u32(out, pos, len(ns))
    pos = _put_bytes(out, pos, ns, 0, len(ns))
    pos = _pad(out, pos, size, 4)
    pos = _put_u32(out, pos, marker_id)
    pos = _put_u32(out, pos, marker_type)
    pos = _put_u32(out, pos, ADD)
    pos = _pad(out, pos, size, 8)
    pos = _put_bytes(out, pos, doubles.view(np.uint8), 0, 80)
    pos = _put_bytes(out, pos, floats.view(np.uint8), 0, 16)
    pos = _put_u32(out, pos, 0)  # lifetime.sec
    pos = _put_u32(out, pos, 0)  # lifetime.nanosec
    out[pos] = 0  # frame_locked
    pos = _pad(out, pos + 1, size, 4)
    pos = _put_u32(out, pos, count)
    return _pad(out, pos, size, 8)


#: Vertex blocks of at least this many bytes stay where they are (a chunk of their own) instead of being copied.
_LARGE_BLOCK = 4096


@nb.njit(cache=True, nogil=True)
def _plane_markers_kernel(
    out,
    breaks,
    size,
    sec,
    nanosec,
    frame_id,
    mesh_ns,
    outline_ns,
    normal_ns,
    tail,
    rgb,
    mesh_alpha,
    line_alpha,
    line_width,
    lengths,
    triangle_bytes,
    segment_bytes,
    arrow_bytes,
    triangle_ends,
    segment_ends,
):
    """The CDR bytes of every plane's markers (see :meth:`_MarkerEncoder.write_planes`) into out (long enough),
    the payload being ``size`` bytes long before them, except the mesh and outline vertex blocks of
    _LARGE_BLOCK bytes or more: each is a row (position in out, 0 triangles / 1 segments, first, stop byte)
    of breaks, to be put at that position. Returns (bytes written, rows of breaks). A vertex block's length
    is a multiple of 8, so leaving one out does not change any later field's alignment."""
    n = len(lengths)
    pos = 0
    n_breaks = 0
    doubles = np.zeros(10)  # pose (x y z, qx qy qz qw), scale
    doubles[6] = 1.0
    floats = np.empty(4, np.float32)
    for j in range(n):
        floats[0], floats[1], floats[2] = rgb[j, 0], rgb[j, 1], rgb[j, 2]
        for kind in range(3):
            if kind == 0:
                first, stop, block, ns, marker_type = (
                    triangle_ends[j],
                    triangle_ends[j + 1],
                    triangle_bytes,
                    mesh_ns,
                    TRIANGLE_LIST,
                )
                doubles[7], doubles[8], doubles[9], floats[3] = 1.0, 1.0, 1.0, mesh_alpha
            elif kind == 1:
                first, stop, block, ns, marker_type = (
                    segment_ends[j],
                    segment_ends[j + 1],
                    segment_bytes,
                    outline_ns,
                    LINE_LIST,
                )
                doubles[7], doubles[8], doubles[9], floats[3] = line_width, 1.0, 1.0, line_alpha
            else:
                first, stop, block, ns, marker_type = 48 * j, 48 * j + 48, arrow_bytes, normal_ns, ARROW
                doubles[7], doubles[8], doubles[9], floats[3] = (
                    0.1 * lengths[j],
                    0.2 * lengths[j],
                    0.3 * lengths[j],
                    line_alpha,
                )
            if stop == first:
                continue  # a plane without triangles has no mesh and no outline
            pos = _marker_head(
                out, pos, size, sec, nanosec, frame_id, ns, j + 1, marker_type, doubles, floats, (stop - first) // 24
            )
            if kind < 2 and stop - first >= _LARGE_BLOCK:
                breaks[n_breaks, 0], breaks[n_breaks, 1], breaks[n_breaks, 2], breaks[n_breaks, 3] = (
                    pos,
                    kind,
                    first,
                    stop,
                )
                n_breaks += 1
            else:
                pos = _put_bytes(out, pos, block, first, stop)
            pos = _put_bytes(out, pos, tail, 0, len(tail))
    return pos, n_breaks


def marker_array_cdr(
    geometry: PlaneGeometry,
    planes: PlaneSet,
    stamped: StampedFrame,
    *,
    colors: np.ndarray,
    mesh_alpha: float = 0.5,
    line_width: float = 0.02,
) -> bytes:
    """Serialize the markers of all planes to a CDR ``visualization_msgs/msg/MarkerArray``.

    Args:
        geometry: from :func:`plane_geometry`.
        planes: the same planes (centroids and normals for the arrows).
        stamped: stamp and frame_id of the input cloud, written into every header.
        colors: ``(J,)`` ``0x00RRGGBB`` colour of each plane (the labelled cloud's colours).
        mesh_alpha: opacity of the meshes in [0, 1]; outlines and arrows are opaque.
        line_width: outline width (m).

    Markers: ``DELETEALL``; then per plane ``j`` its mesh (if it has triangles), its outline (if it
    has boundary edges) and its normal arrow, each with ``id = j``.
    """
    num_planes = planes.num_planes
    if geometry.num_planes != num_planes or len(colors) != num_planes:
        raise ValueError(
            f'geometry ({geometry.num_planes}), colors ({len(colors)}) and planes ({num_planes}) '
            'must describe the same planes'
        )
    if not 0.0 <= mesh_alpha <= 1.0:
        raise ValueError(f'mesh_alpha must lie in [0, 1]; got {mesh_alpha}')
    rgb = rgb_floats(colors)
    lengths = arrow_lengths(geometry.areas)
    arrows = np.stack([planes.centroids, planes.centroids + lengths[:, None] * planes.normals], axis=1)
    triangle_bytes = _byte_view(geometry.triangles)
    segment_bytes = _byte_view(geometry.segments)
    arrow_bytes = _byte_view(arrows)  # (J, 2, 3): centroid, tip
    triangle_ends = 72 * np.concatenate([[0], np.cumsum(geometry.triangle_counts)]).astype(np.int64)
    segment_ends = 48 * np.concatenate([[0], np.cumsum(geometry.segment_counts)]).astype(np.int64)
    markers_per_plane = (geometry.triangle_counts > 0).astype(int) + (geometry.segment_counts > 0) + 1
    writer = CdrWriter()
    writer.uint32(1 + int(markers_per_plane.sum()))
    _write_marker(
        writer,
        stamped,
        ns='',
        marker_id=0,
        marker_type=ARROW,
        action=DELETEALL,
        scale=(1.0, 1.0, 1.0),
        rgba=(0.0, 0.0, 0.0, 0.0),
        points=None,
    )
    encoder = _MarkerEncoder(writer, stamped)
    mesh_ns, outline_ns, normal_ns = (
        ns.encode() + b'\x00' for ns in (MESH_NAMESPACE, OUTLINE_NAMESPACE, NORMAL_NAMESPACE)
    )
    encoder.write_planes(
        (mesh_ns, outline_ns, normal_ns),
        rgb,
        (float(mesh_alpha), 1.0),
        float(line_width),
        lengths,
        (triangle_bytes, segment_bytes, arrow_bytes),
        (triangle_ends, segment_ends),
    )
    encoder.flush()
    return writer.getvalue()
