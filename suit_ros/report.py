"""``suit-ros report``: what a user of the node sees on a labelled dataset.

Runs a checkpoint as the node runs it by default (the streaming detector with the tracker,
boxes published at the checkpoint's published thresholds) over any supported dataset folder
(Argoverse 2, KITTI, nuScenes-format, a synthetic split) and writes:

- ``report.json`` and ``report.md``: per class recall and precision at the published thresholds
  and over a sweep of thresholds, false positives per frame, nuScenes-style AP within
  ``--max-range`` (50 m), car heading error and flip rate, car placement (median range offset
  from the ego and length error of the matched cars), every missed object with what the
  model made of it (the best score of its class there, the strongest box of another class)
  and what the sensor saw of it (its returns' extent along and across its box, their heights),
  and every false positive with its box, the nearest labelled object and what is in it;
- ``bev/<sequence>_<frame>.png``: a bird's-eye view per frame, points with GT, true positives,
  false positives, missed objects and ignored things in different colours.

Matching: same class, greedy by descending score, BEV centre distance below ``--match-dist``
(2 m), GT with at least one return within ``--max-range``; detections on ignored things (parked
bicycles and motorcycles on AV2) count as neither true nor false positives
(:func:`suit_ros.evaluate.drop_ignored`), and in the counts (not in AP, as nuScenes) neither do
boxes on labelled objects without returns in the sweep (:func:`on_seen`).
"""
from __future__ import annotations

import argparse
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
import sys
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import NDArray

from suit_ros.box_fit import BOX_FIT_MODES
from suit_ros.errors import ConfigError, DatasetError
from suit_ros.ground import GROUND_MODES
from suit_ros.overhang import OVERHANG_MODES
from suit_ros.place_bootstrap import CELL, APIntervals
from suit_ros.structures import Detections

if TYPE_CHECKING:
    from suit_ros.params import TrafficSide, TrafficSideParam

SWEEP = tuple(round(0.1 + 0.05 * i, 2) for i in range(18))     # 0.10 .. 0.95
FLIP_RAD = np.deg2rad(135.0)


@dataclass
class ClassCounts:
    """Matched detections of one class over a run, at every threshold (matched once)."""

    scores: NDArray[np.float64]          # (n,) every detection of the class
    tp: NDArray[np.bool_]                # (n,)
    heading_err: NDArray[np.float64]     # (n,) nan where not a TP
    npos: int
    frames: int
    placement: NDArray[np.float64]       # (n, 2) range offset (+: too far), length error

    def at(self, threshold: float) -> dict[str, Any]:
        """Recall, precision, F1, counts and false positives per frame at a threshold."""
        keep = self.scores >= threshold
        tp = int((self.tp & keep).sum())
        fp = int(keep.sum()) - tp
        recall = tp / self.npos if self.npos else float('nan')
        precision = tp / (tp + fp) if tp + fp else float('nan')
        f1 = (2 * recall * precision / (recall + precision)
              if tp and np.isfinite(recall) else 0.0)
        return {'threshold': threshold, 'tp': tp, 'fp': fp, 'gt': self.npos,
                'recall': _r(recall), 'precision': _r(precision), 'f1': _r(f1),
                'fp_per_frame': _r(fp / max(self.frames, 1))}

    def heading(self, threshold: float) -> dict[str, Any]:
        """Heading error of the true positives at a threshold: mean, median, flips."""
        err = self.heading_err[self.tp & (self.scores >= threshold)]
        return {'matched': int(len(err)),
                'mean_deg': _r(float(np.degrees(err.mean()))) if len(err) else None,
                'median_deg': _r(float(np.degrees(np.median(err)))) if len(err) else None,
                'flipped': int((err > FLIP_RAD).sum()),
                'flip_rate': _r(float((err > FLIP_RAD).mean())) if len(err) else None}

    def placement_at(self, threshold: float) -> dict[str, Any]:
        """Where the true positives at a threshold sit against their GT: median range offset
        (+: farther from the ego than the GT) and median length error, in metres."""
        p = self.placement[self.tp & (self.scores >= threshold)]
        return {'matched': int(len(p)),
                'range_offset_m': _r(float(np.median(p[:, 0]))) if len(p) else None,
                'length_error_m': _r(float(np.median(p[:, 1]))) if len(p) else None}


def _f(x: float | None, digits: int = 3) -> str:
    """A table cell: n/a for an undefined ratio (no GT, or nothing published)."""
    return 'n/a' if x is None or not np.isfinite(x) else f'{x:.{digits}f}'


def _finite(x: float | None) -> bool:
    return x is not None and bool(np.isfinite(x))


def _r(x: float) -> float:
    return round(float(x), 4) if np.isfinite(x) else float('nan')


def count_matches(gt: Sequence[Detections], det: Sequence[Detections], label: int,
                  match_dist: float) -> ClassCounts:
    """Match every frame once (greedy by score: a detection's match depends only on the
    higher-scored ones, so any threshold is a cut of the same matching)."""
    from suit_ros.evaluate import match_frame
    scores, tp, err, place = [], [], [], []
    npos = 0
    for g, d in zip(gt, det):
        m = match_frame(g, d, label, match_dist)
        scores.append(m.scores)
        tp.append(m.tp)
        err.append(m.errors[:, 2])
        assert m.placement is not None          # match_frame always measures it
        place.append(m.placement)
        npos += m.npos
    return ClassCounts(np.concatenate(scores) if scores else np.zeros(0),
                       np.concatenate(tp) if tp else np.zeros(0, bool),
                       np.concatenate(err) if err else np.zeros(0), npos, len(gt),
                       np.concatenate(place) if place else np.zeros((0, 2)))


