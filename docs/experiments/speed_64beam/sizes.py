import time, glob, sys, numpy as np, torch
torch.set_num_threads(1)
from suit_ros.checkpoint import load_checkpoint, default_checkpoint_path
from suit_ros.data.sequences import load_sequence
from suit_ros.evaluate import step_inputs
from suit_ros.model.streaming import StreamingDetector
from suit_ros.tracking import FilterConfig
from dataclasses import replace
model, cfg, _ = load_checkpoint(str(default_checkpoint_path()), 'cpu')
def drive(pattern):
    return load_sequence(sorted(glob.glob(f'data_cache/{pattern}-*.npz'))[0])[:24]
sim32 = drive('val-real-sim32'); hdl = drive('val-real-hdl64e')
rng = np.random.default_rng(0)
def dense(f, k=2.3):
    n = int(len(f.points) * k); idx = rng.integers(0, len(f.points), n)
    p = f.points[idx].copy(); p[:, :3] += rng.normal(0, 0.03, (n, 3)).astype(np.float32)
    return replace(f, points=p)
big = [dense(f) for f in hdl]
sets = {'37k': sim32, '114k': hdl, '260k': big}
runners = {k: StreamingDetector(model, precision='auto', velocity_filter=FilterConfig()) for k in sets}
stages = ('sweeps', 'encode', 'head_decode', 'sampling', 'fusion', 'tracking', 'total')
T = {k: {s: [] for s in stages} for k in sets}
for i in range(len(sim32)):
    for k, fs in sets.items():
        r = runners[k].step(*step_inputs(fs[i]))
        if i >= 4:
            for s in stages: T[k][s].append(r.timings[s])
for k in sets:
    print(k, int(np.median([len(f.points) for f in sets[k]])), ' '.join(f'{s} {np.median(T[k][s])*1e3:.1f}' for s in stages))
print('114k/37k %.2f  260k/37k %.2f' % (np.median(T['114k']['total'])/np.median(T['37k']['total']), np.median(T['260k']['total'])/np.median(T['37k']['total'])))
