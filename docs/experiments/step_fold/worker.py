"""ab.py's worker: steps one model over demo frames on request, prints timings and boxes.

Usage (by ab.py): python worker.py MODEL FRAMES [SENSOR]; MODEL a checkpoint name or
``single`` (suit_default with its memory off); THREADS in the environment (default 1).
"""
import json
import os
import sys

import torch

from suit_ros.checkpoint import load_model_as
from suit_ros.data.sequences import synthetic_sequence
from suit_ros.evaluate import step_inputs
from suit_ros.model.streaming import StreamingDetector
from suit_ros.tracking import TrackerConfig

torch.set_num_threads(int(os.environ.get('THREADS', '1')))
name, n = sys.argv[1], int(sys.argv[2])
sensor = sys.argv[3] if len(sys.argv) > 3 else 'sim32'
frames = synthetic_sequence('demo-real', 7, n, sensor=sensor)
model = load_model_as('suit_default', 'none') if name == 'single' else load_model_as(name, None)
runner = StreamingDetector(model, 'cpu', tracker=TrackerConfig())
print('ready', flush=True)
for line in sys.stdin:
    res = runner.step(*step_inputs(frames[int(line)]))
    d = res.detections
    print(json.dumps({'t': {k: v * 1000 for k, v in res.timings.items()},
                      'boxes': d.boxes.tolist(), 'scores': d.scores.tolist()}), flush=True)
