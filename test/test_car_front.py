"""Passenger cars with real cars' greenhouses (``Realism.real_car_roofs``): the worlds without
it keep their keys and bodies; the chosen cars stay inside their boxes, reach high at their
back and stay low at their nose, so their own returns say which end is the front
(docs/experiments/car_front)."""
from __future__ import annotations

import numpy as np
import pytest

from suit_ros import CLASS_NAMES
from suit_ros.data.sim import Realism, preset
from suit_ros.data.sim.actors import dark_top, id_fraction, real_roof
from suit_ros.data.sim.bodies import VEHICLE_SIZES, Body, car_body
from suit_ros.data.sim.scene import Simulation
from suit_ros.errors import ConfigError

CAR = CLASS_NAMES.index('car')
COAT = (0.5, 0.97, 0.0)


def test_the_presets_and_their_keys():
    from suit_ros.data.sequences import _cache_key
    assert _cache_key('val-street-ends', 'hdl32e', 9001, 40) == '52d36ca031398c1e'
    assert _cache_key('val-street-roofs', 'hdl32e', 9001, 40) != '52d36ca031398c1e'
    for name in ('train-ends-roofs', 'val-ends-roofs'):
        r = preset(name).realism
        assert (r.real_car_roofs, r.real_car_ends, r.street_objects, r.parked_rows) == (1, 1, 0, 0)
    for name in ('train-street-roofs', 'val-street-roofs'):
        assert preset(name).realism.street_objects == 1.0
    for name in ('train-parked-roofs', 'val-parked-roofs'):
        r = preset(name).realism
        assert (r.real_car_roofs, r.parked_rows, r.parked_reversed) == (1, 0.5, 0.5)
    assert preset('val-street-ends').realism.real_car_roofs == 0.0
    with pytest.raises(ConfigError, match='real_car_roofs'):
        preset('test', realism=Realism(real_car_roofs=1.5))


def _top(body: Body, size: np.ndarray, lo: float, hi: float) -> float:
    """The highest opaque part's top (of the height) over ``lo..hi`` of the length (-1 back,
    +1 front)."""
    x0 = body.parts[:, 0] - body.parts[:, 3] / 2
    x1 = body.parts[:, 0] + body.parts[:, 3] / 2
    over = (x1 > lo * size[0] / 2) & (x0 < hi * size[0] / 2)
    opaque = (body.porosity == 0) & (body.return_prob > 0.5)
    tops = body.parts[over & opaque, 2] + body.parts[over & opaque, 5] / 2
    return float(tops.max() / size[2]) if len(tops) else 0.0


@pytest.mark.parametrize('kind', ['sedan', 'hatchback', 'suv', 'van', 'pickup'])
@pytest.mark.parametrize('ends', [False, True])
def test_a_real_greenhouse_stays_in_the_box_high_at_the_back_low_at_the_nose(kind, ends):
    for pick in (0, 1):
        size = np.array([r[pick] for r in VEHICLE_SIZES[kind]])
        body = car_body(kind, size, COAT, Realism(), real_ends=ends, real_roof=True)
        lo = body.parts[:, :3] - body.parts[:, 3:6] / 2
        hi = body.parts[:, :3] + body.parts[:, 3:6] / 2
        assert (body.parts[:, 3:6] > 0).all()
        assert (lo[:, :2] >= -size[:2] / 2 - 1e-9).all()
        assert (hi[:, :2] <= size[:2] / 2 + 1e-9).all()
        assert (lo[:, 2] >= 0).all() and (hi[:, 2] <= size[2] + 1e-9).all()
        plain = car_body(kind, size, COAT, Realism(), real_ends=ends)
        if kind == 'van':               # a van keeps its body
            np.testing.assert_array_equal(body.parts, plain.parts)
            continue
        assert _top(body, size, 0.75, 1.0) <= 0.61          # the nose: hood and bumper
        if kind != 'pickup':                                # a pickup's back is its bed
            assert _top(body, size, -1.0, -0.75) >= 0.7     # trunk deck or tailgate
            if ends:                                        # as the training worlds
                assert _top(plain, size, -1.0, -0.75) < 0.7
        # the rear pillars: narrow opaque parts at the sides of the back half, up to the roof
        assert _pillar_top(body, size) >= 0.9
        assert _pillar_top(plain, size) < 0.9


def _pillar_top(body: Body, size: np.ndarray) -> float:
    """The highest top (of the height) of a narrow opaque part along a side of the back half."""
    x, y, z, _, wy, hz = body.parts[:, :6].T
    side = (wy <= 0.1) & (np.abs(y) > size[1] / 2 - 0.2) & (x < 0)
    opaque = (body.porosity == 0) & (body.return_prob > 0.5)
    tops = (z + hz / 2)[side & opaque]
    return float(tops.max() / size[2]) if len(tops) else 0.0


def test_the_cars_are_chosen_by_id_apart_from_the_other_choices():
    ids = range(1, 4001)
    chosen = np.array([real_roof(i, 0.5) for i in ids])
    ends = np.array([id_fraction(i) < 0.5 for i in ids])
    tops = np.array([dark_top(i, 0.5) for i in ids])
    assert abs(chosen.mean() - 0.5) < 0.03
    assert abs((chosen & ends).mean() - 0.25) < 0.03 and abs((chosen & tops).mean() - 0.25) < 0.03
    assert not any(real_roof(i, 0.0) for i in ids) and all(real_roof(i, 1.0) for i in ids)


def test_the_rows_cars_get_them_too():
    either = Simulation(preset('val-parked-either', sensor='hdl64e', frames=2), 9011)
    roofs = Simulation(preset('val-parked-roofs', sensor='hdl64e', frames=2), 9011)
    cars = [(a, b) for a, b in zip(either.actors, roofs.actors, strict=True) if a.label == CAR]
    still = [(a, b) for a, b in cars if not a.v.any()]     # the rows' cars and other parked
    assert len(still) > 30
    changed = [not np.array_equal(a.body.parts, b.body.parts) for a, b in still]
    assert np.mean(changed) > 0.8          # all but the vans


def test_only_the_cars_change_and_their_backs_return_higher():
    plain = Simulation(preset('val-street-ends', sensor='hdl64e', frames=12), 9011)
    roofs = Simulation(preset('val-street-roofs', sensor='hdl64e', frames=12), 9011)
    kinds_changed = 0
    for a, b in zip(plain.actors, roofs.actors, strict=True):
        assert np.array_equal(a.s, b.s) and a.label == b.label
        if a.label != CAR:
            assert np.array_equal(a.body.parts, b.body.parts)
        else:
            kinds_changed += int(not np.array_equal(a.body.parts, b.body.parts))
    assert kinds_changed > 10
    high = {False: 0, True: 0}      # cars' own returns in their back eighth above 0.6 h
    total = {False: 0, True: 0}
    for k in range(12):
        for f, world in ((plain.render(k), False), (roofs.render(k), True)):
            for box, label, inst in zip(f.gt.boxes, f.gt.labels, f.instance_ids):
                if label != CAR:
                    continue
                mine = f.surface_instance == inst
                d = np.stack([f.cloud['x'][mine] - box[0], f.cloud['y'][mine] - box[1]])
                u = np.cos(box[6]) * d[0] + np.sin(box[6]) * d[1]
                z = f.cloud['z'][mine] - (box[2] - box[5] / 2)
                back = u < -0.375 * box[3]
                high[world] += int(np.sum(back & (z > 0.6 * box[5])))
                total[world] += len(z)
    assert total[False] > 5000 and total[True] > 5000
    assert high[True] / total[True] > 1.5 * high[False] / total[False], (high, total)