@dataclass
class Report:
    """Everything ``suit-ros report`` computes."""

    class_names: tuple[str, ...]
    thresholds: list[float]
    counts: dict[str, ClassCounts]
    ap: dict[str, float]
    frames: int
    source: str
    notes: list[str] = field(default_factory=list)
    # AP at each match distance (m) of the nuScenes-style mean (found but misplaced boxes
    # score at 2-4 m, not at 0.5-1 m)
    ap_by_distance: dict[str, dict[float, float]] = field(default_factory=dict)
    # the detections as published (carried boxes at their own thresholds; None: the cuts of
    # ``counts`` at ``thresholds``)
    published: dict[str, ClassCounts] | None = None
    # the objects not found and the false positives at the published thresholds
    # (:func:`findings`)
    missed: list[dict[str, Any]] = field(default_factory=list)
    false: list[dict[str, Any]] = field(default_factory=list)
    # AP intervals over resampled places (suit_ros/place_bootstrap.py), and against a
    # baseline checkpoint when ``baseline`` names one (the second run of ``intervals``)
    intervals: APIntervals | None = None
    baseline: str = ''
    # frames by the sweeps in the model's input (fewer than the model takes: a sequence's
    # first frames, single scans)
    input_sweeps: dict[int, int] = field(default_factory=dict)

    def at_published(self, c: str) -> dict[str, Any]:
        """Class ``c``'s counts as published."""
        if self.published is None:
            return self.counts[c].at(self.thresholds[self.class_names.index(c)])
        return self.published[c].at(0.0)

    def to_json(self) -> dict[str, Any]:
        """JSON-serialisable summary."""
        out: dict[str, Any] = {'source': self.source, 'frames': self.frames,
                               'published_thresholds': dict(zip(self.class_names,
                                                                self.thresholds)),
                               'notes': self.notes, 'classes': {}}
        if self.input_sweeps:
            out['frames_by_input_sweeps'] = {str(k): v for k, v in
                                             sorted(self.input_sweeps.items())}
        for c in self.class_names:
            cc = self.counts[c]
            by_dist = self.ap_by_distance.get(c, {})
            iv = self.intervals
            out['classes'][c] = {'published': self.at_published(c),
                                 'ap': _r(self.ap[c]) if cc.npos else None,
                                 'ap_interval': ([_r(v) for v in iv.interval[c][0]]
                                                 if iv is not None and cc.npos else None),
                                 'ap_by_distance': ({f'{d:g}': _r(v) for d, v in by_dist.items()}
                                                    if cc.npos else None),
                                 'sweep': [cc.at(t) for t in SWEEP]}
        if 'car' in self.counts:
            cars, at = ((self.counts['car'], self.thresholds[self.class_names.index('car')])
                        if self.published is None else (self.published['car'], 0.0))
            out['car_heading'] = cars.heading(at)
            out['car_placement'] = cars.placement_at(at)
        out['missed'] = self.missed
        out['false_positives'] = self.false
        if self.intervals is not None:
            iv = self.intervals
            out['places'] = {'places': iv.places, 'resamples': iv.resamples,
                             'left_out': dict(iv.left_out)}
            if self.baseline:
                out['baseline'] = {
                    'checkpoint': self.baseline,
                    # both APs over the same places (a box goes with its nearest object
                    # there), so the difference is the one of the two columns
                    'classes': {c: {'ap_this': _r(iv.ap[c][0]), 'ap': _r(iv.ap[c][1]),
                                    'difference': _r(iv.difference[c][0]),
                                    'interval': [_r(v) for v in iv.difference[c][1]]}
                                for c in self.class_names if self.counts[c].npos}}
        return out

    def markdown(self) -> str:
        """Tables for a human."""
        j = self.to_json()
        lines = [f'# Real-data report: {self.source}', '',
                 f'{self.frames} frames. Published thresholds: '
                 + ', '.join(f'{c} {t:.2f}' for c, t in zip(self.class_names, self.thresholds))
                 + ('' if self.published is None else
                    ' (boxes held by the carry branch where the cloud has no returns: the '
                    "checkpoint's carry thresholds)"),
                 '', '| class | GT | recall | precision | FP / frame | AP (nuScenes-style) '
                 '| AP at 0.5 / 1 / 2 / 4 m |',
                 '|---|---|---|---|---|---|---|']
        for c in self.class_names:
            p = j['classes'][c]['published']
            ap = j['classes'][c]['ap']
            by_dist = ' / '.join(_f(v) for v in (j['classes'][c]['ap_by_distance'] or {}).values())
            iv = j['classes'][c]['ap_interval']
            ap_cell = _f(ap) + ('' if not iv else f' [{_f(iv[0])}, {_f(iv[1])}]'
                                if _finite(iv[0]) else ' (one place: no interval)')
            lines.append(f'| {c} | {p["gt"]} | {_f(p["recall"])} | {_f(p["precision"])} | '
                         f'{p["fp_per_frame"]:.2f} | {ap_cell} | {by_dist or "n/a"} |')
        if 'places' in j:
            lines += ['', f'AP intervals: 95% over {j["places"]["resamples"]} resamples of the '
                      f'{j["places"]["places"]} places the frames cover ({CELL:g} m squares; a '
                      'box goes with the nearest labelled object within 4 m: '
                      'suit_ros/place_bootstrap.py). A small set gives a wide interval.'
                      + ('' if not j['places'].get('left_out') else
                         ' Resamples holding no object of a class leave its AP undefined and '
                         'are left out of its interval: '
                         + ', '.join(f'{c} {n}' for c, n in j['places']['left_out'].items())
                         + '.')]
        if 'baseline' in j:
            lines += ['', f'## Against the baseline ({j["baseline"]["checkpoint"]})', '',
                      'Paired: the same place resamples score both; the difference is this '
                      'checkpoint minus the baseline. Both APs are over the places (a box goes '
                      'with the nearest labelled object), so they can differ a little from the '
                      'table above.', '',
                      '| class | AP | baseline AP | difference [95% interval] |',
                      '|---|---|---|---|']
            for c, b in j['baseline']['classes'].items():
                lines.append(f'| {c} | {_f(b["ap_this"])} | {_f(b["ap"])} | '
                             f'{b["difference"]:+.3f} '
                             + (f'[{b["interval"][0]:+.3f}, {b["interval"][1]:+.3f}] |'
                                if _finite(b['interval'][0]) else '(one place: no interval) |'))
        if 'car_heading' in j:
            h = j['car_heading']
            lines += ['', f'Car heading (matched cars at the published threshold): '
                      f'{h["matched"]} matched, mean error {h["mean_deg"]} deg, median '
                      f'{h["median_deg"]} deg, flipped (> 135 deg) {h["flipped"]} '
                      f'({h["flip_rate"]})']
        if j.get('car_placement', {}).get('matched'):
            p = j['car_placement']
            lines += ['', f'Car placement (the same matched cars): median range offset '
                      f'{p["range_offset_m"]:+.2f} m (+: farther from the ego than the label), '
                      f'median length error {p["length_error_m"]:+.2f} m']
        lines += ['', '## Over thresholds (recall / precision / FP per frame)', '',
                  '| threshold | ' + ' | '.join(self.class_names) + ' |',
                  '|---|' + '---|' * len(self.class_names)]
        for i, t in enumerate(SWEEP):
            cells = []
            for c in self.class_names:
                s = j['classes'][c]['sweep'][i]
                cells.append(f'{_f(s["recall"], 2)} / {_f(s["precision"], 2)} / '
                             f'{s["fp_per_frame"]:.1f}')
            lines.append(f'| {t:.2f} | ' + ' | '.join(cells) + ' |')
        lines += _findings_markdown(self.missed, self.false)
        lines += [''] + [f'- {n}' for n in self.notes]
        return '\n'.join(lines) + '\n'


