"""Validation of coasting (docs/experiments/coast): suit_default tracked, coasting off and N
frames at 10 Hz (coast_s N / 10),
paired per-drive bootstrap over the fixed validation drives.

    python docs/experiments/coast/val_coast.py N OUT.json
"""
import json
import sys

import torch

from suit_ros.accuracy import bootstrap, plain_intervals
from suit_ros.checkpoint import load_checkpoint
from suit_ros.data.sequences import synthetic_split
from suit_ros.evaluate import run_model
from suit_ros.tracking import TrackerConfig

torch.set_num_threads(2)
n = int(sys.argv[1])
val = synthetic_split('val', 16, 40, 'data_cache')
model, cfg, _ = load_checkpoint('suit_default')
runs = {f'tracking, coast {n}': run_model(model, val, tracker=TrackerConfig(coast_s=n / 10)),
        'tracking': run_model(model, val, tracker=TrackerConfig(coast_s=0.0))}
stats, diffs = bootstrap(runs, cfg.class_names, [(f'tracking, coast {n}', 'tracking')], 100)
out = {'runs': plain_intervals(stats), 'differences': plain_intervals(diffs)}
json.dump(out, open(sys.argv[2], 'w'), indent=2)
for k, d in out['differences'].items():
    print(k, {m: [round(x, 4) for x in d[m]] for m in ('mAP', 'NDS', 'mAVE')})
for k, r in out['runs'].items():
    print(k, {m: round(r[m][0], 4) for m in ('mAP', 'NDS', 'mAVE', 'AP car', 'AP pedestrian')})
