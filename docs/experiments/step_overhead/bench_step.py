"""`suit-ros bench`'s step measurement alone (its runners, frames and interleaving: the single
frame, SUIT and the dense memory step each frame in turn, tracker on, precision auto): p50 of
each model's step, SUIT's over the single frame's, and SUIT's memory over the dense one's after
2 and 10 frames (since stop 67). Run it in two source trees (git
worktrees) in turn to compare them on one machine.

Usage: python bench_step.py CHECKPOINT THREADS FRAMES
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

keep_freed_memory()
checkpoint, threads, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
torch.set_num_threads(threads)
args = argparse.Namespace(config=None, checkpoint=checkpoint)
sim = Simulation(preset('demo-real', frames=max(n, 12)), 7)
rendered = [sim.render(k) for k in range(n)]
frames = [to_frame(f, 7) for f in rendered]
C = MessageClasses.from_rclpy()
clouds = [array_to_pointcloud2(f.cloud, C.header(f.stamp_ns, 'lidar'), C) for f in rendered]
runners = {t: StreamingDetector(bench._model(args, t), 'cpu', precision='auto',
                                tracker=TrackerConfig()) for t in ('none', 'suit', 'dense')}
res = bench._per_stage(runners, frames, clouds, C)
s = res['step_ms']
mem = res['memory_ratio_suit_dense']
print(f"{checkpoint} threads {threads}: none {s['none']['p50']:.1f} suit {s['suit']['p50']:.1f}"
      f" dense {s['dense']['p50']:.1f} ms, SUIT / single {res['suit_over_single']:.3f},"
      f" memory after 2 / 10 frames {mem[2]:.2%} / {mem[10]:.2%}")
