"""Detections <-> custom-field PointCloud2, and -> MarkerArray (both message flavours)."""
from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import PointCloud2

from suit_ros.msg_adapters.classes import MessageClasses
from suit_ros.msg_adapters.detections import (
    DELETEALL,
    LINE_LIST,
    PALETTE,
    TEXT_VIEW_FACING,
    detections_to_markerarray,
    detections_to_pointcloud2,
    pointcloud2_to_detections,
)
from suit_ros.msg_adapters.errors import MessageError, PointCloudError
from suit_ros.msg_adapters.pointcloud2 import FLOAT32, UINT8, UINT32

STORE = get_typestore(Stores.ROS2_JAZZY)
RCLPY = MessageClasses.from_rclpy()
ROSBAGS = MessageClasses.from_rosbags(STORE)
BOTH = [RCLPY, ROSBAGS]
KIND = {'ids': lambda c: c.kind}
NAMES = ('car', 'truck', 'pedestrian', 'cyclist')
MARKER_ARRAY = 'visualization_msgs/msg/MarkerArray'


def random_boxes(n, seed=0):
    rng = np.random.default_rng(seed)
    boxes = np.c_[rng.uniform(-40, 40, (n, 2)), rng.uniform(-1, 1, n), rng.uniform(0.5, 10, n),
                  rng.uniform(0.5, 3, n), rng.uniform(1, 3, n), rng.uniform(-3, 3, n)]
    vel = rng.normal(0, 3, (n, 2))
    return boxes, vel, rng.uniform(0, 1, n), rng.integers(0, 4, n)


@pytest.mark.parametrize('C', BOTH, **KIND)
def test_cloud_layout_and_round_trip_with_gt_fields(C):
    boxes, vel, scores, labels = random_boxes(40)
    extra = {'num_points': np.arange(40, dtype=np.uint32),
             'instance_id': np.arange(100, 140, dtype=np.uint32)}
    msg = detections_to_pointcloud2(boxes, vel, scores, labels, C.header(77, 'lidar'), C, extra)
    layout = [(f.name, f.offset, f.datatype, f.count) for f in msg.fields]
    floats = ['x', 'y', 'z', 'length', 'width', 'height', 'yaw', 'vx', 'vy', 'score']
    assert layout == ([(n, 4 * i, FLOAT32, 1) for i, n in enumerate(floats)]
                      + [('label', 40, UINT8, 1), ('num_points', 44, UINT32, 1),
                         ('instance_id', 48, UINT32, 1)])
    assert msg.header.frame_id == 'lidar' and msg.header.stamp.nanosec == 77
    assert (msg.width, msg.height, msg.point_step) == (40, 1, 52)
    back = pointcloud2_to_detections(msg)
    np.testing.assert_array_equal(back['boxes'], boxes.astype(np.float32))
    np.testing.assert_array_equal(back['velocities'], vel.astype(np.float32))
    np.testing.assert_array_equal(back['scores'], scores.astype(np.float32))
    np.testing.assert_array_equal(back['labels'], labels)
    assert back['labels'].dtype == np.int64 and back['boxes'].shape == (40, 7)
    np.testing.assert_array_equal(back['num_points'], extra['num_points'])
    np.testing.assert_array_equal(back['instance_id'], extra['instance_id'])
    assert msg.is_dense
    boxes[3, 0] = np.nan                      # a box with no centre: the cloud is not dense
    assert not detections_to_pointcloud2(boxes, vel, scores, labels, C.header(77, 'lidar'), C,
                                         extra).is_dense


