"""Time spent a frame in the pieces of suit_carry's head (the carry head at its cells, the
fold's layers, the gathered products, the compiled gathers), the module functions wrapped, 60
demo frames, precision auto.

Usage: python forward_at_parts.py THREADS
"""
from collections import defaultdict
from collections.abc import Callable
import functools
import sys
import time
from typing import Any

import numpy as np
import torch

from suit_ros.checkpoint import load_model_as
from suit_ros.data.sim import preset
from suit_ros.data.sim.scene import Simulation, to_frame
from suit_ros.evaluate import step_inputs
from suit_ros.heap import keep_freed_memory
import suit_ros.model.detector as detector
import suit_ros.model.head as head
from suit_ros.model.streaming import StreamingDetector
import suit_ros.ops.kernels as kernels
from suit_ros.tracking import TrackerConfig

keep_freed_memory()
threads = int(sys.argv[1])
torch.set_num_threads(threads)
n = 60
sim = Simulation(preset('demo-real', frames=n), 7)
inputs = [step_inputs(to_frame(sim.render(k), 7)) for k in range(n)]
runner = StreamingDetector(load_model_as('suit_ros/checkpoints/suit_carry.safetensors', None),
                           'cpu', precision='auto', tracker=TrackerConfig())
runner.warm_up()
spent: dict[str, float] = defaultdict(float)
calls: dict[str, int] = defaultdict(int)


def wrap(owner: Any, name: str, label: str = '') -> None:
    fn: Callable[..., Any] = getattr(owner, name)

    @functools.wraps(fn)
    def timed(*a: Any, **k: Any) -> Any:
        t = time.perf_counter()
        out = fn(*a, **k)
        spent[label or name] += time.perf_counter() - t
        calls[label or name] += 1
        return out
    setattr(owner, name, timed)


wrap(head, '_neighbourhoods')
wrap(head, '_at_cells')
wrap(head.HeadFold, 'at', 'fold.at')
wrap(head.HeadFold, 'dense', 'fold.dense')
wrap(detector, 'dilated_cells')
for name in ('feeding_map', 'gather_taps_bf16', 'gather_taps', 'add_tap_spread',
             'add_tap_spread_dense_bf16', 'sum_triples'):
    wrap(kernels, name)
wrap(runner.model.carry.head, 'forward_at')
wrap(runner.model, 'predict')
wrap(runner.model.head, 'forward_lazy')
steps = []
for i, args in enumerate(inputs):
    if i == 5:
        spent.clear()
        calls.clear()
    t = time.perf_counter()
    runner.step(*args)
    if i >= 5:
        steps.append(time.perf_counter() - t)
f = len(steps)
print(f'step p50 {np.median(steps) * 1e3:.2f} ms, threads {threads}')
for k, v in sorted(spent.items(), key=lambda kv: -kv[1]):
    print(f'{k:26s} {v / f * 1e3:6.3f} ms a frame ({calls[k] / f:.1f} calls)')
