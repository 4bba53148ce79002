"""PointCloud2 adapters: round trips (rclpy and rosbags classes, CDR), properties, edge cases."""
from __future__ import annotations

import array
import struct

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from suit_ros.msg_adapters.classes import MessageClasses
from suit_ros.msg_adapters.errors import PointCloudError
from suit_ros.msg_adapters.pointcloud2 import (
    DATATYPES,
    array_to_pointcloud2,
    pointcloud2_to_array,
    pointcloud2_to_xyzi,
)

STORE = get_typestore(Stores.ROS2_JAZZY)
RCLPY = MessageClasses.from_rclpy()
ROSBAGS = MessageClasses.from_rosbags(STORE)
BOTH = [RCLPY, ROSBAGS]
DRIVER = np.dtype({'names': ['x', 'y', 'z', 'intensity', 'time', 'ring'],
                   'formats': ['<f4', '<f4', '<f4', '<f4', '<f4', '<u2'],
                   'offsets': [0, 4, 8, 12, 16, 20], 'itemsize': 24})
STRUCT = {1: 'b', 2: 'B', 3: 'h', 4: 'H', 5: 'i', 6: 'I', 7: 'f', 8: 'd'}


def driver_cloud(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = np.zeros(n, DRIVER)
    for k in ('x', 'y', 'z'):
        a[k] = rng.uniform(-50, 50, n)
    a['intensity'] = rng.uniform(0, 255, n)
    a['ring'] = rng.integers(0, 32, n)
    a['time'] = rng.uniform(0, 0.1, n)
    return a


def raw_cloud(C, fields, point_step, width, height, data, bigendian=False, row_step=None):
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


@pytest.mark.parametrize('C', BOTH, ids=lambda c: c.kind)
def test_round_trip_structured(C):
    a = driver_cloud(1000)
    msg = array_to_pointcloud2(a, C.header(123, 'lidar'), C)
    assert msg.point_step == 24 and msg.width == 1000 and msg.height == 1
    back = pointcloud2_to_array(msg)
    assert back.dtype.names == a.dtype.names
    for k in a.dtype.names:
        np.testing.assert_array_equal(back[k], a[k])
    assert not back.flags.writeable            # the message cannot be modified through it


@pytest.mark.parametrize('C', BOTH, ids=lambda c: c.kind)
def test_xyzi_fast_path_drops_nonfinite(C):
    a = driver_cloud(500)
    a['x'][[3, 7]] = np.nan
    a['z'][11] = np.inf
    msg = array_to_pointcloud2(a, C.header(1, 'lidar'), C)
    out = pointcloud2_to_xyzi(msg)
    keep = np.ones(500, bool)
    keep[[3, 7, 11]] = False
    assert out.num_input == 500 and out.num_nonfinite == 3 and out.has_intensity
    assert out.points.dtype == np.float32 and out.points.flags.c_contiguous
    expect = np.stack([a['x'], a['y'], a['z'], a['intensity']], 1)[keep]
    np.testing.assert_array_equal(out.points, expect)


def test_cdr_round_trip_rclpy_and_rosbags():
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import PointCloud2
    a = driver_cloud(300, 1)
    m = array_to_pointcloud2(a, RCLPY.header(9, 'lidar'), RCLPY)
    as_rosbags = STORE.deserialize_cdr(serialize_message(m), 'sensor_msgs/msg/PointCloud2')
    np.testing.assert_array_equal(pointcloud2_to_array(as_rosbags), a)
    m2 = array_to_pointcloud2(a, ROSBAGS.header(9, 'lidar'), ROSBAGS)
    as_rclpy = deserialize_message(bytes(STORE.serialize_cdr(m2, 'sensor_msgs/msg/PointCloud2')),
                                   PointCloud2)
    np.testing.assert_array_equal(pointcloud2_to_array(as_rclpy), a)
    assert as_rclpy.header.frame_id == 'lidar'


def test_input_message_not_modified_big_endian():
    rng = np.random.default_rng(2)
    vals = rng.normal(size=(10, 4)).astype('>f4')
    data = vals.tobytes()
    msg = raw_cloud(ROSBAGS, [('x', 0, 7, 1), ('y', 4, 7, 1), ('z', 8, 7, 1),
                              ('intensity', 12, 7, 1)], 16, 10, 1, data, bigendian=True)
    before = bytes(msg.data)
    out = pointcloud2_to_xyzi(msg)
    np.testing.assert_allclose(out.points, vals.astype('<f4'))
    assert bytes(msg.data) == before


def test_organized_cloud_and_row_padding():
    H, W = 3, 4
    rows = []
    for r in range(H):
        row = b''.join(struct.pack('<fff', r, c, r * c) for c in range(W))
        rows.append(row + b'\xee' * 8)                      # row padding
    msg = raw_cloud(RCLPY, [('x', 0, 7, 1), ('y', 4, 7, 1), ('z', 8, 7, 1)], 12, W, H,
                    b''.join(rows), row_step=12 * W + 8)
    arr = pointcloud2_to_array(msg)
    assert arr.shape == (H, W)
    np.testing.assert_array_equal(arr['x'][:, 0], [0, 1, 2])
    np.testing.assert_array_equal(arr['z'][2], [0, 2, 4, 6])
    out = pointcloud2_to_xyzi(msg)
    assert out.points.shape == (12, 4) and not out.has_intensity
    np.testing.assert_array_equal(out.points[:, 3], 0)


def test_empty_and_all_nan():
    empty = raw_cloud(ROSBAGS, [('x', 0, 7, 1), ('y', 4, 7, 1), ('z', 8, 7, 1)], 12, 0, 1, b'')
    out = pointcloud2_to_xyzi(empty)
    assert out.points.shape == (0, 4) and out.num_input == 0
    nan = np.full((5, 3), np.nan, '<f4').tobytes()
    out = pointcloud2_to_xyzi(raw_cloud(ROSBAGS, [('x', 0, 7, 1), ('y', 4, 7, 1),
                                                  ('z', 8, 7, 1)], 12, 5, 1, nan))
    assert out.points.shape == (0, 4) and out.num_nonfinite == 5


@pytest.mark.parametrize('fields,step,width,data,match', [
    ([('x', 0, 7, 1), ('y', 4, 7, 1), ('z', 8, 7, 1)], 12, 10, bytes(100), 'truncated'),
    ([('x', 0, 7, 1), ('y', 4, 7, 1), ('z', 10, 7, 1)], 12, 1, bytes(12), 'overruns'),
    ([('x', 0, 7, 1), ('y', 4, 7, 1)], 12, 1, bytes(12), 'no z'),
    ([('x', 0, 7, 1), ('y', 4, 9, 1), ('z', 8, 7, 1)], 12, 1, bytes(12), 'unknown datatype'),
    ([('x', 0, 7, 1), ('y', 2, 7, 1), ('z', 8, 7, 1)], 12, 1, bytes(12), 'overlap'),
    ([('x', 0, 7, 0), ('y', 4, 7, 1), ('z', 8, 7, 1)], 12, 1, bytes(12), 'count'),
])
def test_invalid_clouds_raise_clear_errors(fields, step, width, data, match):
    msg = raw_cloud(ROSBAGS, fields, step, width, 1, data)
    with pytest.raises(PointCloudError, match=match):
        pointcloud2_to_xyzi(msg)


@st.composite
def layouts(draw):
    n_fields = draw(st.integers(1, 5))
    offset = 0
    fields = []
    names = ['x', 'y', 'z'] + [f'f{i}' for i in range(n_fields)]
    for name in names:
        datatype = draw(st.integers(1, 8))
        count = draw(st.integers(1, 3)) if name.startswith('f') else 1
        offset += draw(st.integers(0, 3))                       # padding before the field
        fields.append((name, offset, datatype, count))
        offset += int(DATATYPES[datatype][1]) * count
    step = offset + draw(st.integers(0, 5))
    width = draw(st.integers(0, 6))
    height = draw(st.integers(1, 3))
    big = draw(st.booleans())
    data = draw(st.binary(min_size=step * width * height, max_size=step * width * height))
    return fields, step, width, height, big, data


@settings(max_examples=150, deadline=None)
@given(layouts())
def test_decode_matches_struct(layout):
    fields, step, width, height, big, data = layout
    msg = raw_cloud(ROSBAGS, fields, step, width, height, data, bigendian=big)
    arr = pointcloud2_to_array(msg).reshape(-1)
    order = '>' if big else '<'
    for i in range(width * height):
        for name, off, dt, cnt in fields:
            ref = struct.unpack_from(order + STRUCT[dt] * cnt, data, i * step + off)
            got = np.atleast_1d(arr[name][i])
            np.testing.assert_array_equal(got, np.array(ref, dtype=got.dtype))
    xyzi = pointcloud2_to_xyzi(msg)
    assert xyzi.num_input == width * height
    assert xyzi.points.shape[0] + xyzi.num_nonfinite == width * height
