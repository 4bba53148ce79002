"""``suit-ros report`` and the published thresholds: counts, cuts, pictures, the command."""
from __future__ import annotations

import json

import numpy as np
import pytest
from test_av2 import write_log

from suit_ros.checkpoint import (
    default_checkpoint_path,
    load_checkpoint,
    published_thresholds,
    read_metadata,
    update_metadata,
)
from suit_ros.cli import main
from suit_ros.evaluate import ModelRun
from suit_ros.report import SWEEP, add_seen, build_report, count_matches, draw_bev, seen_of
from suit_ros.structures import Detections
from suit_ros.thresholds_cli import best_f1


def dets(xs, scores, labels=None, yaw=0.0):
    n = len(xs)
    boxes = np.zeros((n, 7))
    boxes[:, 0] = xs
    boxes[:, 3:6] = (4.5, 1.9, 1.6)
    boxes[:, 6] = yaw
    return Detections(boxes, np.zeros((n, 2)), np.asarray(scores, float),
                      np.zeros(n, np.int64) if labels is None else np.asarray(labels))


def test_counts_at_any_threshold_are_cuts_of_one_matching():
    gt = [dets([10.0, 20.0, 30.0], [1, 1, 1])]
    # a sure hit, a faint hit, a sure false positive, a faint duplicate of the first
    det = [dets([10.3, 20.5, 40.0, 10.1], [0.9, 0.3, 0.8, 0.2])]
    c = count_matches(gt, det, 0, 2.0)
    low, high = c.at(0.1), c.at(0.5)
    assert (low['tp'], low['fp'], low['gt']) == (2, 2, 3)
    assert low['recall'] == pytest.approx(2 / 3, abs=1e-4)
    assert low['precision'] == pytest.approx(0.5)
    assert (high['tp'], high['fp']) == (1, 1)
    assert high['fp_per_frame'] == pytest.approx(1.0)
    # the same as matching only the detections above the cut
    cut = count_matches(gt, [det[0].select(det[0].scores >= 0.5)], 0, 2.0).at(0.0)
    assert (cut['tp'], cut['fp']) == (high['tp'], high['fp'])


def test_heading_flips_are_counted_on_true_positives():
    gt = [dets([10.0, 20.0, 30.0], [1, 1, 1])]
    det = [Detections(np.array([[10, 0, 0, 4.5, 1.9, 1.6, np.pi],       # flipped
                                [20, 0, 0, 4.5, 1.9, 1.6, 0.1],         # fine
                                [30, 0, 0, 4.5, 1.9, 1.6, 2.0]]),       # 115 deg: not flipped
                      np.zeros((3, 2)), np.array([0.9, 0.9, 0.9]), np.zeros(3, np.int64))]
    h = count_matches(gt, det, 0, 2.0).heading(0.5)
    assert (h['matched'], h['flipped']) == (3, 1)
    assert h['flip_rate'] == pytest.approx(1 / 3, abs=1e-4)


def test_placement_is_signed_by_range_from_the_ego():
    # a car ahead placed 0.5 m too far, one behind 0.3 m too near, one beside 0.2 m further
    # out; the length 0.4 m too long on all three; a false positive adds nothing
    gt = [Detections(np.array([[10, 0, 0, 4.5, 1.9, 1.6, 0], [-20, 0, 0, 4.5, 1.9, 1.6, 0],
                               [0, 15, 0, 4.5, 1.9, 1.6, 0]]), np.zeros((3, 2)), np.ones(3),
                     np.zeros(3, np.int64))]
    det = [Detections(np.array([[10.5, 0, 0, 4.9, 1.9, 1.6, 0], [-19.7, 0, 0, 4.9, 1.9, 1.6, 0],
                                [0, 15.2, 0, 4.9, 1.9, 1.6, 0], [30, 0, 0, 4.9, 1.9, 1.6, 0]]),
                      np.zeros((4, 2)), np.array([0.9, 0.8, 0.7, 0.9]), np.zeros(4, np.int64))]
    c = count_matches(gt, det, 0, 2.0)
    np.testing.assert_allclose(c.placement[:3], [[0.5, 0.4], [-0.3, 0.4], [0.2, 0.4]],
                               atol=1e-6)
    assert np.isnan(c.placement[3]).all()
    p = c.placement_at(0.5)
    assert p['matched'] == 3
    assert p['range_offset_m'] == pytest.approx(0.2)
    assert p['length_error_m'] == pytest.approx(0.4)
    assert c.placement_at(0.85)['range_offset_m'] == pytest.approx(0.5)
    assert count_matches(gt, det, 0, 2.0).placement_at(0.95) == {
        'matched': 0, 'range_offset_m': None, 'length_error_m': None}
    rep = build_report(ModelRun(gt, det, [np.full(3, 20, np.uint32)], [0.0], [0], {}, [0],
                                [np.zeros((0, 7), np.float32)]), ('car',), [0.5], 'test')
    assert rep.to_json()['car_placement']['range_offset_m'] == pytest.approx(0.2)
    assert 'median range offset +0.20 m' in rep.markdown()


