"""The fair benchmark: metrics by speed and visibility bucket, per-drive bootstrap intervals,
and the car heading / velocity figures of the motion issue.

Buckets follow nuScenes' attribute rule: a bucket's AP is computed against the GT in the bucket;
a detection matched (at each distance threshold, against every GT box) to a GT box outside the
bucket is ignored (neither TP nor FP), and an unmatched detection counts as a false positive in
every bucket, since it could belong to any (:func:`bucket_matches`).

Intervals resample *drives* with replacement (frames of a drive are not independent) and
recompute each metric on the resampled set; differences between two runs use the same resamples
(paired), so an interval of a difference above 0 means the gain holds across drives. A class
without GT in a resample has no AP there, and a resample without a class that the whole set
holds leaves the means (mAP, NDS, the mTP errors) out of their interval: a mean over fewer
classes is another quantity.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from suit_ros.evaluate import (
    DIST_THRESHOLDS,
    FrameMatches,
    ModelRun,
    filter_frames,
    match_frame,
    result_from_matches,
)
from suit_ros.structures import Detections, Frame

MOVING_SPEED = 1.0                 # m/s: GT faster than this is "moving"
VISIBILITY = {'1-5': (1, 5), '6-20': (6, 20), '>20': (21, 1 << 31)}
Bucket = Literal['all', 'moving', 'vis 1-5', 'vis 6-20', 'vis >20']
BUCKETS: tuple[Bucket, ...] = ('all', 'moving', 'vis 1-5', 'vis 6-20', 'vis >20')


def bucket_mask(gt: Detections, num_points: NDArray[np.uint32] | None,
                bucket: Bucket) -> NDArray[np.bool_]:
    """Which GT boxes of a frame are in ``bucket``."""
    n = len(gt)
    if bucket == 'all':
        return np.ones(n, bool)
    if bucket == 'moving':
        return np.hypot(gt.velocities[:, 0], gt.velocities[:, 1]) > MOVING_SPEED
    lo, hi = VISIBILITY[bucket.split(' ', 1)[1]]
    pts = np.zeros(n, np.int64) if num_points is None else num_points.astype(np.int64)
    return (pts >= lo) & (pts <= hi)


def bucket_matches(gt: Detections, det: Detections, keep: NDArray[np.bool_], label: int,
                   dist_th: float) -> FrameMatches:
    """One frame's class-``label`` matches at ``dist_th`` for a bucket (``keep``: which GT
    boxes are in it): the detections are matched against every GT box (nuScenes' greedy
    rule), those matched to a box outside the bucket are left out (neither TP nor FP), the
    unmatched ones stay as false positives, and only the bucket's boxes count as positives."""
    m = match_frame(gt, det, label, dist_th)
    if keep.all():
        return m
    assert m.gt_index is not None             # match_frame always records it
    inside = keep[gt.labels == label]
    own = ~m.tp
    own[m.tp] = inside[m.gt_index[m.tp]]
    return FrameMatches(m.scores[own], m.tp[own], m.errors[own], int(inside.sum()))


