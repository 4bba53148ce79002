"""nuScenes-style detection metrics for the project's classes, and model evaluation.

Matching is greedy by descending score over all frames on BEV centre distance (0.5/1/2/4 m),
per-class evaluation ranges from the sensor, GT without LiDAR returns removed, AP as the
normalised area of the 101-point interpolated precision above min precision 0.1 from min recall
0.1, TP errors (ATE, ASE, AOE, AVE) at 2 m averaged over the recall range, as the nuScenes
devkit computes them. NDS here has no attribute term: NDS = (5 mAP + sum of the four
(1 - min(1, mTP))) / 9 instead of / 10.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from suit_ros import CLASS_NAMES
from suit_ros.structures import Detections, Frame

if TYPE_CHECKING:
    from suit_ros.box_fit import BoxFitMode
    from suit_ros.ground import GroundMode
    from suit_ros.model.inference import PrecisionChoice
    from suit_ros.overhang import OverhangMode
    from suit_ros.params import TrafficSide, TrafficSideParam
    from suit_ros.tracking import TrackerConfig

DIST_THRESHOLDS = (0.5, 1.0, 2.0, 4.0)
TP_DIST = 2.0
IGNORE_MARGIN = 0.5        # m: an ignored box's footprint grown by this
MIN_RECALL = 0.1
MIN_PRECISION = 0.1
CLASS_RANGES = {'car': 50.0, 'truck': 50.0, 'pedestrian': 40.0, 'cyclist': 40.0}
TP_METRICS = ('trans_err', 'scale_err', 'orient_err', 'vel_err')
TP_NAMES = {'trans_err': 'mATE', 'scale_err': 'mASE', 'orient_err': 'mAOE', 'vel_err': 'mAVE'}
NDS_NOTE = 'NDS without the attribute term: (5 mAP + sum(1 - min(1, mTP)) over 4 TP) / 9'


@dataclass
class ClassCurve:
    """101-point interpolated curves of one class at one distance threshold."""

    recall: NDArray[np.float64]
    precision: NDArray[np.float64]
    confidence: NDArray[np.float64]
    errors: dict[str, NDArray[np.float64]]


def _nanmean(values: Sequence[float]) -> float:
    """The mean of the finite values; nan when there are none (and no warning)."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else float('nan')


def _round(value: float, digits: int = 4) -> float | None:
    """``value`` rounded for JSON; None when undefined (nan is not JSON)."""
    return round(value, digits) if np.isfinite(value) else None


