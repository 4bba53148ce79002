"""Deskew: a sweep taken over time by a moving sensor, put back at its stamp.

The kernel against numpy; a static world seen by a sensor moving with a known twist (with a
turned, offset extrinsic) comes back to where the sensor saw it at the stamp; the twist from
odometry poses, covering the sweep or not; the time fields drivers write; a synthetic sweep
cast over time comes back onto the world the sim cast it from.
"""
from __future__ import annotations

import numpy as np
import pytest

from suit_ros.deskew import (
    MAX_SPEED,
    arc_matrix,
    body_twist,
    deskew,
    deskew_sweep,
    relative_times,
    rotation_vector,
    twist_from_poses,
)
from suit_ros.msg_adapters.odometry import PoseBuffer
from suit_ros.ops.geometry import pose_from_xyz_rpy, se3_inverse
from suit_ros.ops.kernels import deskew_points

S = 10**9


def rodrigues(w, t):
    """Rotation matrix of the rotation vector ``w * t``."""
    v = np.asarray(w, np.float64) * t
    a = np.linalg.norm(v)
    if a == 0:
        return np.eye(3)
    k = v / a
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def test_kernel_matches_numpy():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-40, 40, (500, 5)).astype(np.float32)
    times = rng.uniform(-0.05, 0.1, 500).astype(np.float32)
    w, v = np.array([0.05, -0.02, 0.6]), np.array([9.0, 0.5, 0.1])
    out = pts.copy()
    deskew_points(out, times, w, v)
    want = np.stack([rodrigues(w, t) @ p + arc_matrix(w * t) @ (t * v) for p, t in
                     zip(pts[:, :3].astype(np.float64), times.astype(np.float64))])
    np.testing.assert_allclose(out[:, :3], want, atol=2e-5)
    np.testing.assert_array_equal(out[:, 3:], pts[:, 3:])      # other columns kept
    still = pts.copy()
    deskew_points(still, times, np.zeros(3), np.zeros(3))
    np.testing.assert_array_equal(still, pts)
    fast = pts.copy()                  # 4 rad/s over 0.1 s: past the series, cos and sin
    w = np.array([0.3, 0.1, 4.0])
    deskew_points(fast, times, w, v)
    want = np.stack([rodrigues(w, t) @ p + arc_matrix(w * t) @ (t * v) for p, t in
                     zip(pts[:, :3].astype(np.float64), times.astype(np.float64))])
    np.testing.assert_allclose(fast[:, :3], want, atol=2e-5)


@pytest.mark.parametrize('rpy', [(0.0, 0.0, 0.0), (0.02, -0.03, 1.2)])
def test_a_static_world_seen_by_a_moving_sensor_comes_back(rpy):
    # the vehicle drives at 12 m/s turning at 0.5 rad/s; the sensor sits 1.2 m ahead, 1.9 m
    # up, turned by rpy; each return is reported in the sensor frame of its own time
    T_bl = pose_from_xyz_rpy((1.2, 0.1, 1.9), rpy)
    twist = np.array([0.0, 0.0, 0.5, 12.0, 0.0, 0.0])

    def pose_at(t):                                  # vehicle pose: the exact constant twist
        T = np.eye(4)
        T[:3, :3] = rodrigues(twist[:3], t)
        w = 0.5
        T[:3, 3] = [12.0 * np.sin(w * t) / w, 12.0 * (1 - np.cos(w * t)) / w, 0.0]
        return T
    rng = np.random.default_rng(1)
    world = rng.uniform([-40, -40, -1], [40, 40, 3], (2000, 3))
    times = np.sort(rng.uniform(0, 0.1, 2000)).astype(np.float32)
    seen = np.stack([(se3_inverse(pose_at(t) @ T_bl) @ np.append(p, 1.0))[:3]
                     for p, t in zip(world, times.astype(np.float64))]).astype(np.float32)
    at_stamp = (world @ se3_inverse(T_bl)[:3, :3].T + se3_inverse(T_bl)[:3, 3])  # pose_at(0) = I
    raw_err = np.linalg.norm(seen - at_stamp, axis=1)
    out = deskew(seen, times, twist, T_bl)
    err = np.linalg.norm(out - at_stamp, axis=1)
    assert raw_err.max() > 1.0                       # what the sweep's motion does
    assert err.max() < 1e-4                          # float32 points
    assert out.dtype == np.float32 and out is not seen


