#!/usr/bin/env python3
"""The shipped model in the world with the kerbs lined by parked cars, against the same drives
without the rows (the street world it was fine-tuned in): tracked car AP and mAP, and car
recall at the published cut by how much of the car its returns show. Tune-split seeds.

Usage: shipped_in_rows.py [DRIVES] [FRAMES] [CHECKPOINT]
"""
from __future__ import annotations

import sys

import numpy as np

from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint, published_thresholds
from suit_ros.data.sequences import SPLIT_SEEDS, synthetic_split
from suit_ros.evaluate import evaluate, run_model
from suit_ros.tracking import TrackerConfig

drives = int(sys.argv[1]) if len(sys.argv) > 1 else 8
frames = int(sys.argv[2]) if len(sys.argv) > 2 else 20
ckpt = sys.argv[3] if len(sys.argv) > 3 else str(default_checkpoint_path())
model, cfg, meta = load_checkpoint(ckpt)
names = tuple(cfg.class_names)
car = names.index('car')
cut = float(published_thresholds(meta, list(names))[car])
print('tune seeds from', SPLIT_SEEDS['tune'], 'car cut', cut)
for world in ('tune-street-ends', 'tune-parked-rows'):
    seqs = synthetic_split('tune', drives, frames, 'data_cache',
                           preset_name=world.replace('tune-', 'val-'))
    run = run_model(model, seqs, tracker=TrackerConfig())
    res = evaluate(run.gt, run.det, names, num_points=run.num_points)
    found, total = np.zeros(3), np.zeros(3)
    for g, d, n in zip(run.gt, run.det, run.num_points):
        pub = d.boxes[(d.labels == car) & (d.scores >= cut)]
        for b, lab, k in zip(g.boxes, g.labels, n):
            if lab != car or k == 0 or np.hypot(*b[:2]) > 50:
                continue
            band = 0 if k < 30 else (1 if k < 150 else 2)
            total[band] += 1
            if len(pub) and np.hypot(*(pub[:, :2] - b[:2]).T).min() <= 2.0:
                found[band] += 1
    cars = sum(int(((g.labels == car) & (np.hypot(*g.boxes[:, :2].T) <= 50) & (n > 0)).sum())
               for g, n in zip(run.gt, run.num_points)) / len(run.gt)
    print(f'{world}: visible cars within 50 m a frame {cars:.1f}; mAP {res.mean_ap:.3f}; '
          f'car AP {res.class_ap["car"]:.3f}; car recall at {cut} by returns <30 / 30-150 / '
          f'150+: ' + ' / '.join(f'{f / max(t, 1):.2f} ({int(t)})' for f, t in zip(found, total)),
          flush=True)
