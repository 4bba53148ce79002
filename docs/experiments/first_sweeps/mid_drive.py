"""Is a drive's first frame hard because it has one sweep (and no memory), or because of
what the drives' first frames hold? The same frames read two ways: each drive of a split
(tune: 16 x 40 frames, seeds 8000+; val: seeds 9000+) streamed whole, and the same drive
started afresh at frames 10, 20 and 30 (the stream from there on: one sweep and no memory at
the start, as the node after a reset);
recall / precision at the published thresholds of frames k, k + 1, k + 2 after each start,
pooled over the three starts, tracker on (node defaults) and off.

Usage: python mid_drive.py SPLIT CHECKPOINT (a shipped name or a path)
"""
import sys

import numpy as np
from shared import cell, checkpoint  # this folder's (the script's folder is on the path)

from suit_ros.data.sequences import synthetic_split
from suit_ros.evaluate import run_model
from suit_ros.report import class_counts
from suit_ros.tracking import TrackerConfig

split, name = sys.argv[1], sys.argv[2]
model, names, thr = checkpoint(name)
drives = synthetic_split(split, 16, 40, 'data_cache')
STARTS = (10, 20, 30)
print(f'{split} split, 16 drives, fresh starts at frames {STARTS}, {name}; published thresholds '
      f'{dict(zip(names, thr))}')
for label, tracker in (('tracked', TrackerConfig()), ('model alone', None)):
    whole = run_model(model, drives, tracker=tracker, deskew=True)
    cut = [d[s:s + 3] for s in STARTS for d in drives]
    fresh = run_model(model, cut, tracker=tracker, deskew=True)
    first = np.cumsum([0] + [len(d) for d in drives])     # each drive's frame 0 in ``whole``
    print(f'\n{label}: recall / precision (GT)')
    print(f"{'frames after the start':26s}" + ''.join(f'{c:>22s}' for c in names))
    for k in range(3):
        rows = {'streamed whole': (whole, [int(first[i]) + s + k for s in STARTS
                                           for i in range(len(drives))]),
                'started afresh': (fresh, [j * 3 + k for j in range(len(cut))])}
        for how, (run, idx) in rows.items():
            sub = run.select_frames(idx)
            counts = class_counts(sub.gt, sub.scored_detections(), names, sub.num_points)
            print(f'{k} {how:24s}' + ''.join(
                cell(counts[c].at(thr[i])).rjust(22) for i, c in enumerate(names)))
