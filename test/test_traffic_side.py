"""``traffic_side: auto``: the side of the road read from the oncoming tracked vehicles
(suit_ros/traffic_side.py); numpy inputs, and the shipped model on a validation drive."""
from __future__ import annotations

import numpy as np
import pytest

from suit_ros.ops.geometry import pose_from_xyz_rpy
from suit_ros.traffic_side import SideVoteConfig, TrafficSideVote

NAMES = ('car', 'truck', 'pedestrian', 'cyclist')
BASE = np.eye(4)
S = 10**9


class Ego:
    """The ego driving straight along x at ``speed`` m/s, one pose per 0.1 s."""

    def __init__(self, speed=10.0):
        self.speed, self.k = speed, 0

    def pose(self):
        T = np.eye(4)
        T[0, 3] = self.speed * 0.1 * self.k
        self.k += 1
        return T, self.k * S // 10


def fresh(names=NAMES, speed=10.0):
    """A vote and its ego, the ego's first pose given (its speed known from the next)."""
    vote, ego = TrafficSideVote(names), Ego(speed)
    vote.update(*frame(), BASE, *ego.pose())
    return vote, ego


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


def step(vote, ego, *cars, T=BASE):
    """One update: ``cars`` (see :func:`frame`) seen from the ego's next pose."""
    return vote.update(*frame(*cars), T, *ego.pose())


def drive_past(vote, ego, tid, y, frames=3, speed=10.0):
    """A vehicle coming by the ego ``y`` m beside it for ``frames`` updates; returns
    whether the side changed at any of them."""
    changed = False
    for k in range(frames):
        changed |= step(vote, ego, (tid, 10.0 - 2.0 * k, y, -speed, 0.0))
    return changed


def test_oncoming_vehicles_on_the_left_keep_right_hand_traffic():
    vote, ego = fresh()
    for tid in range(1, 8):
        assert not drive_past(vote, ego, tid, 4.0)
    assert vote.side == 'right' and vote.counts == (5, 0) and vote.switches == 0
    assert 'of the latest 5 oncoming vehicles, 5 passed on the left' in vote.describe()


def test_four_oncoming_vehicles_on_the_right_switch_to_left_hand_traffic():
    assert TrafficSideVote(NAMES).describe() == 'right (auto: no odometry: no tracked velocities)'
    vote, ego = fresh()
    assert vote.describe() == 'right (auto: no oncoming traffic seen yet)'
    for tid, y in ((1, -4.0), (2, -3.5), (3, -7.0)):
        assert not drive_past(vote, ego, tid, y)
    assert vote.side == 'right' and vote.counts == (0, 3)
    # the fourth vehicle votes on its third frame, and the side changes then
    assert not drive_past(vote, ego, 4, -6.0, frames=2)
    assert step(vote, ego, (4, 4.0, -6.0, -9.0, 0.5))
    assert vote.side == 'left' and vote.switches == 1
    # votes for the side in use change nothing; 4 of the latest 5 the other way change back
    assert not drive_past(vote, ego, 5, -4.0)
    for tid in (6, 7, 8):
        assert not drive_past(vote, ego, tid, 4.0)
    assert drive_past(vote, ego, 9, 4.0) and vote.side == 'right' and vote.switches == 2


def test_a_vehicle_votes_once_however_long_it_is_seen():
    vote, ego = fresh()
    for _ in range(30):
        step(vote, ego, (7, 5.0, -4.0, -10.0, 0.0))
    assert vote.counts == (0, 1) and vote.side == 'right'


