"""Faults found against the live node, over real DDS: odometry from the future, a one-frame
warning that /diagnostics must show, Ctrl-C while clouds flow."""
from __future__ import annotations

import signal
import time

import pytest
from rosgraph import Probe, diag_values, node_checkpoint, running_node, start_node, stop
from test_node import cloud

pytestmark = [pytest.mark.ros, pytest.mark.slow]
S = 10**9


@pytest.fixture(scope='module')
def checkpoint(tmp_path_factory):
    return node_checkpoint(tmp_path_factory.mktemp('ckpt'))


class Watcher:
    """Publishes clouds (reliable) and odometry; records diagnostics with level and message."""

    def __init__(self):
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from rclpy.qos import QoSProfile, QoSReliabilityPolicy
        from sensor_msgs.msg import PointCloud2
        self.p = Probe('fault_probe')
        n = self.p.node
        self.diags: list[tuple[int, str, dict[str, str], float]] = []
        self.dets: list[object] = []

        def on_diag(m):
            for st in m.status:
                if st.name.endswith(': suit_ros detector'):
                    self.diags.append((int.from_bytes(st.level, 'little')
                                       if isinstance(st.level, bytes) else int(st.level),
                                       st.message, diag_values(m), time.monotonic()))
        n.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 100)
        n.create_subscription(PointCloud2, '/detector/detections', self.dets.append, 100)
        self.pub = n.create_publisher(PointCloud2, '/points', QoSProfile(
            depth=10, reliability=QoSReliabilityPolicy.RELIABLE))
        self.odom = n.create_publisher(Odometry, '/odom', 100)

    def ready(self, proc, timeout=60.0):
        ok = self.p.spin_until(lambda: bool(self.diags) or proc.poll() is not None, timeout)
        assert ok and proc.poll() is None, stop(proc)
        self.p.spin_until(lambda: self.pub.get_subscription_count() > 0
                          and self.odom.get_subscription_count() > 0, 20.0)

    def now_ns(self) -> int:
        return self.p.node.get_clock().now().nanoseconds

    def odometry(self, stamp: int):
        from nav_msgs.msg import Odometry
        m = Odometry()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, S)
        m.header.frame_id, m.child_frame_id = 'odom', 'base_link'
        m.pose.pose.orientation.w = 1.0
        self.odom.publish(m)

    def frame(self, msg, timeout=30.0):
        n = len(self.dets)
        self.pub.publish(msg)
        assert self.p.spin_until(lambda: len(self.dets) > n, timeout)


@pytest.fixture()
def node_and_watcher(checkpoint):
    with running_node(checkpoint, Watcher, 'diagnostics_period_s:=0.2') as pair:
        yield pair


def test_odometry_from_the_future_is_refused_and_counted(node_and_watcher):
    proc, w = node_and_watcher
    now = w.now_ns()
    for k in range(10):                                  # 0.2 s of real odometry
        w.odometry(now - S // 5 + k * S // 50)
    w.odometry(now + 10 * S)                             # one from 10 s ahead
    w.p.spin_for(0.3)
    w.frame(cloud(now))                                  # covered by the real odometry
    w.p.spin_until(lambda: w.diags[-1][2].get('odometry_rejected') == '1'
                   and w.diags[-1][2].get('frames_out') == '1', 5.0)
    assert w.diags[-1][2]['odometry_rejected'] == '1'
    assert w.diags[-1][2]['pose_source'] == 'odometry'
    # the odometry stops; a cloud 1 s later must run single-frame and say so, not
    # interpolate toward the pose from the future
    w.frame(cloud(now + S))
    w.p.spin_until(lambda: w.diags[-1][2].get('frames_out') == '2', 5.0)
    level, message, values, _ = w.diags[-1]
    assert values['pose_source'].startswith('none') and 'single-frame' in message
    assert not values['pose_age_s'].startswith('-')
    assert proc.poll() is None


def test_a_frame_id_change_stays_visible_in_diagnostics(node_and_watcher):
    proc, w = node_and_watcher
    base = w.now_ns()
    w.frame(cloud(base))
    changed = cloud(base + S // 10)
    changed.header.frame_id = 'other_lidar'
    w.frame(changed)
    seen = time.monotonic()
    steady = cloud(base + 2 * S // 10)                   # the new frame from now on
    steady.header.frame_id = 'other_lidar'
    w.frame(steady)

    def held() -> list:                                   # inside the warning's 5 s hold
        return [d for d in w.diags if seen + 1.0 < d[3] < seen + 4.5]
    assert w.p.spin_until(lambda: bool(held()), 10.0), 'no diagnostics 1 s after the change'
    later = held()
    assert all(d[0] >= 1 and 'frame_id' in d[1] for d in later), [d[1] for d in later]
    assert proc.poll() is None


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_while_clouds_flow_stops_cleanly(checkpoint, sig):
    """Ctrl-C (or a launch's SIGTERM) while clouds flow: the worker stops before the
    context goes, the process exits 0 without an error."""
    proc = start_node(checkpoint, 'diagnostics_period_s:=0.2')
    w = Watcher()
    try:
        w.ready(proc)
        base = w.now_ns()
        for k in range(40):                               # 20 Hz, faster than the node
            w.pub.publish(cloud(base + k * S // 20, n=20000))
            w.p.spin_for(0.05)
        assert w.p.spin_until(lambda: bool(w.dets), 30.0), 'the node published nothing'
        proc.send_signal(sig)
        for k in range(10):                               # clouds keep coming meanwhile
            w.pub.publish(cloud(base + (40 + k) * S // 20, n=20000))
            w.p.spin_for(0.05)
        rc = proc.wait(20)
    finally:
        w.p.close()
        out = stop(proc)
    assert rc == 0, out[-3000:]
    assert 'frame failed' not in out and 'RCLError' not in out, out[-3000:]
    assert 'Traceback' not in out, out[-3000:]


def test_a_burst_is_counted_as_replaced_not_lost(node_and_watcher):
    """Clouds faster than the model: the newest is taken, the others are replaced in the
    node's mailbox and counted as dropped; none is reported as lost before the callback (the
    reader keeps a few, so the executor takes every one). The replaced clouds still feed the
    model's sweeps: the last input holds the last three clouds."""
    proc, w = node_and_watcher
    base = w.now_ns()
    for k in range(-10, 11):                              # odometry over the burst
        w.odometry(base + k * S // 50)
    w.frame(cloud(base, n=20000))
    for k in range(1, 9):                                 # a burst, back to back
        w.pub.publish(cloud(base + k * S // 100, n=20000))
    w.p.spin_until(lambda: w.diags[-1][2].get('frames_in') == '9', 20.0)

    def settled() -> bool:                                # the last cloud may still be running
        v = w.diags[-1][2]
        return int(v.get('dropped_frames', 0)) + int(v.get('frames_out', 0)) == 9

    w.p.spin_until(settled, 20.0)
    values = w.diags[-1][2]
    assert values['frames_in'] == '9', values
    assert values['lost_before_callback'] == '0', values
    assert int(values['dropped_frames']) > 0, values
    assert int(values['dropped_frames']) + int(values['frames_out']) == 9, values
    assert 0 < int(values['frames_sweeps_only']) <= int(values['dropped_frames']), values
    assert values['input_sweeps'] == '3 over 0.02 s', values
    assert 'never received' not in w.diags[-1][1]
