"""How close a model comes to the pedestrians standing in front of buildings: on the first 8
validation drives of the fronts world (preset ``val-fronts``), per pedestrian within 50 m with
5 or more returns, the highest pedestrian heatmap probability within 3 cells (1.2 m) of its
centre; quantiles for those standing at a front and the rest.

Usage: python front_heat.py CHECKPOINT_PATH [CHECKPOINT_PATH ...]
"""
from pathlib import Path
import sys

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'bystanders'))
from fronts import at_fronts  # noqa: E402  (this folder's)
from probe import heatmaps  # noqa: E402  (the bystanders page's heatmap hook)

from suit_ros import CLASS_NAMES  # noqa: E402
from suit_ros.checkpoint import load_checkpoint  # noqa: E402
from suit_ros.data.sequences import split_drives, synthetic_sequence  # noqa: E402
from suit_ros.evaluate import step_inputs  # noqa: E402
from suit_ros.model.streaming import StreamingDetector  # noqa: E402

torch.set_num_threads(2)
PED = CLASS_NAMES.index('pedestrian')
for path in sys.argv[1:]:
    model, cfg, meta = load_checkpoint(path)
    runner = StreamingDetector(model, 'cpu', precision='auto')
    heat = heatmaps(runner.model)
    vals: dict[bool, list[float]] = {True: [], False: []}
    for seed, sensor in split_drives('val', 8, 0):
        at = at_fronts(seed, sensor)
        runner.reset('next drive')
        for f in synthetic_sequence('val-fronts', seed, 40, 'data_cache', sensor):
            runner.step(*step_inputs(f))
            T = np.asarray(f.T_base_lidar)
            assert f.gt is not None and f.instance_ids is not None and f.num_points is not None
            for b, label, iid, n in zip(f.gt.boxes, f.gt.labels, f.instance_ids, f.num_points):
                if label != PED or n < 5 or np.hypot(*b[:2]) > 50:
                    continue
                xy = b[:2] @ T[:2, :2].T + T[:2, 3]
                col, row = (int(v) for v in
                            runner.model.grid.xy_to_cell(torch.tensor(xy[None]).float())[0])
                m = heat['map'][PED, max(row - 3, 0):row + 4, max(col - 3, 0):col + 4].max()
                vals[int(iid) in at].append(float(m))
    for front, v in vals.items():
        q = np.round(np.percentile(np.array(v), [10, 25, 50, 75, 90]), 2)
        print(f'{path}: pedestrians {"at a front" if front else "elsewhere"} {len(v)}, '
              f'heatmap quantiles 10/25/50/75/90: {q}')
