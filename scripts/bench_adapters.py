#!/usr/bin/env python3
"""Benchmark of the message adapters (issue 2): medians and ratios measured in one run.

1. PointCloud2 of 100k and 1M points (x, y, z, intensity float32, ring uint16, time float32;
   ``point_step`` 22 packed, and 24 padded as real drivers do) -> the (N, 4) float32 detector
   input with non-finite filtering (1 % NaN points), from an rclpy message (``data`` is an
   ``array.array``) and from a rosbags message (a uint8 ndarray). Baseline: the steps of ROS's
   sensor_msgs_py ``read_points_numpy(cloud, ('x', 'y', 'z', 'intensity'), skip_nans=True)``
   (a structured view, the fields stacked, a finite filter), written out below and run on the
   same messages. It is not sensor_msgs_py itself (not installable here), so the ratio says
   nothing about the real package's speed. Goal: <= ~1.1 ms per 100k points.
2. Writing: ``array_to_pointcloud2`` for rclpy against passing the bytes to the generated
   constructor (``data=``), which copies them again.
3. 500 boxes -> MarkerArray and -> the detections PointCloud2 (``scripts/bench_markers.py``
   measures building and publishing at several box counts).

Run: ``python scripts/bench_adapters.py`` (about 10 s).
"""
from __future__ import annotations

import array
from collections.abc import Callable
import resource
import time
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore

from suit_ros.msg_adapters.classes import MessageClasses
from suit_ros.msg_adapters.detections import detections_to_markerarray, detections_to_pointcloud2
from suit_ros.msg_adapters.pointcloud2 import (
    array_to_pointcloud2,
    dtype_from_fields,
    fields_from_dtype,
    pointcloud2_to_xyzi,
)

NAMES = ['x', 'y', 'z', 'intensity', 'ring', 'time']
PACKED = np.dtype({'names': NAMES, 'formats': ['<f4'] * 4 + ['<u2', '<f4'],
                   'offsets': [0, 4, 8, 12, 16, 18], 'itemsize': 22})
PADDED = np.dtype({'names': NAMES, 'formats': ['<f4'] * 4 + ['<u2', '<f4'],
                   'offsets': [0, 4, 8, 12, 16, 20], 'itemsize': 24})


def median_ms(fn: Callable[[], Any], repeats: int) -> tuple[float, float]:
    """Median milliseconds over ``repeats`` calls (after one warm-up) and page faults/call."""
    fn()
    times = []
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults
    return float(np.median(times)) * 1e3, faults / repeats


def reference_read_points_numpy(msg: Any) -> np.ndarray:
    """sensor_msgs_py's read_points_numpy(..., ('x','y','z','intensity'), skip_nans=True),
    re-implemented: structured view, fields stacked, non-finite rows dropped."""
    dtype = dtype_from_fields(msg.fields, msg.point_step, msg.is_bigendian)
    arr = np.frombuffer(msg.data, dtype=dtype, count=msg.width * msg.height)
    pts = np.stack([arr[f] for f in ('x', 'y', 'z', 'intensity')], axis=1)
    return pts[np.isfinite(pts).all(axis=1)]


def make_cloud(n: int, dtype: np.dtype) -> np.ndarray:
    rng = np.random.default_rng(0)
    a = np.zeros(n, dtype)
    for k in ('x', 'y', 'z', 'intensity', 'time'):
        a[k] = rng.uniform(-50, 50, n)
    a['ring'] = rng.integers(0, 128, n)
    a['x'][rng.integers(0, n, n // 100)] = np.nan
    return a


def constructor_copy(points: np.ndarray, header: Any, classes: MessageClasses) -> Any:
    """The straightforward rclpy write: bytes through the generated constructor."""
    return classes.PointCloud2(header=header, height=1, width=len(points),
                               fields=fields_from_dtype(points.dtype, classes),
                               is_bigendian=False, point_step=points.dtype.itemsize,
                               row_step=points.dtype.itemsize * len(points),
                               data=array.array('B', points.tobytes()), is_dense=False)


def main() -> None:
    store = get_typestore(Stores.ROS2_JAZZY)
    rclpy_classes = MessageClasses.from_rclpy()
    kinds = [rclpy_classes, MessageClasses.from_rosbags(store)]
    print('PointCloud2 -> (N, 4) float32 with non-finite filtering (median ms; faults/call)')
    print(f'{"cloud":<28}{"ours ms":>9}{"faults":>8}{"baseline ms":>13}{"faults":>8}'
          f'{"speedup":>9}{"ours ms/100k":>14}')
    for n in (100_000, 1_000_000):
        reps = 40 if n == 100_000 else 10
        for dtype in (PACKED, PADDED):
            a = make_cloud(n, dtype)
            for C in kinds:
                msg = array_to_pointcloud2(a, C.header(0, 'lidar'), C)
                out = pointcloud2_to_xyzi(msg)
                ref = reference_read_points_numpy(msg)
                if not np.array_equal(out.points, ref):
                    raise RuntimeError('fast path and baseline disagree')
                ours, f_ours = median_ms(lambda m=msg: pointcloud2_to_xyzi(m), reps)
                base, f_base = median_ms(lambda m=msg: reference_read_points_numpy(m), reps)
                label = f'{n // 1000}k step {dtype.itemsize} {C.kind}'
                print(f'{label:<28}{ours:>9.2f}{f_ours:>8.0f}{base:>13.2f}{f_base:>8.0f}'
                      f'{base / ours:>9.2f}{ours / (n / 100_000):>14.2f}')
    print('\narray_to_pointcloud2 (rclpy, step 24): median ms')
    for n in (100_000, 1_000_000):
        a = make_cloud(n, PADDED)
        h = rclpy_classes.header(0, 'lidar')
        ours, _ = median_ms(lambda a=a, h=h: array_to_pointcloud2(a, h, rclpy_classes), 10)
        ctor, _ = median_ms(lambda a=a, h=h: constructor_copy(a, h, rclpy_classes), 10)
        print(f'{n // 1000}k points: ours {ours:.2f} ms, bytes through the constructor '
              f'{ctor:.2f} ms ({ctor / ours:.2f}x)')
    n = 500
    rng = np.random.default_rng(1)
    boxes = np.c_[rng.uniform(-40, 40, (n, 3)), rng.uniform(1, 5, (n, 3)), rng.uniform(-3, 3, n)]
    vel, scores, labels = rng.normal(0, 3, (n, 2)), rng.uniform(size=n), rng.integers(0, 4, n)
    names = ('car', 'truck', 'pedestrian', 'cyclist')
    print('\n500 boxes: median ms')
    for C in kinds:
        h = C.header(0, 'lidar')
        m, _ = median_ms(lambda C=C, h=h: detections_to_markerarray(
            boxes, vel, scores, labels, h, names, C), 20)
        count = len(detections_to_markerarray(boxes, vel, scores, labels, h, names, C).markers)
        p, _ = median_ms(lambda C=C, h=h: detections_to_pointcloud2(
            boxes, vel, scores, labels, h, C), 30)
        print(f'{C.kind:<8} MarkerArray ({count} markers) {m:.2f} ms, '
              f'detections PointCloud2 {p:.3f} ms')


if __name__ == '__main__':
    main()
