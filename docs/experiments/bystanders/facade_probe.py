"""The real dev pedestrian at 13 m (seen from the waist up in front of a facade): the shipped
model's heatmap there as the sweeps are, and with the returns around it taken out of both
sweeps' clouds (a probe of what hides it, not a fix): those within R m of its centre outside
its box (R = 1.5, 3.0), and those only above 2 m within 3 m; and as recorded with the input
not leveled (``ground: as_given``; the checkpoint asks for ``local``). Heatmap: the highest
probability of each class within 3 cells (1.2 m) of its centre, per sweep.

Usage: python facade_probe.py [CHECKPOINT_NAME]
"""
import sys
from typing import Any

import numpy as np
from probe import heatmaps  # this folder's (the script's folder is on the path)
import torch

from suit_ros.checkpoint import load_model_as
from suit_ros.data.av2 import av2_sequences
from suit_ros.evaluate import step_inputs
from suit_ros.model.streaming import StreamingDetector

torch.set_num_threads(2)
name = sys.argv[1] if len(sys.argv) > 1 else 'suit_default'
seq = av2_sequences('../shared/data/real-dev/av2')[0]
frames = [seq[i] for i in range(len(seq))]


def target(f: Any) -> tuple[np.ndarray, np.ndarray]:
    """The pedestrian 12-14 m away: its box in the LiDAR frame and in base_link."""
    T = np.asarray(f.T_base_lidar)
    for b, label in zip(f.gt.boxes, f.gt.labels):
        base = b.copy()
        base[:3] = b[:3] @ T[:3, :3].T + T[:3, 3]
        if label == 2 and 12 < np.hypot(*base[:2]) < 14:
            return b, base
    raise SystemExit('no pedestrian 12-14 m away')


def without(f: Any, radius: float, above: float | None) -> Any:
    from dataclasses import replace
    b, _ = target(f)
    p = f.points
    d = p[:, :2] - b[:2]
    c, s = np.cos(b[6]), np.sin(b[6])
    inside = ((np.abs(d[:, 0] * c + d[:, 1] * s) <= b[3] / 2)
              & (np.abs(-d[:, 0] * s + d[:, 1] * c) <= b[4] / 2))
    near = (np.hypot(d[:, 0], d[:, 1]) < radius) & ~inside
    if above is not None:
        near &= p[:, 2] > b[2] - b[5] / 2 + above
    keep = ~near
    times = None if f.times is None else f.times[keep]
    return replace(f, points=p[keep], times=times), int(near.sum())


variants: list[tuple[str, float, float | None, str]] = [
    ('as recorded', 0.0, None, 'local'), ('without returns within 1.5 m', 1.5, None, 'local'),
    ('without returns within 3 m', 3.0, None, 'local'),
    ('without returns above 2 m within 3 m', 3.0, 2.0, 'local'),
    ('as recorded, ground as given', 0.0, None, 'as_given')]
for label, radius, above, ground in variants:
    runner = StreamingDetector(load_model_as(f'suit_ros/checkpoints/{name}.safetensors', None),
                               'cpu', precision='float32', ground=ground)
    heat = heatmaps(runner.model)
    shown = []
    for f in frames:
        g, removed = without(f, radius, above) if radius else (f, 0)
        runner.step(*step_inputs(g))
        _, base = target(f)
        col, row = (int(v) for v in
                    runner.model.grid.xy_to_cell(torch.tensor(base[None, :2]).float())[0])
        m = heat['map'][:, row - 3:row + 4, col - 3:col + 4].amax((1, 2))
        shown.append(f'{removed} removed: ' + ' '.join(
            f'{n} {v:.2f}' for n, v in zip(runner.cfg.class_names, m.tolist())))
    print(f'{label:38s} | ' + ' | '.join(shown))
