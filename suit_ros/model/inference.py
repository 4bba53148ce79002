"""An inference copy of a model: batch norms folded into the convolutions before them.

In eval mode a ``BatchNorm`` is a per-channel affine map ``y = g (x - mu) / sqrt(var + eps) + b``,
so a convolution followed by one equals a single convolution with scaled weights and a bias.
Folding removes a third of the backbone's and head's kernels from every step, and lets the
pillar encoder take its fast path (no decorated point tensor). ``scripts/bench_inference.py``
measures the step both ways; the outputs agree to float rounding (tested).

Precision: on CPUs with bfloat16 matrix units (Intel AMX, or AVX512-BF16), oneDNN runs a
bfloat16 3x3 convolution several times faster than a float32 one. ``precision='bfloat16'``
runs the backbone, the neck, the fusion's 1x1 convolution over the current features and the
head's 3x3 convolutions in bfloat16 (the pillar encoder writes its pseudo-image in bfloat16,
the backbone hands bfloat16 features to the fusion, the past term is added to the fused map in
bfloat16 and the head takes that map as it is; where the heads read the fused map through W1
(:func:`fold_fusion`), their first layer runs in bfloat16 on the backbone's features and the
past term and edge correction, computed in float32, are added to its bfloat16 output); the
pillar features, the memory's features (gathered as float32), the past term and GeoNet, the
head's final 1x1 projections and the decoding stay float32, so box parameters and scores come
from float32 maps and the memory holds float32 features.
:func:`resolve_precision` picks bfloat16 for ``auto`` only where the CPU has those units.

The layers that run as gathered products at a few hundred cells (the heads' layers where a
carry head or the regression is read, a fold's conv, the fusion's W1 at the memory's cells)
keep their weights as those products take them (:func:`keep_gathered_weights`), and GeoNet's
convolutions over a memory sample's patch become three matrix products
(:meth:`~suit_ros.model.geonet.GeoNet.as_products`): on a few dozen rows the framework's
per-operation cost, not arithmetic, was the time.
"""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
import copy
import sys
from typing import Literal

import torch
from torch import Tensor, nn

Foldable = nn.Conv2d | nn.ConvTranspose2d | nn.Linear
Precision = Literal['float32', 'bfloat16']
PrecisionChoice = Literal['auto', 'float32', 'bfloat16']
CPU_BF16_FLAGS = ('amx_bf16', 'avx512_bf16')


def compiled_ok(*tensors: Tensor) -> bool:
    """Whether a compiled pass (:mod:`suit_ros.ops.kernels`, on numpy views of the tensors)
    may stand in for tensor code on ``tensors``: on the CPU, without autograd (grad mode off,
    and none of them requires grad)."""
    return not torch.is_grad_enabled() and all(
        t.device.type == 'cpu' and not t.requires_grad for t in tensors)


@contextmanager
def one_thread(enabled: bool = True) -> Iterator[None]:
    """Torch operations in this block on the calling thread alone (its torch thread count set
    to 1 and back): a step's small work, a few hundred cells, boxes or samples a tensor,
    whose operations a second thread only slows (forking the team for an operation of 65k
    elements and joining it cost more than it saved: the memory's sampling took 2.1 ms at
    two threads, 1.5 at one; docs/experiments/step_beside). Torch keeps the count per thread
    and a process-wide default for threads that start torch work later, which this block
    also sets to 1 while it lasts."""
    n = torch.get_num_threads()
    if not enabled or n == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


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


def cpu_has_bf16_units(cpuinfo: str = '/proc/cpuinfo') -> bool:
    """Whether this CPU has bfloat16 matrix units (AMX-BF16 or AVX512-BF16), read from the
    kernel's CPU flags; False where they cannot be read (not Linux)."""
    if not sys.platform.startswith('linux'):
        return False
    try:
        with open(cpuinfo, encoding='utf-8', errors='replace') as f:
            for line in f:
                if line.startswith('flags'):
                    flags = set(line.split(':', 1)[-1].split())
                    return any(flag in flags for flag in CPU_BF16_FLAGS)
    except OSError:
        return False
    return False


def resolve_precision(choice: PrecisionChoice, device: torch.device | str) -> Precision:
    """The precision the inference copy runs in: ``auto`` is bfloat16 on a CPU with bfloat16
    units (:func:`cpu_has_bf16_units`) and float32 everywhere else (CUDA included)."""
    if choice not in ('auto', 'float32', 'bfloat16'):
        raise ValueError(f'precision must be auto, float32 or bfloat16, got {choice!r}')
    if choice != 'auto':
        return choice
    return 'bfloat16' if torch.device(device).type == 'cpu' and cpu_has_bf16_units() \
        else 'float32'


class Cast(nn.Module):
    """Run ``inner`` with its weights in ``dtype``: the input is cast to ``dtype``, the output
    to ``out_dtype``."""

    def __init__(self, inner: nn.Module, dtype: torch.dtype, out_dtype: torch.dtype) -> None:
        super().__init__()
        self.inner = inner.to(dtype)
        self.dtype = dtype
        self.out_dtype = out_dtype

    def forward(self, x: Tensor) -> Tensor:
        """``inner(x as dtype)`` as ``out_dtype``."""
        out: Tensor = self.inner(x.to(self.dtype))
        return out.to(self.out_dtype)


