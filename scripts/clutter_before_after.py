#!/usr/bin/env python3
"""False positives on street clutter before and after the detailed world, on the fixed
validation drives.

*Before* is the checkpoint shipped before the real-sensor work (commit 1e0d6b8: one sweep, the
LiDAR frame as the model frame, trained on the box world, which had no clutter); *after* are
the shipped checkpoints (trained with clutter as negatives). All run on the same validation
drives (``val`` seeds 9000..9015, 40 frames each), which hold clutter. The before model gets the
input it was trained on: one sweep in the LiDAR frame (the extrinsic set to identity, so its
model frame is the LiDAR frame). Counts are false-positive boxes per frame with score >= 0.3
on a clutter object (``suit_ros.data.sim.clutter.clutter_false_positives``), with a per-drive
bootstrap 95% interval of the total; mAP is given for context.

Usage: scripts/clutter_before_after.py [--before PATH] (default: read from git at 1e0d6b8)
"""
from __future__ import annotations

import argparse
from dataclasses import replace
import json
from pathlib import Path
import subprocess
import sys
import tempfile
import time
from typing import Any

import numpy as np

BEFORE_COMMIT = '1e0d6b8'
# model-config keys that the checkpoint of BEFORE_COMMIT has and this code no longer reads
# (the staleness threshold moved from the model to the pipeline)
RETIRED_KEYS = ('max_time_gap',)


def before_checkpoint(path: str, workdir: Path) -> str:
    """The before checkpoint with its retired config keys dropped (a copy in ``workdir``)."""
    from safetensors import safe_open
    from safetensors.torch import save_file
    src = path or str(workdir / 'before.safetensors')
    if not path:
        blob = subprocess.run(['git', 'show', f'{BEFORE_COMMIT}:suit_ros/checkpoints/'
                               'suit_default.safetensors'], check=True,
                              capture_output=True).stdout
        Path(src).write_bytes(blob)
    with safe_open(src, framework='pt') as f:
        meta = json.loads((f.metadata() or {})['suit_ros'])
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    for key in RETIRED_KEYS:
        meta['config'].pop(key, None)
    out = workdir / 'before-clean.safetensors'
    save_file(tensors, str(out), metadata={'suit_ros': json.dumps(meta)})
    return str(out)


def lidar_as_model_frame(frame: Any) -> Any:
    """One sweep, the LiDAR frame as the model frame (what the before model was trained on)."""
    return replace(frame, T_base_lidar=np.eye(4))


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or '').splitlines()[0])
    parser.add_argument('--before', default='', help=f'default: the checkpoint at '
                        f'{BEFORE_COMMIT}, read with git')
    parser.add_argument('--single', default='suit_ros/checkpoints/centerpoint_single.safetensors')
    parser.add_argument('--suit', default='suit_ros/checkpoints/suit_default.safetensors')
    parser.add_argument('--drives', type=int, default=16)
    parser.add_argument('--frames', type=int, default=40)
    parser.add_argument('--min-score', type=float, default=0.3)
    parser.add_argument('--resamples', type=int, default=1000)
    parser.add_argument('--cache-dir', default='data_cache')
    parser.add_argument('--out', default='docs/clutter_before_after.json')
    args = parser.parse_args()
    import torch
    torch.set_num_threads(2)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from ablation import (  # type: ignore[import-not-found]
        clutter_counts,
        clutter_frames,
        clutter_summary,
    )

    from suit_ros.checkpoint import load_checkpoint
    from suit_ros.data.sequences import split_drives, synthetic_split
    from suit_ros.evaluate import run_model
    t0 = time.monotonic()
    val = synthetic_split('val', args.drives, args.frames, args.cache_dir)
    drives = split_drives('val', args.drives)
    with tempfile.TemporaryDirectory() as tmp:
        before, bcfg, _ = load_checkpoint(before_checkpoint(args.before, Path(tmp)), 'cpu')
    if bcfg.sweeps != 1:
        raise SystemExit(f'the before checkpoint has {bcfg.sweeps} sweeps; expected 1')
    runs = {'before (one sweep, box world)': run_model(before, val,
                                                       transform=lidar_as_model_frame),
            'single (shipped)': run_model(load_checkpoint(args.single, 'cpu')[0], val),
            'suit (shipped)': run_model(load_checkpoint(args.suit, 'cpu')[0], val)}
    sim_frames = clutter_frames(drives, args.frames)
    counts = {name: clutter_counts(run, sim_frames, args.min_score) for name, run in runs.items()}
    fp = clutter_summary(counts)
    from suit_ros.data.sim.clutter import CLUTTER_TYPES
    rng = np.random.default_rng(0)
    n = len(drives)
    picks = rng.integers(0, n, (args.resamples, n))
    out: dict[str, Any] = {'meta': {'drives': [list(d) for d in drives], 'frames': args.frames,
                                    'min_score': args.min_score, 'before': BEFORE_COMMIT,
                                    'date': time.strftime('%Y-%m-%d')},
                           'clutter_fp_per_frame': fp, 'all_interval': {}, 'mAP': {}}
    per_drive = {name: c.sum(1).reshape(n, args.frames).mean(1) for name, c in counts.items()}
    boot = {name: v[picks].mean(1) for name, v in per_drive.items()}    # same resamples
    for name, run in runs.items():
        out['all_interval'][name] = [float(np.percentile(boot[name], 2.5)),
                                     float(np.percentile(boot[name], 97.5))]
        out['mAP'][name] = float(run.evaluate(bcfg.class_names).mean_ap)
    before_name, *after_names = runs
    for name in after_names:
        ratio = boot[name] / np.maximum(boot[before_name], 1e-9)
        out.setdefault('after_over_before', {})[name] = [
            float(per_drive[name].mean() / max(per_drive[before_name].mean(), 1e-9)),
            float(np.percentile(ratio, 2.5)), float(np.percentile(ratio, 97.5))]
    Path(args.out).write_text(json.dumps(out, indent=1))
    cols = list(CLUTTER_TYPES) + ['all']
    print('| run | ' + ' | '.join(cols) + ' | all, 95% interval | mAP |')
    print('|---' * (len(cols) + 3) + '|')
    for name in runs:
        lo, hi = out['all_interval'][name]
        print(f'| {name} | ' + ' | '.join(f'{fp[name][c]:.2f}' for c in cols)
              + f' | [{lo:.2f}, {hi:.2f}] | {out["mAP"][name]:.3f} |')
    for name, (v, lo, hi) in out.get('after_over_before', {}).items():
        print(f'{name} / before (all clutter FP): {v:.2f} [{lo:.2f}, {hi:.2f}]')
    print(f'[clutter] {(time.monotonic() - t0) / 60:.1f} min')
    return 0


if __name__ == '__main__':
    sys.exit(main())
