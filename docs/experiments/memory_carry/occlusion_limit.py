#!/usr/bin/env python3
"""Where the occluded objects are lost (issue 21, diagnosis): on the outage benchmark's drives
as the sensor saw them (seeds 8500+, 16 x 40 frames, no sector removed), recall of objects
occluded 3-10 frames (no returns now, returns 3-10 frames before) by each model
- at its published thresholds (what the node publishes, carried boxes at theirs),
- at the decode threshold 0.1 for every box (is there a box at all?),
- the same with the memory dropped before every frame (what the memory adds).
No tracker. Run from the repository root: prints one line per model."""
from __future__ import annotations

from suit_ros.checkpoint import load_checkpoint, published_thresholds
from suit_ros.data.sequences import synthetic_split
from suit_ros.evaluate import run_model
from suit_ros.outage import count_occlusion, intervals, published_by_drive

MODELS = {'suit_default': 'suit_ros/checkpoints/suit_default.safetensors',
          'suit_carry': 'suit_ros/checkpoints/suit_carry.safetensors',
          'single': 'suit_ros/checkpoints/centerpoint_single.safetensors'}
plain = synthetic_split('outage', 16, 40, 'data_cache')
for name, path in MODELS.items():
    model, cfg, meta = load_checkpoint(path)
    n = len(cfg.class_names)
    thr = published_thresholds(meta, cfg.class_names)
    carry = published_thresholds(meta, cfg.class_names, carried=True)
    low = [0.1] * n
    zero = [0.0] * n
    line = []
    for label, drop in (('memory', False), ('memory dropped', True)):
        run = run_model(model, plain, drop_memory=drop)
        for tlabel, t, c in (('published', thr, carry), ('at 0.1', low, low)):
            occ = intervals(count_occlusion(plain, published_by_drive(run, t, c), zero))
            r = occ['recall_from_frame_3']
            line.append(f'{label}, {tlabel}: {r[0]:.2f} [{r[1]:.2f}, {r[2]:.2f}]')
    print(f'{name:<14}' + ' | '.join(line), flush=True)
