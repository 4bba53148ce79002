#!/usr/bin/env python3
"""Choose the velocity filter's noise settings on the ``tune`` split (never trained or validated
on): the checkpoint runs once with the head's velocities, then the filter replays over the
stored detections for every setting of a grid; prints moving-car velocity error, mAVE and the
speed slope per setting, sorted by mAVE + moving-car velocity error (the choice; ``--grid
scores``: the score smoothing, by NDS), and writes them to ``--out`` (JSON).

The filter runs on the detections in the LiDAR frame with the LiDAR pose; the streaming detector
runs it in base_link with the vehicle pose: the same centres and velocities in the odometry frame.

Usage: scripts/tune_velocity_filter.py [--checkpoint C] [--drives 16] [--out tune.json]
"""
from __future__ import annotations

import argparse
from dataclasses import asdict, replace
import itertools
import json
import time


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or '').splitlines()[0])
    parser.add_argument('--checkpoint', default='', help='default: the shipped SUIT checkpoint')
    parser.add_argument('--drives', type=int, default=16)
    parser.add_argument('--frames', type=int, default=40)
    parser.add_argument('--cache-dir', default='data_cache')
    parser.add_argument('--out', default='')
    parser.add_argument('--grid', choices=['velocity', 'scores'], default='velocity',
                        help='velocity: the noise and track settings; scores: score_mix')
    args = parser.parse_args()
    import torch
    torch.set_num_threads(2)
    from suit_ros.benchmark import car_motion
    from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.evaluate import evaluate, run_model
    from suit_ros.tracking import FilterConfig, VelocityFilter

    t0 = time.monotonic()
    seqs = synthetic_split('tune', args.drives, args.frames, args.cache_dir)
    model, cfg, _ = load_checkpoint(args.checkpoint or default_checkpoint_path(), 'cpu')
    names = tuple(cfg.class_names)
    run = run_model(model, seqs)
    frames = [f for seq in seqs for f in seq]
    car = names.index('car')
    print(f'[tune] model run over {len(frames)} frames in {time.monotonic() - t0:.0f} s')

    def score(filt: FilterConfig | None) -> dict[str, float]:
        dets = run.det
        if filt is not None:
            dets, vf, drive = [], VelocityFilter(filt), -1
            for d, f, k in zip(run.det, frames, run.drive):
                if k != drive:
                    vf.reset()
                    drive = k
                dets.append(vf.update(d, f.stamp_ns, f.pose)[0])
        res = evaluate(run.gt, dets, names, num_points=run.num_points)
        motion = car_motion(run.gt, dets, car)
        ave = {f'AVE {c}': round(res.tp[c]['vel_err'], 3) for c in res.evaluated}
        return {'mAVE': round(res.mean_tp['mAVE'], 4), 'NDS': round(res.nds, 4),
                'mAP': round(res.mean_ap, 4), **ave,
                **{k: round(v, 4) for k, v in motion.items()
                   if k in ('moving car vel err', 'moving car speed slope',
                            'static car vel err')}}

    base = FilterConfig()
    if args.grid == 'scores':      # the velocity settings fixed (chosen first), then the scores
        grid: dict[str, tuple[float, ...]] = {'score_mix': (0.0, 0.3, 0.5, 0.7)}
    else:
        grid = {'pos_sigma': (0.2, 0.3), 'vel_sigma': (3.0, 4.5), 'accel_sigma': (1.0, 2.0),
                'birth_score': (0.4, 0.5), 'max_misses': (4, 6)}
    rows = [{'setting': 'head velocities', **score(None)}]
    print(rows[0])
    for values in itertools.product(*grid.values()):
        filt = replace(base, **dict(zip(grid, values)))
        row = {'setting': {k: getattr(filt, k) for k in grid}, **score(filt)}
        print(row, flush=True)
        rows.append(row)
    # the choice: the least mAVE + moving-car velocity error (both m/s); for the scores, the
    # highest NDS
    rows[1:] = sorted(rows[1:], key=lambda r: (-r['NDS'] if args.grid == 'scores' else
                                               r['mAVE'] + r['moving car vel err']))
    print('[tune] best:', rows[1])
    if args.out:
        with open(args.out, 'w', encoding='utf-8') as f:
            json.dump({'checkpoint': args.checkpoint or str(default_checkpoint_path()),
                       'drives': args.drives, 'frames': args.frames, 'base': asdict(base),
                       'rows': rows}, f, indent=1)
    print(f'[tune] {time.monotonic() - t0:.0f} s')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
