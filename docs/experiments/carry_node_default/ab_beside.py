"""The past term beside the encoder (a second thread) or in the step's own thread: the single
frame, suit_carry and suit_default each both ways, stepped frame by frame in turn over the
demo drive in one process (tracker on, precision auto); the median step and its ratio to the
single frame's. Usage: python ab_beside.py THREADS FRAMES (PYTHONPATH: the tree)
"""
from pathlib import Path
import sys

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'carry_step'))
from demo_runners import demo_runners

threads, n, inputs, runners = demo_runners({
    'single': ('suit_carry', 'none'), 'carry_beside': ('suit_carry', None),
    'carry_serial': ('suit_carry', None), 'default_beside': ('suit_default', None),
    'default_serial': ('suit_default', None)})
for k, r in runners.items():          # the single frame has no past term either way
    r.beside = k.endswith('beside')
for r in runners.values():
    r.warm_up()
tot = {k: [] for k in runners}
for i, args in enumerate(inputs):
    for k, r in runners.items():
        res = r.step(*args)
        if i >= 5:
            tot[k].append(res.timings['total'])
s = np.median(tot['single'])
for k, v in tot.items():
    print(f'{k:16s} {np.median(v)*1e3:7.2f} ms  {np.median(v)/s:.3f}x')
