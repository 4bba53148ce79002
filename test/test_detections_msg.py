"""Detections <-> custom-field PointCloud2, and -> MarkerArray (both message flavours)."""
from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from suit_ros.msg_adapters.builders import MessageFactory, message_factory
from suit_ros.msg_adapters.classes import MessageClasses
from suit_ros.msg_adapters.detections import (
    ARROW,
    CUBE,
    DELETEALL,
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


@pytest.mark.parametrize('C', BOTH, **KIND)
def test_markers(C):
    boxes, vel, scores, labels = random_boxes(25, 3)
    vel[0] = 0.0
    vel[1] = [0.1, -0.15]                                  # 0.18 m/s: no arrow
    header = C.header(123_000_000_456, 'lidar')
    ma = detections_to_markerarray(boxes, vel, scores, labels, header, NAMES, C)
    m = ma.markers
    assert m[0].action == DELETEALL
    assert all(x.header.frame_id == 'lidar' and x.header.stamp.sec == 123
               and x.header.stamp.nanosec == 456 for x in m)
    assert all(x.lifetime.sec == 0 and x.lifetime.nanosec == 0 for x in m)
    cubes = [x for x in m[1:] if x.type == CUBE]
    texts = [x for x in m[1:] if x.type == TEXT_VIEW_FACING]
    arrows = {x.id: x for x in m[1:] if x.type == ARROW}
    assert len(m) == 1 + 25 + 25 + 23 and len(cubes) == 25 and len(texts) == 25
    assert sorted(arrows) == list(range(2, 25))
    for i, c in enumerate(cubes):
        name = NAMES[labels[i]]
        assert c.ns == f'{name}/box' and c.id == i and c.action == 0
        q = c.pose.orientation
        assert np.isclose(q.x ** 2 + q.y ** 2 + q.z ** 2 + q.w ** 2, 1.0)
        assert q.x == 0 and q.y == 0
        yaw = 2 * np.arctan2(q.z, q.w)
        assert np.isclose(np.cos(yaw - boxes[i, 6]), 1.0, atol=1e-12)
        assert np.isclose(np.sin(yaw - boxes[i, 6]), 0.0, atol=1e-12)
        assert [c.pose.position.x, c.pose.position.y, c.pose.position.z] == list(boxes[i, :3])
        assert [c.scale.x, c.scale.y, c.scale.z] == list(boxes[i, 3:6])
        assert (c.color.r, c.color.g, c.color.b) == PALETTE[labels[i]] and 0 < c.color.a < 1
        t = texts[i]
        assert t.ns == f'{name}/label' and t.text == f'{name} {scores[i]:.2f}'
        assert t.pose.position.z > boxes[i, 2] + boxes[i, 5] / 2
        if i in arrows:
            a = arrows[i]
            assert a.ns == f'{name}/velocity'
            assert np.isclose(a.scale.x, np.hypot(*vel[i]))
            heading = 2 * np.arctan2(a.pose.orientation.z, a.pose.orientation.w)
            np.testing.assert_allclose([np.cos(heading), np.sin(heading)],
                                       vel[i] / np.hypot(*vel[i]), atol=1e-12)
            assert (a.color.r, a.color.g, a.color.b) == PALETTE[labels[i]]
    keys = {(x.ns, x.id) for x in m[1:]}
    assert len(keys) == len(m) - 1                      # unique ids per namespace


def test_markers_unknown_label_and_input_checks():
    boxes, vel, scores, _ = random_boxes(2)
    ma = detections_to_markerarray(boxes, vel, scores, np.array([0, 9]), RCLPY.header(0, 'l'),
                                   NAMES, RCLPY)
    assert {x.ns for x in ma.markers[1:]} >= {'car/box', 'class9/box'}
    with pytest.raises(MessageError, match='velocities'):
        detections_to_markerarray(boxes, vel[:1], scores, np.zeros(2, int),
                                  RCLPY.header(0, 'l'), NAMES, RCLPY)


def test_fast_factories_build_what_the_constructors_build():
    """The slot/dict factories against the plain constructors: same bytes on the wire."""
    assert type(message_factory(RCLPY)) is not MessageFactory
    assert type(message_factory(ROSBAGS)) is not MessageFactory
    boxes, vel, scores, labels = random_boxes(30, 9)
    for C in BOTH:
        header = C.header(5_000_000_007, 'lidar')
        fast = detections_to_markerarray(boxes, vel, scores, labels, header, NAMES, C)
        ref = detections_to_markerarray(boxes, vel, scores, labels, header, NAMES, C,
                                        factory=MessageFactory(C))
        if C.kind == 'rclpy':
            assert fast == ref
            wire = serialize_message(fast)
            assert (deserialize_message(wire, MarkerArray)
                    == deserialize_message(serialize_message(ref), MarkerArray))
            decoded = STORE.deserialize_cdr(wire, MARKER_ARRAY)     # readable by rosbags too
            assert [x.text for x in decoded.markers] == [x.text for x in ref.markers]
        else:
            assert (bytes(STORE.serialize_cdr(fast, MARKER_ARRAY))
                    == bytes(STORE.serialize_cdr(ref, MARKER_ARRAY)))


def test_checked_fields_use_the_constructors():
    """With ROS_PYTHON_CHECK_FIELDS=1 rclpy checks every field; the factory then goes through
    the generated constructors, and the markers still pass those checks."""
    import os
    import subprocess
    import sys
    code = ('import numpy as np\n'
            'from suit_ros.msg_adapters.builders import MessageFactory, message_factory\n'
            'from suit_ros.msg_adapters.classes import MessageClasses\n'
            'from suit_ros.msg_adapters.detections import detections_to_markerarray\n'
            'C = MessageClasses.from_rclpy()\n'
            'assert type(message_factory(C)) is MessageFactory\n'
            'b = np.array([[1.0, 2, 0, 4, 2, 1.5, 0.3]])\n'
            "m = detections_to_markerarray(b, [[1.0, 0.0]], [0.9], [0], C.header(1, 'l'),\n"
            "                              ('car',), C)\n"
            'print(len(m.markers), m.markers[2].text)\n')
    env = dict(os.environ, ROS_PYTHON_CHECK_FIELDS='1')
    out = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == '4 car 0.90'


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
