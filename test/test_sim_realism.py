"""The detailed synthetic world: the box world is untouched, actors have a front and a back,
glass and hedges pass rays, clutter stays out of GT, and false positives on clutter count."""
from __future__ import annotations

from dataclasses import replace
import hashlib
from types import SimpleNamespace

import numpy as np
import pytest

from suit_ros.data.sim import Realism, preset
from suit_ros.data.sim.bodies import car_body, parked_bicycle_body
from suit_ros.data.sim.clutter import CLUTTER_ID, CLUTTER_TYPES, clutter_false_positives
from suit_ros.data.sim.lidar import GROUND, Porosity, RangeImage, cast, ray_directions
from suit_ros.data.sim.scene import Simulation, points_in_boxes
from suit_ros.errors import ConfigError
from suit_ros.structures import Detections

CFG = preset('test-real', frames=3)
# the box world's bytes as generated before the detailed world existed (commit 8560812);
# if numpy's float results change on a new platform, regenerate them from that commit
BOX_WORLD_SHA256 = {
    # sim32 since 2026-12-05: its sweep is cast at one instant, so its returns' time field is 0
    # (it said each column's firing time, which a deskewing reader would have applied)
    # both since 2026-12-06: an object's returns are its own where more than those in its
    # box (range noise put half a box's returns outside it; a moving sweep, more): the points,
    # boxes and surfaces are unchanged, only num_points
    None: '0f97b348d540d4ac5e004d5f10752f40d01c139cb7058ff83504cff02dd63af1',
    'hdl32e': 'f893a8612e311fd918aeec397600312fda09614fc409d1fc0af97af87b78d9ea',
}


@pytest.fixture(scope='module')
def sim():
    return Simulation(CFG, 11)


@pytest.fixture(scope='module')
def frames(sim):
    return [sim.render(k) for k in range(CFG.frames)]


def xyz(f):
    return np.stack([f.cloud['x'], f.cloud['y'], f.cloud['z']], 1).astype(np.float64)


def digest(cfg, seed, n):
    sim = Simulation(cfg, seed)
    h = hashlib.sha256()
    for k in range(n):
        f = sim.render(k)
        for a in (f.cloud, f.gt.boxes, f.num_points, f.surface):
            h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


@pytest.mark.parametrize('sensor', [None, 'hdl32e'])
def test_box_world_is_byte_identical(sensor):
    # exact_sectors=False: the old sector lookup (the default casts exactly since it exists)
    cfg = preset('test', sensor=sensor, frames=2, exact_sectors=False)
    assert digest(cfg, 11, 2) == BOX_WORLD_SHA256[sensor]


def test_detailed_world_is_deterministic_per_seed():
    assert digest(CFG, 4, 2) == digest(CFG, 4, 2)
    assert digest(CFG, 4, 2) != digest(CFG, 5, 2)


def test_exact_sectors_see_what_an_undistorted_sweep_sees():
    base = preset('test', sensor='hdl32e', frames=1, moving_vehicles=0, parked_vehicles=0,
                  pedestrians=0, cyclists=0)

    def static_hits(exact, **kw):
        cfg = replace(base, lidar=replace(base.lidar, dropout=0.0, **kw), exact_sectors=exact)
        sim = Simulation(cfg, 3)
        s = sim.render(0).surface
        return int(((s >= 0) & (s < len(sim.world.boxes))).sum())
    still = static_hits(True, motion_distortion=False)       # buildings, walls, poles, trees
    assert abs(static_hits(True, motion_distortion=True) - still) < 0.1 * still
    assert static_hits(False, motion_distortion=True) < 0.5 * still   # the old lookup misses


def cast_one(boxes, origin, porosity=None, u_seed=0):
    lidar = replace(preset('test').lidar, beams=64, azimuth_resolution=0.2)
    dirs = ray_directions(lidar)
    img = RangeImage(np.full(dirs.shape[:2], np.inf), np.full(dirs.shape[:2], -2),
                     np.zeros(dirs.shape[:2]))
    por = None
    if porosity is not None:
        por = Porosity(np.asarray(porosity, float),
                       np.random.default_rng(u_seed).random(dirs.shape[:2]))
    cast(dirs, np.asarray(origin, float), np.eye(3), boxes, slice(None), 100.0, img,
         porosity=por)
    hit = img.hit >= 0
    pts = dirs[hit] * img.rng[hit][:, None] + origin
    return img, pts