@pytest.mark.parametrize('car', [
    (1, 5.0, -4.0, 0.0, 0.0),           # parked
    (1, 5.0, -4.0, -2.5, 0.0),          # too slow
    (1, 5.0, -4.0, -4.5, 0.0),          # slower than half the ego's 10 m/s
    (1, 5.0, -4.0, 10.0, 0.0),          # the same direction as the ego
    (1, 5.0, -4.0, -3.0, 9.0),          # crossing
    (1, 5.0, -1.0, -10.0, 0.0),         # the ego's own lane
    (1, 5.0, -12.0, -10.0, 0.0),        # far beside (a parallel road)
    (1, 30.0, -4.0, -10.0, 0.0),        # far ahead (a bend can move its lane across)
    (0, 5.0, -4.0, -10.0, 0.0),         # untracked
    (1, 5.0, -4.0, -10.0, 0.0, 3),      # a cyclist
    (1, 5.0, -4.0, -10.0, 0.0, 2),      # a pedestrian
])
def test_what_casts_no_vote(car):
    vote, ego = fresh()
    for _ in range(5):
        step(vote, ego, car)
    assert vote.counts == (0, 0)
    fine, ego = fresh()        # the same vehicle oncoming beside: a vote
    for _ in range(5):
        step(fine, ego, (1, 5.0, -4.0, -10.0, 0.0))
    assert fine.counts == (0, 1)


