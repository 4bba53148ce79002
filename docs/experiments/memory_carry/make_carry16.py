"""Run 12's composite: every weight of run 16 (suit_default: the overhang filter), the carry
branch (its W2 and head) of the earlier suit_carry (run 6), in its config with run 16's filter
(docs/experiments/memory_carry/configs/model_branch16.yaml, ground local as it runs). Run 16
is suit_default at commit 240b9ee (before its memory sampling moved to alpha 0.2), run 6 is
suit_carry there:

    git show 240b9ee:suit_ros/checkpoints/suit_default.safetensors > run16.safetensors
    git show 240b9ee:suit_ros/checkpoints/suit_carry.safetensors > run6.safetensors
    python docs/experiments/memory_carry/make_carry16.py run16.safetensors run6.safetensors OUT

Any SUIT base and carry checkpoint graft the same way; a fourth argument replaces the
description (run 26: suit_default of 2026-12-05, run 22, with suit_carry's branch).
"""
import dataclasses
import sys

from safetensors.torch import load_file
import torch

from suit_ros.checkpoint import (
    load_checkpoint,
    load_weights_into,
    read_metadata,
    save_checkpoint,
    update_metadata,
)
from suit_ros.model.detector import SUITDetector

default, carry, out = sys.argv[1:4]
description = (sys.argv[4] if len(sys.argv) > 4 else
               "run 16 (suit_default) with suit_carry's carry branch "
               '(docs/experiments/memory_carry, run 12)')
carry_model, _, _ = load_checkpoint(carry, 'cpu')
base_cfg = load_checkpoint(default, 'cpu')[0].cfg
cfg = dataclasses.replace(carry_model.cfg, pillars=base_cfg.pillars)
m = SUITDetector(cfg)
fresh = load_weights_into(m, default)
print('not from the base:', fresh)
weights = load_file(carry)
with torch.no_grad():
    for name, p in m.carry.state_dict(keep_vars=True).items():
        p.copy_(weights[f'carry.{name}'])
meta = read_metadata(default)
save_checkpoint(out, m.eval(), cfg, extra={'composite': [default, carry]})
update_metadata(out, publish_thresholds=meta['publish_thresholds'], description=description)