def test_front_and_back_of_a_car_differ():
    body = car_body('sedan', np.array([4.6, 1.8, 1.45]), (0.5, 1.0, 0.0), Realism())
    # seen from 12 m ahead of its nose, then from 12 m behind its tail
    front = body.parts.copy()
    back = body.parts.copy()
    back[:, 0] = -back[:, 0]
    profiles = []
    for parts in (front, back):
        _, pts = cast_one(parts, [14.3, 0.0, 1.8], porosity=np.zeros(len(parts)))
        near = pts[:, 0] > pts[:, 0].max() - 0.3            # the face nearest the sensor
        profiles.append(pts[near, 2].max())
    assert profiles[1] - profiles[0] > 0.1                # the nose is lower than the trunk


def test_glass_and_hedges_pass_some_rays():
    wall = np.array([[20.0, 0.0, 2.0, 0.3, 30.0, 4.0, 0.0]])
    hedge = np.array([[10.0, 0.0, 1.0, 0.8, 6.0, 2.0, 0.0]])
    boxes = np.concatenate([hedge, wall])
    opaque, _ = cast_one(boxes, [0, 0, 1.0], porosity=[0.0, 0.0])
    porous, _ = cast_one(boxes, [0, 0, 1.0], porosity=[0.4, 0.0])
    on_hedge = (opaque.hit == 0).sum()
    assert on_hedge > 100
    assert 0.45 < (porous.hit == 0).sum() / on_hedge < 0.75  # about 1 - 0.4 stays on it
    assert (porous.hit == 1).sum() > (opaque.hit == 1).sum()  # the rest reaches the wall
    other, _ = cast_one(boxes, [0, 0, 1.0], porosity=[0.4, 0.0], u_seed=1)
    assert (other.hit != porous.hit).any()


def test_glass_drops_returns(sim):
    sf = sim.surfaces
    glassy = sf.porosity[len(sf.static) + len(sf.ego):] > 0
    assert glassy.any()
    assert (sf.return_prob[len(sf.static) + len(sf.ego):][glassy] < 1).all()
    # a car cabin seen side-on: fewer returns above the belt line than the doors below give
    body = car_body('sedan', np.array([4.6, 1.8, 1.45]), (0.5, 1.0, 0.0), Realism())
    img, pts = cast_one(body.parts, [0.0, 8.0, 0.87], porosity=body.porosity)
    belt = 0.6 * 1.45
    above = (pts[:, 2] > belt + 0.02).sum()
    below = ((pts[:, 2] < belt - 0.02) & (pts[:, 2] > belt - 0.45)).sum()
    assert above < 0.8 * below


def test_clutter_never_in_gt(sim, frames):
    actor_ids = {a.instance_id for a in sim.actors}
    for f in frames:
        assert set(f.instance_ids.tolist()) <= actor_ids
        bikes = f.clutter_boxes[f.clutter_types == CLUTTER_ID['parked_bicycle']]
        if len(bikes) and len(f.gt.boxes):
            d = np.hypot(*(bikes[:, None, :2] - f.gt.boxes[None, :, :2]).transpose(2, 0, 1))
            assert d.min() > 0.05
        clutter_pts = (f.surface >= 0) & (f.surface_instance == 0)
        assert clutter_pts.any()
    types = np.concatenate([f.clutter_types for f in frames])
    for name in ('parked_bicycle', 'tree', 'curb', 'ego_body'):
        assert (types == CLUTTER_ID[name]).any(), name


def test_gt_boxes_hold_their_actors_points(frames):
    noise = 5 * CFG.lidar.range_noise
    seen = 0
    for f in frames:
        pts = xyz(f)
        in_box = points_in_boxes(pts, f.gt.boxes).sum(0)
        for i, iid in enumerate(f.instance_ids):
            own = f.surface_instance == iid
            assert f.num_points[i] == max(in_box[i], int(own.sum()))
            grown = f.gt.boxes[i:i + 1].copy()
            grown[:, 3:6] += 2 * noise
            assert points_in_boxes(pts[own], grown).all()
            seen += int(own.sum())
    assert seen > 50


