"""The fair benchmark: speed/visibility buckets, per-drive bootstrap intervals, car motion."""
from __future__ import annotations

import numpy as np
import pytest

from suit_ros.accuracy import (
    RunMetrics,
    bootstrap,
    bucket_mask,
    bucket_matches,
    car_motion,
    drive_frames,
)
from suit_ros.evaluate import ModelRun
from suit_ros.structures import Detections

NAMES = ('car', 'truck', 'pedestrian', 'cyclist')


def dets(rows, vel=None, scores=None, labels=None) -> Detections:
    rows = np.asarray(rows, np.float64).reshape(-1, 7)
    n = len(rows)
    return Detections(rows, np.zeros((n, 2)) if vel is None else vel,
                      np.ones(n) if scores is None else scores,
                      np.zeros(n, np.int64) if labels is None else labels)


GT = dets([[10, 0, 0, 4, 2, 1.5, 0], [20, 5, 0, 4, 2, 1.5, 0]],
          vel=np.array([[5.0, 0.0], [0.0, 0.0]]))
NUM = np.array([3, 40], np.uint32)


def test_buckets_by_gt_speed_and_points():
    assert bucket_mask(GT, NUM, 'moving').tolist() == [True, False]
    assert bucket_mask(GT, NUM, 'vis 1-5').tolist() == [True, False]
    assert bucket_mask(GT, NUM, 'vis 6-20').tolist() == [False, False]
    assert bucket_mask(GT, NUM, 'vis >20').tolist() == [False, True]
    assert bucket_mask(GT, NUM, 'all').all()


def test_bucket_matches_ignore_detections_matched_outside_and_keep_false_positives():
    det = dets([[10.3, 0, 0, 4, 2, 1.5, 0], [20.2, 5, 0, 4, 2, 1.5, 0],
                [-30, 0, 0, 4, 2, 1.5, 0]], scores=np.array([0.9, 0.8, 0.7]))
    moving = bucket_mask(GT, NUM, 'moving')
    m = bucket_matches(GT, det, moving, 0, 2.0)
    assert m.npos == 1
    # the static car's detection is ignored, the unmatched one stays as a false positive
    assert m.scores.tolist() == pytest.approx([0.9, 0.7]) and m.tp.tolist() == [True, False]
    # a detection of another class near an out-of-bucket GT is not ignored
    ped = dets([[20.2, 5, 0, 0.7, 0.7, 1.7, 0]], labels=np.array([2]))
    assert len(bucket_matches(GT, ped, moving, 2, 2.0).scores) == 1
    # 3 m from the static car: a false positive at 2 m, ignored at 4 m where it matches it
    # (the bucket follows each threshold's matching, not a fixed radius)
    off = dets([[23.0, 5, 0, 4, 2, 1.5, 0]])
    assert bucket_matches(GT, off, moving, 0, 2.0).tp.tolist() == [False]
    assert len(bucket_matches(GT, off, moving, 0, 4.0).scores) == 0
    assert bucket_matches(GT, off, np.ones(2, bool), 0, 4.0).tp.tolist() == [True]


def test_a_class_absent_from_a_resample_leaves_its_means_out():
    """A class with GT in one drive only: resamples without that drive have no AP for it and
    no mAP (a mean over fewer classes is another quantity), instead of AP 0 and an mAP over
    the classes they happen to hold."""
    run = ModelRun([], [], [], [], [], {})
    for d in range(4):
        labels = np.array([0, 1]) if d == 0 else np.array([0])
        g = dets([[10, 0, 0, 4, 2, 1.5, 0], [20, 5, 0, 8, 2.5, 3, 0]][:len(labels)],
                 labels=labels)
        run.gt.append(g)
        det = dets(g.boxes + [0.1, 0, 0, 0, 0, 0, 0], scores=np.full(len(g), 0.9),
                   labels=labels)
        if d == 0:                       # the truck found half as surely as it is missed
            det = dets(np.r_[det.boxes, [[20, 25, 0, 8, 2.5, 3, 0]]],
                       scores=np.array([0.9, 0.5, 0.9]), labels=np.array([0, 1, 1]))
        run.det.append(det)
        run.num_points.append(np.full(len(g), 30, np.uint32))
        run.drive.append(d)
    stats, _ = bootstrap({'a': run}, NAMES, resamples=200)
    truck = stats['a']['AP truck']
    assert 0 < truck.value < 1
    assert truck.low > 0.1                          # no resample scores it 0
    mAP = stats['a']['mAP']                         # every resample's over car and truck
    assert mAP.value == pytest.approx((1.0 + truck.value) / 2) and mAP.high < 1.0
    assert np.isnan(RunMetrics(run, NAMES)([1, 2, 3])['AP truck'])
    # how many resamples were left out is kept and said: about (3/4)^4 of 200 lack drive 0
    from suit_ros.accuracy import left_out_counts
    assert 30 < truck.left_out == mAP.left_out < 100 and stats['a']['AP car'].left_out == 0
    counts = left_out_counts(stats)['a']
    assert counts['AP truck'] == truck.left_out and 'AP car' not in counts
    from suit_ros.compare import Comparison, _left_out
    meta = {'resamples': 200}
    line = _left_out(Comparison(stats, {}, {}, {}, meta, list(NAMES)))[-1]
    assert f'AP truck {truck.left_out}' in line and 'of 200' in line
    held = Comparison({}, {}, {}, {}, meta, list(NAMES), heldout=stats)   # its own line
    assert _left_out(held) == [] and _left_out(held, heldout=True)[-1] == line
    full = make_run(True)
    assert _left_out(Comparison(bootstrap({'a': full}, NAMES[:1], resamples=20)[0], {}, {},
                                {}, meta, list(NAMES[:1]))) == []


