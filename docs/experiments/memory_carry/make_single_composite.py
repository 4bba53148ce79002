"""Composite for run 10: the carry branch on the single-frame model.

The shipped single-frame checkpoint gives the pillars, the backbone and the head (also copied
into the carry head); the fusion keeps its initialisation (W1 the identity, W2 zero), so every
cell with returns decodes exactly as the single-frame model; GeoNet and the carry W2 come from
the shipped suit_carry checkpoint (trained on SUIT's features: a starting point only).

    python docs/experiments/memory_carry/make_single_composite.py SINGLE SUIT_CARRY OUT
"""
import sys

from safetensors.torch import load_file
import torch

from suit_ros.checkpoint import load_weights_into, read_metadata, save_checkpoint, update_metadata
from suit_ros.config import load_model_config
from suit_ros.model.detector import SUITDetector

single, carry_src, out = sys.argv[1:4]
cfg = load_model_config('docs/experiments/memory_carry/configs/model_branch.yaml')
m = SUITDetector(cfg)
fresh = load_weights_into(m, single)
state = load_file(carry_src)
taken = {k: v for k, v in state.items() if k.startswith(('geonet.', 'carry.past.'))}
m.load_state_dict(taken, strict=False)
print('from', carry_src, sorted(taken))
print('initialised fresh:', sorted(set(fresh) - set(taken)))
assert m.fusion is not None
with torch.no_grad():   # the own path adds nothing: observed cells decode as the single frame
    assert torch.equal(m.fusion.current.weight[:, :, 0, 0], torch.eye(m.fusion.past.in_features))
    assert not m.fusion.past.weight.any()
save_checkpoint(out, m.eval(), cfg, extra={'composite': [single, carry_src]})
update_metadata(out, publish_thresholds=read_metadata(single)['publish_thresholds'])
