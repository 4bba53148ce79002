"""The outage benchmark (suit_ros.outage): sectors removed, objects counted where they vanish."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from suit_ros.outage import (
    Outage,
    OutageCounts,
    count_events,
    count_occlusion,
    count_outage,
    intervals,
    occlusion_events,
    outages_for,
    recall_difference,
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
    assert '| m | 1.00 [1.00, 1.00] |' in text and '| frames 3+ |' in text
    assert '| objects | 1 | 1 | 1 | 0 | 0 | |' in text


def hidden(frames, car_frames):
    """The drive with the car ahead (id 1) without returns at ``car_frames``."""
    out = list(frames)
    for k in car_frames:
        out[k] = replace(out[k], num_points=np.array([0, 50], np.uint32))
    return out


def test_an_outage_counts_an_objects_own_returns_as_the_world_does():
    """A moving sweep puts a car's returns outside its box (its own, by the returns' owners):
    the world counts them; so does a frame with a sector lost elsewhere (it recounted the box
    alone: 0, a visible car taken for lost); a sector over them loses them."""
    frames = drive()
    for k, f in enumerate(frames):
        pts = f.points.copy()
        pts[:50, 0] += 3.0                     # the car ahead's returns 11-15 m: past its box
        frames[k] = replace(f, points=pts, owners=np.repeat(np.array([1, 2], np.uint32), 50))
    behind, ahead = Outage(180.0, 60.0, 4, 2), Outage(0.0, 60.0, 4, 2)
    kept = with_outages(frames, [behind])[4]
    assert kept.num_points.tolist() == [50, 0]
    assert kept.owners is not None and len(kept.owners) == len(kept.points) == 50
    assert with_outages(frames, [ahead])[4].num_points.tolist() == [0, 50]


def test_an_occlusion_event_is_an_object_hidden_0_3_to_1_s_and_seen_again():
    """Events: hidden 3-10 frames at 10 Hz between frames with returns. Hidden 2 frames is
    too short, 11 too long; hidden to the end of the drive, or from its start, is none (it
    never comes back, or was never seen); an object that leaves the labels while hidden is
    none."""
    def car_events(frames):
        return [int(p[0]) for p in occlusion_events(frames)]
    assert car_events(hidden(drive(), [4, 5, 6])) == [0] * 4 + [1, 2, 3] + [0] * 5
    assert car_events(hidden(drive(), [4, 5])) == [0] * 12
    assert car_events(hidden(drive(16), range(2, 13))) == [0] * 16
    assert car_events(hidden(drive(16), range(2, 12))) == [0, 0] + list(range(1, 11)) + [0] * 4
    assert car_events(hidden(drive(), range(8, 12))) == [0] * 12          # never back
    assert car_events(hidden(drive(), range(0, 4))) == [0] * 12           # never seen before
    both = hidden(drive(), [3, 4, 5, 8, 9, 10])                # two events of one object
    assert car_events(both) == [0, 0, 0, 1, 2, 3, 0, 0, 1, 2, 3, 0]
    gone = hidden(drive(), [4, 5, 6])
    gone[5] = replace(gone[5], gt=gone[5].gt.select(np.array([False, True])),
                      num_points=np.array([50], np.uint32), instance_ids=np.array([2], np.uint32))
    assert car_events(gone)[4] == 0 and occlusion_events(gone)[5].tolist() == [0]


def test_event_recall_and_its_paired_difference_between_two_models():
    frames = hidden(drive(), [4, 5, 6])
    car = Detections(np.array([box(10.5, 0)]), np.zeros((1, 2)), np.array([0.9]), [0])
    empty = Detections.empty()
    holds = count_events([frames], [[empty] * 4 + [car] * 3 + [empty] * 5], [0.5] * 4, 5)
    drops = count_events([frames], [[empty] * 4 + [car] + [empty] * 7], [0.5] * 4, 5)
    assert holds.objects.tolist() == [[1, 1, 1, 0, 0]]
    assert holds.found.tolist() == [[1, 1, 1, 0, 0]] and drops.found.tolist() == [[1, 0, 0, 0, 0]]
    d = recall_difference(holds, drops, resamples=20)
    assert d['recall'][0] == pytest.approx(2 / 3, abs=1e-3)
    assert d['recall_from_frame_3'] == [1.0, 1.0, 1.0]
    with pytest.raises(ValueError, match='same objects'):
        recall_difference(holds, count_events([drive()], [[empty] * 12], [0.5] * 4, 5))
    # two runs written out separately pair as well as in one (the JSON keeps the counts)
    import json
    back = [OutageCounts.from_json(json.loads(json.dumps(c.to_json()))) for c in (holds, drops)]
    assert recall_difference(*back, resamples=20) == d
    assert back[0].found.dtype == np.int64 and back[0].found.tolist() == holds.found.tolist()


def test_a_neighbours_box_does_not_find_a_hidden_object():
    """Boxes are matched against every object of the frame: the box on a visible car 1.2 m
    from a hidden one is that car's, and does not count the hidden one as found."""
    frames = []
    for f in hidden(drive(), [4, 5, 6]):
        gt = Detections(np.r_[f.gt.boxes, [box(10, 1.2)]], np.zeros((3, 2)), np.ones(3),
                        np.array([0, 0, 0]))
        frames.append(replace(f, gt=gt, num_points=np.r_[f.num_points, 50].astype(np.uint32),
                              instance_ids=np.array([1, 2, 3], np.uint32)))
    beside = Detections(np.array([box(10, 1.2)]), np.zeros((1, 2)), np.array([0.9]), [0])
    c = count_events([frames], [[beside] * 12], [0.5] * 4, 5)
    assert c.objects.tolist() == [[1, 1, 1, 0, 0]] and c.found.tolist() == [[0, 0, 0, 0, 0]]
    on_it = Detections(np.array([box(10, 1.2), box(10.3, 0)]), np.zeros((2, 2)),
                       np.array([0.9, 0.8]), [0, 0])
    assert count_events([frames], [[on_it] * 12], [0.5] * 4, 5).found.tolist() == \
        [[1, 1, 1, 0, 0]]