def test_missed_objects_and_false_positives_say_what_the_model_made_of_them():
    # cars at 10 m (found), 20 m (its box scores 0.3 under the 0.5 cut; a pedestrian box at
    # 0.6 sits on it), 30 m (nothing there), 60 m (out of range); a pedestrian at 15 m without
    # returns (not scored); a duplicate car box on the found one takes nothing
    gt = [dets([10.0, 20.0, 30.0, 60.0, 15.0], [1] * 5, [0, 0, 0, 0, 1])]
    det = [dets([10.2, 9.9, 20.3, 20.1], [0.9, 0.6, 0.3, 0.6], [0, 0, 0, 1])]
    run = ModelRun(gt, det, [np.array([50, 40, 3, 20, 0], np.uint32)], [0.0], [0], {}, [0],
                   [None])
    rep = build_report(run, ('car', 'pedestrian'), [0.5, 0.5], 'test')
    box20, box30 = [20.0, 0, 0, 4.5, 1.9, 1.6, 0], [30.0, 0, 0, 4.5, 1.9, 1.6, 0]
    assert rep.missed == [
        {'frame': 0, 'class': 'car', 'range_m': 20.0, 'box': box20, 'returns': 40,
         'best_score': 0.3, 'other': {'class': 'pedestrian', 'score': 0.6}},
        {'frame': 0, 'class': 'car', 'range_m': 30.0, 'box': box30, 'returns': 3,
         'best_score': 0.0, 'other': None}]
    assert rep.to_json()['missed'] == rep.missed
    # the false positives: the pedestrian box on the missed car, and the duplicate car box
    # on the found one
    assert rep.false == [
        {'frame': 0, 'class': 'car', 'score': 0.6, 'range_m': 9.9,
         'box': [9.9, 0, 0, 4.5, 1.9, 1.6, 0],
         'nearest': {'class': 'car', 'distance_m': 0.1, 'found': True}},
        {'frame': 0, 'class': 'pedestrian', 'score': 0.6, 'range_m': 20.1,
         'box': [20.1, 0, 0, 4.5, 1.9, 1.6, 0],
         'nearest': {'class': 'car', 'distance_m': 0.1, 'found': False}}]
    assert rep.to_json()['false_positives'] == rep.false
    md = rep.markdown()
    assert '| 0 | car | 20.0 | 40 | n/a | 0.30 | pedestrian 0.60 |' in md
    assert '| 0 | car | 30.0 | 3 | n/a | 0.00 | none |' in md
    # what the sensor saw of them: the 20 m car's near end only (a 0.5 x 1.2 m patch,
    # 0.2-1.0 m above its bottom), nothing of the 30 m one in these points
    rng = np.random.default_rng(0)
    patch = np.c_[rng.uniform(17.75, 18.25, 200), rng.uniform(-0.6, 0.6, 200),
                  rng.uniform(-0.6, 0.2, 200)]
    assert '| 0 | pedestrian | 0.60 | 20.1 | car 0.10 | no | n/a |' in md
    add_seen([*rep.missed, *rep.false], lambda i: np.r_[patch, [[50.0, 0.0, 0.0]]])
    seen = rep.missed[0]['seen']
    assert seen['returns'] == 200
    assert seen['length_m'] == pytest.approx(0.5, abs=0.02)
    assert seen['width_m'] == pytest.approx(1.2, abs=0.03)
    low, high = np.percentile(patch[:, 2] + 0.8, [10, 90])      # the box's bottom at -0.8
    assert seen['low_m'] == pytest.approx(low, abs=1e-3) and 0.2 < low < 0.4
    assert seen['high_m'] == pytest.approx(high, abs=1e-3) and 0.8 < high < 1.0
    assert rep.missed[1]['seen'] is None
    assert seen_of(patch, box30) is None and seen_of(np.zeros((0, 3)), box20) is None
    md = rep.markdown()
    assert f'| 0 | car | 20.0 | 40 | 0.5 x 1.2, {low:.1f}-{high:.1f} | 0.30 | pedestrian 0.60 |' \
        in md
    assert '| 0 | car | 30.0 | 3 | n/a | 0.00 | none |' in md
    # the false pedestrian box on the missed car (x from 17.85 m) holds most of the patch;
    # the duplicate car box at 9.9 m holds nothing of these points
    fp = rep.false[1]['seen']
    assert fp['returns'] == int((patch[:, 0] >= 17.85).sum()) and rep.false[0]['seen'] is None
    assert (f'| 0 | pedestrian | 0.60 | 20.1 | car 0.10 | no | {fp["returns"]}; '
            f'{fp["length_m"]:.1f} x {fp["width_m"]:.1f}, {fp["low_m"]:.1f}-{fp["high_m"]:.1f} |'
            ) in md
    assert '| 0 | car | 0.60 | 9.9 | car 0.10 | yes | n/a |' in md
    # at a cut of 0.25 the 20 m car is found; nothing is missed in a run that finds all
    assert [m['range_m'] for m in build_report(run, ('car', 'pedestrian'), [0.25, 0.5],
                                               'test').missed] == [30.0]
    # a box far from every object is on the background
    run.det = [dets([10.0, 20.0, 30.0, 45.0], [0.9, 0.9, 0.9, 0.7])]
    full = build_report(run, ('car', 'pedestrian'), [0.5, 0.5], 'test')
    assert full.missed == [] and 'Missed objects' not in full.markdown()
    assert full.false == [{'frame': 0, 'class': 'car', 'score': 0.7, 'range_m': 45.0,
                           'box': [45.0, 0, 0, 4.5, 1.9, 1.6, 0], 'nearest': None}]
    assert '| 0 | car | 0.70 | 45.0 | none |  | n/a |' in full.markdown()


