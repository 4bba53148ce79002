"""Pedestrians standing beside street objects and parked cars (``Realism.bystanders``): the
worlds without it keep their bytes and cache keys; those moved stand still, on the sidewalk,
beside an anchor and clear of everything else, and the sensor sees them."""
from __future__ import annotations

import numpy as np
import pytest

from suit_ros import CLASS_NAMES
from suit_ros.data.sim import Realism, preset
from suit_ros.data.sim.bystanders import (
    ANCHOR_TYPES,
    SOLID_TYPES,
    chosen,
    place_bystanders,
    sidewalk_distance,
)
from suit_ros.data.sim.clutter import CLUTTER_ID
from suit_ros.data.sim.scene import Simulation
from suit_ros.errors import ConfigError

PED = CLASS_NAMES.index('pedestrian')


@pytest.fixture(scope='module')
def worlds():
    return (Simulation(preset('val-street-ends', frames=4), 9001),
            Simulation(preset('val-bystanders', frames=4), 9001))


def box_gap(p, boxes):
    """Distance from a point to each oriented footprint's edge (0 inside)."""
    d = p[None, :] - boxes[:, :2]
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    u = np.abs(c * d[:, 0] + s * d[:, 1]) - boxes[:, 3] / 2
    v = np.abs(-s * d[:, 0] + c * d[:, 1]) - boxes[:, 4] / 2
    return np.hypot(np.maximum(u, 0), np.maximum(v, 0))


def test_worlds_without_bystanders_keep_their_keys():
    from suit_ros.data.sequences import _cache_key
    # the keys the street-objects validation drives were cached under before this existed
    # (cache version 3 since 2026-12-06)
    assert _cache_key('val-street-ends', 'hdl32e', 9001, 40) == '52d36ca031398c1e'
    assert _cache_key('val-real', 'sim32', 9000, 40) == 'a66fafdfe5c2ae10'
    assert _cache_key('val-bystanders', 'hdl32e', 9001, 40) != '52d36ca031398c1e'
    assert preset('val-street-ends').realism.bystanders == 0.0
    for name in ('train-bystanders', 'val-bystanders'):
        r = preset(name).realism
        assert (r.bystanders, r.street_objects, r.real_car_ends) == (0.5, 1.0, 1.0)
    with pytest.raises(ConfigError, match='bystanders'):
        preset('test', realism=Realism(bystanders=1.5))


def only_the_chosen_move(plain, busy, choose):
    """The pedestrians ``choose(instance_id)`` picks are about half and nearly all moved from
    where they stood in ``plain``; every other actor and the static scene are as they were."""
    assert len(plain.actors) == len(busy.actors)
    moved = 0
    for a, b in zip(plain.actors, busy.actors):
        assert a.instance_id == b.instance_id and np.array_equal(a.size, b.size)
        same = np.array_equal(a.poly, b.poly) and np.array_equal(a.s, b.s)
        if a.label != PED or not choose(a.instance_id):
            assert same and np.array_equal(a.body.parts, b.body.parts)
        elif not same:
            moved += 1
    peds = [a for a in plain.actors if a.label == PED]
    wanted = sum(choose(a.instance_id) for a in peds)
    assert 0.3 * len(peds) < wanted < 0.7 * len(peds)
    assert moved >= 0.8 * wanted                     # nearly all find a place within reach
    np.testing.assert_array_equal(plain.scene.objects, busy.scene.objects)


def test_only_the_chosen_pedestrians_move(worlds):
    only_the_chosen_move(*worlds, lambda i: chosen(i, 0.5))


def test_bystanders_stand_beside_an_anchor_on_the_sidewalk(worlds):
    plain, busy = worlds
    scene, world = busy.scene, busy.world
    anchors = scene.objects[np.isin(scene.types, [CLUTTER_ID[t] for t in ANCHOR_TYPES])]
    parked = np.array([[a.poly[0, 0], a.poly[0, 1], 0, *a.size, a.heading] for a in busy.actors
                       if len(a.poly) == 1 and a.label != PED])
    anchors = np.concatenate([anchors, parked])
    solid = np.concatenate([scene.objects[np.isin(scene.types, [CLUTTER_ID[t]
                                                                for t in SOLID_TYPES])], parked])
    spots = []
    for a, b in zip(plain.actors, busy.actors):
        if b.label != PED or np.array_equal(a.poly, b.poly):
            continue
        assert len(b.poly) == 1 and b.v.max() == 0 and b.s.max() == 0
        p = b.poly[0]
        half = max(b.size[0], b.size[1]) / 2
        gaps = box_gap(p, anchors) - half
        assert 0.05 < gaps.min() < 0.65, gaps.min()       # 0.1-0.6 m off its anchor
        assert (box_gap(p, solid) - half > 0.05).all()    # inside nothing
        d = sidewalk_distance(p[None, :], world)[0]
        assert world.road_half_width + 0.2 + half - 1e-9 <= d       # not on the road
        spots.append(p)
    spots = np.array(spots)
    pair = np.linalg.norm(spots[:, None] - spots[None], axis=2) + 9 * np.eye(len(spots))
    assert pair.min() > 1.0


def test_the_sensor_sees_bystanders_and_gt_keeps_them(worlds):
    _, busy = worlds
    moved = {a.instance_id for a in busy.actors if a.label == PED and len(a.poly) == 1}
    seen = 0
    for k in range(4):
        f = busy.render(k)
        for inst, n in zip(f.instance_ids, f.num_points):
            seen += int(inst in moved and n > 0)
    assert seen > 0


def test_nothing_moves_without_a_share_or_anchors(worlds):
    _, busy = worlds
    assert place_bystanders(busy.actors, busy.scene, busy.world, 0.0,
                            np.random.default_rng(0)) == []
    empty = type(busy.scene)(*(getattr(busy.scene, n)[:0] for n in (
        'parts', 'reflectivity', 'return_prob', 'porosity', 'owner', 'objects', 'types')))
    walkers = [a for a in busy.actors if len(a.poly) > 1]
    assert place_bystanders(walkers, empty, busy.world, 1.0, np.random.default_rng(0)) == []


def test_sidewalk_distance_is_from_the_nearest_road_axis():
    world = Simulation(preset('test-real', frames=1), 1).world
    b = world.block
    xy = np.array([[3.0, 0.5 * b], [0.5 * b, b - 8.0], [b + 9.0, 2 * b + 30.0]])
    np.testing.assert_allclose(sidewalk_distance(xy, world), [3.0, 8.0, 9.0])
