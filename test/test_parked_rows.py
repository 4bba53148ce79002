"""Rows of parked cars along the kerbs (``Realism.parked_rows``): the worlds without them keep
their bytes and cache keys; the rows stand at the kerb, clear of each other and of every path
driven or walked during the drive, and the sensor sees them in part."""
from __future__ import annotations

import numpy as np
import pytest

from suit_ros import CLASS_NAMES
from suit_ros.data.sim import Realism, preset
from suit_ros.data.sim.parked_rows import CLEAR_END, park_rows
from suit_ros.data.sim.scene import Simulation, to_frame
from suit_ros.errors import ConfigError

CAR = CLASS_NAMES.index('car')


@pytest.fixture(scope='module')
def worlds():
    return (Simulation(preset('val-street-ends', frames=4), 9003),
            Simulation(preset('val-parked-rows', frames=4), 9003))


def rows_of(plain, rows):
    return rows.actors[len(plain.actors):]


def test_worlds_without_rows_keep_their_keys_and_values_are_checked():
    from suit_ros.data.sequences import _cache_key
    assert _cache_key('val-street-ends', 'hdl32e', 9001, 40) == '52d36ca031398c1e'
    assert _cache_key('val-parked-rows', 'hdl32e', 9001, 40) != '52d36ca031398c1e'
    # the rows' reversed share at its default (0.15, what the rows had before it was a field)
    assert _cache_key('val-parked-rows', 'hdl32e', 9001, 20) == 'f1fc79ab11fb9ada'
    assert _cache_key('val-parked-either', 'hdl32e', 9001, 20) != 'f1fc79ab11fb9ada'
    assert preset('val-street-ends').realism.parked_rows == 0.0
    for name in ('train-parked-rows', 'val-parked-rows'):
        r = preset(name).realism
        assert (r.parked_rows, r.street_objects, r.real_car_ends) == (0.5, 1.0, 1.0)
    with pytest.raises(ConfigError, match='parked_rows'):
        preset('test', realism=Realism(parked_rows=1.5))
    with pytest.raises(ConfigError, match='parked_reversed'):
        preset('test', realism=Realism(parked_rows=0.5, parked_reversed=-0.1))


def test_the_rest_of_the_world_is_unchanged(worlds):
    plain, rows = worlds
    assert len(rows.actors) > len(plain.actors)
    for a, b in zip(plain.actors, rows.actors):
        assert a.instance_id == b.instance_id and np.array_equal(a.size, b.size)
        assert np.array_equal(a.poly, b.poly) and np.array_equal(a.s, b.s)
    assert np.array_equal(plain.scene.parts, rows.scene.parts)
    assert park_rows(plain.actors, plain.ego, plain.world, Realism(parked_rows=0.0),
                     np.random.default_rng(0)) == []


def rects_touch(a, b, clear=0.0):
    """Whether two footprints (x, y, l, w, yaw) come within ``clear`` of each other (the
    separating axis test, written apart from the module's)."""
    def axes(r):
        u = np.array([np.cos(r[4]), np.sin(r[4])])
        return u, np.array([-u[1], u[0]])

    ua, va = axes(a)
    ub, vb = axes(b)
    d = b[:2] - a[:2]
    for n in (ua, va, ub, vb):
        ha = abs(n @ ua) * a[2] / 2 + abs(n @ va) * a[3] / 2
        hb = abs(n @ ub) * b[2] / 2 + abs(n @ vb) * b[3] / 2
        if abs(n @ d) > ha + hb + clear:
            return False
    return True


@pytest.fixture(scope='module')
def long_drive():
    """A 40-frame drive in the rows world (where the first version let a row car stand in a
    bus that drove off at the start) and the same drive without the rows."""
    return (Simulation(preset('val-street-ends', frames=40), 9000),
            Simulation(preset('val-parked-rows', frames=40), 9000))


