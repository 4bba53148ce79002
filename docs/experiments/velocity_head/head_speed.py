"""Where the head's velocity goes wrong on moving cars: the error split along and across the
car's direction of travel, by frame of the drive, returns, speed, range and ego motion.

    python docs/experiments/velocity_head/head_speed.py --split tune --drives 6 --out tune.json
    python docs/experiments/velocity_head/head_speed.py --split train --drives 4 --out train.json

``--split train`` reads the last recipe stages' own drives (288+, ``train-ends-all``); the tune
drives (seeds 8000+) are never trained on. The model runs alone (no tracker), each car matched
at score >= 0.3 within 2 m (as ``suit_ros.accuracy.car_motion_frame``).
"""
from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np

from suit_ros.compare import load_as
from suit_ros.data.sequences import synthetic_split
from suit_ros.evaluate import run_model


def rows_of(run: Any, frames: list[Any], per_drive: int) -> list[dict[str, float]]:
    """One row per matched moving car and frame."""
    rows = []
    for fi, (g, d, npts) in enumerate(zip(run.gt, run.det, run.num_points)):
        gm = np.nonzero(g.labels == 0)[0]
        dm = np.nonzero((d.labels == 0) & (d.scores >= 0.3))[0]
        dm = dm[np.argsort(-d.scores[dm], kind='stable')]
        taken = np.zeros(len(gm), bool)
        here, before = frames[fi], frames[fi - 1] if fi % per_drive else frames[fi + 1]
        dt = (here.stamp_ns - before.stamp_ns) * 1e-9
        ego = (np.linalg.inv(here.pose) @ before.pose)[:2, 3] / -dt    # in the current frame
        for j in dm:
            if not len(gm):
                break
            dist = np.hypot(g.boxes[gm, 0] - d.boxes[j, 0], g.boxes[gm, 1] - d.boxes[j, 1])
            dist[taken] = np.inf
            k = int(np.argmin(dist))
            if dist[k] >= 2.0:
                continue
            taken[k] = True
            v = g.velocities[gm[k]].astype(np.float64)
            s = float(np.hypot(*v))
            if s <= 1.0:
                continue
            u = v / s
            e = d.velocities[j] - v
            rows.append({'frame': fi % per_drive, 'points': int(npts[gm[k]]), 'speed': s,
                         'range': float(np.hypot(*g.boxes[gm[k], :2])),
                         'along': float(e @ u), 'across': float(e[1] * u[0] - e[0] * u[1]),
                         'err': float(np.hypot(*e)), 'ego_along': float(ego @ u)})
    return rows


def summary(rows: list[dict[str, float]]) -> list[str]:
    """Mean error, mean along-track error and its share of the speed, by bucket."""
    a = {k: np.array([r[k] for r in rows]) for k in rows[0]}
    out = [f'{len(rows)} matched moving cars: error {a["err"].mean():.2f} m/s, along '
           f'{a["along"].mean():+.2f}, |across| {np.abs(a["across"]).mean():.2f}']
    for name, key, edges in [('frame', 'frame', [0, 1, 2, 3, 5, 1000]),
                             ('returns', 'points', [0, 10, 30, 100, 300, 10**9]),
                             ('speed', 'speed', [1, 6, 10, 16]),
                             ('range', 'range', [0, 15, 30, 50, 200]),
                             ('ego along', 'ego_along', [-40, -3, 3, 40])]:
        for lo, hi in zip(edges[:-1], edges[1:]):
            m = (a[key] >= lo) & (a[key] < hi)
            if m.any():
                out.append(f'{name} {lo}-{hi}: n {m.sum()}, error {a["err"][m].mean():.2f}, '
                           f'along {a["along"][m].mean():+.2f} '
                           f'({(a["along"][m] / a["speed"][m]).mean():+.2f} of the speed)')
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--checkpoint', default='suit_ros/checkpoints/suit_default.safetensors')
    p.add_argument('--split', choices=['tune', 'train'], default='tune')
    p.add_argument('--drives', type=int, default=6)
    p.add_argument('--drop-memory', action='store_true')
    p.add_argument('--out', required=True)
    args = p.parse_args()
    model = load_as(args.checkpoint)
    if args.split == 'train':
        seqs = synthetic_split('train', args.drives, 60, 'data_cache',
                               preset_name='train-ends-all', first=288)
    else:
        seqs = synthetic_split('tune', args.drives, 40, 'data_cache')
    run = run_model(model, seqs, drop_memory=args.drop_memory)
    rows = rows_of(run, [f for s in seqs for f in s], len(seqs[0]))
    with open(args.out, 'w') as f:
        json.dump(rows, f)
    print('\n'.join(summary(rows)))


if __name__ == '__main__':
    main()