TABLE_ROWS = 40                         # rows of each of the markdown's per-object tables


def _table(title: str, intro: str, header: Sequence[str], rows: Sequence[Sequence[str]]
           ) -> list[str]:
    """A markdown table of the first :data:`TABLE_ROWS` rows (all are in the JSON)."""
    if not rows:
        return []
    lines = ['', f'## {title}', '', intro, '', '| ' + ' | '.join(header) + ' |',
             '|' + '---|' * len(header)]
    lines += ['| ' + ' | '.join(r) + ' |' for r in rows[:TABLE_ROWS]]
    if len(rows) > TABLE_ROWS:
        lines.append(f'\n({len(rows) - TABLE_ROWS} more in report.json)')
    return lines


def _seen_cell(seen: dict[str, float] | None) -> str:
    if seen is None:
        return 'n/a'
    return (f'{seen["length_m"]:.1f} x {seen["width_m"]:.1f}, '
            f'{seen["low_m"]:.1f}-{seen["high_m"]:.1f}')


def _box_cell(box: dict[str, Any] | None, key: str) -> str:
    return 'none' if box is None else f'{box["class"]} {box[key]:.2f}'


def _findings_markdown(missed: Sequence[dict[str, Any]], false: Sequence[dict[str, Any]]
                       ) -> list[str]:
    """The missed-objects and false-positives tables."""
    lines = _table(
        'Missed objects (at the published thresholds)',
        'Seen: the extent of its returns along and across its box (first to last) and their '
        "heights above the box's bottom (10th-90th percentile): a patch where the box is long "
        "is an object seen in part. Best score: the highest score a box of the object's class "
        'got there (within the match distance; a threshold below it would find the object). '
        'Other box: the strongest box of another class there.',
        ('frame', 'class', 'range (m)', 'returns', 'seen: along x across, heights (m)',
         'best score', 'other box'),
        [(str(m['frame']), m['class'], f'{m["range_m"]:.1f}',
          'n/a' if m['returns'] is None else str(m['returns']), _seen_cell(m.get('seen')),
          f'{m["best_score"]:.2f}', _box_cell(m['other'], 'score')) for m in missed])
    lines += _table(
        'False positives (published boxes that match no object)',
        f'Nearest object: the nearest labelled object of any class within {NEAR_M:.0f} m '
        '(distance in metres) and whether a published box of its class found it: near a '
        'found object of the same class, a duplicate or a misplaced box; near one of another '
        'class, a wrong class; none, a box on the background (see the pictures). In it: the '
        'returns in the box, their extent along and across it and their heights above its '
        'bottom, as for the misses.',
        ('frame', 'class', 'score', 'range (m)', 'nearest object', 'found',
         'in it: returns; along x across, heights (m)'),
        [(str(f['frame']), f['class'], f'{f["score"]:.2f}', f'{f["range_m"]:.1f}',
          _box_cell(f['nearest'], 'distance_m'),
          '' if f['nearest'] is None else ('yes' if f['nearest']['found'] else 'no'),
          'n/a' if f.get('seen') is None else
          f'{f["seen"]["returns"]}; {_seen_cell(f["seen"])}')
         for f in false])
    return lines


