"""Where `suit_carry`'s tracked validation cost is: the published boxes of `suit_default` and
`suit_carry` on the 16 validation drives, tracked and deskewed as the node runs them, split by
whether the box is held where the cloud has no returns (`carried`: the carry head's, or a
track coasted by the tracker) and counted as matching an object (same class, BEV centre within
2 m, one box per object, greedy by score) or not. Published: each box at its checkpoint's
published threshold (carried ones at the carry thresholds, as the node cuts them).

Usage: python carried_precision.py [DRIVES] [OUT] (OUT: the JSON written, default
carried_precision.json; docs/experiments/carry_default reran it with stop 51's tracker)
"""
import json
import sys

import numpy as np

from suit_ros.checkpoint import load_checkpoint
from suit_ros.data.sequences import synthetic_split
from suit_ros.evaluate import run_model, tracker_for

drives = int(sys.argv[1]) if len(sys.argv) > 1 else 16
seqs = synthetic_split('val', drives, 40, 'data_cache')
out = {}
for name in ('suit_default', 'suit_carry'):
    model, cfg, meta = load_checkpoint(name, 'cpu')
    run = run_model(model, seqs, tracker=tracker_for(seqs), deskew=True)
    names = list(cfg.class_names)
    thr = np.array([meta['publish_thresholds'][c] for c in names])
    carry_thr = np.array([(meta.get('carry_publish_thresholds') or
                           meta['publish_thresholds'])[c] for c in names])
    counts = {k: [0, 0] for k in ('seen', 'carried')}        # [boxes, matched]
    per_drive = np.zeros((drives, 2, 2), np.int64)
    for det, carried, gt, drive in zip(run.det, run.carried, run.gt, run.drive):
        published = det.scores >= np.where(carried, carry_thr[det.labels], thr[det.labels])
        order = [i for i in np.argsort(-det.scores) if published[i]]
        taken = np.zeros(len(gt), bool)
        for i in order:
            same = np.flatnonzero((gt.labels == det.labels[i]) & ~taken)
            hit = False
            if len(same):
                d = np.hypot(*(gt.boxes[same, :2] - det.boxes[i, :2]).T)
                j = int(np.argmin(d))
                if d[j] <= 2.0:
                    taken[same[j]] = hit = True
            key = 'carried' if carried[i] else 'seen'
            counts[key][0] += 1
            counts[key][1] += int(hit)
            per_drive[drive, int(carried[i]), 0] += 1
            per_drive[drive, int(carried[i]), 1] += int(hit)
    out[name] = {k: {'boxes': b, 'matched': m, 'precision': m / max(b, 1)}
                 for k, (b, m) in counts.items()}
    out[name]['per_drive'] = per_drive.tolist()
    print(name, json.dumps({k: v for k, v in out[name].items() if k != 'per_drive'}))
json.dump(out, open(sys.argv[2] if len(sys.argv) > 2 else 'carried_precision.json', 'w'),
          indent=1)
