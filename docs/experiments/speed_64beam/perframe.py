"""Per-frame SUIT step on the demo drive as an hdl64e sees it, in one process alone (1 thread, tracker on, after a warm-up): the in-node step compared with this."""
import numpy as np, torch, time
from suit_ros.checkpoint import default_checkpoint_path, load_checkpoint
from suit_ros.data.sequences import synthetic_sequence
from suit_ros.evaluate import step_inputs
from suit_ros.model.streaming import StreamingDetector
from suit_ros.tracking import TrackerConfig
torch.set_num_threads(1)
model, _, _ = load_checkpoint(str(default_checkpoint_path()), 'cpu')
frames = synthetic_sequence('demo-real', 7, 100, sensor='hdl64e')
r = StreamingDetector(model, precision='auto', tracker=TrackerConfig()); r.warm_up()
tot = []
for f in frames:
    res = r.step(*step_inputs(f)); tot.append(res.timings['total'] * 1e3)
print([round(t) for t in tot])
print('p50', np.median(tot), 'p95', np.percentile(tot, 95), 'max', max(tot))