@pytest.mark.parametrize('which', ['short', 'long'])
def test_rows_stand_at_the_kerb_clear_of_everything(worlds, long_drive, which):
    plain, rows = worlds if which == 'short' else long_drive
    new = rows_of(plain, rows)
    assert len(new) >= 20
    ids = [a.instance_id for a in new]
    assert len(set(ids)) == len(ids) and min(ids) > max(a.instance_id for a in plain.actors)
    world = rows.world
    right = 0
    for a in new:
        assert a.label == CAR and len(a.poly) == 1 and not a.v.any() and a.body is not None
        p = a.poly[0]
        axis = np.round(p / world.block) * world.block       # the nearest road's lines
        off = np.abs(p - axis)
        k = int(np.argmin(off))                              # across the road it stands on
        side = off[k] + a.size[1] / 2
        assert world.road_half_width - 0.36 <= side <= world.road_half_width - 0.14
        # its near end at least CLEAR_END from the crossing road's centre line
        assert off[1 - k] - a.size[0] / 2 >= CLEAR_END - 1e-6
        # the kerb on its right: it faces its side's traffic (right-hand traffic)
        heading = np.array([np.cos(a.heading), np.sin(a.heading)])
        to_kerb = np.zeros(2)
        to_kerb[k] = np.sign(p[k] - axis[k])
        right += heading @ np.array([-to_kerb[1], to_kerb[0]]) > 0.9
    assert 0.7 * len(new) <= right <= 0.97 * len(new)
    # at every rendered frame, no row car's footprint meets another actor's (the ego's
    # included), whatever drives past it, stands or walks
    ego_box = np.array([*rows.ego.size[:2]])
    n_old = len(plain.actors)
    for t in np.arange(0, 40, 3) * 0.1:
        boxes, _ = rows.actor_boxes(t)
        fp = boxes[:, [0, 1, 3, 4, 6]]
        ex, ey, eyaw, _, _ = rows.ego.state(t)
        others = np.concatenate([fp, [[ex, ey, *ego_box, eyaw]]])
        for i in range(n_old, len(fp)):
            near = np.flatnonzero(np.hypot(*(others[:, :2] - fp[i, :2]).T) < 12.0)
            for j in near[near != i]:
                assert not rects_touch(fp[i], others[j], 0.15), (t, i, j)
    # rows: most cars have a neighbour in line within 3 m of their end
    rowed = [np.array([a.poly[0, 0], a.poly[0, 1], a.size[0], a.size[1], a.heading])
             for a in new]
    close = sum(any(rects_touch(b, o, 3.0) and abs(np.sin(b[4] - o[4])) < 0.1
                    for o in rowed if o is not b) for b in rowed)
    assert close >= 0.6 * len(rowed)


def test_a_full_share_ends(worlds):
    """Every kerb lined (share 1): each kerb ends when the next car no longer fits."""
    plain, _ = worlds
    full = park_rows(plain.actors, plain.ego, plain.world,
                     Realism(parked_rows=1.0, real_car_ends=1.0), np.random.default_rng(3))
    half = park_rows(plain.actors, plain.ego, plain.world,
                     Realism(parked_rows=0.5, real_car_ends=1.0), np.random.default_rng(3))
    assert len(full) > 1.3 * len(half) > 0


def test_the_sensor_sees_the_rows_and_gt_keeps_them(worlds):
    plain, rows = worlds
    new = {a.instance_id for a in rows_of(plain, rows)}
    f = to_frame(rows.render(2), 9003)
    g = f.gt
    near = np.hypot(*g.boxes[:, :2].T) < 50
    in_rows = np.isin(f.instance_ids, list(new))
    seen = in_rows & near & (f.num_points > 0)
    assert (g.labels[in_rows] == CAR).all()
    # many of them, some only in part (a neighbour hides the rest)
    assert seen.sum() >= 5
    assert (f.num_points[seen] < 15).any() and (f.num_points[seen] > 40).any()
    plain_cars = (to_frame(plain.render(2), 9003).gt.labels == CAR).sum()
    assert (g.labels == CAR).sum() >= plain_cars + 5


def test_compare_scores_the_rows_world():
    """``compare --variant 'tracking, parked rows'``: the validation drives with rows, scored
    on their own labels (the rows' cars counted)."""
    from suit_ros.compare import VARIANTS, variant_run
    from suit_ros.config import model_config_from_dict
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.model.detector import SUITDetector
    assert {'parked rows', 'tracking, parked rows'} <= set(VARIANTS)
    drives = synthetic_split('val', 1, 2)
    model = SUITDetector(model_config_from_dict({'temporal': 'none'}, 'test')).eval()
    plain = variant_run('unused', model, 'tracking', drives, 'float32')
    rows = variant_run('unused', model, 'tracking, parked rows', drives, 'float32')
    assert rows is not None and len(rows.gt) == len(plain.gt) == 2
    for a, b in zip(rows.gt, plain.gt):
        assert (a.labels == CAR).sum() > (b.labels == CAR).sum()


def test_either_way_parks_half_the_row_cars_against_traffic(worlds):
    """``parked_reversed`` 0.5 (``*-parked-either``): the side of the road says nothing of a
    parked car's heading; the same rows as at 0.15 otherwise (same draws)."""
    plain, rows = worlds
    either = Simulation(preset('val-parked-either', frames=4), 9003)
    a, b = rows_of(plain, rows), rows_of(plain, either)
    assert len(a) >= 20
    assert [x.poly.tolist() for x in a] == [x.poly.tolist() for x in b]
    turned = np.array([np.cos(x.heading - y.heading) < -0.9 for x, y in zip(a, b)])
    kept = np.array([np.cos(x.heading - y.heading) > 0.9 for x, y in zip(a, b)])
    assert (turned | kept).all() and 0.2 * len(a) <= turned.sum() <= 0.55 * len(a)
    assert Realism(parked_rows=0.5).parked_reversed == 0.15
