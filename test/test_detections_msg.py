"""Detections <-> custom-field PointCloud2, and -> MarkerArray."""
from __future__ import annotations

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from suit_ros.msg_adapters.classes import MessageClasses
from suit_ros.msg_adapters.detections import (
    ARROW,
    CUBE,
    DELETEALL,
    TEXT_VIEW_FACING,
    detections_to_markerarray,
    detections_to_pointcloud2,
    pointcloud2_to_detections,
)

STORE = get_typestore(Stores.ROS2_JAZZY)
BOTH = [MessageClasses.from_rclpy(), MessageClasses.from_rosbags(STORE)]
NAMES = ('car', 'truck', 'pedestrian', 'cyclist')


def random_boxes(n, seed=0):
    rng = np.random.default_rng(seed)
    boxes = np.c_[rng.uniform(-40, 40, (n, 2)), rng.uniform(-1, 1, n), rng.uniform(0.5, 10, n),
                  rng.uniform(0.5, 3, n), rng.uniform(1, 3, n), rng.uniform(-3, 3, n)]
    vel = rng.normal(0, 3, (n, 2))
    return boxes, vel, rng.uniform(0, 1, n), rng.integers(0, 4, n)


@pytest.mark.parametrize('C', BOTH, ids=lambda c: c.kind)
def test_cloud_round_trip_with_gt_fields(C):
    boxes, vel, scores, labels = random_boxes(40)
    extra = {'num_points': np.arange(40, dtype=np.uint32),
             'instance_id': np.arange(100, 140, dtype=np.uint32)}
    msg = detections_to_pointcloud2(boxes, vel, scores, labels, C.header(77, 'lidar'), C, extra)
    assert [f.name for f in msg.fields][:11] == ['x', 'y', 'z', 'length', 'width', 'height',
                                                 'yaw', 'vx', 'vy', 'score', 'label']
    assert msg.header.frame_id == 'lidar' and msg.width == 40
    back = pointcloud2_to_detections(msg)
    np.testing.assert_allclose(back['boxes'], boxes.astype(np.float32))
    np.testing.assert_allclose(back['velocities'], vel.astype(np.float32))
    np.testing.assert_array_equal(back['labels'], labels)
    np.testing.assert_array_equal(back['instance_id'], extra['instance_id'])


@pytest.mark.parametrize('C', BOTH, ids=lambda c: c.kind)
def test_empty_detections(C):
    msg = detections_to_pointcloud2(np.zeros((0, 7)), np.zeros((0, 2)), np.zeros(0),
                                    np.zeros(0, int), C.header(1, 'lidar'), C)
    assert msg.width == 0 and len(pointcloud2_to_detections(msg)['boxes']) == 0
    ma = detections_to_markerarray(np.zeros((0, 7)), np.zeros((0, 2)), np.zeros(0),
                                   np.zeros(0, int), C.header(1, 'lidar'), NAMES, C)
    assert len(ma.markers) == 1 and ma.markers[0].action == DELETEALL


@pytest.mark.parametrize('C', BOTH, ids=lambda c: c.kind)
def test_markers(C):
    boxes, vel, scores, labels = random_boxes(25, 3)
    vel[0] = 0.0
    header = C.header(123_000_000_456, 'lidar')
    ma = detections_to_markerarray(boxes, vel, scores, labels, header, NAMES, C)
    m = ma.markers
    assert m[0].action == DELETEALL
    assert all(x.header.frame_id == 'lidar' and x.header.stamp.nanosec == 456 for x in m)
    cubes = [x for x in m[1:] if x.type == CUBE]
    texts = [x for x in m[1:] if x.type == TEXT_VIEW_FACING]
    arrows = [x for x in m[1:] if x.type == ARROW]
    assert len(cubes) == 25 and len(texts) == 25 and len(arrows) == 24   # box 0 is still
    for i, c in enumerate(cubes):
        assert c.ns == f'{NAMES[labels[i]]}/box'
        yaw = 2 * np.arctan2(c.pose.orientation.z, c.pose.orientation.w)
        assert np.isclose(np.cos(yaw - boxes[i, 6]), 1.0, atol=1e-9)
        assert np.isclose(c.scale.x, boxes[i, 3])
    assert texts[4].text == f'{NAMES[labels[4]]} {scores[4]:.2f}'
    keys = {(x.ns, x.id) for x in m[1:]}
    assert len(keys) == len(m) - 1                      # unique ids per namespace