NEAR_M = 4.0                            # how far a false positive's nearest object is looked for


def findings(gt: Sequence[Detections], published: Sequence[Detections],
             decoded: Sequence[Detections], class_names: Sequence[str],
             num_points: Sequence[Any] | None, max_range: float = 50.0,
             match_dist: float = 2.0) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The objects missed and the false positives, at the published boxes.

    Missed: every scored GT object (within ``max_range``, with returns) that no published box
    matches, with what the model made of it: the best score of a box of its class within
    ``match_dist`` among the ``decoded`` ones (0: none) and the strongest box of another class
    there; sorted by class, then range. False: every published box that matches no object,
    with the nearest scored object of any class within :data:`NEAR_M` and whether it was
    found; sorted by class, then descending score.
    """
    from suit_ros.evaluate import filter_frames, match_boxes
    names = tuple(class_names)
    ranges = dict.fromkeys(names, max_range)
    gts, pubs, npts = filter_frames(gt, published, names, ranges, num_points)
    _, decs, _ = filter_frames(gt, decoded, names, ranges, num_points)
    missed: list[dict[str, Any]] = []
    false: list[dict[str, Any]] = []
    for i, (g, p, d, n) in enumerate(zip(gts, pubs, decs, npts)):
        taken, found = match_boxes(g, p, match_dist)
        unmatched = taken < 0
        for gi in np.flatnonzero(~found):
            b, k = g.boxes[gi], int(g.labels[gi])
            near = np.hypot(d.boxes[:, 0] - b[0], d.boxes[:, 1] - b[1]) < match_dist
            own = d.scores[near & (d.labels == k)]
            other = np.flatnonzero(near & (d.labels != k))
            best = other[np.argmax(d.scores[other])] if len(other) else None
            missed.append({'frame': i, 'class': names[k], 'range_m': _r(np.hypot(b[0], b[1])),
                           'box': [_r(v) for v in b],
                           'returns': None if n is None else int(n[gi]),
                           'best_score': _r(own.max()) if len(own) else 0.0,
                           'other': None if best is None else
                           {'class': names[int(d.labels[best])],
                            'score': _r(d.scores[best])}})
        for j in np.flatnonzero(unmatched):
            b = p.boxes[j]
            dist = np.hypot(g.boxes[:, 0] - b[0], g.boxes[:, 1] - b[1])
            q = int(np.argmin(dist)) if len(g) else -1
            false.append({'frame': i, 'class': names[int(p.labels[j])],
                          'score': _r(p.scores[j]), 'range_m': _r(np.hypot(b[0], b[1])),
                          'box': [_r(v) for v in b],
                          'nearest': None if q < 0 or dist[q] > NEAR_M else
                          {'class': names[int(g.labels[q])], 'distance_m': _r(dist[q]),
                           'found': bool(found[q])}})
    missed.sort(key=lambda r: (names.index(r['class']), r['range_m']))
    false.sort(key=lambda r: (names.index(r['class']), -r['score']))
    return missed, false


def seen_of(points: NDArray[np.floating[Any]], box: Sequence[float]) -> dict[str, float] | None:
    """What the sensor saw in a box: its returns (the current sweep's, time lag 0 where the
    points have one), their extent along and across the box, first to last (m), and their
    heights above the box's bottom (10th and 90th percentiles, m); None without returns. A car
    seen whole spans its length; one seen in part, a patch; a false box on a pole, a column."""
    from suit_ros.ops.geometry import in_box_frames
    b = np.asarray(box, np.float64)
    pts = np.asarray(points)
    if pts.ndim == 2 and pts.shape[1] > 4:
        pts = pts[pts[:, 4] == 0]
    along, across, up = (v[:, 0] for v in in_box_frames(np.asarray(pts)[:, :3], b))
    inside = (np.abs(along) <= b[3] / 2) & (np.abs(across) <= b[4] / 2) & (np.abs(up) <= b[5] / 2)
    if not inside.any():
        return None
    low, high = np.percentile(up[inside] + b[5] / 2, [10, 90])
    return {'returns': int(inside.sum()), 'length_m': _r(np.ptp(along[inside])),
            'width_m': _r(np.ptp(across[inside])), 'low_m': _r(low), 'high_m': _r(high)}


def add_seen(rows: Sequence[dict[str, Any]],
             points_of: Callable[[int], NDArray[np.floating[Any]]]) -> None:
    """Give every missed object or false positive (:func:`findings`) what the sensor saw in
    its box (:func:`seen_of`), reading each frame's points (``points_of(frame)``) once."""
    by_frame: dict[int, list[dict[str, Any]]] = {}
    for m in rows:
        by_frame.setdefault(int(m['frame']), []).append(m)
    for i, in_frame in by_frame.items():
        pts = points_of(i)
        for m in in_frame:
            m['seen'] = seen_of(pts, m['box'])


