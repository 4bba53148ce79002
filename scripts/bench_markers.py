#!/usr/bin/env python3
"""Publish cost of the node's outputs: the MarkerArray and the detections cloud.

For several box counts, prints medians over repeated runs of: building the MarkerArray (one
LINE_LIST per class plus a label per box, public constructors), publishing it through an rclpy
publisher (conversion to the C message and serialization happen in ``publish``; one local
subscriber in another context so that DDS really sends it), and the same for the detections
PointCloud2.

Usage: . scripts/env.sh && python scripts/bench_markers.py [--repeats 30]
"""
from __future__ import annotations

import argparse
from collections.abc import Callable
import functools
import statistics
import sys
import time


def median_ms(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time of ``fn`` in ms (after one warm-up call)."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def main() -> int:
    """Measure and print."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--repeats', type=int, default=30)
    parser.add_argument('--boxes', type=int, nargs='+', default=[10, 50, 200, 500])
    args = parser.parse_args()
    import numpy as np
    import rclpy
    from rclpy.context import Context
    from sensor_msgs.msg import PointCloud2
    from visualization_msgs.msg import MarkerArray

    from suit_ros.msg_adapters.classes import MessageClasses
    from suit_ros.msg_adapters.detections import (
        detections_to_markerarray,
        detections_to_pointcloud2,
    )
    C = MessageClasses.from_rclpy()
    names = ('car', 'truck', 'pedestrian', 'cyclist')
    pub_ctx, sub_ctx = Context(), Context()
    rclpy.init(context=pub_ctx)
    rclpy.init(context=sub_ctx)
    pub_node = rclpy.create_node('bench_markers_pub', context=pub_ctx)
    sub_node = rclpy.create_node('bench_markers_sub', context=sub_ctx)
    sub_node.create_subscription(MarkerArray, '/bench/markers', lambda m: None, 1)
    sub_node.create_subscription(PointCloud2, '/bench/detections', lambda m: None, 1)
    pub_m = pub_node.create_publisher(MarkerArray, '/bench/markers', 1)
    pub_d = pub_node.create_publisher(PointCloud2, '/bench/detections', 1)
    end = time.monotonic() + 10
    while (pub_m.get_subscription_count() == 0 or pub_d.get_subscription_count() == 0) \
            and time.monotonic() < end:
        time.sleep(0.05)
    print(f'medians of {args.repeats} runs, ms (rclpy messages)')
    print(f'{"boxes":>6} {"markers":>8} {"build":>8} {"publish":>8} {"total":>8} '
          f'{"cloud build":>12} {"cloud publish":>14}')
    rng = np.random.default_rng(0)
    try:
        for n in args.boxes:
            boxes = np.c_[rng.uniform(-40, 40, (n, 2)), rng.uniform(-1, 1, n),
                          rng.uniform(0.5, 10, n), rng.uniform(0.5, 3, n),
                          rng.uniform(1, 3, n), rng.uniform(-3, 3, n)]
            inputs = (boxes, rng.normal(0, 3, (n, 2)), rng.uniform(0, 1, n),
                      rng.integers(0, 4, n), C.header(1, 'lidar'))
            build = functools.partial(detections_to_markerarray, *inputs, names, C)
            cloud = functools.partial(detections_to_pointcloud2, *inputs, C)
            ma, pc = build(), cloud()
            t_build = median_ms(build, args.repeats)
            t_pub = median_ms(functools.partial(pub_m.publish, ma), args.repeats)
            t_cloud = median_ms(cloud, args.repeats)
            t_cloud_pub = median_ms(functools.partial(pub_d.publish, pc), args.repeats)
            print(f'{n:>6} {len(ma.markers):>8} {t_build:>8.2f} {t_pub:>8.2f} '
                  f'{t_build + t_pub:>8.2f} {t_cloud:>12.3f} {t_cloud_pub:>14.3f}', flush=True)
    finally:
        pub_node.destroy_node()
        sub_node.destroy_node()
        rclpy.try_shutdown(context=pub_ctx)
        rclpy.try_shutdown(context=sub_ctx)
    return 0


if __name__ == '__main__':
    sys.exit(main())
