"""The step of three models under two GIL switch intervals, in one process: each frame, every
model is stepped once with the interval at A (its own runner) and once at B (a second runner
of the same model), so that both see the machine at the same minute; the median of each
stage's time (the streaming detector's own timings) and of the whole step.

Usage: python ab_interval.py THREADS FRAMES A_SECONDS B_SECONDS
"""
import sys

import numpy as np

sys.path.insert(0, 'docs/experiments/carry_step')
from demo_runners import demo_runners  # noqa: E402

a_s, b_s = float(sys.argv[3]), float(sys.argv[4])
models = {'single': ('suit_carry', 'none'), 'suit_default': ('suit_default', None),
          'suit_carry': ('suit_carry', None)}
threads, n, inputs, runners = demo_runners(
    {f'{k}@{s}': v for s in ('A', 'B') for k, v in models.items()})
for r in runners.values():
    r.warm_up()
timings: dict[str, list[dict[str, float]]] = {k: [] for k in runners}
for i, args in enumerate(inputs):
    for s, interval in (('A', a_s), ('B', b_s)) if i % 2 else (('B', b_s), ('A', a_s)):
        sys.setswitchinterval(interval)
        for k in models:
            res = runners[f'{k}@{s}'].step(*args)
            if i >= 5:
                timings[f'{k}@{s}'].append(res.timings)
sys.setswitchinterval(0.005)
print(f'threads {threads}, {n - 5} frames, median ms; A: switch interval {a_s} s, B: {b_s} s')
print(f"{'stage':12s}" + ''.join(f'{k:>16s}' for k in runners))
for stage in timings['single@A'][0]:
    print(f'{stage:12s}' + ''.join(
        f'{np.median([t[stage] for t in timings[k]]) * 1e3:16.3f}' for k in runners))
for s in ('A', 'B'):
    single = np.median([t['total'] for t in timings[f'single@{s}']])
    print(f'{s}: / single' + ''.join(
        f"{k:>14s} {np.median([t['total'] for t in timings[f'{k}@{s}']]) / single:.3f}"
        for k in models))
