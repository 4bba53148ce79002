"""What deskew costs the node: DetectionPipeline.process on the demo drive recorded as a
32-beam and a 64-beam sensor sweep it (motion distortion on, a time field per return; the
64-beam sweeps also densified 2.3x), two pipelines fed the same bag, deskew on and off, frame
by frame in turn, one torch thread. Prints the medians of the pipeline's convert stage
(PointCloud2 to points, filters, deskew) and of the whole process call, and their ratio.
Usage: python docs/experiments/deskew/bench_deskew.py [FRAMES]
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path
import sys
import tempfile
import time

import numpy as np
import torch

from suit_ros.data.bag import open_reader
from suit_ros.data.sim import preset
from suit_ros.data.sim.recording import write_bag
from suit_ros.params import DetectorParams
from suit_ros.pipeline import DetectionPipeline, load_detector

torch.set_num_threads(1)
n = int(sys.argv[1]) if len(sys.argv) > 1 else 20
for name, sensor, factor in (('37k', 'sim32', 1.0), ('114k', 'hdl64e', 1.0),
                             ('260k', 'hdl64e', 2.3)):
    cfg = preset('demo-real', sensor=sensor, frames=n)
    cfg = replace(cfg, lidar=replace(cfg.lidar, motion_distortion=True))
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / 'bag'
        write_bag(bag, cfg, 7, densify=factor)
        pipes = {}
        for on in (True, False):
            params = DetectorParams(deskew=on, extrinsic_xyz=cfg.lidar.extrinsic_xyz)
            det, _, _ = load_detector(params)
            pipes[on] = DetectionPipeline(det, params, None)
        convert: dict[bool, list[float]] = {True: [], False: []}
        total: dict[bool, list[float]] = {True: [], False: []}
        clouds = 0
        with open_reader(bag) as r:
            for c, _, raw in r.messages():
                if c.topic not in ('/odom', '/points'):
                    continue
                msg = r.deserialize(raw, c.msgtype)
                for on, pipe in pipes.items():
                    if c.topic == '/odom':
                        pipe.add_odometry(msg)
                        continue
                    t0 = time.perf_counter()
                    out = pipe.process(msg)
                    t1 = time.perf_counter()
                    if clouds >= 3:
                        convert[on].append(out.timings['convert'] * 1e3)
                        total[on].append((t1 - t0) * 1e3)
                    if on:
                        status, points = out.deskew, out.points_used
                clouds += c.topic == '/points'
    c_on, c_off = np.median(convert[True]), np.median(convert[False])
    p_on, p_off = np.median(total[True]), np.median(total[False])
    print(f'{name} ({points} points): convert p50 {c_on:.2f} ms deskew on, {c_off:.2f} off '
          f'(+{c_on - c_off:.2f} ms); process p50 {p_on:.1f} vs {p_off:.1f} ms '
          f'(ratio {p_on / p_off:.3f}); last frame: {status}', flush=True)