@pytest.mark.parametrize('C', BOTH, **KIND)
def test_track_ids_field_and_marker_text(C):
    boxes, vel, scores, labels = random_boxes(5)
    ids = np.array([3, 0, 7, 4_000_000_000, 1])
    msg = detections_to_pointcloud2(boxes, vel, scores, labels, C.header(5, 'lidar'), C,
                                    track_ids=ids)
    layout = [(f.name, f.offset, f.datatype) for f in msg.fields]
    assert layout[-2:] == [('label', 40, UINT8), ('track_id', 44, UINT32)]
    assert msg.point_step == 48
    np.testing.assert_array_equal(pointcloud2_to_detections(msg)['track_id'], ids)
    plain = detections_to_pointcloud2(boxes, vel, scores, labels, C.header(5, 'lidar'), C)
    assert 'track_id' not in pointcloud2_to_detections(plain)
    arr = detections_to_markerarray(boxes, vel, scores, labels, C.header(5, 'lidar'), NAMES, C,
                                    track_ids=ids)
    texts = [m.text for m in arr.markers if m.type == TEXT_VIEW_FACING]
    assert texts[0].endswith(' #3') and '#' not in texts[1] and texts[3].endswith(' #4000000000')
    with pytest.raises(MessageError, match='track ids'):
        detections_to_pointcloud2(boxes, vel, scores, labels, C.header(5, 'lidar'), C,
                                  track_ids=ids[:2])
    with pytest.raises(MessageError, match='track ids'):
        detections_to_markerarray(boxes, vel, scores, labels, C.header(5, 'lidar'), NAMES, C,
                                  track_ids=ids[:2])
    with pytest.raises(PointCloudError, match='UINT32'):
        detections_to_pointcloud2(boxes, vel, scores, labels, C.header(5, 'lidar'), C,
                                  track_ids=-ids)


@pytest.mark.parametrize('C', BOTH, **KIND)
def test_num_points_field_between_label_and_track_id(C):
    boxes, vel, scores, labels = random_boxes(4)
    ids, counts = np.array([3, 0, 7, 1]), np.array([120, 0, 5, 4_000_000_000])
    msg = detections_to_pointcloud2(boxes, vel, scores, labels, C.header(5, 'lidar'), C,
                                    track_ids=ids, num_points=counts)
    layout = [(f.name, f.offset, f.datatype) for f in msg.fields]
    assert layout[-3:] == [('label', 40, UINT8), ('num_points', 44, UINT32),
                           ('track_id', 48, UINT32)]
    assert msg.point_step == 52
    back = pointcloud2_to_detections(msg)
    np.testing.assert_array_equal(back['num_points'], counts)
    np.testing.assert_array_equal(back['track_id'], ids)
    alone = detections_to_pointcloud2(boxes, vel, scores, labels, C.header(5, 'lidar'), C,
                                      num_points=counts)
    assert [f.name for f in alone.fields][-1] == 'num_points' and alone.point_step == 48
    with pytest.raises(MessageError, match='point counts'):
        detections_to_pointcloud2(boxes, vel, scores, labels, C.header(5, 'lidar'), C,
                                  num_points=counts[:2])
    with pytest.raises(PointCloudError, match='UINT32'):
        detections_to_pointcloud2(boxes, vel, scores, labels, C.header(5, 'lidar'), C,
                                  num_points=-counts - 1)


@pytest.mark.parametrize('C', BOTH, **KIND)
def test_held_field_sits_after_label_and_says_why_a_box_is_there(C):
    """``held`` (UINT8: 0 seen, 1 carried, 2 coasted) takes the padding byte after
    ``label``: the other fields keep their offsets and the point its size; the markers say
    it; a wrong length or value is refused."""
    boxes, vel, scores, labels = random_boxes(4)
    ids, counts = np.array([3, 0, 7, 1]), np.array([120, 0, 0, 9])
    std = np.ones(4, np.float32)
    held = np.array([0, 1, 2, 0])
    msg = detections_to_pointcloud2(boxes, vel, scores, labels, C.header(5, 'lidar'), C,
                                    track_ids=ids, num_points=counts, vel_std=std, held=held)
    layout = [(f.name, f.offset, f.datatype) for f in msg.fields]
    assert layout[-5:] == [('label', 40, UINT8), ('held', 41, UINT8),
                           ('num_points', 44, UINT32), ('track_id', 48, UINT32),
                           ('vel_std', 52, FLOAT32)]
    assert msg.point_step == 56
    back = pointcloud2_to_detections(msg)
    np.testing.assert_array_equal(back['held'], held)
    np.testing.assert_array_equal(back['labels'], labels)
    np.testing.assert_array_equal(back['num_points'], counts)
    texts = [m.text for m in detections_to_markerarray(
        boxes, vel, scores, labels, C.header(5, 'lidar'), NAMES, C, track_ids=ids,
        held=held).markers if m.type == TEXT_VIEW_FACING]
    assert [t.endswith(' carried') for t in texts] == [False, True, False, False]
    assert [t.endswith(' coasted') for t in texts] == [False, False, True, False]
    with pytest.raises(MessageError, match='held flags'):
        detections_to_pointcloud2(boxes, vel, scores, labels, C.header(5, 'lidar'), C,
                                  held=held[:2])
    with pytest.raises(PointCloudError, match='held must be'):
        detections_to_pointcloud2(boxes, vel, scores, labels, C.header(5, 'lidar'), C,
                                  held=held + 1)


