"""Does the model find objects in a drive's first frames, where it has one or two sweeps
(the real dev set has two: the model sees one, then two), as it does later with three?

A synthetic split (tune: 16 drives x 40 frames, seeds 8000+; or val, seeds 9000+; world
val-real) run as the node runs it (tracker on, deskewed, the checkpoint's ground), and with
the tracker off; recall and precision at the published thresholds, BEV centre within 2 m,
within 50 m, by the frame's index in its drive: 0 (one sweep), 1 (two), 2 (three), 0-1,
3-39; and pedestrians and cyclists pooled.

Usage: python by_frame.py SPLIT CHECKPOINT (a shipped name or a path)
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
seqs = synthetic_split(split, 16, 40, 'data_cache')
print(f'{split} split, {name}; published thresholds {dict(zip(names, thr))}')
for label, tracker in (('tracked (node)', TrackerConfig()), ('model alone', None)):
    run = run_model(model, seqs, tracker=tracker, deskew=True)
    index = np.concatenate([np.arange(len(s)) for s in seqs])
    print(f'\n{label}: recall / precision (GT) at the published thresholds')
    print(f"{'frames':10s}" + ''.join(f'{c:>22s}' for c in names) + f"{'ped+cyc':>22s}")
    for what, pick in (('0', index == 0), ('1', index == 1), ('2', index == 2),
                       ('0-1', index <= 1), ('3-39', index >= 3)):
        sub = run.select_frames(np.flatnonzero(pick).tolist())
        counts = class_counts(sub.gt, sub.scored_detections(), names, sub.num_points)
        cells = []
        tp = fp = gt = 0
        for k, c in enumerate(names):
            a = counts[c].at(thr[k])
            cells.append(cell(a))
            if c in ('pedestrian', 'cyclist'):
                tp, fp, gt = tp + a['tp'], fp + a['fp'], gt + a['gt']
        cells.append(f'{tp / max(gt, 1):.3f} / {tp / max(tp + fp, 1):.3f} ({gt})')
        print(f'{what:10s}' + ''.join(f'{x:>22s}' for x in cells))
