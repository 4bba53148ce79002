"""Odometry adapters and the pose buffer (interpolation against scipy, errors)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from suit_ros.msg_adapters.classes import MessageClasses
from suit_ros.msg_adapters.errors import MessageError, PoseLookupError
from suit_ros.msg_adapters.odometry import (
    PoseBuffer,
    TimeLine,
    matrix_to_quaternion,
    ns_to_stamp,
    odometry_to_pose,
    quaternion_to_matrix,
    slerp,
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
    rots = Rotation.random(50, random_state=1)
    # include the branches for rotations by ~180 degrees (trace <= 0)
    rots = Rotation.concatenate([rots, Rotation.from_rotvec(np.pi * np.eye(3)),
                                 Rotation.from_rotvec([[0, 0, 3.1], [2.0, 2.0, 0.5]])])
    for q in rots.as_quat():
        q = q if q[3] >= 0 else -q
        np.testing.assert_allclose(matrix_to_quaternion(quaternion_to_matrix(*q)), q, atol=1e-9)
        np.testing.assert_allclose(quaternion_to_matrix(*q), Rotation.from_quat(q).as_matrix(),
                                   atol=1e-12)


def test_non_normalised_quaternion_and_bad_position():
    C = MessageClasses.from_rclpy()
    q = 3.0 * Rotation.from_euler('z', 0.4).as_quat()
    T, _ = odometry_to_pose(odom(C, 5, (0.0, 0.0, 0.0), q))
    np.testing.assert_allclose(T[:3, :3], Rotation.from_euler('z', 0.4).as_matrix(), atol=1e-12)
    with pytest.raises(MessageError, match='position'):
        odometry_to_pose(odom(C, 5, (np.inf, 0.0, 0.0), (0, 0, 0, 1)))


def test_stamps():
    C = MessageClasses.from_rclpy()
    for ns in (0, 1, 999_999_999, 1_000_000_000, 1_700_000_123_456_789):
        t = ns_to_stamp(ns, C.Time)
        assert 0 <= t.nanosec < 10**9 and stamp_to_ns(t) == ns
    assert stamp_to_ns(C.header(42_000_000_001, 'x').stamp) == 42_000_000_001


def test_slerp_close_and_opposite_sign_quaternions():
    """Nearly equal rotations (50 Hz odometry) and q / -q pairs (shortest arc)."""
    for angle in (1e-7, 1e-4, 0.03, 1.5):
        r0 = Rotation.from_rotvec([0.1, 0.2, 0.3])
        r1 = Rotation.from_rotvec([0.1, 0.2, 0.3 + angle])
        q0, q1 = r0.as_quat(), -r1.as_quat()
        s = Slerp([0, 1], Rotation.concatenate([r0, r1]))
        for f in (0.0, 0.25, 0.5, 1.0):
            got = Rotation.from_quat(slerp(q0, q1, f))
            assert (got.inv() * s([f])[0]).magnitude() < 1e-12


def make_pose(t, yaw):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler('z', yaw).as_matrix()
    T[:3, 3] = t
    return T


def test_interpolation_against_scipy():
    # offline (rewind_ns None): any order of arrival, every pose in place at once
    buf = PoseBuffer(max_age_ns=10**10, tolerance_ns=50_000_000, rewind_ns=None)
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


def test_lookup_outside_span_and_tolerance_both_sides():
    buf = PoseBuffer(max_age_ns=10**10, tolerance_ns=100_000_000)
    with pytest.raises(PoseLookupError, match='no pose'):
        buf.lookup(0)
    buf.add(1_000_000_000, make_pose([1, 0, 0], 0.0))
    buf.add(2_000_000_000, make_pose([2, 0, 0], 0.5))
    np.testing.assert_allclose(buf.lookup(2_050_000_000), make_pose([2, 0, 0], 0.5))   # hold
    np.testing.assert_allclose(buf.lookup(2_100_000_000), make_pose([2, 0, 0], 0.5))   # edge
    np.testing.assert_allclose(buf.lookup(900_000_000), make_pose([1, 0, 0], 0.0))
    with pytest.raises(PoseLookupError, match=r'2\.200 s is outside the buffered poses '
                                              r'\[1\.000, 2\.000\] s'):
        buf.lookup(2_200_000_000)
    with pytest.raises(PoseLookupError, match='0.800 s'):
        buf.lookup(800_000_000)
    buf.clear()
    assert len(buf) == 0 and buf.span() is None


def test_duplicates_replace_and_old_poses_evicted():
    buf = PoseBuffer(max_age_ns=1_000_000_000, tolerance_ns=0)
    buf.add(0, make_pose([0, 0, 0], 0))
    buf.add(0, make_pose([5, 0, 0], 0))
    assert len(buf) == 1 and buf.lookup(0)[0, 3] == 5
    for k in range(1, 8):
        buf.add(k * 400_000_000, make_pose([k, 0, 0], 0))
    # newest 2.8 s: everything before 1.8 s is gone, the rest kept in order
    assert buf.span() == (2_000_000_000, 2_800_000_000) and len(buf) == 3
    buf.add(2_200_000_000, make_pose([7, 0, 0], 0))       # late but recent: held, until
    np.testing.assert_allclose(buf.lookup(2_100_000_000)[0, 3], 5.25)
    buf.add(2_900_000_000, make_pose([8, 0, 0], 0))       # the next pose says it was late
    np.testing.assert_allclose(buf.lookup(2_100_000_000)[0, 3], 6.0)     # in place
    buf.add(3_000_000_000 + 10**9, make_pose([1, 0, 0], 0))
    assert buf.span() == (4_000_000_000, 4_000_000_000) and buf.rewinds == 0


def test_time_going_back_empties_the_buffer():
    """A looped bag or a simulator reset: poses more than rewind_ns before the newest, two in
    a row, are another time line. The buffer starts again from them (nothing of the old one
    is interpolated with them), and counts it; one late pose alone, or a pose a little late,
    is inserted in place."""
    buf = PoseBuffer(max_age_ns=10 * 10**9, tolerance_ns=0, rewind_ns=10**9)
    for k in range(50):                                   # 1000.0 .. 1004.9 s
        buf.add(1000 * 10**9 + k * 10**8, make_pose([100 + k, 0, 0], 0))
    buf.add(1004 * 10**9 + 5 * 10**7, make_pose([0, 0, 0], 0))   # 0.85 s late: held,
    assert buf.rewinds == 0 and len(buf) == 50
    buf.add(1001 * 10**9 + 5 * 10**7, make_pose([0, 0, 0], 0))   # in place after one 3.85 s late
    assert buf.rewinds == 0 and len(buf) == 51
    buf.add(1005 * 10**9, make_pose([150, 0, 0], 0))              # and on as before
    assert buf.rewinds == 0 and len(buf) == 53
    for k in range(20):                                   # the bag again: 5.0 .. 6.9 s
        buf.add(5 * 10**9 + k * 10**8, make_pose([k, 0, 0], 0))
    assert buf.rewinds == 1 and buf.span() == (5 * 10**9, 6_900_000_000) and len(buf) == 20
    np.testing.assert_allclose(buf.lookup(6 * 10**9)[0, 3], 10.0)


def test_a_late_pose_just_before_time_goes_back_is_not_the_new_line():
    """A pose 1.5 s late, then the bag loops: the late pose belongs to the old time line. The
    new line starts from its own first two poses (not from the late one, which would push the
    new line's poses out of the buffer by age), and the rewind counts once."""
    buf = PoseBuffer(max_age_ns=10 * 10**9, tolerance_ns=0, rewind_ns=10**9)
    for k in range(100):                                  # 90.0 .. 99.9 s
        buf.add(90 * 10**9 + k * 10**8, make_pose([k, 0, 0], 0))
    buf.add(98_400_000_000, make_pose([-1, 0, 0], 0))     # 1.5 s late
    buf.add(100_000_000, make_pose([1, 0, 0], 0))         # the bag again from 0.1 s
    buf.add(200_000_000, make_pose([2, 0, 0], 0))
    assert buf.rewinds == 1 and buf.span() == (100_000_000, 200_000_000) and len(buf) == 2
    np.testing.assert_allclose(buf.lookup(150_000_000)[0, 3], 1.5)
    for k in range(3, 30):
        buf.add(k * 10**8, make_pose([k, 0, 0], 0))
    assert buf.rewinds == 1 and buf.span() == (100_000_000, 2_900_000_000)


def _moving(buf, start_ns, n, x0, period_ns=20_000_000):
    """``n`` poses at 50 Hz from ``start_ns``, x going up by 1 a pose from ``x0``."""
    for k in range(n):
        buf.add(start_ns + k * period_ns, make_pose([x0 + k, 0, 0], 0))


def test_time_going_back_less_than_a_second_is_not_mixed_with_the_time_before():
    """A simulator reset 0.4 s into its run: odometry goes back 0.3 s to another place.
    Three poses in a row before the newest, each after the last, are the new time line: the
    buffer starts again from them (the old line kept as it was, ``previous``, for its
    clouds still on their way). Until the third, the poses are held aside, so no lookup
    ever interpolates between the two lines."""
    buf = PoseBuffer(max_age_ns=10 * 10**9, tolerance_ns=0)
    _moving(buf, 0, 21, 0)                                # 0 .. 0.4 s, x 0 .. 20
    buf.add(100_000_000, make_pose([-500, 0, 0], 0))      # the reset: 0.3 s back, elsewhere
    np.testing.assert_allclose(buf.lookup(50_000_000)[0, 3], 2.5)   # before it: the old line
    np.testing.assert_allclose(buf.lookup(110_000_000)[0, 3], 5.5)  # held: still the old line
    buf.add(120_000_000, make_pose([-499, 0, 0], 0))
    assert buf.rewinds == 0 and len(buf) == 21
    buf.add(140_000_000, make_pose([-498, 0, 0], 0))      # the third: time went back
    assert buf.rewinds == 1 and buf.span() == (100_000_000, 140_000_000) and len(buf) == 3
    np.testing.assert_allclose(buf.lookup(130_000_000)[0, 3], -498.5)
    np.testing.assert_allclose(buf.previous.lookup(300_000_000)[0, 3], 15.0)
    _moving(buf, 160_000_000, 20, -497)                   # and on, past the old newest
    xs = [buf.lookup(t)[0, 3] for t in range(100_000_000, 540_000_000, 10_000_000)]
    np.testing.assert_allclose(np.diff(xs), 0.5)          # one line: no old pose in it
    assert buf.rewinds == 1


def test_late_poses_and_a_pose_from_the_future():
    """Late poses that do not line up (each followed by newer ones) go in place and never
    count as time going back; a single pose stamped 0.5 s ahead (a glitch) is dropped once
    three poses in a row come before it, rather than bending the path for 0.5 s, and the path
    before it stays."""
    buf = PoseBuffer(max_age_ns=10 * 10**9, tolerance_ns=0)
    _moving(buf, 0, 10, 0)                                # 0 .. 0.18 s
    for k in range(10, 30, 2):                            # pairs swapped on the way
        buf.add((k + 1) * 20_000_000, make_pose([k + 1, 0, 0], 0))
        buf.add(k * 20_000_000, make_pose([k, 0, 0], 0))
    assert buf.rewinds == 0 and len(buf) == 30            # late by less than one: in place
    buf.add(30 * 20_000_000, make_pose([30, 0, 0], 0))
    assert buf.rewinds == 0 and len(buf) == 31
    np.testing.assert_allclose(buf.lookup(570_000_000)[0, 3], 28.5)
    buf.add(31 * 20_000_000 + 500_000_000, make_pose([99, 0, 0], 0))   # the glitch
    _moving(buf, 31 * 20_000_000, 3, 31)
    assert buf.rewinds == 1 and buf.span() == (0, 660_000_000) and len(buf) == 34
    np.testing.assert_allclose(buf.lookup(650_000_000)[0, 3], 32.5)
    np.testing.assert_allclose(buf.lookup(490_000_000)[0, 3], 24.5)    # the path before it
    for _ in range(5):                  # a stamp repeated before the newest: held once
        buf.add(600_000_000, make_pose([30, 0, 0], 0))
    assert len(buf._run) == 1


def test_time_line_never_goes_back_offline():
    line = TimeLine(None)
    assert not any(line.went_back(s, 10**12) for s in (0, 1, 2, 3, 4))
    near = TimeLine(10**9)
    assert [near.went_back(s, 10**9) for s in (1, 2, 3)] == [False, False, True]
    assert [near.went_back(s, 10**9) for s in (3, 2, 1, 4, 5)] == [False] * 4 + [True]
    assert [near.went_back(s, 10**10) for s in (1, 2)] == [False, True]     # far: two


def test_nan_pose_rejected():
    buf = PoseBuffer()
    bad = make_pose([np.nan, 0, 0], 0)
    with pytest.raises(MessageError):
        buf.add(0, bad)
    assert stamp_to_ns(MessageClasses.from_rclpy().Time(sec=3, nanosec=7)) == 3_000_000_007


def test_odometry_through_cdr_gives_the_same_pose():
    from rclpy.serialization import serialize_message
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    q = Rotation.from_euler('zyx', [-2.0, 0.3, 0.2]).as_quat()
    m = odom(MessageClasses.from_rclpy(), 7_000_000_001, (4.0, -5.0, 0.5), q)
    other = store.deserialize_cdr(serialize_message(m), 'nav_msgs/msg/Odometry')
    T0, s0 = odometry_to_pose(m)
    T1, s1 = odometry_to_pose(other)
    assert s0 == s1 == 7_000_000_001
    np.testing.assert_array_equal(T0, T1)
