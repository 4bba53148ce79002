"""Synthetic validation pedestrians seen only from the waist up, and the shipped model's recall
on them: each pedestrian within 50 m with at least 5 of its own returns (the simulator's
`owners`), split by the height of its lowest own return above its box's bottom (the ground),
and whether a published pedestrian box (3 sweeps, the checkpoint's published thresholds and
ground, no tracker) lies within 2 m (BEV; any such box, not matched one to one).

Usage: python torso_only.py [CHECKPOINT_NAME] [DRIVES]   (default suit_default, 16)
"""
import sys

import numpy as np
import torch

from suit_ros.checkpoint import load_checkpoint, published_thresholds
from suit_ros.data.sequences import synthetic_split
from suit_ros.evaluate import step_inputs
from suit_ros.model.streaming import StreamingDetector

torch.set_num_threads(2)
name = sys.argv[1] if len(sys.argv) > 1 else 'suit_default'
drives = int(sys.argv[2]) if len(sys.argv) > 2 else 16
model, cfg, meta = load_checkpoint(f'suit_ros/checkpoints/{name}.safetensors')
runner = StreamingDetector(model, 'cpu', precision='auto')
# the published thresholds (the runner alone decodes at the evaluation threshold, 0.1;
# before stop 60 this script used that and called it published)
runner.set_thresholds(published_thresholds(meta, cfg.class_names))
names = runner.cfg.class_names
ped = names.index('pedestrian')
BINS = ((0.0, 0.3), (0.3, 0.8), (0.8, 9.0))       # lowest own return above the ground (m)
found = np.zeros(len(BINS), int)
total = np.zeros(len(BINS), int)
for seq in synthetic_split('val', drives, 40, 'data_cache'):
    runner.reset('next drive')
    for f in seq:
        res = runner.step(*step_inputs(f))
        det = res.detections
        mine = det.labels == ped
        gt = f.gt
        if gt is None or f.owners is None or f.instance_ids is None:
            raise SystemExit('the synthetic frames carry owners and instance ids')
        for b, label, iid in zip(gt.boxes, gt.labels, f.instance_ids):
            if label != ped or np.hypot(*b[:2]) > 50:
                continue
            own = f.points[f.owners == iid]
            if len(own) < 5:
                continue
            low = float(own[:, 2].min() - (b[2] - b[5] / 2))
            k = next(i for i, (lo, hi) in enumerate(BINS) if lo <= low < hi or i == 2)
            total[k] += 1
            hit = bool(mine.any() and
                       (np.hypot(*(det.boxes[mine, :2] - b[:2]).T) <= 2.0).any())
            found[k] += hit
for (lo, hi), n, k in zip(BINS, total, found):
    print(f'{name}: pedestrians whose lowest own return is {lo:.1f}-{hi:.1f} m up: {n:5d}, '
          f'found at the published thresholds {k / max(n, 1):.3f}')
