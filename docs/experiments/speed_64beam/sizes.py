#!/usr/bin/env python3
"""The SUIT step by stage at 40k / 115k / 264k points a sweep (cached val-real drives; the
264k input is the hdl64e sweeps densified 2.3x by jittered copies, each beside its original
(scan order kept), and `260kshuf` the same points shuffled), 1 thread, tracker on, the sizes
stepping in turn. Before/after a change: run it at each commit (PYTHONPATH=a worktree).
Run from the repository root (the data_cache of the validation split must exist); prints
one line per size and the ratios."""
from __future__ import annotations

from dataclasses import replace
import glob

import numpy as np

try:                                   # the allocator as the node of that commit sets it
    from suit_ros.heap import keep_freed_memory
    keep_freed_memory()
except ImportError:                    # commits before suit_ros/heap.py
    pass
import torch  # noqa: E402

from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
from suit_ros.data.sequences import load_sequence
from suit_ros.evaluate import step_inputs
from suit_ros.model.streaming import StreamingDetector
from suit_ros.tracking import TrackerConfig

STAGES = ('sweeps', 'encode', 'head_decode', 'sampling', 'fusion', 'tracking', 'total')


def drive(pattern: str) -> list:
    return load_sequence(sorted(glob.glob(f'data_cache/{pattern}-*.npz'))[0])[:24]


def main() -> None:
    torch.set_num_threads(1)
    model, _, _ = load_checkpoint(str(default_checkpoint_path()), 'cpu')
    rng = np.random.default_rng(0)
    sim32, hdl = drive('val-real-sim32'), drive('val-real-hdl64e')

    def dense(f, k=2.3, order=True):
        n = int(len(f.points) * k)
        idx = rng.integers(0, len(f.points), n)
        if order:
            idx = np.sort(idx)
        p = f.points[idx].copy()
        p[:, :3] += rng.normal(0, 0.03, (n, 3)).astype(np.float32)
        return replace(f, points=p)
    sets = {'37k': sim32, '114k': hdl, '260k': [dense(f) for f in hdl],
            '260kshuf': [dense(f, order=False) for f in hdl]}
    runners = {k: StreamingDetector(model, precision='auto', tracker=TrackerConfig())
               for k in sets}
    times = {k: {s: [] for s in STAGES} for k in sets}
    for i in range(len(sim32)):
        for k, fs in sets.items():
            r = runners[k].step(*step_inputs(fs[i]))
            if i >= 4:
                for s in STAGES:
                    times[k][s].append(r.timings[s])
    for k in sets:
        points = int(np.median([len(f.points) for f in sets[k]]))
        print(k, points, ' '.join(f'{s} {np.median(times[k][s]) * 1e3:.1f}' for s in STAGES))
    total = {k: np.median(times[k]['total']) for k in sets}
    print(f'114k/37k {total["114k"] / total["37k"]:.2f}  260k/37k '
          f'{total["260k"] / total["37k"]:.2f}')


if __name__ == '__main__':
    main()
