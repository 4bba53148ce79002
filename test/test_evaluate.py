"""Our nuScenes-style metrics agree with nuscenes-devkit's own functions to 1e-6."""
from __future__ import annotations

import numpy as np
import pytest

from suit_ros.evaluate import DIST_THRESHOLDS, TP_METRICS, ModelRun, evaluate
from suit_ros.structures import Detections

NAMES = ('car', 'truck', 'pedestrian', 'cyclist')
DEVKIT_NAMES = {'car': 'car', 'truck': 'truck', 'pedestrian': 'pedestrian',
                'cyclist': 'bicycle'}


def scene(rng, frames=12):
    gts, dets = [], []
    for _ in range(frames):
        n = int(rng.integers(0, 12))
        boxes = np.c_[rng.uniform(-30, 30, (n, 2)), rng.uniform(-1, 1, n),
                      rng.uniform(0.5, 6, (n, 3)), rng.uniform(-np.pi, np.pi, n)]
        gt = Detections(boxes, rng.normal(0, 3, (n, 2)), np.ones(n), rng.integers(0, 4, n))
        keep = rng.random(n) < 0.8                                     # misses
        noisy = boxes[keep] + np.c_[rng.normal(0, 0.8, (keep.sum(), 2)),
                                    rng.normal(0, 0.2, (keep.sum(), 4)),
                                    rng.normal(0, 0.4, keep.sum())]
        noisy[:, 3:6] = np.abs(noisy[:, 3:6]) + 0.1
        m = int(rng.integers(0, 5))                                     # false positives
        fp = np.c_[rng.uniform(-30, 30, (m, 2)), np.zeros(m), rng.uniform(1, 4, (m, 3)),
                   rng.uniform(-3, 3, m)]
        boxes_d = np.concatenate([noisy, fp])
        k = len(boxes_d)
        lab = np.concatenate([gt.labels[keep], rng.integers(0, 4, m)])
        lab = np.where(rng.random(k) < 0.05, rng.integers(0, 4, k), lab)   # wrong class
        det = Detections(boxes_d, np.concatenate([gt.velocities[keep], rng.normal(0, 3, (m, 2))])
                         + rng.normal(0, 0.5, (k, 2)), rng.uniform(0, 1, k), lab)
        gts.append(gt)
        dets.append(det)
    return gts, dets


def to_devkit(frames, is_gt):
    from nuscenes.eval.common.data_classes import EvalBoxes
    from nuscenes.eval.detection.data_classes import DetectionBox
    boxes = EvalBoxes()
    for i, f in enumerate(frames):
        items = []
        for b, v, s, lab in zip(f.boxes.astype(float), f.velocities.astype(float),
                                f.scores.astype(float), f.labels):
            yaw = float(b[6])
            items.append(DetectionBox(
                sample_token=f's{i}', translation=tuple(b[:3]), size=(b[4], b[3], b[5]),
                rotation=(np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)), velocity=tuple(v),
                ego_translation=tuple(b[:3]), num_pts=10,
                detection_name=DEVKIT_NAMES[NAMES[lab]],
                detection_score=-1.0 if is_gt else float(s), attribute_name=''))
        boxes.add_boxes(f's{i}', items)
    return boxes


@pytest.mark.parametrize('seed', [0, 1, 2, 3])
def test_matches_nuscenes_devkit(seed):
    from nuscenes.eval.common.utils import center_distance
    from nuscenes.eval.detection.algo import accumulate, calc_ap, calc_tp
    rng = np.random.default_rng(seed)
    gts, dets = scene(rng)
    ours = evaluate(gts, dets, NAMES, ranges=dict.fromkeys(NAMES, 1000000000.0))
    gt_boxes, pred_boxes = to_devkit(gts, True), to_devkit(dets, False)
    for c in NAMES:
        for th in DIST_THRESHOLDS:
            md = accumulate(gt_boxes, pred_boxes, DEVKIT_NAMES[c], center_distance, th)
            assert ours.ap[c][th] == pytest.approx(calc_ap(md, 0.1, 0.1), abs=1e-6), (c, th)
            if th == 2.0:
                for k in TP_METRICS:
                    ref = calc_tp(md, 0.1, k)
                    assert ours.tp[c][k] == pytest.approx(ref, abs=1e-6), (c, k)


