"""How well the tracker's published velocity standard deviation (``vel_std``) describes the
velocity error of matched cars, and what ``TrackerConfig.speed_std_fraction`` does to it.

    python docs/experiments/velocity_std/calibrate.py --split tune --drives 16 --out tune.npz
    python docs/experiments/velocity_std/calibrate.py --split val --drives 16 --out val.npz

The shipped SUIT model runs as the node runs it (tracker on, deskewed sweeps) over the drives;
the tracker's own standard deviation (``speed_std_fraction`` 0) is recorded for every car
matched at score >= 0.3 within 2 m, with its velocity error per axis, its GT speed and its
published speed; the table then widens it by each fraction. The fraction is chosen on the tune
split (the rms of the published standard deviation equal to the rms error per axis over all
matched cars); validation only reports it.
"""
from __future__ import annotations

import argparse
from dataclasses import replace
from typing import Any

import numpy as np

from suit_ros.compare import load_as
from suit_ros.data.sequences import synthetic_split
from suit_ros.evaluate import run_model
import suit_ros.tracking as tracking

FRACTIONS = (0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3)


def record(split: str, drives: int) -> dict[str, Any]:
    """Run the model with the tracker; one row per matched car and frame."""
    seen: list[tuple[Any, Any, Any]] = []
    update = tracking.Tracker.update

    def recording(self: tracking.Tracker, *a: Any, **k: Any) -> Any:
        out, ids = update(self, *a, **k)
        seen.append((out, ids, self.velocity_std.copy()))
        return out, ids

    tracking.Tracker.update = recording  # type: ignore[method-assign]
    try:
        model = load_as('suit_ros/checkpoints/suit_default.safetensors')
        seqs = synthetic_split(split, drives, 40, 'data_cache')
        run_model(model, seqs, tracker=replace(tracking.TrackerConfig(), speed_std_fraction=0.0),
                  deskew=True)
    finally:
        tracking.Tracker.update = update  # type: ignore[method-assign]
    frames = [f for s in seqs for f in s]
    assert len(seen) == len(frames)
    rows: dict[str, list[Any]] = {'err': [], 'std': [], 'speed': [], 'published_speed': [],
                                  'tracked': []}
    for (out, ids, std), f in zip(seen, frames):
        T = np.asarray(f.T_base_lidar)            # tracker output: base_link; GT: LiDAR frame
        assert np.allclose(T[:3, :3], np.eye(3))
        g = f.gt
        centres = g.boxes[:, :2] + T[:2, 3]
        mine = np.nonzero((out.labels == 0) & (out.scores >= 0.3))[0]
        mine = mine[np.argsort(-out.scores[mine], kind='stable')]
        cars = np.nonzero(g.labels == 0)[0]
        taken = np.zeros(len(cars), bool)
        for j in mine:
            if not len(cars):
                break
            d = np.hypot(*(centres[cars] - out.boxes[j, :2]).T)
            d[taken] = np.inf
            k = int(np.argmin(d))
            if d[k] >= 2.0:
                continue
            taken[k] = True
            v = g.velocities[cars[k]]
            rows['err'].append(out.velocities[j] - v)
            rows['std'].append(std[j])
            rows['speed'].append(float(np.hypot(*v)))
            rows['published_speed'].append(float(np.hypot(*out.velocities[j])))
            rows['tracked'].append(bool(ids[j] > 0))
    return {k: np.asarray(v) for k, v in rows.items()}


def table(r: dict[str, Any]) -> list[str]:
    """Coverage and scale of the published standard deviation for each fraction."""
    err, moving = r['err'], r['speed'] > 1.0
    groups = (np.ones(len(err), bool), moving, ~moving)
    rms = ', '.join(f'{name} {np.sqrt((err[m] ** 2).mean()):.2f}'
                    for name, m in zip(('all', 'moving', 'parked'), groups))
    lines = [f'{len(err)} matched cars ({moving.sum()} moving > 1 m/s); rms error per axis: '
             f'{rms} m/s', '',
             '| fraction | rms std: all / moving / parked | within 1 std: all / moving / parked '
             '| within 2 std: all / moving / parked |', '|---|---|---|---|']
    for f in FRACTIONS:
        std = np.hypot(r['std'], f * r['published_speed'])
        z = np.abs(err) / std[:, None]
        cells = [[np.sqrt((std[m] ** 2).mean()) for m in groups],
                 [(z[m] < 1).mean() for m in groups], [(z[m] < 2).mean() for m in groups]]
        lines.append(f'| {f:.2f} | ' + ' | '.join(' / '.join(f'{x:.2f}' for x in c)
                                                  for c in cells) + ' |')
    return lines


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--split', choices=['tune', 'val'], default='tune')
    p.add_argument('--drives', type=int, default=16)
    p.add_argument('--out', required=True)
    args = p.parse_args()
    r = record(args.split, args.drives)
    np.savez(args.out, **r)
    print('\n'.join(table(r)))


if __name__ == '__main__':
    main()
