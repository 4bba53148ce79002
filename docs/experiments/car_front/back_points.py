#!/usr/bin/env python3
"""Where the returns in the back eighth of real cars seen from the front lie (the dev sweeps'
first sweep, cars within 35 m; to diagnose only): distance from the box's back end, across
the car (of its half width), height (of its height), intensity.

Usage: back_points.py AV2_ROOT
"""
from __future__ import annotations

import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from probe import CAR  # noqa: E402
from views import view  # noqa: E402

from suit_ros.data.av2 import av2_sequences  # noqa: E402

for seq in av2_sequences(sys.argv[1]):
    for f in list(seq)[:1]:
        g = f.gt
        assert g is not None
        pts = f.points[f.points[:, 4] < 0.01]
        for k in np.nonzero(g.labels == CAR)[0]:
            b = g.boxes[k].astype(np.float64)
            if np.hypot(*b[:2]) > 35 or view(b) < 0.5:
                continue
            x, y, z, length, w, h, yaw = b
            c, s = np.cos(yaw), np.sin(yaw)
            d = pts[:, :3] - b[:3]
            u = d[:, 0] * c + d[:, 1] * s
            v = -d[:, 0] * s + d[:, 1] * c
            inside = ((np.abs(u) < length / 2 + 0.2) & (np.abs(v) < w / 2 + 0.2)
                      & (d[:, 2] > -h / 2 + 0.15) & (d[:, 2] < h / 2 + 0.3))
            back = inside & (u < -length / 2 + length / 8)
            hz = (d[:, 2] + h / 2) / h
            print(f'car at {np.hypot(x, y):4.1f} m, lwh {length:.1f} {w:.1f} {h:.2f}: '
                  f'{inside.sum()} returns, {back.sum()} in the back eighth:',
                  ' '.join(f'({u[i] + length / 2:.2f} m, {v[i] / (w / 2):+.2f}, {hz[i]:.2f}, '
                           f'{pts[i, 3]:.2f})' for i in np.nonzero(back)[0][:6]))
