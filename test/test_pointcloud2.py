"""PointCloud2 adapters: round trips (rclpy and rosbags classes, CDR), properties, edge cases."""
from __future__ import annotations

import array
import math
import struct

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import PointCloud2

from suit_ros.msg_adapters.classes import MessageClasses
from suit_ros.msg_adapters.errors import PointCloudError
from suit_ros.msg_adapters.pointcloud2 import (
    DATATYPES,
    FLOAT32,
    FLOAT64,
    UINT16,
    array_to_pointcloud2,
    dtype_from_fields,
    pointcloud2_to_array,
    pointcloud2_to_xyzi,
)

STORE = get_typestore(Stores.ROS2_JAZZY)
RCLPY = MessageClasses.from_rclpy()
ROSBAGS = MessageClasses.from_rosbags(STORE)
BOTH = [RCLPY, ROSBAGS]
KIND = {'ids': lambda c: c.kind}
DRIVER = np.dtype({'names': ['x', 'y', 'z', 'intensity', 'time', 'ring'],
                   'formats': ['<f4', '<f4', '<f4', '<f4', '<f4', '<u2'],
                   'offsets': [0, 4, 8, 12, 16, 20], 'itemsize': 24})
STRUCT = {1: 'b', 2: 'B', 3: 'h', 4: 'H', 5: 'i', 6: 'I', 7: 'f', 8: 'd'}
XYZ = [('x', 0, FLOAT32, 1), ('y', 4, FLOAT32, 1), ('z', 8, FLOAT32, 1)]


def driver_cloud(n: int, seed: int = 0, dtype: np.dtype = DRIVER) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = np.zeros(n, dtype)
    for k in ('x', 'y', 'z'):
        a[k] = rng.uniform(-50, 50, n)
    a['intensity'] = rng.uniform(0, 255, n)
    a['ring'] = rng.integers(0, 32, n)
    a['time'] = rng.uniform(0, 0.1, n)
    return a


def raw_cloud(C, fields, point_step, width, height, data, bigendian=False, row_step=None):
    """A PointCloud2 of ``C`` around raw bytes, built without the adapters."""
    pf = [C.PointField(name=n, offset=o, datatype=d, count=c) for n, o, d, c in fields]
    if C.kind == 'rclpy':
        buf = array.array('B')
        buf.frombytes(bytes(data))
    else:
        buf = np.frombuffer(bytes(data), np.uint8)
    return C.PointCloud2(header=C.header(5, 'lidar'), height=height, width=width, fields=pf,
                         is_bigendian=bigendian, point_step=point_step,
                         row_step=row_step if row_step is not None else point_step * width,
                         data=buf, is_dense=False)


def assert_same_cloud(got, want):
    """Field by field (structured comparisons do not treat NaN == NaN)."""
    assert got.dtype == want.dtype and got.shape == want.shape
    for k in want.dtype.names:
        np.testing.assert_array_equal(got[k], want[k])


def struct_decode(data, fields, point_step, row_step, width, height, big):
    """Independent decode: one dict of tuples per point, read with ``struct``."""
    order = '>' if big else '<'
    out = []
    for r in range(height):
        for c in range(width):
            base = r * row_step + c * point_step
            out.append({name: struct.unpack_from(order + STRUCT[dt] * cnt, data, base + off)
                        for name, off, dt, cnt in fields})
    return out


@pytest.mark.parametrize('C', BOTH, **KIND)
def test_round_trip_structured(C):
    a = driver_cloud(1000)
    msg = array_to_pointcloud2(a, C.header(123, 'lidar'), C)
    assert msg.point_step == 24 and msg.width == 1000 and msg.height == 1
    assert msg.row_step == 24 * 1000 and not msg.is_bigendian and msg.is_dense
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ('x', 0, 7, 1), ('y', 4, 7, 1), ('z', 8, 7, 1), ('intensity', 12, 7, 1),
        ('time', 16, 7, 1), ('ring', 20, 4, 1)]
    if C.kind == 'rclpy':
        assert isinstance(msg.data, array.array) and msg.data.typecode == 'B'
    back = pointcloud2_to_array(msg)
    assert back.dtype == a.dtype
    np.testing.assert_array_equal(back, a)
    assert not back.flags.writeable            # the message cannot be modified through it
    assert np.shares_memory(back, np.frombuffer(msg.data, np.uint8))        # zero-copy