class RunMetrics:
    """Every metric of a run over any selection of its frames, from matches computed once.

    Frames are matched once per bucket, class and distance threshold
    (:func:`suit_ros.evaluate.match_frame`); a selection (a bootstrap resample, frames may
    repeat) only re-accumulates the curves. ``ranges``: the scored range per class (default
    :data:`suit_ros.evaluate.CLASS_RANGES`).
    """

    def __init__(self, run: ModelRun, class_names: Sequence[str],
                 ranges: dict[str, float] | None = None) -> None:
        self.class_names = tuple(class_names)
        self.num_frames = len(run.gt)
        gts, dets, npts = filter_frames(run.gt, run.scored_detections(), class_names, ranges,
                                        num_points=run.num_points)
        labels = range(len(class_names))
        self.flat: dict[tuple[Bucket, int, float], _Flat] = {}
        for bucket in BUCKETS:
            keeps = [bucket_mask(g, n, bucket) for g, n in zip(gts, npts)]
            for label in labels:
                for th in DIST_THRESHOLDS:
                    self.flat[bucket, label, th] = _Flat(
                        [bucket_matches(g, d, k, label, th)
                         for g, d, k in zip(gts, dets, keeps)])
        car = self.class_names.index('car') if 'car' in self.class_names else 0
        # the scored frames (range, returns, ignore boxes), as the report's headings
        self.motion = [car_motion_frame(g, d, car) for g, d in zip(gts, dets)]

    def present(self, frames: Sequence[int] | None = None) -> dict[Bucket, tuple[str, ...]]:
        """Per bucket, the classes with GT in ``frames`` (all when None)."""
        idx = np.arange(self.num_frames) if frames is None else np.asarray(frames, np.int64)
        th = DIST_THRESHOLDS[0]
        return {b: tuple(c for label, c in enumerate(self.class_names)
                         if self.flat[b, label, th].npos[idx].sum() > 0) for b in BUCKETS}

    def __call__(self, frames: Sequence[int] | None = None,
                 required: Mapping[Bucket, Sequence[str]] | None = None) -> dict[str, float]:
        """mAP, NDS, the mTP errors, AP per class, mAP per bucket and the car motion figures
        over ``frames`` (all when None); a class without GT there has AP nan and is left out
        of the means. ``required`` (a bootstrap resample): per bucket the classes the whole
        set holds; a selection that lacks one has that bucket's means nan (undefined: over
        another class set they are another quantity), not a mean over fewer classes."""
        idx = np.arange(self.num_frames) if frames is None else np.asarray(frames, np.int64)
        out: dict[str, float] = {}
        nan = float('nan')
        for bucket in BUCKETS:
            res = result_from_matches(
                self.class_names,
                {label: {th: [self.flat[bucket, label, th].select(idx)]
                         for th in DIST_THRESHOLDS}
                 for label in range(len(self.class_names))}, len(idx))
            lacking = required is not None and not set(required[bucket]) <= set(res.evaluated)
            if bucket == 'all':
                out.update({'mAP': nan if lacking else res.mean_ap,
                            'NDS': nan if lacking else res.nds,
                            **{k: nan if lacking else v for k, v in res.mean_tp.items()}})
                out.update({f'AP {c}': v for c, v in res.class_ap.items()})
            else:
                out[f'mAP {bucket}'] = nan if lacking else res.mean_ap
        out.update(car_motion_summary([self.motion[i] for i in idx]))
        return out


class _Flat:
    """The matches of every frame in flat arrays, for fast selections of frames."""

    def __init__(self, matches: Sequence[FrameMatches]) -> None:
        self.scores = np.concatenate([m.scores for m in matches])
        self.tp = np.concatenate([m.tp for m in matches])
        self.errors = np.concatenate([m.errors for m in matches])
        self.offsets = np.cumsum([0] + [len(m.scores) for m in matches])
        self.npos = np.array([m.npos for m in matches], np.int64)

    def select(self, frames: NDArray[np.int64]) -> FrameMatches:
        """The frames' matches as one (frames may repeat; order kept)."""
        lens = self.offsets[frames + 1] - self.offsets[frames]
        idx = (np.arange(int(lens.sum())) - np.repeat(np.cumsum(lens) - lens, lens)
               + np.repeat(self.offsets[frames], lens))
        return FrameMatches(self.scores[idx], self.tp[idx], self.errors[idx],
                            int(self.npos[frames].sum()))


def bucket_metrics(run: ModelRun, class_names: Sequence[str], frames: Sequence[int] | None = None
                   ) -> dict[str, float]:
    """mAP, NDS, the mTP errors and AP per bucket over the given frames (all when None)."""
    return RunMetrics(run, class_names)(frames)


# per frame, over matched cars: heading errors; for moving cars: velocity errors, speed ratios,
# GT speeds and the predicted velocity's component along the GT direction of travel
MotionFrame = tuple[list[float], list[float], list[float], list[float], list[float]]


def matched_cars(g: Detections, d: Detections, car: int, min_score: float = 0.3,
                 max_dist: float = 2.0) -> list[tuple[int, int]]:
    """``(detection, GT)`` index pairs of one frame's cars: detections scoring at least
    ``min_score``, surest first, each taking the nearest GT car not yet taken within
    ``max_dist`` m (BEV centre distance)."""
    pairs: list[tuple[int, int]] = []
    gm = np.nonzero(g.labels == car)[0]
    dm = np.nonzero((d.labels == car) & (d.scores >= min_score))[0]
    dm = dm[np.argsort(-d.scores[dm], kind='stable')]
    taken = np.zeros(len(gm), bool)
    for j in dm:
        if len(gm) == 0:
            break
        dist = np.hypot(g.boxes[gm, 0] - d.boxes[j, 0], g.boxes[gm, 1] - d.boxes[j, 1])
        dist[taken] = np.inf
        k = int(np.argmin(dist))
        if dist[k] >= max_dist:
            continue
        taken[k] = True
        pairs.append((int(j), int(gm[k])))
    return pairs


