#!/usr/bin/env python3
"""The streaming step on the model as trained and on its inference copy, in one run.

The inference copy (:mod:`suit_ros.model.inference`) has its batch norms folded, which also
lets the pillar encoder skip building the decorated points.

Both variants step over the same demo-scene frames, interleaved frame by frame (so load
changes hit both alike); prints the step medians, their ratio, and the largest difference of
the detections.

Usage: python scripts/bench_inference.py [--frames 40] [--threads 1 2]
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or '').splitlines()[0])
    parser.add_argument('--frames', type=int, default=40)
    parser.add_argument('--threads', type=int, nargs='+', default=[1, 2])
    args = parser.parse_args()
    import torch

    from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
    from suit_ros.data.sim import preset
    from suit_ros.data.sim.scene import Simulation, to_frame
    from suit_ros.evaluate import step_inputs
    from suit_ros.model.streaming import StreamingDetector
    model, _, _ = load_checkpoint(str(default_checkpoint_path()), 'cpu')
    sim = Simulation(preset('demo-real', frames=args.frames), 7)
    frames = [to_frame(sim.render(k), 7) for k in range(args.frames)]
    folded = StreamingDetector(model)
    plain = StreamingDetector(model)
    plain.model = model.eval()               # the model as trained
    for threads in args.threads:
        torch.set_num_threads(threads)
        times: dict[str, list[float]] = {'plain': [], 'folded': []}
        worst = 0.0
        for r in (plain, folded):
            r.reset('bench')
        for i, f in enumerate(frames):
            out = {}
            for name, r in (('plain', plain), ('folded', folded)):
                t0 = time.perf_counter()
                out[name] = r.step(*step_inputs(f)).detections
                if i >= 5:                    # warm-up frames not timed
                    times[name].append(time.perf_counter() - t0)
            a, b = out['plain'], out['folded']
            if len(a) == len(b) and len(a):
                worst = max(worst, float(np.abs(a.boxes - b.boxes).max()))
            elif len(a) != len(b):
                worst = float('inf')
        p, q = np.median(times['plain']) * 1e3, np.median(times['folded']) * 1e3
        print(f'{threads} torch thread(s), {len(times["plain"])} frames: step p50 as trained '
              f'{p:.1f} ms, inference copy {q:.1f} ms, ratio {q / p:.3f}; largest box difference '
              f'{worst:.2e} m')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
