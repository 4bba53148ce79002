#!/usr/bin/env python3
"""The ablation table (paper Tables I-IV style) on the fixed synthetic validation set.

Every temporal variant is fine-tuned from the same stage-1 single-frame checkpoint with the same
budget (steps, data, seed), then evaluated on the fixed validation split (``val`` seeds
9000..9003, 40 frames each). SUIT is also evaluated with 2 and with 10 frames of history.
Writes docs/results.md and docs/results.json; the SUIT run becomes the shipped checkpoint when
``--ship`` is given.

Usage: scripts/ablation.py --stage1 runs/stage1/model.safetensors --steps 300 [--ship]
"""
from __future__ import annotations

import argparse
from dataclasses import replace
import json
import os
from pathlib import Path
import platform
import shutil
import sys
import time

import numpy as np

VARIANTS = ('none', 'dense', 'sparse', 'sparse_velocity', 'suit')
LABELS = {'none': 'single-frame (CenterPoint-pillar)', 'dense': 'dense BEV fusion',
          'sparse': 'sparse, no GeoNet (zero displacement)',
          'sparse_velocity': 'sparse + predicted velocity', 'suit': 'SUIT (GeoNet)'}


def moving_view(frames_gt, frames_det, npts, speed=1.0):
    """GT and detections restricted to objects moving faster than ``speed`` m/s."""
    g = [d.select(np.hypot(*d.velocities.T) > speed) for d in frames_gt]
    d = [x.select(np.hypot(*x.velocities.T) > speed) for x in frames_det]
    n = [None if p is None else p[np.hypot(*x.velocities.T) > speed]
         for p, x in zip(npts, frames_gt)]
    return g, d, n


def evaluate_variant(ckpt: Path, val, history=None):
    """Metrics for one checkpoint (and the moving-object AP)."""
    from suit_ros.checkpoint import load_checkpoint
    from suit_ros.evaluate import evaluate, run_model
    model, cfg, _ = load_checkpoint(ckpt, 'cpu')
    run = run_model(model, val, 'cpu', history)
    out = run.evaluate(cfg.class_names).summary()
    mg, md, mn = moving_view(run.gt, run.det, run.num_points)
    out['moving_mAP'] = round(evaluate(mg, md, cfg.class_names, num_points=mn).mean_ap, 4)
    for k, v in run.memory_after.items():
        out[f'memory_bytes_after_{k}'] = int(np.median(v))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--stage1', required=True)
    parser.add_argument('--steps', type=int, default=300)
    parser.add_argument('--out', default='runs/ablation')
    parser.add_argument('--config', default='params/train_suit.yaml')
    parser.add_argument('--variants', nargs='+', default=list(VARIANTS))
    parser.add_argument('--ship', action='store_true',
                        help='copy the SUIT checkpoint to suit_ros/checkpoints/')
    parser.add_argument('--skip-train', action='store_true')
    args = parser.parse_args()
    import torch
    torch.set_num_threads(2)
    from suit_ros.data.sequences import VAL_SEQUENCES, synthetic_split
    from suit_ros.train import load_train_config, train
    base = load_train_config(args.config)
    out = Path(args.out)
    rows = {}
    for v in args.variants:
        ckpt = out / v / 'model.safetensors'
        if not args.skip_train or not ckpt.exists():
            if (out / v).exists():
                shutil.rmtree(out / v)
            tc = replace(base, temporal=v, init_from=args.stage1, steps=args.steps,
                         eval_at_end=False)
            t0 = time.monotonic()
            train(tc, out / v, threads=2)
            print(f'[ablation] {v}: trained in {(time.monotonic() - t0) / 60:.1f} min',
                  flush=True)
    val = synthetic_split('val', VAL_SEQUENCES, base.val_frames, base.cache_dir)
    for v in args.variants:
        ckpt = out / v / 'model.safetensors'
        rows[v] = evaluate_variant(ckpt, val)
        print(f'[ablation] {v}: {rows[v]}', flush=True)
    if 'suit' in args.variants:
        for h in (2, 10):
            rows[f'suit@{h}'] = evaluate_variant(out / 'suit' / 'model.safetensors', val, h)
            print(f'[ablation] suit@{h}: {rows[f"suit@{h}"]}', flush=True)
    write_results(rows, args)
    if args.ship and 'suit' in args.variants:
        dst = Path('suit_ros/checkpoints/suit_default.safetensors')
        shutil.copy(out / 'suit' / 'model.safetensors', dst)
        print(f'[ablation] shipped {dst} ({dst.stat().st_size / 1e6:.1f} MB)')
    return 0


def write_results(rows, args) -> None:
    from suit_ros import CLASS_NAMES
    Path('docs').mkdir(exist_ok=True)
    meta = {'machine': f'{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, '
                       f'{platform.python_version()}',
            'steps_per_variant': args.steps, 'stage1': args.stage1,
            'date': time.strftime('%Y-%m-%d')}
    Path('docs/results.json').write_text(json.dumps({'meta': meta, 'rows': rows}, indent=2))
    head = ('| variant | mAP | NDS | ' + ' | '.join(f'AP {c}' for c in CLASS_NAMES)
            + ' | mAVE | moving mAP | latency p50 (ms) | memory bytes (p50) |')
    lines = ['# Results', '',
             'Regenerated by `scripts/ablation.py` (see docs/model_card.md for the recipe).',
             f'Fixed synthetic validation set: `val` seeds 9000-9003, 40 frames each, 32 beams. '
             f'Every variant fine-tuned {args.steps} steps from the same stage-1 checkpoint. '
             f'Machine: {meta["machine"]}; {meta["date"]}.', '',
             'NDS has no attribute term: (5 mAP + sum over ATE/ASE/AOE/AVE of (1 - min(1, x))) '
             '/ 9. "moving mAP": GT and detections with speed > 1 m/s only. Latency: the '
             'streaming model step, p50, this machine, 2 threads.', '', head,
             '|' + '---|' * (head.count('|') - 1)]
    order = [v for v in ('none', 'dense', 'sparse', 'sparse_velocity', 'suit', 'suit@2',
                         'suit@10') if v in rows]
    for v in order:
        r = rows[v]
        label = LABELS.get(v, f'SUIT, {v.split("@")[1]} frames of history' if '@' in v else v)
        lines.append(f'| {label} | {r["mAP"]:.4f} | {r["NDS"]:.4f} | '
                     + ' | '.join(f'{r[f"AP_{c}"]:.4f}' for c in CLASS_NAMES)
                     + f' | {r["mAVE"]:.3f} | {r["moving_mAP"]:.4f} | {r["latency_p50_ms"]} | '
                       f'{r["memory_bytes_p50"]} |')
    Path('docs/results.md').write_text('\n'.join(lines) + '\n')
    print('\n'.join(lines))


if __name__ == '__main__':
    sys.exit(main())
