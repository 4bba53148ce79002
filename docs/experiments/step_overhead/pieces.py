"""Where SUIT's step spends its time beyond the single frame's: the model's pieces (and
those of the memory, the sampling and the tracker they call) timed by wrapping them, the
single frame (the checkpoint with its memory off) and SUIT stepping the same demo frames in
turn, tracker on, precision auto; mean ms a frame (frames 6+), sorted by SUIT's excess.
Wrapped calls nest (``past_term`` holds ``sparse_past_terms``).

Usage: python pieces.py CHECKPOINT THREADS
"""
from collections import defaultdict
from collections.abc import Callable
import functools
import sys
import time
from typing import Any

import torch

from suit_ros.checkpoint import load_model_as
from suit_ros.data.sim import preset
from suit_ros.data.sim.scene import Simulation, to_frame
from suit_ros.evaluate import step_inputs
from suit_ros.heap import keep_freed_memory
import suit_ros.model.detector as detector
import suit_ros.model.sampling as sampling
import suit_ros.model.streaming as streaming
from suit_ros.model.streaming import StreamingDetector
from suit_ros.tracking import TrackerConfig

keep_freed_memory()
checkpoint, threads, n = sys.argv[1], int(sys.argv[2]), 45
torch.set_num_threads(threads)
sim = Simulation(preset('demo-real', frames=n), 7)
frames = [to_frame(sim.render(k), 7) for k in range(n)]
times: defaultdict[str, float] = defaultdict(float)


def wrap(owner: Any, name: str, label: str) -> None:
    fn: Callable[..., Any] = getattr(owner, name)

    @functools.wraps(fn)
    def timed(*a: Any, **k: Any) -> Any:
        t = time.perf_counter()
        try:
            return fn(*a, **k)
        finally:
            times[label] += time.perf_counter() - t
    setattr(owner, name, timed)


for module in (detector, sampling):
    for name in ('significant_sampling', 'relaxation_window', 'gather_window', 'keep_carried',
                 'refined_nms', 'sparse_past_terms', 'transform_sample_positions',
                 'moved_memory', 'suppress_near', 'dilated_cells', 'coarse_topk', 'gate_past'):
        if hasattr(module, name):
            wrap(module, name, name)
wrap(streaming, 'track_step', 'track_step')
wrap(streaming, 'count_points_in_boxes', 'count_points_in_boxes')
runners = {}
for temporal in ('none', None):
    runner = StreamingDetector(load_model_as(checkpoint, temporal), 'cpu',
                               tracker=TrackerConfig())
    m = runner.model
    for name in ('encode_observed', 'past_term', 'predict', 'decode', 'carried',
                 'sample_memory'):
        wrap(m, name, name)
    wrap(m.head, 'forward_lazy', 'head.forward_lazy')
    if m.geonet is not None:
        wrap(m.geonet, 'forward', 'geonet')
    if m.carry is not None:
        wrap(m.carry.head, 'forward_at', 'carry.forward_at')
    runners['single' if temporal == 'none' else 'suit'] = runner
total: dict[str, defaultdict[str, float]] = {k: defaultdict(float) for k in runners}
for i, f in enumerate(frames):
    for key, runner in runners.items():
        times.clear()
        t0 = time.perf_counter()
        runner.step(*step_inputs(f))
        times['step'] += time.perf_counter() - t0
        if i >= 5:
            for k, v in times.items():
                total[key][k] += v * 1e3 / (n - 5)
a, b = total['single'], total['suit']
for k in sorted(set(a) | set(b), key=lambda k: a[k] - b[k]):
    print(f'{k:28s} single {a[k]:6.2f}  SUIT {b[k]:6.2f}  excess {b[k] - a[k]:5.2f}')
