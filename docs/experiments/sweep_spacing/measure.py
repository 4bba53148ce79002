#!/usr/bin/env python3
"""A 20 Hz sensor's model input: its sweeps 0.05 s apart, or 0.1 s apart as in training.

The shipped models were trained on 10 Hz drives: three sweeps 0.1 s apart (lags 0, 0.1, 0.2 s).
A 20 Hz sensor's three latest sweeps lie 0.05 s apart (lags 0, 0.05, 0.1): half the motion the
model learned to read, over half the time. The sweep buffer now takes the earlier sweeps whose
lags are nearest 0.1 and 0.2 s (``pick_sweeps``). nuScenes keyframes (``suit-ros eval
--nuscenes``) came with 10 consecutive sweeps of its 20 Hz LIDAR_TOP (lags 0-0.45 s).

This runs the shipped SUIT checkpoint over the ``outage`` split's drives (seeds 8500+, never
trained, tuned or validated on; four sensor models) simulated at 20 Hz, 80 frames (4 s) each,
no outage drawn in, tracked and deskewed as the node runs it, three ways:

- ``consecutive``: the three latest sweeps (the buffer before this change);
- ``0.1 s apart``: the sweeps nearest 0.1 and 0.2 s back (the buffer now);
- ``10 consecutive``: each frame with its 9 previous sweeps accumulated, as a nuScenes keyframe
  came from the reader before this change (deskewed first, then accumulated).

mAP, NDS, mAVE and the moving-car velocity error over every frame, with per-drive bootstrap
intervals (200 resamples), paired against ``consecutive``.

Usage: docs/experiments/sweep_spacing/measure.py [--drives 16] [--out F.json]
(at commit 4ed8958, where the spacing exists: it was not adopted, README.md here)
"""
from __future__ import annotations

import argparse
from dataclasses import replace
import json
import time
from typing import Any


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or '').splitlines()[0])
    parser.add_argument('--drives', type=int, default=16)
    parser.add_argument('--cache-dir', default='data_cache')
    parser.add_argument('--out', default='')
    args = parser.parse_args()
    import numpy as np
    import torch
    torch.set_num_threads(2)
    from suit_ros.accuracy import bootstrap, plain_intervals
    from suit_ros.checkpoint import load_checkpoint
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.evaluate import ModelRun, deskewed, run_model
    import suit_ros.model.sweeps as sweeps
    from suit_ros.tracking import TrackerConfig

    model, cfg, _ = load_checkpoint('suit_default', 'cpu')
    names = list(cfg.class_names)
    drives = synthetic_split('outage', args.drives, 80, args.cache_dir, rate_hz=20.0)
    print(f'{len(drives)} drives x 80 frames at 20 Hz', flush=True)

    def accumulated(seq: list[Any], count: int) -> list[Any]:
        """Each frame with its ``count - 1`` previous sweeps accumulated (LiDAR frame)."""
        out = []
        for t, f in enumerate(seq):
            used = [sweeps.Sweep(seq[j].points, np.asarray(seq[j].pose), seq[j].stamp_ns)
                    for j in range(t, max(t - count, -1), -1)]           # LiDAR poses
            out.append(replace(f, points=sweeps.accumulate_sweeps(used, np.eye(4)),
                               times=None))
        return out

    runs: dict[str, ModelRun] = {}
    spacing = sweeps.SWEEP_SPACING_S
    for name in ('consecutive', '0.1 s apart', '10 consecutive'):
        t0 = time.monotonic()
        sweeps.SWEEP_SPACING_S = 0.0 if name == 'consecutive' else spacing
        if name == '10 consecutive':
            seqs = [accumulated(deskewed(seq), 10) for seq in drives]
            runs[name] = run_model(model, seqs, tracker=TrackerConfig(), deskew=False)
        else:
            runs[name] = run_model(model, drives, tracker=TrackerConfig(), deskew=True)
        print(f'{name}: {len(runs[name].det)} frames in {time.monotonic() - t0:.0f} s',
              flush=True)
    sweeps.SWEEP_SPACING_S = spacing
    keys = ['mAP', 'NDS', 'mAVE', 'moving car vel err', 'moving car speed slope', 'AP car',
            'AP pedestrian']
    point, diffs = bootstrap(runs, names, pairs=[('0.1 s apart', 'consecutive'),
                                                 ('10 consecutive', 'consecutive')])
    for n, m in {**point, **diffs}.items():
        print(f'  {n:30s} ' + '  '.join(f'{k} {m[k].fmt()}' for k in keys if k in m))
    if args.out:
        with open(args.out, 'w', encoding='utf-8') as f:
            json.dump({'runs': plain_intervals(point), 'paired': plain_intervals(diffs)}, f,
                      indent=1, default=float)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
