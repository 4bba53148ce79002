"""AP intervals over places (suit_ros.place_bootstrap): a small real set's uncertainty."""
from __future__ import annotations

import numpy as np
import pytest

from suit_ros.evaluate import evaluate
from suit_ros.place_bootstrap import ap_intervals, cut_into_places, place_keys
from suit_ros.structures import Detections

NAMES = ('car', 'pedestrian')


def boxes(xy, scores=None, labels=None):
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    n = len(xy)
    b = np.zeros((n, 7))
    b[:, :2] = xy
    b[:, 3:6] = (4.5, 1.9, 1.6)
    return Detections(b, np.zeros((n, 2)), np.full(n, 0.9) if scores is None
                      else np.asarray(scores, np.float64),
                      np.zeros(n, np.int64) if labels is None else np.asarray(labels))


def scene(seed, miss=0.2, jitter=0.4, false=6):
    """Two sweeps of one street: cars and pedestrians, a detector that misses some, places
    its boxes within ``jitter`` m and adds false boxes."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-45, 45, (30, 2))
    labels = (rng.random(30) < 0.3).astype(np.int64)
    gts, dets, npts = [], [], []
    for _ in range(2):
        gts.append(boxes(xy, labels=labels))
        found = rng.random(30) > miss
        fp = rng.uniform(-45, 45, (false, 2))
        dets.append(boxes(np.concatenate([xy[found] + rng.normal(0, jitter, (found.sum(), 2)),
                                          fp]),
                          scores=np.concatenate([rng.uniform(0.3, 1.0, found.sum()),
                                                 rng.uniform(0.1, 0.6, false)]),
                          labels=np.concatenate([labels[found], rng.integers(0, 2, false)])))
        npts.append(np.full(30, 50, np.uint32))
    return gts, dets, npts


def test_a_box_goes_with_the_object_it_could_match_across_a_cell_edge():
    gt = boxes([[19.5, 5.0], [70.0, 5.0]])
    det = boxes([[20.5, 5.0], [30.0, 5.0], [75.0, 5.0]])
    g_key, d_key = place_keys(gt, det, cell=20.0)
    assert g_key.tolist() == [[0, 0], [3, 0]]
    # 1 m from the first object but over the edge: with it; 10 m from any: its own cell;
    # 5 m from the second: more than REACH, its own cell
    assert d_key.tolist() == [[0, 0], [1, 0], [3, 0]]


def test_all_places_once_give_the_ap_of_the_whole_set():
    gts, dets, npts = scene(0)
    places = cut_into_places(gts, [dets], npts)
    iv = ap_intervals(places, NAMES, 50.0, resamples=200)
    whole = evaluate(gts, dets, NAMES, dict.fromkeys(NAMES, 50.0), npts).class_ap
    for c in NAMES:
        assert iv.ap[c][0] == pytest.approx(whole[c], abs=1e-9)
        lo, hi = iv.interval[c][0]
        assert lo <= whole[c] <= hi and hi - lo > 0.02        # a small set is uncertain
    assert iv.places == len(places) > 10


def test_a_run_against_itself_differs_by_nothing_and_a_worse_one_shows():
    gts, dets, npts = scene(1)
    _, worse, _ = scene(1, miss=0.5, jitter=1.2, false=20)
    same = ap_intervals(cut_into_places(gts, [dets, dets], npts), NAMES, 50.0, resamples=100)
    assert same.difference['car'] == (0.0, (0.0, 0.0))
    paired = ap_intervals(cut_into_places(gts, [dets, worse], npts), NAMES, 50.0,
                          resamples=300)
    diff, (lo, hi) = paired.difference['car']
    assert diff == pytest.approx(paired.ap['car'][0] - paired.ap['car'][1])
    assert diff > 0.1 and lo > 0                               # the better run, resolved


def test_an_empty_set_has_no_place():
    places = cut_into_places([Detections.empty()], [[Detections.empty()]], [None])
    assert len(places) == 0
    iv = ap_intervals(places, NAMES, 50.0, resamples=10)
    assert np.isnan(iv.interval['car'][0][0])


def test_only_what_is_scored_makes_a_place():
    """Objects beyond the range or without returns, and boxes beyond the range, are not
    scored: the places they alone would fill are not places (they widened the interval)."""
    gts, dets, npts = scene(3)
    base = cut_into_places(gts, [dets], npts, class_names=NAMES, max_range=50.0)
    far = [Detections(np.r_[g.boxes, [[300.0 + 25 * k, 0, 0, 4.5, 1.9, 1.6, 0]
                                      for k in range(10)]],
                      np.zeros((len(g) + 10, 2)), np.ones(len(g) + 10),
                      np.r_[g.labels, np.zeros(10, np.int64)]) for g in gts]
    dark = [np.r_[n, np.zeros(10, np.uint32)] for n in npts]
    assert len(cut_into_places(far, [dets], dark, class_names=NAMES, max_range=50.0)) == \
        len(base)
    assert len(cut_into_places(far, [dets], dark)) > len(base)        # unfiltered: the old way
    a = ap_intervals(base, NAMES, 50.0, resamples=50)
    b = ap_intervals(cut_into_places(far, [dets], dark, class_names=NAMES, max_range=50.0),
                     NAMES, 50.0, resamples=50)
    assert a.interval == b.interval and a.ap == b.ap


def test_a_class_in_one_place_gets_no_interval():
    """One truck seen in two sweeps is one place: a resample holds it or not, so its AP draws
    say nothing of how AP varies over places; no interval (it read [0.850, 0.852], and before
    an absent class had AP 0, [0.000, 0.852])."""
    gts, dets, npts = scene(5)
    truck = [Detections(np.r_[g.boxes, [[30.0, -30.0, 0, 8, 2.5, 3, 0]]],
                        np.zeros((len(g) + 1, 2)), np.ones(len(g) + 1), np.r_[g.labels, 2])
             for g in gts]
    found = [Detections(np.r_[d.boxes, [[30.2, -30.0, 0, 8, 2.5, 3, 0]]],
                        np.zeros((len(d) + 1, 2)), np.r_[d.scores, 0.8], np.r_[d.labels, 2])
             for d in dets]
    pts = [np.r_[n, 50].astype(np.uint32) for n in npts]
    names = NAMES + ('truck',)
    iv = ap_intervals(cut_into_places(truck, [found, found], pts, class_names=names,
                                      max_range=50.0), names, 50.0, resamples=50)
    assert iv.ap['truck'][0] > 0.5 and all(np.isnan(iv.interval['truck'][0]))
    assert np.isnan(iv.difference['truck'][1][0]) and iv.difference['truck'][0] == 0.0
    assert not np.isnan(iv.interval['car'][0][0])


def test_resamples_without_a_class_are_counted():
    """A class in two places of many: the resamples that draw neither leave its AP undefined;
    the interval leaves them out and says how many (about e^-2 of them)."""
    gts, dets, npts = scene(5)
    trucks = np.array([[30.0, -30.0, 0, 8, 2.5, 3, 0], [-30.0, 30.0, 0, 8, 2.5, 3, 0]])
    gt = [Detections(np.r_[g.boxes, trucks], np.zeros((len(g) + 2, 2)), np.ones(len(g) + 2),
                     np.r_[g.labels, 2, 2]) for g in gts]
    found = [Detections(np.r_[d.boxes, trucks + [0.2, 0, 0, 0, 0, 0, 0]],
                        np.zeros((len(d) + 2, 2)), np.r_[d.scores, 0.8, 0.7],
                        np.r_[d.labels, 2, 2])
             for d in dets]
    pts = [np.r_[n, 50, 50].astype(np.uint32) for n in npts]
    names = NAMES + ('truck',)
    iv = ap_intervals(cut_into_places(gt, [found], pts, class_names=names, max_range=50.0),
                      names, 50.0, resamples=200)
    assert 5 < iv.left_out['truck'] < 80 and 'car' not in iv.left_out
    assert not np.isnan(iv.interval['truck'][0][0])
