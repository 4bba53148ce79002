#!/usr/bin/env python3
"""The shipped model's dense convolutions, timed alone on this CPU, in the ways torch can run them.

For each convolution shape of the SUIT step (the backbone, the neck's 1x1 and the head's shared
3x3, as the profiler lists them at 37k points), on one torch thread:

- ``fp32 NCHW`` and ``fp32 NHWC``: ``F.conv2d`` + ReLU (the inference copy is NHWC);
- ``fused NHWC``: oneDNN's convolution with the ReLU fused (``torch.ops.mkldnn._convolution_
  pointwise``, what inductor emits when it freezes a model);
- ``int8 <engine>``: the same convolution quantized (uint8 activations, int8 per-channel
  weights) on each quantized engine torch has here.

Prints the medians (ms) and each one's ratio to ``fp32 NHWC``. Figures:
docs/experiments/cpu_float32/README.md.

Usage: python docs/experiments/cpu_float32/conv_kernels.py [--repeats 15]
"""
from __future__ import annotations

import argparse
from collections.abc import Callable
import time
from typing import Any

import torch
from torch.ao.nn import quantized as nnq
import torch.nn.functional as F

# (in channels, out channels, input side, kernel, stride, calls a step)
SHAPES = [(32, 32, 256, 3, 2, 1), (32, 32, 128, 3, 1, 3), (32, 64, 128, 3, 2, 1),
          (64, 64, 64, 3, 1, 2), (64, 128, 64, 3, 2, 1), (128, 128, 32, 3, 1, 2),
          (96, 96, 128, 1, 1, 1), (96, 32, 128, 3, 1, 1)]


def medians_ms(repeats: int, calls: dict[str, tuple[Callable[..., object], tuple[object, ...]]]
               ) -> dict[str, float]:
    """The median wall time (ms) of each ``fn(*args)``, the calls interleaved round by round
    (so the VM's slow spells hit every variant alike), after three warm-up rounds."""
    times: dict[str, list[float]] = {name: [] for name in calls}
    for round_ in range(repeats + 3):
        for name, (fn, args) in calls.items():
            t0 = time.perf_counter()
            fn(*args)
            if round_ >= 3:
                times[name].append(time.perf_counter() - t0)
    return {name: sorted(t)[len(t) // 2] * 1e3 for name, t in times.items()}


def conv_relu(x: torch.Tensor, w: torch.Tensor, b: torch.Tensor, stride: int, pad: int
              ) -> torch.Tensor:
    """``F.conv2d`` then ReLU."""
    return F.relu(F.conv2d(x, w, b, stride, pad))


def quantized_on(engine: str) -> Callable[..., object]:
    """A quantized convolution run on ``engine`` (the engine is set before each call, since the
    variants are interleaved; the module is built once per engine and shape)."""
    built: dict[tuple[int, ...], Any] = {}

    def run(qx: torch.Tensor, ci: int, co: int, k: int, s: int, p: int, qw: torch.Tensor,
            b: torch.Tensor) -> object:
        torch.backends.quantized.engine = engine
        key = (ci, co, k, s, p)
        if key not in built:
            conv = nnq.Conv2d(ci, co, k, s, p)  # type: ignore[no-untyped-call]
            conv.set_weight_bias(qw, b)
            conv.scale, conv.zero_point = 0.05, 0
            built[key] = conv
        return built[key](qx)
    return run


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or '').splitlines()[0])
    parser.add_argument('--repeats', type=int, default=25)
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    pointwise = torch.ops.mkldnn._convolution_pointwise
    engines = [e for e in ('x86', 'fbgemm', 'onednn')
               if e in torch.backends.quantized.supported_engines]
    totals: dict[str, float] = {}
    for ci, co, side, k, s, per_step in SHAPES:
        p = k // 2
        x = torch.randn(1, ci, side, side).relu()
        w = torch.randn(co, ci, k, k) * 0.1
        b = torch.randn(co)
        xc = x.contiguous(memory_format=torch.channels_last)
        wc = w.contiguous(memory_format=torch.channels_last)
        qx = torch.quantize_per_tensor(x, 0.02, 0, torch.quint8).contiguous(
            memory_format=torch.channels_last)
        qw = torch.quantize_per_channel(w, torch.full((co,), 0.002),
                                        torch.zeros(co, dtype=torch.long), 0, torch.qint8)
        calls: dict[str, tuple[Callable[..., object], tuple[object, ...]]] = {
            'fp32 NCHW': (conv_relu, (x, w, b, s, p)),
            'fp32 NHWC': (conv_relu, (xc, wc, b, s, p)),
            'fused NHWC': (pointwise, (xc, wc, b, [p, p], [s, s], [1, 1], 1, 'relu', [None],
                                       None)),
        }
        for engine in engines:
            calls[f'int8 {engine}'] = (quantized_on(engine), (qx, ci, co, k, s, p, qw, b))
        row = medians_ms(args.repeats, calls)
        base = row['fp32 NHWC']
        for name, v in row.items():
            totals[name] = totals.get(name, 0.0) + per_step * v
        print(f'{ci}->{co} {k}x{k}/{s} at {side}x{side} (x{per_step}): ' + ', '.join(
            f'{name} {v:.2f} ms ({v / base:.2f}x)' for name, v in row.items()), flush=True)
    base = totals['fp32 NHWC']
    print("a step's convolutions: " + ', '.join(
        f'{name} {v:.1f} ms ({v / base:.2f}x)' for name, v in totals.items()))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
