#!/usr/bin/env python3
"""Per-frame SUIT step on the demo drive as an hdl64e sees it, in one process alone (1 torch
thread, tracker on, after a warm-up): what the in-node step is compared with."""
import numpy as np
import torch

from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
from suit_ros.data.sequences import synthetic_sequence
from suit_ros.evaluate import step_inputs
from suit_ros.model.streaming import StreamingDetector
from suit_ros.tracking import TrackerConfig

torch.set_num_threads(1)
model, _, _ = load_checkpoint(str(default_checkpoint_path()), 'cpu')
frames = synthetic_sequence('demo-real', 7, 100, sensor='hdl64e')
runner = StreamingDetector(model, precision='auto', tracker=TrackerConfig())
runner.warm_up()
total = []
for f in frames:
    total.append(runner.step(*step_inputs(f)).timings['total'] * 1e3)
print([round(t) for t in total])
print('p50', np.median(total), 'p95', np.percentile(total, 95), 'max', max(total))
