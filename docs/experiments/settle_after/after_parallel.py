"""Does single-threaded small work run slower right after a two-thread torch operation (the
OpenMP worker still spinning) than after a pause (the worker asleep)? One thread's work (a
few hundred small tensor operations, on one torch thread as the step runs them) timed right
after a 2-thread convolution, and after a 20 ms pause following it; p50 over REPS.

Usage: python after_parallel.py REPS
"""
import sys
import time

import numpy as np
import torch

torch.set_num_threads(2)
reps = int(sys.argv[1])
x = torch.randn(1, 96, 128, 128)
conv = torch.nn.Conv2d(96, 96, 3, padding=1)
rows = torch.randn(400, 96)
w = torch.randn(96, 32)


def small() -> float:
    torch.set_num_threads(1)
    t = time.perf_counter()
    for _ in range(100):
        v = rows @ w
        v = torch.relu(v + 1.0)
        v = v[v[:, 0] > 0]
    dt = time.perf_counter() - t
    torch.set_num_threads(2)
    return dt


with torch.inference_mode():
    right, paused = [], []
    for _ in range(reps):
        conv(x)
        right.append(small())
        conv(x)
        time.sleep(0.02)
        paused.append(small())
print(f'small work right after a 2-thread conv: p50 {np.median(right) * 1e3:.2f} ms; after a '
      f'20 ms pause: {np.median(paused) * 1e3:.2f} ms')
