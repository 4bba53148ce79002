"""Could the node make up the sweeps a drive's first frames lack, without training? A probe
(not a fix): where fewer earlier sweeps are buffered than the model takes, the oldest sweep
there is (the current one on a drive's first frame) is repeated as the missing earlier sweeps,
0.1 s apart (the spacing the model trained at), as a world standing still would give them;
the buffer keeps only the real ones. The tune split's first three frames of each drive
(16 drives), with and without, tracker on and off; recall / precision at the published
thresholds, BEV centre within 2 m, within 50 m.

Usage: python pad_probe.py CHECKPOINT (a shipped name or a path)
"""
from collections import deque
import sys

import numpy as np
from shared import cell, checkpoint  # this folder's (the script's folder is on the path)

from suit_ros.data.sequences import synthetic_split
from suit_ros.evaluate import run_model
from suit_ros.model import sweeps as sweeps_module
from suit_ros.model.sweeps import Sweep, SweepBuffer, already_accumulated
from suit_ros.report import class_counts
from suit_ros.tracking import TrackerConfig

name = sys.argv[1]
model, names, thr = checkpoint(name)
seqs = [s[:3] for s in synthetic_split('tune', 16, 40, 'data_cache')]
original = SweepBuffer.push
PERIOD_NS = 100_000_000


def padded(self, points, T_odom_lidar, stamp_ns, T_base_lidar):  # type: ignore[no-untyped-def]
    if T_odom_lidar is None or already_accumulated(points) or not self.past.maxlen:
        return original(self, points, T_odom_lidar, stamp_ns, T_base_lidar)
    if self.past and stamp_ns <= self.past[-1].stamp_ns:
        self.clear()
    while self.past and stamp_ns - self.past[0].stamp_ns > self.max_age_s * 1e9:
        self.past.popleft()
    missing = self.sweeps - 1 - len(self.past)
    if missing <= 0:
        return original(self, points, T_odom_lidar, stamp_ns, T_base_lidar)
    real = list(self.past)
    oldest = real[0] if real else Sweep(np.asarray(points, np.float32),
                                        np.asarray(T_odom_lidar, np.float64), stamp_ns)
    fakes = [Sweep(oldest.points, oldest.T_odom_lidar, oldest.stamp_ns - k * PERIOD_NS)
             for k in range(missing, 0, -1)]
    self.past = deque(fakes + real, maxlen=self.past.maxlen)
    out = original(self, points, T_odom_lidar, stamp_ns, T_base_lidar)
    self.past = deque([s for s in self.past if all(s is not f for f in fakes)],
                      maxlen=self.past.maxlen)
    return out


print(f'tune split, first 3 frames of 16 drives, {name}; published thresholds '
      f'{dict(zip(names, thr))}')
for pad in (False, True):
    sweeps_module.SweepBuffer.push = padded if pad else original  # type: ignore[method-assign]
    for label, tracker in (('tracked', TrackerConfig()), ('model alone', None)):
        run = run_model(model, seqs, tracker=tracker, deskew=True)
        index = np.concatenate([np.arange(len(s)) for s in seqs])
        print(f"\n{'padded' if pad else 'as is'}, {label}: recall / precision (GT)")
        print(f"{'frame':8s}" + ''.join(f'{c:>22s}' for c in names))
        for k in range(3):
            sub = run.select_frames(np.flatnonzero(index == k).tolist())
            counts = class_counts(sub.gt, sub.scored_detections(), names, sub.num_points)
            print(f'{k:<8d}' + ''.join(
                cell(counts[c].at(thr[i])).rjust(22) for i, c in enumerate(names)))
