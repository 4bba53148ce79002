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
    from rclpy.qos import QoSProfile, QoSReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from suit_ros.checkpoint import default_checkpoint_path
    from suit_ros.harness import Probe, start_node, start_player, stop
    from suit_ros.node_probe import demo_bag
    from suit_ros.rosenv import local_ros_env
    os.environ.update(local_ros_env())
    bag = demo_bag('out/demo', 7, 100)
    node = start_node(str(default_checkpoint_path()), 'threads:=2', quiet=True)
    harness_probe = Probe('suit_ros_load_probe')
    probe = harness_probe.node
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
    harness_probe.spin_until(lambda: bool(diags), 90, 0.1)

    def play(rate, seconds):
        p = start_player(bag, '--loop', '--rate', str(rate), '--topics', '/points', '/odom',
                         '--start-delay', '0.5', '--wait-subscribers', '20')
        start = time.monotonic()
        harness_probe.spin_for(seconds, 0.02)
        stop(p)
        return start
    t0 = play(args.rate, args.minutes * 60)
    t1 = play(0.5, args.relief)
    end = time.monotonic()
    harness_probe.close()
    stop(node)

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
