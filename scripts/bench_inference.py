#!/usr/bin/env python3
"""The streaming step on the model as trained and on its inference copies, in one run.

The inference copy (:mod:`suit_ros.model.inference`) has its batch norms folded, which also
lets the pillar encoder skip building the decorated points, and its convolution weights stored
channels-last (NHWC). Four variants: as trained, folded (NCHW), folded + channels-last (the
float32 inference copy), and that copy with its convolutions in bfloat16 (``precision``).

The variants step over the same demo-scene frames, interleaved frame by frame (so load
changes hit all alike); prints the step medians, their ratios to the model as trained, the
largest difference of the detections (inf when their counts differ) and the largest centre
difference of the confident ones (score >= 0.3).

Usage: python scripts/bench_inference.py [--frames 40] [--threads 1 2]
"""
from __future__ import annotations

import argparse
import time
from typing import Any, cast

import numpy as np


def box_difference(a: Any, b: Any) -> float:
    """The largest difference (m, any box parameter) between each box of ``a`` and the box of
    ``b`` with the same label nearest to it, both ways (order-free: boxes whose scores tie to
    float rounding may come out in either order); inf when the label counts differ."""
    if len(a) != len(b) or any((a.labels == k).sum() != (b.labels == k).sum()
                               for k in np.unique(a.labels)):
        return float('inf')
    worst = 0.0
    for x, y in ((a, b), (b, a)):
        for k in np.unique(x.labels):
            p, q = x.boxes[x.labels == k], y.boxes[y.labels == k]
            nearest = np.linalg.norm(p[:, None, :3] - q[None, :, :3], axis=2).argmin(1)
            worst = max(worst, float(np.abs(p - q[nearest]).max()))
    return worst


def confident_difference(a: Any, b: Any, min_score: float = 0.3) -> float:
    """The largest centre distance (m) from a detection with ``score >= min_score`` in either
    set to the nearest detection of the same class in the other (inf when it has none): a
    bfloat16 copy may reorder or drop low-score boxes, the confident ones must stay put."""
    worst = 0.0
    for x, y in ((a, b), (b, a)):
        for box, score, label in zip(x.boxes, x.scores, x.labels):
            if score < min_score:
                continue
            same = y.boxes[y.labels == label, :2]
            if not len(same):
                return float('inf')
            worst = max(worst, float(np.linalg.norm(same - box[:2], axis=1).min()))
    return worst


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
    from suit_ros.model.detector import SUITDetector
    from suit_ros.model.inference import inference_copy
    from suit_ros.model.streaming import StreamingDetector
    model, _, _ = load_checkpoint(str(default_checkpoint_path()), 'cpu')
    sim = Simulation(preset('demo-real', frames=args.frames), 7)
    frames = [to_frame(sim.render(k), 7) for k in range(args.frames)]
    runners = {name: StreamingDetector(model) for name in ('as trained', 'folded', 'folded NHWC')}
    runners['folded NHWC bfloat16'] = StreamingDetector(model, precision='bfloat16')
    runners['as trained'].model = model.eval()
    runners['folded'].model = cast(SUITDetector, inference_copy(model, channels_last=False))
    for threads in args.threads:
        torch.set_num_threads(threads)
        times: dict[str, list[float]] = {name: [] for name in runners}
        worst = dict.fromkeys(runners, 0.0)
        confident = dict.fromkeys(runners, 0.0)
        for r in runners.values():
            r.reset('bench')
        for i, f in enumerate(frames):
            out = {}
            for name, r in runners.items():
                t0 = time.perf_counter()
                out[name] = r.step(*step_inputs(f)).detections
                if i >= 5:                    # warm-up frames not timed
                    times[name].append(time.perf_counter() - t0)
            a = out['as trained']
            for name, b in out.items():
                worst[name] = max(worst[name], box_difference(a, b))
                confident[name] = max(confident[name], confident_difference(a, b))
        p50 = {name: float(np.median(t)) * 1e3 for name, t in times.items()}
        base = p50['as trained']
        n = len(times['as trained'])
        print(f'{threads} torch thread(s), {n} frames, step p50: ' + ', '.join(
            f'{name} {v:.1f} ms ({v / base:.3f}x, largest box difference {worst[name]:.1e} m,'
            f' confident centres {confident[name]:.1e} m)'
            for name, v in p50.items()))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
