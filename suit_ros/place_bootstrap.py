"""How much a small labelled set can tell: AP intervals by resampling places, not frames.

A real dev set of two consecutive sweeps holds the same objects twice; resampling its frames
(as the synthetic benchmark resamples drives, :mod:`suit_ros.accuracy`) would say nothing. What
varies from one street to the next is which objects are there, so the resampling unit here is a
*place*: the scene is cut into ``cell`` x ``cell`` m squares of the sensor frame; a labelled
object belongs to the square its centre is in, and a detection to the square of the nearest
labelled object within :data:`REACH` m (the largest match distance: a box and the object it
could match stay together), else to its own. Every frame's share of a place goes with it, so
an object seen in both sweeps is drawn (or not) once (squares are cut in each sweep's sensor
frame: while the vehicle moves, an object near an edge may fall on either side in two sweeps).

Each resample draws as many places as there are, with replacement, and recomputes AP per class
from matches made once (:class:`~suit_ros.accuracy.RunMetrics`). With a baseline the same
draws score both runs: the interval of their difference is paired. Places that hold only false
positives are places too: a street full of sidewalk furniture weighs as it should.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from suit_ros.evaluate import ModelRun
from suit_ros.structures import Detections

REACH = 4.0                     # m: a detection goes with the nearest labelled object this near
CELL = 20.0                     # m: the side of a place
MIN_PLACES = 2                  # places holding a class for its AP to get an interval


def place_keys(gt: Detections, det: Detections, cell: float = CELL
               ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The place of every labelled object ``(G, 2)`` and every detection ``(D, 2)`` of one
    frame: integer cell coordinates (see the module docstring)."""
    g_key = np.floor(gt.boxes[:, :2] / cell).astype(np.int64).reshape(-1, 2)
    d_key = np.floor(det.boxes[:, :2] / cell).astype(np.int64).reshape(-1, 2)
    if len(gt) and len(det):
        d = np.hypot(det.boxes[:, None, 0] - gt.boxes[None, :, 0],
                     det.boxes[:, None, 1] - gt.boxes[None, :, 1])
        nearest = np.argmin(d, axis=1)
        near = d[np.arange(len(det)), nearest] <= REACH
        d_key[near] = g_key[nearest[near]]
    return g_key, d_key


@dataclass
class Places:
    """Runs cut into places: one piece (a pseudo-frame) per place and frame, the same pieces
    in every run (:func:`cut_into_places`)."""

    runs: list[ModelRun]
    pieces: list[list[int]]          # per place, the indices of its pieces

    def __len__(self) -> int:
        return len(self.pieces)


def cut_into_places(gt: Sequence[Detections], dets: Sequence[Sequence[Detections]],
                    num_points: Sequence[NDArray[np.uint32] | None],
                    cell: float = CELL, class_names: Sequence[str] | None = None,
                    max_range: float | None = None) -> Places:
    """Cut the frames' labels ``gt`` and each run's detections (``dets[r][frame]``, the
    scored ones: ignored objects' boxes already dropped) into places. With ``class_names``
    and ``max_range`` only what is scored is cut (:func:`~suit_ros.evaluate.filter_frames`:
    in range, labels with returns), so a place that holds nothing scored is not a place."""
    if max_range is not None:
        from suit_ros.evaluate import filter_frames
        ranges = dict.fromkeys(class_names or (), float(max_range))
        cut = [filter_frames(gt, d, class_names or (), ranges, num_points) for d in dets]
        if cut:
            gt, num_points = cut[0][0], cut[0][2]
            dets = [c[1] for c in cut]
    keyed: list[tuple[int, int, int]] = []          # (place x, place y, frame)
    owners: list[list[tuple[NDArray[np.int64], NDArray[np.int64]]]] = []
    for i, g in enumerate(gt):
        per_run = []
        for run_dets in dets:
            g_key, d_key = place_keys(g, run_dets[i], cell)
            per_run.append((g_key, d_key))
            keyed += [(int(x), int(y), i) for x, y in np.concatenate([g_key, d_key])]
        owners.append(per_run)
    order = sorted(set(keyed))
    places = sorted({(x, y) for x, y, _ in order})
    place_index = {p: k for k, p in enumerate(places)}
    pieces: list[list[int]] = [[] for _ in places]
    runs = [ModelRun([], [], [], [], [], {}) for _ in dets]
    for x, y, i in order:
        pieces[place_index[x, y]].append(len(runs[0].gt))
        for r, run_dets in enumerate(dets):
            g_key, d_key = owners[i][r]
            g_in = (g_key[:, 0] == x) & (g_key[:, 1] == y)
            d_in = (d_key[:, 0] == x) & (d_key[:, 1] == y)
            runs[r].gt.append(gt[i].select(g_in))
            runs[r].det.append(run_dets[i].select(d_in))
            n = num_points[i]
            runs[r].num_points.append(None if n is None else n[g_in])
    return Places(runs, pieces)


