"""Where SUIT's step goes, stage by stage: the single frame (suit_carry's weights run as
temporal none), suit_default and suit_carry stepped frame by frame in turn over the demo
drive in one process, tracker on, precision auto; the median of each stage's time (the
streaming detector's own timings) and of the whole step.

Usage: python stages.py THREADS FRAMES
"""

from demo_runners import demo_runners
import numpy as np

threads, n, inputs, runners = demo_runners({
    'single': ('suit_carry', 'none'), 'suit_default': ('suit_default', None),
    'suit_carry': ('suit_carry', None)})
for r in runners.values():
    r.warm_up()
timings: dict[str, list[dict[str, float]]] = {k: [] for k in runners}
for i, args in enumerate(inputs):
    for k, r in runners.items():
        res = r.step(*args)
        if i >= 5:
            timings[k].append(res.timings)
print(f'threads {threads}, {n - 5} frames, median ms')
print(f"{'stage':12s}" + ''.join(f'{k:>14s}' for k in runners))
for stage in timings['single'][0]:
    print(f'{stage:12s}' + ''.join(
        f'{np.median([t[stage] for t in timings[k]]) * 1e3:14.3f}' for k in runners))
single = np.median([t['total'] for t in timings['single']])
print(f"{'/ single':12s}" + ''.join(
    f"{np.median([t['total'] for t in timings[k]]) / single:14.3f}" for k in runners))
