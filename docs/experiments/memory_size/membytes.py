"""Memory bytes of SUIT checkpoints on the first 40 frames of the demo drive (the bench's scene),
against the dense memory of the first one; a spec is PATH[:key=value...] of sampling settings.

    python docs/experiments/memory_size/membytes.py CKPT CKPT:alpha=0.2 CKPT:top_k=60
"""
import dataclasses
import sys

import numpy as np
import torch

from suit_ros.checkpoint import load_model_as
from suit_ros.data.sim import preset
from suit_ros.data.sim.scene import Simulation, to_frame
from suit_ros.evaluate import step_inputs
from suit_ros.model.streaming import StreamingDetector
from suit_ros.tracking import TrackerConfig

torch.set_num_threads(2)
N = 40
sim = Simulation(preset('demo-real', frames=N), 7)
frames = [to_frame(sim.render(k), 7) for k in range(N)]


def run(path: str, temporal: str = 'suit', **samp: float) -> np.ndarray:
    m = load_model_as(path, temporal, 'cpu')
    if samp:
        m.cfg = dataclasses.replace(m.cfg, sampling=dataclasses.replace(m.cfg.sampling, **samp))
    r = StreamingDetector(m, 'cpu', tracker=TrackerConfig())
    return np.array([r.step(*step_inputs(f)).memory_bytes for f in frames])


dense = run(sys.argv[1], 'dense')
for spec in sys.argv[1:]:
    path, *kv = spec.split(':')
    samp = {k: (float(v) if '.' in v else int(v)) for k, v in (x.split('=') for x in kv)}
    b = run(path, **samp)
    pct = (b[1] / dense[1] * 100, b[9] / dense[9] * 100)
    med = np.median(b) / np.median(dense) * 100
    top = b.max() / np.median(dense) * 100
    print(f'{spec} frames 2/10: {b[1]} {b[9]} {pct[0]:.2f}% {pct[1]:.2f}% '
          f'median over {N}: {int(np.median(b))} {med:.2f}% max {top:.2f}%')