def test_best_f1_picks_the_best_cut_and_a_class_without_gt_the_highest():
    gt = [dets([10.0, 20.0], [1, 1])]
    det = [dets([10.0, 20.0, 40.0, 50.0], [0.9, 0.7, 0.3, 0.2])]
    assert best_f1(count_matches(gt, det, 0, 2.0))['threshold'] == pytest.approx(0.35)
    none = count_matches([dets([], [])], [dets([5.0], [0.5])], 0, 2.0)
    assert best_f1(none)['threshold'] == SWEEP[-1]


def test_report_drops_ignored_and_out_of_range_and_draws(tmp_path):
    gt = [dets([10.0, 60.0], [1, 1])]
    det = [dets([10.2, 3.0, 60.0, 25.0], [0.9, 0.8, 0.8, 0.6])]
    ignore = np.array([[3.0, 0, 0, 1.7, 0.6, 1.0, 0]], np.float32)     # a parked bicycle
    run = ModelRun(gt, det, [np.array([20, 20], np.uint32)], [0.0], [0], {}, [0], [ignore])
    rep = build_report(run, ('car',), [0.5], 'test')
    p = rep.to_json()['classes']['car']['published']
    assert (p['gt'], p['tp'], p['fp']) == (1, 1, 1)        # 60 m: out; 3 m: ignored
    assert rep.to_json()['car_heading']['matched'] == 1
    assert '| car | 1 | 1.000 | 0.500 |' in rep.markdown()
    # AP by match distance: the box 0.2 m off is found at every distance; its mean is the AP
    by_dist = rep.to_json()['classes']['car']['ap_by_distance']
    assert list(by_dist) == ['0.5', '1', '2', '4']
    assert np.mean(list(by_dist.values())) == pytest.approx(rep.to_json()['classes']['car']['ap'],
                                                            abs=1e-3)
    far = build_report(ModelRun(gt, [dets([11.5, 3.0], [0.9, 0.8])],
                                [np.array([20, 20], np.uint32)], [0.0], [0], {}, [0], [ignore]),
                       ('car',), [0.5], 'test').to_json()['classes']['car']['ap_by_distance']
    assert far['0.5'] == far['1'] == 0.0 and far['2'] > 0.5      # 1.5 m off: found at 2 and 4 m
    # carried boxes at their own thresholds: the one at 25 m (0.6) goes at a carry cut of 0.7,
    # a carried one at 0.3 stays at a cut of 0.2
    run.det = [dets([10.2, 3.0, 60.0, 25.0, 30.0], [0.9, 0.8, 0.8, 0.6, 0.3])]
    run.carried = [np.array([False, False, False, True, True])]
    p = build_report(run, ('car',), [0.5], 'test', carry_thresholds=[0.2]).at_published('car')
    assert (p['gt'], p['tp'], p['fp']) == (1, 1, 2)        # 25 m and 30 m published
    p = build_report(run, ('car',), [0.5], 'test', carry_thresholds=[0.7]).at_published('car')
    assert (p['gt'], p['tp'], p['fp']) == (1, 1, 0)
    png = tmp_path / 'bev.png'
    draw_bev(png, np.random.default_rng(0).uniform(-40, 40, (500, 5)), gt[0], det[0], ('car',),
             [0.5], ignore)
    assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def test_published_thresholds_come_from_the_checkpoint(tmp_path):
    meta = {'config': {'head': {'score_threshold': 0.1}}}
    assert published_thresholds(meta, ['car', 'truck']) == [0.1, 0.1]
    meta['publish_thresholds'] = {'car': 0.4}
    assert published_thresholds(meta, ['car', 'truck']) == [0.4, 0.1]
    # the carry branch's: its own where stored, else the published ones
    assert published_thresholds(meta, ['car', 'truck'], carried=True) == [0.4, 0.1]
    meta['carry_publish_thresholds'] = {'truck': 0.05}
    assert published_thresholds(meta, ['car', 'truck'], carried=True) == [0.4, 0.05]
    assert published_thresholds(meta, ['car', 'truck']) == [0.4, 0.1]
    path = tmp_path / 'c.safetensors'
    path.write_bytes(default_checkpoint_path().read_bytes())
    before = load_checkpoint(path)[0].state_dict()
    update_metadata(path, publish_thresholds={'car': 0.45, 'pedestrian': 0.5})
    model, cfg, meta = load_checkpoint(path)
    assert published_thresholds(meta, cfg.class_names)[0] == pytest.approx(0.45)
    assert read_metadata(path)['class_names'] == list(cfg.class_names)     # the rest kept
    for k, v in model.state_dict().items():
        assert np.array_equal(v.numpy(), before[k].numpy()), k


