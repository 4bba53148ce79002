#!/usr/bin/env python3
"""Soak: N frames through the streaming model step with the memory carried (issue 7).

Cycles the demo drive (the memory is reset only when the drive loops, as the node would on a
looped bag) and reports RSS growth and latency drift: medians of the first and last 10% of
frames, and RSS sampled every 500 frames.
Usage: scripts/soak.py [--frames 10000] [--checkpoint X]
"""
from __future__ import annotations

import argparse
import resource
import sys
import time

import numpy as np


def rss_mb() -> float:
    with open('/proc/self/status', encoding='utf-8') as f:
        for line in f:
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--frames', type=int, default=10_000)
    parser.add_argument('--checkpoint', default='')
    parser.add_argument('--threads', type=int, default=2)
    args = parser.parse_args()
    import torch

    from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
    from suit_ros.data.sequences import synthetic_sequence
    from suit_ros.evaluate import step_inputs
    from suit_ros.model.streaming import StreamingDetector
    torch.set_num_threads(args.threads)
    model, _, _ = load_checkpoint(args.checkpoint or default_checkpoint_path())
    runner = StreamingDetector(model, 'cpu')
    drive = synthetic_sequence('demo-real', 7, 100, 'data_cache')
    lat, rss = [], []
    period = drive[1].stamp_ns - drive[0].stamp_ns
    t0 = time.monotonic()
    for i in range(args.frames):
        f = drive[i % len(drive)]
        if i % len(drive) == 0:
            runner.reset('drive looped')
        stamp = f.stamp_ns + (i // len(drive)) * len(drive) * period
        pts, _, T_odom_base, T_base_lidar = step_inputs(f)
        r = runner.step(pts, stamp, T_odom_base, T_base_lidar)
        lat.append(r.timings['total'])
        if i % 500 == 0 or i == args.frames - 1:
            rss.append((i, rss_mb()))
    k = max(1, args.frames // 10)
    first, last = np.median(lat[:k]) * 1e3, np.median(lat[-k:]) * 1e3
    print(f'soak: {args.frames} frames in {(time.monotonic() - t0) / 60:.1f} min; latency p50 '
          f'first 10% {first:.1f} ms, last 10% {last:.1f} ms (drift {last - first:+.1f} ms); '
          f'p95 overall {np.percentile(lat, 95) * 1e3:.1f} ms')
    print(f'RSS: {rss[0][1]:.0f} MB at frame {rss[0][0]}, {rss[1][1]:.0f} MB at frame '
          f'{rss[1][0]}, {rss[-1][1]:.0f} MB at frame {rss[-1][0]} (growth after the first 500 '
          f'frames: {rss[-1][1] - rss[1][1]:+.1f} MB)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