def _low_precision(model: nn.Module, dtype: torch.dtype) -> int:
    """Wrap the backbone, the fusion's current-feature conv and the head's 3x3 layers of a
    detector in :class:`Cast` (in place); return how many modules were wrapped."""
    wrapped = 0
    pillars = getattr(model, 'pillars', None)
    if pillars is not None and hasattr(pillars, 'canvas_dtype'):
        pillars.canvas_dtype = dtype          # the pseudo-image is written in the backbone's dtype
    backbone = getattr(model, 'backbone', None)
    if isinstance(backbone, nn.Module):
        # its output stays in low precision: the fusion's conv and the head take it as it is
        model.backbone = Cast(backbone, dtype, dtype)
        wrapped += 1
    fusion = getattr(model, 'fusion', None)
    if fusion is not None and isinstance(getattr(fusion, 'current', None), nn.Conv2d):
        # the fused map stays in low precision too (the past term is added in it): the head
        # takes it as it is (or, folded, reads it through W1); the memory's features are
        # gathered from it as float32
        fusion.current = Cast(fusion.current, dtype, dtype)
        wrapped += 1
    carry = getattr(model, 'carry', None)
    for head in (getattr(model, 'head', None), getattr(carry, 'head', None)):
        if head is not None and isinstance(getattr(head, 'shared', None), nn.Sequential):
            head.shared = Cast(head.shared, dtype, dtype)
            wrapped += 1
            if getattr(head, 'fold', None) is not None:   # the shared layer composed with W1
                head.fold.conv = Cast(head.fold.conv, dtype, dtype)
                wrapped += 1
            for name in ('heatmap', 'regression'):
                branch = getattr(head, name)
                # the 3x3 conv (+ folded norm, ReLU) in low precision, the final 1x1 in float32
                setattr(head, name, nn.Sequential(Cast(branch[:-1], dtype, torch.float32),
                                                  branch[-1]))
                wrapped += 1
    return wrapped


def fold_fusion(model: nn.Module) -> int:
    """Compose the first layer of a sparse-memory detector's heads (its own and a carry
    branch's) with the fusion's current-feature 1 x 1 convolution W1
    (:class:`~suit_ros.model.head.HeadFold`), so that no step runs W1 over the whole map; in
    place, on a model whose norms are folded. Not for a W1 that is the identity (skipped
    already) or a dense memory. Returns the number of heads folded."""
    from suit_ros.config import SPARSE_MEMORIES
    from suit_ros.model.head import HeadFold
    fusion = getattr(model, 'fusion', None)
    cfg = getattr(model, 'cfg', None)
    if (fusion is None or cfg is None or cfg.temporal not in SPARSE_MEMORIES
            or not isinstance(fusion.current, nn.Conv2d) or fusion.mark_identity()):
        return 0
    folded = 0
    carry = getattr(model, 'carry', None)
    for head in (getattr(model, 'head', None), getattr(carry, 'head', None)):
        if head is not None:
            head.fold = HeadFold(head.shared, fusion.current, head.grid.H, head.grid.W)
            folded += 1
    return folded


def inference_copy(model: nn.Module, channels_last: bool = True,
                   precision: Precision = 'float32') -> nn.Module:
    """A deep copy of ``model`` in eval mode with its batch norms folded (the original is left
    as it is, so training can go on with it).

    :param channels_last: store the 4-D convolution weights channels-last (NHWC), which
        oneDNN's CPU convolutions run faster (the BEV maps then flow NHWC through the backbone
        and head; ``scripts/bench_inference.py`` measures it).
    :param precision: ``bfloat16`` runs the backbone, the fusion's current-feature conv and
        the head's 3x3 convolutions in bfloat16 (see the module docstring); resolve ``auto``
        with :func:`resolve_precision`.
    """
    if precision not in ('float32', 'bfloat16'):
        raise ValueError(f'precision must be float32 or bfloat16, got {precision!r}')
    copied = copy.deepcopy(model).eval()
    fold_batchnorm(copied)
    fold_fusion(copied)
    cfg = getattr(copied, 'cfg', None)
    if hasattr(copied, 'lazy_regression') and cfg is not None:
        # the regression branch only at the cells decoded and sampled (CenterHead.forward_lazy)
        copied.lazy_regression = cfg.fusion_gate != 'unobserved_output'
    if precision == 'bfloat16':
        _low_precision(copied, torch.bfloat16)
    if channels_last:
        for m in copied.modules():
            if isinstance(m, nn.Conv2d | nn.ConvTranspose2d):
                m.weight.data = m.weight.data.contiguous(memory_format=torch.channels_last)
    from suit_ros.model.fusion import TemporalFusion
    from suit_ros.model.geonet import GeoNet
    for m in copied.modules():
        if isinstance(m, TemporalFusion):
            m.mark_identity()
        elif isinstance(m, GeoNet):
            m.as_products()
    keep_gathered_weights(copied)
    return copied


def keep_gathered_weights(model: nn.Module) -> int:
    """Let the layer stacks that an inference copy runs as gathered products at a few cells
    (the heads' layers, a fold's conv, the fusion's W1: :func:`~suit_ros.model.head._at_cells`)
    keep their weights as those products take them (``gathered_cache``), converted once, not
    every step; for a copy whose weights no longer change. Returns the number of stacks."""
    from suit_ros.model.fusion import TemporalFusion
    stacks: list[nn.Module] = []
    carry = getattr(model, 'carry', None)
    for head in (getattr(model, 'head', None), getattr(carry, 'head', None)):
        if head is None:
            continue
        stacks += [getattr(head, name) for name in ('shared', 'heatmap', 'regression')]
        if getattr(head, 'fold', None) is not None:
            stacks.append(head.fold.conv)
    stacks += [m for m in model.modules() if isinstance(m, TemporalFusion)]
    for m in stacks:
        m.__dict__['gathered_cache'] = {}     # a plain attribute, not a module or buffer
    return len(stacks)