@dataclass
class EvalResult:
    """Per-class AP per threshold, TP errors, mAP and NDS."""

    class_names: tuple[str, ...]
    ap: dict[str, dict[float, float]]
    tp: dict[str, dict[str, float]]
    curves: dict[str, dict[float, ClassCurve]]
    num_gt: dict[str, int]
    num_frames: int
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def evaluated(self) -> tuple[str, ...]:
        """Classes with GT in the evaluated frames; the others are shown as n/a, their AP is
        undefined (nan) and they are left out of mAP, the mTP errors and NDS (the devkit would
        count them as AP 0)."""
        return tuple(c for c in self.class_names if self.num_gt[c] > 0)

    @property
    def class_ap(self) -> dict[str, float]:
        """Mean AP over the distance thresholds, per class; nan for a class without GT."""
        return {c: float(np.mean(list(self.ap[c].values()))) if self.num_gt[c] > 0
                else float('nan') for c in self.class_names}

    @property
    def mean_ap(self) -> float:
        """mAP over the evaluated classes (nan when no class has GT)."""
        aps = [self.class_ap[c] for c in self.evaluated]
        return float(np.mean(aps)) if aps else float('nan')

    @property
    def mean_tp(self) -> dict[str, float]:
        """mATE, mASE, mAOE, mAVE (means over the evaluated classes)."""
        return {TP_NAMES[k]: _nanmean([self.tp[c][k] for c in self.evaluated])
                for k in TP_METRICS}

    @property
    def nds(self) -> float:
        """NDS without the attribute term (denominator 9)."""
        tp = sum(1.0 - min(1.0, v) for v in self.mean_tp.values())
        return float((5.0 * self.mean_ap + tp) / 9.0)

    def summary(self) -> dict[str, Any]:
        """Flat numbers for logs and checkpoints."""
        out: dict[str, Any] = {'mAP': _round(self.mean_ap), 'NDS': _round(self.nds)}
        out.update({k: _round(v) for k, v in self.mean_tp.items()})
        out.update({f'AP_{c}': _round(v) for c, v in self.class_ap.items()})   # None: no GT
        out['frames'] = self.num_frames
        out.update(self.extra)
        return out

    def to_json(self) -> dict[str, Any]:
        """Everything, JSON-serialisable."""
        return {'summary': self.summary(), 'nds_note': NDS_NOTE,
                'ap': {c: {str(k): v for k, v in d.items()} if self.num_gt[c] else None
                       for c, d in self.ap.items()},
                'tp': self.tp, 'num_gt': self.num_gt}

    def table(self) -> str:
        """A terminal table."""
        lines = [f'{"class":<12}{"AP":>7}' + ''.join(f'{f"AP@{d}":>8}' for d in DIST_THRESHOLDS)
                 + ''.join(f'{TP_NAMES[k][1:]:>7}' for k in TP_METRICS) + f'{"GT":>7}']
        for c in self.class_names:
            if c not in self.evaluated:
                lines.append(f'{c:<12}{"n/a (no GT in these frames)":>34}')
                continue
            lines.append(f'{c:<12}{self.class_ap[c]:>7.3f}'
                         + ''.join(f'{self.ap[c][d]:>8.3f}' for d in DIST_THRESHOLDS)
                         + ''.join(f'{self.tp[c][k]:>7.3f}' for k in TP_METRICS)
                         + f'{self.num_gt[c]:>7d}')
        tp = self.mean_tp
        if not self.evaluated:
            lines.append(f'mAP n/a  NDS n/a: no GT of any class in these {self.num_frames} '
                         'frames')
            lines.append(f'note: {NDS_NOTE}')
            return '\n'.join(lines)
        lines.append(f'mAP {self.mean_ap:.4f}  NDS {self.nds:.4f}  '
                     + '  '.join(f'{k} {v:.3f}' for k, v in tp.items())
                     + f'  ({self.num_frames} frames)')
        lines.append(f'note: {NDS_NOTE}')
        return '\n'.join(lines)

    def plot_pr(self, path: str) -> None:
        """PNG of precision-recall curves per class and distance threshold."""
        import matplotlib
        matplotlib.use('Agg')
        import matplotlib.pyplot as plt
        n = len(self.class_names)
        fig, axes = plt.subplots(1, n, figsize=(4 * n, 3.6), squeeze=False)
        for ax, c in zip(axes[0], self.class_names):
            for d, curve in self.curves[c].items():
                ax.plot(curve.recall, curve.precision, label=f'{d} m (AP {self.ap[c][d]:.2f})')
            ax.set_title(f'{c} (AP {self.class_ap[c]:.3f})')
            ax.set_xlabel('recall')
            ax.set_ylabel('precision')
            ax.set_xlim(0, 1)
            ax.set_ylim(0, 1.02)
            ax.legend(fontsize=7, loc='lower left')
            ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)


def _filter(det: Detections, ranges: NDArray[np.float64], num_points: NDArray[np.uint32] | None
            ) -> NDArray[np.bool_]:
    dist = np.hypot(det.boxes[:, 0], det.boxes[:, 1])
    keep = np.asarray(dist <= ranges[det.labels], bool)
    if num_points is not None:
        keep &= num_points > 0
    return keep


