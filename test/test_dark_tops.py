"""Cars seen only below the belt (``Realism.dark_tops``): the worlds without it keep their keys
and bodies; the chosen cars keep their shape and lose most returns above the belt."""
from __future__ import annotations

import numpy as np
import pytest

from suit_ros import CLASS_NAMES
from suit_ros.data.sim import Realism, preset
from suit_ros.data.sim.actors import dark_top
from suit_ros.data.sim.bodies import DARK_ROOF, car_body
from suit_ros.data.sim.scene import Simulation
from suit_ros.errors import ConfigError

CAR = CLASS_NAMES.index('car')


def test_the_presets_and_their_keys():
    from suit_ros.data.sequences import _cache_key
    assert _cache_key('val-street-ends', 'hdl32e', 9001, 40) == '52d36ca031398c1e'
    assert _cache_key('val-dark-tops', 'hdl32e', 9001, 40) != '52d36ca031398c1e'
    for name in ('train-dark-tops', 'val-dark-tops'):
        r = preset(name).realism
        assert (r.dark_tops, r.street_objects, r.real_car_ends, r.bystanders) == (0.5, 1, 1, 0)
    assert preset('val-street-ends').realism.dark_tops == 0.0
    with pytest.raises(ConfigError, match='dark_tops'):
        preset('test', realism=Realism(dark_tops=-0.1))


def test_a_dark_top_keeps_its_shape_and_loses_its_returns_up_there():
    size = np.array([4.6, 1.8, 1.45])
    plain = car_body('sedan', size, (0.5, 0.97, 0.0), Realism(), real_ends=True)
    top = car_body('sedan', size, (0.5, 0.97, 0.0), Realism(), real_ends=True, dark_top=True)
    np.testing.assert_array_equal(plain.parts, top.parts)
    # glass, roof and the seats behind the glass (not the mirrors, narrow parts at the belt)
    upper = ((plain.parts[:, 2] - plain.parts[:, 5] / 2 >= 0.5 * size[2])
             & (plain.parts[:, 4] > 1.0))
    assert upper.sum() == 3
    assert (top.return_prob[upper] <= 0.3).all() and DARK_ROOF[1] in top.return_prob[upper]
    assert (plain.return_prob[upper] > top.return_prob[upper]).all()
    below = plain.parts[:, 2] + plain.parts[:, 5] / 2 <= 0.6 * size[2]      # body and wheels
    np.testing.assert_array_equal(plain.return_prob[below], top.return_prob[below])


def test_only_the_chosen_cars_change_and_they_return_less_up_high():
    plain = Simulation(preset('val-street-ends', sensor='hdl64e', frames=12), 9011)
    tops = Simulation(preset('val-dark-tops', sensor='hdl64e', frames=12), 9011)
    for a, b in zip(plain.actors, tops.actors):
        assert np.array_equal(a.body.parts, b.body.parts) and np.array_equal(a.s, b.s)
        changed = not np.array_equal(a.body.return_prob, b.body.return_prob)
        assert changed == (a.label == CAR and dark_top(a.instance_id, 0.5)), a.instance_id
    upper = {True: 0, False: 0}      # the chosen cars' own returns above 3/4 of their height
    total = {True: 0, False: 0}
    for k in range(12):
        for f, world in ((plain.render(k), False), (tops.render(k), True)):
            for box, label, inst in zip(f.gt.boxes, f.gt.labels, f.instance_ids):
                if label != CAR or not dark_top(int(inst), 0.5):
                    continue
                z = f.cloud['z'][f.surface_instance == inst] - (box[2] - box[5] / 2)
                upper[world] += int(np.sum(z > 0.75 * box[5]))
                total[world] += len(z)
    assert total[True] > 5000 and total[False] > 5000
    assert upper[True] / total[True] < 0.4 * upper[False] / total[False], (upper, total)