def class_counts(gt: Sequence[Detections], det: Sequence[Detections],
                 class_names: Sequence[str], num_points: Sequence[Any] | None,
                 max_range: float = 50.0, match_dist: float = 2.0) -> dict[str, ClassCounts]:
    """Per class, the detections within ``max_range`` matched to the GT with returns there
    (one matching; any threshold is a cut of it: :meth:`ClassCounts.at`)."""
    from suit_ros.evaluate import filter_frames
    names = tuple(class_names)
    gts, dets, _ = filter_frames(gt, det, names, dict.fromkeys(names, max_range), num_points)
    return {c: count_matches(gts, dets, k, match_dist) for k, c in enumerate(names)}


def on_seen(run: Any, dets: Sequence[Detections], match_dist: float = 2.0
            ) -> list[Detections]:
    """``dets`` less the boxes on labelled objects without returns in the sweep (occluded
    now, held by the tracker or the memory): matched (per class, greedy by score, within
    ``match_dist``) against every labelled object, a box that takes one without returns is
    neither a true nor a false positive in the counts, as nothing of the object is there to
    find; AP counts it as a false positive, as nuScenes does."""
    from suit_ros.evaluate import match_boxes
    if not run.num_points:
        return list(dets)
    out = []
    for d, g, n in zip(dets, run.gt, run.num_points):
        if n is None or len(d) == 0 or (np.asarray(n) > 0).all():
            out.append(d)
            continue
        taken, _ = match_boxes(g, d, match_dist)
        dark = np.asarray(n) == 0
        out.append(d.select((taken < 0) | ~dark[np.maximum(taken, 0)]))
    return out


def build_report(run: Any, class_names: Sequence[str], thresholds: Sequence[float],
                 source: str, max_range: float = 50.0, match_dist: float = 2.0,
                 carry_thresholds: Sequence[float] | None = None) -> Report:
    """The report of a :class:`~suit_ros.evaluate.ModelRun` (detections at the decoding
    threshold; the published thresholds are cuts of them, and with ``carry_thresholds`` the
    boxes a carry branch decoded where the input had no returns are cut at those)."""
    from suit_ros.evaluate import evaluate
    names = tuple(class_names)
    scored = run.scored_detections()
    result = evaluate(run.gt, scored, names, dict.fromkeys(names, max_range), run.num_points)
    scored = on_seen(run, scored, match_dist)
    counts = class_counts(run.gt, scored, names, run.num_points, max_range, match_dist)
    published = None
    boxes_out = on_seen(run, run.as_published(thresholds, carry_thresholds or thresholds)
                        .scored_detections(), match_dist)
    if carry_thresholds is not None and any(c.any() for c in run.carried):
        published = class_counts(run.gt, boxes_out, names, run.num_points, max_range,
                                 match_dist)
    missed, false = findings(run.gt, boxes_out, scored, names, run.num_points, max_range,
                             match_dist)
    return Report(names, [float(t) for t in thresholds], counts, result.class_ap, len(run.gt),
                  source, published=published, missed=missed, false=false,
                  ap_by_distance={c: dict(sorted(result.ap[c].items())) for c in result.ap},
                  input_sweeps=dict(Counter(run.input_sweeps)))


