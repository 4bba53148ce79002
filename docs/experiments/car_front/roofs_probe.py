#!/usr/bin/env python3
"""The probe (probe.py) trained on 4 drives of the world with `real_car_roofs` (in the commit
that added this page; cached drives of `val-street-roofs` needed), scored on its other 4 and
on the real dev cars (to diagnose only).

Usage: roofs_probe.py AV2_ROOT [PRESET]
(PRESET: default val-street-roofs; its cached validation drives 9000-9007)
"""
from __future__ import annotations

import glob
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from probe import CAR, anti, collect, fit, profile, report  # noqa: E402

from suit_ros.data.av2 import av2_sequences  # noqa: E402

rng = np.random.default_rng(0)
preset_name = sys.argv[2] if len(sys.argv) > 2 else 'val-street-roofs'
files = sorted(glob.glob(f'data_cache/{preset_name}-*-900[0-7]-40-*.npz'))
assert len(files) == 8, files
Xa, _ = collect(files[:4], rng, jitter=True, every=2)
Xb, _ = collect(files[4:], rng, jitter=True, every=2)
w = fit(Xa)
report('roofs A (train)', Xa, w)
report('roofs B', Xb, w)
X = []
for seq in av2_sequences(sys.argv[1]):
    for f in seq:
        g = f.gt
        assert g is not None
        pts = f.points[f.points[:, 4] < 0.01]
        for k in np.nonzero(g.labels == CAR)[0]:
            if np.hypot(*g.boxes[k, :2]) > 50:
                continue
            fp = profile(pts, g.boxes[k].astype(np.float64))
            if fp is not None:
                X.append(anti(fp))
report('real dev', np.array(X), w)