@dataclass
class APIntervals:
    """Per class: the AP of each run over all places and the 95% interval over place
    resamples; with a baseline (the second run) the paired difference and its interval."""

    ap: dict[str, list[float]]
    interval: dict[str, list[tuple[float, float]]]
    difference: dict[str, tuple[float, tuple[float, float]]]
    places: int
    resamples: int
    # per class: resamples holding none of its objects (AP undefined), left out of its
    # intervals; absent where none was
    left_out: dict[str, int] = field(default_factory=dict)


def ap_intervals(places: Places, class_names: Sequence[str], max_range: float,
                 resamples: int = 500, seed: int = 0) -> APIntervals:
    """AP per class with 95% intervals over resampled places (see the module docstring); the
    difference is run 0 minus run 1 when there are two."""
    from suit_ros.accuracy import RunMetrics
    names = tuple(class_names)
    if len(places) == 0:                    # nothing labelled, nothing detected
        nan = float('nan')
        return APIntervals({c: [nan] * len(places.runs) for c in names},
                           {c: [(nan, nan)] * len(places.runs) for c in names},
                           dict.fromkeys(names, (nan, (nan, nan))) if len(places.runs) == 2
                           else {}, 0, resamples)
    ranges = dict.fromkeys(names, float(max_range))
    metrics = [RunMetrics(r, names, ranges) for r in places.runs]
    everything = [k for piece in places.pieces for k in piece]
    full = [m(everything) for m in metrics]
    rng = np.random.default_rng(seed)
    draws: list[list[dict[str, float]]] = [[] for _ in metrics]
    for _ in range(resamples):
        chosen = rng.integers(0, len(places), len(places))
        frames = [k for p in chosen for k in places.pieces[p]]
        for r, m in enumerate(metrics):
            draws[r].append(m(frames))

    def bounds(values: list[float]) -> tuple[float, float]:
        v = np.asarray(values, np.float64)
        v = v[np.isfinite(v)]
        if len(v) == 0:
            return float('nan'), float('nan')
        return float(np.percentile(v, 2.5)), float(np.percentile(v, 97.5))

    out = APIntervals({}, {}, {}, len(places), resamples)
    gt = places.runs[0].gt
    for label, c in enumerate(names):
        key = f'AP {c}'
        out.ap[c] = [f[key] for f in full]
        # a class in one place only: a resample holds it once or not at all, and its AP
        # draws say nothing of how it varies from place to place: no interval
        holding = sum(any((gt[k].labels == label).any() for k in piece)
                      for piece in places.pieces)
        if holding < MIN_PLACES:
            unknown = (float('nan'), float('nan'))
            out.interval[c] = [unknown] * len(metrics)
            if len(metrics) == 2:
                out.difference[c] = (full[0][key] - full[1][key], unknown)
            continue
        out.interval[c] = [bounds([d[key] for d in run_draws]) for run_draws in draws]
        lacking = sum(not np.isfinite(d[key]) for d in draws[0])
        if lacking:
            out.left_out[c] = lacking
        if len(metrics) == 2:
            out.difference[c] = (full[0][key] - full[1][key],
                                 bounds([a[key] - b[key] for a, b in zip(*draws)]))
    return out
