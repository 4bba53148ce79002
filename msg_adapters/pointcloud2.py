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
    """

    points: NDArray[np.float32]
    has_intensity: bool
    num_input: int
    num_nonfinite: int


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
    data = msg.data
    if isinstance(data, np.ndarray):
        return data.view(np.uint8).reshape(-1)
    return np.frombuffer(data, dtype=np.uint8)


def _check_layout(msg: Any, buf: NDArray[np.uint8]) -> tuple[int, int, int, int]:
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    if height * width == 0:
        return height, width, point_step, row_step
    if point_step <= 0:
        raise PointCloudError(f'point_step is {point_step}; it must be > 0')
    if row_step < width * point_step:
        raise PointCloudError(f'row_step {row_step} is shorter than width * point_step '
                              f'({width} * {point_step})')
    need = row_step * (height - 1) + width * point_step
    if buf.size < need:
        raise PointCloudError(f'data has {buf.size} bytes but height {height} x row_step '
                              f'{row_step} needs {row_step * height}: the cloud is truncated')
    return height, width, point_step, row_step


def pointcloud2_to_array(msg: Any) -> NDArray[Any]:
    """Read-only structured view of a cloud: shape ``(width,)``, or ``(height, width)`` when
    organized (``height > 1``)."""
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


def _field_offsets(msg: Any) -> dict[str, tuple[int, int, int]]:
    return {str(f.name): (int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields}


def pointcloud2_to_xyzi(msg: Any) -> XYZI:
    """The detector's input: ``(N, 4)`` float32 x, y, z, intensity, non-finite points dropped."""
    fields = _field_offsets(msg)
    missing = [n for n in ('x', 'y', 'z') if n not in fields]
    if missing:
        raise PointCloudError(f'cloud has no {"/".join(missing)} field(s); fields are '
                              f'{sorted(fields)}')
    inten_name = next((n for n in INTENSITY_NAMES if n in fields), None)
    names = ['x', 'y', 'z'] + ([inten_name] if inten_name else [])
    buf = _buffer(msg)
    height, width, point_step, row_step = _check_layout(msg, buf)
    n = height * width
    offs = [fields[k][0] for k in names]
    fast = (not msg.is_bigendian and point_step % 4 == 0 and row_step == width * point_step
            and all(fields[k][1] == FLOAT32 and fields[k][2] == 1 for k in names)
            and all(o % 4 == 0 for o in offs))
    if n == 0:
        pts = np.zeros((0, 4), np.float32)
    elif fast:
        words = np.frombuffer(buf, dtype='<f4', count=n * point_step // 4)
        table = words.reshape(n, point_step // 4)
        cols = [o // 4 for o in offs]
        if inten_name is None:
            pts = np.zeros((n, 4), np.float32)
            pts[:, :3] = table[:, cols]
        elif cols == [cols[0], cols[0] + 1, cols[0] + 2, cols[0] + 3]:
            pts = np.ascontiguousarray(table[:, cols[0]:cols[0] + 4])   # one strided copy
        else:
            pts = np.ascontiguousarray(table[:, cols])
        dtype_check_fields(msg, point_step)
    else:
        arr = pointcloud2_to_array(msg).reshape(-1)
        pts = np.zeros((n, 4), np.float32)
        for i, k in enumerate(names):
            col = arr[k]
            if col.ndim > 1:   # count > 1: take the first element
                col = col[:, 0]
            with np.errstate(over='ignore', invalid='ignore'):
                pts[:, i] = col.astype(np.float32)   # out-of-range values become inf
    # x + y + z is non-finite iff a coordinate is (or the sum overflows float32, ~1e38 m)
    with np.errstate(over='ignore', invalid='ignore'):
        total = pts[:, 0] + pts[:, 1]
        total += pts[:, 2]
    finite = np.isfinite(total)
    dropped = int(n - np.count_nonzero(finite))
    if dropped:
        pts = pts[finite]
    if inten_name is not None and not np.isfinite(pts[:, 3].sum(dtype=np.float64)):
        np.nan_to_num(pts[:, 3], copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    return XYZI(pts, inten_name is not None, n, dropped)


def dtype_check_fields(msg: Any, point_step: int) -> None:
    """Validate the field table (overruns, overlaps, datatypes) without building a view."""
    dtype_from_fields(msg.fields, point_step, bool(msg.is_bigendian))


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
    """Build a PointCloud2 from a structured array ``(N,)`` or organized ``(H, W)``."""
    if points.dtype.fields is None:
        raise PointCloudError('array_to_pointcloud2 needs a structured array')
    le = points.dtype.newbyteorder('<')
    arr = np.ascontiguousarray(points.astype(le, copy=False))
    height, width = (arr.shape[0], arr.shape[1]) if arr.ndim == 2 else (1, arr.shape[0])
    fields = fields_from_dtype(le, classes)
    if is_dense is None:
        is_dense = True
        for name in ('x', 'y', 'z'):
            if name in (le.names or ()) and le[name].kind == 'f':
                is_dense = is_dense and bool(np.isfinite(arr[name]).all())
    raw = arr.tobytes()
    data: Any
    if classes.kind == 'rclpy':
        data = array.array('B')
        data.frombytes(raw)
    else:
        data = np.frombuffer(raw, dtype=np.uint8)
    return classes.PointCloud2(header=header, height=height, width=width, fields=fields,
                               is_bigendian=False, point_step=le.itemsize,
                               row_step=le.itemsize * width, data=data, is_dense=is_dense)