def car_motion_frame(g: Detections, d: Detections, car: int, min_score: float = 0.3,
                     max_dist: float = 2.0) -> MotionFrame:
    """One frame's matched cars (:func:`matched_cars`): heading errors, moving-car velocity
    errors, speed ratios, GT speeds and predicted along-track speeds."""
    head: list[float] = []
    vel_moving: list[float] = []
    speed: list[float] = []
    gt_speed: list[float] = []
    along: list[float] = []
    for j, gk in matched_cars(g, d, car, min_score, max_dist):
        err = (d.boxes[j, 6] - g.boxes[gk, 6] + np.pi) % (2 * np.pi) - np.pi
        head.append(float(abs(err)))
        v = g.velocities[gk]
        s = float(np.hypot(*v))
        if s > MOVING_SPEED:
            vel_moving.append(float(np.hypot(*(d.velocities[j] - v))))
            speed.append(float(np.hypot(*d.velocities[j])) / s)
            gt_speed.append(s)
            along.append(float(d.velocities[j] @ v) / s)
    return head, vel_moving, speed, gt_speed, along


def car_motion_summary(frames: Sequence[MotionFrame]) -> dict[str, float]:
    """Mean heading error, flipped share (> 135 deg), moving-car velocity error, median speed
    ratio, and how far predicted speed follows GT speed over moving cars: the least-squares
    slope of the predicted along-track speed on the GT speed (1: reads speed, 0: predicts one
    speed for all) and their correlation."""
    h = np.asarray([x for f in frames for x in f[0]])
    vel = [x for f in frames for x in f[1]]
    speed = [x for f in frames for x in f[2]]
    gs = np.asarray([x for f in frames for x in f[3]])
    al = np.asarray([x for f in frames for x in f[4]])
    slope = corr = float('nan')
    if len(gs) >= 2 and gs.std() > 0:
        slope = float(np.mean((gs - gs.mean()) * (al - al.mean())) / gs.var())
        corr = float(np.corrcoef(gs, al)[0, 1]) if al.std() > 0 else 0.0
    return {'car heading err': float(h.mean()) if len(h) else float('nan'),
            'car flipped %': float(100 * (h > 0.75 * np.pi).mean()) if len(h) else float('nan'),
            'moving car vel err': float(np.mean(vel)) if vel else float('nan'),
            'moving car speed ratio': float(np.median(speed)) if speed else float('nan'),
            'moving car speed slope': slope, 'moving car speed corr': corr}


def car_motion(gt: Sequence[Detections], det: Sequence[Detections], car: int,
               min_score: float = 0.3, max_dist: float = 2.0) -> dict[str, float]:
    """Car heading error over the full circle, flipped share (error > 135 deg), and velocity
    error of moving cars, on detections with score >= ``min_score`` matched greedily within
    ``max_dist`` m (BEV centre distance)."""
    return car_motion_summary([car_motion_frame(g, d, car, min_score, max_dist)
                               for g, d in zip(gt, det)])


