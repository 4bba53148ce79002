#!/usr/bin/env python3
"""``traffic_side: auto`` against the fixed sides, on validation drives as they are
(right-hand traffic) and mirrored (left-hand traffic), the node's tracker on.

Per condition: tracked mAP and NDS (the model's boxes, as docs/results.md scores them), the
matched cars (score >= 0.3 within 2 m) whose heading is more than 135 degrees off, all and
standing ones (GT speed < 0.5 m/s), and for ``auto`` the drives whose side changed and the
frame it changed at (the model runs in the other world from the next frame on).

Usage: measure.py DRIVES FRAMES [CHECKPOINT] [--preset=NAME] [--only=plain|mirrored]
"""
from __future__ import annotations

import sys

import numpy as np

from suit_ros.accuracy import matched_cars
from suit_ros.checkpoint import load_checkpoint
from suit_ros.data.augment import mirror_world
from suit_ros.data.sequences import synthetic_split
from suit_ros.evaluate import run_model
from suit_ros.tracking import TrackerConfig

drives, frames = int(sys.argv[1]), int(sys.argv[2])
args = [a for a in sys.argv[3:] if not a.startswith('--')]
ckpt = args[0] if args else 'suit_default'
PRESET = next((a.split('=', 1)[1] for a in sys.argv if a.startswith('--preset=')), None)
ONLY = next((a.split('=', 1)[1] for a in sys.argv if a.startswith('--only=')), None)
seqs = synthetic_split('val', drives, frames, 'data_cache', preset_name=PRESET)
model, cfg, _ = load_checkpoint(ckpt)
car = list(cfg.class_names).index('car')
print(f'{ckpt}; {drives} validation drives x {frames} frames'
      + (f', world {PRESET}' if PRESET else ''), flush=True)
print('| drives | traffic_side | mAP | NDS | cars flipped | standing cars flipped | '
      'drives switched (frame) |')
print('|---|---|---|---|---|---|---|')
for world, transform in (('as they are (right-hand)', None), ('mirrored (left-hand)',
                                                               mirror_world)):
    if ONLY is not None and ONLY != ('plain' if transform is None else 'mirrored'):
        continue
    for side in (('right', 'auto') if transform is None else ('right', 'left', 'auto')):
        run = run_model(model, seqs, tracker=TrackerConfig(), transform=transform,
                        traffic_side=side)
        res = run.evaluate(cfg.class_names)
        flips = {'all': [0, 0], 'standing': [0, 0]}
        for g, d in zip(run.gt, run.det):
            for j, k in matched_cars(g, d, car, 0.3, 2.0):
                err = abs((d.boxes[j, 6] - g.boxes[k, 6] + np.pi) % (2 * np.pi) - np.pi)
                keys = ['all']
                if np.isfinite(g.velocities[k]).all() and np.hypot(*g.velocities[k]) < 0.5:
                    keys.append('standing')
                for key in keys:
                    flips[key][0] += 1
                    flips[key][1] += int(err > 0.75 * np.pi)
        switched = []
        for drive in range(drives):
            s = [side_ for side_, dr in zip(run.sides, run.drive) if dr == drive]
            changes = [t for t in range(1, len(s)) if s[t] != s[t - 1]]
            if changes:
                switched.append(f'{drive}: {",".join(str(t) for t in changes)}')
        cells = [f'{m} of {n} ({100 * m / max(n, 1):.1f}%)' for n, m in flips.values()]
        print(f'| {world} | {side} | {res.mean_ap:.4f} | {res.nds:.4f} | {cells[0]} | '
              f'{cells[1]} | {len(switched)} ({"; ".join(switched) or "-"}) |', flush=True)
