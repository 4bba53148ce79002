"""sensor_msgs/PointCloud2 <-> numpy, for rclpy and rosbags messages alike.

Reading builds a structured dtype from the message's fields (every datatype, ``count > 1``,
offsets, padding, ``point_step``, ``row_step``, big-endian) and returns a read-only, zero-copy
view of the message's buffer: the message is never modified. ``pointcloud2_to_xyzi`` is the
detector's fast path.
"""
from __future__ import annotations

import array
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .classes import MessageClasses
from .errors import PointCloudError

# sensor_msgs/PointField datatypes
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
DATATYPES: dict[int, str] = {INT8: 'i1', UINT8: 'u1', INT16: 'i2', UINT16: 'u2', INT32: 'i4',
                             UINT32: 'u4', FLOAT32: 'f4', FLOAT64: 'f8'}
KINDS: dict[tuple[str, int], int] = {('i', 1): INT8, ('u', 1): UINT8, ('i', 2): INT16,
                                     ('u', 2): UINT16, ('i', 4): INT32, ('u', 4): UINT32,
                                     ('f', 4): FLOAT32, ('f', 8): FLOAT64}
INTENSITY_NAMES = ('intensity', 'i', 'reflectivity')


@dataclass
class XYZI:
    """The detector's input from a cloud.

    :param points: ``(N, 4)`` float32 C-contiguous ``x, y, z, intensity`` (finite x/y/z only).
    :param has_intensity: False when the cloud had no intensity field (column 3 is then 0).
    :param num_input: points in the message; ``num_nonfinite``: dropped for NaN/Inf x/y/z.
    :param times: with a ``time_field``: each kept point's time field as stored (its rows),
        None when none was asked for or found; ``time_field``: the field read ('' none).
    """

    points: NDArray[np.float32]
    has_intensity: bool
    num_input: int
    num_nonfinite: int
    times: NDArray[Any] | None = None
    time_field: str = ''


def dtype_from_fields(fields: Any, point_step: int, is_bigendian: bool) -> np.dtype[Any]:
    """Structured dtype (offsets honoured, itemsize ``point_step``) of PointField entries."""
    order = '>' if is_bigendian else '<'
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    spans: list[tuple[int, int, str]] = []
    for f in fields:
        name = str(f.name)
        datatype, count, offset = int(f.datatype), int(f.count), int(f.offset)
        if datatype not in DATATYPES:
            raise PointCloudError(f'field {name!r} has unknown datatype {datatype} '
                                  '(PointField datatypes are 1..8)')
        if count < 1:
            raise PointCloudError(f'field {name!r} has count {count}; it must be >= 1')
        if name in names:
            raise PointCloudError(f'field {name!r} appears twice')
        size = int(DATATYPES[datatype][1]) * count
        if offset < 0 or offset + size > point_step:
            raise PointCloudError(f'field {name!r} (offset {offset}, {size} bytes) overruns '
                                  f'point_step {point_step}')
        spans.append((offset, offset + size, name))
        fmt = order + DATATYPES[datatype]
        names.append(name)
        formats.append(fmt if count == 1 else (fmt, (count,)))
        offsets.append(offset)
    spans.sort()
    for (_, a1, an), (b0, _, bn) in zip(spans, spans[1:]):
        if b0 < a1:
            raise PointCloudError(f'fields {an!r} and {bn!r} overlap (bytes {b0}..{a1})')
    return np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                     'itemsize': point_step})


def _buffer(msg: Any) -> NDArray[np.uint8]:
    """The message's bytes as a uint8 array, zero-copy (array.array, ndarray, bytes)."""
    data = msg.data
    if isinstance(data, np.ndarray):
        return data.view(np.uint8).reshape(-1)
    return np.frombuffer(data, dtype=np.uint8)


