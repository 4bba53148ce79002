"""Per-frame outputs of the streaming detector over 30 demo frames (published boxes, scores,
labels, track ids, carried flags, and the memory it holds after each frame), float32 and
precision auto, for checkpoints by name; frame 20 keeps only the returns ahead (an outage of the
rear half). Written to an .npz for `compare_outputs.py` (two source trees, same machine).

Usage: python same_outputs.py OUT.npz NAME [NAME ...]   (NAME: suit_carry, suit_default, ...)
"""
import sys

import numpy as np
import torch

from suit_ros.checkpoint import load_model_as
from suit_ros.data.sim import preset
from suit_ros.data.sim.scene import Simulation, to_frame
from suit_ros.evaluate import step_inputs
from suit_ros.model.streaming import StreamingDetector
from suit_ros.tracking import TrackerConfig

torch.set_num_threads(1)
n = 30
sim = Simulation(preset('demo-real', frames=n), 7)
inputs = [step_inputs(to_frame(sim.render(k), 7)) for k in range(n)]
out = {}
FIELDS = ('batch_index', 'cell_xy', 'features', 'probs', 'mask', 'boxes', 'velocities')
for name in sys.argv[2:]:
    for precision in ('float32', 'auto'):
        runner = StreamingDetector(load_model_as(f'suit_ros/checkpoints/{name}.safetensors', None),
                                   'cpu', precision=precision, tracker=TrackerConfig())
        for k, args in enumerate(inputs):
            if k == 20:
                args = (args[0][args[0][:, 0] > 0],) + tuple(args[1:])
            res = runner.step(*args)
            key = f'{name}/{precision}/{k}/'
            out[key + 'boxes'] = res.detections.boxes
            out[key + 'scores'] = res.detections.scores
            out[key + 'labels'] = res.detections.labels
            out[key + 'ids'] = res.track_ids
            out[key + 'carried'] = res.carried
            mem = runner.memory
            if mem is not None:
                for f in FIELDS:
                    t = getattr(mem, f)
                    out[key + 'mem_' + f] = (t.float() if t.dtype.is_floating_point else t).numpy()
                out[key + 'mem_ages'] = mem.age().numpy()
                out[key + 'mem_own'] = mem.owned().numpy()
np.savez(sys.argv[1], **out)
print(len(out), 'arrays')