@pytest.mark.parametrize('C', BOTH, **KIND)
def test_written_message_owns_its_data(C):
    a = driver_cloud(50)
    msg = array_to_pointcloud2(a, C.header(1, 'lidar'), C)
    a['x'] = 1e6                                # the caller reuses its array
    assert np.abs(pointcloud2_to_array(msg)['x']).max() <= 50


@pytest.mark.parametrize('C', BOTH, **KIND)
def test_round_trip_organized_subarray_big_endian_input(C):
    dt = np.dtype({'names': ['x', 'y', 'z', 'rgb', 'normal'],
                   'formats': ['>f4', '>f4', '>f4', 'u1', ('>f8', (3,))],
                   'offsets': [0, 4, 8, 13, 16], 'itemsize': 48})
    rng = np.random.default_rng(7)
    a = np.zeros((3, 5), dt)
    for k in ('x', 'y', 'z'):
        a[k] = rng.normal(size=(3, 5))
    a['rgb'] = rng.integers(0, 255, (3, 5))
    a['normal'] = rng.normal(size=(3, 5, 3))
    msg = array_to_pointcloud2(a, C.header(2, 'cam'), C)
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (3, 5, 48, 240)
    assert not msg.is_bigendian
    assert [(f.name, f.datatype, f.count) for f in msg.fields][-1] == ('normal', FLOAT64, 3)
    back = pointcloud2_to_array(msg)
    assert back.shape == (3, 5)
    for k in dt.names:
        np.testing.assert_array_equal(back[k], a[k])
        assert back[k].dtype.byteorder in '<=|'


@pytest.mark.parametrize('C', BOTH, **KIND)
def test_xyzi_fast_path_drops_nonfinite(C):
    a = driver_cloud(500)
    a['x'][[3, 7]] = np.nan
    a['z'][11] = np.inf
    a['y'][13] = -np.inf
    a['intensity'][20] = np.nan                 # kept, intensity 0
    msg = array_to_pointcloud2(a, C.header(1, 'lidar'), C)
    assert not msg.is_dense
    out = pointcloud2_to_xyzi(msg)
    keep = np.ones(500, bool)
    keep[[3, 7, 11, 13]] = False
    assert out.num_input == 500 and out.num_nonfinite == 4 and out.has_intensity
    assert out.points.dtype == np.float32 and out.points.flags.c_contiguous
    assert out.points.flags.writeable and not np.shares_memory(
        out.points, np.frombuffer(msg.data, np.uint8))
    expect = np.stack([a['x'], a['y'], a['z'], a['intensity']], 1)[keep]
    expect[np.isnan(expect)] = 0.0
    np.testing.assert_array_equal(out.points, expect)


def test_xyzi_same_result_for_every_layout_and_type():
    """Fast path (adjacent, scattered, packed-unaligned FLOAT32) and the conversion path
    (FLOAT64, INT16 fields) give the same points."""
    rng = np.random.default_rng(3)
    vals = rng.integers(-300, 300, (64, 4)).astype(np.float64)
    vals[5, 1] = np.nan
    expect = vals[np.isfinite(vals).all(1)].astype(np.float32)
    layouts = [
        (['<f4'] * 4, [0, 4, 8, 12], 16),       # adjacent
        (['<f4'] * 4, [12, 0, 24, 4], 28),      # scattered, out of order
        (['<f4'] * 4, [1, 5, 9, 13], 19),       # unaligned, odd point_step
        (['>f4'] * 4, [0, 4, 8, 12], 18),       # big-endian
        (['>f4'] * 4, [8, 20, 0, 14], 24),      # big-endian, scattered
        (['<f8'] * 4, [0, 8, 16, 24], 32),      # converted
        (['<f8', '<f8', '<f8', '<u2'], [0, 8, 16, 24], 26),
    ]
    for formats, offsets, step in layouts:
        v = vals.copy()
        if formats[3] == '<u2':
            v[:, 3] = np.abs(v[:, 3])
        dt = np.dtype({'names': ['x', 'y', 'z', 'intensity'], 'formats': formats,
                       'offsets': offsets, 'itemsize': step})
        a = np.zeros(len(v), dt)
        for i, k in enumerate(dt.names):
            a[k] = v[:, i]
        big = formats[0].startswith('>')
        fields = [(k, o, {'f4': FLOAT32, 'f8': FLOAT64, 'u2': UINT16}[f[1:]], 1)
                  for k, o, f in zip(dt.names, offsets, formats)]
        msg = raw_cloud(ROSBAGS, fields, step, len(a), 1, a.tobytes(), bigendian=big)
        out = pointcloud2_to_xyzi(msg)
        want = expect.copy()
        if formats[3] == '<u2':
            want[:, 3] = np.abs(want[:, 3])
        np.testing.assert_array_equal(out.points, want, err_msg=str(formats + offsets))
        assert out.num_nonfinite == 1