def test_shipped_checkpoints_carry_published_thresholds_above_the_decoding_one():
    for name in ('suit_default', 'centerpoint_single', 'suit_carry'):
        meta = read_metadata(name)
        thr = published_thresholds(meta, meta['class_names'])
        assert set(meta['publish_thresholds']) == set(meta['class_names'])
        assert all(t > meta['config']['head']['score_threshold'] for t in thr), (name, thr)
        carry = published_thresholds(meta, meta['class_names'], carried=True)
        if meta['config'].get('fusion_gate') == 'carry_branch':
            # its own, lower ones for what it holds where the cloud has no returns
            assert set(meta['carry_publish_thresholds']) == set(meta['class_names'])
            assert all(0.1 < c < t for c, t in zip(carry, thr)), (name, carry)
        else:
            assert carry == thr and 'carry_publish_thresholds' not in meta


@pytest.mark.slow
def test_report_command_on_an_av2_log(tmp_path, capsys):
    write_log(tmp_path / 'data')
    out = tmp_path / 'rep'
    assert main(['report', '--av2', str(tmp_path / 'data'), '--out', str(out),
                 '--score-thresholds', '0.3', '--pictures', '2']) == 0
    j = (out / 'report.json').read_text()
    assert '"published_thresholds"' in j and '"car_heading"' in j
    missed = json.loads(j)['missed']
    assert missed and all('seen' in m for m in missed)  # read from each frame's points
    assert any(m['seen'] is not None for m in missed)
    # the log's first frame has one sweep and its second two: the report counts them
    by = json.loads(j)['frames_by_input_sweeps']
    assert by['1'] == 1 and by['2'] == 1 and sum(by.values()) == json.loads(j)['frames']
    assert 'frames read with fewer than 3 sweeps (1 with 1, 1 with 2' in \
        (out / 'report.md').read_text()
    assert len(list((out / 'bev').glob('*.png'))) == 2
    assert 'Real-data report' in capsys.readouterr().out
    # again into the same folder with one picture: the earlier report's are not left beside
    # it, a file of the user's is, and the command says what it replaced
    (out / 'bev' / 'notes.png').write_bytes(b'mine')
    assert main(['report', '--av2', str(tmp_path / 'data'), '--out', str(out),
                 '--score-thresholds', '0.3', '--pictures', '1']) == 0
    pictures = sorted(p.name for p in (out / 'bev').glob('*.png'))
    assert len(pictures) == 2 and 'notes.png' in pictures, pictures
    assert [p for p in pictures if p != 'notes.png'][0].endswith('_0000.png'), pictures
    assert (out / 'bev' / 'notes.png').read_bytes() == b'mine'
    assert 'replaced the earlier report in' in capsys.readouterr().err
    assert main(['report', '--av2', str(tmp_path / 'data'), '--out', str(tmp_path / 'rep2'),
                 '--pictures', '0', '--overhang', 'drop', '--ground', 'local',
                 '--box-fit', 'faces', '--traffic-side', 'left']) == 0
    assert 'overhang drop' in (tmp_path / 'rep2' / 'report.md').read_text()
    assert 'traffic side left' in (tmp_path / 'rep2' / 'report.md').read_text()
    assert 'box fit faces' in (tmp_path / 'rep2' / 'report.md').read_text()
    # against a baseline: the paired AP difference per class over resampled places
    assert main(['report', '--av2', str(tmp_path / 'data'), '--out', str(tmp_path / 'rep3'),
                 '--pictures', '0', '--baseline', 'centerpoint_single',
                 '--resamples', '50']) == 0
    j3 = json.loads((tmp_path / 'rep3' / 'report.json').read_text())
    assert j3['baseline']['checkpoint'] == 'centerpoint_single'
    assert j3['places']['resamples'] == 50 and j3['places']['places'] >= 1
    assert j3['places']['left_out'] == {}       # (a class in one place: no interval at all)
    for b in j3['baseline']['classes'].values():
        # the difference is the one of the two columns shown (both over the places)
        assert b['difference'] == pytest.approx(b['ap_this'] - b['ap'], abs=2e-4)
        # (no interval for a class in one place: null)
        assert b['interval'][0] is None or b['interval'][0] <= b['interval'][1]
    # one car and one pedestrian, each in one place: AP, but no interval over places
    assert '(one place: no interval)' in (tmp_path / 'rep3' / 'report.md').read_text()
    assert '## Against the baseline (centerpoint_single)' in \
        (tmp_path / 'rep3' / 'report.md').read_text()
    assert main(['report', '--av2', str(tmp_path / 'data'), '--out', str(tmp_path / 'rep4'),
                 '--baseline', 'centerpoint_single', '--resamples', '0']) == 1