@pytest.mark.parametrize('C', BOTH, **KIND)
def test_vel_std_field_comes_last_and_is_checked(C):
    """The tracker's velocity standard deviation: FLOAT32 after track_id, read back as it
    was written; absent unless given; a wrong length, a negative or infinite value refused;
    NaN (a NaN velocity's: unknown) kept."""
    boxes, vel, scores, labels = random_boxes(4)
    ids, counts = np.array([3, 0, 7, 1]), np.array([120, 0, 5, 9])
    std = np.array([4.5, 0.31, 1.25, 0.0], np.float32)
    msg = detections_to_pointcloud2(boxes, vel, scores, labels, C.header(5, 'lidar'), C,
                                    track_ids=ids, num_points=counts, vel_std=std)
    layout = [(f.name, f.offset, f.datatype) for f in msg.fields]
    assert layout[-3:] == [('num_points', 44, UINT32), ('track_id', 48, UINT32),
                           ('vel_std', 52, FLOAT32)]
    assert msg.point_step == 56
    back = pointcloud2_to_detections(msg)
    np.testing.assert_array_equal(back['vel_std'], std)
    np.testing.assert_array_equal(back['track_id'], ids)
    np.testing.assert_allclose(back['velocities'], vel, rtol=1e-6)
    plain = detections_to_pointcloud2(boxes, vel, scores, labels, C.header(5, 'lidar'), C,
                                      track_ids=ids)
    assert 'vel_std' not in pointcloud2_to_detections(plain)
    with pytest.raises(MessageError, match='velocity standard deviations for 4 boxes'):
        detections_to_pointcloud2(boxes, vel, scores, labels, C.header(5, 'lidar'), C,
                                  vel_std=std[:3])
    for bad in (-0.1, np.inf):
        with pytest.raises(PointCloudError, match='>= 0 and finite'):
            detections_to_pointcloud2(boxes, vel, scores, labels, C.header(5, 'lidar'), C,
                                      vel_std=np.where(np.arange(4) == 2, bad, std))
    unknown = np.where(np.arange(4) == 2, np.nan, std)   # the velocity's NaN: unknown
    back = pointcloud2_to_detections(detections_to_pointcloud2(
        boxes, vel, scores, labels, C.header(5, 'lidar'), C, vel_std=unknown))
    np.testing.assert_array_equal(back['vel_std'], unknown.astype(np.float32))


def test_cloud_through_cdr_both_ways():
    boxes, vel, scores, labels = random_boxes(12, 5)
    m = detections_to_pointcloud2(boxes, vel, scores, labels, RCLPY.header(1, 'lidar'), RCLPY)
    assert [f.name for f in m.fields][-1] == 'label' and m.point_step == 44
    other = STORE.deserialize_cdr(serialize_message(m), 'sensor_msgs/msg/PointCloud2')
    again = deserialize_message(
        bytes(STORE.serialize_cdr(other, 'sensor_msgs/msg/PointCloud2')), PointCloud2)
    for msg in (other, again):
        back = pointcloud2_to_detections(msg)
        np.testing.assert_array_equal(back['boxes'], boxes.astype(np.float32))
        np.testing.assert_array_equal(back['labels'], labels)
        assert 'num_points' not in back


