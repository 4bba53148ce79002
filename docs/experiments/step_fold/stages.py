"""The single frame (suit_default, memory off), suit_default and suit_carry stepping the same
40 demo frames in one process, frame by frame in turn: stage medians (frames 5+) and step
ratios. Usage: python stages.py [THREADS]
"""
import sys

import numpy as np
import torch

from suit_ros.checkpoint import load_model_as
from suit_ros.data.sequences import synthetic_sequence
from suit_ros.evaluate import step_inputs
from suit_ros.model.streaming import StreamingDetector
from suit_ros.tracking import TrackerConfig

torch.set_num_threads(int(sys.argv[1]) if len(sys.argv) > 1 else 1)
names = ['single', 'suit_default', 'suit_carry']
frames = synthetic_sequence('demo-real', 7, 40, sensor='sim32')
runners = {n: StreamingDetector(load_model_as('suit_default', 'none') if n == 'single'
                                else load_model_as(n, None), 'cpu', tracker=TrackerConfig())
           for n in names}
keys = ('sweeps', 'encode', 'fusion', 'head_decode', 'sampling', 'tracking', 'total')
t: dict[str, dict[str, list[float]]] = {n: {k: [] for k in keys} for n in names}
for i, f in enumerate(frames):
    for n in names:
        r = runners[n].step(*step_inputs(f))
        if i >= 4:
            for k in keys:
                t[n][k].append(r.timings[k] * 1000)
for n in names:
    print(n, ' '.join(f'{k} {np.median(v):.1f}' for k, v in t[n].items()))
for n in names[1:]:
    print(f"{n} / single {np.median(t[n]['total']) / np.median(t['single']['total']):.3f}")
