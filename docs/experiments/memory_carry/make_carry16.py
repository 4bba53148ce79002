"""Run 12's composite: every weight of run 16 (suit_default: the overhang filter), the carry
branch (its W2 and head) of suit_carry, in suit_carry's config with run 16's filter.

    python docs/experiments/memory_carry/make_carry16.py OUT.safetensors
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

out = sys.argv[1]
default = 'suit_ros/checkpoints/suit_default.safetensors'
carry = 'suit_ros/checkpoints/suit_carry.safetensors'
carry_model, _, _ = load_checkpoint(carry, 'cpu')
base_cfg = load_checkpoint(default, 'cpu')[0].cfg
cfg = dataclasses.replace(carry_model.cfg, pillars=base_cfg.pillars)
m = SUITDetector(cfg)
fresh = load_weights_into(m, default)
print('not from run 16:', fresh)
weights = load_file(carry)
with torch.no_grad():
    for name, p in m.carry.state_dict(keep_vars=True).items():
        p.copy_(weights[f'carry.{name}'])
meta = read_metadata(default)
save_checkpoint(out, m.eval(), cfg, extra={'composite': [default, carry]})
update_metadata(out, publish_thresholds=meta['publish_thresholds'],
                description='run 16 (suit_default) with suit_carry\'s carry branch '
                            '(docs/experiments/memory_carry, run 12)')
