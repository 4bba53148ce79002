#!/usr/bin/env python3
"""An overloaded node: the model runs on every k-th cloud; what it is given of the others.

The validation drives (16, seeds 9000+, 40 frames) as the node runs them by default (tracker
on, sweeps deskewed, the checkpoint's ground and overhang), three ways:

- ``full rate``: the model runs on every cloud (scored on the frames the others run on);
- ``every k, sweeps of the clouds it ran on``: the node before this change: a skipped cloud
  was dropped, so the input's past sweeps were the last clouds the model ran on, k x 0.1 s
  apart instead of the 0.1 s the model was trained on;
- ``every k, skipped clouds buffered``: the node now (``StreamingDetector.add_sweep``): the
  input's sweeps are the clouds just before it, as in training; the memory spans k frames.

Per-drive bootstrap (200 resamples), paired over the same drives and frames.
Usage: docs/experiments/overload/measure.py [--every 2 3] [--drives 16] [--out FILE.json]
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or '').splitlines()[0])
    parser.add_argument('--every', type=int, nargs='+', default=[2, 3])
    parser.add_argument('--drives', type=int, default=16)
    parser.add_argument('--checkpoint', default='')
    parser.add_argument('--cache-dir', default='data_cache')
    parser.add_argument('--out', default='')
    args = parser.parse_args()
    import torch
    torch.set_num_threads(2)
    from suit_ros.accuracy import bootstrap, plain_intervals
    from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.evaluate import ModelRun, run_model
    from suit_ros.tracking import TrackerConfig

    seqs = synthetic_split('val', args.drives, 40, args.cache_dir)
    model, cfg, _ = load_checkpoint(args.checkpoint or str(default_checkpoint_path()), 'cpu')
    names = list(cfg.class_names)

    def node_run(**kw: object) -> ModelRun:
        t0 = time.monotonic()
        run = run_model(model, seqs, tracker=TrackerConfig(), deskew=True, **kw)  # type: ignore[arg-type]
        print(f'  {kw or "full rate"}: {len(run.det)} frames in {time.monotonic() - t0:.0f} s',
              flush=True)
        return run

    full = node_run()
    frame_of_drive = [t for seq in seqs for t in range(len(seq))]
    report: dict[str, object] = {}
    for k in args.every:
        keep = [i for i, t in enumerate(frame_of_drive) if t % k == 0]
        same = full.select_frames(keep)
        runs = {'full rate': same,
                f'every {k}, sweeps of the clouds it ran on': node_run(run_every=k,
                                                                       buffer_skipped=False),
                f'every {k}, skipped clouds buffered': node_run(run_every=k)}
        a, b, c = list(runs)
        point, diffs = bootstrap(runs, names, pairs=[(b, a), (c, a), (c, b)])
        keys = ['mAP', 'NDS', 'AP car', 'AP pedestrian', 'moving car vel err']
        print(f'\nmodel on every {k}th cloud ({len(keep)} frames scored)')
        for n, m in point.items():
            print(f'  {n:45s} ' + '  '.join(f'{key} {m[key].fmt()}' for key in keys if key in m))
        for n, m in diffs.items():
            print(f'  {n:90s} ' + '  '.join(f'{key} {m[key].fmt()}' for key in keys[:2]))
        report[f'every {k}'] = {'runs': plain_intervals(point), 'paired': plain_intervals(diffs),
                                'frames': len(keep)}
    if args.out:
        with open(args.out, 'w', encoding='utf-8') as f:
            json.dump(report, f, indent=1, default=float)
    return 0


if __name__ == '__main__':
    np.set_printoptions(precision=3)
    raise SystemExit(main())
