"""The synthetic world is right, not just running: geometry, occlusion, ego motion, velocity,
bag output readable by rosbags and rclpy, determinism."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from suit_ros.data.sim import preset
from suit_ros.data.sim.lidar import GROUND, RangeImage, cast, ray_directions
from suit_ros.data.sim.scene import Simulation, points_in_boxes
from suit_ros.ops.geometry import se3_inverse, transform_points

CFG = preset('test', frames=6)


@pytest.fixture(scope='module')
def sim():
    return Simulation(CFG, 11)


@pytest.fixture(scope='module')
def frames(sim):
    return [sim.render(k) for k in range(CFG.frames)]


def xyz(f):
    return np.stack([f.cloud['x'], f.cloud['y'], f.cloud['z']], 1).astype(np.float64)


def test_returns_lie_on_surfaces(frames):
    noise = 5 * CFG.lidar.range_noise + 1e-3
    for f in frames:
        pw = transform_points(f.T_odom_lidar, xyz(f))
        ground = f.surface == GROUND
        assert ground.any() and (~ground).any()
        assert np.abs(pw[ground, 2]).max() < noise + 0.01
        hit = f.surface[~ground]
        boxes = f.boxes_world[hit]
        d = pw[~ground] - boxes[:, :3]
        c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
        local = np.abs(np.stack([d[:, 0] * c + d[:, 1] * s, -d[:, 0] * s + d[:, 1] * c,
                                 d[:, 2]], 1))
        outside = np.clip(local - boxes[:, 3:6] / 2, 0, None).max(1)
        assert np.percentile(outside, 99) < noise
        assert outside.max() < 0.5


def test_num_points_counts_an_objects_returns(sim, frames):
    """The returns in the box, or the object's own where more: a box world's returns lie on
    its boxes' faces, and range noise puts about half of them outside."""
    first_actor = len(sim.world.boxes)
    more = 0
    for f in frames:
        inside = points_in_boxes(xyz(f), f.gt.boxes).sum(0)
        own = np.array([(f.surface == first_actor + int(i) - 1).sum() for i in f.instance_ids])
        np.testing.assert_array_equal(np.maximum(inside, own), f.num_points)
        more += int((own > inside).sum())
    assert more > 0
    assert sum(int((f.num_points > 0).sum()) for f in frames) > 10


def test_occlusion_by_wall():
    lidar = replace(CFG.lidar, dropout=0.0, range_noise=0.0, azimuth_resolution=0.4)
    dirs = ray_directions(lidar)
    origin, R = np.array([0.0, 0.0, 1.8]), np.eye(3)
    car = np.array([[20.0, 0.0, 0.8, 4.5, 1.9, 1.6, 0.0]])
    wall_full = np.array([[10.0, 0.0, 2.0, 0.3, 12.0, 4.0, 0.0]])
    wall_half = np.array([[10.0, 3.0, 2.0, 0.3, 6.2, 4.0, 0.0]])

    def hits_on_car(boxes):
        img = RangeImage(np.full(dirs.shape[:2], np.inf), np.full(dirs.shape[:2], -2),
                         np.zeros(dirs.shape[:2]))
        cast(dirs, origin, R, boxes, slice(None), lidar.max_range, img)
        return int((img.hit == 0).sum())
    alone = hits_on_car(car)
    assert alone > 20
    assert hits_on_car(np.concatenate([car, wall_full])) == 0
    assert 0 < hits_on_car(np.concatenate([car, wall_half])) < alone


def test_ego_motion_static_world_coincides(tmp_path):
    from suit_ros.data.bag import read_bag_frames
    from suit_ros.data.sim.recording import write_bag
    cfg = replace(preset('test', frames=3), lidar=replace(CFG.lidar, range_noise=0.0,
                                                          dropout=0.0))
    write_bag(tmp_path / 'bag', cfg, 5, 'sqlite3')
    fr = list(read_bag_frames(tmp_path / 'bag'))
    sim = Simulation(cfg, 5)
    f0, f1 = sim.render(0), sim.render(1)
    # static returns (ground excluded: its z carries no xy information) of a building/pole id
    s0 = f0.surface
    static = (s0 >= 0) & (s0 < len(sim.world.boxes))
    w0 = transform_points(fr[0].pose, fr[0].points[static, :3])
    # every static world point seen at t0, seen from t1's pose, lies on the same surface
    in1 = transform_points(se3_inverse(fr[1].pose), w0)
    back = transform_points(f1.T_odom_lidar, in1)
    np.testing.assert_allclose(back, w0, atol=1e-4)
    # and the bag's interpolated odometry reproduces the simulator's LiDAR poses
    for k in range(3):
        np.testing.assert_allclose(fr[k].pose, sim.render(k).T_odom_lidar, atol=1e-6)
    np.testing.assert_allclose(fr[0].points[:, :3], xyz(f0), atol=1e-5)