def test_body_twist_and_rotation_vector():
    T_a = pose_from_xyz_rpy((5.0, 2.0, 0.0), (0.0, 0.0, 0.3))
    D = pose_from_xyz_rpy((1.0, 0.1, 0.0), (0.0, 0.0, 0.05))
    tw = body_twist(T_a, T_a @ D, 0.1)
    np.testing.assert_allclose(tw[:3], [0, 0, 0.5], atol=1e-9)
    # the twist's translation after 0.1 s is D's
    np.testing.assert_allclose(arc_matrix(tw[:3] * 0.1) @ tw[3:] * 0.1, [1.0, 0.1, 0.0],
                               atol=1e-9)
    for v in ([0.0, 0.0, 0.0], [1e-9, 0, 0], [0.3, -2.0, 1.0]):
        np.testing.assert_allclose(rotation_vector(rodrigues(v, 1.0)), v, atol=1e-9)


def buffer_of(stamps_ns, speed=10.0, yaw_rate=0.0):
    poses = PoseBuffer()
    for s in stamps_ns:
        t = s * 1e-9
        poses.add(int(s), pose_from_xyz_rpy((speed * t, 0.0, 0.0), (0.0, 0.0, yaw_rate * t)))
    return poses


def test_twist_from_poses_over_the_sweep_or_the_latest_motion():
    odom = buffer_of(range(0, S + 1, S // 50), yaw_rate=0.2)
    tw = twist_from_poses(odom, S // 2, S // 2 + S // 10)          # covered: the sweep's own
    assert tw[2] == pytest.approx(0.2) and np.hypot(tw[3], tw[4]) == pytest.approx(10.0, 1e-3)
    late = twist_from_poses(odom, S, S + S // 10)                   # odometry ends at the start
    assert late[2] == pytest.approx(0.2) and np.hypot(late[3], late[4]) == pytest.approx(10, 1e-3)
    assert twist_from_poses(buffer_of([0]), 0, S // 10) is None           # one pose: no motion
    assert twist_from_poses(PoseBuffer(), 0, S // 10) is None
    assert twist_from_poses(buffer_of([0, S // 100]), 0, S // 10) is None  # 10 ms: too little


def test_deskew_sweep_leaves_a_sweep_of_one_instant_or_without_odometry():
    pts = np.ones((10, 4), np.float32)
    odom = buffer_of(range(0, S + 1, S // 50))
    same, tw, why = deskew_sweep(pts, np.zeros(10, np.float32), S // 2, odom, np.eye(4))
    assert same is pts and tw is None and why == 'sweep at one instant'
    same, tw, why = deskew_sweep(pts, np.linspace(0, 0.1, 10, dtype=np.float32), 5 * S,
                                 PoseBuffer(), np.eye(4))
    assert same is pts and tw is None and why == 'no odometry over the sweep'
    moved, tw, why = deskew_sweep(pts, np.linspace(0, 0.1, 10, dtype=np.float32), S // 2,
                                  odom, np.eye(4))
    np.testing.assert_allclose(moved[:, 0], 1.0 + 10.0 * np.linspace(0, 0.1, 10), atol=1e-4)
    # a cloud whose returns were all taken 50 ms after its stamp: moved by 0.5 m all the same
    late, tw, _ = deskew_sweep(pts, np.full(10, 0.05, np.float32), S // 2, odom, np.eye(4))
    np.testing.assert_allclose(late[:, 0], 1.5, atol=1e-4)


def test_an_odometry_jump_is_not_a_sweeps_motion():
    odom = buffer_of(range(0, S + 1, S // 50))
    odom.add(S + S // 50, pose_from_xyz_rpy((40.0, 0.0, 0.0), (0.0, 0.0, 0.0)))   # relocalised
    pts = np.ones((10, 4), np.float32)
    same, tw, why = deskew_sweep(pts, np.linspace(0, 0.1, 10, dtype=np.float32), S, odom,
                                 np.eye(4))
    assert same is pts and tw is None and 'a jump' in why


def test_a_small_odometry_step_inside_the_sweep_is_a_jump_too():
    # standing still, relocalised by 0.3 m early in the sweep: 3 m/s over the window,
    # well under MAX_SPEED, but its halves read 0 and 6 m/s
    odom = buffer_of(range(0, S // 2 + 1, S // 50), speed=0.0)
    odom.add(S // 2 + S // 50, pose_from_xyz_rpy((0.3, 0.0, 0.0), (0.0, 0.0, 0.0)))
    odom.add(S // 2 + S // 10, pose_from_xyz_rpy((0.3, 0.0, 0.0), (0.0, 0.0, 0.0)))
    pts = np.ones((10, 4), np.float32)
    times = np.linspace(0, 0.1, 10, dtype=np.float32)
    assert 0 < twist_from_poses(odom, S // 2, S // 2 + S // 10)[3] < MAX_SPEED
    same, tw, why = deskew_sweep(pts, times, S // 2, odom, np.eye(4))
    assert same is pts and tw is None and 'within the sweep' in why and 'a jump' in why
    # braking hard (8 m/s^2 from 15 m/s) while turning: one motion, deskewed
    brake = PoseBuffer()
    for s in range(0, S + 1, S // 100):
        t = s * 1e-9
        brake.add(s, pose_from_xyz_rpy((15 * t - 4 * t * t, 0.0, 0.0), (0.0, 0.0, 0.3 * t)))
    moved, tw, why = deskew_sweep(pts, times, S // 2, brake, np.eye(4))
    assert why == '' and tw is not None and moved is not pts


STAMP = 1_700_000_000 * S + 123_456_789


@pytest.mark.parametrize('values, want', [
    (np.array([0.0, 0.05, 0.0999], np.float32), [0.0, 0.05, 0.0999]),        # Velodyne time, s
    (np.array([-0.0999, -0.05, 0.0], np.float32), [-0.0999, -0.05, 0.0]),     # stamp at the end
    (np.array([0, 50_000_000, 99_900_000], np.uint32), [0.0, 0.05, 0.0999]),  # Ouster t, ns
    (STAMP * 1e-9 + np.array([0.0, 0.05, 0.0999]), [0.0, 0.05, 0.0999]),      # Hesai, epoch s
    (np.array([STAMP, STAMP + 50_000_000, STAMP + 99_900_000], np.int64),
     [0.0, 0.05, 0.0999]),                                                    # epoch ns
    (np.array([STAMP, STAMP + 50_000_000, STAMP + 99_900_000], np.float64),
     [0.0, 0.05, 0.0999]),                                         # Livox: epoch ns, float
])
def test_time_fields_as_drivers_write_them(values, want):
    times, why = relative_times(values, STAMP)
    assert why == '' and times.dtype == np.float32
    np.testing.assert_allclose(times, want, atol=2e-6)


def test_absolute_times_of_a_clock_that_started_near_zero():
    # simulation time (Gazebo, CARLA) or a bag replayed from 0: under a day, but one sweep only
    # against the stamp
    stamp = 1234 * S + 500_000_000
    for values in (stamp + np.array([0, 50_000_000, 99_900_000], np.int64),
                   stamp * 1e-9 + np.array([0.0, 0.05, 0.0999])):
        times, why = relative_times(values, stamp)
        assert why == ''
        np.testing.assert_allclose(times, [0.0, 0.05, 0.0999], atol=2e-6)
    times, why = relative_times(np.array([0.0, 0.05], np.float32), stamp)   # relative: as is
    np.testing.assert_allclose(times, [0.0, 0.05])
    times, why = relative_times(np.array([1200.0, 1200.05]), stamp)         # neither reading
    assert times is None and 'not one sweep' in why


def test_range_filter_needs_one_time_per_point():
    from suit_ros.ops.kernels import in_range_times
    with pytest.raises(ValueError, match='one time per point'):
        in_range_times(np.ones((5, 4), np.float32), np.zeros(4, np.float32), 0.0, 10.0)


@pytest.mark.parametrize('values, says', [
    (np.array([0.0, np.nan], np.float32), 'not finite'),
    (np.array([0.0, 0.9], np.float32), 'not one sweep'),
    (np.array([3.0, 3.05], np.float32), 'not one sweep'),
    (np.array([1.7e9, 1.7e9 + 0.05], np.float32), '32-bit float'),
])
def test_unusable_time_fields_say_why(values, says):
    times, why = relative_times(values, STAMP)
    assert times is None and says in why


def test_a_synthetic_sweep_cast_over_time_comes_back_onto_its_world():
    from suit_ros.data.sim import preset
    from suit_ros.data.sim.scene import SECTORS, Simulation, base_pose, to_frame
    from suit_ros.evaluate import deskewed
    cfg = preset('test', sensor='hdl32e', frames=2)
    sim = Simulation(cfg, 3)
    frames = [to_frame(sim.render(k), 3) for k in range(2)]
    assert all(f.times is not None and f.times.max() > 0.09 for f in frames)
    out = deskewed(frames)
    period, C = 1.0 / cfg.lidar.rate_hz, sim.dirs.shape[1]
    bounds = np.linspace(0, C, SECTORS + 1).astype(int)
    for k, f in enumerate(frames):      # the first by the motion to the next, the last before
        assert out[k].times is None
        sector = np.searchsorted(bounds, np.round(f.times / period * C), side='right') - 1
        T0 = f.pose
        raw, fixed = [], []
        for j in range(SECTORS):        # each sector was cast from the pose at its mid time
            m = sector == j
            Tj = base_pose(sim.ego, (k + (bounds[j] + bounds[j + 1]) / 2 / C) * period) \
                @ sim.T_base_lidar
            world = f.points[m, :3] @ Tj[:3, :3].T + Tj[:3, 3]
            for P, err in ((f.points, raw), (out[k].points, fixed)):
                err.append(np.linalg.norm(P[m, :3] @ T0[:3, :3].T + T0[:3, 3] - world, axis=1))
        raw_e, fixed_e = np.concatenate(raw), np.concatenate(fixed)
        assert raw_e.max() > 0.3                   # the sim's ego drives
        assert np.percentile(fixed_e, 99) < 0.1 * raw_e.max()


def test_a_sweep_cast_at_one_instant_has_no_times():
    from suit_ros.data.sim import preset
    from suit_ros.data.sim.scene import Simulation, to_frame
    sim = Simulation(preset('test', frames=1), 3)
    f = sim.render(0)
    assert not f.cloud['time'].any()              # sim32 casts the whole sweep at its stamp
    assert to_frame(f, 3).times is None


def test_cached_drives_keep_their_times_and_old_caches_are_made_again(tmp_path):
    from suit_ros.data.sequences import save_sequence, synthetic_sequence
    frames = synthetic_sequence('test', 5, 2, tmp_path, sensor='hdl32e')
    assert all(f.times is not None for f in frames)
    again = synthetic_sequence('test', 5, 2, tmp_path, sensor='hdl32e')
    for a, b in zip(frames, again):
        np.testing.assert_array_equal(a.times, b.times)
    (path,) = tmp_path.glob('*.npz')
    from dataclasses import replace
    save_sequence(path, [replace(f, times=None) for f in frames])   # as written before
    remade = synthetic_sequence('test', 5, 2, tmp_path, sensor='hdl32e')
    assert all(f.times is not None for f in remade)
    assert all(f.times is not None for f in synthetic_sequence('test', 5, 2, tmp_path,
                                                               sensor='hdl32e'))


def test_the_benchmarks_drives_keep_each_return_its_time():
    # outages remove returns, slabs add some (cast at the stamp: time 0), screens move them:
    # every drive a benchmark derives keeps one time per return, and deskews
    from suit_ros.data.occluders import occluded_drives
    from suit_ros.data.overhead import overhead_drives
    from suit_ros.data.sequences import synthetic_sequence
    from suit_ros.evaluate import deskewed
    from suit_ros.model.sweeps import model_frame
    from suit_ros.outage import Outage, with_outages
    drive = synthetic_sequence('test', 5, 3, None, sensor='hdl32e')
    lost = with_outages(drive, [Outage(0.0, 120.0, 0, 3)])
    assert all(len(f.points) < len(g.points) for f, g in zip(lost, drive))
    screened = occluded_drives([drive])[0]
    for derived in (lost, overhead_drives([drive])[0], screened):
        assert all(f.times is not None and len(f.times) == len(f.points) for f in derived)
        assert all(f.times is None for f in deskewed(derived))
    # a screen's returns are placed in the frame at the stamp: their time is 0
    moved = [np.any(f.points != g.points, axis=1) for f, g in zip(screened, drive)]
    assert sum(m.sum() for m in moved) > 0
    assert all((f.times[m] == 0).all() for f, m in zip(screened, moved))
    from suit_ros.data.augment import Augmentation, apply
    dropped = apply(drive[1], Augmentation(False, 0.0, 1.0, point_dropout=0.3))
    assert len(dropped.times) == len(dropped.points) < len(drive[1].points)
    assert model_frame(drive, 2, 3).times is None       # accumulated: no sweep's times
    with pytest.raises(ValueError, match='times for'):
        deskew(drive[0].points, drive[0].times[:-1], np.zeros(6), np.eye(4))


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    """Two small synthetic bags: swept over time (with the returns' times) and at one
    instant."""
    from dataclasses import replace

    from suit_ros.data.sim import preset
    from suit_ros.data.sim.recording import write_bag
    root = tmp_path_factory.mktemp('bags')
    cfg = preset('test', frames=3)
    write_bag(root / 'swept', replace(cfg, lidar=replace(cfg.lidar, motion_distortion=True)), 4)
    write_bag(root / 'instant', cfg, 4)
    return root / 'swept', root / 'instant'


def test_bag_frames_carry_their_returns_times(bags):
    from suit_ros.data.bag import read_bag_frames
    swept = list(read_bag_frames(bags[0]))
    assert all(len(f.times) == len(f.points) and 0.09 < f.times.max() < 0.1 for f in swept)
    assert all(f.times is None for f in read_bag_frames(bags[1]))     # all 0: one instant


def test_training_on_bags_can_deskew_as_the_node_does(bags):
    from suit_ros import CLASS_NAMES
    from suit_ros.data.sequences import bag_sequences
    from suit_ros.evaluate import deskewed
    from suit_ros.train import TrainConfig, training_sequences
    tc = TrainConfig(dataset='bags', dataset_paths=(str(bags[0]),), deskew=True)
    data = training_sequences(tc, CLASS_NAMES)
    want = deskewed(bag_sequences([bags[0]])[0])
    for got, w in zip(data[0], want):
        np.testing.assert_array_equal(got.points, w.points)
    as_taken = training_sequences(TrainConfig(dataset='bags', dataset_paths=(str(bags[0]),)),
                                  CLASS_NAMES)
    assert not np.array_equal(as_taken[0][1].points, data[0][1].points)
