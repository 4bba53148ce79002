#!/usr/bin/env python3
"""Simulate and cache training drives before a run (what `suit-ros train` would make at its
start, one process; two of these split the work over two cores).

Usage: make_drives.py PRESET FIRST COUNT FRAMES   (drives FIRST..FIRST+COUNT-1 of `train`)
"""
import sys
import time

import numpy as np

from suit_ros.data.sequences import synthetic_split

name, first, count, frames = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
t0 = time.monotonic()
for k in range(first, first + count):
    synthetic_split('train', 1, frames, 'data_cache', preset_name=name,
                    points_dtype=np.float16, first=k)
    print(f'{name} drive {k}: {time.monotonic() - t0:.0f} s', flush=True)
