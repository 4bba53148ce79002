import time, glob, numpy as np, torch
torch.set_num_threads(1)
from suit_ros.checkpoint import load_checkpoint, default_checkpoint_path
from suit_ros.data.sequences import load_sequence
from suit_ros.model.sweeps import model_frame
from suit_ros.model.inference import inference_copy
from suit_ros.model.pillars import PillarEncoder
model, cfg, _ = load_checkpoint(str(default_checkpoint_path()), 'cpu')
enc = inference_copy(model).pillars
for name in ['val-real-sim32', 'val-real-hdl64e']:
    seq = load_sequence(sorted(glob.glob(f'data_cache/{name}-*.npz'))[0])
    pts = [torch.cat([torch.zeros(len(f.points), 1), torch.from_numpy(f.points)], 1) for f in (model_frame(seq, t, 3) for t in range(4, 24))]
    T = {'one chunk': [], '32k chunks': []}
    with torch.no_grad():
        for p in pts:
            for k, c in (('one chunk', 10**9), ('32k chunks', 32768)):
                PillarEncoder.CHUNK = c
                s = time.perf_counter(); enc(p, 1); T[k].append(time.perf_counter() - s)
    print(name, len(pts[0]), {k: round(np.median(v) * 1e3, 1) for k, v in T.items()})