@pytest.mark.parametrize('seed', [0, 1])
def test_unknown_gt_velocities_score_as_the_devkit(seed):
    """GT velocities unknown (NaN: isolated annotations) are skipped by the velocity error;
    a class whose every matched velocity is unknown scores the worst error, 1, as the devkit
    (not 0, which read as perfect)."""
    from nuscenes.eval.common.utils import center_distance
    from nuscenes.eval.detection.algo import accumulate, calc_tp
    rng = np.random.default_rng(seed)
    gts, dets = scene(rng)
    for g in gts:
        unknown = (rng.random(len(g)) < 0.3) | (g.labels == 1)      # trucks: all unknown
        g.velocities[unknown] = np.nan
    ours = evaluate(gts, dets, NAMES, ranges=dict.fromkeys(NAMES, 1000000000.0))
    gt_boxes, pred_boxes = to_devkit(gts, True), to_devkit(dets, False)
    for c in NAMES:
        md = accumulate(gt_boxes, pred_boxes, DEVKIT_NAMES[c], center_distance, 2.0)
        ref = calc_tp(md, 0.1, 'vel_err')
        assert ours.tp[c]['vel_err'] == pytest.approx(ref, abs=1e-6), c
    assert ours.tp['truck']['vel_err'] == 1.0


def test_perfect_and_empty():
    rng = np.random.default_rng(9)
    gts, _ = scene(rng, 6)
    perfect = [Detections(g.boxes, g.velocities, np.full(len(g), 0.9), g.labels) for g in gts]
    r = evaluate(gts, perfect, NAMES)
    present = [c for c in NAMES if r.num_gt[c]]
    assert all(r.class_ap[c] == pytest.approx(1.0) for c in present)
    assert r.mean_tp['mATE'] < 1e-5 or len(present) < len(NAMES)
    only_cars = [g.select(g.labels == 0) for g in gts]
    r = evaluate(only_cars, only_cars, NAMES)
    assert r.evaluated == ('car',) and r.mean_ap == pytest.approx(1.0)
    assert 'n/a' in r.table()
    assert np.isnan(r.class_ap['truck'])                # no GT: no AP (not 0)
    assert r.summary()['AP_truck'] is None and r.summary()['AP_car'] == pytest.approx(1.0)
    empty = evaluate(gts, [Detections.empty() for _ in gts], NAMES)
    assert empty.mean_ap == 0.0 and empty.nds == 0.0
    nothing = evaluate([Detections.empty()] * 2, [Detections.empty()] * 2, NAMES)
    assert np.isnan(nothing.mean_ap) and 'mAP n/a' in nothing.table()
    assert 'NDS without the attribute term' in empty.table()
    with pytest.raises(ValueError):
        evaluate(gts, gts[:-1], NAMES)


def test_range_and_num_points_filters():
    gt = Detections(np.array([[10, 0, 0, 4, 2, 1.5, 0], [45, 0, 0, 0.7, 0.7, 1.7, 0],
                              [5, 5, 0, 4, 2, 1.5, 0]]), np.zeros((3, 2)), np.ones(3),
                    np.array([0, 2, 0]))
    det = Detections(gt.boxes[:1], np.zeros((1, 2)), np.ones(1), np.array([0]))
    r = evaluate([gt], [det], NAMES, num_points=[np.array([5, 5, 0], np.uint32)])
    assert r.num_gt['car'] == 1 and r.num_gt['pedestrian'] == 0     # 45 m > 40 m; 0 points
    assert r.class_ap['car'] == pytest.approx(1.0)


def test_pr_plot(tmp_path):
    gts, dets = scene(np.random.default_rng(4), 5)
    r = evaluate(gts, dets, NAMES)
    r.plot_pr(str(tmp_path / 'pr.png'))
    assert (tmp_path / 'pr.png').stat().st_size > 5000


def test_eval_synthetic_val_is_the_fixed_validation_set(monkeypatch):
    """``suit-ros eval --synthetic val`` runs on the drives docs/results.md reports."""
    import suit_ros.data.sequences as seqs
    from suit_ros.evaluate_cli import synthetic_sequences
    calls = []
    monkeypatch.setattr(seqs, 'synthetic_split', lambda *a, **k: calls.append(a) or [[1]])
    assert synthetic_sequences('val', 'cache') == [[1]]
    assert calls == [('val', seqs.VAL_SEQUENCES, 40, 'cache')]


