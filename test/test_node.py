"""The detector node over real DDS: node, player and probe in separate processes/contexts."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from rclpy.qos import QoSProfile, QoSReliabilityPolicy
from rosgraph import (
    Probe,
    diag_values,
    node_checkpoint,
    ros_env,
    running_node,
    start_node,
    stop,
    synthetic_bag,
)

# separate processes over DDS: integration tests, outside the fast unit loop
pytestmark = [pytest.mark.ros, pytest.mark.slow]


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    # swept as a real spinning sensor's driver publishes it: the node deskews by its times
    return synthetic_bag(tmp_path_factory.mktemp('bag'), 12, 21, 'mcap', distorted=True)


@pytest.fixture(scope='module')
def checkpoint(tmp_path_factory):
    return node_checkpoint(tmp_path_factory.mktemp('ckpt'))


class Recorder:
    def __init__(self):
        from diagnostic_msgs.msg import DiagnosticArray
        from sensor_msgs.msg import PointCloud2
        from visualization_msgs.msg import MarkerArray
        self.p = Probe()
        self.dets, self.markers, self.diags = [], [], []
        n = self.p.node
        n.create_subscription(PointCloud2, '/detector/detections', self.dets.append, 100)
        n.create_subscription(MarkerArray, '/detector/markers', self.markers.append, 100)
        n.create_subscription(DiagnosticArray, '/diagnostics',
                              lambda m: self.diags.append(diag_values(m)), 100)
        self.pub = n.create_publisher(PointCloud2, '/points', QoSProfile(
            depth=10, reliability=QoSReliabilityPolicy.RELIABLE))

    def ready(self, node_proc, timeout=60.0):
        ok = self.p.spin_until(lambda: bool(self.diags) or node_proc.poll() is not None,
                               timeout)
        assert ok and node_proc.poll() is None, stop(node_proc)
        # wait for discovery of our publisher by the node
        self.p.spin_until(lambda: self.pub.get_subscription_count() > 0, 20.0)


@pytest.fixture()
def node_and_recorder(checkpoint):
    with running_node(checkpoint, Recorder, 'diagnostics_period_s:=0.2') as pair:
        yield pair


def stamp_ns(msg):
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def test_plays_bag_and_publishes_stamped_detections(node_and_recorder, bag):
    proc, rec = node_and_recorder
    # start after the node's points QoS follows the player (re-checked every second): clouds
    # published while the subscription is being replaced can be lost (see the README)
    player = subprocess.Popen([sys.executable, '-m', 'suit_ros.cli', 'play', str(bag),
                               '--rate', '0.25', '--start-delay', '2.5',
                               '--wait-subscribers', '20'], env=ros_env(),
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    rec.p.spin_until(lambda: player.poll() is not None, 90.0)

    def settled() -> bool:          # every cloud taken is published, with its markers
        d = rec.diags[-1] if rec.diags else {}
        return (int(d.get('frames_out', -1)) + int(d.get('dropped_frames', 0))
                == int(d.get('frames_in', 0)) and len(rec.dets) == int(d['frames_out'])
                == len(rec.markers) and len(rec.dets) >= 12)
    rec.p.spin_until(settled, 30.0)
    stop(player)
    from suit_ros.data.bag import open_reader
    with open_reader(bag) as r:
        stamps = sorted(stamp_ns(r.deserialize(raw, c.msgtype))
                        for c, _, raw in r.messages() if c.topic == '/points')
    got = [stamp_ns(m) for m in rec.dets]
    dropped = int(rec.diags[-1]['dropped_frames'])
    assert len(got) + dropped >= len(stamps) - 1 and len(got) >= len(stamps) // 2
    assert set(got) <= set(stamps) and got == sorted(got)
    assert all(m.header.frame_id == 'lidar' for m in rec.dets)
    assert {stamp_ns(m.markers[0]) for m in rec.markers} == set(got)
    assert all(m.markers[0].action == 3 for m in rec.markers)           # DELETEALL first
    last = rec.diags[-1]
    assert last['pose_source'] == 'odometry' and last['used_memory'] == 'True'
    assert last['deskew'].startswith('on: sweep 0.1'), last['deskew']
    assert last['traffic_side'].startswith('right'), last['traffic_side']   # the drive's
    assert int(last['memory_bytes']) > 0 and float(last['model_ms_p50']) > 0
    # the tracker (on by default): track ids over the wire, kept across frames
    from suit_ros.msg_adapters.detections import pointcloud2_to_detections
    from suit_ros.tracking import TrackerConfig
    ids = [set(pointcloud2_to_detections(m)['track_id'].tolist()) - {0} for m in rec.dets]
    assert sum(bool(a & b) for a, b in zip(ids, ids[1:])) >= len(ids) // 2
    # and each box's velocity standard deviation, the filter's: tracks that have run a few
    # frames are surer than the head alone
    read = [pointcloud2_to_detections(m) for m in rec.dets]
    std = np.concatenate([r['vel_std'] for r in read])
    speed = np.concatenate([np.hypot(*r['velocities'].T) for r in read])
    assert len(std) and np.isfinite(std).all() and (std > 0).all()
    cfg = TrackerConfig()                # coasting adds a little; the speed widens it
    coast = int(cfg.coast_s * 10 + 0.25)                  # frames coasted at 10 Hz
    most = np.sqrt(cfg.vel_sigma ** 2 + coast * (cfg.max_gap_s * cfg.accel_sigma) ** 2)
    assert (std <= np.hypot(most, cfg.speed_std_fraction * speed) + 1e-4).all()
    assert (std < 0.5 * cfg.vel_sigma).any()
    assert int(last['tracks']) > 0
    # why each box is there (held: 0 seen, 1 carried, 2 coasted), over the wire; the last
    # frame's held boxes counted in the diagnostics
    assert all(set(r['held'].tolist()) <= {0, 1, 2} for r in read)
    assert sum(int((r['held'] == 0).sum()) for r in read) > 0
    held_last = {stamp_ns(m): int((pointcloud2_to_detections(m)['held'] > 0).sum())
                 for m in rec.dets}
    assert int(last['held_boxes']) in held_last.values()


def cloud(stamp, fields='xyzi', n=2000, big=False, nan=False, pad=0):
    from suit_ros.msg_adapters.classes import MessageClasses
    from suit_ros.msg_adapters.pointcloud2 import array_to_pointcloud2
    C = MessageClasses.from_rclpy()
    rng = np.random.default_rng(int(stamp % 1000))
    names = ['x', 'y', 'z'] + (['intensity'] if 'i' in fields else [])
    order = '>' if big else '<'
    dt = np.dtype({'names': names, 'formats': [order + 'f4'] * len(names),
                   'offsets': [4 * i for i in range(len(names))],
                   'itemsize': 4 * len(names) + pad})
    a = np.zeros(n, dt)
    for k in names:
        a[k] = rng.uniform(-30, 30, n) if k in 'xy' else rng.uniform(-2, 0, n)
    if nan:
        a['x'] = np.nan
    msg = array_to_pointcloud2(a, C.header(stamp, 'lidar'), C)
    if big:   # re-encode big-endian by hand
        import array
        raw = a.astype(dt).tobytes()
        msg.is_bigendian = True
        msg.data = array.array('B', raw)
    return msg


def test_bad_inputs_over_the_wire(node_and_recorder):
    proc, rec = node_and_recorder
    base = 2_000_000_000_000_000_000
    cases = [('normal', cloud(base)), ('empty', cloud(base + 10**8, n=0)),
             ('nan', cloud(base + 2 * 10**8, nan=True)),
             ('no_intensity', cloud(base + 3 * 10**8, fields='xyz')),
             ('big_endian', cloud(base + 4 * 10**8, big=True)),
             ('padded', cloud(base + 5 * 10**8, pad=12)),
             ('backwards', cloud(base + 1 * 10**8 + 5))]
    seen = {}
    for name, msg in cases:
        n_before = len(rec.dets)
        rec.pub.publish(msg)
        assert rec.p.spin_until(lambda n=n_before: len(rec.dets) > n, 30.0), name
        out = rec.dets[-1]
        assert stamp_ns(out) == stamp_ns(msg) and out.header.frame_id == 'lidar', name
        # diagnostics that have counted this frame (a timer's, not the frame's own)
        published = len(rec.dets)
        assert rec.p.spin_until(lambda k=published: bool(rec.diags) and int(
            rec.diags[-1].get('frames_out', 0)) >= k, 30.0), name
        seen[name] = (out, rec.diags[-1])
    assert seen['empty'][0].width == 0 and 'empty cloud' in seen['empty'][1]['last_warning']
    assert seen['nan'][0].width == 0 and seen['nan'][1]['points_nonfinite'] == '2000'
    assert seen['no_intensity'][1]['has_intensity'] == 'False'
    assert seen['big_endian'][1]['points_used'] != '0'
    assert seen['padded'][1]['points_used'] != '0'
    assert 'no odometry' in seen['normal'][1]['pose_source']
    assert 'backwards' in seen['backwards'][1]['last_reset_reason']
    assert proc.poll() is None                                   # still running


def test_reset_service_and_runtime_parameters(node_and_recorder):
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters
    from std_srvs.srv import Trigger
    proc, rec = node_and_recorder
    cli = rec.p.node.create_client(Trigger, '/detector/reset_memory')
    assert cli.wait_for_service(timeout_sec=10.0)
    fut = cli.call_async(Trigger.Request())
    assert rec.p.spin_until(fut.done, 10.0) and fut.result().success
    params = rec.p.node.create_client(SetParameters, '/detector/set_parameters')
    assert params.wait_for_service(timeout_sec=10.0)

    def set_param(name, value):
        v = ParameterValue(type=ParameterType.PARAMETER_DOUBLE_ARRAY, double_array_value=value) \
            if isinstance(value, list) else ParameterValue(type=ParameterType.PARAMETER_STRING,
                                                           string_value=value)
        f = params.call_async(SetParameters.Request(parameters=[Parameter(name=name, value=v)]))
        assert rec.p.spin_until(f.done, 10.0)
        return f.result().results[0]
    assert set_param('score_thresholds', [0.3, 0.3, 0.2, 0.2]).successful
    bad = set_param('score_thresholds', [2.0])
    assert not bad.successful and 'within 0..1' in bad.reason
    assert not set_param('checkpoint', 'x').successful               # read-only
    n_before = len(rec.dets)
    rec.pub.publish(cloud(3_000_000_000_000_000_000))
    assert rec.p.spin_until(lambda: len(rec.dets) > n_before, 30.0)
    assert rec.p.spin_until(
        lambda: 'service' in rec.diags[-1].get('last_reset_reason', ''), 30.0), rec.diags[-1]
    assert 'reset_memory service' in rec.diags[-1]['last_reset_reason']


def test_node_refuses_to_start_with_a_bad_checkpoint(tmp_path):
    bad = tmp_path / 'bad.pt'
    bad.write_bytes(b'\x80\x04K\x01.')                               # a pickle
    proc = start_node(str(bad))
    try:
        proc.wait(60)
    finally:
        out = stop(proc)
    assert proc.returncode == 1 and 'pickle' in out
