"""``sensor_msgs/PointCloud2`` <-> numpy, for rclpy messages and rosbags messages alike.

Nothing here imports rclpy or rosbags: the functions work on any object with the PointCloud2
attributes (``header, height, width, fields, is_bigendian, point_step, row_step, data, is_dense``)
and build messages from the classes they are given. One code path serves both flavours:

* reading: a numpy structured dtype is built from ``msg.fields`` (name, offset, datatype, count),
  with ``itemsize = point_step`` and the byte order of ``is_bigendian``, and laid over ``msg.data``
  (an ``array.array('B')`` in rclpy, a numpy uint8 array in rosbags) with strides
  ``(row_step, point_step)``, so padding inside points and at row ends is skipped without copying.
* writing: the structured array is serialized with one ``tobytes()``; rclpy gets an
  ``array.array('B')`` filled with ``frombytes`` (assigning a numpy array or memoryview to an rclpy
  ``uint8[]`` field checks every element: 100-600 ms for a 640x480 cloud), rosbags a numpy uint8 array.

Layout: ``height`` is the number of rows and ``width`` the number of columns; point (row, col)
starts at byte ``row * row_step + col * point_step``. ``height == 1`` is an unorganized cloud.
"""

from __future__ import annotations

import array
import dataclasses
from typing import Any

import numpy as np

from ppe_ros.core.colors import UNLABELLED_COLOR, label_colors  # noqa: F401  (re-exported: the outputs' colours)

#: sensor_msgs/PointField datatype constants -> numpy type (without byte order).
POINTFIELD_DATATYPES: dict[int, str] = {
    1: 'i1',  # INT8
    2: 'u1',  # UINT8
    3: 'i2',  # INT16
    4: 'u2',  # UINT16
    5: 'i4',  # INT32
    6: 'u4',  # UINT32
    7: 'f4',  # FLOAT32
    8: 'f8',  # FLOAT64
}
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)

_NUMPY_TO_DATATYPE: dict[str, int] = {code: datatype for datatype, code in POINTFIELD_DATATYPES.items()}

#: The largest ``point_step`` read (numpy's limit on the size of one record: 2**31 - 1 bytes).
MAX_POINT_STEP = 2**31 - 1


class PointCloudError(ValueError):
    """A PointCloud2 message that cannot be read as described by its own fields and sizes."""


# --------------------------------------------------------------------------------------------
# PointCloud2 -> numpy
# --------------------------------------------------------------------------------------------


def message_bytes(data: Any) -> np.ndarray:
    """A message's ``data`` (bytes, ``array.array``, numpy array or list) as a 1-D uint8 array without copying
    when possible."""
    if isinstance(data, np.ndarray):
        return np.ascontiguousarray(data).view(np.uint8).reshape(-1)
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except (TypeError, ValueError):
        return np.asarray(data, dtype=np.uint8).reshape(-1)


