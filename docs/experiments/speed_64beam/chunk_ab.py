#!/usr/bin/env python3
"""The folded pillar encoder over one chunk of points against 32k-point chunks, interleaved
frame by frame over cached val-real drives (sim32 and hdl64e, three sweeps per input)."""
from __future__ import annotations

import glob
import time

import numpy as np
import torch

from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
from suit_ros.data.sequences import load_sequence
from suit_ros.model.inference import inference_copy
from suit_ros.model.pillars import PillarEncoder
from suit_ros.model.sweeps import model_frame


def main() -> None:
    torch.set_num_threads(1)
    model, _, _ = load_checkpoint(str(default_checkpoint_path()), 'cpu')
    enc = inference_copy(model).pillars
    for name in ('val-real-sim32', 'val-real-hdl64e'):
        seq = load_sequence(sorted(glob.glob(f'data_cache/{name}-*.npz'))[0])
        frames = [model_frame(seq, t, 3) for t in range(4, 24)]
        pts = [torch.cat([torch.zeros(len(f.points), 1), torch.from_numpy(f.points)], 1)
               for f in frames]
        times: dict[str, list[float]] = {'one chunk': [], '32k chunks': []}
        with torch.no_grad():
            for p in pts:
                for k, c in (('one chunk', 10**9), ('32k chunks', 32768)):
                    PillarEncoder.CHUNK = c
                    t0 = time.perf_counter()
                    enc(p, 1)
                    times[k].append(time.perf_counter() - t0)
        print(name, len(pts[0]), {k: round(float(np.median(v)) * 1e3, 1)
                                  for k, v in times.items()})


if __name__ == '__main__':
    main()