def make_run(good: bool, drives: int = 4, frames: int = 3, seed: int = 0) -> ModelRun:
    rng = np.random.default_rng(seed)
    run = ModelRun([], [], [], [], [], {})
    for d in range(drives):
        for _ in range(frames):
            x = rng.uniform(5, 30, 3)
            g = dets(np.c_[x, np.zeros((3, 2)), np.tile([4, 2, 1.5, 0], (3, 1))],
                     vel=np.c_[np.full(3, 4.0), np.zeros(3)])
            run.gt.append(g)
            if good:
                run.det.append(dets(g.boxes + [0.1, 0, 0, 0, 0, 0, 0], vel=g.velocities,
                                    scores=np.full(3, 0.9)))
            else:   # boxes 3 m off: all false positives
                run.det.append(dets(g.boxes + [3.0, 0, 0, 0, 0, 0, 0], scores=np.full(3, 0.9)))
            run.num_points.append(np.full(3, 30, np.uint32))
            run.drive.append(d)
    return run


def test_bootstrap_intervals_and_paired_differences():
    runs = {'good': make_run(True), 'bad': make_run(False), 'same': make_run(True)}
    assert [len(f) for f in drive_frames(runs['good'])] == [3, 3, 3, 3]
    stats, diffs = bootstrap(runs, NAMES, [('good', 'bad'), ('good', 'same')], resamples=30)
    assert stats['good']['mAP'].value > 0.9 and stats['bad']['mAP'].value < 0.5
    iv = stats['good']['mAP']
    assert iv.low <= iv.value <= iv.high
    assert diffs['good - bad']['mAP'].low > 0.3               # holds in every resample
    from suit_ros.accuracy import plain_intervals
    as_json = plain_intervals(diffs)
    assert as_json['good - bad']['mAP'] == [diffs['good - bad']['mAP'].value,
                                            diffs['good - bad']['mAP'].low,
                                            diffs['good - bad']['mAP'].high]
    same = diffs['good - same']['mAP']
    assert same.value == same.low == same.high == 0.0         # identical runs: exactly zero
    assert stats['good']['moving car vel err'].value == pytest.approx(0.0, abs=1e-6)
    assert '[' in stats['good']['mAP'].fmt()


def test_car_motion_heading_and_flips():
    g = dets([[10, 0, 0, 4, 2, 1.5, 0.5], [20, 0, 0, 4, 2, 1.5, 0.0]],
             vel=np.array([[6.0, 0.0], [0.0, 0.0]]))
    d = dets([[10.2, 0, 0, 4, 2, 1.5, 0.5 + np.pi], [20.1, 0, 0, 4, 2, 1.5, 0.1]],
             vel=np.array([[5.0, 0.0], [0.0, 0.0]]), scores=np.array([0.9, 0.8]))
    m = car_motion([g], [d], 0)
    assert m['car flipped %'] == pytest.approx(50.0)
    assert m['car heading err'] == pytest.approx((np.pi + 0.1) / 2, abs=1e-5)
    assert m['moving car vel err'] == pytest.approx(1.0, abs=1e-6)
    assert m['moving car speed ratio'] == pytest.approx(5 / 6, abs=1e-6)
    assert np.isnan(m['moving car speed slope'])                  # one moving car: no slope


