"""``traffic_side: auto``: the side of the road read from the oncoming tracked vehicles
(suit_ros/traffic_side.py); numpy inputs, and the shipped model on a validation drive."""
from __future__ import annotations

import numpy as np
import pytest

from suit_ros.ops.geometry import pose_from_xyz_rpy
from suit_ros.traffic_side import SideVoteConfig, TrafficSideVote

NAMES = ('car', 'truck', 'pedestrian', 'cyclist')
BASE = np.eye(4)


def frame(*cars):
    """One frame's tracked boxes: each car ``(track id, x, y, vx, vy[, label])`` in the base
    frame."""
    boxes = np.zeros((len(cars), 7), np.float32)
    vel = np.zeros((len(cars), 2), np.float32)
    labels = np.zeros(len(cars), np.int64)
    ids = np.zeros(len(cars), np.int64)
    for i, car in enumerate(cars):
        ids[i], boxes[i, 0], boxes[i, 1], vel[i, 0], vel[i, 1] = car[:5]
        labels[i] = car[5] if len(car) > 5 else 0
        boxes[i, 3:6] = 4.5, 1.9, 1.6
    return boxes, vel, labels, ids


def drive_past(vote, tid, y, frames=3, T=BASE, speed=10.0):
    """A vehicle coming towards the ego ``y`` m beside it for ``frames`` updates; returns
    whether the side changed at any of them."""
    changed = False
    for k in range(frames):
        changed |= vote.update(*frame((tid, 30.0 - 1.0 * k, y, -speed, 0.0)), T)
    return changed


def test_oncoming_vehicles_on_the_left_keep_right_hand_traffic():
    vote = TrafficSideVote(NAMES)
    for tid in range(1, 6):
        assert not drive_past(vote, tid, 4.0)
    assert vote.side == 'right' and vote.counts == (5, 0) and vote.switches == 0
    assert 'of the latest 5 oncoming vehicles, 5 passed on the left' in vote.describe()


def test_three_oncoming_vehicles_on_the_right_switch_to_left_hand_traffic():
    vote = TrafficSideVote(NAMES)
    assert vote.describe() == 'right (auto: no oncoming traffic seen yet)'
    assert not drive_past(vote, 1, -4.0) and not drive_past(vote, 2, -3.5)
    assert vote.side == 'right' and vote.counts == (0, 2)
    # the third vehicle votes on its third frame, and the side changes then
    assert not drive_past(vote, 3, -6.0, frames=2)
    assert vote.update(*frame((3, 20.0, -6.0, -9.0, 0.5)), BASE)
    assert vote.side == 'left' and vote.switches == 1
    # votes for the side in use change nothing
    assert not drive_past(vote, 4, -4.0) and vote.side == 'left'


def test_a_vehicle_votes_once_however_long_it_is_seen():
    vote = TrafficSideVote(NAMES)
    drive_past(vote, 7, -4.0, frames=30)
    assert vote.counts == (0, 1) and vote.side == 'right'


@pytest.mark.parametrize('car', [
    (1, 20.0, -4.0, 0.0, 0.0),          # parked
    (1, 20.0, -4.0, 1.5, 0.5),          # too slow
    (1, 20.0, -4.0, 10.0, 0.0),         # the same direction as the ego
    (1, 20.0, -4.0, -3.0, 9.0),         # crossing
    (1, 20.0, -0.5, -10.0, 0.0),        # the ego's own lane
    (1, 20.0, -25.0, -10.0, 0.0),       # far beside
    (1, 80.0, -4.0, -10.0, 0.0),        # far ahead
    (0, 20.0, -4.0, -10.0, 0.0),        # untracked
    (1, 20.0, -4.0, -10.0, 0.0, 3),     # a cyclist
    (1, 20.0, -4.0, -10.0, 0.0, 2),     # a pedestrian
])
def test_what_casts_no_vote(car):
    vote = TrafficSideVote(NAMES)
    for _ in range(5):
        vote.update(*frame(car), BASE)
    assert vote.counts == (0, 0)


def test_trucks_vote_and_the_class_names_say_which_label_is_a_vehicle():
    vote = TrafficSideVote(NAMES)
    for _ in range(3):
        vote.update(*frame((1, 20.0, -4.0, -10.0, 0.0, 1)), BASE)
    assert vote.counts == (0, 1)
    other = TrafficSideVote(('pedestrian', 'car'))          # the car is label 1 here
    for _ in range(3):
        other.update(*frame((1, 20.0, -4.0, -10.0, 0.0, 0)), BASE)
        other.update(*frame((2, 20.0, -4.0, -10.0, 0.0, 1)), BASE)
    assert other.counts == (0, 1)