@pytest.mark.slow
def test_report_command_fails_clearly(tmp_path, capsys):
    assert main(['report', '--av2', str(tmp_path / 'missing'), '--out', str(tmp_path)]) == 1
    assert 'not a folder' in capsys.readouterr().err
    write_log(tmp_path / 'data')
    assert main(['report', '--av2', str(tmp_path / 'data'), '--out', str(tmp_path / 'r'),
                 '--score-thresholds', '0.1', '0.2']) == 1
    assert 'needs 1 or 4 values' in capsys.readouterr().err
    assert main(['report', '--synthetic', 'tune', '--preset', 'val-nowhere',
                 '--out', str(tmp_path / 'r')]) == 1
    assert "'val-nowhere' is not a preset" in capsys.readouterr().err
    assert main(['report', '--av2', str(tmp_path / 'data'), '--preset', 'val-ends-all',
                 '--out', str(tmp_path / 'r')]) == 1
    assert '--preset sets the world of a --synthetic val or tune split' in \
        capsys.readouterr().err


def lost_sector_run():
    """The drive of test_outage with a 120-degree sector lost for 4 frames, and a run on it:
    the car ahead seen at 0.9, held by the carry at 0.2 while its sector is lost, with a ghost
    held at 0.12 beside it."""
    from test_outage import box, drive

    from suit_ros.outage import Outage, with_outages
    o = Outage(0.0, 120.0, 4, 4)
    played = with_outages(drive(), [o])
    det, carried = [], []
    for k in range(len(played)):
        lost = bool(o.active(k))
        boxes = [box(10.3, 0), box(20, 2)] if lost else [box(10.3, 0)]
        scores = [0.2, 0.12] if lost else [0.9]
        det.append(Detections(np.array(boxes), np.zeros((len(boxes), 2)), np.array(scores),
                              np.zeros(len(boxes), np.int64)))
        carried.append(np.full(len(boxes), lost))
    run = ModelRun([f.gt for f in played], det, [f.num_points for f in played],
                   [0.0] * 12, [0] * 12, {}, [0] * 12, carried=carried)
    return o, played, run