def _cummean(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """The running mean of ``x``, NaN skipped; all NaN (no error defined: every matched GT's
    velocity unknown) is 1, the worst score, as the nuScenes devkit's ``cummean``."""
    if len(x) == 0:
        return x
    if np.isnan(x).all():
        return np.ones(len(x))
    nan = np.isnan(x)
    sums = np.nancumsum(x.astype(np.float64))
    counts = np.cumsum(~nan)
    return np.divide(sums, counts, out=np.zeros_like(sums), where=counts != 0)


def _wrap_abs(a: NDArray[np.float64]) -> NDArray[np.float64]:
    d = (a + np.pi) % (2 * np.pi) - np.pi
    return np.asarray(np.abs(d), np.float64)


@dataclass
class FrameMatches:
    """One frame's detections of one class matched to its GT at one distance threshold.

    Greedy matching by descending score only depends on the frame's own detections (a GT box
    is taken within its frame), so frames can be matched once and combined in any selection:
    what the per-drive bootstrap does.
    """

    scores: NDArray[np.float64]       # (n,)
    tp: NDArray[np.bool_]             # (n,)
    errors: NDArray[np.float64]       # (n, 4) TP errors in TP_METRICS order (nan if not TP)
    npos: int
    # (n, 2) of a TP: its centre's range from the ego origin minus its GT's (+: placed too
    # far) and its length minus the GT's; nan if not TP (None where not computed)
    placement: NDArray[np.float64] | None = None
    # (n,) of a TP: the index of its GT among the frame's GT of the class; -1 if not TP
    # (None where not computed)
    gt_index: NDArray[np.int64] | None = None


def match_frame(g: Detections, d: Detections, label: int, dist_th: float) -> FrameMatches:
    """Greedy nuScenes matching of one frame's class-``label`` detections (descending score,
    nearest free GT by BEV centre distance below ``dist_th``)."""
    gm = g.labels == label
    gb, gv = g.boxes[gm].astype(np.float64), g.velocities[gm].astype(np.float64)
    dm = d.labels == label
    pb, pv = d.boxes[dm].astype(np.float64), d.velocities[dm].astype(np.float64)
    ps = d.scores[dm].astype(np.float64)
    n = len(ps)
    tp = np.zeros(n, bool)
    errors = np.full((n, len(TP_METRICS)), np.nan)
    placement = np.full((n, 2), np.nan)
    gt_index = np.full(n, -1, np.int64)
    if len(gb) and n:
        dist = np.hypot(pb[:, None, 0] - gb[None, :, 0], pb[:, None, 1] - gb[None, :, 1])
        taken = np.zeros(len(gb), bool)
        for j in np.argsort(-ps, kind='stable'):
            row = np.where(taken, np.inf, dist[j])
            k = int(np.argmin(row))
            if row[k] < dist_th:
                taken[k] = True
                tp[j] = True
                gt_index[j] = k
                inter = np.prod(np.minimum(gb[k, 3:6], pb[j, 3:6]))
                union = np.prod(gb[k, 3:6]) + np.prod(pb[j, 3:6]) - inter
                errors[j] = (row[k], 1 - inter / union,
                             float(_wrap_abs(np.array(pb[j, 6] - gb[k, 6]))),
                             float(np.hypot(*(pv[j] - gv[k]))))
                placement[j] = (np.hypot(*pb[j, :2]) - np.hypot(*gb[k, :2]),
                                pb[j, 3] - gb[k, 3])
    return FrameMatches(ps, tp, errors, int(len(gb)), placement, gt_index)


def match_boxes(g: Detections, d: Detections, dist_th: float = TP_DIST
                ) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """One frame's detections of every class matched to its GT (:func:`match_frame` per
    class): per detection the index in ``g`` of the GT box it took (-1: none), and per GT box
    whether a detection took it."""
    taken = np.full(len(d), -1, np.int64)
    for k in np.unique(d.labels):
        m = match_frame(g, d, int(k), dist_th)
        assert m.gt_index is not None              # match_frame always records it
        taken[np.flatnonzero(d.labels == k)[m.tp]] = \
            np.flatnonzero(g.labels == k)[m.gt_index[m.tp]]
    found = np.zeros(len(g), bool)
    found[taken[taken >= 0]] = True
    return taken, found


def curve_from(matches: Sequence[FrameMatches]) -> tuple[ClassCurve, int]:
    """The class curve of a set of matched frames (frames may repeat)."""
    npos = int(sum(m.npos for m in matches))
    rec_interp = np.linspace(0, 1, 101)
    empty = ClassCurve(rec_interp, np.zeros(101), np.zeros(101),
                       {k: np.ones(101) for k in TP_METRICS})
    if npos == 0:
        return empty, 0
    ps = np.concatenate([m.scores for m in matches]) if matches else np.zeros(0)
    tp_all = np.concatenate([m.tp for m in matches]) if matches else np.zeros(0, bool)
    err_all = (np.concatenate([m.errors for m in matches]) if matches
               else np.zeros((0, len(TP_METRICS))))
    order = np.argsort(-ps, kind='stable')
    tp = tp_all[order].astype(np.float64)
    if tp.sum() == 0:
        return empty, npos
    ctp = np.cumsum(tp)
    cfp = np.cumsum(1 - tp)
    prec = ctp / (ctp + cfp)
    rec = ctp / npos
    conf = ps[order]
    precision = np.interp(rec_interp, rec, prec, right=0)
    confidence = np.interp(rec_interp, rec, conf, right=0)
    hit = tp_all[order]
    ctp_conf = conf[hit]
    errs = err_all[order][hit]
    errors = {}
    for i, key in enumerate(TP_METRICS):
        tmp = _cummean(errs[:, i])
        errors[key] = np.interp(confidence[::-1], ctp_conf[::-1], tmp[::-1])[::-1]
    return ClassCurve(rec_interp, precision, confidence, errors), npos


def _ap(curve: ClassCurve) -> float:
    prec = np.copy(curve.precision)[round(100 * MIN_RECALL) + 1:]
    prec -= MIN_PRECISION
    prec[prec < 0] = 0
    return float(np.mean(prec)) / (1.0 - MIN_PRECISION)


def _tp(curve: ClassCurve, key: str) -> float:
    first = round(100 * MIN_RECALL) + 1
    nz = np.nonzero(curve.confidence)[0]
    last = int(nz[-1]) if len(nz) else 0
    if last < first:
        return 1.0
    return float(np.mean(curve.errors[key][first:last + 1]))


def filter_frames(gt: Sequence[Detections], det: Sequence[Detections],
                  class_names: Sequence[str] = CLASS_NAMES,
                  ranges: dict[str, float] | None = None,
                  num_points: Sequence[NDArray[np.uint32] | None] | None = None,
                  max_boxes_per_frame: int = 500
                  ) -> tuple[list[Detections], list[Detections], list[NDArray[np.uint32] | None]]:
    """What is scored: GT and detections within the class ranges, GT with LiDAR returns,
    at most ``max_boxes_per_frame`` detections (the highest scores); ``num_points`` follows."""
    if len(gt) != len(det):
        raise ValueError(f'{len(gt)} GT frames but {len(det)} detection frames')
    rng = ranges or CLASS_RANGES
    r = np.array([rng.get(c, 50.0) for c in class_names])
    gts, dets, npts_out = [], [], []
    for i, (g, d) in enumerate(zip(gt, det)):
        npts = num_points[i] if num_points is not None else None
        keep = _filter(g, r, npts)
        gts.append(g.select(keep))
        npts_out.append(None if npts is None else npts[keep])
        d = d.select(_filter(d, r, None))
        if len(d) > max_boxes_per_frame:
            d = d.select(np.argsort(-d.scores, kind='stable')[:max_boxes_per_frame])
        dets.append(d)
    return gts, dets, npts_out


def result_from_matches(class_names: Sequence[str],
                        matches: Mapping[int, Mapping[float, Sequence[FrameMatches]]],
                        num_frames: int) -> EvalResult:
    """AP, TP errors, mAP and NDS from matched frames (``matches[label][threshold]``)."""
    names = tuple(class_names)
    ap: dict[str, dict[float, float]] = {}
    tp: dict[str, dict[str, float]] = {}
    curves: dict[str, dict[float, ClassCurve]] = {}
    num_gt: dict[str, int] = {}
    for label, c in enumerate(names):
        curves[c] = {}
        ap[c] = {}
        for th in DIST_THRESHOLDS:
            curve, npos = curve_from(matches[label][th])
            curves[c][th] = curve
            ap[c][th] = _ap(curve)
            num_gt[c] = npos
        tp[c] = {k: _tp(curves[c][TP_DIST], k) for k in TP_METRICS}
    return EvalResult(names, ap, tp, curves, num_gt, num_frames)


def evaluate(gt: Sequence[Detections], det: Sequence[Detections],
             class_names: Sequence[str] = CLASS_NAMES,
             ranges: dict[str, float] | None = None,
             num_points: Sequence[NDArray[np.uint32] | None] | None = None,
             max_boxes_per_frame: int = 500) -> EvalResult:
    """Evaluate detections against GT, frame by frame (both in each frame's sensor frame)."""
    gts, dets, _ = filter_frames(gt, det, class_names, ranges, num_points, max_boxes_per_frame)
    matches = {label: {th: [match_frame(g, d, label, th) for g, d in zip(gts, dets)]
                       for th in DIST_THRESHOLDS} for label in range(len(class_names))}
    return result_from_matches(class_names, matches, len(gt))


def drop_ignored(det: Detections, gt: Detections, ignore: NDArray[np.floating[Any]],
                 radius: float = TP_DIST, num_points: NDArray[np.uint32] | None = None
                 ) -> Detections:
    """``det`` without the detections on ignored things (real datasets: parked bicycles, an
    RV, a tram): a detection whose BEV centre lies within ``radius`` of an ignored box's
    centre, or on its footprint grown by :data:`IGNORE_MARGIN` m (a box on the end of a 12 m
    vehicle is 6 m from its centre), counts as neither a true nor a false positive, unless it
    lies within ``radius`` of a GT box of its own class that is scored (with returns, when
    ``num_points`` is given): a box of another class, or one evaluation leaves out, vouches
    for nothing."""
    ig = np.asarray(ignore, np.float64).reshape(-1, 7)
    if len(ig) == 0 or len(det) == 0:
        return det
    xy = det.boxes[:, None, :2].astype(np.float64)
    rel = xy - ig[None, :, :2]                                   # (D, I, 2)
    cos, sin = np.cos(ig[:, 6]), np.sin(ig[:, 6])
    along = np.abs(rel[..., 0] * cos + rel[..., 1] * sin)
    across = np.abs(-rel[..., 0] * sin + rel[..., 1] * cos)
    on = (along <= ig[:, 3] / 2 + IGNORE_MARGIN) & (across <= ig[:, 4] / 2 + IGNORE_MARGIN)
    near_ignored = ((np.hypot(rel[..., 0], rel[..., 1]) < radius) | on).any(1)
    scored = np.ones(len(gt), bool) if num_points is None else np.asarray(num_points) > 0
    if scored.any():
        g = gt.boxes[None, scored, :2].astype(np.float64)
        near = np.hypot(*(xy - g).transpose(2, 0, 1)) < radius
        near &= det.labels[:, None] == gt.labels[None, scored]
        near_ignored &= ~near.any(1)
    return det.select(~near_ignored)


@dataclass
class ModelRun:
    """Per-frame outputs of a model run over sequences (the inputs of :func:`evaluate`)."""

    gt: list[Detections]
    det: list[Detections]
    num_points: list[Any]
    latency_s: list[float]
    memory_bytes: list[int]
    memory_after: dict[int, list[int]]
    drive: list[int] = field(default_factory=list)
    ignore: list[NDArray[np.float32] | None] = field(default_factory=list)
    carried: list[NDArray[np.bool_]] = field(default_factory=list)
    used_memory: list[bool] = field(default_factory=list)   # per frame: a memory was fused
    # per frame the side of the road the model was given traffic on (``traffic_side``)
    sides: list[TrafficSide] = field(default_factory=list)
    # per frame the sweeps in the model's input: fewer than the model takes on a sequence's
    # first frames and on single scans (a dataset's accumulated keyframe counts as whole)
    input_sweeps: list[int] = field(default_factory=list)

    def held(self) -> list[NDArray[np.bool_]]:
        """Per frame, which detections are held where the input had no returns (``carried``;
        none when the run has no such flags)."""
        return self.carried or [np.zeros(len(d), bool) for d in self.det]

    def published_masks(self, thresholds: Sequence[float], carry_thresholds: Sequence[float]
                        ) -> list[NDArray[np.bool_]]:
        """Per frame, which detections are published (:meth:`published`)."""
        thr, carry = np.asarray(thresholds, np.float32), np.asarray(carry_thresholds, np.float32)
        return [d.scores >= np.where(c, carry[d.labels], thr[d.labels])
                for d, c in zip(self.det, self.held())]

    def published(self, thresholds: Sequence[float], carry_thresholds: Sequence[float]
                  ) -> list[Detections]:
        """Each frame's detections at per-class published thresholds, the boxes a carry
        branch decoded where the input had no returns at ``carry_thresholds``."""
        return [d.select(m) for d, m in zip(self.det, self.published_masks(thresholds,
                                                                             carry_thresholds))]

    def select_frames(self, idx: Sequence[int]) -> ModelRun:
        """The run on the frames ``idx`` only (in that order; ``memory_after`` kept)."""
        def pick(values: list[Any]) -> list[Any]:
            return [values[i] for i in idx] if values else values
        return replace(self, gt=pick(self.gt), det=pick(self.det),
                       num_points=pick(self.num_points), latency_s=pick(self.latency_s),
                       memory_bytes=pick(self.memory_bytes), drive=pick(self.drive),
                       ignore=pick(self.ignore), carried=pick(self.carried),
                       used_memory=pick(self.used_memory), sides=pick(self.sides),
                       input_sweeps=pick(self.input_sweeps))

    def as_published(self, thresholds: Sequence[float], carry_thresholds: Sequence[float]
                     ) -> ModelRun:
        """The run with only its published detections (:meth:`published`)."""
        return replace(self, det=self.published(thresholds, carry_thresholds), carried=[])

    def scored_detections(self) -> list[Detections]:
        """The detections, less those on ignored things (:func:`drop_ignored`)."""
        if not self.ignore:
            return self.det
        num = self.num_points or [None] * len(self.det)
        return [d if ig is None else drop_ignored(d, g, ig, num_points=n)
                for d, g, ig, n in zip(self.det, self.gt, self.ignore, num)]

    def evaluate(self, class_names: Sequence[str],
                 ranges: dict[str, float] | None = None) -> EvalResult:
        """Metrics of the run, with latency p50 and memory p50 in ``extra``."""
        result = evaluate(self.gt, self.scored_detections(), class_names, ranges=ranges,
                          num_points=self.num_points)
        result.extra.update({'latency_p50_ms': round(float(np.median(self.latency_s)) * 1e3, 1),
                             'memory_bytes_p50': int(np.median(self.memory_bytes))})
        return result


def run_model(model: Any, sequences: Sequence[Sequence[Any]], device: Any = None,
              history: int | None = None, drop_memory: bool = False,
              transform: Callable[[Frame], Frame] | None = None,
              precision: PrecisionChoice = 'float32',
              tracker: TrackerConfig | None = None, ground: GroundMode | None = None,
              overhang: OverhangMode | None = None, box_fit: BoxFitMode = 'off',
              deskew: bool = False, run_every: int = 1, buffer_skipped: bool = True,
              max_gap_s: float = 0.5,
              traffic_side: TrafficSideParam | Sequence[TrafficSideParam] = 'right'
              ) -> ModelRun:
    """Run a SUITDetector over sequences of sensor frames (memory and sweeps carried within
    each, reset between them).

    :param history: None: stream each sequence with the memory carried throughout; ``h``: each
        frame is detected after a fresh run over its last ``h`` frames (h frames of history).
    :param drop_memory: forget the feature memory before every frame (the sweeps are kept):
        what the temporal path is worth.
    :param transform: applied to every input frame (e.g. intensity removed).
    :param precision: of the streaming detector (:mod:`suit_ros.model.inference`).
    :param tracker: the streaming detector's (:mod:`suit_ros.tracking`); None: the
        head's velocities.
    :param ground: the input's height reference (:mod:`suit_ros.ground`; None: as the
        checkpoint was trained).
    :param overhang: keep or drop the returns that hang (:mod:`suit_ros.overhang`; None: as
        the checkpoint says).
    :param box_fit: car boxes fitted to their visible faces or not (:mod:`suit_ros.box_fit`).
    :param deskew: move the returns of a sweep taken over time (frames with ``times``) to the
        sensor's pose at its stamp, by the motion over the sweep (:mod:`suit_ros.deskew`, as the
        node does with a time field and odometry; here the odometry is the frames' poses:
        :func:`deskewed`).
    :param run_every: the model runs on every this-many-th frame of a drive (the first, then
        each ``run_every``-th), as a node too slow for its sensor does; only those frames are
        in the run. The others are taken into the sweep buffer (``buffer_skipped``, as the
        node does) or dropped (a node that feeds the model only the clouds it runs on). As
        the node, it drops a memory older than ``max_gap_s`` (the node's parameter; at 10 Hz
        from ``run_every`` 6 on), the sweeps kept; with ``run_every`` 1 the gap is not read.
    :param traffic_side: as the node's parameter: ``left`` gives the model each drive mirrored
        (:func:`~suit_ros.data.augment.mirror_world`) and mirrors its boxes back; ``auto``
        starts right and goes on mirrored from the frame after the tracked oncoming vehicles
        say left (:mod:`suit_ros.traffic_side`; the memory and the tracks reset there, as in
        the node; without a ``tracker`` nothing votes and it stays right, as the node; not
        with ``history``); the GT is the drive's own; one side, or one per drive.
    """
    if run_every < 1:
        raise ValueError(f'run_every must be at least 1, got {run_every}')
    sides = ([traffic_side] * len(sequences) if isinstance(traffic_side, str)
             else list(traffic_side))
    if 'auto' in sides and history is not None:
        raise ValueError('traffic_side auto reads the side from tracks, which a history '
                         'window resets every frame: give the side')
    if not set(sides) <= {'auto', 'right', 'left'} or len(sides) != len(sequences):
        raise ValueError(f'traffic_side must be auto, right or left, or one per drive '
                         f'({len(sequences)}), got {traffic_side!r}')
    from suit_ros.model.streaming import StreamingDetector
    was_training = model.training
    runner = StreamingDetector(model, device, precision=precision,
                               tracker=tracker, ground=ground, overhang=overhang,
                               box_fit=box_fit)
    out = ModelRun([], [], [], [], [], {})
    from suit_ros.data.augment import mirror_detections
    from suit_ros.traffic_side import TrafficSideVote
    for drive, given in enumerate(sequences):
        runner.reset('new sequence')
        if transform is not None:
            given = [transform(f) for f in given]
        worlds = _DriveWorlds(given, deskew)
        vote = (TrafficSideVote(runner.cfg.class_names) if sides[drive] == 'auto' and
                tracker is not None else None)      # (untracked: no votes, as the node)
        side: TrafficSide = 'left' if sides[drive] == 'left' else 'right'
        for t in range(len(given)):
            frame = worlds[side][t]
            if t % run_every:
                if buffer_skipped:
                    runner.add_sweep(*step_inputs(frame))
                continue
            if run_every > 1:                   # as the node's pipeline
                runner.drop_stale_memory(frame.stamp_ns, max_gap_s)
            if drop_memory:
                runner.reset('drop memory', sweeps=False)
            if history is not None:
                runner.reset('window')
                for past in worlds[side][max(0, t - history + 1):t]:
                    runner.step(*step_inputs(past))
            res = runner.step(*step_inputs(frame))
            out.input_sweeps.append(_input_sweeps(frame, runner))
            out.latency_s.append(res.timings['total'])
            out.memory_bytes.append(res.memory_bytes)
            if history is None and t + 1 in (2, 10):
                out.memory_after.setdefault(t + 1, []).append(res.memory_bytes)
            det = (res.detections if side == 'right'             # in the drive's world
                   else mirror_detections(res.detections))
            out.det.append(det)
            out.sides.append(side)
            if vote is not None and vote.update(det.boxes, det.velocities, det.labels,
                                                res.track_ids, given[t].T_base_lidar,
                                                step_inputs(given[t])[2], given[t].stamp_ns):
                side = vote.side             # from the next frame on, as the node
                runner.reset('traffic side changed')
            out.carried.append(res.carried)
            out.used_memory.append(res.used_memory)
            out.gt.append(given[t].gt)
            out.num_points.append(given[t].num_points)
            out.drive.append(drive)
            out.ignore.append(given[t].ignore_boxes)
    model.train(was_training)
    return out


def _input_sweeps(frame: Frame, runner: Any) -> int:
    """The sweeps in the model's input of ``frame`` (just stepped): the buffer's, or for a
    frame accumulated already (a dataset's keyframe with its sweeps) its distinct time lags,
    at most the model's count (lags per return count as whole)."""
    from suit_ros.model.sweeps import already_accumulated
    if already_accumulated(frame.points):
        return int(min(len(np.unique(frame.points[:, 4])), runner.cfg.sweeps))
    return len(runner.sweeps.last_lags_s)


class _DriveWorlds:
    """One drive as the model is given it in right- and in left-hand traffic (mirrored,
    :func:`~suit_ros.data.augment.mirror_world`), each made when first asked for, deskewed
    where :func:`run_model` deskews."""

    def __init__(self, given: Sequence[Frame], deskew: bool) -> None:
        self.given, self.deskew = given, deskew
        self.worlds: dict[TrafficSide, list[Frame]] = {}

    def __getitem__(self, side: TrafficSide) -> list[Frame]:
        if side not in self.worlds:
            from suit_ros.data.augment import mirror_world
            frames = (list(self.given) if side == 'right'
                      else [mirror_world(f) for f in self.given])
            self.worlds[side] = deskewed(frames) if self.deskew else frames
        return self.worlds[side]


def tracker_for(sequences: Sequence[Sequence[Frame]], config: TrackerConfig | None = None
                ) -> TrackerConfig:
    """The tracker for an offline run over ``sequences``: ``config`` (default: the node's) with
    its ``max_gap_s`` widened to 2.5 frame intervals (the median within the sequences) where
    the frames come further apart than a LiDAR's. nuScenes keyframes are 2 Hz, about 0.5 s
    apart with jitter: at the node's 0.5 s, every keyframe that came a little late would drop
    every track. Sequence boundaries still reset the tracks. The lifetimes stay in seconds
    (``max_miss_s``, ``coast_s``): at 2 Hz a track outlives no missed keyframe."""
    from suit_ros.tracking import TrackerConfig
    cfg = config if config is not None else TrackerConfig()
    gaps = [b.stamp_ns - a.stamp_ns for seq in sequences for a, b in zip(seq[:-1], seq[1:])]
    positive = [g for g in gaps if g > 0]
    if not positive:
        return cfg
    widened = 2.5 * float(np.median(positive)) * 1e-9
    return replace(cfg, max_gap_s=widened) if widened > cfg.max_gap_s else cfg


def deskewed(seq: Sequence[Frame]) -> list[Frame]:
    """The frames of one drive with their sweeps deskewed (:func:`run_model`'s ``deskew``):
    each by the motion the frames' poses show over its sweep's own times (interpolated
    between frames; a sweep stamped at its end: from the frame before), as the node's odometry
    covers a sweep by the time it runs; ``times`` None after."""
    from suit_ros.deskew import deskew_sweep
    from suit_ros.msg_adapters.odometry import PoseBuffer
    poses = PoseBuffer(max_age_ns=2 ** 62, rewind_ns=None)   # offline: every pose kept
    for frame in seq:              # the odometry: every frame's pose, as the node has it by
        poses.add(*step_inputs(frame)[1:3])   # the end of a sweep (at 50 Hz; here 10 Hz)
    out = []
    for frame in seq:
        points, stamp, T_odom_base, T_bl = step_inputs(frame)
        if frame.times is not None:
            frame = replace(frame, points=deskew_sweep(points, frame.times, stamp, poses,
                                                       T_bl)[0], times=None)
        out.append(frame)
    return out


def step_inputs(frame: Frame) -> tuple[NDArray[np.float32], int, NDArray[np.float64],
                                        NDArray[np.float64]]:
    """A sensor frame as the streaming step's arguments: points, stamp, ``T_odom_base``,
    ``T_base_lidar``."""
    from suit_ros.ops.geometry import se3_inverse
    T_bl = np.asarray(frame.T_base_lidar, np.float64)
    return frame.points, frame.stamp_ns, np.asarray(frame.pose) @ se3_inverse(T_bl), T_bl


def evaluate_model(model: Any, sequences: Sequence[Sequence[Any]], device: Any = None,
                   history: int | None = None) -> EvalResult:
    """Run a model over sequences (see :func:`run_model`) and evaluate it."""
    return run_model(model, sequences, device, history).evaluate(model.cfg.class_names)


def dump_json(result: EvalResult, path: str) -> None:
    """Write ``result.to_json()`` (an undefined figure as null)."""
    from suit_ros.outputs import json_text
    with open(path, 'w', encoding='utf-8') as f:
        f.write(json_text(result.to_json()))