def test_a_long_stretch_on_one_side_outweighs_a_few_contrary_votes():
    vote = TrafficSideVote(NAMES)
    for tid in range(1, 16):
        drive_past(vote, tid, 4.0)
    for tid in range(100, 111):          # 11 of the latest 15 say left: not enough (12)
        assert not drive_past(vote, tid, -4.0)
    assert vote.side == 'right' and vote.counts == (4, 11)
    assert drive_past(vote, 111, -4.0)
    assert vote.side == 'left' and vote.counts == (3, 12)


def test_the_vote_reads_the_detections_in_the_base_frame():
    """A LiDAR mounted turned round (yaw 180 degrees) and to the side: boxes and velocities
    in its frame say the same as in the base frame."""
    T = pose_from_xyz_rpy((1.0, 0.5, 1.8), (0.0, 0.0, np.pi))
    inverse = np.linalg.inv(T)
    vote = TrafficSideVote(NAMES)
    for tid in (1, 2, 3):
        for k in range(3):
            x, y = 30.0 - k, -4.0                      # base frame: oncoming on the right
            p = inverse @ np.array([x, y, 0.0, 1.0])
            v = inverse[:2, :2] @ np.array([-10.0, 0.0])
            vote.update(*frame((tid, p[0], p[1], v[0], v[1])), T)
    assert vote.side == 'left' and vote.counts == (0, 3)


def test_restart_forgets_the_votes():
    vote = TrafficSideVote(NAMES)
    drive_past(vote, 1, -4.0)
    vote.restart('left')
    assert vote.side == 'left' and vote.counts == (0, 0)
    drive_past(vote, 1, 4.0, frames=1)      # the track seen before the restart starts over
    assert vote.counts == (0, 0)


def test_an_invalid_config_is_refused():
    for bad in ({'min_votes': 0}, {'min_votes': 20}, {'share': 0.5}, {'oncoming_angle': 95},
                {'min_lateral': 30.0}, {'frames': 0}, {'min_speed': 0.0}):
        with pytest.raises(ValueError, match='SideVoteConfig'):
            SideVoteConfig(**bad)


@pytest.mark.slow
def test_the_shipped_model_reads_left_hand_traffic_from_a_mirrored_drive():
    """The shipped model and the node's tracker on a validation drive with oncoming traffic:
    mirrored (left-hand traffic) ``auto`` goes over to ``left`` within its first second and
    from the next frame on gives the model the drive mirrored (its boxes then as ``left``'s
    after a reset); as it is (right-hand), ``auto`` stays right and gives ``right``'s boxes."""
    from suit_ros.checkpoint import load_checkpoint
    from suit_ros.data.augment import mirror_world
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.evaluate import run_model
    from suit_ros.tracking import TrackerConfig
    drive = synthetic_split('val', 1, 12, first=13)[0]
    model, _, _ = load_checkpoint('suit_default')
    mirrored = [mirror_world(f) for f in drive]
    auto = run_model(model, [mirrored], tracker=TrackerConfig(), traffic_side='auto')
    switch = auto.sides.index('left')
    assert 2 <= switch <= 10 and set(auto.sides[switch:]) == {'left'}
    left = run_model(model, [mirrored[switch:]], tracker=TrackerConfig(), traffic_side='left')
    for a, b in zip(auto.det[switch:], left.det):
        np.testing.assert_allclose(a.boxes, b.boxes, atol=1e-3)
    plain = run_model(model, [drive], tracker=TrackerConfig(), traffic_side='auto')
    right = run_model(model, [drive], tracker=TrackerConfig())
    assert set(plain.sides) == {'right'}
    for a, b in zip(plain.det, right.det):
        np.testing.assert_array_equal(a.boxes, b.boxes)


def test_report_and_eval_take_the_recordings_side_else_the_nodes_default():
    """``--traffic-side auto`` of ``report`` and ``eval``: the side a dataset says (nuScenes'
    log location), else the node's default ``traffic_side``; a side given is every drive's."""
    from suit_ros.params import DetectorParams
    from suit_ros.report import traffic_sides
    assert traffic_sides('left', 2, ['right', 'right']) == ['left', 'left']
    assert traffic_sides('auto', 2, ['left', 'right']) == ['left', 'right']
    assert traffic_sides('auto', 3, None) == [DetectorParams().traffic_side] * 3
