#!/usr/bin/env python3
"""Compare checkpoints on the fixed validation drives, with paired per-drive intervals.

Each checkpoint runs as it is (its own config: sweeps, temporal mode) over the same validation
drives as ``scripts/ablation.py``; every metric gets a per-drive bootstrap 95% interval, and
every run after the first a paired difference against the first. Writes ``OUT/results.md`` and
``OUT/results.json``.

``--drop-memory`` adds, for each temporal checkpoint, a run with its memory dropped before every
frame, paired with it.

Usage: scripts/compare.py --run 3-sweeps runs/a/model.safetensors \\
                          --run 5-sweeps runs/b/model.safetensors --out docs/experiments/x
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
import time

import numpy as np

COLUMNS = ['mAP', 'NDS', 'mAP moving', 'mAVE', 'mAOE', 'moving car vel err',
           'moving car speed ratio', 'moving car speed slope', 'car heading err']


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or '').splitlines()[0])
    parser.add_argument('--run', nargs=2, action='append', required=True,
                        metavar=('NAME', 'CHECKPOINT'), help='a label and a checkpoint')
    parser.add_argument('--drives', type=int, default=16)
    parser.add_argument('--frames', type=int, default=40)
    parser.add_argument('--resamples', type=int, default=100)
    parser.add_argument('--cache-dir', default='data_cache')
    parser.add_argument('--precision', default='float32',
                        choices=['auto', 'float32', 'bfloat16'])
    parser.add_argument('--drop-memory', action='store_true',
                        help='also run each temporal checkpoint with its memory dropped before '
                             'every frame (sweeps kept), paired with it: what its memory is worth')
    parser.add_argument('--out', required=True)
    args = parser.parse_args()
    if len({name for name, _ in args.run}) != len(args.run):
        parser.error('run names must differ')
    import torch
    torch.set_num_threads(2)
    from suit_ros.accuracy import bootstrap, plain_intervals
    from suit_ros.checkpoint import load_checkpoint
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.evaluate import run_model

    t0 = time.monotonic()
    val = synthetic_split('val', args.drives, args.frames, args.cache_dir)
    runs, names = {}, None
    pairs = [(name, args.run[0][0]) for name, _ in args.run[1:]]
    for name, path in args.run:
        model, cfg, _ = load_checkpoint(path, 'cpu')
        if names is not None and tuple(cfg.class_names) != names:
            parser.error(f'{path} has classes {cfg.class_names}, not {names}')
        names = tuple(cfg.class_names)
        runs[name] = run_model(model, val, precision=args.precision)
        if args.drop_memory and cfg.temporal != 'none':
            runs[f'{name}, memory dropped'] = run_model(model, val, drop_memory=True,
                                                        precision=args.precision)
            pairs.append((name, f'{name}, memory dropped'))
        print(f'[compare] {name}: {(time.monotonic() - t0) / 60:.1f} min', flush=True)
    assert names is not None
    first = args.run[0][0]
    stats, diffs = bootstrap(runs, names, pairs, args.resamples)
    latency = {k: float(np.median(r.latency_s)) * 1e3 for k, r in runs.items()}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'results.json').write_text(json.dumps(
        {'runs': plain_intervals(stats), 'differences': plain_intervals(diffs),
         'latency_p50_ms': latency,
         'checkpoints': dict(args.run), 'drives': args.drives, 'frames': args.frames,
         'precision': args.precision, 'date': time.strftime('%Y-%m-%d')}, indent=1))
    lines = ['# Checkpoint comparison', '', f'`scripts/compare.py`, {time.strftime("%Y-%m-%d")}: '
             f'{args.drives} validation drives x {args.frames} frames, {args.precision}, value '
             f'[95% per-drive bootstrap interval, {args.resamples} resamples].', '',
             'The step times come from runs one after another (not interleaved): on a machine '
             'whose speed drifts they are not a speed comparison.', '',
             '| run | checkpoint | step p50 (ms, 2 threads) |', '|---|---|---|']
    lines += [f'| {n} | `{p}` | {latency[n]:.1f} |' for n, p in args.run]
    for title, rows in (('Metrics', stats), (f'Paired differences (runs against {first}'
                                              + (', each against its memory dropped'
                                                 if args.drop_memory else '') + ')', diffs)):
        lines += ['', f'## {title}', '', '| run | ' + ' | '.join(COLUMNS) + ' |',
                  '|---' * (len(COLUMNS) + 1) + '|']
        lines += [f'| {r} | ' + ' | '.join(m[c].fmt(3) if c in m else 'n/a' for c in COLUMNS)
                  + ' |' for r, m in rows.items()]
    text = '\n'.join(lines) + '\n'
    (out / 'results.md').write_text(text)
    print(text)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
