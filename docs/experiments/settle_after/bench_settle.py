"""`suit-ros bench`'s step measurement alone (its runners, frames and interleaving, tracker
on, precision auto), for each checkpoint given: the step to the detections and the model's
whole work on the frame, p50 ms, and SUIT's over the single frame's. Runs in a tree before
this page's change too (there the step holds the sampling: step and frame are the same).

Usage: python bench_settle.py THREADS FRAMES CHECKPOINT...
"""
import argparse
import sys

import torch

from suit_ros import bench
from suit_ros.data.sim import preset
from suit_ros.data.sim.scene import Simulation, to_frame
from suit_ros.heap import keep_freed_memory
from suit_ros.model.streaming import StreamingDetector
from suit_ros.msg_adapters.classes import MessageClasses
from suit_ros.msg_adapters.pointcloud2 import array_to_pointcloud2
from suit_ros.tracking import TrackerConfig


def demo_drive(threads: int, n: int) -> tuple[list, list, MessageClasses]:
    """The bench's inputs: the demo drive's first ``n`` frames and their clouds as
    PointCloud2, torch on ``threads`` threads, the allocator as the node sets it."""
    keep_freed_memory()
    torch.set_num_threads(threads)
    sim = Simulation(preset('demo-real', frames=max(n, 12)), 7)
    rendered = [sim.render(k) for k in range(n)]
    C = MessageClasses.from_rclpy()
    return ([to_frame(f, 7) for f in rendered],
            [array_to_pointcloud2(f.cloud, C.header(f.stamp_ns, 'lidar'), C) for f in rendered],
            C)


def main() -> None:
    threads, n = int(sys.argv[1]), int(sys.argv[2])
    frames, clouds, C = demo_drive(threads, n)
    for checkpoint in sys.argv[3:]:
        args = argparse.Namespace(config=None, checkpoint=checkpoint)
        runners = {t: StreamingDetector(bench._model(args, t), 'cpu', precision='auto',
                                        tracker=TrackerConfig())
                   for t in ('none', 'suit', 'dense')}
        res = bench._per_stage(runners, frames, clouds, C)
        s = res['step_ms']
        f = res.get('frame_ms', s)
        print(f"{checkpoint} threads {threads}: step none {s['none']['p50']:.2f} suit "
              f"{s['suit']['p50']:.2f} ms, {res['suit_over_single']:.3f}x; frame none "
              f"{f['none']['p50']:.2f} suit {f['suit']['p50']:.2f} ms, "
              f"{res.get('suit_over_single_frame', res['suit_over_single']):.3f}x", flush=True)
        for r in runners.values():
            r.close()


if __name__ == '__main__':
    main()