@pytest.mark.parametrize('sensor', ['vlp16', 'hdl64e'])
def test_an_object_counts_its_own_returns_in_a_moving_sweep(sensor):
    """A sweep taken over 0.1 s while the ego and the object move puts the object's returns
    outside its box at the stamp: it still counts them (it was counted 0, trained as
    background and left unscored, for a fifth to a third of the visible objects)."""
    sim = Simulation(preset('val-real', sensor=sensor, frames=12), 9002)
    assert sim.cfg.lidar.motion_distortion
    outside = 0
    for k in (4, 8, 11):
        f = sim.render(k)
        in_box = points_in_boxes(xyz(f), f.gt.boxes).sum(0)
        for i, iid in enumerate(f.instance_ids):
            own = int((f.surface_instance == iid).sum())
            assert f.num_points[i] == max(own, in_box[i])
            outside += int(own > 0 and in_box[i] == 0)
    assert outside > 0          # the case exists in these frames


def test_returns_lie_on_parts(frames):
    for f in frames:
        hit = f.surface[f.surface != GROUND]
        assert len(f.boxes_world) > hit.max()


def test_clutter_false_positives_counts_by_type():
    clutter = np.array([[10.0, 0.0, 0.5, 4.0, 1.0, 1.0, 0.0],        # hedge
                        [0.0, 10.0, 0.5, 0.3, 0.3, 1.0, 0.0],        # bollard
                        [30.0, 0.0, 0.5, 1.8, 0.5, 1.0, 0.0]])       # parked bicycle
    types = np.array([CLUTTER_ID['hedge'], CLUTTER_ID['bollard'], CLUTTER_ID['parked_bicycle']])
    gt = np.array([[30.5, 1.0, 0.8, 1.8, 0.6, 1.7, 0.0]])           # a cyclist by the bikes
    frame = SimpleNamespace(clutter_boxes=clutter, clutter_types=types,
                            gt=Detections(gt, np.zeros((1, 2)), np.ones(1), np.array([3])))

    def dets(*xy):
        b = np.array([[x, y, 0.5, 1.0, 1.0, 1.0, 0.0] for x, y in xy]).reshape(-1, 7)
        return Detections(b, np.zeros((len(b), 2)), np.ones(len(b)), np.zeros(len(b), int))
    counts = clutter_false_positives(
        [frame, frame], [dets((11.5, 0.2), (9.0, 0.4), (0.3, 10.4), (30.0, 0.0), (50.0, 50.0),
                              (0.0, 11.0)),
                         dets()])
    assert counts.shape == (2, len(CLUTTER_TYPES))
    # two on the hedge, one on the bollard (and one 0.85 m from it: beyond the margin), the one
    # on the bicycles is within 2 m of the cyclist's GT, the far one is on nothing
    expected = np.zeros(len(CLUTTER_TYPES), int)
    expected[CLUTTER_ID['hedge']] = 2
    expected[CLUTTER_ID['bollard']] = 1
    np.testing.assert_array_equal(counts[0], expected)
    assert counts[1].sum() == 0
    with pytest.raises(ValueError, match='one detection set per frame'):
        clutter_false_positives([frame], [])


def test_parked_bicycle_fits_its_box():
    body, size = parked_bicycle_body(np.random.default_rng(0))
    lo = body.parts[:, :3] - body.parts[:, 3:6] / 2
    hi = body.parts[:, :3] + body.parts[:, 3:6] / 2
    assert (lo[:, :2] >= -size[:2] / 2 - 1e-9).all() and (hi[:, :2] <= size[:2] / 2 + 1e-9).all()
    assert (lo[:, 2] >= 0).all() and (hi[:, 2] <= size[2] + 1e-9).all()


def test_realism_is_validated():
    with pytest.raises(ConfigError, match='glass_porosity'):
        preset('test', realism=Realism(glass_porosity=1.5))
    with pytest.raises(ConfigError, match='hedge_porosity'):
        preset('test', realism=Realism(hedge_porosity=(0.7, 0.2)))
    assert preset('train-real').realism == Realism()
    assert preset('train').realism is None


