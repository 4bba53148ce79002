"""Deskew on the tune split: each shipped checkpoint as the node runs it (tracker on), its
sweeps as taken and deskewed (suit_ros.deskew, the motion of the poses up to each frame),
paired over drives. Usage: python docs/experiments/deskew/tune_deskew.py OUT.json [CKPT ...]
"""
from __future__ import annotations

import json
import sys

import torch

from suit_ros.accuracy import bootstrap, plain_intervals
from suit_ros.checkpoint import load_model_as, resolve_checkpoint
from suit_ros.data.sequences import split_drives, synthetic_split
from suit_ros.evaluate import run_model
from suit_ros.tracking import TrackerConfig

torch.set_num_threads(1)
out_path, names = sys.argv[1], sys.argv[2:] or ['suit_default', 'centerpoint_single']
drives = split_drives('tune', 16)
tune = synthetic_split('tune', 16, 40, 'data_cache')
# the drives whose sensor sweeps over time (every real spinning one): where deskew acts
moving = [i for i, f in enumerate(tune) if f[0].times is not None]
result: dict[str, object] = {'drives': [list(d) for d in drives], 'distorted': moving}
for name in names:
    model = load_model_as(resolve_checkpoint(name), None, 'cpu')
    for subset, seqs in (('all', tune), ('distorted', [tune[i] for i in moving])):
        runs = {f'{name} as taken': run_model(model, seqs, tracker=TrackerConfig()),
                f'{name} deskewed': run_model(model, seqs, tracker=TrackerConfig(),
                                              deskew=True)}
        stats, diffs = bootstrap(runs, model.cfg.class_names,
                                 [(f'{name} deskewed', f'{name} as taken')], 200)
        result[f'{name} {subset}'] = {'stats': plain_intervals(stats),
                                      'diffs': plain_intervals(diffs)}
        for k, v in stats.items():
            print(subset, k, {m: round(v[m].value, 4) for m in
                              ('mAP', 'NDS', 'mAVE', 'moving car vel err')}, flush=True)
        for k, v in diffs.items():
            print(subset, k, {m: [round(v[m].value, 4), round(v[m].low, 4), round(v[m].high, 4)]
                              for m in ('mAP', 'NDS', 'mAVE', 'moving car vel err')}, flush=True)
with open(out_path, 'w', encoding='utf-8') as f:
    json.dump(result, f, indent=1, default=float)
