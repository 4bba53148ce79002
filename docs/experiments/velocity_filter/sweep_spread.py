#!/usr/bin/env python3
"""Sweep readings weighed by how far their earlier sweeps agree: validation, as the node runs.

``sweep_velocities`` reads a vehicle's speed from how its returns shift between the sweeps of
the model input; each earlier sweep also gives a speed of its own. The tracker used to fuse
every reading at ``sweep_sigma`` 1.5 m/s; it now widens a reading's noise by how far its
sweeps' speeds lie apart (``sweep_spread_gain`` 3, ``sweep_sigma`` 0.75), and takes a reading
only one earlier sweep gave at ``sweep_single_sigma`` 1.0 m/s, chosen on the tune split in that
order (``scripts/tune_tracker.py --grid spread``, then ``--grid single``: ``tune_spread.json``,
``tune_single.json``).

This runs the shipped SUIT checkpoint over the validation drives (16, seeds 9000+, 40 frames,
never trained or tuned on), tracked and deskewed as the node runs it, with the tracker as it
was (``before``) and as it is (``after``), and prints mAP, NDS, mAVE and the moving-car
velocity error with per-drive bootstrap intervals (200 resamples), paired, over every frame
and from frame 3 of each drive on (a node that has run for 0.3 s).

Usage: docs/experiments/velocity_filter/sweep_spread.py [--drives 16] [--out F.json]
"""
from __future__ import annotations

import argparse
import json
import time
from typing import Any


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or '').splitlines()[0])
    parser.add_argument('--drives', type=int, default=16)
    parser.add_argument('--cache-dir', default='data_cache')
    parser.add_argument('--out', default='')
    args = parser.parse_args()
    import torch
    torch.set_num_threads(2)
    from suit_ros.accuracy import bootstrap, plain_intervals
    from suit_ros.checkpoint import load_checkpoint
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.evaluate import ModelRun, run_model
    from suit_ros.tracking import TrackerConfig

    model, cfg, _ = load_checkpoint('suit_default', 'cpu')
    names = list(cfg.class_names)
    seqs = synthetic_split('val', args.drives, 40, args.cache_dir)
    configs = {'before': TrackerConfig(sweep_sigma=1.5, sweep_spread_gain=0.0,
                                       sweep_single_sigma=None),
               'after': TrackerConfig()}
    runs: dict[str, ModelRun] = {}
    for name, tracker in configs.items():
        t0 = time.monotonic()
        runs[name] = run_model(model, seqs, tracker=tracker, deskew=True)
        print(f'{name}: sweep_sigma {tracker.sweep_sigma}, sweep_spread_gain '
              f'{tracker.sweep_spread_gain}, sweep_single_sigma {tracker.sweep_single_sigma}: '
              f'{len(runs[name].det)} frames in '
              f'{time.monotonic() - t0:.0f} s', flush=True)
    keys = ['mAP', 'NDS', 'mAVE', 'moving car vel err', 'moving car speed slope']
    drive = runs['before'].drive
    late = [i for i in range(len(drive)) if i >= 3 and drive[i - 3] == drive[i]]
    report: dict[str, Any] = {}
    for part, picked in (('every frame', runs),
                         ('from frame 3', {n: r.select_frames(late) for n, r in runs.items()})):
        point, diffs = bootstrap(picked, names, pairs=[('after', 'before')])
        print(part)
        for n, m in {**point, **diffs}.items():
            print(f'  {n:16s} ' + '  '.join(f'{k} {m[k].fmt()}' for k in keys if k in m))
        report[part] = {'runs': plain_intervals(point), 'paired': plain_intervals(diffs)}
    if args.out:
        with open(args.out, 'w', encoding='utf-8') as f:
            json.dump(report, f, indent=1, default=float)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