def test_cdr_round_trip_rclpy_and_rosbags():
    a = driver_cloud(300, 1)
    a['y'][4] = np.nan
    m = array_to_pointcloud2(a, RCLPY.header(9_000_000_123, 'lidar'), RCLPY)
    as_rosbags = STORE.deserialize_cdr(serialize_message(m), 'sensor_msgs/msg/PointCloud2')
    assert_same_cloud(pointcloud2_to_array(as_rosbags), a)
    np.testing.assert_array_equal(pointcloud2_to_xyzi(as_rosbags).points,
                                  pointcloud2_to_xyzi(m).points)
    assert as_rosbags.header.stamp.sec == 9 and as_rosbags.header.stamp.nanosec == 123
    m2 = array_to_pointcloud2(a, ROSBAGS.header(9, 'lidar'), ROSBAGS)
    as_rclpy = deserialize_message(bytes(STORE.serialize_cdr(m2, 'sensor_msgs/msg/PointCloud2')),
                                   PointCloud2)
    assert_same_cloud(pointcloud2_to_array(as_rclpy), a)
    assert as_rclpy.header.frame_id == 'lidar'
    # both writers produce the same payload and layout (the CDR padding bytes rclpy writes
    # are uninitialised, so whole messages are not compared byte for byte)
    assert bytes(m.data) == m2.data.tobytes() == bytes(as_rosbags.data)
    assert [(f.name, f.offset, f.datatype, f.count) for f in as_rclpy.fields] == [
        (f.name, f.offset, f.datatype, f.count) for f in m.fields]


def test_cdr_round_trip_organized_with_row_padding():
    H, W = 2, 3
    rows = [b''.join(struct.pack('<fffH', r, c, r + c, 7 * c) + b'\0\0' for c in range(W))
            + b'\xab' * 4 for r in range(H)]
    fields = XYZ + [('ring', 12, UINT16, 1)]
    msg = raw_cloud(RCLPY, fields, 16, W, H, b''.join(rows), row_step=16 * W + 4)
    wire = serialize_message(msg)
    other = STORE.deserialize_cdr(wire, 'sensor_msgs/msg/PointCloud2')
    for m in (msg, other):
        arr = pointcloud2_to_array(m)
        assert arr.shape == (H, W)
        np.testing.assert_array_equal(arr['z'], [[0, 1, 2], [1, 2, 3]])
        np.testing.assert_array_equal(arr['ring'], [[0, 7, 14]] * 2)
    back = deserialize_message(bytes(STORE.serialize_cdr(other, 'sensor_msgs/msg/PointCloud2')),
                               PointCloud2)
    assert bytes(back.data) == bytes(msg.data)


@pytest.mark.parametrize('C', BOTH, **KIND)
def test_input_message_not_modified_big_endian(C):
    rng = np.random.default_rng(2)
    vals = rng.normal(size=(10, 4)).astype('>f4')
    vals[2, 0] = np.nan
    msg = raw_cloud(C, [('x', 0, 7, 1), ('y', 4, 7, 1), ('z', 8, 7, 1),
                        ('intensity', 12, 7, 1)], 16, 10, 1, vals.tobytes(), bigendian=True)
    before = bytes(msg.data)
    out = pointcloud2_to_xyzi(msg)
    np.testing.assert_array_equal(out.points, np.delete(vals, 2, 0).astype('<f4'))
    assert out.points.dtype.byteorder in '<=' and out.num_nonfinite == 1
    arr = pointcloud2_to_array(msg)
    np.testing.assert_array_equal(arr['y'], vals[:, 1])
    assert bytes(msg.data) == before and msg.is_bigendian


