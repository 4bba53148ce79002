"""An inference copy of a model: batch norms folded into the convolutions before them.

In eval mode a ``BatchNorm`` is a per-channel affine map ``y = g (x - mu) / sqrt(var + eps) + b``,
so a convolution followed by one equals a single convolution with scaled weights and a bias.
Folding removes a third of the backbone's and head's kernels from every step, and lets the
pillar encoder take its fast path (no decorated point tensor). ``scripts/bench_inference.py``
measures the step both ways; the outputs agree to float rounding (tested).
"""
from __future__ import annotations

import copy

import torch
from torch import nn

Foldable = nn.Conv2d | nn.ConvTranspose2d | nn.Linear


def _fold(layer: Foldable, bn: nn.BatchNorm1d | nn.BatchNorm2d) -> None:
    """Fold ``bn`` (eval statistics) into ``layer`` in place."""
    assert bn.running_mean is not None and bn.running_var is not None
    scale = (bn.weight if bn.affine else torch.ones_like(bn.running_var)) \
        / torch.sqrt(bn.running_var + bn.eps)
    shift = (bn.bias if bn.affine else torch.zeros_like(bn.running_mean)) \
        - bn.running_mean * scale
    with torch.no_grad():
        w = layer.weight
        if isinstance(layer, nn.ConvTranspose2d):          # (C_in, C_out / groups, kh, kw)
            w.mul_(scale.view(1, -1, *([1] * (w.dim() - 2))))
        else:                                              # (C_out, ...)
            w.mul_(scale.view(-1, *([1] * (w.dim() - 1))))
        bias = layer.bias if layer.bias is not None else torch.zeros_like(shift)
        new_bias = bias * scale + shift
        if layer.bias is None:
            layer.bias = nn.Parameter(new_bias)
        else:
            layer.bias.copy_(new_bias)


def _try_fold(layer: nn.Module, norm: nn.Module) -> bool:
    """Fold ``norm`` into ``layer`` when that is exact; return whether it was folded."""
    if (isinstance(norm, nn.BatchNorm1d | nn.BatchNorm2d) and norm.track_running_stats
            and isinstance(layer, Foldable)):
        _fold(layer, norm)
        return True
    return False


def fold_batchnorm(module: nn.Module) -> int:
    """Fold every ``BatchNorm`` that directly follows a conv or linear layer inside an
    ``nn.Sequential``, or that a module names in its ``fold_pairs`` (``(layer attribute, norm
    attribute)``, for a forward that applies them in that order), into that layer (the norm
    becomes ``nn.Identity``); in place, for a module in eval mode. Returns the number of norms
    folded."""
    if module.training:
        raise ValueError('fold_batchnorm needs a module in eval mode (running statistics)')
    folded = 0
    for m in module.modules():
        for layer_name, norm_name in getattr(m, 'fold_pairs', ()):
            layer, norm = getattr(m, layer_name), getattr(m, norm_name)
            if _try_fold(layer, norm):
                setattr(m, norm_name, nn.Identity())
                folded += 1
    for seq in [m for m in module.modules() if isinstance(m, nn.Sequential)]:
        for i in range(1, len(seq)):
            prev, cur = seq[i - 1], seq[i]
            if _try_fold(prev, cur):
                seq[i] = nn.Identity()
                folded += 1
    return folded


def inference_copy(model: nn.Module, channels_last: bool = True) -> nn.Module:
    """A deep copy of ``model`` in eval mode with its batch norms folded (the original is left
    as it is, so training can go on with it).

    :param channels_last: store the 4-D convolution weights channels-last (NHWC), which
        oneDNN's CPU convolutions run faster (the BEV maps then flow NHWC through the backbone
        and head; ``scripts/bench_inference.py`` measures it).
    """
    copied = copy.deepcopy(model).eval()
    fold_batchnorm(copied)
    if channels_last:
        for m in copied.modules():
            if isinstance(m, nn.Conv2d | nn.ConvTranspose2d):
                m.weight.data = m.weight.data.contiguous(memory_format=torch.channels_last)
    return copied
