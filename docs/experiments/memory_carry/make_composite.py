"""Composite for the carry branch: the shipped SUIT model, its head copied into the carry head,
the carry W2 taken from a run-4 checkpoint (trained to carry with the shipped head frozen)."""
import sys

from safetensors.torch import load_file
import torch

from suit_ros.checkpoint import load_weights_into, read_metadata, save_checkpoint, update_metadata
from suit_ros.config import load_model_config
from suit_ros.model.detector import SUITDetector

shipped, carry_src, out = sys.argv[1:4]
cfg = load_model_config('docs/experiments/memory_carry/configs/model_branch.yaml')
m = SUITDetector(cfg)
fresh = load_weights_into(m, shipped)
print('not initialised:', fresh)
if carry_src != 'zero':
    w = load_file(carry_src)['fusion.past.weight']
    with torch.no_grad():
        m.carry.past.weight.copy_(w)
meta = read_metadata(shipped)
save_checkpoint(out, m.eval(), cfg, extra={'composite': [shipped, carry_src]})
update_metadata(out, publish_thresholds=meta['publish_thresholds'])