@pytest.mark.parametrize('speed', [0.0, 1.5, -5.0])
def test_nothing_votes_while_the_ego_stands_or_reverses(speed):
    """A standing ego (or a frozen odometry: the parked cars beside a moving ego then look
    oncoming) and one reversing cast no votes; nor without odometry."""
    vote, ego = fresh(speed=speed)
    for k in range(5):
        step(vote, ego, (1, 5.0 - k, -4.0, -10.0, 0.0))
    assert vote.counts == (0, 0)
    blind = TrafficSideVote(NAMES)
    for k in range(5):
        assert not blind.update(*frame((1, 5.0 - k, -4.0, -10.0, 0.0)), BASE, None, k * S // 10)
    assert blind.counts == (0, 0) and 'no odometry' in blind.describe()
    late = TrafficSideVote(NAMES)                   # poses 2 s apart: no speed, no vote
    for k in range(5):
        T = np.eye(4)
        T[0, 3] = 20.0 * k
        late.update(*frame((1, 5.0 - k, -4.0, -10.0, 0.0)), BASE, T, 2 * k * S)
    assert late.counts == (0, 0) and np.isnan(late.ego_speed)


def test_trucks_vote_and_the_class_names_say_which_label_is_a_vehicle():
    vote, ego = fresh()
    for _ in range(3):
        step(vote, ego, (1, 5.0, -4.0, -10.0, 0.0, 1))
    assert vote.counts == (0, 1)
    other, ego = fresh(('pedestrian', 'car'))     # the car is label 1 here
    for _ in range(3):
        step(other, ego, (1, 5.0, -4.0, -10.0, 0.0, 0), (2, 5.0, -4.0, -10.0, 0.0, 1))
    assert other.counts == (0, 1)


def test_a_false_change_is_undone_as_fast_as_it_was_made():
    """3 contrary votes among right ones change nothing; 4 of the latest 5 do, either way."""
    vote, ego = fresh()
    for tid in range(1, 16):
        drive_past(vote, ego, tid, 4.0)
    for tid in (20, 21, 22):
        assert not drive_past(vote, ego, tid, -4.0)
    assert vote.side == 'right' and vote.counts == (2, 3)
    assert drive_past(vote, ego, 23, -4.0) and vote.side == 'left'
    for tid in (30, 31, 32):
        assert not drive_past(vote, ego, tid, 4.0)
    assert drive_past(vote, ego, 33, 4.0) and vote.side == 'right'


def test_the_vote_reads_the_detections_in_the_base_frame():
    """A LiDAR mounted turned round (yaw 180 degrees) and to the side: boxes and velocities
    in its frame say the same as in the base frame."""
    T = pose_from_xyz_rpy((1.0, 0.5, 1.8), (0.0, 0.0, np.pi))
    inverse = np.linalg.inv(T)
    vote, ego = fresh()
    for tid in (1, 2, 3, 4):
        for k in range(3):
            p = inverse @ np.array([10.0 - 2 * k, -4.0, 0.0, 1.0])   # base: on the right
            v = inverse[:2, :2] @ np.array([-10.0, 0.0])
            step(vote, ego, (tid, p[0], p[1], v[0], v[1]), T=T)
    assert vote.side == 'left' and vote.counts == (0, 4)


def test_restart_forgets_the_votes_and_the_tracks():
    vote, ego = fresh()
    drive_past(vote, ego, 1, -4.0)
    drive_past(vote, ego, 2, -4.0, frames=2)         # seen twice, not yet voted
    vote.restart('left')
    assert vote.side == 'left' and vote.counts == (0, 0)
    drive_past(vote, ego, 2, -4.0, frames=1)         # its third time, counted from none
    assert vote.counts == (0, 0)
    drive_past(vote, ego, 2, -4.0, frames=2)
    assert vote.counts == (0, 1)


def test_an_invalid_config_is_refused():
    for bad in ({'min_votes': 0}, {'min_votes': 2}, {'min_votes': 6}, {'oncoming_angle': 95},
                {'min_lateral': 30.0}, {'frames': 0}, {'min_speed': 0.0},
                {'min_ego_speed': 0.0}):
        with pytest.raises(ValueError, match='SideVoteConfig'):
            SideVoteConfig(**bad)


@pytest.mark.slow
def test_the_shipped_model_reads_left_hand_traffic_from_a_mirrored_drive():
    """The shipped model and the node's tracker on a validation drive with oncoming traffic:
    mirrored (left-hand traffic) ``auto`` goes over to ``left`` within its first 4 seconds
    and from the next frame on gives the model the drive mirrored (its boxes then as
    ``left``'s after a reset); as it is (right-hand), ``auto`` stays right and gives
    ``right``'s boxes."""
    from suit_ros.checkpoint import load_checkpoint
    from suit_ros.data.augment import mirror_world
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.evaluate import run_model
    from suit_ros.tracking import TrackerConfig
    drive = synthetic_split('val', 1, 40, first=13)[0]
    model, _, _ = load_checkpoint('suit_default')
    mirrored = [mirror_world(f) for f in drive]
    auto = run_model(model, [mirrored], tracker=TrackerConfig(), traffic_side='auto')
    switch = auto.sides.index('left')
    assert 10 <= switch <= 38 and set(auto.sides[switch:]) == {'left'}
    left = run_model(model, [mirrored[switch:]], tracker=TrackerConfig(), traffic_side='left')
    assert len(left.det) == len(drive) - switch
    for a, b in zip(auto.det[switch:], left.det):
        assert len(a) > 3
        np.testing.assert_allclose(a.boxes, b.boxes, atol=1e-3)
    plain = run_model(model, [drive], tracker=TrackerConfig(), traffic_side='auto')
    right = run_model(model, [drive], tracker=TrackerConfig())
    assert set(plain.sides) == {'right'}
    for a, b in zip(plain.det, right.det):
        assert len(a) > 3
        np.testing.assert_array_equal(a.boxes, b.boxes)
    with pytest.raises(ValueError, match='history'):
        run_model(model, [drive], tracker=TrackerConfig(), traffic_side='auto', history=2)


def test_report_and_eval_take_the_recordings_side_else_the_nodes_default():
    """``--traffic-side auto`` of ``report`` and ``eval``: the side a dataset says (nuScenes'
    log location), else the node's default ``traffic_side``; a side given is every drive's."""
    from suit_ros.params import DetectorParams
    from suit_ros.report import traffic_sides
    assert traffic_sides('left', 2, ['right', 'right']) == ['left', 'left']
    assert traffic_sides('auto', 2, ['left', 'right']) == ['left', 'right']
    assert traffic_sides('auto', 3, None) == [DetectorParams().traffic_side] * 3
