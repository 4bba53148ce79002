"""Where `suit_carry`'s carried detections come from (carried_tune.log).

Usage: python analyze.py [DRIVES] (from the repository root). Runs the tracker as it was
before this stop (carried_refresh=True, carried_as_seen=False). `suit_carry` tracked and
deskewed on the tune split (ordinary, and with outages drawn in as `choose-thresholds` does);
each detection its carry head decoded where the input had no returns, by whether it continues
a track, how many frames since that track's last detection seen in the cloud, its score, and
whether it matches an object (same class, BEV centre within 2 m, greedy by score).
"""
import sys

import numpy as np

from suit_ros.checkpoint import load_checkpoint
from suit_ros.data.sequences import synthetic_split
from suit_ros.evaluate import run_model, tracker_for
from suit_ros.outage import outages_for, with_outages
import suit_ros.tracking as T

drives = int(sys.argv[1]) if len(sys.argv) > 1 else 16
rec = []
orig = T.Tracker.update


def update(self, det, stamp_ns, T_odom_frame, swept=None, carried=None, current=None,
           sensor=None):
    """The tracker's update, recording per detection the frames since its track's last
    detection seen in the cloud (-1: no such track), whether carried, and its id."""
    if not hasattr(self, '_real'):
        self._real = {}
    if (self.stamp_ns is None or stamp_ns <= self.stamp_ns
            or (stamp_ns - self.stamp_ns) * 1e-9 > self.config.max_gap_s):
        self._real = {}
    out, ids = orig(self, det, stamp_ns, T_odom_frame, swept, carried, current, sensor)
    c = np.zeros(len(det), bool) if carried is None else np.asarray(carried, bool)
    age = []
    for i in range(len(det)):
        tid = int(ids[i])
        if c[i]:
            last = self._real.get(tid)
            age.append(-1 if last is None else int(round((stamp_ns - last) * 1e-9 / 0.1)))
        else:
            if tid:
                self._real[tid] = stamp_ns
            age.append(0)
    rec.append((np.array(age), c.copy(), ids.copy()))
    return out, ids


T.Tracker.update = update
before = T.TrackerConfig(carried_refresh=True, carried_as_seen=False)
model, cfg, meta = load_checkpoint('suit_carry', 'cpu')
seqs = synthetic_split('tune', drives, 40, 'data_cache')
for setname in ('ordinary', 'outage'):
    played = seqs
    if setname == 'outage':
        outs = [outages_for(i, len(s), seed=1) for i, s in enumerate(seqs)]
        played = [with_outages(s, o) for s, o in zip(seqs, outs)]
    rec.clear()
    run = run_model(model, played, tracker=tracker_for(played, before), deskew=True)
    rows = []
    for (age, c, ids), det, gt in zip(rec, run.det, run.gt):
        taken = np.zeros(len(gt), bool)
        hit = np.zeros(len(det), bool)
        for i in np.argsort(-det.scores):
            same = np.flatnonzero((gt.labels == det.labels[i]) & ~taken)
            if len(same):
                d = np.hypot(*(gt.boxes[same, :2] - det.boxes[i, :2]).T)
                j = int(np.argmin(d))
                if d[j] <= 2.0:
                    taken[same[j]] = hit[i] = True
        rows += [(int(age[i]), int(ids[i] != 0), float(det.scores[i]), int(hit[i]))
                 for i in range(len(age)) if c[i]]
    age, tracked, score, hit = np.array(rows).T
    print(setname, 'carried dets', len(rows), 'precision', hit.mean().round(3))
    for lo, hi in ((0.1, 0.2), (0.2, 0.3), (0.3, 0.45), (0.45, 1.01)):
        m = (score >= lo) & (score < hi)
        print(f'  score {lo}-{hi}: n {m.sum()} prec {hit[m].mean() if m.any() else 0:.3f}')
    for a in (-1, 1, 2, 3, 4, 5, 6, 8, 10, 12):
        m = (age == a) if a < 6 else (age >= a) & (age < a + 2 if a < 12 else age < 99)
        print(f'  age {a}{"" if a < 6 else "+"}: n {m.sum()} '
              f'prec {hit[m].mean() if m.any() else 0:.3f} '
              f'mean score {score[m].mean() if m.any() else 0:.3f}')
    m = tracked == 0
    print(f'  untracked: n {m.sum()} prec {hit[m].mean() if m.any() else 0:.3f}')