@pytest.mark.parametrize('C', BOTH, **KIND)
def test_organized_cloud_and_row_padding(C):
    H, W = 3, 4
    rows = []
    for r in range(H):
        row = b''.join(struct.pack('<fff', r, c, r * c) for c in range(W))
        rows.append(row + b'\xee' * 8)                      # row padding
    msg = raw_cloud(C, XYZ, 12, W, H, b''.join(rows), row_step=12 * W + 8)
    arr = pointcloud2_to_array(msg)
    assert arr.shape == (H, W)
    np.testing.assert_array_equal(arr['x'][:, 0], [0, 1, 2])
    np.testing.assert_array_equal(arr['z'][2], [0, 2, 4, 6])
    out = pointcloud2_to_xyzi(msg)
    assert out.points.shape == (12, 4) and not out.has_intensity
    np.testing.assert_array_equal(out.points[:, 3], 0)
    np.testing.assert_array_equal(out.points[:, 0], np.repeat(np.arange(3), 4))   # row major
    np.testing.assert_array_equal(out.points[:, 2], [r * c for r in range(3) for c in range(4)])


def test_huge_finite_coordinates_are_kept():
    vals = np.array([[3e38, 3e38, 3e38, 1], [-3e38, 3e38, np.nan, 2]], '<f4')
    out = pointcloud2_to_xyzi(raw_cloud(RCLPY, XYZ + [('intensity', 12, FLOAT32, 1)], 16, 2, 1,
                                        vals.tobytes()))
    np.testing.assert_array_equal(out.points, vals[:1])
    assert out.num_nonfinite == 1


def test_intensity_field_names_and_types():
    data = b''.join(struct.pack('<fffH', 1, 2, 3, 40) for _ in range(3))
    msg = raw_cloud(ROSBAGS, XYZ + [('i', 12, UINT16, 1)], 14, 3, 1, data)
    out = pointcloud2_to_xyzi(msg)
    assert out.has_intensity
    np.testing.assert_array_equal(out.points, [[1, 2, 3, 40]] * 3)


def test_empty_and_all_nan():
    for C in BOTH:
        empty = raw_cloud(C, XYZ, 12, 0, 1, b'')
        out = pointcloud2_to_xyzi(empty)
        assert out.points.shape == (0, 4) and out.num_input == 0 and out.num_nonfinite == 0
        assert pointcloud2_to_array(empty).shape == (0,)
        assert array_to_pointcloud2(np.zeros(0, DRIVER), C.header(0, 'l'), C).width == 0
    nan = np.full((5, 3), np.nan, '<f4').tobytes()
    out = pointcloud2_to_xyzi(raw_cloud(ROSBAGS, XYZ, 12, 5, 1, nan))
    assert out.points.shape == (0, 4) and out.num_nonfinite == 5 and out.num_input == 5
    empty_rows = raw_cloud(ROSBAGS, XYZ, 12, 0, 4, b'')
    assert pointcloud2_to_array(empty_rows).shape == (4, 0)
    # a default-constructed cloud (no fields, no points): what some filters publish when
    # nothing is left is an empty cloud, not an unusable one; with data it stays an error
    for C in BOTH:
        out = pointcloud2_to_xyzi(raw_cloud(C, [], 0, 0, 0, b''))
        assert out.points.shape == (0, 4) and out.num_input == 0 and not out.has_intensity
        with pytest.raises(PointCloudError, match='no x/y/z field'):
            pointcloud2_to_xyzi(raw_cloud(C, [], 0, 0, 0, bytes(12)))