def picture_matches(gt: Detections, pub: Detections, match_dist: float = 2.0
                    ) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Which objects a picture draws as missed and which boxes as true positives: one
    matching per class (greedy by score, BEV centre within ``match_dist``); an object is
    found when the matching gave it a box, not when a true positive of another lies near."""
    from suit_ros.evaluate import match_boxes
    taken, found = match_boxes(gt, pub, match_dist)
    return ~found, taken >= 0


def draw_bev(path: Path, points: NDArray[np.floating[Any]], gt: Detections, det: Detections,
             class_names: Sequence[str], thresholds: Sequence[float],
             ignore: NDArray[np.floating[Any]] | None, max_range: float = 50.0,
             match_dist: float = 2.0, title: str = '') -> None:
    """A bird's-eye PNG: points (grey), GT (blue outline; orange when missed), published
    detections (green: true positive, red: false positive), ignored things (dashed grey)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    thr = np.asarray(thresholds, np.float64)
    pub = det.select(det.scores >= thr[det.labels]) if len(det) else det
    fig, ax = plt.subplots(figsize=(10, 10))
    p = np.asarray(points)
    near = (np.abs(p[:, 0]) < max_range + 5) & (np.abs(p[:, 1]) < max_range + 5)
    p = p[near]
    ax.scatter(p[:, 0], p[:, 1], s=0.15, c=np.clip(p[:, 2], -1, 3), cmap='Greys', vmin=-2,
               vmax=3, linewidths=0)
    missed, tp_det = picture_matches(gt, pub, match_dist)
    for j, b in enumerate(gt.boxes):
        _box(ax, b, 'orange' if missed[j] else 'royalblue', 1.6 if missed[j] else 1.0)
    if ignore is not None:
        for b in np.asarray(ignore).reshape(-1, 7):
            _box(ax, b, 'grey', 0.8, '--')
    for j, b in enumerate(pub.boxes):
        colour = 'limegreen' if tp_det[j] else 'red'
        _box(ax, b, colour, 1.2, heading=True)
        ax.text(b[0], b[1] + 0.8, f'{class_names[pub.labels[j]][:3]} {pub.scores[j]:.2f}',
                fontsize=5, color=colour)
    ax.set_xlim(-max_range, max_range)
    ax.set_ylim(-max_range, max_range)
    ax.set_aspect('equal')
    ax.set_title(f'{title}\nblue: GT found, orange: GT missed, green: TP, red: FP, '
                 'dashed: ignored', fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _box(ax: Any, b: NDArray[np.floating[Any]], colour: str, width: float, style: str = '-',
         heading: bool = False) -> None:
    x, y, _, length, w, _, yaw = (float(v) for v in b)
    c, s = np.cos(yaw), np.sin(yaw)
    corners = np.array([[length, w], [length, -w], [-length, -w], [-length, w],
                        [length, w]]) / 2
    xy = corners @ np.array([[c, s], [-s, c]]) + (x, y)
    ax.plot(xy[:, 0], xy[:, 1], color=colour, lw=width, ls=style)
    if heading:
        ax.plot([x, x + c * length / 2], [y, y + s * length / 2], color=colour, lw=width)


# ------------------------------------------------------------------ command line
def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add ``report`` options."""
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument('--av2', metavar='ROOT', help='Argoverse 2 sensor-dataset folder or log')
    src.add_argument('--kitti', metavar='ROOT',
                     help='KITTI-format folder (scored in the camera field of view only)')
    src.add_argument('--nuscenes', metavar='ROOT', help='nuScenes-format folder')
    src.add_argument('--synthetic', choices=['val', 'tune', 'demo'], help='a synthetic split')
    parser.add_argument('--preset', default=None,
                        help='the world of a --synthetic val or tune split (a preset of '
                        'suit_ros/data/sim/config.py, e.g. val-ends-all; default val-real)')
    parser.add_argument('--out', required=True, help='folder for report.json/.md and bev/')
    parser.add_argument('--checkpoint', default='', help='default: the shipped checkpoint')
    parser.add_argument('--score-thresholds', type=float, nargs='+', metavar='T',
                        help="published thresholds: one, or one per class (default: the "
                        "checkpoint's, as the node)")
    parser.add_argument('--no-tracking', action='store_true',
                        help="the model's own output (the node tracks by default)")
    parser.add_argument('--ground', choices=list(GROUND_MODES), default=None,
                        help="the input's height reference (the node's `ground` parameter; "
                        'default: as the checkpoint was trained)')
    parser.add_argument('--overhang', choices=list(OVERHANG_MODES), default=None,
                        help='keep or drop the returns that hang over a gap in their column '
                        "(the node's `overhang` parameter; default: as the checkpoint says)")
    parser.add_argument('--max-range', type=float, default=50.0, help='scored range (m)')
    parser.add_argument('--box-fit', choices=list(BOX_FIT_MODES), default='off',
                        help="car boxes moved onto the returns of their visible faces (the "
                        "node's `box_fit` parameter; suit_ros/box_fit.py)")
    add_traffic_side_option(parser)
    parser.add_argument('--deskew', choices=['on', 'off'], default='on',
                        help="sweeps taken over time put back at their stamps (the node's "
                        '`deskew` parameter; synthetic sweeps of real sensors; the readers of '
                        'Argoverse 2, KITTI and nuScenes give none: theirs are compensated or '
                        'carry no times)')
    parser.add_argument('--match-dist', type=float, default=2.0, help='BEV centre distance (m)')
    parser.add_argument('--pictures', type=int, default=50,
                        help="bird's-eye PNGs for the first N frames (0: none)")
    parser.add_argument('--baseline', default='', metavar='CHECKPOINT',
                        help='also run this checkpoint the same way and give the paired AP '
                        'difference per class with its interval over places')
    parser.add_argument('--resamples', type=int, default=500,
                        help='place resamples of the AP intervals (0: none)')
    parser.add_argument('--version', default='v1.0-mini', help='nuScenes table version')
    parser.add_argument('--kitti-intensity-scale', type=float, default=1.0)
    parser.add_argument('--cache-dir', default='data_cache')


def _sequences(args: argparse.Namespace, class_names: Sequence[str], sweeps: int
               ) -> tuple[list[Any], str, list[TrafficSide] | None]:
    """The frames, what they are, and the side of the road each sequence keeps to where
    the dataset says it (nuScenes' log locations; None: not said)."""
    if args.av2:
        from suit_ros.data.av2 import av2_sequences
        return list(av2_sequences(args.av2, class_names)), f'Argoverse 2 ({args.av2})', None
    if args.kitti:
        from suit_ros.data.sequences import kitti_sequences
        return list(kitti_sequences(args.kitti, args.kitti_intensity_scale)), \
            f'KITTI ({args.kitti}, camera field of view)', None
    if args.nuscenes:
        from suit_ros.data.sequences import nuscenes_scenes
        seqs, sides = nuscenes_scenes(args.nuscenes, args.version, sweeps)
        return seqs, f'nuScenes ({args.nuscenes})', sides
    from suit_ros.data.sequences import SPLIT_SEEDS, synthetic_sequence, synthetic_split
    from suit_ros.data.sim.config import PRESETS
    if args.synthetic == 'demo':
        return [synthetic_sequence('demo-real', SPLIT_SEEDS['demo'], 100, args.cache_dir)], \
            'synthetic demo drive', None
    if args.preset is not None and args.preset not in PRESETS:
        raise ConfigError(f'--preset {args.preset!r} is not a preset; one of '
                          f'{", ".join(sorted(PRESETS))}')
    return synthetic_split(args.synthetic, 16, 40, args.cache_dir, args.preset), \
        f'synthetic {args.synthetic} split (16 drives' + \
        (f', world {args.preset})' if args.preset else ')'), None


def add_traffic_side_option(parser: argparse.ArgumentParser) -> None:
    """``--traffic-side`` of ``eval`` and ``report`` (read with :func:`traffic_sides`)."""
    parser.add_argument('--traffic-side', choices=['auto', 'right', 'left'], default='auto',
                        help="the side of the road traffic keeps to, as the node's "
                        '`traffic_side` parameter would be set there (left gives the model '
                        "each drive mirrored); auto: nuScenes' Singapore scenes left (their "
                        "log location), everything else as the node's default")


def traffic_sides(choice: Literal['auto', 'right', 'left'], count: int,
                  own: list[TrafficSide] | None, tracked: bool = True
                  ) -> list[TrafficSideParam]:
    """The side of the road each of ``count`` sequences keeps to: ``--traffic-side``, or
    with ``auto`` the recording's own where the dataset says it (``own``), else the node's
    default ``traffic_side`` (``auto``: read from the tracked traffic,
    :mod:`suit_ros.traffic_side`; right where the run has no tracks, untracked or in history
    windows, as the node without tracking stays right)."""
    if choice == 'right' or choice == 'left':
        return [choice] * count
    if own is not None:
        return list(own)
    from suit_ros.params import DetectorParams
    default = DetectorParams().traffic_side
    return [default if default != 'auto' or tracked else 'right'] * count


def report_thresholds(meta: dict[str, Any], class_names: Sequence[str],
                      override: Sequence[float] | None = None) -> list[float]:
    """``override`` (one, or one per class), else the checkpoint's published thresholds."""
    from suit_ros.checkpoint import published_thresholds
    k = len(class_names)
    if override:
        if len(override) not in (1, k) or not all(0.0 <= v <= 1.0 for v in override):
            raise ConfigError(f'--score-thresholds needs 1 or {k} values within 0..1')
        return [float(v) for v in override] * (k if len(override) == 1 else 1)
    return published_thresholds(meta, list(class_names))


def run(args: argparse.Namespace) -> int:
    """Run the model, write the report and pictures."""
    from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint, published_thresholds
    from suit_ros.evaluate import run_model
    from suit_ros.tracking import TrackerConfig
    if args.preset is not None and args.synthetic not in ('val', 'tune'):
        raise ConfigError('--preset sets the world of a --synthetic val or tune split; '
                          'drop it for a dataset folder or the demo drive')
    if args.resamples < 0 or (args.baseline and args.resamples == 0):
        raise ConfigError('--resamples must be >= 0, and > 0 with --baseline')
    from suit_ros.outputs import json_text, output_dir
    out = output_dir(args.out, '--out folder')       # before the run, not after it
    model, cfg, meta = load_checkpoint(args.checkpoint or default_checkpoint_path())
    names = tuple(cfg.class_names)
    thresholds = report_thresholds(meta, names, args.score_thresholds)
    seqs, source, own_sides = _sequences(args, names, cfg.sweeps)
    if not seqs or not any(len(s) for s in seqs):
        raise DatasetError('the dataset holds no frame')
    baseline = None
    if args.baseline:
        baseline, base_cfg, _ = load_checkpoint(args.baseline)
        if tuple(base_cfg.class_names) != names:
            raise ConfigError(f'--baseline {args.baseline} detects {base_cfg.class_names}, '
                              f'the checkpoint {names}: compare checkpoints of one class list')
        if args.nuscenes and base_cfg.sweeps != cfg.sweeps:
            raise ConfigError(f'--baseline {args.baseline} takes {base_cfg.sweeps} sweeps, the '
                              f'checkpoint {cfg.sweeps}: nuScenes keyframes are read once, with '
                              "the checkpoint's count; compare checkpoints of one count")
    filt = None if args.no_tracking else TrackerConfig()
    if filt is not None and args.nuscenes:
        from suit_ros.evaluate import tracker_for
        filt = tracker_for(seqs, filt)          # keyframes 0.5 s apart: see tracker_for
    deskew = args.deskew == 'on'
    sides = traffic_sides(args.traffic_side, len(seqs), own_sides, filt is not None)
    result = run_model(model, seqs, tracker=filt, ground=args.ground, overhang=args.overhang,
                       box_fit=args.box_fit, deskew=deskew, traffic_side=sides)
    base_run = None if baseline is None else run_model(
        baseline, seqs, tracker=filt, ground=args.ground, overhang=args.overhang,
        box_fit=args.box_fit, deskew=deskew, traffic_side=sides)
    notes = [f'as the node by default: {cfg.sweeps} sweeps, tracker on (tracker and score '
             'smoothing)' if filt else "the model's own output (tracker off)"]
    if args.ground is not None or cfg.pillars.ground != 'as_given':
        notes.append(f'input heights: ground {args.ground or cfg.pillars.ground} '
                     '(suit_ros/ground.py)')
    if deskew and args.synthetic:
        notes.append('sweeps of sensors that take them over time deskewed '
                     '(suit_ros/deskew.py), as the node does with their time field')
    if args.overhang is not None:
        notes.append(f'overhang {args.overhang}: the returns that hang over a gap in their '
                     'column (suit_ros/overhang.py)')
    if 'left' in sides:
        notes.append(f'traffic side left in {sides.count("left")} of {len(sides)} sequences '
                     "(the node's `traffic_side`: the model given the drive mirrored, its "
                     'boxes mirrored back)')
    if 'auto' in sides:
        went_left = len({d for d, side in zip(result.drive, result.sides) if side == 'left'})
        notes.append(f'traffic side read from the oncoming traffic in {sides.count("auto")} '
                     f"of {len(sides)} sequences (the node's `traffic_side: auto`); it went "
                     f'over to left-hand traffic in {went_left}')
    if args.box_fit != 'off':
        notes.append(f'box fit {args.box_fit}: car boxes moved onto the returns of the faces '
                     'the sensor sees (suit_ros/box_fit.py)')
    short = [n for n in result.input_sweeps if n < cfg.sweeps]
    if short:
        by = ', '.join(f'{v} with {k}' for k, v in sorted(Counter(short).items()))
        notes.append(f'{len(short)} of {len(result.input_sweeps)} frames read with fewer than '
                     f"{cfg.sweeps} sweeps ({by}: after a sequence's start, a reset or a gap; "
                     'single scans): the model finds fewer objects on them than with its '
                     f'{cfg.sweeps} (docs/experiments/first_sweeps)')
    if args.kitti:
        from suit_ros.data.kitti import camera_fov_run
        result = camera_fov_run(result, seqs)
        base_run = None if base_run is None else camera_fov_run(base_run, seqs)
        notes.append('KITTI labels only the front camera view: only it is scored')
    carry = (None if args.score_thresholds
             else published_thresholds(meta, list(names), carried=True))
    report = build_report(result, names, thresholds, source, args.max_range, args.match_dist,
                          carry)
    report.notes += notes
    frames = [(seq, k) for seq in seqs for k in range(len(seq))]
    add_seen([*report.missed, *report.false], lambda i: frames[i][0][frames[i][1]].points)
    if args.resamples:
        from suit_ros.place_bootstrap import ap_intervals, cut_into_places
        runs = [result] + ([] if base_run is None else [base_run])
        places = cut_into_places(result.gt, [r.scored_detections() for r in runs],
                                 result.num_points, class_names=names,
                                 max_range=args.max_range)
        report.intervals = ap_intervals(places, names, args.max_range, args.resamples)
        report.baseline = args.baseline
    replaced = (out / 'report.json').exists()
    (out / 'report.json').write_text(json_text(report.to_json()), encoding='utf-8')
    (out / 'report.md').write_text(report.markdown(), encoding='utf-8')
    # an earlier report's pictures would stay beside this one's (other frames, other counts)
    old = sorted((out / 'bev').glob('*_[0-9][0-9][0-9][0-9].png')) if (out / 'bev').is_dir() \
        else []
    for f in old:
        f.unlink()
    if replaced or old:
        print(f'replaced the earlier report in {out} ({len(old)} old picture(s) removed from '
              f'{out / "bev"})', file=sys.stderr)
    scored, drawn_at = result.scored_detections(), list(thresholds)
    if report.published is not None:       # the pictures show what is published
        scored = result.as_published(thresholds, carry or thresholds).scored_detections()
        drawn_at = [0.0] * len(names)
    first = drawn = 0                  # first: the run's index of the sequence's frame 0
    for seq in seqs:
        for k, f in enumerate(seq[:max(args.pictures, 0)]):
            draw_bev(out / 'bev' / f'{f.sequence_id or "seq"}_{k:04d}.png',
                     f.points, result.gt[first + k], scored[first + k], names, drawn_at,
                     f.ignore_boxes, args.max_range, args.match_dist,
                     f'{source}: frame {k} of {f.sequence_id}')
            drawn += 1
        first += len(seq)
    print(report.markdown())
    print(f'wrote {out / "report.json"}, {out / "report.md"} and '
          f'{drawn} picture(s) in {out / "bev"}')
    return 0
