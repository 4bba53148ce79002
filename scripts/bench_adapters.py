#!/usr/bin/env python3
"""Benchmark of the message adapters (issue 2), medians and ratios measured in one run.

PointCloud2 (x, y, z, intensity float32, ring uint16, time float32; point_step 24) of 100k and
1M points -> the (N, 4) float32 detector input with non-finite filtering, from an rclpy message
(data: array.array) and a rosbags message, against a re-implementation of what ROS's
sensor_msgs_py ``read_points_numpy(cloud, ('x','y','z','intensity'), skip_nans=True)`` does
(structured view, stack the fields, drop NaN rows) on the same messages. Then 500 boxes to a
MarkerArray and to the detections PointCloud2.
"""
from __future__ import annotations

import time

import numpy as np
from rosbags.typesys import Stores, get_typestore

from suit_ros.data.sim.scene import POINT_DTYPE
from suit_ros.msg_adapters.classes import MessageClasses
from suit_ros.msg_adapters.detections import detections_to_markerarray, detections_to_pointcloud2
from suit_ros.msg_adapters.pointcloud2 import (
    array_to_pointcloud2,
    dtype_from_fields,
    pointcloud2_to_xyzi,
)


def median_ms(fn, repeats):
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)) * 1e3


def reference_read_points_numpy(msg):
    """What sensor_msgs_py.point_cloud2.read_points_numpy does (re-implemented here)."""
    dtype = dtype_from_fields(msg.fields, msg.point_step, msg.is_bigendian)
    arr = np.frombuffer(msg.data, dtype=dtype, count=msg.width * msg.height)
    pts = np.stack([arr[f] for f in ('x', 'y', 'z', 'intensity')], axis=1)
    return pts[~np.isnan(pts).any(axis=1)]


def main():
    store = get_typestore(Stores.ROS2_JAZZY)
    kinds = [MessageClasses.from_rclpy(), MessageClasses.from_rosbags(store)]
    print(f'{"cloud":<22}{"ours ms":>10}{"reference ms":>14}{"ratio":>8}{"ms/100k":>9}')
    for n in (100_000, 1_000_000):
        rng = np.random.default_rng(0)
        a = np.zeros(n, POINT_DTYPE)
        for k in ('x', 'y', 'z', 'intensity', 'time'):
            a[k] = rng.uniform(-50, 50, n)
        a['x'][rng.integers(0, n, n // 100)] = np.nan
        for C in kinds:
            msg = array_to_pointcloud2(a, C.header(0, 'lidar'), C)
            reps = 30 if n == 100_000 else 8
            ours = median_ms(lambda m=msg: pointcloud2_to_xyzi(m), reps)
            ref = median_ms(lambda m=msg: reference_read_points_numpy(m), reps)
            print(f'{f"{n // 1000}k {C.kind}":<22}{ours:>10.2f}{ref:>14.2f}{ref / ours:>8.2f}'
                  f'{ours / (n / 100_000):>9.2f}')
    n = 500
    rng = np.random.default_rng(1)
    boxes = np.c_[rng.uniform(-40, 40, (n, 3)), rng.uniform(1, 5, (n, 3)), rng.uniform(-3, 3, n)]
    vel, scores, labels = rng.normal(0, 3, (n, 2)), rng.uniform(size=n), rng.integers(0, 4, n)
    names = ('car', 'truck', 'pedestrian', 'cyclist')
    for C in kinds:
        h = C.header(0, 'lidar')
        m = median_ms(lambda C=C, h=h: detections_to_markerarray(boxes, vel, scores, labels, h,
                                                                  names, C), 10)
        p = median_ms(lambda C=C, h=h: detections_to_pointcloud2(boxes, vel, scores, labels, h,
                                                                  C), 30)
        print(f'500 boxes ({C.kind}): MarkerArray {m:.2f} ms, detections PointCloud2 {p:.3f} ms')


if __name__ == '__main__':
    main()