@pytest.mark.parametrize('fields,step,width,height,data,row_step,match', [
    (XYZ, 12, 10, 1, bytes(100), None, 'truncated'),
    (XYZ, 12, 2, 2, bytes(52), 28, 'truncated'),          # last row's padding missing
    (XYZ, 12, 4, 1, bytes(48), 40, 'row_step 40 is shorter'),
    (XYZ[:2] + [('z', 10, 7, 1)], 12, 1, 1, bytes(12), None, 'overruns'),
    (XYZ[:2], 12, 1, 1, bytes(12), None, 'no z'),
    ([('y', 4, 7, 1), ('z', 8, 7, 1)], 12, 1, 1, bytes(12), None, 'no x'),
    (XYZ[:1] + [('y', 4, 9, 1), ('z', 8, 7, 1)], 12, 1, 1, bytes(12), None, 'unknown datatype'),
    (XYZ[:1] + [('y', 2, 7, 1), ('z', 8, 7, 1)], 12, 1, 1, bytes(12), None, 'overlap'),
    ([('x', 0, 7, 0)] + XYZ[1:], 12, 1, 1, bytes(12), None, 'count 0'),
    (XYZ + [('x', 8, 7, 1)], 12, 1, 1, bytes(12), None, 'twice'),
])
def test_invalid_clouds_raise_clear_errors(fields, step, width, height, data, row_step, match):
    for C in BOTH:
        msg = raw_cloud(C, fields, step, width, height, data, row_step=row_step)
        with pytest.raises(PointCloudError, match=match):
            pointcloud2_to_xyzi(msg)
        if 'no ' not in match:                               # x/y/z are the fast path's need
            with pytest.raises(PointCloudError, match=match):
                pointcloud2_to_array(msg)


def test_array_to_pointcloud2_rejects_what_pointfield_cannot_describe():
    with pytest.raises(PointCloudError, match='structured'):
        array_to_pointcloud2(np.zeros((3, 3), np.float32), RCLPY.header(0, 'l'), RCLPY)
    bad = np.zeros(3, [('x', '<f4'), ('y', '<f4'), ('z', '<c8')])
    with pytest.raises(PointCloudError, match="'z'"):
        array_to_pointcloud2(bad, RCLPY.header(0, 'l'), RCLPY)


@st.composite
def layouts(draw):
    """Random valid layouts: any datatype, counts, padding, endianness, row padding; the
    coordinates are FLOAT32 and adjacent often enough to exercise the fast path."""
    extra = draw(st.integers(0, 3))
    names = ['x', 'y', 'z'] + [draw(st.sampled_from(['intensity', 'i', 'ring', 't']))
                               + str(i) * (i > 0) for i in range(extra)]
    fast = draw(st.booleans())
    offset = draw(st.integers(0, 3))
    fields = []
    for name in names:
        coord = name in ('x', 'y', 'z') or name.startswith('intensity') or name == 'i'
        datatype = FLOAT32 if fast and coord else draw(st.integers(1, 8))
        count = 1 if coord else draw(st.integers(1, 3))
        if not (fast and coord):
            offset += draw(st.integers(0, 3))                   # padding before the field
        fields.append((name, offset, datatype, count))
        offset += int(DATATYPES[datatype][1]) * count
    if draw(st.booleans()):
        fields = draw(st.permutations(fields))
    step = offset + draw(st.integers(0, 5))
    width = draw(st.integers(0, 6))
    height = draw(st.integers(1, 3))
    row_step = step * width + draw(st.integers(0, 7))
    big = draw(st.booleans())
    kind = draw(st.sampled_from(BOTH))
    size = row_step * height
    data = draw(st.binary(min_size=size, max_size=size + 3))
    return kind, fields, step, row_step, width, height, big, data


def expected_xyzi(ref, inten):
    """x, y, z, intensity as float32 rows for the points whose x/y/z are finite."""
    expect = []
    for point in ref:
        row = [np.float32(point[k][0]) if not isinstance(point[k][0], float)
               else np.float64(point[k][0]).astype(np.float32) for k in ('x', 'y', 'z')]
        if not all(math.isfinite(v) for v in row):
            continue
        value = np.float32(point[inten][0]) if inten else np.float32(0)
        expect.append(row + [value if math.isfinite(value) else np.float32(0)])
    return expect


