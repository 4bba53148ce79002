"""Synthetic pedestrians standing close in front of a building or a wall, and a model's recall
on them: the validation drives in the world where half the pedestrians (by id) stand 0.1-0.6 m
in front of a building or a wall (preset ``val-fronts``), each pedestrian within 50 m with at
least 5 returns, split into those standing at a front and the rest; found if a published
pedestrian box (3 sweeps, the checkpoint's published thresholds and ground, no tracker) lies
within 2 m (BEV; any such box, not matched one to one). Also the published pedestrian boxes a
frame that lie 2 m or more from every labelled pedestrian.

Usage: python front_recall.py [CHECKPOINT] [DRIVES]   (default suit_default, 16)
"""
import sys

from fronts import at_fronts  # this folder's (the script's folder is on the path)
import numpy as np
import torch

from suit_ros import CLASS_NAMES
from suit_ros.checkpoint import load_checkpoint, published_thresholds
from suit_ros.data.sequences import split_drives, synthetic_sequence
from suit_ros.evaluate import step_inputs
from suit_ros.model.streaming import StreamingDetector

torch.set_num_threads(2)
name = sys.argv[1] if len(sys.argv) > 1 else 'suit_default'
path = name if name.endswith('.safetensors') else f'suit_ros/checkpoints/{name}.safetensors'
drives = int(sys.argv[2]) if len(sys.argv) > 2 else 16
PED = CLASS_NAMES.index('pedestrian')
model, cfg, meta = load_checkpoint(path)
runner = StreamingDetector(model, 'cpu', precision='auto')
runner.set_thresholds(published_thresholds(meta, cfg.class_names))
found = {'at a front': [0, 0], 'elsewhere': [0, 0]}
stray, frames = 0, 0
for seed, sensor in split_drives('val', drives, 0):
    at_front = at_fronts(seed, sensor)
    runner.reset('next drive')
    for f in synthetic_sequence('val-fronts', seed, 40, 'data_cache', sensor):
        det = runner.step(*step_inputs(f)).detections
        mine = det.boxes[det.labels == PED, :2]
        gt = f.gt
        assert gt is not None and f.instance_ids is not None and f.num_points is not None
        peds = gt.boxes[gt.labels == PED, :2]
        frames += 1
        if len(mine):
            near = np.hypot(*(mine[:, None] - peds[None]).transpose(2, 0, 1)) < 2.0 \
                if len(peds) else np.zeros((len(mine), 0), bool)
            stray += int((~near.any(axis=1)).sum())
        for b, label, iid, n in zip(gt.boxes, gt.labels, f.instance_ids, f.num_points):
            if label != PED or n < 5 or np.hypot(*b[:2]) > 50:
                continue
            group = found['at a front' if int(iid) in at_front else 'elsewhere']
            group[1] += 1
            group[0] += int(len(mine) > 0 and (np.hypot(*(mine - b[:2]).T) <= 2.0).any())
for group, (k, n) in found.items():
    print(f'{name}: pedestrians {group}: {n:5d}, found at the published thresholds '
          f'{k / max(n, 1):.3f}')
print(f'{name}: published pedestrian boxes 2 m or more from every pedestrian: '
      f'{stray / max(frames, 1):.2f} a frame ({frames} frames)')
