"""The real dev set's pedestrians within 50 m, as the shipped model sees them (float32, node
defaults: 3 sweeps, tracker, ground local): per label the highest heatmap probability of each
class within 3 cells (1.2 m) of its centre, and its box's returns (count; heights above the box
bottom: min / 10th - 90th percentile / max; median intensity) and the returns within 1.5 m
outside it (count; 10th - 90th percentile heights).

Usage: python real_pedestrians.py [CHECKPOINT_NAME]   (default suit_default)
"""
import sys

import numpy as np
from probe import heatmaps  # this folder's (the script's folder is on the path)
import torch

from suit_ros.checkpoint import load_model_as
from suit_ros.data.av2 import av2_sequences
from suit_ros.evaluate import step_inputs
from suit_ros.model.streaming import StreamingDetector
from suit_ros.tracking import TrackerConfig

torch.set_num_threads(2)
name = sys.argv[1] if len(sys.argv) > 1 else 'suit_default'
seq = av2_sequences('../shared/data/real-dev/av2')[0]
runner = StreamingDetector(load_model_as(f'suit_ros/checkpoints/{name}.safetensors', None),
                           'cpu', precision='float32', tracker=TrackerConfig(), ground='local')
model = runner.model
heat = heatmaps(model)
names = model.cfg.class_names
for i in range(len(seq)):
    f = seq[i]
    runner.step(*step_inputs(f))
    T = np.asarray(f.T_base_lidar)                      # points and labels into base_link
    pts = f.points.copy()
    pts[:, :3] = pts[:, :3] @ T[:3, :3].T + T[:3, 3]
    boxes = f.gt.boxes.copy()
    boxes[:, :3] = boxes[:, :3] @ T[:3, :3].T + T[:3, 3]
    boxes[:, 6] += np.arctan2(T[1, 0], T[0, 0])
    for b, label in zip(boxes, f.gt.labels):
        if names[int(label)] != 'pedestrian' or np.hypot(*b[:2]) > 50:
            continue
        col, row = (int(v) for v in model.grid.xy_to_cell(torch.tensor(b[None, :2]).float())[0])
        near_max = heat['map'][:, max(row - 3, 0):row + 4, max(col - 3, 0):col + 4].amax((1, 2))
        d = pts[:, :2] - b[:2]
        c, s = np.cos(b[6]), np.sin(b[6])
        along, across = d[:, 0] * c + d[:, 1] * s, -d[:, 0] * s + d[:, 1] * c
        inside = ((np.abs(along) <= b[3] / 2) & (np.abs(across) <= b[4] / 2)
                  & (np.abs(pts[:, 2] - b[2]) <= b[5] / 2))
        around = (np.hypot(d[:, 0], d[:, 1]) < 1.5) & ~inside
        bottom = b[2] - b[5] / 2
        h = np.percentile(pts[inside, 2] - bottom, [0, 10, 90, 100])
        ha = np.percentile(pts[around, 2] - bottom, [10, 90])
        print(f'frame {i} pedestrian at {np.hypot(*b[:2]):4.1f} m: {inside.sum():3d} returns, '
              f'heights {h[0]:.2f} / {h[1]:.2f}-{h[2]:.2f} / {h[3]:.2f} m, intensity '
              f'{np.median(pts[inside, 3]):.2f}; within 1.5 m outside {around.sum():4d} '
              f'({ha[0]:.1f}-{ha[1]:.1f} m); heatmap '
              + ' '.join(f'{n} {v:.2f}' for n, v in zip(names, near_max.tolist())))