def test_carry_thresholds_take_the_factor_of_best_f1_on_outage_frames():
    """The carry thresholds: one factor on the published ones, the one of best F1 between
    the recall of the lost sector's objects and the precision of the boxes published there on
    outage frames 3+, the highest among ties."""
    from suit_ros.thresholds_cli import best_carry_factor, carry_factor_rows
    o, played, run = lost_sector_run()
    rows = {r['factor']: r for r in carry_factor_rows(run, [played], [[o]], [0.4] * 4)}
    assert rows[0.3]['recall'] == 1.0 and rows[0.3]['precision'] == 0.5     # the ghost too
    assert rows[0.5]['recall'] == 1.0 and rows[0.5]['precision'] == 1.0
    assert rows[0.55]['recall'] == 0.0 and rows[1.0]['f1'] == 0.0
    assert best_carry_factor(list(rows.values())) == 0.5        # 0.35..0.5 tie at F1 1


def test_carry_thresholds_count_the_held_boxes_of_ordinary_drives():
    """The carry factor's precision pools the lost sectors' boxes with the boxes a run of the
    drives as they are holds where the cloud shows nothing: a held ghost published at the low
    factors lowers it there, a held box on an object counts as true, a seen box not at all."""
    from test_outage import box, drive

    from suit_ros.thresholds_cli import best_carry_factor, carry_factor_rows, held_counts
    o, played, run = lost_sector_run()
    frames = drive()
    # the drive as it is: the car seen (0.9), the car held in frame 0 (0.25, no seen box of it
    # then), a ghost held at 0.15 in every frame
    odet, ocarried = [], []
    for k in range(len(frames)):
        boxes, scores = [box(-30, 5)], [0.15]
        boxes.append(box(10.3, 0))
        scores.append(0.25 if k == 0 else 0.9)
        odet.append(Detections(np.array(boxes), np.zeros((2, 2)), np.array(scores),
                               np.zeros(2, np.int64)))
        ocarried.append(np.array([True, k == 0]))
    ordinary = ModelRun([f.gt for f in frames], odet, [f.num_points for f in frames],
                        [0.0] * 12, [0] * 12, {}, [0] * 12, carried=ocarried)
    assert held_counts(ordinary, [0.4] * 4, [0.3 * 0.4] * 4) == (13, 1)
    assert held_counts(ordinary, [0.4] * 4, [0.4 * 0.4] * 4) == (1, 1)     # ghost cut
    assert held_counts(ordinary, [0.4] * 4, [0.7 * 0.4] * 4) == (0, 0)
    rows = {r['factor']: r for r in carry_factor_rows(run, [played], [[o]], [0.4] * 4,
                                                       ordinary)}
    assert rows[0.3]['sector_precision'] == 0.5 and rows[0.3]['held_boxes'] == 13
    assert rows[0.3]['precision'] == (2 + 1) / (4 + 13)     # frames 3-4: 2 boxes each
    assert rows[0.4]['precision'] == 1.0 and rows[0.5]['precision'] == 1.0
    assert best_carry_factor(list(rows.values())) == 0.5


