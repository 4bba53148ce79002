#!/usr/bin/env python3
"""The probe (probe.py) trained on 4 validation drives of one world (drives 9000-9003: one per
sensor) and scored on its other 4 (9004-9007: the same sensors) and on the real dev cars (to
diagnose only; the KITTI sample has no car). The same drives and traffic in each world; only
the cars' bodies differ.

Usage: roofs_probe.py AV2_ROOT [PRESET ...]
(PRESET: default val-street-ends and val-street-roofs; their cached drives 9000-9007)
"""
from __future__ import annotations

import glob
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from probe import collect, fit, real_cars, report  # noqa: E402

from suit_ros.data.av2 import av2_sequences  # noqa: E402

av2, _ = real_cars([f for s in av2_sequences(sys.argv[1]) for f in s])
for name in sys.argv[2:] or ['val-street-ends', 'val-street-roofs']:
    files = {k: sorted(glob.glob(f'data_cache/{name}-*-{k}-40-*.npz')) for k in range(9000, 9008)}
    assert all(len(v) == 1 for v in files.values()), files
    rng = np.random.default_rng(0)
    Xa, _ = collect([files[k][0] for k in range(9000, 9004)], rng, jitter=True, every=2)
    Xb, _ = collect([files[k][0] for k in range(9004, 9008)], rng, jitter=True, every=2)
    w = fit(Xa)
    print(f'== {name}')
    report('drives 9000-9003 (its own)', Xa, w)
    report('drives 9004-9007', Xb, w)
    report('real dev (Argoverse 2)', av2, w)
