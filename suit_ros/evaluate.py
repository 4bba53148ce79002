"""nuScenes-style detection metrics for the project's classes, and model evaluation.

Matching is greedy by descending score over all frames on BEV centre distance (0.5/1/2/4 m),
per-class evaluation ranges from the sensor, GT without LiDAR returns removed, AP as the
normalised area of the 101-point interpolated precision above min precision 0.1 from min recall
0.1, TP errors (ATE, ASE, AOE, AVE) at 2 m averaged over the recall range, as the nuScenes
devkit computes them. NDS here has no attribute term: NDS = (5 mAP + sum of the four
(1 - min(1, mTP))) / 9 instead of / 10.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
import json
from typing import Any

import numpy as np
from numpy.typing import NDArray

from suit_ros import CLASS_NAMES
from suit_ros.structures import Detections, Frame

DIST_THRESHOLDS = (0.5, 1.0, 2.0, 4.0)
TP_DIST = 2.0
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
        """Classes with GT in the evaluated frames; the others are shown as n/a and left out
        of mAP, the mTP errors and NDS (the devkit would count them as AP 0)."""
        present = tuple(c for c in self.class_names if self.num_gt[c] > 0)
        return present or self.class_names

    @property
    def class_ap(self) -> dict[str, float]:
        """Mean AP over the distance thresholds, per class."""
        return {c: float(np.mean(list(self.ap[c].values()))) for c in self.class_names}

    @property
    def mean_ap(self) -> float:
        """mAP over the evaluated classes."""
        return float(np.mean([self.class_ap[c] for c in self.evaluated]))

    @property
    def mean_tp(self) -> dict[str, float]:
        """mATE, mASE, mAOE, mAVE (means over the evaluated classes)."""
        return {TP_NAMES[k]: float(np.nanmean([self.tp[c][k] for c in self.evaluated]))
                for k in TP_METRICS}

    @property
    def nds(self) -> float:
        """NDS without the attribute term (denominator 9)."""
        tp = sum(1.0 - min(1.0, v) for v in self.mean_tp.values())
        return float((5.0 * self.mean_ap + tp) / 9.0)

    def summary(self) -> dict[str, Any]:
        """Flat numbers for logs and checkpoints."""
        out: dict[str, Any] = {'mAP': round(self.mean_ap, 4), 'NDS': round(self.nds, 4)}
        out.update({k: round(v, 4) for k, v in self.mean_tp.items()})
        out.update({f'AP_{c}': round(v, 4) for c, v in self.class_ap.items()})
        out['frames'] = self.num_frames
        out.update(self.extra)
        return out

    def to_json(self) -> dict[str, Any]:
        """Everything, JSON-serialisable."""
        return {'summary': self.summary(), 'nds_note': NDS_NOTE,
                'ap': {c: {str(k): v for k, v in d.items()} for c, d in self.ap.items()},
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
    if len(x) == 0:
        return x
    nan = np.isnan(x)
    sums = np.nancumsum(x.astype(np.float64))
    counts = np.cumsum(~nan)
    return np.divide(sums, counts, out=np.zeros_like(sums), where=counts != 0)


def _wrap_abs(a: NDArray[np.float64]) -> NDArray[np.float64]:
    d = (a + np.pi) % (2 * np.pi) - np.pi
    return np.asarray(np.abs(d), np.float64)


def _accumulate(gt: Sequence[Detections], det: Sequence[Detections], label: int,
                dist_th: float) -> tuple[ClassCurve, int]:
    gts = [g.boxes[g.labels == label] for g in gt]
    gvs = [g.velocities[g.labels == label] for g in gt]
    npos = int(sum(len(b) for b in gts))
    frame_idx, boxes, vels, scores = [], [], [], []
    for i, d in enumerate(det):
        m = d.labels == label
        frame_idx.append(np.full(int(m.sum()), i))
        boxes.append(d.boxes[m])
        vels.append(d.velocities[m])
        scores.append(d.scores[m])
    rec_interp = np.linspace(0, 1, 101)
    empty = ClassCurve(rec_interp, np.zeros(101), np.zeros(101),
                       {k: np.ones(101) for k in TP_METRICS})
    if npos == 0:
        return empty, 0
    fi = np.concatenate(frame_idx) if frame_idx else np.zeros(0, int)
    pb = np.concatenate(boxes) if boxes else np.zeros((0, 7))
    pv = np.concatenate(vels) if vels else np.zeros((0, 2))
    ps = np.concatenate(scores) if scores else np.zeros(0)
    order = np.argsort(-ps, kind='stable')
    taken = [np.zeros(len(b), bool) for b in gts]
    tp = np.zeros(len(order))
    errs: dict[str, list[float]] = {k: [] for k in TP_METRICS}
    conf_tp: list[float] = []
    for n, j in enumerate(order):
        g = gts[fi[j]]
        if len(g) == 0:
            continue
        d = np.hypot(g[:, 0] - pb[j, 0], g[:, 1] - pb[j, 1])
        d[taken[fi[j]]] = np.inf
        k = int(np.argmin(d))
        if d[k] < dist_th:
            taken[fi[j]][k] = True
            tp[n] = 1
            gb = g[k]
            errs['trans_err'].append(float(d[k]))
            errs['vel_err'].append(float(np.hypot(*(pv[j] - gvs[fi[j]][k]))))
            inter = np.prod(np.minimum(gb[3:6], pb[j, 3:6]))
            union = np.prod(gb[3:6]) + np.prod(pb[j, 3:6]) - inter
            errs['scale_err'].append(float(1 - inter / union))
            errs['orient_err'].append(float(_wrap_abs(np.array(pb[j, 6] - gb[6]))))
            conf_tp.append(float(ps[j]))
    if tp.sum() == 0:
        return empty, npos
    ctp = np.cumsum(tp)
    cfp = np.cumsum(1 - tp)
    prec = ctp / (ctp + cfp)
    rec = ctp / npos
    conf = ps[order]
    precision = np.interp(rec_interp, rec, prec, right=0)
    confidence = np.interp(rec_interp, rec, conf, right=0)
    ctp_conf = np.array(conf_tp)
    errors = {}
    for key in TP_METRICS:
        tmp = _cummean(np.array(errs[key]))
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


def evaluate(gt: Sequence[Detections], det: Sequence[Detections],
             class_names: Sequence[str] = CLASS_NAMES,
             ranges: dict[str, float] | None = None,
             num_points: Sequence[NDArray[np.uint32] | None] | None = None,
             max_boxes_per_frame: int = 500) -> EvalResult:
    """Evaluate detections against GT, frame by frame (both in each frame's sensor frame)."""
    if len(gt) != len(det):
        raise ValueError(f'{len(gt)} GT frames but {len(det)} detection frames')
    names = tuple(class_names)
    rng = ranges or CLASS_RANGES
    r = np.array([rng.get(c, 50.0) for c in names])
    gts, dets = [], []
    for i, (g, d) in enumerate(zip(gt, det)):
        npts = num_points[i] if num_points is not None else None
        gts.append(g.select(_filter(g, r, npts)))
        d = d.select(_filter(d, r, None))
        if len(d) > max_boxes_per_frame:
            d = d.select(np.argsort(-d.scores, kind='stable')[:max_boxes_per_frame])
        dets.append(d)
    ap: dict[str, dict[float, float]] = {}
    tp: dict[str, dict[str, float]] = {}
    curves: dict[str, dict[float, ClassCurve]] = {}
    num_gt: dict[str, int] = {}
    for label, c in enumerate(names):
        curves[c] = {}
        ap[c] = {}
        for th in DIST_THRESHOLDS:
            curve, npos = _accumulate(gts, dets, label, th)
            curves[c][th] = curve
            ap[c][th] = _ap(curve)
            num_gt[c] = npos
        tp[c] = {k: _tp(curves[c][TP_DIST], k) for k in TP_METRICS}
    return EvalResult(names, ap, tp, curves, num_gt, len(gt))


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

    def evaluate(self, class_names: Sequence[str]) -> EvalResult:
        """Metrics of the run, with latency p50 and memory p50 in ``extra``."""
        result = evaluate(self.gt, self.det, class_names, num_points=self.num_points)
        result.extra.update({'latency_p50_ms': round(float(np.median(self.latency_s)) * 1e3, 1),
                             'memory_bytes_p50': int(np.median(self.memory_bytes))})
        return result


def run_model(model: Any, sequences: Sequence[Sequence[Any]], device: Any = None,
              history: int | None = None, drop_memory: bool = False,
              transform: Callable[[Frame], Frame] | None = None) -> ModelRun:
    """Run a SUITDetector over sequences of sensor frames (memory and sweeps carried within
    each, reset between them).

    :param history: None: stream each sequence with the memory carried throughout; ``h``: each
        frame is detected after a fresh run over its last ``h`` frames (h frames of history).
    :param drop_memory: forget the feature memory before every frame (the sweeps are kept):
        what the temporal path is worth.
    :param transform: applied to every input frame (e.g. intensity removed).
    """
    from suit_ros.model.streaming import StreamingDetector
    was_training = model.training
    runner = StreamingDetector(model, device)
    out = ModelRun([], [], [], [], [], {})
    for drive, seq in enumerate(sequences):
        runner.reset('new sequence')
        if transform is not None:
            seq = [transform(f) for f in seq]
        for t, frame in enumerate(seq):
            if drop_memory:
                runner.reset('drop memory', sweeps=False)
            if history is not None:
                runner.reset('window')
                for past in seq[max(0, t - history + 1):t]:
                    runner.step(*step_inputs(past))
            res = runner.step(*step_inputs(frame))
            out.latency_s.append(res.timings['total'])
            out.memory_bytes.append(res.memory_bytes)
            if history is None and t + 1 in (2, 10):
                out.memory_after.setdefault(t + 1, []).append(res.memory_bytes)
            out.det.append(res.detections)
            out.gt.append(frame.gt)
            out.num_points.append(frame.num_points)
            out.drive.append(drive)
    model.train(was_training)
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
    """Write ``result.to_json()``."""
    with open(path, 'w', encoding='utf-8') as f:
        json.dump(result.to_json(), f, indent=2)
