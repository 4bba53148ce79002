"""In one process, frame by frame in turn: the single frame, SUIT sampling its next memory in
the step (``now``) and SUIT sampling it after the detections' messages were built
(``later``: ``step(settle=False)``, the messages, ``settle()``): p50 of the step to the
detections, of the model's whole work on the frame, and of the sampling. Runs at commit
2d92c96 (the trial), not after it.

Usage: python in_process_ab.py THREADS FRAMES CHECKPOINT
"""
import argparse
import sys
import time

from bench_settle import demo_drive
import numpy as np

from suit_ros import bench
from suit_ros.evaluate import step_inputs
from suit_ros.model.streaming import StreamingDetector
from suit_ros.msg_adapters.detections import (
    detections_to_markerarray,
    detections_to_pointcloud2,
)
from suit_ros.msg_adapters.pointcloud2 import pointcloud2_to_xyzi
from suit_ros.tracking import TrackerConfig

threads, n, ck = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
frames, clouds, C = demo_drive(threads, n)
args = argparse.Namespace(config=None, checkpoint=ck)
model, single = bench._model(args, 'suit'), bench._model(args, 'none')
runners = {name: StreamingDetector(m, 'cpu', precision='auto', tracker=TrackerConfig())
           for name, m in (('single', single), ('now', model), ('later', model))}
names = runners['now'].cfg.class_names
T: dict[str, dict[str, list[float]]] = {
    k: {'step': [], 'frame': [], 'sampling': []} for k in runners}
for i, (f, msg) in enumerate(zip(frames, clouds)):
    for k, r in runners.items():
        pts = pointcloud2_to_xyzi(msg).points
        pts[:, 3] /= 255.0
        t1 = time.perf_counter()
        res = r.step(pts, *step_inputs(f)[1:], settle=(k != 'later'))
        t2 = time.perf_counter()
        d = res.detections
        detections_to_pointcloud2(d.boxes, d.velocities, d.scores, d.labels, msg.header, C,
                                  track_ids=res.track_ids, num_points=res.num_points,
                                  vel_std=res.velocity_std)
        detections_to_markerarray(d.boxes, d.velocities, d.scores, d.labels, msg.header, names,
                                  C, track_ids=res.track_ids)
        settled = r.settle()
        if i < 3:
            continue
        T[k]['step'].append((t2 - t1) * 1e3)
        T[k]['frame'].append((t2 - t1 + settled) * 1e3)
        T[k]['sampling'].append(res.timings.get('sampling', 0.0) * 1e3)
for k, v in T.items():
    print(k, ' '.join(f'{a} {np.median(x):.2f}' for a, x in v.items()))
p50 = {k: {a: float(np.median(x)) for a, x in v.items()} for k, v in T.items()}
print(f"ratio step now {p50['now']['step'] / p50['single']['step']:.3f} later "
      f"{p50['later']['step'] / p50['single']['step']:.3f}; frame now "
      f"{p50['now']['frame'] / p50['single']['frame']:.3f} later "
      f"{p50['later']['frame'] / p50['single']['frame']:.3f}")