def test_cloud_input_errors():
    boxes, vel, scores, labels = random_boxes(3)
    with pytest.raises(PointCloudError, match='0..255'):
        detections_to_pointcloud2(boxes, vel, scores, np.array([0, 1, 300]),
                                  RCLPY.header(0, 'l'), RCLPY)
    plain = RCLPY.PointCloud2(fields=[RCLPY.PointField(name='x', offset=0, datatype=7,
                                                       count=1)], point_step=4)
    with pytest.raises(PointCloudError, match='not a detections cloud'):
        pointcloud2_to_detections(plain)


@pytest.mark.parametrize('C', BOTH, **KIND)
def test_empty_detections(C):
    msg = detections_to_pointcloud2(np.zeros((0, 7)), np.zeros((0, 2)), np.zeros(0),
                                    np.zeros(0, int), C.header(1, 'lidar'), C)
    assert msg.width == 0 and len(pointcloud2_to_detections(msg)['boxes']) == 0
    ma = detections_to_markerarray(np.zeros((0, 7)), np.zeros((0, 2)), np.zeros(0),
                                   np.zeros(0, int), C.header(1, 'lidar'), NAMES, C)
    assert len(ma.markers) == 1 and ma.markers[0].action == DELETEALL


def reference_corners(box):
    """The 8 corners of one box, written out independently of box_corners."""
    x, y, z, length, width, height, yaw = box
    out = []
    for dz in (-height / 2, height / 2):
        for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
            lx, ly = sx * length / 2, sy * width / 2
            out.append((x + lx * np.cos(yaw) - ly * np.sin(yaw),
                        y + lx * np.sin(yaw) + ly * np.cos(yaw), z + dz))
    return np.array(out)


@pytest.mark.parametrize('C', BOTH, **KIND)
def test_markers(C):
    boxes, vel, scores, labels = random_boxes(25, 3)
    vel[0] = 0.0
    vel[1] = [0.1, -0.15]                                  # 0.18 m/s: no velocity segment
    header = C.header(123_000_000_456, 'lidar')
    ma = detections_to_markerarray(boxes, vel, scores, labels, header, NAMES, C)
    m = ma.markers
    assert m[0].action == DELETEALL
    assert all(x.header.frame_id == 'lidar' and x.header.stamp.sec == 123
               and x.header.stamp.nanosec == 456 for x in m)
    # the next array's DELETEALL clears them; if none comes (input stopped, node ended), a
    # second later they are gone from a viewer
    assert all(x.lifetime.sec == 1 and x.lifetime.nanosec == 0 for x in m)
    short = detections_to_markerarray(boxes, vel, scores, labels, header, NAMES, C,
                                      lifetime_s=0.25).markers
    assert all(x.lifetime.sec == 0 and x.lifetime.nanosec == 250_000_000 for x in short)
    with pytest.raises(ValueError, match='lifetime_s'):
        detections_to_markerarray(boxes, vel, scores, labels, header, NAMES, C, lifetime_s=-1)
    lines = [x for x in m[1:] if x.type == LINE_LIST]
    texts = [x for x in m[1:] if x.type == TEXT_VIEW_FACING]
    present = sorted(set(labels.tolist()))
    assert len(m) == 1 + len(present) + 25 and len(lines) == len(present)
    moving = np.hypot(vel[:, 0], vel[:, 1]) >= 0.2
    for line, k in zip(lines, present):
        idx = np.flatnonzero(labels == k)
        assert line.ns == f'{NAMES[k]}/boxes' and line.id == 0 and line.action == 0
        assert (line.color.r, line.color.g, line.color.b) == PALETTE[k] and line.color.a == 1
        assert line.scale.x > 0 and line.pose.orientation.w == 1.0
        pts = np.array([[p.x, p.y, p.z] for p in line.points])
        assert len(pts) == 24 * len(idx) + 2 * moving[idx].sum()
        for n, i in enumerate(idx):
            segs = pts[24 * n:24 * (n + 1)].reshape(12, 2, 3)
            ref = reference_corners(boxes[i])
            # every edge joins two corners, and every corner pair that is an edge appears
            got = {tuple(sorted((tuple(np.round(a, 9)), tuple(np.round(b, 9))))) for a, b in segs}
            want = {tuple(sorted((tuple(np.round(ref[a], 9)), tuple(np.round(ref[b], 9)))))
                    for a, b in [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7),
                                 (7, 4), (0, 4), (1, 5), (2, 6), (3, 7)]}
            assert got == want
        tail = pts[24 * len(idx):].reshape(-1, 2, 3)
        for (start, end), i in zip(tail, idx[moving[idx]]):
            np.testing.assert_allclose(start, [*boxes[i, :2], boxes[i, 2] + boxes[i, 5] / 2])
            np.testing.assert_allclose(end[:2] - start[:2], vel[i])
    for i, t in enumerate(texts):
        name = NAMES[labels[i]]
        assert t.ns == f'{name}/labels' and t.id == i and t.text == f'{name} {scores[i]:.2f}'
        assert t.pose.position.z > boxes[i, 2] + boxes[i, 5] / 2
    keys = {(x.ns, x.id) for x in m[1:]}
    assert len(keys) == len(m) - 1                      # unique ids per namespace


