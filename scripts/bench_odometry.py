#!/usr/bin/env python3
"""Odometry under load: how many frames run single-frame while the node runs flat out.

For each odometry rate, starts the detector node (every parameter at its default, unless
given) in its own process, then publishes from this process, over DDS: odometry at the rate
(reliable, depth 100, stamped with the clock) and a demo-scene cloud (~48k points) at 20 Hz,
faster than the node can process, so inference keeps the cores busy. Prints, per run, the
frames processed and the share of them that ran single-frame (no pose for the stamp), read
from the node's /diagnostics.

Usage: . scripts/env.sh && python scripts/bench_odometry.py [--seconds 20] [--rates 50 100]
       [--node-param odom_wait_s:=0.0 ...]
"""
from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from typing import Any


def one_run(rate_hz: float, seconds: float, node_params: list[str]) -> dict[str, Any]:
    """Run the node against odometry at ``rate_hz``; return its counters."""
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import PointCloud2

    from suit_ros.checkpoint import default_checkpoint_path
    from suit_ros.data.sim import preset
    from suit_ros.data.sim.scene import Simulation
    from suit_ros.harness import Probe, start_node, stop
    from suit_ros.msg_adapters.classes import MessageClasses
    from suit_ros.msg_adapters.pointcloud2 import array_to_pointcloud2
    ckpt = next((p.split(':=', 1)[1] for p in node_params if p.startswith('checkpoint:=')),
                str(default_checkpoint_path()))
    node = start_node(ckpt, *[p for p in node_params if not p.startswith('checkpoint:=')],
                      quiet=True)
    harness_probe = Probe('bench_odometry')
    probe, ex = harness_probe.node, harness_probe.ex
    diags: list[dict[str, str]] = []
    probe.create_subscription(DiagnosticArray, '/diagnostics', lambda m: diags.append(
        {kv.key: kv.value for kv in m.status[0].values}), 10)
    odom_pub = probe.create_publisher(Odometry, '/odom', QoSProfile(depth=100))
    cloud_pub = probe.create_publisher(PointCloud2, '/points', QoSProfile(depth=1))
    C = MessageClasses.from_rclpy()
    sim = Simulation(preset('demo', frames=2), 7).render(1)
    cloud = array_to_pointcloud2(sim.cloud, C.header(0, 'lidar'), C)
    stop_event = threading.Event()

    def publish_odometry() -> None:
        period = 1.0 / rate_hz
        due = time.monotonic()
        x = 0.0
        while not stop_event.is_set():
            msg = Odometry()
            msg.header.stamp = probe.get_clock().now().to_msg()
            msg.header.frame_id, msg.child_frame_id = 'odom', 'base_link'
            x += 10.0 * period
            msg.pose.pose.position.x = x
            msg.pose.pose.orientation.w = 1.0
            odom_pub.publish(msg)
            due += period
            time.sleep(max(0.0, due - time.monotonic()))

    def publish_clouds() -> None:
        while not stop_event.is_set():
            cloud.header.stamp = probe.get_clock().now().to_msg()
            cloud_pub.publish(cloud)
            time.sleep(0.05)
    try:
        end = time.monotonic() + 90
        while time.monotonic() < end and (not diags or odom_pub.get_subscription_count() == 0
                                          or cloud_pub.get_subscription_count() == 0):
            ex.spin_once(timeout_sec=0.1)
        threads = [threading.Thread(target=publish_odometry, daemon=True)]
        threads[0].start()
        time.sleep(1.0)
        threads.append(threading.Thread(target=publish_clouds, daemon=True))
        threads[1].start()
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
        stop_event.set()
        for t in threads:
            t.join()
        n = len(diags)
        end = time.monotonic() + 5
        while len(diags) < n + 2 and time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
    finally:
        harness_probe.close()
        stop(node)
    last = diags[-1]
    out = int(last['frames_out'])
    single = int(last['frames_single_frame'])
    return {'frames_in': int(last['frames_in']), 'frames_out': out, 'single': single,
            'single_pct': 100.0 * single / max(out, 1),
            'odometry_waits': int(last['odometry_waits']),
            'reasons': {k.split('.', 1)[1]: int(v) for k, v in last.items()
                        if k.startswith('single_frame.')},
            'model_ms_p50': float(last['model_ms_p50']),
            'odom_delay_p50': float(last['odometry_delay_ms_p50']),
            'odom_delay_max': float(last['odometry_delay_ms_max'])}


def main() -> int:
    """Parse the arguments, run every rate, print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--seconds', type=float, default=20.0)
    parser.add_argument('--rates', type=float, nargs='+', default=[50.0, 100.0])
    parser.add_argument('--node-param', action='append', default=[],
                        help='NAME:=VALUE passed to the node (repeatable)')
    args = parser.parse_args()
    from suit_ros.dds import use_large_data_profile
    use_large_data_profile(os.environ)           # this process publishes ~1.2 MB clouds
    print(f'node parameters: {args.node_param or "defaults"}; {args.seconds:.0f} s per rate, '
          'clouds at 20 Hz, odometry depth 100')
    for rate in args.rates:
        r = one_run(rate, args.seconds, args.node_param)
        print(f'odometry {rate:.0f} Hz: {r["frames_out"]} frames processed of '
              f'{r["frames_in"]} received, {r["single"]} single-frame '
              f'({r["single_pct"]:.1f}%; {r["reasons"] or "-"}), waited for odometry '
              f'{r["odometry_waits"]} times, '
              f'model p50 {r["model_ms_p50"]:.0f} ms, odometry delay at the node p50 '
              f'{r["odom_delay_p50"]:.1f} ms, max (last 500) {r["odom_delay_max"]:.1f} ms',
              flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