def test_car_motion_speed_slope_reads_whether_speed_follows_gt():
    """Slope 1 and correlation 1 when predicted speed follows GT speed (even with an offset);
    slope 0 when every moving car gets the same speed; along-track only (a sideways error does
    not count as speed)."""
    speeds = np.array([3.0, 6.0, 9.0, 12.0])
    boxes = [[10.0 * (i + 1), 0, 0, 4, 2, 1.5, 0.0] for i in range(4)]
    g = dets(boxes, vel=np.c_[speeds, np.zeros(4)])

    def motion(pred):
        d = dets(boxes, vel=pred, scores=np.full(4, 0.9))
        return car_motion([g], [d], 0)
    m = motion(np.c_[speeds + 1.0, np.full(4, 2.0)])
    assert m['moving car speed slope'] == pytest.approx(1.0)
    assert m['moving car speed corr'] == pytest.approx(1.0)
    m = motion(np.c_[np.full(4, 7.0), np.zeros(4)])
    assert m['moving car speed slope'] == pytest.approx(0.0)
    assert m['moving car speed corr'] == 0.0
    m = motion(np.c_[0.5 * speeds, np.zeros(4)])
    assert m['moving car speed slope'] == pytest.approx(0.5)
    # low-score detections and far ones are not matched
    low = dets([[10.2, 0, 0, 4, 2, 1.5, 0.5]], scores=np.array([0.1]))
    assert np.isnan(car_motion([g], [low], 0)['car heading err'])


@pytest.mark.slow
def test_past_share_is_zero_at_init_and_grows_with_the_past_weights():
    import torch

    from suit_ros.accuracy import past_share
    from suit_ros.config import BackboneConfig, ModelConfig, PillarConfig, SamplingConfig
    from suit_ros.model.detector import SUITDetector
    from suit_ros.ops.geometry import pose_from_xyz_rpy
    from suit_ros.structures import Frame
    torch.manual_seed(0)
    cfg = ModelConfig(temporal='sparse',
                      pillars=PillarConfig(point_range=(-25.6, -25.6, -2.0, 25.6, 25.6, 4.0),
                                           channels=8),
                      backbone=BackboneConfig(num_filters=(8, 8, 8),
                                              num_upsample_filters=(8, 8, 8)),
                      sampling=SamplingConfig(top_k=5000))
    model = SUITDetector(cfg).eval()
    with torch.no_grad():                 # every cell significant: the memory covers the map
        model.head.heatmap[-1].bias.fill_(5.0)
    rng = np.random.default_rng(0)
    frames = []
    for t in range(4):
        pts = np.c_[rng.uniform(-20, 20, (2000, 2)), rng.uniform(0, 2, 2000),
                    rng.uniform(0, 1, 2000), np.zeros(2000)].astype(np.float32)
        pts[:300, :2] = rng.normal([5, 3], 0.6, (300, 2))
        gt = dets([[5, 3, 0.8, 4, 2, 1.5, 0]])
        frames.append(Frame(pts, pose_from_xyz_rpy((0.5 * t, 0, 0), (0, 0, 0)),
                            int(1e9 + t * 1e8), gt=gt, num_points=np.array([300], np.uint32)))
    zero = past_share(model, [frames])
    assert zero['cells'] == 3 and zero['past share'] == 0.0     # W2 starts at zero
    with torch.no_grad():
        model.fusion.past.weight.copy_(torch.eye(model.fusion.past.weight.shape[0]))
    grown = past_share(model, [frames])
    assert grown['past share'] > 0.0


def test_cached_matches_equal_a_fresh_evaluation_on_any_selection():
    from suit_ros.accuracy import RunMetrics
    from suit_ros.evaluate import evaluate
    run = make_run(True, drives=3, frames=4, seed=3)
    rng = np.random.default_rng(1)
    for i in range(len(run.det)):          # some misses, some far detections
        d = run.det[i]
        run.det[i] = dets(d.boxes + rng.normal(0, 1.2, d.boxes.shape) * [1, 1, 0, 0, 0, 0, 0],
                          vel=d.velocities, scores=rng.uniform(0.1, 1, len(d)))
    cached = RunMetrics(run, NAMES)
    for frames in (None, [0, 1, 2, 3], [5, 5, 7, 11, 0]):
        idx = range(len(run.gt)) if frames is None else frames
        fresh = evaluate([run.gt[i] for i in idx], [run.det[i] for i in idx], NAMES,
                         num_points=[run.num_points[i] for i in idx])
        got = cached(frames)
        assert got['mAP'] == pytest.approx(fresh.mean_ap, abs=1e-12)
        assert got['NDS'] == pytest.approx(fresh.nds, abs=1e-12)
        assert got['mATE'] == pytest.approx(fresh.mean_tp['mATE'], abs=1e-12)