def test_markers_unknown_label_and_input_checks():
    boxes, vel, scores, _ = random_boxes(2)
    ma = detections_to_markerarray(boxes, vel, scores, np.array([0, 9]), RCLPY.header(0, 'l'),
                                   NAMES, RCLPY)
    assert {x.ns for x in ma.markers[1:]} >= {'car/boxes', 'class9/boxes', 'class9/labels'}
    with pytest.raises(MessageError, match='velocities'):
        detections_to_markerarray(boxes, vel[:1], scores, np.zeros(2, int),
                                  RCLPY.header(0, 'l'), NAMES, RCLPY)


def test_markers_cross_between_rclpy_and_rosbags():
    """The same MarkerArray from both bundles: rclpy's CDR reads back in rosbags equal."""
    boxes, vel, scores, labels = random_boxes(30, 9)
    a = detections_to_markerarray(boxes, vel, scores, labels, RCLPY.header(5, 'lidar'), NAMES,
                                  RCLPY)
    b = detections_to_markerarray(boxes, vel, scores, labels, ROSBAGS.header(5, 'lidar'),
                                  NAMES, ROSBAGS)
    decoded = STORE.deserialize_cdr(serialize_message(a), MARKER_ARRAY)
    from_rosbags = STORE.deserialize_cdr(STORE.serialize_cdr(b, MARKER_ARRAY), MARKER_ARRAY)

    def summary(ma):
        return [(x.ns, x.id, x.type, x.action, x.text, x.scale.x, np.float32(x.color.r),
                 [(p.x, p.y, p.z) for p in x.points]) for x in ma.markers]
    assert summary(decoded) == summary(from_rosbags) == summary(a)


def test_checked_fields_pass():
    """With ROS_PYTHON_CHECK_FIELDS=1 rclpy checks every field the constructors get."""
    import os
    import subprocess
    import sys
    code = ('import numpy as np\n'
            'from suit_ros.msg_adapters.classes import MessageClasses\n'
            'from suit_ros.msg_adapters.detections import detections_to_markerarray\n'
            'C = MessageClasses.from_rclpy()\n'
            'b = np.array([[1.0, 2, 0, 4, 2, 1.5, 0.3]])\n'
            "m = detections_to_markerarray(b, [[1.0, 0.0]], [0.9], [0], C.header(1, 'l'),\n"
            "                              ('car',), C)\n"
            'print(len(m.markers), len(m.markers[1].points), m.markers[2].text)\n')
    env = dict(os.environ, ROS_PYTHON_CHECK_FIELDS='1')
    out = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == '3 26 car 0.90'


def test_cloud_shape_errors():
    boxes, vel, scores, labels = random_boxes(4)
    h = RCLPY.header(0, 'l')
    with pytest.raises(MessageError, match='velocities'):
        detections_to_pointcloud2(boxes, vel[:3], scores, labels, h, RCLPY)
    with pytest.raises(MessageError, match="'instance_id' has 2 values for 4 boxes"):
        detections_to_pointcloud2(boxes, vel, scores, labels, h, RCLPY,
                                  {'num_points': np.zeros(4), 'instance_id': np.zeros(2)})
    with pytest.raises(MessageError, match='missing'):
        detections_to_pointcloud2(boxes, vel, scores, labels, h, RCLPY, {'num_points': [1]})
