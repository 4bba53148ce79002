#!/usr/bin/env python3
"""Which parked cars' headings flip in the rows world: matched standing cars (score >= 0.3
within 2 m, GT speed < 0.5 m/s) split by whether they face their side's traffic (the kerb on
their right) or stand against it, and the share of each whose predicted heading is more than
135 degrees off. Validation drives in the rows world, the node's tracker (`--no-tracker`: the
model's own boxes).

Usage: flips.py [DRIVES] [FRAMES] [CHECKPOINT ...] [--no-tracker] [--preset=NAME]
(NAME a rows world, default val-parked-rows; val-parked-roofs: docs/experiments/car_front)
"""
from __future__ import annotations

import sys

import numpy as np

from suit_ros.accuracy import matched_cars
from suit_ros.checkpoint import load_checkpoint
from suit_ros.data.sequences import synthetic_split
from suit_ros.data.sim import preset
from suit_ros.evaluate import run_model
from suit_ros.tracking import TrackerConfig

drives = int(sys.argv[1]) if len(sys.argv) > 1 else 16
frames = int(sys.argv[2]) if len(sys.argv) > 2 else 40
NO_TRACKER = '--no-tracker' in sys.argv
PRESET = next((a.split('=', 1)[1] for a in sys.argv if a.startswith('--preset=')),
              'val-parked-rows')
checkpoints = [a for a in sys.argv[3:] if not a.startswith('--')] or ['suit_default']
block = preset(PRESET).block
seqs = synthetic_split('val', drives, frames, 'data_cache', preset_name=PRESET)
for ckpt in checkpoints:
    model, cfg, _ = load_checkpoint(ckpt)
    car = list(cfg.class_names).index('car')
    run = run_model(model, seqs, tracker=None if NO_TRACKER else TrackerConfig())
    frames_all = [f for s in seqs for f in s]
    counts = {'with traffic': [0, 0], 'against traffic': [0, 0]}
    for f, g, d in zip(frames_all, run.gt, run.det):
        for j, k in matched_cars(g, d, car, 0.3, 2.0):
            if np.hypot(*g.velocities[k]) >= 0.5 or not np.isfinite(g.velocities[k]).all():
                continue
            c = f.pose @ np.array([*g.boxes[k, :3], 1.0])          # the world frame
            yaw = g.boxes[k, 6] + np.arctan2(f.pose[1, 0], f.pose[0, 0])
            axis = np.round(c[:2] / block) * block
            off = np.abs(c[:2] - axis)
            a = int(np.argmin(off))                                # across its road
            kerb = np.zeros(2)
            kerb[a] = np.sign(c[a] - axis[a])
            facing = np.array([np.cos(yaw), np.sin(yaw)]) @ np.array([-kerb[1], kerb[0]])
            key = 'with traffic' if facing > 0 else 'against traffic'
            err = abs((d.boxes[j, 6] - g.boxes[k, 6] + np.pi) % (2 * np.pi) - np.pi)
            counts[key][0] += 1
            counts[key][1] += int(err > 0.75 * np.pi)
    print(ckpt, ', '.join(f'{k}: {n} matched, {m} flipped ({100 * m / max(n, 1):.1f}%)'
                          for k, (n, m) in counts.items()), flush=True)