def test_a_run_publishes_carried_boxes_at_their_own_thresholds():
    det = Detections(np.zeros((4, 7)), np.zeros((4, 2)), np.array([0.2, 0.5, 0.2, 0.5]),
                     np.array([0, 0, 1, 1]))
    run = ModelRun([det], [det], [None], [0.0], [0], {})
    assert len(run.published([0.3, 0.3], [0.1, 0.1])[0]) == 2           # none carried
    run.carried = [np.array([True, False, False, True])]
    got = run.published([0.3, 0.6], [0.1, 0.1])[0]
    # box 0 (carried, 0.2 >= 0.1), box 1 (seen, 0.5 >= 0.3); box 2 (seen, class 1, 0.2 < 0.6);
    # box 3 (carried, 0.5 >= 0.1)
    assert got.scores.tolist() == pytest.approx([0.2, 0.5, 0.5])


def test_a_run_on_some_of_its_frames_keeps_every_per_frame_list_in_step():
    dets = [Detections(np.zeros((k, 7)), np.zeros((k, 2)), np.full(k, 0.5), np.zeros(k, int))
            for k in range(4)]
    run = ModelRun(dets, dets, [np.full(k, k, np.uint32) for k in range(4)],
                   [0.1 * k for k in range(4)], [10 * k for k in range(4)], {2: [5]},
                   drive=[0, 0, 1, 1], ignore=[None] * 4,
                   carried=[np.zeros(k, bool) for k in range(4)],
                   used_memory=[False, True, False, True], input_sweeps=[1, 2, 3, 3])
    sub = run.select_frames([3, 1])
    assert [len(d) for d in sub.det] == [3, 1] and [len(g) for g in sub.gt] == [3, 1]
    assert [n.tolist() for n in sub.num_points] == [[3, 3, 3], [1]]
    assert sub.latency_s == pytest.approx([0.3, 0.1]) and sub.memory_bytes == [30, 10]
    assert sub.drive == [1, 0] and sub.used_memory == [True, True]
    assert sub.input_sweeps == [3, 2]
    assert [len(c) for c in sub.carried] == [3, 1] and sub.memory_after == {2: [5]}
    assert len(ModelRun(dets, dets, [None] * 4, [0.0] * 4, [0] * 4, {}).select_frames(
        [0]).drive) == 0                                          # lists left empty stay empty


def test_traffic_side_left_runs_the_model_on_the_drive_mirrored():
    """``run_model(traffic_side='left')`` (``report --traffic-side left``, as the node's
    parameter): a left-hand drive (a right-hand one mirrored) gives the right-hand drive's boxes
    mirrored, scored against its own GT; read as right-hand traffic it gives other boxes."""
    from suit_ros.config import model_config_from_dict
    from suit_ros.data.augment import mirror_world
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.evaluate import run_model
    from suit_ros.model.detector import SUITDetector
    from suit_ros.tracking import TrackerConfig
    drives = synthetic_split('val', 1, 3)
    model = SUITDetector(model_config_from_dict({'temporal': 'none'}, 'test')).eval()
    left_hand = [[mirror_world(f) for f in d] for d in drives]
    plain = run_model(model, drives, tracker=TrackerConfig())
    left = run_model(model, left_hand, tracker=TrackerConfig(), traffic_side='left')
    as_right = run_model(model, left_hand, tracker=TrackerConfig())
    for p, q, g, f in zip(plain.det, left.det, left.gt, left_hand[0]):
        assert len(p) > 5 and len(p) == len(q)
        np.testing.assert_allclose(q.scores, p.scores, atol=1e-5)
        np.testing.assert_allclose(q.boxes[:, 1], -p.boxes[:, 1], atol=1e-3)
        np.testing.assert_allclose(q.boxes[:, [0, 2, 3, 4, 5]], p.boxes[:, [0, 2, 3, 4, 5]],
                                   atol=1e-3)
        np.testing.assert_allclose(np.cos(q.boxes[:, 6] + p.boxes[:, 6]), 1.0, atol=1e-5)
        np.testing.assert_array_equal(g.boxes, f.gt.boxes)          # the drive's own GT
    r, q = as_right.det[-1], left.det[-1]
    assert not (len(r) == len(q) and np.allclose(r.scores, q.scores, atol=1e-5))
    # one side per drive: a right-hand and a left-hand drive in one run
    mixed = run_model(model, [drives[0], left_hand[0]], tracker=TrackerConfig(),
                      traffic_side=['right', 'left'])
    assert mixed.drive == [0] * 3 + [1] * 3
    for p, q in zip(mixed.det[:3], mixed.det[3:]):
        np.testing.assert_allclose(q.boxes[:, 1], -p.boxes[:, 1], atol=1e-3)
        np.testing.assert_allclose(q.scores, p.scores, atol=1e-5)
    for wrong in ('Left', ['left']):
        with pytest.raises(ValueError, match='traffic_side'):
            run_model(model, [drives[0], left_hand[0]], traffic_side=wrong)