def pointcloud2_dtype(msg: Any) -> np.dtype:
    """Structured dtype of one point of ``msg``: its fields at their offsets, itemsize ``point_step``.

    Raises:
        PointCloudError: point_step 0, unsupported datatype, count < 1, duplicate names, or a field
            that extends beyond point_step.
    """
    point_step = int(msg.point_step)
    if point_step <= 0:
        raise PointCloudError(f'point_step is {point_step}; it must be the positive size of one point in bytes')
    if point_step > MAX_POINT_STEP:
        raise PointCloudError(f'point_step is {point_step}; at most {MAX_POINT_STEP} bytes per point are supported')
    order = '>' if msg.is_bigendian else '<'
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    for field in msg.fields:
        name = str(field.name)
        datatype = int(field.datatype)
        count = int(field.count)
        offset = int(field.offset)
        if datatype not in POINTFIELD_DATATYPES:
            raise PointCloudError(
                f'field {name!r} has unsupported datatype {datatype} '
                f'(sensor_msgs/PointField defines 1 INT8 .. 8 FLOAT64)'
            )
        if count < 1:
            # count 0 occurs in the wild for "no value"; such a field holds no bytes: skip it
            continue
        if name in names:
            raise PointCloudError(f'field {name!r} appears twice in msg.fields')
        base = np.dtype(order + POINTFIELD_DATATYPES[datatype])
        end = offset + base.itemsize * count
        if offset < 0 or end > point_step:
            raise PointCloudError(
                f'field {name!r} (offset {offset}, {count} x {base.itemsize} bytes) extends to byte {end}, '
                f'beyond point_step {point_step}'
            )
        names.append(name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(offset)
    try:
        return np.dtype({'names': names, 'formats': formats, 'offsets': offsets, 'itemsize': point_step})
    except (ValueError, TypeError) as exc:  # e.g. a field name numpy does not take
        raise PointCloudError(f'fields {names} at offsets {offsets} do not form a point layout: {exc}') from None


def pointcloud2_to_structured(msg: Any, *, allow_empty: bool = False) -> np.ndarray:
    """All fields of ``msg`` as a read-only structured array of shape ``(height, width)``.

    The array is a view on ``msg.data`` (no copy); copy it before modifying.

    Args:
        msg: a PointCloud2 message of any flavour.
        allow_empty: return an empty array for ``height == 0`` or ``width == 0`` (e.g. a plane table
            of a frame without planes) instead of raising.

    Raises:
        PointCloudError: empty cloud (unless allowed), inconsistent sizes (say expected vs actual),
            bad fields.
    """
    height = int(msg.height)
    width = int(msg.width)
    if height < 0 or width < 0:
        raise PointCloudError(f'negative size: height {height}, width {width}')
    if not allow_empty and (height == 0 or width == 0):
        raise PointCloudError(f'empty cloud: height {height}, width {width}')
    dtype = pointcloud2_dtype(msg)
    if height == 0 or width == 0:
        size = message_bytes(msg.data).size
        if size != 0:
            raise PointCloudError(f'data has {size} bytes, expected 0 for a cloud of height {height}, width {width}')
        return np.zeros((height, width), dtype=dtype)
    point_step = dtype.itemsize
    row_step = int(msg.row_step)
    if row_step < width * point_step:
        raise PointCloudError(
            f'row_step {row_step} is smaller than width × point_step = {width} × {point_step} = {width * point_step}'
        )
    raw = message_bytes(msg.data)
    expected = row_step * height
    if raw.size != expected:
        raise PointCloudError(
            f'data has {raw.size} bytes, expected row_step × height = {row_step} × {height} = {expected}'
        )
    view = np.ndarray(shape=(height, width), dtype=dtype, buffer=raw, offset=0, strides=(row_step, point_step))
    view.flags.writeable = False
    return view


def is_organized(msg: Any) -> bool:
    """True if the cloud is a 2-D grid (``height > 1``); ``height == 1`` means an unordered list."""
    return int(msg.height) > 1


def pointcloud2_to_xyz(msg: Any, *, require_organized: bool = False, zero_is_no_return: bool = False) -> np.ndarray:
    """The x, y, z fields of ``msg`` as an ``(height, width, 3)`` float64 array (NaN = no return).

    A point with any non-finite coordinate becomes all NaN. x, y, z must share one datatype
    (float32 or float64 in practice; integer types are converted as they are).

    Args:
        msg: a PointCloud2 message of any flavour (rclpy, rosbags or an equivalent object).
        require_organized: raise if the cloud is unorganized (``height == 1``).
        zero_is_no_return: a point at exactly (0, 0, 0) becomes all NaN too (many drivers, Ouster's
            among them, publish that for a pixel without a return; the file loaders do the same).

    Raises:
        PointCloudError: see :func:`pointcloud2_to_structured`; missing x/y/z; x/y/z of different
            types or with count != 1; unorganized cloud when ``require_organized``.
    """
    if require_organized and not is_organized(msg):
        raise PointCloudError(
            f'the cloud is not organized (height {int(msg.height)}, width {int(msg.width)}): '
            f'plane extraction needs an organized cloud (height > 1 rows of width columns)'
        )
    cloud = pointcloud2_to_structured(msg)
    names = cloud.dtype.names
    missing = [axis for axis in 'xyz' if axis not in names]
    if missing:
        present = ', '.join(names) or 'none'
        raise PointCloudError(f'the cloud has no {"/".join(missing)} field (fields: {present})')
    by_name = {str(f.name): f for f in msg.fields if int(f.count) >= 1}  # the fields the dtype holds
    datatypes = {axis: int(by_name[axis].datatype) for axis in 'xyz'}
    if len(set(datatypes.values())) != 1:
        described = ', '.join(f'{axis} {datatype}' for axis, datatype in datatypes.items())
        raise PointCloudError(f'x, y, z must have the same datatype; found {described}')
    for axis in 'xyz':
        if cloud.dtype[axis].shape != ():
            raise PointCloudError(f'field {axis!r} has count {int(by_name[axis].count)}; expected 1')
    xyz = np.empty((*cloud.shape, 3), dtype=np.float64)
    with np.errstate(invalid='ignore'):  # a signalling NaN (e.g. bytes of the wrong byte order) warns
        for index, axis in enumerate('xyz'):
            xyz[..., index] = cloud[axis]
    # a sum is non-finite exactly when a term is (inf - inf is NaN; only coordinates beyond 1e307 m
    # could overflow it); a sum over the small last axis, or isfinite(xyz).all(axis=2), costs ten
    # times more on a 128 x 1024 cloud
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    with np.errstate(invalid='ignore', over='ignore'):
        invalid = ~np.isfinite(x + y + z)
    if zero_is_no_return:
        invalid |= (x == 0.0) & (y == 0.0) & (z == 0.0)
    # only points that are not all NaN already need writing
    partial = invalid & ~(np.isnan(x) & np.isnan(y) & np.isnan(z))
    if partial.any():
        xyz[partial] = np.nan
    return xyz


#: Fields that give each point's beam, in the order they are looked for: ``ring`` (Velodyne, Ouster,
#: Hesai, RoboSense) and ``line`` (Livox: its laser line, which does not make rows of a grid).
BEAM_FIELDS: tuple[str, ...] = ('ring', 'line')


def pointcloud2_field(msg: Any, name: str) -> np.ndarray | None:
    """Field ``name`` of ``msg`` as an ``(height, width)`` array in native byte order, or None if the
    cloud has no such field with count 1.

    Raises:
        PointCloudError: see :func:`pointcloud2_to_structured`.
    """
    cloud = pointcloud2_to_structured(msg)
    if name not in (cloud.dtype.names or ()) or cloud.dtype[name].shape != ():
        return None
    base = cloud.dtype[name]
    with np.errstate(invalid='ignore'):
        return np.asarray(cloud[name]).astype(base.newbyteorder('='))


def pointcloud2_beams(msg: Any) -> tuple[np.ndarray | None, str | None]:
    """The first of :data:`BEAM_FIELDS` that ``msg`` has, as ``(height, width)`` values, and its name;
    ``(None, None)`` without one."""
    for name in BEAM_FIELDS:
        values = pointcloud2_field(msg, name)
        if values is not None:
            return values, name
    return None, None


# --------------------------------------------------------------------------------------------
# numpy -> PointCloud2
# --------------------------------------------------------------------------------------------


def _byte_buffer(msg_class: type, payload: bytes) -> Any:
    """``data`` value for a message class: numpy uint8 for dataclasses (rosbags), array('B') otherwise."""
    if dataclasses.is_dataclass(msg_class):
        return np.frombuffer(payload, dtype=np.uint8).copy()
    buffer = array.array('B')
    buffer.frombytes(payload)
    return buffer


def structured_to_pointcloud2(
    cloud: np.ndarray,
    *,
    header: Any,
    msg_class: type,
    field_class: type,
    datatypes: dict[str, int] | None = None,
    is_dense: bool | None = None,
) -> Any:
    """A PointCloud2 holding a structured array: one message field per array field.

    Args:
        cloud: structured array of shape ``(height, width)`` (organized) or ``(n,)`` (sent as
            height 1, width n). Field types: int8..uint32, float32, float64; a sub-array field
            ``(type, (k,))`` becomes a field of count k. Offsets and itemsize are kept as they are.
        header: the message header (a ``std_msgs/Header`` of the same flavour as ``msg_class``).
        msg_class, field_class: ``PointCloud2`` and ``PointField`` classes (rclpy or rosbags).
        datatypes: field name -> PointField datatype to declare instead of the one of its numpy
            type (same size), e.g. ``{'rgb': FLOAT32}`` for colours stored as uint32.
        is_dense: default True unless an x, y or z value is non-finite.

    Raises:
        ValueError: not a structured array, unsupported field types, bad datatype overrides.
    """
    table = np.asarray(cloud)
    if table.dtype.names is None:
        raise ValueError(f'cloud must be a structured numpy array with named fields; got dtype {table.dtype}')
    if table.ndim == 1:
        table = table.reshape(1, -1)
    if table.ndim != 2:
        raise ValueError(f'cloud must have shape (height, width) or (n,); got {table.shape}')
    height, width = table.shape
    overrides = dict(datatypes or {})
    unknown = set(overrides) - set(table.dtype.names)
    if unknown:
        raise ValueError(f'datatypes names fields that the cloud does not have: {sorted(unknown)}')
    fields = []
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    for name in table.dtype.names:
        field_dtype, offset = table.dtype.fields[name][:2]
        base = field_dtype.base
        count = int(np.prod(field_dtype.shape)) if field_dtype.shape else 1
        code = f'{base.kind}{base.itemsize}'
        if code not in _NUMPY_TO_DATATYPE:
            raise ValueError(
                f'field {name!r} has dtype {base}, which PointCloud2 cannot carry '
                f'(int8..int32, uint8..uint32, float32, float64)'
            )
        datatype = _NUMPY_TO_DATATYPE[code]
        if name in overrides:
            declared = int(overrides[name])
            if declared not in POINTFIELD_DATATYPES:
                raise ValueError(f'datatypes[{name!r}] = {declared} is not a PointField datatype (1..8)')
            if np.dtype(POINTFIELD_DATATYPES[declared]).itemsize != base.itemsize:
                raise ValueError(f'datatypes[{name!r}] = {declared} has another size than the field dtype {base}')
            datatype = declared
        fields.append(field_class(name=name, offset=int(offset), datatype=datatype, count=count))
        names.append(name)
        little_base = base.newbyteorder('<')
        formats.append(little_base if field_dtype.shape == () else (little_base, field_dtype.shape))
        offsets.append(int(offset))
    little = np.dtype({'names': names, 'formats': formats, 'offsets': offsets, 'itemsize': table.dtype.itemsize})
    payload = np.ascontiguousarray(table.astype(little, copy=False)).tobytes()
    if is_dense is None:
        is_dense = True
        for axis in 'xyz':
            if axis in table.dtype.names and np.issubdtype(table.dtype[axis].base, np.floating):
                if not np.all(np.isfinite(table[axis])):
                    is_dense = False
    point_step = table.dtype.itemsize
    return msg_class(
        header=header,
        height=height,
        width=width,
        fields=fields,
        is_bigendian=False,
        point_step=point_step,
        row_step=point_step * width,
        data=_byte_buffer(msg_class, payload),
        is_dense=bool(is_dense),
    )


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """``(..., 3)`` uint8 colours -> ``(...)`` uint32 ``0x00RRGGBB``."""
    colours = np.asarray(rgb)
    if colours.shape[-1:] != (3,):
        raise ValueError(f'rgb colours must have a last axis of 3 (r, g, b); got shape {colours.shape}')
    channels = colours.astype(np.uint32)
    return (channels[..., 0] << 16) | (channels[..., 1] << 8) | channels[..., 2]


def xyz_to_pointcloud2(
    points: np.ndarray,
    *,
    header: Any,
    msg_class: type,
    field_class: type,
    labels: np.ndarray | None = None,
    rgb: np.ndarray | None = None,
) -> Any:
    """An organized PointCloud2 with fields ``x y z`` (float32) [``label`` (uint32)] [``rgb``].

    Args:
        points: ``(H, W, 3)`` (or ``(N, 3)``, sent as height 1) coordinates in metres; NaN = no return.
        header: the message header of the same flavour as ``msg_class``.
        msg_class, field_class: ``PointCloud2`` and ``PointField`` classes (rclpy or rosbags).
        labels: ``(H, W)`` integer labels in 0 .. 2**32 - 1, field ``label`` (UINT32).
        rgb: ``(H, W)`` uint32 ``0x00RRGGBB`` or ``(H, W, 3)`` uint8, field ``rgb`` declared FLOAT32
            (the uint32 bits reinterpreted, as PCL and RViz expect).

    Returns:
        A ``msg_class`` instance; ``is_dense`` is False when any coordinate is NaN.
    """
    cloud = np.asarray(points)
    if cloud.ndim == 2 and cloud.shape[1] == 3:
        cloud = cloud.reshape(1, -1, 3)
    if cloud.ndim != 3 or cloud.shape[2] != 3:
        raise ValueError(f'points must be an (H, W, 3) or (N, 3) array; got shape {cloud.shape}')
    if not np.issubdtype(cloud.dtype, np.number):
        raise ValueError(f'points must be numeric; got dtype {cloud.dtype}')
    grid = cloud.shape[:2]
    layout: list[tuple[str, Any]] = [('x', '<f4'), ('y', '<f4'), ('z', '<f4')]
    label_values = None
    rgb_values = None
    if labels is not None:
        label_values = np.asarray(labels)
        if label_values.size == grid[0] * grid[1] and label_values.ndim == 1 and grid[0] == 1:
            label_values = label_values.reshape(grid)
        if label_values.shape != grid:
            raise ValueError(f'labels must have shape {grid} like the points grid; got {label_values.shape}')
        if not np.issubdtype(label_values.dtype, np.integer):
            raise ValueError(f'labels must be integers; got dtype {label_values.dtype}')
        if label_values.size and (label_values.min() < 0 or label_values.max() > np.iinfo(np.uint32).max):
            raise ValueError(
                f'labels must lie in 0 .. 2**32 - 1 (uint32); found {label_values.min()} .. {label_values.max()}'
            )
        layout.append(('label', '<u4'))
    if rgb is not None:
        rgb_values = np.asarray(rgb)
        if rgb_values.shape == (*grid, 3):
            rgb_values = pack_rgb(rgb_values)
        if rgb_values.shape != grid or not np.issubdtype(rgb_values.dtype, np.integer):
            raise ValueError(
                f'rgb must be {grid} uint32 0x00RRGGBB or {(*grid, 3)} uint8; got {rgb_values.shape} {rgb_values.dtype}'
            )
        layout.append(('rgb', '<u4'))
    table = np.empty(grid, dtype=np.dtype(layout))
    with np.errstate(over='ignore', invalid='ignore'):  # beyond float32's 3.4e38 m: inf, as a cast gives
        table['x'] = cloud[..., 0]
        table['y'] = cloud[..., 1]
        table['z'] = cloud[..., 2]
    if label_values is not None:
        table['label'] = label_values
    if rgb_values is not None:
        table['rgb'] = rgb_values
    return structured_to_pointcloud2(
        table,
        header=header,
        msg_class=msg_class,
        field_class=field_class,
        datatypes={'rgb': FLOAT32} if rgb_values is not None else None,
    )


# --------------------------------------------------------------------------------------------
# colours
# --------------------------------------------------------------------------------------------
