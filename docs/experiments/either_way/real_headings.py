#!/usr/bin/env python3
"""The real dev sweeps' matched cars (score >= 0.3 within 2 m) one by one: where each stands
(range, the side of the ego's x axis), its labelled speed, and each checkpoint's heading error,
tracked as the node runs and the model alone (`report --av2` counts the published ones).

Usage: real_headings.py AV2_ROOT CHECKPOINT [CHECKPOINT ...]
"""
from __future__ import annotations

import sys

import numpy as np

from suit_ros.accuracy import matched_cars
from suit_ros.checkpoint import load_checkpoint
from suit_ros.data.av2 import av2_sequences
from suit_ros.evaluate import run_model
from suit_ros.tracking import TrackerConfig

root, checkpoints = sys.argv[1], sys.argv[2:]
rows: dict[tuple[int, int], dict[str, object]] = {}
for ckpt in checkpoints:
    model, cfg, _ = load_checkpoint(ckpt)
    car = list(cfg.class_names).index('car')
    seqs = list(av2_sequences(root, cfg.class_names))
    for how, tracker in (('tracked', TrackerConfig()), ('alone', None)):
        run = run_model(model, seqs, tracker=tracker)
        for t, (g, d) in enumerate(zip(run.gt, run.det)):
            for j, k in matched_cars(g, d, car, 0.3, 2.0):
                row = rows.setdefault((t, k), {
                    'frame': t, 'x': g.boxes[k, 0], 'y': g.boxes[k, 1],
                    'speed': float(np.hypot(*g.velocities[k])) if np.isfinite(
                        g.velocities[k]).all() else float('nan')})
                err = abs((d.boxes[j, 6] - g.boxes[k, 6] + np.pi) % (2 * np.pi) - np.pi)
                row[f'{ckpt.rsplit("/", 2)[-2] if "/" in ckpt else ckpt} {how}'] = (
                    f'{np.degrees(err):5.0f}{"*" if err > 0.75 * np.pi else " "}'
                    f' {d.scores[j]:.2f}')
keys = sorted({k for r in rows.values() for k in r} - {'frame', 'x', 'y', 'speed'})
print('frame      x      y  speed | ' + ' | '.join(keys)
      + '   (heading error deg, * flipped; score)')
for (_, _), r in sorted(rows.items(), key=lambda kv: (kv[1]['frame'], kv[1]['y'], kv[1]['x'])):
    print(f'{r["frame"]:5d} {r["x"]:6.1f} {r["y"]:6.1f} {r["speed"]:6.1f} | '
          + ' | '.join(str(r.get(k, '     -     ')) for k in keys))