def test_a_box_on_an_object_without_returns_is_neither_found_nor_false():
    """A labelled car with no return in the sweep (hidden now, held by the tracker): the box
    on it is not a false positive in the counts (nothing of it is there to find); AP counts
    it as one, as nuScenes does."""
    gt = [dets([10.0, 20.0], [1, 1])]
    det = [dets([10.1, 20.1], [0.9, 0.8])]
    run = ModelRun(gt, det, [np.array([30, 0], np.uint32)], [0.0], [0], {}, [0])
    rep = build_report(run, ('car',), [0.5], 'test')
    p = rep.to_json()['classes']['car']['published']
    assert (p['gt'], p['tp'], p['fp']) == (1, 1, 0) and rep.false == []
    assert rep.to_json()['classes']['car']['ap'] < 1.0
    # a box of its class on a car seen now still counts, beside a hidden one
    run.det = [dets([10.1, 20.1, 21.0], [0.9, 0.8, 0.7])]
    run.gt = [dets([10.0, 20.0, 21.5], [1, 1, 1])]
    run.num_points = [np.array([30, 0, 30], np.uint32)]
    p = build_report(run, ('car',), [0.5], 'test').to_json()['classes']['car']['published']
    assert (p['gt'], p['tp'], p['fp']) == (2, 2, 0)


def test_report_json_is_standard_json(tmp_path):
    """An undefined ratio (no GT of a class, nothing published) is null, not NaN."""
    from suit_ros.outputs import json_text
    run = ModelRun([dets([10.0], [1])], [dets([], [])], [np.array([30], np.uint32)], [0.0],
                   [0], {}, [0])
    text = json_text(build_report(run, ('car', 'truck'), [0.5, 0.5], 'test').to_json())
    assert 'NaN' not in text and 'Infinity' not in text
    data = json.loads(text, parse_constant=lambda c: pytest.fail(f'{c} in the JSON'))
    assert data['classes']['car']['published']['precision'] is None
    assert json.loads(json_text({'a': [float('nan'), 1.5, float('inf')]})) == {'a': [None, 1.5,
                                                                                  None]}


def test_the_picture_draws_an_object_found_only_when_a_box_was_matched_to_it():
    """Two cars 1.5 m apart and one box between them: one car is found, the other missed
    (the picture drew both as found: a true positive lay within 2 m of each)."""
    from suit_ros.report import picture_matches
    gt = dets([10.0, 11.5], [1, 1])
    missed, tp = picture_matches(gt, dets([10.7], [0.9]))
    assert missed.tolist() == [False, True] and tp.tolist() == [True]
    missed, _ = picture_matches(gt, dets([10.0, 11.5], [0.9, 0.8]))
    assert not missed.any()
