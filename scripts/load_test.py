#!/usr/bin/env python3
"""Load test (issue 7): the node under a publisher at twice its sustainable rate, then relief.

Plays the demo bag in a loop at ``--rate`` x 10 Hz (default 2.0: 20 Hz, about twice what the
node sustains on 2 cores) for ``--minutes``, then at 0.5x for ``--relief`` seconds. Prints, per
minute, frames in/out, drops (from /diagnostics) and latency p50/p95 (cloud received ->
detections received at a probe), so a growing backlog or unbounded latency would show.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--minutes', type=float, default=10.0)
    parser.add_argument('--rate', type=float, default=2.0)
    parser.add_argument('--relief', type=float, default=60.0)
    args = parser.parse_args()
    from diagnostic_msgs.msg import DiagnosticArray
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, QoSReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from suit_ros.checkpoint import default_checkpoint_path
    from suit_ros.data.sim import preset
    from suit_ros.data.simulate_cli import write_bag
    from suit_ros.rosenv import local_ros_env
    env = local_ros_env()
    os.environ.update(env)
    bag = 'out/demo/demo-seed7-100f'
    if not os.path.exists(bag):
        write_bag(bag, preset('demo-real', frames=100), 7, 'mcap')
    node = subprocess.Popen([sys.executable, '-m', 'suit_ros.node', '--ros-args', '-p',
                             f'checkpoint:={default_checkpoint_path()}', '-p', 'threads:=2'],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ctx = Context()
    rclpy.init(context=ctx)
    probe = rclpy.create_node('suit_ros_load_probe', context=ctx)
    sent: dict[tuple[int, int], float] = {}
    events: list[tuple[float, float]] = []
    diags: list[tuple[float, dict[str, str]]] = []

    def key(m):
        return (m.header.stamp.sec, m.header.stamp.nanosec)

    def on_cloud(m):
        sent[key(m)] = time.monotonic()

    def on_det(m):
        t = time.monotonic()
        if key(m) in sent:
            events.append((t, t - sent.pop(key(m))))
    probe.create_subscription(PointCloud2, '/points', on_cloud,
                              QoSProfile(depth=10, reliability=QoSReliabilityPolicy.RELIABLE))
    probe.create_subscription(PointCloud2, '/detector/detections', on_det, 50)
    probe.create_subscription(DiagnosticArray, '/diagnostics', lambda m: diags.append(
        (time.monotonic(), {kv.key: kv.value for kv in m.status[0].values})), 10)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(probe)
    while not diags:
        ex.spin_once(timeout_sec=0.1)

    def play(rate, seconds):
        p = subprocess.Popen([sys.executable, '-m', 'suit_ros.cli', 'play', bag, '--loop',
                              '--rate', str(rate), '--topics', '/points', '/odom',
                              '--start-delay', '0.5', '--wait-subscribers', '20'],
                             env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        start = time.monotonic()
        while time.monotonic() - start < seconds:
            ex.spin_once(timeout_sec=0.02)
        p.terminate()
        p.wait(10)
        return start
    t0 = play(args.rate, args.minutes * 60)
    t1 = play(0.5, args.relief)
    end = time.monotonic()
    ex.shutdown()
    probe.destroy_node()
    rclpy.try_shutdown(context=ctx)
    node.terminate()
    node.wait(10)

    def window(a, b, label):
        lat = [lt for t, lt in events if a <= t < b]
        d = [v for t, v in diags if a <= t < b]
        fin = int(d[-1]['frames_in']) - int(d[0]['frames_in']) if len(d) > 1 else 0
        drop = int(d[-1]['dropped_frames']) - int(d[0]['dropped_frames']) if len(d) > 1 else 0
        p50 = np.median(lat) * 1e3 if lat else float('nan')
        p95 = np.percentile(lat, 95) * 1e3 if lat else float('nan')
        print(f'{label:<22} in {fin:>5}  out {len(lat):>5}  dropped {drop:>5}  latency p50 '
              f'{p50:6.1f} ms  p95 {p95:6.1f} ms')
    print(f'load test: {args.rate * 10:.0f} Hz for {args.minutes} min, then 5 Hz for '
          f'{args.relief:.0f} s')
    m = 0
    while t0 + 60 * m < t1:
        window(t0 + 60 * m, min(t0 + 60 * (m + 1), t1), f'overload minute {m + 1}')
        m += 1
    window(t1, end, 'relief (5 Hz)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
