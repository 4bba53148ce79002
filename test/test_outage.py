"""The outage benchmark (suit_ros.outage): sectors removed, objects counted where they vanish."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from suit_ros.outage import (
    Outage,
    count_occlusion,
    count_outage,
    intervals,
    outages_for,
    with_outages,
)
from suit_ros.structures import Detections, Frame


def box(x, y, label=0):
    return [x, y, 0.8, 4.5, 1.9, 1.6, 0.0]


def drive(frames=12):
    """A car ahead (azimuth 0) and one behind (azimuth 180), points on both, ids 1 and 2."""
    out = []
    rng = np.random.default_rng(0)
    for k in range(frames):
        pts = np.concatenate([np.c_[rng.uniform(8, 12, (50, 1)), rng.uniform(-0.9, 0.9, (50, 1))],
                              np.c_[rng.uniform(-12, -8, (50, 1)),
                                    rng.uniform(-0.9, 0.9, (50, 1))]])
        pts = np.c_[pts, np.full((100, 1), 0.8), np.zeros((100, 2))].astype(np.float32)
        gt = Detections(np.array([box(10, 0), box(-10, 0)]), np.zeros((2, 2)), np.ones(2),
                        np.array([0, 0]))
        out.append(Frame(pts, np.eye(4), k * 10**8, 'lidar', gt, np.array([50, 50], np.uint32),
                         np.array([1, 2], np.uint32)))
    return out


def test_the_sector_is_removed_only_while_the_outage_lasts():
    o = Outage(0.0, 120.0, 4, 3)
    assert [o.active(k) for k in range(2, 9)] == [0, 0, 1, 2, 3, 0, 0]
    assert o.contains(np.array([[10.0, 0.0], [-10.0, 0.0], [1.0, 1.5]])).tolist() == [
        True, False, True]
    played = with_outages(drive(), [o])
    assert len(played[3].points) == 100 and len(played[4].points) == 50
    assert played[4].num_points.tolist() == [0, 50] and played[7].num_points.tolist() == [50, 50]
    assert (played[5].points[:, 0] < 0).all()
    assert len(outages_for(0, 40)) == 3 and outages_for(3, 40) == outages_for(3, 40)


def test_recall_and_sector_precision_count_what_the_memory_must_hold():
    o = Outage(0.0, 120.0, 4, 3)
    played = with_outages(drive(), [o])
    car = Detections(np.array([box(10.3, 0)]), np.zeros((1, 2)), np.array([0.9]), [0])
    ghost = Detections(np.array([box(20, 2)]), np.zeros((1, 2)), np.array([0.9]), [0])
    faint = Detections(np.array([box(10.3, 0)]), np.zeros((1, 2)), np.array([0.2]), [0])
    empty = Detections.empty()
    dets = [empty] * 4 + [car, Detections(np.r_[car.boxes, ghost.boxes], np.zeros((2, 2)),
                                          [0.9, 0.9], [0, 0]), faint] + [empty] * 5
    c = count_outage([played], [dets], [[o]], [0.5, 0.5, 0.5, 0.5], 3)
    # the car ahead vanished (the one behind is outside the sector)
    assert c.objects.tolist() == [[1, 1, 1]]
    assert c.found.tolist() == [[1, 1, 0]]                   # frame 3: below the threshold
    np.testing.assert_allclose(c.recall(), [1, 1, 0])
    np.testing.assert_allclose(c.precision(), [1.0, 0.5, np.nan])
    j = intervals(c, resamples=20)
    assert j['recall'][0][0] == 1.0 and j['recall_from_frame_3'][0] == 0.0
    assert np.isnan(j['sector_precision_from_frame_3'][0])       # no box published there
    assert j['objects'] == [1, 1, 1]
    low = intervals(count_outage([played], [dets], [[o]], [0.1] * 4, 3), resamples=20)
    assert low['recall_from_frame_3'][0] == 1.0 and low['sector_precision_from_frame_3'][0] == 1.0


def test_occluded_objects_are_counted_by_frames_since_last_seen():
    """The car ahead loses its returns at frames 4-6 (occluded); at frame 5 it was last seen 2
    frames before. A published box of its class within 2 m finds it; an object never seen is
    not counted; one seen again counts at gap 0 (not at all)."""
    frames = drive()
    for k in (4, 5, 6):
        frames[k] = Frame(frames[k].points, frames[k].pose, frames[k].stamp_ns, 'lidar',
                          frames[k].gt, np.array([0, 50], np.uint32), frames[k].instance_ids)
    car = Detections(np.array([box(10.5, 0)]), np.zeros((1, 2)), np.array([0.9]), [0])
    empty = Detections.empty()
    dets = [empty] * 4 + [car, empty, car] + [empty] * 5
    c = count_occlusion([frames], [dets], [0.5] * 4, max_gap=5)
    assert c.objects.tolist() == [[1, 1, 1, 0, 0]]
    assert c.found.tolist() == [[1, 0, 1, 0, 0]]
    j = intervals(c, resamples=20)
    assert j['recall_from_frame_3'][0] == 1.0 and j['objects'] == [1, 1, 1, 0, 0]
    from suit_ros.outage import tables
    o = Outage(0.0, 120.0, 4, 3)
    out = intervals(count_outage([with_outages(drive(), [o])], [dets], [[o]], [0.5] * 4, 3),
                    resamples=20)
    text = tables({'length': 3, 'width_deg': 120.0, 'drives': 1, 'frames': 12,
                   'runs': {'m': out}, 'occlusion': {'m': j}})
    assert '| m | 1.00 [1.00, 1.00] |' in text and '| 3-10 frames |' in text
    assert '| objects | 1 | 1 | 1 | 0 | 0 | |' in text


def test_occlusion_run_keeps_the_occluded_objects_on_the_occlusion_frames():
    """The car ahead is occluded at frames 4-6: only those frames are scored, their GT keeps
    it with the visible car behind; a detector that holds it scores higher than one that
    drops it, and a box where nothing is costs."""
    from suit_ros.evaluate import ModelRun
    from suit_ros.outage import occlusion_run
    frames = drive()
    for k in (4, 5, 6):
        frames[k] = Frame(frames[k].points, frames[k].pose, frames[k].stamp_ns, 'lidar',
                          frames[k].gt, np.array([0, 50], np.uint32), frames[k].instance_ids)
    both = Detections(np.array([box(10.5, 0), box(-10.2, 0)]), np.zeros((2, 2)),
                      np.array([0.9, 0.8]), [0, 0])
    behind = both.select(np.array([False, True]))
    with_ghost = Detections(np.array([box(10.5, 0), box(-10.2, 0), box(0, 20)]),
                            np.zeros((3, 2)), np.array([0.9, 0.8, 0.95]), [0, 0, 0])
    names = ('car', 'truck', 'pedestrian', 'cyclist')

    def scored(dets):
        run = ModelRun([f.gt for f in frames], dets, [f.num_points for f in frames],
                       [0.0] * 12, [0] * 12, {}, [0] * 12)
        return occlusion_run(run, [frames])
    held = scored([both] * 12)
    assert len(held.gt) == 3 and all(len(g) == 2 for g in held.gt)
    assert held.num_points[0].tolist() == [1, 50]
    dropped = scored([behind] * 12)
    haunted = scored([both] * 4 + [with_ghost] * 3 + [both] * 5)
    ap = {k: r.evaluate(names).class_ap['car'] for k, r in
          (('held', held), ('dropped', dropped), ('haunted', haunted))}
    assert ap['held'] > ap['haunted'] and ap['held'] > ap['dropped'], ap
    with pytest.raises(ValueError, match='frames'):
        occlusion_run(replace(held, det=held.det[:2]), [frames])      # not the drives' run


@pytest.mark.slow
def test_outage_command_runs(tmp_path, capsys):
    from suit_ros.cli import main
    out = tmp_path / 'o.json'
    assert main(['outage', '--drives', '1', '--frames', '14', '--cache-dir',
                 str(tmp_path / 'cache'), '--json-out', str(out)]) == 0
    text = capsys.readouterr().out
    assert 'SUIT, tracker' in text and 'single frame' in text and out.is_file()
    assert 'frames since last seen' in text and 'occlusion mAP' in text


@pytest.mark.slow
def test_coasting_holds_the_shipped_models_cars_through_a_lost_sector():
    """The shipped SUIT model, tracked as the node runs it, on a synthetic drive with a
    120-degree sector lost for 6 frames: with ``coast_s`` its confident cars in the sector
    are still published on outage frames 3-6 (as carried boxes with no returns in them, a
    track id, within 2 m of an object that is there); without it none is."""
    from suit_ros.checkpoint import load_checkpoint
    from suit_ros.data.sim import preset, sim_frames
    from suit_ros.evaluate import step_inputs
    from suit_ros.model.streaming import StreamingDetector
    from suit_ros.tracking import TrackerConfig
    seq = list(sim_frames(preset('test-real', frames=14), 3))
    lost = Outage(90.0, 120.0, 6, 6)                      # to the left, frames 6-11
    frames = with_outages(seq, [lost])
    model = load_checkpoint('suit_default', 'cpu')[0]
    held = {}
    for coast in (0.0, 0.5):
        runner = StreamingDetector(model, tracker=TrackerConfig(coast_s=coast))
        held[coast] = []
        for k, f in enumerate(frames):
            r = runner.step(*step_inputs(f))
            if lost.active(k) < 3:
                continue
            coasted = r.carried & lost.contains(r.detections.boxes[:, :2])
            held[coast].append(int(coasted.sum()))
            assert (r.num_points[coasted] == 0).all() and (r.track_ids[coasted] > 0).all()
            for b in r.detections.boxes[coasted]:
                assert np.hypot(*(f.gt.boxes[:, :2] - b[:2]).T).min() < 2.0
    assert sum(held[0.0]) == 0 and min(held[0.5]) >= 1, held
