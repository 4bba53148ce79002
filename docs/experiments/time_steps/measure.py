"""Clouds and odometry whose time goes back: which pose each cloud takes (docs/experiments/
time_steps). Runs the node's DetectionPipeline on the tree on PYTHONPATH; the messages arrive
as a worker takes them (each cloud after the odometry that came before it, drained first; the
worker's wait for odometry is not modelled). Usage: measure.py OUT.json
"""
from __future__ import annotations

from dataclasses import replace
import json
import sys

import numpy as np

S = 10**9
SPEED = 10.0            # m/s along x
ODOM_HZ = (10, 50, 100)
LAG_S = 0.15            # a cloud arrives this long after its stamp (the sweep, the driver)


def cloud_msg(C, stamp):
    from suit_ros.msg_adapters.pointcloud2 import array_to_pointcloud2
    rng = np.random.default_rng(stamp % 997)
    n = 3000
    a = np.zeros(n, [('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4')])
    a['x'], a['y'] = rng.uniform(-30, 30, n), rng.uniform(-30, 30, n)
    a['z'] = rng.uniform(-1.5, 0.5, n)
    a['intensity'] = rng.uniform(0, 100, n)
    return array_to_pointcloud2(a, C.header(stamp, 'lidar'), C)


def odom_msg(stamp, x):
    from nav_msgs.msg import Odometry
    m = Odometry()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(int(stamp), S)
    m.header.frame_id, m.child_frame_id = 'odom', 'base_link'
    m.pose.pose.position.x = float(x)
    m.pose.pose.orientation.w = 1.0
    return m


def scenario(name, odom_hz):
    """Messages ``(arrival_s, kind, stamp_ns, x_true)``: odometry at ``odom_hz`` and clouds at
    10 Hz over 3 s of physical time, stamped by a clock that ``name`` disturbs."""
    T0 = 1_700_000_000 * S
    events = []

    def clock(t):           # physical time -> (stamp, x)
        if name == 'ntp step back 0.5 s':     # (off the odometry's grid by 7 ms)
            return T0 + int((t - (0.507 if t >= 1.5 else 0.0)) * S), SPEED * t
        if name == 'simulator reset 0.6 s back':   # at 1.5 s: time 0.9 s, elsewhere
            return (T0 + int(t * S), SPEED * t) if t < 1.5 else \
                (T0 + int((t - 0.607) * S), -300.0 + SPEED * (t - 1.5))
        if name == 'bag of 0.8 s looped':
            u = t % 0.8
            return T0 + int(u * S), SPEED * u
        return T0 + int(t * S), SPEED * t
    for k in range(int(3.0 * odom_hz)):
        t = k / odom_hz
        stamp, x = clock(t)
        if name == 'one odometry message 0.4 s ahead' and k == int(1.5 * odom_hz):
            stamp += int(0.4 * S)
            x += 50.0
        events.append((t + 0.005, 'odom', stamp, x))
    for k in range(30):
        t = k / 10 + 0.033          # the sensor's own phase
        stamp, x = clock(t)
        events.append((t + LAG_S, 'cloud', stamp, x))
    events.sort(key=lambda e: (e[0], e[1] == 'cloud'))
    return events


def run(name, odom_hz, pipe_factory, C):
    pipe = pipe_factory()
    got = []
    original = pipe._pose

    def spy(*args, **kwargs):
        result = original(*args, **kwargs)
        got.append(result[0])
        return result
    pipe._pose = spy
    counts = {'right': 0, 'wrong': 0, 'none': 0}
    worst = 0.0
    for _, kind, stamp, x in scenario(name, odom_hz):
        if kind == 'odom':
            pipe.add_odometry(odom_msg(stamp, x), 0)
            continue
        got.clear()
        pipe.process(cloud_msg(C, stamp), markers=False)
        T = got[0] if got else None
        if T is None:
            counts['none'] += 1
            continue
        err = abs(float(T[0, 3]) - x)
        worst = max(worst, err)
        counts['right' if err < 0.5 else 'wrong'] += 1
    return {**counts, 'worst_error_m': round(worst, 2)}


def main() -> int:
    from suit_ros.detect_bag import build_pipeline
    from suit_ros.msg_adapters.classes import MessageClasses
    from suit_ros.params import DetectorParams
    C = MessageClasses.from_rclpy()
    params = replace(DetectorParams(), checkpoint='suit_default', deskew=False)
    cache = {}

    def factory():
        if 'p' not in cache:
            cache['p'] = build_pipeline(params, C)
        p = cache['p']
        # a fresh stream each run, the model loaded once
        from suit_ros.pipeline import DetectionPipeline
        return DetectionPipeline(p.detector, params, C)
    names = ['ntp step back 0.5 s', 'simulator reset 0.6 s back', 'bag of 0.8 s looped',
             'one odometry message 0.4 s ahead']
    out = {}
    for name in names:
        for hz in ODOM_HZ:
            r = run(name, hz, factory, C)
            out[f'{name}, odometry {hz} Hz'] = r
            print(f'{name:34s} odometry {hz:3d} Hz: {r}', flush=True)
    with open(sys.argv[1], 'w', encoding='utf-8') as f:
        json.dump(out, f, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