def past_share(model: Any, sequences: Sequence[Sequence[Frame]], class_index: int = 0
               ) -> dict[str, float]:
    """How much the temporal path contributes: the norm of the fusion's past term relative to
    the current term ``W1 F_t`` at the head cells of GT object centres (class ``class_index``,
    with LiDAR returns), over frames that fused a memory."""
    from suit_ros.evaluate import step_inputs
    from suit_ros.model.streaming import StreamingDetector
    from suit_ros.model.sweeps import model_frame
    runner = StreamingDetector(model)
    runner.keep_terms = True
    grid = model.grid
    past_n, own_n = [], []
    for seq in sequences:
        runner.reset('new sequence')
        for t, f in enumerate(seq):
            runner.step(*step_inputs(f))
            terms = runner.last_terms
            if terms is None:
                continue
            own, past = terms
            if past is None:
                continue
            gt = model_frame(seq, t, 1).gt
            if gt is None or f.num_points is None:
                continue
            keep = (gt.labels == class_index) & (f.num_points > 0)
            for x, y in gt.boxes[keep, :2]:
                c, r = int((x - grid.point_range[0]) // grid.cell), \
                    int((y - grid.point_range[1]) // grid.cell)
                if 0 <= c < grid.W and 0 <= r < grid.H:
                    past_n.append(float(past[0, :, r, c].norm()))
                    own_n.append(float(own[0, :, r, c].norm()))
    if not own_n:
        return {'past share': float('nan'), 'cells': 0.0}
    return {'past share': float(np.mean(past_n)) / max(float(np.mean(own_n)), 1e-12),
            'cells': float(len(own_n))}


@dataclass
class Interval:
    """A point estimate with its bootstrap 95% interval; ``left_out``: resamples in which the
    metric is undefined (no GT of a class in them; for the car heading and velocity figures,
    no matched or moving car), which the interval leaves out."""

    value: float
    low: float
    high: float
    left_out: int = 0

    def fmt(self, digits: int = 3) -> str:
        """``value [low, high]``."""
        return f'{self.value:.{digits}f} [{self.low:.{digits}f}, {self.high:.{digits}f}]'


def left_out_counts(d: dict[str, dict[str, Interval]]) -> dict[str, dict[str, int]]:
    """``{run: {metric: resamples left out}}`` of the intervals that left any out while the
    metric is defined over all drives (one undefined there is n/a, not an interval)."""
    out = {r: {k: v.left_out for k, v in m.items() if v.left_out and np.isfinite(v.value)}
           for r, m in d.items()}
    return {r: m for r, m in out.items() if m}


def plain_intervals(d: dict[str, dict[str, Interval]]) -> dict[str, dict[str, list[float]]]:
    """``{run: {metric: Interval}}`` as JSON-ready ``{run: {metric: [value, low, high]}}``."""
    return {r: {k: [v.value, v.low, v.high] for k, v in m.items()} for r, m in d.items()}


def drive_frames(run: ModelRun) -> list[list[int]]:
    """Frame indices of each drive of a run."""
    drives: dict[int, list[int]] = {}
    for i, d in enumerate(run.drive):
        drives.setdefault(d, []).append(i)
    return [drives[k] for k in sorted(drives)]


def bootstrap(runs: dict[str, ModelRun], class_names: Sequence[str],
              pairs: Sequence[tuple[str, str]] = (), resamples: int = 200, seed: int = 0
              ) -> tuple[dict[str, dict[str, Interval]], dict[str, dict[str, Interval]]]:
    """Per-drive bootstrap of every metric of every run, and of paired differences ``a - b``.

    All runs must cover the same drives in the same order.
    :return: ``{run: {metric: Interval}}`` and ``{'a - b': {metric: Interval}}``.
    """
    names = list(runs)
    drives = drive_frames(runs[names[0]])
    for n in names[1:]:
        if runs[n].drive != runs[names[0]].drive:
            raise ValueError(f'bootstrap: run {n!r} covers other drives or frames than '
                             f'{names[0]!r}: pairs and resamples need the same frames')
    metrics = {n: RunMetrics(runs[n], class_names) for n in names}
    point = {n: metrics[n]() for n in names}
    required = {n: metrics[n].present() for n in names}   # (a variant may hold other GT)
    rng = np.random.default_rng(seed)
    samples: dict[str, list[dict[str, float]]] = {n: [] for n in names}
    for _ in range(resamples):
        pick = rng.integers(0, len(drives), len(drives))
        frames = [i for k in pick for i in drives[k]]
        for n in names:
            samples[n].append(metrics[n](frames, required[n]))

    def interval(values: list[float], value: float) -> Interval:
        v = np.asarray(values, np.float64)
        v = v[np.isfinite(v)]
        left = len(values) - len(v)
        if len(v) == 0:
            return Interval(value, float('nan'), float('nan'), left)
        return Interval(value, float(np.percentile(v, 2.5)), float(np.percentile(v, 97.5)),
                        left)

    out = {n: {k: interval([s[k] for s in samples[n]], point[n][k]) for k in point[n]}
           for n in names}
    diffs = {f'{a} - {b}': {k: interval([sa[k] - sb[k] for sa, sb in
                                         zip(samples[a], samples[b])],
                                        point[a][k] - point[b][k]) for k in point[a]}
             for a, b in pairs}
    return out, diffs