def test_street_objects_only_in_the_street_presets():
    """train-street adds the street objects of real sidewalks; the validation drives stay
    what they were (no street objects; the key changed with the cache's version only)."""
    from suit_ros.data.sequences import _cache_key
    from suit_ros.data.sim import preset
    from suit_ros.data.sim.clutter import CLUTTER_TYPES
    from suit_ros.data.sim.scene import Simulation
    street = {'trash_can', 'hydrant', 'parking_meter', 'utility_box', 'planter', 'street_tree',
              'lamp_post', 'column', 'shelter'}
    assert _cache_key('val-real', 'sim32', 9000, 40) == 'a66fafdfe5c2ae10'     # version 3
    plain = Simulation(preset('val-real', frames=2), 3).scene
    names = {CLUTTER_TYPES[t] for t in plain.types}
    assert not names & street
    busy = Simulation(preset('train-street', frames=2), 3).scene
    counts = {n: int(sum(CLUTTER_TYPES[t] == n for t in busy.types)) for n in street}
    assert all(c > 0 for c in counts.values()), counts
    frame = Simulation(preset('train-street', frames=2), 3).render(1)
    assert frame.clutter_boxes is not None and len(frame.cloud) > 1000


def test_real_car_ends_start_inside_the_box():
    """A car with real ends, seen from 12 m behind: its returns start inside its box (a
    bumper 0.1 m in, the body over it 0.35 m in), where a boxy car's start at the box's end;
    the parts stay inside the box."""
    size = np.array([4.6, 1.8, 1.45])
    starts = []
    for real in (False, True):
        body = car_body('sedan', size, (0.5, 1.0, 0.0), Realism(), real_ends=real)
        lo = body.parts[:, :3] - body.parts[:, 3:6] / 2
        hi = body.parts[:, :3] + body.parts[:, 3:6] / 2
        assert (lo[:, :2] >= -size[:2] / 2 - 1e-9).all()
        assert (hi[:, :2] <= size[:2] / 2 + 1e-9).all()
        _, pts = cast_one(body.parts, [size[0] / 2 + 12.0, 0.0, 1.8],
                          porosity=np.zeros(len(body.parts)))
        on = pts[pts[:, 2] > 0.3]
        starts.append(size[0] / 2 - np.percentile(on[:, 0], 95))   # depth of the near returns
    assert starts[0] < 0.02
    assert 0.08 < starts[1] < 0.5


def test_real_car_ends_change_only_the_cars_shapes():
    """``real_car_ends`` is drawn from each car's id: the presets without it keep their world
    (the same actors, sizes, routes), the others give some cars real ends and others not."""
    from suit_ros.data.sim.actors import id_fraction
    plain = Simulation(preset('val-real', frames=2), 3)
    ends = Simulation(preset('val-ends', frames=2), 3)
    cars = [(a, b) for a, b in zip(plain.actors, ends.actors) if a.body is not None
            and a.label == 0]
    assert len(cars) > 10
    for a, b in cars:
        assert a.instance_id == b.instance_id and np.array_equal(a.size, b.size)
        assert np.array_equal(a.s, b.s)
    changed = [not np.array_equal(a.body.parts, b.body.parts) for a, b in cars]
    expected = [id_fraction(a.instance_id) < 0.5 for a, _ in cars]
    assert changed == expected and 0 < sum(changed) < len(cars)
    every = Simulation(preset('val-ends-all', frames=2), 3)
    shaped = [(a, b) for a, b in zip(plain.actors, every.actors) if a.body is not None
              and a.label == 0]
    assert all(not np.array_equal(a.body.parts, b.body.parts) for a, b in shaped)
    assert preset('val-real').realism.real_car_ends == 0.0
    assert preset('train-ends-all').realism.real_car_ends == 1.0
    for name in ('train-street-ends', 'val-street-ends'):
        assert preset(name).realism.real_car_ends == preset(name).realism.street_objects == 1.0
    with pytest.raises(ConfigError, match='real_car_ends'):
        preset('test', realism=Realism(real_car_ends=1.5))