def test_gt_velocity_equals_finite_difference(sim):
    dt = 1.0 / CFG.lidar.rate_hz
    for k in range(1, CFG.frames - 1):
        a, b, c = (sim.render(j) for j in (k - 1, k, k + 1))
        ids_b = list(b.instance_ids)
        for i, iid in enumerate(ids_b):
            if iid not in a.instance_ids or iid not in c.instance_ids:
                continue
            ia, ic = list(a.instance_ids).index(iid), list(c.instance_ids).index(iid)
            pa = transform_points(a.T_odom_lidar, a.gt.boxes[ia:ia + 1, :3])[0]
            pc = transform_points(c.T_odom_lidar, c.gt.boxes[ic:ic + 1, :3])[0]
            v_world = (pc - pa)[:2] / (2 * dt)
            v_l = np.r_[b.gt.velocities[i], 0.0]
            v_w = (b.T_odom_lidar[:3, :3] @ v_l)[:2]
            np.testing.assert_allclose(v_w, v_world, atol=0.35)


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_bag_reads_back_and_is_deterministic(tmp_path, storage):
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import PointCloud2

    from suit_ros.data.bag import open_reader
    from suit_ros.data.sim.recording import write_bag
    cfg = preset('test', frames=2)
    blobs = []
    for run in range(2):
        write_bag(tmp_path / f'b{run}', cfg, 3, storage)
        with open_reader(tmp_path / f'b{run}') as reader:
            topics = {c.topic: c.msgtype for c in reader.connections}
            msgs = [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()]
        blobs.append(msgs)
    assert topics == {'/points': 'sensor_msgs/msg/PointCloud2',
                      '/odom': 'nav_msgs/msg/Odometry',
                      '/gt/objects': 'sensor_msgs/msg/PointCloud2',
                      '/tf_static': 'tf2_msgs/msg/TFMessage'}
    assert blobs[0] == blobs[1]
    for topic, _, raw in blobs[0]:
        if topic == '/points':
            m = deserialize_message(raw, PointCloud2)
            assert m.header.frame_id == 'lidar' and m.point_step == 24 and m.width > 100
            assert [f.name for f in m.fields] == ['x', 'y', 'z', 'intensity', 'time', 'ring']
        elif topic == '/odom':
            assert deserialize_message(raw, Odometry).child_frame_id == 'base_link'


def test_simulate_cli(tmp_path, capsys):
    from suit_ros.cli import main
    assert main(['simulate', '--out', str(tmp_path / 'x'), '--frames', '2', '--preset',
                 'test']) == 0
    assert 'points per frame' in capsys.readouterr().out
    assert main(['simulate', '--out', str(tmp_path / 'x'), '--frames', '2']) == 1   # exists
    assert main(['simulate', '--out', str(tmp_path / 'y'), '--beams', '7']) == 1


def _cache_writer(path, frames, times, go):
    from suit_ros.data.sequences import save_sequence
    go.wait()
    for _ in range(times):
        save_sequence(path, frames)


def test_two_processes_caching_one_drive_leave_a_whole_file(tmp_path, frames):
    """Each writer writes a temporary file of its own (a shared one was renamed under the
    other writer: FileNotFoundError there, and a torn file for a reader)."""
    import multiprocessing as mp

    from suit_ros.data.sequences import load_sequence
    from suit_ros.structures import Frame
    drive = [Frame(xyz(f).astype(np.float32), f.T_odom_base, f.stamp_ns, 'lidar', f.gt,
                   f.num_points, f.instance_ids) for f in frames]
    path = tmp_path / 'drive.npz'
    ctx = mp.get_context('spawn')
    go = ctx.Event()
    writers = [ctx.Process(target=_cache_writer, args=(path, drive, 30, go)) for _ in range(2)]
    for w in writers:
        w.start()
    go.set()                                 # both write at once
    for w in writers:
        w.join(120)
    assert [w.exitcode for w in writers] == [0, 0]
    assert len(load_sequence(path)) == len(drive)
    assert [p.name for p in tmp_path.iterdir()] == ['drive.npz']     # no temporary left