def test_eval_of_a_bag_refuses_a_traffic_side(tmp_path, capsys):
    """A bag holds detections already made: the side was detect-bag's."""
    from suit_ros.cli import main
    assert main(['eval', '--bag', str(tmp_path / 'bag'), '--traffic-side', 'left']) != 0
    assert 'detect-bag --traffic-side' in capsys.readouterr().err


def test_ignored_things_cover_their_footprint():
    """A box on the end of a 12 m ignored vehicle (an RV, a tram) is 6 m from its centre: it
    is on the ignored thing, not a false positive; a box 3 m clear of it still is one."""
    from suit_ros.evaluate import drop_ignored
    rv = np.array([[20.0, 0, 0, 12.0, 2.6, 3.5, 0]], np.float32)
    det = Detections(np.array([[25.0, 0, 0, 8, 2.5, 3, 0], [20.0, 0.5, 0, 8, 2.5, 3, 0],
                               [20.0, 4.6, 0, 4.5, 1.9, 1.6, 0]]), np.zeros((3, 2)),
                     np.full(3, 0.8), np.array([1, 1, 0]))
    kept = drop_ignored(det, Detections.empty(), rv)
    assert kept.boxes[:, 1].tolist() == [pytest.approx(4.6)]
    turned = rv.copy()
    turned[0, 6] = np.pi / 2             # turned across: it covers y -6..6, not x 25
    assert drop_ignored(det, Detections.empty(), turned).boxes[:, 0].tolist() == [25.0]


def test_eval_scores_real_data_within_50_m_for_every_class(capsys):
    """`eval --av2` and `--kitti` score pedestrians and cyclists to 50 m, as `report` does;
    nuScenes' class ranges stay for the synthetic and nuScenes data; --max-range sets one."""
    import argparse

    from suit_ros.cli import main
    from suit_ros.evaluate_cli import _ranges
    ns = argparse.Namespace(max_range=None, av2='x', kitti=None)
    assert _ranges(ns, NAMES) == dict.fromkeys(NAMES, 50.0)
    ns.av2 = None
    assert _ranges(ns, NAMES) is None
    ns.max_range = 30.0
    assert _ranges(ns, NAMES) == dict.fromkeys(NAMES, 30.0)
    assert main(['eval', '--synthetic', 'val', '--max-range', 'nan']) == 1
    assert '--max-range must be a positive number' in capsys.readouterr().err


def test_eval_of_a_bag_says_which_frames_the_detector_did_not_answer(tmp_path, capsys):
    """A live node that skipped clouds (busy) published no detections at their stamps: eval
    --bag says how many GT frames it leaves out, and --unanswered empty scores them as
    frames with no box (what a user of the output got)."""
    from suit_ros.cli import main
    from suit_ros.data.bag import open_writer, typestore
    from suit_ros.msg_adapters.classes import MessageClasses
    from suit_ros.msg_adapters.detections import detections_to_pointcloud2
    store = typestore()
    C = MessageClasses.from_rosbags(store)
    car = np.array([[10.0, 0, 0, 4.5, 1.9, 1.6, 0]])
    counts = {'num_points': np.array([40], np.uint32), 'instance_id': np.array([1], np.uint32)}
    with open_writer(tmp_path / 'b') as w:
        for k in range(4):
            stamp = 10**9 + k * 10**8
            args = (car, np.zeros((1, 2)), np.ones(1), np.zeros(1, np.int64), C.header(stamp,
                                                                                      'lidar'), C)
            w.write('/gt/objects', 'sensor_msgs/msg/PointCloud2', stamp,
                    detections_to_pointcloud2(*args, extra_fields=counts))
            if k % 2 == 0:                          # the node answered every other cloud
                w.write('/detector/detections', 'sensor_msgs/msg/PointCloud2', stamp,
                        detections_to_pointcloud2(*args))
    out = tmp_path / 'm.json'
    assert main(['eval', '--bag', str(tmp_path / 'b'), '--json-out', str(out)]) == 0
    assert '2 of 4 GT frames have no detections' in capsys.readouterr().err
    import json
    assert json.loads(out.read_text())['summary']['AP_car'] == pytest.approx(1.0)
    assert main(['eval', '--bag', str(tmp_path / 'b'), '--unanswered', 'empty',
                 '--json-out', str(out)]) == 0
    summary = json.loads(out.read_text())['summary']
    assert summary['frames'] == 4 and summary['AP_car'] < 0.6          # half the car missed
    assert main(['eval', '--synthetic', 'val', '--unanswered', 'empty']) == 1
