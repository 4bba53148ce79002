#!/usr/bin/env python3
"""The view-split top profiles (views.py) at two mounting heights, 1.73 m (KITTI) and 2.0 m
(Argoverse 2's upper LiDAR above the road): 4 drives (seeds 9100-9103, HDL-64E beams), every
4th of 40 frames, in the street world and with `real_car_roofs` (in the commit that added
this page)."""
from __future__ import annotations

import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from views import gather  # noqa: E402

from suit_ros.data.sim import preset  # noqa: E402
from suit_ros.data.sim.scene import Simulation, to_frame  # noqa: E402

np.set_printoptions(precision=2, suppress=True, linewidth=160)
for name in ('val-street-ends', 'val-street-roofs'):
    for z in (1.73, 2.0):
        acc: dict[str, list[np.ndarray]] = {'front': [], 'side': [], 'rear': []}
        for seed in (9100, 9101, 9102, 9103):
            sim = Simulation(preset(name, sensor='hdl64e', extrinsic_xyz=(0.76, 0.0, z),
                                    frames=40), seed)
            d = gather(to_frame(sim.render(k), seed) for k in range(0, 40, 4))
            for k in acc:
                acc[k] += list(d[k])
        for k, rows in acc.items():
            F = np.array(rows)
            if len(F):
                print(f'{name:18s} z {z} {k:5s} n={len(F):4d} top {F[:, :8].mean(0)}',
                      flush=True)
