"""Pedestrian scores on the real sweeps with the intensity scaled (diagnosis, no change):
per labelled pedestrian within 50 m, the best pedestrian score within 2 m, for each scale.

Usage: ped_intensity.py AV2_ROOT KITTI_ROOT
"""
from __future__ import annotations

from dataclasses import replace
import sys

import numpy as np

from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
from suit_ros.data.av2 import av2_sequences
from suit_ros.data.sequences import kitti_sequences
from suit_ros.evaluate import run_model
from suit_ros.tracking import TrackerConfig

model, cfg, _ = load_checkpoint(str(default_checkpoint_path()))
names = tuple(cfg.class_names)
ped = names.index('pedestrian')
sources = {'av2': list(av2_sequences(sys.argv[1], names)),
           'kitti': list(kitti_sequences(sys.argv[2], 1.0))}
for name, seqs in sources.items():
    for scale in (0.0, 0.5, 1.0, 2.0, 4.0):
        def scaled(f, s=scale):  # type: ignore[no-untyped-def]
            p = f.points.copy()
            p[:, 3] = np.clip(p[:, 3] * s, 0.0, 1.0)
            return replace(f, points=p)
        run = run_model(model, seqs, transform=scaled, tracker=TrackerConfig())
        best = []
        for g, d in zip(run.gt, run.scored_detections()):
            for b in g.boxes[g.labels == ped]:
                if np.hypot(*b[:2]) > 50:
                    continue
                near = (d.labels == ped) & (np.hypot(*(d.boxes[:, :2] - b[:2]).T) <= 2.0)
                best.append(float(d.scores[near].max()) if near.any() else 0.0)
        print(name, 'intensity x', scale, 'pedestrian best scores', np.round(best, 2))
