"""Odometry adapters and the pose buffer (interpolation against scipy, errors)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from suit_ros.msg_adapters.classes import MessageClasses
from suit_ros.msg_adapters.errors import MessageError, PoseLookupError
from suit_ros.msg_adapters.odometry import (
    PoseBuffer,
    matrix_to_quaternion,
    odometry_to_pose,
    quaternion_to_matrix,
    stamp_to_ns,
)


def odom(C, stamp_ns, xyz, quat):
    m = C.Odometry() if C.kind == 'rclpy' else None
    if m is None:
        from rosbags.typesys import Stores, get_typestore
        t = get_typestore(Stores.ROS2_JAZZY).types
        cov = np.zeros(36)
        return C.Odometry(
            header=C.header(stamp_ns, 'odom'), child_frame_id='base_link',
            pose=t['geometry_msgs/msg/PoseWithCovariance'](
                pose=C.Pose(position=C.Point(x=xyz[0], y=xyz[1], z=xyz[2]),
                            orientation=C.Quaternion(x=quat[0], y=quat[1], z=quat[2],
                                                     w=quat[3])), covariance=cov),
            twist=t['geometry_msgs/msg/TwistWithCovariance'](
                twist=t['geometry_msgs/msg/Twist'](linear=C.Vector3(x=0.0, y=0.0, z=0.0),
                                                   angular=C.Vector3(x=0.0, y=0.0, z=0.0)),
                covariance=cov))
    m.header = C.header(stamp_ns, 'odom')
    m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z = map(float, xyz)
    o = m.pose.pose.orientation
    o.x, o.y, o.z, o.w = map(float, quat)
    return m


@pytest.mark.parametrize('kind', ['rclpy', 'rosbags'])
def test_odometry_to_pose(kind):
    from rosbags.typesys import Stores, get_typestore
    C = (MessageClasses.from_rclpy() if kind == 'rclpy'
         else MessageClasses.from_rosbags(get_typestore(Stores.ROS2_JAZZY)))
    q = Rotation.from_euler('zyx', [0.7, 0.1, -0.05]).as_quat()
    T, stamp = odometry_to_pose(odom(C, 1_234_567_890_123, (1.0, 2.0, 3.0), q))
    assert stamp == 1_234_567_890_123
    np.testing.assert_allclose(T[:3, :3], Rotation.from_quat(q).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [1, 2, 3])


@pytest.mark.parametrize('q', [(0, 0, 0, 0), (np.nan, 0, 0, 1)])
def test_bad_quaternion(q):
    with pytest.raises(MessageError, match='quaternion'):
        quaternion_to_matrix(*q)


def test_matrix_quaternion_round_trip():
    rng = np.random.default_rng(0)
    for q in Rotation.random(50, random_state=1).as_quat():
        q = q if q[3] >= 0 else -q
        np.testing.assert_allclose(matrix_to_quaternion(quaternion_to_matrix(*q)), q, atol=1e-9)
    del rng


def make_pose(t, yaw):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler('z', yaw).as_matrix()
    T[:3, 3] = t
    return T


def test_interpolation_against_scipy():
    buf = PoseBuffer(max_age_ns=10**10, tolerance_ns=50_000_000)
    stamps = np.arange(0, 10) * 20_000_000
    rots = Rotation.from_euler('zyx', np.random.default_rng(3).uniform(-1, 1, (10, 3)))
    trans = np.random.default_rng(4).normal(size=(10, 3))
    for i in np.random.default_rng(5).permutation(10):          # out-of-order arrival
        T = np.eye(4)
        T[:3, :3] = rots[i].as_matrix()
        T[:3, 3] = trans[i]
        buf.add(int(stamps[i]), T)
    slerp = Slerp(stamps, rots)
    for s in np.linspace(0, stamps[-1], 37):
        T = buf.lookup(int(s))
        np.testing.assert_allclose(T[:3, :3], slerp([s]).as_matrix()[0], atol=1e-9)
        expect = np.array([np.interp(s, stamps, trans[:, k]) for k in range(3)])
        np.testing.assert_allclose(T[:3, 3], expect, atol=1e-9)


def test_lookup_outside_span_and_tolerance():
    buf = PoseBuffer(max_age_ns=10**10, tolerance_ns=100_000_000)
    with pytest.raises(PoseLookupError, match='no pose'):
        buf.lookup(0)
    buf.add(1_000_000_000, make_pose([1, 0, 0], 0.0))
    buf.add(2_000_000_000, make_pose([2, 0, 0], 0.5))
    np.testing.assert_allclose(buf.lookup(2_050_000_000)[:3, 3], [2, 0, 0])   # edge hold
    with pytest.raises(PoseLookupError, match='outside the buffered poses'):
        buf.lookup(2_200_000_000)
    with pytest.raises(PoseLookupError):
        buf.lookup(800_000_000)


def test_duplicates_replace_and_old_poses_evicted():
    buf = PoseBuffer(max_age_ns=1_000_000_000, tolerance_ns=0)
    buf.add(0, make_pose([0, 0, 0], 0))
    buf.add(0, make_pose([5, 0, 0], 0))
    assert len(buf) == 1 and buf.lookup(0)[0, 3] == 5
    buf.add(3_000_000_000, make_pose([1, 0, 0], 0))
    assert buf.span() == (3_000_000_000, 3_000_000_000)


def test_nan_pose_rejected():
    buf = PoseBuffer()
    bad = make_pose([np.nan, 0, 0], 0)
    with pytest.raises(MessageError):
        buf.add(0, bad)
    assert stamp_to_ns(MessageClasses.from_rclpy().Time(sec=3, nanosec=7)) == 3_000_000_007