def _check_layout(msg: Any, buf: NDArray[np.uint8]) -> tuple[int, int, int, int]:
    """``(height, width, point_step, row_step)`` after checking them against the data size."""
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    if height < 0 or width < 0:
        raise PointCloudError(f'height {height} / width {width} must not be negative')
    if height * width == 0:
        return height, width, point_step, row_step
    if point_step <= 0:
        raise PointCloudError(f'point_step is {point_step}; it must be > 0')
    if row_step < width * point_step:
        raise PointCloudError(f'row_step {row_step} is shorter than width * point_step '
                              f'({width} * {point_step} = {width * point_step})')
    if buf.size < row_step * height:
        raise PointCloudError(f'data has {buf.size} bytes but height {height} x row_step '
                              f'{row_step} needs {row_step * height}: the cloud is truncated')
    return height, width, point_step, row_step


def pointcloud2_to_array(msg: Any) -> NDArray[Any]:
    """Read-only structured view of a cloud (no copy; the message is not modified).

    :param msg: a sensor_msgs/PointCloud2 (rclpy or rosbags).
    :return: shape ``(width,)``, or ``(height, width)`` when organized (``height > 1``); the
        dtype has the message's fields at their offsets, itemsize ``point_step``.
    :raises PointCloudError: for an invalid field table or data shorter than the layout.
    """
    dtype = dtype_from_fields(msg.fields, int(msg.point_step), bool(msg.is_bigendian))
    buf = _buffer(msg)
    height, width, point_step, row_step = _check_layout(msg, buf)
    if height * width == 0:
        out: NDArray[Any] = np.zeros((height, width) if height > 1 else (width,), dtype)
        return out
    arr: NDArray[Any] = np.ndarray(shape=(height, width), dtype=dtype, buffer=buf,
                                   strides=(row_step, point_step))
    arr.flags.writeable = False
    return arr if height > 1 else arr[0]


def _grid(buffer: Any, dtype: str, offset: int, height: int, width: int, row_stride: int,
          item_stride: int) -> NDArray[Any]:
    """A ``(height, width)`` strided view of ``dtype`` items in ``buffer`` (no copy)."""
    view: NDArray[Any] = np.ndarray((height, width), dtype=dtype, buffer=buffer, offset=offset,
                                    strides=(row_stride, item_stride))
    return view


def _finite_rows(x: NDArray[Any], y: NDArray[Any], z: NDArray[Any]) -> NDArray[np.bool_]:
    """True where x, y and z are all finite (same shape as the inputs)."""
    finite: NDArray[np.bool_] = np.isfinite(x)
    finite &= np.isfinite(y)
    finite &= np.isfinite(z)
    return finite


def _xyzi_float32(buf: NDArray[np.uint8], offsets: list[int], height: int, width: int,
                  point_step: int, row_step: int, bigendian: bool
                  ) -> tuple[NDArray[np.float32], int, NDArray[np.bool_]]:
    """FLOAT32 fields at ``offsets`` (x, y, z[, intensity]) -> ``((N', 4) float32, dropped,
    the kept rows as a (height, width) mask)``.

    The finite mask is computed on strided views of the message, then the kept points are
    copied once into a new array: when the fields are adjacent (as every driver writes them)
    each point's 12 or 16 bytes move as one opaque item, otherwise one column at a time.
    """
    order = '>' if bigendian else '<'
    x, y, z = (_grid(buf, order + 'f4', o, height, width, row_step, point_step)
               for o in offsets[:3])
    finite = _finite_rows(x, y, z)
    kept = int(np.count_nonzero(finite))
    k = len(offsets)
    out: NDArray[np.float32]
    if offsets == [offsets[0] + 4 * i for i in range(k)]:
        block = _grid(buf, f'V{4 * k}', offsets[0], height, width, row_step, point_step)
        if k == 4:
            out = block[finite].view(np.float32).reshape(kept, 4)
        else:
            out = np.zeros((kept, 4), np.float32)
            _grid(out, 'V12', 0, 1, kept, 16 * kept, 16)[0] = block[finite]
        if bigendian:
            out.byteswap(inplace=True)         # our own copy: the message stays as it was
    else:
        out = np.zeros((kept, 4), np.float32)
        for i, offset in enumerate(offsets):
            column = x if i == 0 else y if i == 1 else z if i == 2 else _grid(
                buf, order + 'f4', offset, height, width, row_step, point_step)
            out[:, i] = column[finite]
    return out, height * width - kept, finite


