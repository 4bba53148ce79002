#!/usr/bin/env python3
"""Choose the tracking settings on the ``tune`` split (never trained or validated on).

The checkpoint runs once with its own output; then the tracker (``suit_ros/tracking.py``)
replays over the stored detections for every setting of a grid, in base_link with the vehicle
pose and the velocities read from each frame's accumulated sweeps, as the streaming detector
runs it. Prints mAP, NDS, mAVE, per-class AVE and moving-car velocity error per setting and
writes them to ``--out`` (JSON). The grids, in the order the choices were made (each fixes the
settings the earlier ones chose):

- ``velocity``: noise and track settings (no score smoothing, no sweep reading); the choice:
  the least mAVE + moving-car velocity error;
- ``scores``: ``score_mix`` (no sweep reading); the choice: the highest NDS;
- ``sweeps``: ``sweep_sigma``; the choice: the least mAVE + moving-car velocity error.
- ``spread``: ``sweep_spread_gain`` with ``sweep_sigma`` (how far a reading whose earlier
  sweeps disagree is trusted); the choice: the least mAVE + moving-car velocity error;
- ``single``: ``sweep_single_sigma`` (a reading only one earlier sweep gave); the same choice.

Usage: scripts/tune_tracker.py --grid velocity|scores|sweeps|spread|single [--out F.json]
"""
from __future__ import annotations

import argparse
from dataclasses import asdict, replace
import itertools
import json
import time
from typing import Any

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or '').splitlines()[0])
    parser.add_argument('--checkpoint', default='', help='default: the shipped SUIT checkpoint')
    parser.add_argument('--drives', type=int, default=16)
    parser.add_argument('--frames', type=int, default=40)
    parser.add_argument('--cache-dir', default='data_cache')
    parser.add_argument('--out', default='')
    parser.add_argument('--grid', choices=['velocity', 'scores', 'sweeps', 'spread', 'single'],
                        default='single',
                        help='which choice to make (see the module docstring)')
    parser.add_argument('--threads', type=int, default=2)
    args = parser.parse_args()
    import torch
    torch.set_num_threads(args.threads)
    from suit_ros.accuracy import car_motion
    from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.evaluate import evaluate, run_model, step_inputs
    from suit_ros.model.sweeps import boxes_to_lidar, model_frame
    from suit_ros.ops.geometry import transform_boxes
    from suit_ros.structures import Detections
    from suit_ros.tracking import Tracker, TrackerConfig, sweep_velocities, track_step

    t0 = time.monotonic()
    seqs = synthetic_split('tune', args.drives, args.frames, args.cache_dir)
    model, cfg, _ = load_checkpoint(args.checkpoint or default_checkpoint_path(), 'cpu')
    names = tuple(cfg.class_names)
    run = run_model(model, seqs)
    frames = [f for seq in seqs for f in seq]
    car = names.index('car')
    print(f'[tune] model run over {len(frames)} frames in {time.monotonic() - t0:.0f} s')
    # each frame as the streaming detector's filter sees it: detections in base_link, the
    # vehicle pose, the velocities read from the sweeps
    replay = []
    for seq, first in zip(seqs, np.cumsum([0] + [len(q) for q in seqs])):
        for t, f in enumerate(seq):
            d = run.det[first + t]
            _, _, T_ob, T_bl = step_inputs(f)
            boxes, vel = transform_boxes(T_bl, d.boxes, d.velocities)
            base_det = Detections(boxes, d.velocities if vel is None else vel, d.scores,
                                  d.labels)
            swept = sweep_velocities(model_frame(seq, t, cfg.sweeps).points, boxes,
                                     TrackerConfig().sweep_targets(d, names))
            replay.append((base_det, T_ob, T_bl, swept))

    def score(filt: TrackerConfig | None) -> dict[str, float]:
        dets = run.det
        if filt is not None:
            dets, vf, drive = [], Tracker(filt, names), -1
            for (d, T_ob, T_bl, swept), f, k in zip(replay, frames, run.drive):
                if k != drive:
                    vf.reset()
                    drive = k
                # the streaming detector's own tracking step, on the replayed frame
                dets.append(boxes_to_lidar(track_step(vf, d, f.stamp_ns, T_ob, None, swept)[0],
                                           T_bl))
        res = evaluate(run.gt, dets, names, num_points=run.num_points)
        motion = car_motion(run.gt, dets, car)
        ave = {f'AVE {c}': round(res.tp[c]['vel_err'], 3) for c in res.evaluated}
        return {'mAVE': round(res.mean_tp['mAVE'], 4), 'NDS': round(res.nds, 4),
                'mAP': round(res.mean_ap, 4), **ave,
                **{k: round(v, 4) for k, v in motion.items()
                   if k in ('moving car vel err', 'moving car speed slope',
                            'static car vel err')}}

    grid: dict[str, tuple[Any, ...]]
    if args.grid == 'velocity':
        base = TrackerConfig(score_mix=0.0, sweep_sigma=None)
        grid = {'pos_sigma': (0.2, 0.3), 'vel_sigma': (3.0, 4.5), 'accel_sigma': (1.0, 2.0),
                'birth_score': (0.4, 0.5), 'max_miss_s': (0.4, 0.6)}
    elif args.grid == 'scores':
        base = TrackerConfig(sweep_sigma=None)
        grid = {'score_mix': (0.0, 0.3, 0.5, 0.7)}
    elif args.grid == 'sweeps':
        base = TrackerConfig(sweep_spread_gain=0.0)
        grid = {'sweep_sigma': (None, 1.0, 1.5, 2.5, 4.0)}
    elif args.grid == 'spread':
        base = TrackerConfig(sweep_single_sigma=None)
        grid = {'sweep_spread_gain': (0.0, 0.5, 1.0, 2.0, 3.0, 4.0),
                'sweep_sigma': (0.5, 0.75, 1.0, 1.5)}
    else:
        base = TrackerConfig()
        grid = {'sweep_single_sigma': (None, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0)}
    rows: list[dict[str, Any]] = [{'setting': 'head velocities', **score(None)}]
    print(rows[0])
    for values in itertools.product(*grid.values()):
        filt = replace(base, **dict(zip(grid, values)))
        row = {'setting': {k: getattr(filt, k) for k in grid}, **score(filt)}
        print(row, flush=True)
        rows.append(row)
    rows[1:] = sorted(rows[1:], key=lambda r: (-r['NDS'] if args.grid == 'scores' else
                                               r['mAVE'] + r['moving car vel err']))
    print('[tune] best:', rows[1])
    if args.out:
        with open(args.out, 'w', encoding='utf-8') as fh:
            json.dump({'checkpoint': args.checkpoint or str(default_checkpoint_path()),
                       'drives': args.drives, 'frames': args.frames, 'base': asdict(base),
                       'rows': rows}, fh, indent=1)
    print(f'[tune] {time.monotonic() - t0:.0f} s')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
