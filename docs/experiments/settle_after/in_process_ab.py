import argparse, sys, time
import numpy as np, torch
from suit_ros import bench
from suit_ros.data.sim import preset
from suit_ros.data.sim.scene import Simulation, to_frame
from suit_ros.heap import keep_freed_memory
from suit_ros.model.streaming import StreamingDetector
from suit_ros.tracking import TrackerConfig
from suit_ros.evaluate import step_inputs
from suit_ros.msg_adapters.classes import MessageClasses
from suit_ros.msg_adapters.pointcloud2 import array_to_pointcloud2, pointcloud2_to_xyzi
from suit_ros.msg_adapters.detections import detections_to_markerarray, detections_to_pointcloud2
keep_freed_memory()
threads, n, ck = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
torch.set_num_threads(threads)
sim = Simulation(preset('demo-real', frames=max(n, 12)), 7)
rendered = [sim.render(k) for k in range(n)]
frames = [to_frame(f, 7) for f in rendered]
C = MessageClasses.from_rclpy()
clouds = [array_to_pointcloud2(f.cloud, C.header(f.stamp_ns, 'lidar'), C) for f in rendered]
args = argparse.Namespace(config=None, checkpoint=ck)
model = bench._model(args, 'suit')
single = bench._model(args, 'none')
runners = {'single': StreamingDetector(single, 'cpu', precision='auto', tracker=TrackerConfig()),
           'now': StreamingDetector(model, 'cpu', precision='auto', tracker=TrackerConfig()),
           'later': StreamingDetector(model, 'cpu', precision='auto', tracker=TrackerConfig())}
names = runners['now'].cfg.class_names
T = {k: {'step': [], 'frame': [], 'settle': []} for k in runners}
for i, (f, msg) in enumerate(zip(frames, clouds)):
    for k, r in runners.items():
        pts = pointcloud2_to_xyzi(msg).points; pts[:, 3] /= 255.0
        t1 = time.perf_counter()
        res = r.step(pts, *step_inputs(f)[1:], settle=(k != 'later'))
        t2 = time.perf_counter()
        d = res.detections
        detections_to_pointcloud2(d.boxes, d.velocities, d.scores, d.labels, msg.header, C, track_ids=res.track_ids, num_points=res.num_points, vel_std=res.velocity_std)
        detections_to_markerarray(d.boxes, d.velocities, d.scores, d.labels, msg.header, names, C, track_ids=res.track_ids)
        s = r.settle()
        if i < 3: continue
        T[k]['step'].append((t2 - t1) * 1e3); T[k]['frame'].append((t2 - t1 + s) * 1e3); T[k]['settle'].append(res.timings.get('sampling', 0) * 1e3)
for k in T:
    print(k, ' '.join('%s %.2f' % (a, np.median(v)) for a, v in T[k].items()))
print('ratio step now %.3f later %.3f; frame now %.3f later %.3f' % (np.median(T['now']['step'])/np.median(T['single']['step']), np.median(T['later']['step'])/np.median(T['single']['step']), np.median(T['now']['frame'])/np.median(T['single']['frame']), np.median(T['later']['frame'])/np.median(T['single']['frame'])))