def _convert_fields(msg: Any, names: list[str]
                    ) -> tuple[NDArray[np.float32], int, NDArray[np.bool_]]:
    """Fields of any numeric datatype (``count > 1``: the first element) -> like
    :func:`_xyzi_float32`."""
    arr = pointcloud2_to_array(msg).reshape(-1)
    pts = np.zeros((len(arr), 4), np.float32)
    for i, name in enumerate(names):
        col = arr[name]
        if col.ndim > 1:
            col = col[:, 0]
        with np.errstate(over='ignore', invalid='ignore'):
            pts[:, i] = col                   # float64 beyond float32's range becomes inf
    finite = _finite_rows(pts[:, 0], pts[:, 1], pts[:, 2])
    kept = int(np.count_nonzero(finite))
    if kept < len(pts):
        pts = pts.view('V16').reshape(-1)[finite].view(np.float32).reshape(kept, 4)
    return pts, len(arr) - kept, finite


def _time_column(msg: Any, buf: NDArray[np.uint8], spec: tuple[int, int, int], height: int,
                 width: int, point_step: int, row_step: int, kept: NDArray[np.bool_]
                 ) -> NDArray[Any]:
    """A time field's values (``spec``: offset, datatype, count; the first element) at the
    rows the points kept (``kept``: the converter's finite mask), as a new array."""
    order = '>' if msg.is_bigendian else '<'
    col = _grid(buf, order + DATATYPES[spec[1]], spec[0], height, width, row_step, point_step)
    return np.array(col.reshape(-1)[kept.reshape(-1)])