def test_an_object_across_the_sectors_edge_is_not_lost():
    """An outage counts the objects it hides: a car whose centre is in the sector but whose
    returns outside it are still seen is not counted (it was, as lost, before)."""
    o = Outage(0.0, 120.0, 4, 3)
    frames = drive()
    edge = np.array([[6.0, 9.0]])                   # azimuth 56 deg: just inside the sector
    for k, f in enumerate(frames):
        rng = np.random.default_rng(k)
        across = np.c_[rng.uniform(3.8, 8.2, (40, 1)), np.full((40, 1), 9.0)]
        pts = np.c_[across, np.full((40, 1), 0.8), np.zeros((40, 2))].astype(np.float32)
        gt = Detections(np.r_[f.gt.boxes, [[*edge[0], 0.8, 4.5, 1.9, 1.6, 0.0]]],
                        np.zeros((3, 2)), np.ones(3), np.array([0, 0, 0]))
        frames[k] = replace(f, points=np.r_[f.points, pts], gt=gt,
                            num_points=np.array([50, 50, 40], np.uint32),
                            instance_ids=np.array([1, 2, 3], np.uint32))
    played = with_outages(frames, [o])
    assert played[4].num_points[2] > 0                  # part of it outside the sector
    c = count_outage([played], [[Detections.empty()] * 12], [[o]], [0.5] * 4, 3)
    assert c.objects.tolist() == [[1, 1, 1]]                      # the car ahead only


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

    bike = np.array([[0.0, -15.0, 0.5, 1.7, 0.6, 1.0, 0.0]], np.float32)
    frames[5] = replace(frames[5], ignore_boxes=bike)          # the frame's own ignore box

    def scored(dets):
        run = ModelRun([f.gt for f in frames], dets, [f.num_points for f in frames],
                       [0.0] * 12, [0] * 12, {}, [0] * 12,
                       carried=[np.zeros(len(d), bool) for d in dets],
                       used_memory=[True] * 12)
        return occlusion_run(run, [frames])
    held = scored([both] * 12)
    assert len(held.gt) == 3 and all(len(g) == 2 for g in held.gt)
    assert held.num_points[0].tolist() == [1, 50]
    assert len(held.carried) == len(held.used_memory) == 3       # in step with the frames
    np.testing.assert_array_equal(held.ignore[1], bike)
    dropped = scored([behind] * 12)
    haunted = scored([both] * 4 + [with_ghost] * 3 + [both] * 5)
    ap = {k: r.evaluate(names).class_ap['car'] for k, r in
          (('held', held), ('dropped', dropped), ('haunted', haunted))}
    assert ap['held'] > ap['haunted'] and ap['held'] > ap['dropped'], ap
    with pytest.raises(ValueError, match='frames'):
        occlusion_run(replace(held, det=held.det[:2]), [frames])      # not the drives' run


@pytest.mark.slow
def test_outage_command_runs(tmp_path, capsys):
    import json

    from suit_ros.cli import main
    from suit_ros.outage import tables
    out = tmp_path / 'o.json'
    assert main(['outage', '--drives', '1', '--frames', '14', '--cache-dir',
                 str(tmp_path / 'cache'), '--json-out', str(out)]) == 0
    text = capsys.readouterr().out
    assert 'SUIT carry, tracker' in text and 'single frame' in text and out.is_file()
    assert 'occlusion events' in text and 'occlusion mAP' in text
    assert 'passing events' in text and 'passing mAP' in text
    assert 'SUIT carry - single frame' in text and 'SUIT carry - SUIT:' in text
    result = json.loads(out.read_text())
    assert set(result['passing']) == {'SUIT carry', 'SUIT carry, tracker', 'SUIT',
                                      'SUIT, tracker', 'single frame', 'single frame, tracker'}
    assert 'Passing occluders' in tables(result)
    assert set(result['counts']) == {'outage', 'occlusion', 'passing'}


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
            assert (r.held[coasted] == 2).all() and (r.held[~r.carried] == 0).all()  # coasted
            for b in r.detections.boxes[coasted]:
                assert np.hypot(*(f.gt.boxes[:, :2] - b[:2]).T).min() < 2.0
    assert sum(held[0.0]) == 0 and min(held[0.5]) >= 1, held