@settings(max_examples=200, deadline=None)
@given(layouts())
def test_decode_matches_struct(layout):
    C, fields, step, row_step, width, height, big, data = layout
    msg = raw_cloud(C, fields, step, width, height, data, bigendian=big, row_step=row_step)
    ref = struct_decode(data, fields, step, row_step, width, height, big)
    arr = pointcloud2_to_array(msg)
    assert arr.shape == ((height, width) if height > 1 else (width,))
    flat = arr.reshape(-1)
    for i, point in enumerate(ref):
        for name, values in point.items():
            got = np.atleast_1d(flat[name][i])
            np.testing.assert_array_equal(got, np.array(values, dtype=got.dtype))
    # the detector's input against the same decode
    names = {f[0] for f in fields}
    inten = next((n for n in ('intensity', 'i') if n in names), None)
    with np.errstate(over='ignore'):             # float64 beyond float32 becomes inf: dropped
        expect = expected_xyzi(ref, inten)
    xyzi = pointcloud2_to_xyzi(msg)
    assert xyzi.has_intensity == (inten is not None)
    assert xyzi.num_input == width * height
    assert xyzi.num_nonfinite == width * height - len(expect)
    np.testing.assert_array_equal(xyzi.points, np.array(expect, np.float32).reshape(-1, 4))
    assert bytes(msg.data) == data                             # never modified


def test_dtype_from_fields_itemsize_and_offsets():
    class F:
        def __init__(self, name, offset, datatype, count):
            self.name, self.offset, self.datatype, self.count = name, offset, datatype, count
    dt = dtype_from_fields([F('a', 2, 3, 2), F('b', 8, 8, 1)], 20, True)
    assert dt.itemsize == 20 and dt.fields['a'][1] == 2 and dt.fields['b'][1] == 8
    assert dt['a'].subdtype[1] == (2,) and dt['b'] == np.dtype('>f8')


def test_adapters_import_no_ros_package():
    """msg_adapters is pure: importing it loads neither rclpy nor any message package."""
    import subprocess
    import sys
    code = ('import sys\n'
            'import suit_ros.msg_adapters.pointcloud2, suit_ros.msg_adapters.detections\n'
            'import suit_ros.msg_adapters.odometry, suit_ros.msg_adapters.builders\n'
            "print([m for m in sys.modules if m.split('.')[0] in ('rclpy', 'rosbags') "
            "or m.split('.')[0].endswith('_msgs') or m.split('.')[0] == 'builtin_interfaces'])")
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         timeout=60, cwd='/')
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == '[]'


@pytest.mark.parametrize('C', BOTH, ids=KIND['ids'])
@pytest.mark.parametrize('xyz_type', ['<f4', '<f8'])
def test_time_field_rows_follow_the_kept_points(C, xyz_type):
    # the fast float32 path and the converted one drop the same non-finite rows from times
    dtype = np.dtype([('x', xyz_type), ('y', xyz_type), ('z', xyz_type), ('intensity', '<f4'),
                      ('t', '<u4')])
    a = np.zeros(50, dtype)
    for k in 'xyz':
        a[k] = np.arange(50) + 1.0
    a['t'] = np.arange(50) * 1000
    a['x'][[3, 17]] = np.nan
    a['z'][40] = np.inf
    msg = array_to_pointcloud2(a, C.header(5, 'lidar'), C)
    got = pointcloud2_to_xyzi(msg, time_fields=('time', 't'))
    keep = np.setdiff1d(np.arange(50), [3, 17, 40])
    assert got.time_field == 't' and got.times.dtype == np.uint32
    np.testing.assert_array_equal(got.times, keep * 1000)
    np.testing.assert_array_equal(got.points[:, 1], a['y'][keep].astype(np.float32))
    assert pointcloud2_to_xyzi(msg).times is None                  # none asked for
    none = pointcloud2_to_xyzi(msg, time_fields=('time',))         # asked, not there
    assert none.times is None and none.time_field == ''


def test_organized_cloud_times_in_row_order():
    a = driver_cloud(24, seed=3)
    a['x'][5] = np.nan
    msg = array_to_pointcloud2(a.reshape(4, 6), RCLPY.header(5, 'lidar'), RCLPY)
    got = pointcloud2_to_xyzi(msg, time_fields=('time',))
    np.testing.assert_array_equal(got.times, np.delete(a['time'], 5))
