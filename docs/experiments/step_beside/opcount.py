"""Torch operations a frame by piece of the step (each piece's own, its labelled callees'
counted apart), from the profiler, 2 threads, the checkpoint's SUIT model, 10 demo frames.

Usage: python opcount.py CHECKPOINT
"""
from collections import Counter
from collections.abc import Callable
import functools
import sys
from typing import Any

import torch
from torch.profiler import ProfilerActivity, profile, record_function

from suit_ros.checkpoint import load_model_as
from suit_ros.data.sim import preset
from suit_ros.data.sim.scene import Simulation, to_frame
from suit_ros.evaluate import step_inputs
import suit_ros.model.detector as detector
import suit_ros.model.fusion as fusion
import suit_ros.model.head as head
import suit_ros.model.memory as memory
import suit_ros.model.sampling as sampling
import suit_ros.model.streaming as streaming
from suit_ros.model.streaming import StreamingDetector
from suit_ros.tracking import TrackerConfig

torch.set_num_threads(2)
n = 16
sim = Simulation(preset('demo-real', frames=n), 7)
inputs = [step_inputs(to_frame(sim.render(k), 7)) for k in range(n)]
try:                    # the past term in the step's own thread, where it can be elsewhere
    runner = StreamingDetector(load_model_as(sys.argv[1], None), 'cpu', precision='auto',
                               tracker=TrackerConfig(), beside=False)
except TypeError:       # a tree from before the second thread
    runner = StreamingDetector(load_model_as(sys.argv[1], None), 'cpu', precision='auto',
                               tracker=TrackerConfig())
runner.warm_up()


def wrap(owner: Any, name: str) -> None:
    fn: Callable[..., Any] = getattr(owner, name)

    @functools.wraps(fn)
    def labelled(*a: Any, **k: Any) -> Any:
        with record_function('@' + name):
            return fn(*a, **k)
    setattr(owner, name, labelled)


m = runner.model
for name in ('encode_observed', 'past_term', 'predict', 'decode', 'carried', 'sample_memory'):
    wrap(m, name)
if m.carry is not None:
    wrap(m.carry.head, 'forward_at')
for owner, names in (
        (detector, ('significant_sampling', 'relaxation_window', 'gather_window',
                    'keep_carried', 'sparse_past_terms', 'transform_sample_positions',
                    'moved_memory', 'rotate_velocities', 'gate_past')),
        (sampling, ('coarse_topk', 'refined_nms', 'cell_flags', 'concat_memories')),
        (memory.SparseMemory, ('select',)), (head.CenterHead, ('decode_cells',)),
        (head.HeadFold, ('at', 'dense')), (fusion.FoldedFused, ('rows',)),
        (streaming, ('track_step',))):
    for name in names:
        if hasattr(owner, name):
            wrap(owner, name)
for a in inputs[:6]:
    runner.step(*a)
with profile(activities=[ProfilerActivity.CPU]) as prof:
    for a in inputs[6:]:
        runner.step(*a)
frames = n - 6
counts: Counter[str] = Counter()


def size(ev: Any) -> int:
    return sum(1 + size(c) for c in ev.cpu_children)


def walk(ev: Any, label: str) -> None:
    for child in ev.cpu_children:
        if child.name.startswith('@'):
            walk(child, child.name)
        else:
            counts[label] += 1 + size(child)


for ev in prof.events():
    if ev.cpu_parent is None:
        if ev.name.startswith('@'):
            walk(ev, ev.name)
        else:
            counts['(outside)'] += 1 + size(ev)
for label, count in counts.most_common():
    print(f'{label:28s} {count / frames:7.1f} ops a frame')