def pointcloud2_to_xyzi(msg: Any, intensity_field: str = '',
                        time_fields: tuple[str, ...] = ()) -> XYZI:
    """The detector's input: ``(N, 4)`` float32 x, y, z, intensity, non-finite points dropped.

    Intensity comes from a field named ``intensity``, ``i`` or ``reflectivity`` (0 and
    ``has_intensity=False`` when there is none; a non-finite intensity becomes 0). Fields of any
    numeric datatype are converted; the common FLOAT32 layout takes a fast path.

    :param msg: a sensor_msgs/PointCloud2 (rclpy or rosbags); never modified.
    :param intensity_field: ``''``: the first of the usual names; ``'none'``: ignore intensity
        (all 0); any other name: that field, which must exist.
    :param time_fields: the per-point time fields to look for, first found read into
        ``times`` (the points' rows, the field's own type: :func:`suit_ros.deskew.relative_times`
        makes seconds of it).
    :return: :class:`XYZI` with ``points (N, 4)`` float32 C-contiguous.
    :raises PointCloudError: missing x/y/z, an invalid field table, or truncated data.
    """
    fields = {str(f.name): (int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields}
    if not fields and int(msg.height) * int(msg.width) == 0 and len(msg.data) == 0:
        # a default-constructed cloud: what some filters publish when nothing is left
        return XYZI(np.zeros((0, 4), np.float32), False, 0, 0, None, '')
    missing = [n for n in ('x', 'y', 'z') if n not in fields]
    if missing:
        raise PointCloudError(f'cloud has no {"/".join(missing)} field(s); fields are '
                              f'{sorted(fields)}: x, y and z are required')
    if intensity_field == 'none':
        intensity = None
    elif intensity_field:
        if intensity_field not in fields:
            raise PointCloudError(f'cloud has no {intensity_field!r} field (intensity_field); '
                                  f'fields are {sorted(fields)}')
        intensity = intensity_field
    else:
        intensity = next((n for n in INTENSITY_NAMES if n in fields), None)
    names = ['x', 'y', 'z'] + ([intensity] if intensity else [])
    buf = _buffer(msg)
    height, width, point_step, row_step = _check_layout(msg, buf)
    dtype_from_fields(msg.fields, point_step, bool(msg.is_bigendian))     # validates the table
    n = height * width
    time_field = next((f for f in time_fields if f in fields), '')
    if n == 0:
        empty = (np.zeros(0, DATATYPES[fields[time_field][1]]) if time_field else None)
        return XYZI(np.zeros((0, 4), np.float32), intensity is not None, 0, 0, empty,
                    time_field)
    if all(fields[k][1] == FLOAT32 and fields[k][2] == 1 for k in names):
        pts, dropped, finite = _xyzi_float32(buf, [fields[k][0] for k in names], height,
                                             width, point_step, row_step,
                                             bool(msg.is_bigendian))
    else:
        pts, dropped, finite = _convert_fields(msg, names)
    if intensity is not None and not np.isfinite(pts[:, 3].sum(dtype=np.float64)):
        np.nan_to_num(pts[:, 3], copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    times = (_time_column(msg, buf, fields[time_field], height, width, point_step, row_step,
                          finite) if time_field else None)
    return XYZI(pts, intensity is not None, n, dropped, times, time_field)


def fields_from_dtype(dtype: np.dtype[Any], classes: MessageClasses) -> list[Any]:
    """PointField entries describing a structured dtype (little-endian)."""
    out = []
    if dtype.fields is None:
        raise PointCloudError('array_to_pointcloud2 needs a structured array')
    for name, spec in dtype.fields.items():
        ftype, offset = spec[0], spec[1]
        count = 1
        if ftype.subdtype is not None:
            base, shape = ftype.subdtype
            count = int(np.prod(shape))
            ftype = base
        key = (ftype.kind, ftype.itemsize)
        if key not in KINDS:
            raise PointCloudError(f'field {name!r} has dtype {ftype}, which PointField '
                                  'cannot describe')
        out.append(classes.PointField(name=name, offset=int(offset), datatype=KINDS[key],
                                      count=count))
    return out


def array_to_pointcloud2(points: NDArray[Any], header: Any, classes: MessageClasses,
                         is_dense: bool | None = None) -> Any:
    """Build a PointCloud2 from a structured array (the inverse of pointcloud2_to_array).

    :param points: structured array ``(N,)`` or organized ``(H, W)``; any byte order (the
        message is little-endian), padding and offsets kept, ``point_step`` = itemsize.
    :param header: the std_msgs/Header to put on the message (of ``classes``).
    :param classes: which message classes to build (rclpy or rosbags).
    :param is_dense: default: True iff every float x/y/z value is finite.
    :return: a PointCloud2 owning a copy of the data (``array.array('B')`` for rclpy, a uint8
        ndarray for rosbags).
    """
    if points.dtype.fields is None:
        raise PointCloudError('array_to_pointcloud2 needs a structured array, got dtype '
                              f'{points.dtype}')
    if points.ndim not in (1, 2):
        raise PointCloudError(f'points must be (N,) or (H, W), got shape {points.shape}')
    le = points.dtype.newbyteorder('<')
    arr = np.ascontiguousarray(points.astype(le, copy=False))
    height, width = (arr.shape[0], arr.shape[1]) if arr.ndim == 2 else (1, arr.shape[0])
    fields = fields_from_dtype(le, classes)
    if is_dense is None:
        is_dense = True
        for name in ('x', 'y', 'z'):
            if name in (le.names or ()) and le[name].kind == 'f':
                is_dense = is_dense and bool(np.isfinite(arr[name]).all())
    raw = arr.reshape(-1).view(np.uint8)       # (N * point_step,) bytes, no copy
    common = {'header': header, 'height': height, 'width': width, 'fields': fields,
              'is_bigendian': False, 'point_step': le.itemsize,
              'row_step': le.itemsize * width, 'is_dense': is_dense}
    if classes.kind != 'rclpy':
        # own the bytes: a caller changing ``points`` later must not change the message
        data = raw.copy() if np.may_share_memory(raw, points) else raw
        return classes.PointCloud2(data=data, **common)
    msg = classes.PointCloud2(**common)
    buffer = array.array('B')
    buffer.frombytes(raw.data)                  # one memcpy
    if '_data' in getattr(type(msg), '__slots__', ()):
        msg._data = buffer                      # the generated setter would copy it again
    else:
        msg.data = buffer
    return msg
