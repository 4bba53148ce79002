"""``suit-ros outage``: what the node sees of objects whose returns vanish (the memory's job).

A fixed set of synthetic drives (the ``outage`` split of :mod:`suit_ros.data.sequences`,
seeds 8500+, never trained, tuned or validated on) is played with a sector of every sweep
lost for a run of frames, as when a truck passes between the car and its surroundings, a
sensor is blocked, or a driver drops packets: the returns of that azimuth sector (about the
sensor) are removed from the sensor sweeps before the multi-sweep accumulation, so the
earlier sweeps still hold what they saw, and the GT objects stay (they are still there).
Each model runs as the node does (published thresholds; with or without the tracker), and
per outage frame 1..N the report gives:

- **recall** of the GT objects in the lost sector that had returns before the outage (same
  class, BEV centre within 2 m), with a per-drive bootstrap interval;
- **sector precision**: the share of published boxes in the lost sector that match an object
  (boxes kept for objects that left or were never there are ghosts).

Frames 1-2 are carried by the previous sweeps in the input (3 sweeps); from frame 3 on only a
memory can hold an object.

A lost object is one in the sector that had returns before the outage and has none now (one
across the sector's edge that is still seen is not counted).

On the drives as the sensor saw them (natural occlusion: objects behind others), recall
through **occlusion events** (an object hidden 0.3-1.0 s between frames where it has returns:
:func:`occlusion_events`) by frame of the event, and the **occlusion mAP**: mAP over the
frames with an object inside an event, whose GT keeps those objects (they are still there;
:func:`occlusion_run`); each model also runs with its memory dropped before every frame, and
the paired difference is what the memory is worth there. The first model's recall minus each
other's (outage and occlusion) comes with a paired per-drive interval.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from suit_ros.data.sequences import seen_ids
from suit_ros.evaluate import ModelRun, match_boxes
from suit_ros.structures import Detections, Frame
from suit_ros.tracking import TrackerConfig

MATCH_DIST = 2.0


@dataclass(frozen=True)
class Outage:
    """A sector of ``width_deg`` centred at ``centre_deg`` (sensor azimuth) lost for frames
    ``first .. first + frames - 1`` of a drive."""

    centre_deg: float
    width_deg: float
    first: int
    frames: int

    def active(self, k: int) -> int:
        """1-based frame of the outage at drive frame ``k`` (0: not in the outage)."""
        return k - self.first + 1 if self.first <= k < self.first + self.frames else 0

    def contains(self, xy: NDArray[np.floating[Any]]) -> NDArray[np.bool_]:
        """Whether sensor-frame points lie in the sector."""
        az = np.degrees(np.arctan2(xy[:, 1], xy[:, 0]))
        off = (az - self.centre_deg + 180.0) % 360.0 - 180.0
        return np.asarray(np.abs(off) <= self.width_deg / 2)


def outages_for(drive: int, frames: int, width_deg: float = 120.0, length: int = 6,
                period: int = 14, seed: int = 0) -> list[Outage]:
    """Outages of one drive: every ``period`` frames from frame 6, a random sector each."""
    rng = np.random.default_rng([seed, drive])
    return [Outage(float(rng.uniform(-180, 180)), width_deg, first, length)
            for first in range(6, frames - length + 1, period)]


def with_outages(seq: Sequence[Frame], outages: Sequence[Outage]) -> list[Frame]:
    """The drive with the outages' sectors removed from its sweeps (GT kept); each object's
    returns counted again as the world counts them (:func:`~suit_ros.structures.
    object_returns`: with the returns' owners where the frame has them)."""
    from suit_ros.structures import object_returns
    out = []
    for k, f in enumerate(seq):
        lost = [o for o in outages if o.active(k)]
        if not lost:
            out.append(f)
            continue
        keep = np.ones(len(f.points), bool)
        for o in lost:
            keep &= ~o.contains(f.points[:, :2])
        pts = f.points[keep]
        owners = None if f.owners is None else f.owners[keep]
        num = (object_returns(pts, f.gt.boxes, owners, f.instance_ids) if f.gt is not None
               else f.num_points)
        out.append(replace(f, points=pts, num_points=num, owners=owners,
                           times=None if f.times is None else f.times[keep]))
    return out


@dataclass
class OutageCounts:
    """Per drive and outage frame: objects to find, found; published boxes in the sector,
    matched."""

    objects: NDArray[np.int64]      # (drives, length)
    found: NDArray[np.int64]
    boxes: NDArray[np.int64]
    true: NDArray[np.int64]

    def recall(self, pick: NDArray[np.int64] | None = None) -> NDArray[np.float64]:
        """Recall per outage frame over the picked drives (all by default)."""
        p = np.arange(len(self.objects)) if pick is None else pick
        return np.asarray(self.found[p].sum(0) / np.maximum(self.objects[p].sum(0), 1))

    def precision(self, pick: NDArray[np.int64] | None = None) -> NDArray[np.float64]:
        """Sector precision per outage frame over the picked drives."""
        p = np.arange(len(self.boxes)) if pick is None else pick
        b = self.boxes[p].sum(0)
        return np.asarray(np.where(b > 0, self.true[p].sum(0) / np.maximum(b, 1), np.nan))

    def to_json(self) -> dict[str, list[list[int]]]:
        """The counts as lists (``suit-ros outage --json-out`` keeps them, so that two runs
        over the same drives can be paired later: :meth:`from_json`)."""
        return {k: getattr(self, k).tolist() for k in ('objects', 'found', 'boxes', 'true')}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> OutageCounts:
        """Counts written by :meth:`to_json`."""
        return cls(*(np.asarray(data[k], np.int64).reshape(len(data[k]), -1) if len(data[k])
                     else np.zeros((0, 0), np.int64)
                     for k in ('objects', 'found', 'boxes', 'true')))


def count_outage(gt_seqs: Sequence[Sequence[Frame]], det_seqs: Sequence[Sequence[Detections]],
                 outages: Sequence[Sequence[Outage]], thresholds: Sequence[float],
                 length: int) -> OutageCounts:
    """Count recall and sector precision per drive and outage frame.

    :param gt_seqs: the drives as played (outage sweeps, GT kept); ``det_seqs`` their
        detections (sensor frame) at the decoding threshold; ``thresholds`` the published ones
        (zeros for detections already cut at them).
    """
    n = len(gt_seqs)
    objects, found = np.zeros((n, length), np.int64), np.zeros((n, length), np.int64)
    boxes, true = np.zeros((n, length), np.int64), np.zeros((n, length), np.int64)
    thr = np.asarray(thresholds, np.float64)
    for d, (frames, dets, outs) in enumerate(zip(gt_seqs, det_seqs, outages)):
        for o in outs:
            seen_before = seen_ids(frames[o.first - 1])
            for j in range(o.frames):
                f, det = frames[o.first + j], dets[o.first + j]
                if f.gt is None or f.instance_ids is None:
                    continue
                in_sector = o.contains(f.gt.boxes[:, :2]) & np.isin(
                    f.instance_ids, list(seen_before))
                in_sector &= np.hypot(f.gt.boxes[:, 0], f.gt.boxes[:, 1]) <= 50.0
                if f.num_points is not None:    # lost: no returns left (one across the
                    in_sector &= f.num_points == 0   # sector's edge is still seen)
                pub = det.select(det.scores >= thr[det.labels]) if len(det) else det
                pub_in = o.contains(pub.boxes[:, :2]) if len(pub) else np.zeros(0, bool)
                objects[d, j] += int(in_sector.sum())
                boxes[d, j] += int(pub_in.sum())
                # matched against every object: a visible neighbour's box finds no lost one
                taken, gt_hit = match_boxes(f.gt, pub, MATCH_DIST)
                found[d, j] += int((gt_hit & in_sector).sum())
                true[d, j] += int(((taken >= 0) & pub_in).sum())
    return OutageCounts(objects, found, boxes, true)


def frames_since_seen(frames: Sequence[Frame]
                      ) -> Iterator[tuple[Frame, NDArray[np.int64] | None]]:
    """Each frame of a drive with, per GT object, the frames since it last had returns (0:
    it has returns now, or it never had); None for a frame without GT ids and point counts."""
    last_seen: dict[int, int] = {}
    for k, f in enumerate(frames):
        if f.gt is None or f.instance_ids is None or f.num_points is None:
            yield f, None
            continue
        ids, counts = f.instance_ids.tolist(), f.num_points.tolist()
        yield f, np.array([k - last_seen[i] if c == 0 and i in last_seen else 0
                           for i, c in zip(ids, counts)], np.int64)
        last_seen.update({i: k for i, c in zip(ids, counts) if c > 0})


EVENT_S = (0.3, 1.0)            # the occlusion events scored: hidden for 0.3 to 1.0 s


def occlusion_events(frames: Sequence[Frame], min_s: float = EVENT_S[0],
                     max_s: float = EVENT_S[1]) -> list[NDArray[np.int64] | None]:
    """Per frame of a drive, per GT object, its frame within an occlusion event (1-based; 0:
    in none); None for a frame without GT ids and point counts.

    An event is a run of frames in which an object, labelled in each, has no returns, between
    a frame where it had returns and one where it has them again, lasting ``min_s`` to
    ``max_s`` (from its first frame without returns to its first frame with them again: 3 to
    10 frames at 10 Hz). An object that never comes back, or leaves the labels, makes no
    event: nothing could tell a memory that holds it from one that keeps ghosts.
    """
    out: list[NDArray[np.int64] | None] = []
    seen: dict[int, list[tuple[int, int, bool]]] = {}     # id -> (frame, row, has returns)
    for k, f in enumerate(frames):
        if f.gt is None or f.instance_ids is None or f.num_points is None:
            out.append(None)
            continue
        out.append(np.zeros(len(f.gt), np.int64))
        for row, (i, c) in enumerate(zip(f.instance_ids.tolist(), f.num_points.tolist())):
            seen.setdefault(int(i), []).append((k, row, c > 0))
    tol = 1_000_000                                    # 1 ms of stamp jitter
    lo, hi = int(min_s * 1e9) - tol, int(max_s * 1e9) + tol
    for track in seen.values():
        n = 0
        while n < len(track):
            k, _, visible = track[n]
            if visible or n == 0 or not track[n - 1][2] or track[n - 1][0] != k - 1:
                n += 1
                continue
            m = n                    # hidden from track[n]; it had returns the frame before
            while m + 1 < len(track) and track[m + 1][0] == track[m][0] + 1 \
                    and not track[m + 1][2]:
                m += 1
            back = m + 1
            if back < len(track) and track[back][0] == track[m][0] + 1:   # seen again
                duration = frames[track[back][0]].stamp_ns - frames[k].stamp_ns
                if lo <= duration <= hi:
                    for pos, (kk, row, _) in enumerate(track[n:back], start=1):
                        events = out[kk]
                        assert events is not None
                        events[row] = pos
            n = back
    return out


def count_events(gt_seqs: Sequence[Sequence[Frame]], det_seqs: Sequence[Sequence[Detections]],
                 thresholds: Sequence[float], max_len: int = 10) -> OutageCounts:
    """Recall of objects through their occlusion events (:func:`occlusion_events`), by frame of
    the event (1..``max_len``): an object counts at each frame of its event within 50 m;
    found: matched by a published box of its class within 2 m. The boxes columns stay 0."""
    return _count_by_column(gt_seqs, det_seqs, thresholds, max_len, occlusion_events)


def _count_by_column(gt_seqs: Sequence[Sequence[Frame]],
                     det_seqs: Sequence[Sequence[Detections]], thresholds: Sequence[float],
                     width: int,
                     columns: Callable[[Sequence[Frame]], list[NDArray[np.int64] | None]]
                     ) -> OutageCounts:
    """Objects and found per drive and column: ``columns(frames)`` gives, per frame, each GT
    object's column (1..``width``; 0: not counted); an object counts within 50 m, found when
    a published box of its class lies within 2 m."""
    n = len(gt_seqs)
    objects = np.zeros((n, width), np.int64)
    found = np.zeros((n, width), np.int64)
    thr = np.asarray(thresholds, np.float64)
    for d, (frames, dets) in enumerate(zip(gt_seqs, det_seqs)):
        for f, col, det in zip(frames, columns(frames), dets):
            if col is None or f.gt is None:
                continue
            near = np.hypot(f.gt.boxes[:, 0], f.gt.boxes[:, 1]) <= 50.0
            pub = det.select(det.scores >= thr[det.labels]) if len(det) else det
            _, gt_hit = match_boxes(f.gt, pub, MATCH_DIST)
            for c in np.unique(col[near & (col > 0) & (col <= width)]):
                objects[d, c - 1] += int((near & (col == c)).sum())
                found[d, c - 1] += int((near & (col == c) & gt_hit).sum())
    zeros = np.zeros_like(objects)
    return OutageCounts(objects, found, zeros, zeros.copy())


def recall_difference(a: OutageCounts, b: OutageCounts, resamples: int = 200, seed: int = 0
                      ) -> dict[str, list[float]]:
    """Recall of ``a`` minus ``b`` (two models on the same drives), over every counted frame
    and from frame 3 on, ``[value, low, high]`` with a paired per-drive bootstrap: each
    resample draws the same drives for both."""
    if a.objects.shape != b.objects.shape or not np.array_equal(a.objects, b.objects):
        raise ValueError('recall_difference: the counts are not over the same objects')

    def recall(c: OutageCounts, pick: NDArray[np.int64], first: int) -> float:
        return float(c.found[pick, first:].sum() / max(c.objects[pick, first:].sum(), 1))
    rng = np.random.default_rng(seed)
    n = len(a.objects)
    every = np.arange(n)
    picks = [rng.integers(0, n, n) for _ in range(resamples)]
    out = {}
    for key, first in (('recall', 0), ('recall_from_frame_3', 2)):
        out[key] = _interval(recall(a, every, first) - recall(b, every, first),
                             [recall(a, p, first) - recall(b, p, first) for p in picks])
    return out


def count_occlusion(gt_seqs: Sequence[Sequence[Frame]],
                    det_seqs: Sequence[Sequence[Detections]], thresholds: Sequence[float],
                    max_gap: int = 10) -> OutageCounts:
    """Recall of objects by frames since they were last visible (1..``max_gap``), on drives
    as the sensor saw them (occlusion by other objects, no sector removed).

    An object counts at a frame when it has no returns in it and had returns ``g`` frames
    before (``g <= max_gap``), within 50 m; found: matched by a published box of its class
    within 2 m. Column ``g - 1`` of the counts is gap ``g`` (the boxes columns stay 0).
    """
    return _count_by_column(gt_seqs, det_seqs, thresholds, max_gap,
                            lambda frames: [gap for _, gap in frames_since_seen(frames)])


def occlusion_run(run: ModelRun, drives: Sequence[Sequence[Frame]]) -> ModelRun:
    """``run`` (over ``drives``, in order) on its occlusion frames: the frames with an object
    within 50 m inside an occlusion event (:func:`occlusion_events`); their GT is every object
    with returns plus those occluded ones (still there); another object without returns (one
    that never comes back, or hidden longer) is ignored, as are the frame's own ignore boxes
    (a detection on them is neither true nor false)."""
    keep_frames: list[int] = []
    gt: list[Detections] = []
    ignore: list[NDArray[np.float32] | None] = []
    num: list[Any] = []
    i = 0
    for frames in drives:
        for f, pos in zip(frames, occlusion_events(frames)):
            if pos is None or f.gt is None or f.num_points is None:
                raise ValueError('occlusion_run needs GT with instance ids and point counts')
            near = np.hypot(f.gt.boxes[:, 0], f.gt.boxes[:, 1]) <= 50.0
            occluded = pos > 0
            if (occluded & near).any():
                kept = (f.num_points > 0) | occluded
                keep_frames.append(i)
                gt.append(f.gt.select(kept))
                own = np.zeros((0, 7), np.float32) if f.ignore_boxes is None else \
                    np.asarray(f.ignore_boxes, np.float32).reshape(-1, 7)
                ignore.append(np.concatenate([own, f.gt.boxes[~kept].astype(np.float32)]))
                num.append(np.maximum(f.num_points[kept], 1))
            i += 1
    if i != len(run.det):
        raise ValueError(f'the run has {len(run.det)} frames, the drives {i}')
    return replace(run.select_frames(keep_frames), gt=gt, num_points=num, ignore=ignore)


def occlusion_ap(model: Any, drives: Sequence[Sequence[Frame]], plain: ModelRun,
                 class_names: Sequence[str], deskew: bool = True) -> dict[str, list[float]]:
    """Occlusion mAP ``[value, low, high]`` of a model's run, of the same model with its
    memory dropped, and their paired difference (per-drive bootstrap)."""
    from suit_ros.accuracy import bootstrap
    from suit_ros.evaluate import run_model
    runs = {'model': occlusion_run(plain, drives)}
    if not runs['model'].det:               # no occlusion event on these drives: nothing scored
        nan = [float('nan')] * 3
        return {'model': nan} if model.cfg.temporal == 'none' else \
            {'model': nan, 'memory dropped': nan, 'difference': nan}
    if model.cfg.temporal != 'none':
        runs['memory dropped'] = occlusion_run(
            run_model(model, drives, drop_memory=True, deskew=deskew), drives)
    out, diffs = bootstrap(runs, class_names,
                           [('model', 'memory dropped')] if len(runs) > 1 else [])
    def listed(i: Any) -> list[float]:
        return [round(i.value, 3), round(i.low, 3), round(i.high, 3)]
    result = {k: listed(v['mAP']) for k, v in out.items()}
    for v in diffs.values():
        result['difference'] = listed(v['mAP'])
    return result


def intervals(counts: OutageCounts, resamples: int = 200, seed: int = 0
              ) -> dict[str, list[list[float]]]:
    """Per outage frame ``[value, low, high]`` of recall and sector precision (per-drive
    bootstrap), and of both over frames 3.. (the memory's part)."""
    rng = np.random.default_rng(seed)
    n = len(counts.objects)
    rec, prec, late, late_prec = [], [], [], []

    def late_precision(pick: NDArray[np.int64]) -> float:
        boxes = counts.boxes[pick, 2:].sum()
        return float(counts.true[pick, 2:].sum() / boxes) if boxes else float('nan')
    for _ in range(resamples):
        pick = rng.integers(0, n, n)
        rec.append(counts.recall(pick))
        prec.append(counts.precision(pick))
        late.append(counts.found[pick, 2:].sum() / max(counts.objects[pick, 2:].sum(), 1))
        late_prec.append(late_precision(pick))

    def band(samples: list[NDArray[np.float64]], value: NDArray[np.float64]
             ) -> list[list[float]]:
        s = np.asarray(samples)
        out = []
        for i, v in enumerate(value):
            col = s[:, i][np.isfinite(s[:, i])]
            lo, hi = ((float(np.percentile(col, 2.5)), float(np.percentile(col, 97.5)))
                      if len(col) else (float('nan'), float('nan')))
            out.append([round(float(v), 3), round(lo, 3), round(hi, 3)])
        return out
    late_value = counts.found[:, 2:].sum() / max(counts.objects[:, 2:].sum(), 1)
    return {'recall': band(rec, counts.recall()), 'sector_precision': band(prec,
                                                                            counts.precision()),
            'recall_from_frame_3': _interval(late_value, late),
            'sector_precision_from_frame_3': _interval(late_precision(np.arange(n)), late_prec),
            'objects': counts.objects.sum(0).tolist(), 'boxes': counts.boxes.sum(0).tolist()}


def _interval(value: float, samples: Sequence[float]) -> list[float]:
    """``[value, 2.5th, 97.5th percentile of the bootstrap samples]``, rounded."""
    finite = np.asarray(samples, np.float64)
    finite = finite[np.isfinite(finite)]
    if not len(finite):
        return [round(float(value), 3), float('nan'), float('nan')]
    return [round(float(value), 3), round(float(np.percentile(finite, 2.5)), 3),
            round(float(np.percentile(finite, 97.5)), 3)]


# ------------------------------------------------------------------ command line
def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add ``outage`` options."""
    parser.add_argument('--checkpoint', action='append', metavar='NAME=PATH',
                        help='a model to measure (repeatable; default: the three shipped ones, '
                             "the node's default suit_carry as 'SUIT carry')")
    parser.add_argument('--drives', type=int, default=16)
    parser.add_argument('--frames', type=int, default=40)
    parser.add_argument('--width', type=float, default=120.0, help='sector (degrees)')
    parser.add_argument('--length', type=int, default=6, help='outage frames')
    parser.add_argument('--deskew', choices=['on', 'off'], default='on',
                        help="the sweeps of sensors that take them over time put back at "
                        "their stamps, as the node's `deskew` does")
    parser.add_argument('--cache-dir', default='data_cache')
    parser.add_argument('--occlusion', choices=['both', 'natural', 'passing', 'none'],
                        default='both',
                        help='occlusion events scored on the drives as the sensor saw them '
                        '(natural), with passing occluders hiding well-seen objects (passing), '
                        'both, or none')
    parser.add_argument('--no-occlusion', dest='occlusion', action='store_const', const='none',
                        help='the same as --occlusion none')
    parser.add_argument('--coast-s', type=float, default=None, metavar='S',
                        help="the tracker's coast_s, seconds (default: the node's)")
    parser.add_argument('--json-out', help='write the figures as JSON here')
    parser.add_argument('--markdown', help='write the tables (markdown) here')


def run(args: argparse.Namespace) -> int:
    """Run every model with and without the tracker; print and write the table."""
    from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint, published_thresholds
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.outputs import json_text, output_file
    for option, path in (('--json-out', args.json_out), ('--markdown', args.markdown)):
        if path:                    # checked before the runs, not after them
            output_file(path, f'{option} file')
    shipped = default_checkpoint_path().parent
    # the labels docs/outage/README.md's tables (and scripts/model_card.py) read
    models = dict(a.split('=', 1) for a in args.checkpoint) if args.checkpoint else {
        'SUIT carry': str(shipped / 'suit_carry.safetensors'),
        'SUIT': str(shipped / 'suit_default.safetensors'),
        'single frame': str(shipped / 'centerpoint_single.safetensors')}
    plain = synthetic_split('outage', args.drives, args.frames, args.cache_dir)
    outs = [outages_for(i, args.frames, args.width, args.length) for i in range(len(plain))]
    seqs = [with_outages(seq, o) for seq, o in zip(plain, outs)]
    # the drives as the sensor saw them ('occlusion': their own events, few and mostly far
    # objects flickering) and with passing occluders ('passing': data/occluders.py)
    occlusion_sets: dict[str, list[list[Frame]]] = {}
    if args.occlusion in ('natural', 'both'):
        occlusion_sets['occlusion'] = plain
    if args.occlusion in ('passing', 'both'):
        from suit_ros.data.occluders import passing_drives
        occlusion_sets['passing'] = passing_drives(plain)
    result: dict[str, Any] = {'drives': args.drives, 'frames': args.frames,
                              'width_deg': args.width, 'length': args.length, 'runs': {},
                              'deskew': args.deskew, 'outage_difference': {}}
    for what in ('occlusion', 'passing'):
        result.update({what: {}, f'{what}_ap': {}, f'{what}_difference': {}})
    counted: dict[str, dict[str, OutageCounts]] = {
        'outage': {}, **{what: {} for what in occlusion_sets}}
    tracker = TrackerConfig()
    if args.coast_s is not None:
        try:
            tracker = TrackerConfig(coast_s=args.coast_s)
        except ValueError as exc:
            raise SystemExit(f'suit-ros outage: --coast-s: {exc}') from None
    for name, path in models.items():
        model, cfg, meta = load_checkpoint(path)
        thr = published_thresholds(meta, cfg.class_names)
        carry = published_thresholds(meta, cfg.class_names, carried=True)
        zero = [0.0] * len(thr)     # (for detections already cut at the published thresholds)
        for tracked in (False, True):
            key = f'{name}, tracker' if tracked else name
            runs = _run(model, seqs, tracker if tracked else None, args.deskew == 'on')
            counts = count_outage(seqs, published_by_drive(runs, thr, carry), outs, zero,
                                  args.length)
            counted['outage'][key] = counts
            result['runs'][key] = r = intervals(counts)
            print(f'{key:<24} recall by outage frame ' + ' '.join(_num(v[0]) for v in
                                                                   r['recall'])
                  + f' | frames 3+: {_band(r["recall_from_frame_3"])} | sector precision '
                  + ' '.join(_num(v[0]) for v in r['sector_precision']), flush=True)
            for what, drives in occlusion_sets.items():
                run_ = _run(model, drives, tracker if tracked else None, args.deskew == 'on')
                occ = count_events(drives, published_by_drive(run_, thr, carry), zero)
                counted[what][key] = occ
                result[what][key] = o = intervals(occ)
                print(f'{key:<24} {what} events, recall by frame of the event '
                      + ' '.join(_num(v[0]) for v in o['recall'])
                      + f' | frames 3+: {_band(o["recall_from_frame_3"])}', flush=True)
                if not tracked:
                    result[f'{what}_ap'][name] = a = occlusion_ap(
                        model, drives, run_, cfg.class_names, args.deskew == 'on')
                    print(f'{name:<24} {what} mAP {_band(a["model"])}'
                          + (f' | memory dropped {_band(a["memory dropped"])} | difference '
                             f'{_band(a["difference"])}' if 'difference' in a else ''),
                          flush=True)
    names = list(models)
    for what, counts_by in counted.items():      # paired: the first model against the others
        for other in names[1:]:
            for suffix in ('', ', tracker'):
                a, b = names[0] + suffix, other + suffix
                if a in counts_by and b in counts_by:
                    d = recall_difference(counts_by[a], counts_by[b])
                    result[f'{what}_difference'][f'{a} - {b}'] = d
                    print(f'{what}: {a} - {b}: recall {_band(d["recall"])}, frames 3+ '
                          f'{_band(d["recall_from_frame_3"])}', flush=True)
    result['counts'] = {what: {key: c.to_json() for key, c in counts_by.items()}
                        for what, counts_by in counted.items()}
    if args.json_out:
        Path(args.json_out).write_text(json_text(result), encoding='utf-8')
    if args.markdown:
        Path(args.markdown).write_text(tables(result), encoding='utf-8')
    return 0


def tables(result: dict[str, Any]) -> str:
    """The figures of :func:`run` as markdown tables (value [95% per-drive interval])."""
    n = result['length']
    runs = result['runs']
    lines = [f'Outage: a {result["width_deg"]:.0f}-degree sector lost for {n} frames '
             f'({result["drives"]} drives x {result["frames"]} frames). Recall of the objects '
             'in the lost sector that had returns before the outage:', '',
             '| model | ' + ' | '.join(f'frame {k}' for k in range(1, n + 1))
             + ' | frames 3+ | objects at frame 1 |', '|---' * (n + 3) + '|']
    for key, r in runs.items():
        lines.append(f'| {key} | ' + ' | '.join(_band(v) for v in r['recall'])
                     + f' | {_band(r["recall_from_frame_3"])} | {r["objects"][0]} |')
    lines += ['', 'Sector precision (published boxes in the lost sector that match an object), '
              'per outage frame, and the boxes counted:', '',
              '| model | ' + ' | '.join(f'frame {k}' for k in range(1, n + 1))
              + ' | frames 3+ | boxes |', '|---' * (n + 3) + '|']
    for key, r in runs.items():
        late = r.get('sector_precision_from_frame_3')
        lines.append(f'| {key} | ' + ' | '.join(_num(v[0]) for v in r['sector_precision'])
                     + f' | {_band(late) if late else ""} | {sum(r["boxes"])} |')
    lines += _difference_table(result.get('outage_difference') or {},
                               'Paired differences (the same drives and resamples), outage '
                               'recall:')
    lines += _occlusion_tables(
        result, 'occlusion', 'Natural occlusion (the same drives as the sensor saw them): '
        f'occlusion events, objects hidden {EVENT_S[0]:g}-{EVENT_S[1]:g} s between frames with '
        'returns (3-10 frames at 10 Hz); recall by frame of the event:')
    lines += _occlusion_tables(
        result, 'passing', 'Passing occluders (the same drives, in every 10 frames up to two '
        'objects with 10 or more returns 6-40 m away hidden 0.3-0.7 s by something truck-high '
        'crossing their line of sight: suit_ros/data/occluders.py): occlusion events as above, '
        'recall by frame of the event:')
    return '\n'.join(lines) + '\n'


def _occlusion_tables(result: dict[str, Any], what: str, title: str) -> list[str]:
    """The recall, paired-difference and mAP tables of one occlusion set (``what``)."""
    occ = result.get(what) or {}
    lines: list[str] = []
    if occ:
        gaps = len(next(iter(occ.values()))['recall'])
        lines += ['', title, '', '| model | ' + ' | '.join(str(g) for g in range(1, gaps + 1))
                  + ' | frames 3+ |', '|---' * (gaps + 2) + '|']
        for key, r in occ.items():
            lines.append(f'| {key} | ' + ' | '.join(_num(v[0]) for v in r['recall'])
                         + f' | {_band(r["recall_from_frame_3"])} |')
        lines.append('| objects | ' + ' | '.join(str(c) for c in
                                                   next(iter(occ.values()))['objects'])
                     + ' | |')
    lines += _difference_table(result.get(f'{what}_difference') or {},
                               'Paired differences, recall through these occlusion events:')
    occ_ap = result.get(f'{what}_ap') or {}
    if occ_ap:
        lines += ['', 'mAP over these occlusion frames (the frames with an object inside an '
                  'occlusion event, its GT kept), with the memory dropped before every frame, '
                  'and the paired difference (what the memory is worth):',
                  '', '| model | mAP | memory dropped | difference |', '|---|---|---|---|']
        for key, a in occ_ap.items():
            lines.append(f'| {key} | {_band(a["model"])} | '
                         + (f'{_band(a["memory dropped"])} | {_band(a["difference"])} |'
                            if 'difference' in a else '| |'))
    return lines


def _difference_table(diffs: dict[str, dict[str, list[float]]], title: str) -> list[str]:
    if not diffs:
        return []
    lines = ['', title, '', '| models | every frame | frames 3+ |', '|---|---|---|']
    for pair, d in diffs.items():
        lines.append(f'| {pair} | {_band(d["recall"], True)} | '
                     f'{_band(d["recall_from_frame_3"], True)} |')
    return lines


def _num(x: float | None, signed: bool = False) -> str:
    """A figure of the tables: nan for an undefined one (null in the JSON, nan in memory)."""
    if x is None or not np.isfinite(x):
        return 'nan'
    return f'{x:+.2f}' if signed else f'{x:.2f}'


def _band(v: Any, signed: bool = False) -> str:
    return f'{_num(v[0], signed)} [{_num(v[1], signed)}, {_num(v[2], signed)}]'


def _run(model: Any, seqs: Sequence[Sequence[Frame]], tracker: TrackerConfig | None,
         deskew: bool = True) -> ModelRun:
    """The drives as the node decodes them (with its tracker, or without: None; deskewed as
    the node does, or as taken)."""
    from suit_ros.evaluate import run_model
    return run_model(model, seqs, tracker=tracker, deskew=deskew)


def published_by_drive(run: ModelRun, thresholds: Sequence[float],
                       carry_thresholds: Sequence[float]) -> list[list[Detections]]:
    """Each drive's published detections (:meth:`ModelRun.published`)."""
    from suit_ros.accuracy import drive_frames
    det = run.published(thresholds, carry_thresholds)
    return [[det[i] for i in frames] for frames in drive_frames(run)]
