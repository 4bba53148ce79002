"""In-process A/B of the step's threads: the single frame with its small work on THREADS
torch threads and on one (``small_work_one_thread``), SUIT serial (``beside=False``), SUIT
with the past term beside the encoder, and that with its small work on one thread; every
runner steps each demo frame in turn; p50 of each stage, the ratios, the paired per-frame
differences of the totals, and whether the boxes are the same.

Usage: python ab_threads.py CHECKPOINT THREADS FRAMES [PRECISION]   (default auto)
"""
import argparse
import sys

import numpy as np
import torch

from suit_ros import bench
from suit_ros.data.sim import preset
from suit_ros.data.sim.scene import Simulation, to_frame
from suit_ros.evaluate import step_inputs
from suit_ros.heap import keep_freed_memory
from suit_ros.model.streaming import StreamingDetector
from suit_ros.tracking import TrackerConfig

keep_freed_memory()
checkpoint, threads, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
precision = sys.argv[4] if len(sys.argv) > 4 else 'auto'
torch.set_num_threads(threads)
args = argparse.Namespace(config=None, checkpoint=checkpoint)
sim = Simulation(preset('demo-real', frames=60), 7)
inputs = [step_inputs(to_frame(sim.render(k % 60), 7)) for k in range(n)]


def make(temporal: str, small: bool, beside: bool | None = None) -> StreamingDetector:
    runner = StreamingDetector(bench._model(args, temporal), 'cpu', precision=precision,
                               tracker=TrackerConfig(), beside=beside)
    runner.model.small_work_one_thread = small
    return runner


runners = {'none_T': make('none', False), 'none_1': make('none', True),
           'suit_serial_T': make('suit', False, False), 'suit_T': make('suit', False),
           'suit_1': make('suit', True)}
T: dict[str, dict[str, list[float]]] = {k: {} for k in runners}
boxes: dict[str, list[np.ndarray]] = {k: [] for k in runners}
for i, a in enumerate(inputs):
    for key, runner in runners.items():
        res = runner.step(*a)
        boxes[key].append(res.detections.boxes)
        if i >= 3:
            for stage, v in res.timings.items():
                T[key].setdefault(stage, []).append(v * 1e3)
for key in runners:
    print(f'{key:14s}', ' '.join(f'{s} {np.median(v):.2f}' for s, v in T[key].items()))
t = {k: np.median(T[k]['total']) for k in T}
same = all(np.array_equal(x, y) for x, y in zip(boxes['suit_T'], boxes['suit_1'])) and all(
    np.array_equal(x, y) for x, y in zip(boxes['suit_serial_T'], boxes['suit_T']))


def paired(a: str, b: str) -> float:
    return float(np.median(np.array(T[a]['total']) - np.array(T[b]['total'])))


print(f"paired median differences (ms): serial_T - beside_T "
      f"{paired('suit_serial_T', 'suit_T'):.2f}, beside_T - beside_1 "
      f"{paired('suit_T', 'suit_1'):.2f}, none_T - none_1 "
      f"{paired('none_T', 'none_1'):.2f}")
print(f"threads {threads}: SUIT / single: serial {t['suit_serial_T'] / t['none_T']:.3f}, beside "
      f"{t['suit_T'] / t['none_T']:.3f}, beside and small work on one thread "
      f"{t['suit_1'] / t['none_1']:.3f} (single frame, one thread / T "
      f"{t['none_1'] / t['none_T']:.3f}); SUIT's boxes the same all three ways: {same}")
