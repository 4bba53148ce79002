"""In one process, frame by frame in turn over the demo drive: the single frame (suit_carry's
weights run as temporal none), suit_carry as shipped (its carry head at its cells on one torch
thread) and suit_carry with the carry head on every torch thread; p50 of each step.

Usage: python ab_carryhead.py THREADS FRAMES
"""
from collections.abc import Iterator
from contextlib import contextmanager
import time

from demo_runners import demo_runners
import numpy as np

import suit_ros.model.detector as detector

threads, n, inputs, runners = demo_runners({
    k: ('suit_carry', t) for k, t in (('none', 'none'), ('carry', None),
                                      ('carry_all_threads', None))})
one_thread = detector.one_thread
every = runners['carry_all_threads'].model


@contextmanager
def carry_head_threads(enabled: bool = True) -> Iterator[None]:
    """predict's one_thread: a no-op for the model under trial."""
    if current is every:
        yield
    else:
        with one_thread(enabled):
            yield


detector.one_thread = carry_head_threads
for r in runners.values():
    current = r.model
    r.warm_up()
steps: dict[str, list[float]] = {k: [] for k in runners}
for i, args in enumerate(inputs):
    for k, r in runners.items():
        current = r.model
        t = time.perf_counter()
        r.step(*args)
        if i >= 3:
            steps[k].append(time.perf_counter() - t)
p = {k: float(np.median(v)) * 1e3 for k, v in steps.items()}
print(f"threads {threads}: none {p['none']:.2f} carry {p['carry']:.2f} "
      f"({p['carry'] / p['none']:.3f}x) carry, head on all threads "
      f"{p['carry_all_threads']:.2f} ({p['carry_all_threads'] / p['none']:.3f}x) ms")
