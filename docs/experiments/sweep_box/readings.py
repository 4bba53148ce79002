#!/usr/bin/env python3
"""The sweep reading of a vehicle's velocity with the current sweep's returns counted over
the whole search band (as shipped) or only over the box (grown by a margin along its
heading): the readings' own error on moving cars, and the tracker's, on a split.

The checkpoint runs once over the split (16 drives x 40 frames); then for each margin the
readings are taken from every frame's model input and the streaming detector's tracking
step is replayed over the stored detections (as scripts/tune_tracker.py does). Prints, per
margin: the readings of moving cars (score >= 0.3 within 2 m, GT speed > 1 m/s): count,
mean / median error, share above 4 m/s, mean along-track error; then tracked mAP, NDS, mAVE,
the moving-car velocity error at 0.3 and at the published car threshold.

Usage: readings.py [--split tune|val] [--margins none,1.0,0.5] [--out F.json]
"""
from __future__ import annotations

import argparse
import json
import time
from typing import Any

import numpy as np


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument('--split', default='tune', choices=['tune', 'val'])
    p.add_argument('--checkpoint', default='')
    p.add_argument('--margins', default='none,1.0,0.5,0.25')
    p.add_argument('--drives', type=int, default=16)
    p.add_argument('--frames', type=int, default=40)
    p.add_argument('--out', default='')
    args = p.parse_args()
    import torch
    torch.set_num_threads(2)
    from suit_ros.accuracy import car_motion, car_motion_frame
    from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint, published_thresholds
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.evaluate import evaluate, run_model, step_inputs
    from suit_ros.model.sweeps import boxes_to_lidar, model_frame
    from suit_ros.ops.geometry import transform_boxes
    from suit_ros.structures import Detections
    from suit_ros.tracking import Tracker, TrackerConfig, sweep_velocities, track_step

    t0 = time.monotonic()
    seqs = synthetic_split(args.split, args.drives, args.frames, 'data_cache')
    ckpt = args.checkpoint or str(default_checkpoint_path())
    model, cfg, meta = load_checkpoint(ckpt, 'cpu')
    names = tuple(cfg.class_names)
    car = names.index('car')
    car_cut = float(published_thresholds(meta, list(names))[car])
    run = run_model(model, seqs)
    frames = [f for seq in seqs for f in seq]
    print(f'model run over {len(frames)} frames in {time.monotonic() - t0:.0f} s', flush=True)
    base = []
    for seq, first in zip(seqs, np.cumsum([0] + [len(q) for q in seqs])):
        for t, f in enumerate(seq):
            d = run.det[first + t]
            _, _, T_ob, T_bl = step_inputs(f)
            boxes, vel = transform_boxes(T_bl, d.boxes, d.velocities)
            base.append((Detections(boxes, d.velocities if vel is None else vel, d.scores,
                                    d.labels), T_ob, T_bl, model_frame(seq, t, cfg.sweeps).points))
    rows: list[dict[str, Any]] = []
    for m in args.margins.split(','):
        margin = None if m == 'none' else float(m)
        t1 = time.monotonic()
        replay, read_frames = [], []
        for (d, T_ob, T_bl, pts), g in zip(base, run.gt):
            which = TrackerConfig().sweep_targets(d, names)
            swept = sweep_velocities(pts, d.boxes, which, current_margin=margin)
            replay.append((d, T_ob, T_bl, swept))
            keep = swept.read & (d.labels == car)
            only = Detections(d.boxes[keep], swept.velocities[keep], d.scores[keep],
                              d.labels[keep])
            read_frames.append(car_motion_frame(g, boxes_to_lidar(only, T_bl), car))
        err = np.array([x for f in read_frames for x in f[1]])
        gs = np.array([x for f in read_frames for x in f[3]])
        al = np.array([x for f in read_frames for x in f[4]])
        reading_s = time.monotonic() - t1
        dets, vf, drive = [], Tracker(TrackerConfig(), names), -1
        for (d, T_ob, T_bl, swept), f, k in zip(replay, frames, run.drive):
            if k != drive:
                vf.reset()
                drive = k
            dets.append(boxes_to_lidar(track_step(vf, d, f.stamp_ns, T_ob, None, swept)[0],
                                       T_bl))
        res = evaluate(run.gt, dets, names, num_points=run.num_points)
        row = {'margin': m, 'readings': len(err),
               'reading err mean': round(float(err.mean()), 3),
               'reading err median': round(float(np.median(err)), 3),
               'reading share > 4 m/s': round(float((err > 4).mean()), 3),
               'reading along - gt mean': round(float((al - gs).mean()), 3),
               'reading s': round(reading_s, 1),
               'mAP': round(res.mean_ap, 4), 'NDS': round(res.nds, 4),
               'mAVE': round(res.mean_tp['mAVE'], 4),
               'moving car vel err': round(car_motion(run.gt, dets, car)['moving car vel err'], 4),
               f'moving car vel err >= {car_cut}': round(
                   car_motion(run.gt, dets, car, min_score=car_cut)['moving car vel err'], 4),
               **{f'AVE {c}': round(res.tp[c]['vel_err'], 3) for c in res.evaluated}}
        print(row, flush=True)
        rows.append(row)
    if args.out:
        with open(args.out, 'w', encoding='utf-8') as fh:
            json.dump({'checkpoint': ckpt, 'split': args.split, 'drives': args.drives,
                       'frames': args.frames, 'rows': rows}, fh, indent=1)
    print(f'{time.monotonic() - t0:.0f} s')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
