"""Pedestrians standing close in front of buildings and walls (``Realism.at_fronts``): the worlds
without it keep their bytes and cache keys; those moved stand still on the sidewalk 0.1-0.5 m
in front of a building or a lot wall (their turned boxes), out of the walkers' way, clear of
everything else and of the bystanders, and the sensor sees them."""
from __future__ import annotations

import numpy as np
import pytest
from test_bystanders import box_gap, only_the_chosen_move  # the helpers both worlds share

from suit_ros import CLASS_NAMES
from suit_ros.compare import VARIANTS, WORLDS
from suit_ros.data.sim import Realism, preset
from suit_ros.data.sim.bystanders import (
    FRONT_DEPTH,
    SOLID_TYPES,
    chosen,
    front_chosen,
    fronts,
    place_at_fronts,
    sidewalk_distance,
)
from suit_ros.data.sim.clutter import CLUTTER_ID
from suit_ros.data.sim.scene import Simulation
from suit_ros.errors import ConfigError

PED = CLASS_NAMES.index('pedestrian')


@pytest.fixture(scope='module')
def worlds():
    return (Simulation(preset('val-street-ends', frames=4), 9001),
            Simulation(preset('val-fronts', frames=4), 9001))


def outline(a, n=12):
    """Points along the edges of a standing actor's turned footprint ``(4 n, 2)``."""
    c, s = np.cos(a.heading), np.sin(a.heading)
    t = np.linspace(-0.5, 0.5, n)
    local = np.concatenate([np.stack([t, np.full(n, k)], 1) for k in (-0.5, 0.5)]
                           + [np.stack([np.full(n, k), t], 1) for k in (-0.5, 0.5)])
    local = local * a.size[:2]
    return a.poly[0] + local @ np.array([[c, s], [-s, c]])


def test_worlds_without_fronts_keep_their_keys():
    from suit_ros.data.sequences import _cache_key
    # the keys these drives were cached under before the option existed (cache version 3)
    assert _cache_key('val-street-ends', 'hdl32e', 9001, 40) == '52d36ca031398c1e'
    assert _cache_key('val-real', 'sim32', 9000, 40) == 'a66fafdfe5c2ae10'
    assert _cache_key('val-fronts', 'hdl32e', 9001, 40) != '52d36ca031398c1e'
    assert preset('val-street-ends').realism.at_fronts == 0.0
    for name in ('train-fronts', 'val-fronts'):
        r = preset(name).realism
        assert (r.at_fronts, r.street_objects, r.real_car_ends, r.bystanders) == (
            0.5, 1.0, 1.0, 0.0)
    assert WORLDS['fronts'] == 'val-fronts' and {'fronts', 'tracking, fronts'} <= set(VARIANTS)
    with pytest.raises(ConfigError, match='at_fronts'):
        preset('test', realism=Realism(at_fronts=-0.1))


def test_only_the_chosen_pedestrians_move(worlds):
    only_the_chosen_move(*worlds, lambda i: front_chosen(i, 0.5))


def test_they_stand_close_in_front_of_a_building_on_the_sidewalk(worlds):
    plain, busy = worlds
    scene, world = busy.scene, busy.world
    front, _ = fronts(scene, world)
    line = world.road_half_width + world.sidewalk_width + 1.0
    # the layout's buildings and lot walls' pieces, not the garden walls nor the gates
    walls = scene.objects[scene.types == CLUTTER_ID['wall']]
    garden = walls[sidewalk_distance(walls[:, :2], world) < line - 0.2]
    assert len(garden) > 0 and len(front) > 0
    assert (sidewalk_distance(front[:, :2], world) > line - 0.2).all()
    parked = np.array([[a.poly[0, 0], a.poly[0, 1], 0, *a.size, a.heading] for a in busy.actors
                       if len(a.poly) == 1 and a.label != PED])
    solid = np.concatenate([scene.objects[np.isin(scene.types, [CLUTTER_ID[t]
                                                                for t in SOLID_TYPES])], parked])
    spots = []
    for a, b in zip(plain.actors, busy.actors):
        if b.label != PED or np.array_equal(a.poly, b.poly):
            continue
        assert len(b.poly) == 1 and b.v.max() == 0 and b.s.max() == 0
        p = b.poly[0]
        edge = outline(b)
        gaps = np.array([box_gap(q, front) for q in edge]).min(0)
        assert 0.1 - 1e-6 < gaps.min() < 0.5 + 1e-6, gaps.min()   # its box 0.1-0.5 m off
        assert (np.array([box_gap(q, solid) for q in edge]) > 0).all()   # inside nothing
        d = sidewalk_distance(edge, world)
        assert d.min() >= max(line - FRONT_DEPTH, world.road_half_width + 0.2) - 1e-6
        assert sidewalk_distance(p[None, :], world)[0] <= line          # the street side
        spots.append(p)
    spots = np.array(spots)
    pair = np.linalg.norm(spots[:, None] - spots[None], axis=2) + 9 * np.eye(len(spots))
    assert pair.min() > 1.0
    # what the option adds: the walkers keep 1.5 m or more off the building line, so none
    # walks through one standing there
    walkers = [a for a in busy.actors if a.label == PED and len(a.poly) > 1]
    path = np.concatenate([a.poly for a in walkers])
    near = path[sidewalk_distance(path, world) < line]
    assert (line - sidewalk_distance(near, world)).min() > FRONT_DEPTH + 0.35


def test_the_sensor_sees_them(worlds):
    plain, busy = worlds
    moved = {b.instance_id for a, b in zip(plain.actors, busy.actors)
             if b.label == PED and not np.array_equal(a.poly, b.poly)}
    seen = 0
    for k in range(4):
        f = busy.render(k)
        seen += sum(int(i in moved and n > 0) for i, n in zip(f.instance_ids, f.num_points))
    assert seen > 0


def test_bystanders_are_left_where_they_stand():
    both = Simulation(preset('val-fronts', frames=1, realism=Realism(
        real_car_ends=1.0, street_objects=1.0, bystanders=0.5, at_fronts=0.5)), 9001)
    alone = Simulation(preset('val-bystanders', frames=1), 9001)
    standing, at_front = [], []
    for a, b in zip(alone.actors, both.actors):
        if a.label == PED and chosen(a.instance_id, 0.5) and len(a.poly) == 1:
            np.testing.assert_array_equal(a.poly, b.poly)      # a bystander stays put
            standing.append(a.poly[0])
        elif b.label == PED and len(b.poly) == 1:
            at_front.append(b.poly[0])
    assert standing and at_front
    gap = np.linalg.norm(np.array(standing)[:, None] - np.array(at_front)[None], axis=2)
    assert gap.min() > 1.0                                     # none stands on a bystander


def test_nothing_moves_without_a_share_or_fronts(worlds):
    _, busy = worlds
    assert place_at_fronts(busy.actors, busy.scene, busy.world, 0.0,
                           np.random.default_rng(0)) == []
    empty = type(busy.scene)(*(getattr(busy.scene, n)[:0] for n in (
        'parts', 'reflectivity', 'return_prob', 'porosity', 'owner', 'objects', 'types')))
    assert place_at_fronts(busy.actors, empty, busy.world, 1.0, np.random.default_rng(0)) == []