def test_run_metrics_score_what_evaluation_scores():
    """RunMetrics (compare, outage, the report's intervals) scores the frames as `eval` does:
    detections on ignored things are neither true nor false positives, and the car heading
    figures leave out cars that are not scored (no returns, out of range)."""
    from suit_ros.accuracy import RunMetrics
    gt = dets([[10, 0, 0, 4, 2, 1.5, 0], [80, 0, 0, 4, 2, 1.5, 0], [-20, 0, 0, 4, 2, 1.5, 0]])
    det = dets([[10.2, 0, 0, 4, 2, 1.5, 0],
                [80.1, 0, 0, 4, 2, 1.5, np.pi],      # beyond 50 m, turned round
                [-20.1, 0, 0, 4, 2, 1.5, np.pi],     # turned round on a car with no returns
                [0, 15, 0, 4, 2, 1.5, 0]],           # on a parked bicycle (ignored)
               scores=np.array([0.9, 0.8, 0.7, 0.95]))
    run = ModelRun([gt], [det], [np.array([30, 30, 0], np.uint32)], [0.1], [0], {}, [0],
                   [np.array([[0, 15, 0, 1.7, 0.6, 1.0, 0]], np.float32)])
    got = RunMetrics(run, NAMES)()
    assert got['mAP'] == pytest.approx(run.evaluate(NAMES).mean_ap, abs=1e-12)
    no_ignore = ModelRun([gt], [det], run.num_points, [0.1], [0], {}, [0])
    assert got['AP car'] > RunMetrics(no_ignore, NAMES)()['AP car']   # the bicycle's box
    assert got['car flipped %'] == 0.0


def test_the_left_out_line_groups_the_runs_that_leave_out_the_same():
    """Most runs of the ablation share their drives' count (mAP vis 1-5 4 of 100): the line
    names the few that differ and counts the rest, rather than one entry a run."""
    from suit_ros.accuracy import Interval
    from suit_ros.compare import Comparison, _left_out
    stats = {f'run {k}': {'mAP vis 1-5': Interval(0.1, 0.0, 0.2, 4),
                          'mAP': Interval(0.5, 0.4, 0.6)} for k in range(10)}
    stats['world'] = {'mAP vis 1-5': Interval(0.1, 0.0, 0.2, 12)}
    stats['none'] = {'mAP': Interval(0.5, 0.4, 0.6)}
    line = _left_out(Comparison(stats, {}, {}, {}, {'resamples': 100}, ['car']))[-1]
    assert line.endswith('of 100: mAP vis 1-5 12: `world`; mAP vis 1-5 4: the other 10 runs.')
    few = {k: v for k, v in stats.items() if k in ('run 0', 'run 1', 'world')}
    line = _left_out(Comparison(few, {}, {}, {}, {'resamples': 100}, ['car']))[-1]
    assert line.endswith(': mAP vis 1-5 12: `world`; mAP vis 1-5 4: `run 0`, `run 1`.')
    # a larger group that is not the largest: by the variants its runs are
    worlds = {f'{c}, {t}{w}': {'mAP vis 1-5': Interval(0.1, 0.0, 0.2, 12)}
              for c in ('single', 'suit') for t in ('', 'tracking, ') for w in ('dark', 'ends')}
    worlds['suit, dark - single, dark'] = worlds['suit, dark']
    plain = {f'{c}{v}': {'mAP vis 1-5': Interval(0.1, 0.0, 0.2, 4)}
             for c in ('single', 'suit') for v in ('', ', tracking', ', a', ', b', ', c')}
    meta = {'resamples': 100, 'checkpoints': {'single': 'x', 'suit': 'y'}}
    line = _left_out(Comparison({**worlds, **plain}, {}, {}, {}, meta, ['car']))[-1]
    assert line.endswith(': mAP vis 1-5 12: dark, ends (8 runs and 1 difference); '
                         'mAP vis 1-5 4: the other 10 runs.')
