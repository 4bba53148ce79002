"""The carry head's first layer at its feeding cells as a bfloat16 product (stop 61), tried in
one process against the shipped float32 one, frame by frame in turn over the demo drive:

- ``single``: suit_carry's weights run as temporal none;
- ``carry``: suit_carry as shipped (the 3 x 3 neighbourhoods of the bfloat16 map gathered as
  float32, a float32 product, on one torch thread);
- ``carry_bf16``: the neighbourhoods gathered as bfloat16 (half the bytes, no conversion) and
  ``F.linear`` in bfloat16 (oneDNN, AMX on this CPU), its output rounded to bfloat16 as the
  dense conv's is, then the bias and the past term added in float32; on one torch thread;
- ``carry_bf16_all``: the same on every torch thread.

Prints each variant's step p50 and its ratio to the single frame's, the time inside the
first layer (``HeadFold.at``) per frame, and how many published boxes differ from ``carry``'s.

Usage: python bf16_first_layer.py THREADS FRAMES
"""
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
import time
from typing import Any

from demo_runners import demo_runners
import numba
import numpy as np
import torch
import torch.nn.functional as F

import suit_ros.model.detector as detector
import suit_ros.model.head as head
from suit_ros.ops.kernels import _tap_row, add_tap_spread


@numba.njit(nogil=True)
def gather_taps_u16(rows: Any, cells: Any, H: int, W: int, out: Any) -> None:
    """The 3 x 3 neighbourhoods of ``cells`` of bfloat16 rows (their uint16 bits), as bits."""
    C = rows.shape[1]
    none = np.zeros(0, np.int64)
    for m in range(cells.shape[0]):
        for t in range(9):
            r = _tap_row(cells, m, t, H, W, none, rows.shape[0])
            for c in range(C):
                out[m, t * C + c] = rows[r, c] if r >= 0 else np.uint16(0)


threads, n, inputs, runners = demo_runners({
    k: ('suit_carry', 'none' if k == 'single' else None)
    for k in ('single', 'carry', 'carry_bf16', 'carry_bf16_all')})
current = ['single']
spent: dict[str, float] = defaultdict(float)
shipped_at = head.HeadFold.at
low_weights: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}


def at(self: head.HeadFold, fused: Any, cells: torch.Tensor,
       where: torch.Tensor | None = None) -> torch.Tensor:
    t0 = time.perf_counter()
    if not current[0].startswith('carry_bf16') or fused.current.dtype != torch.bfloat16:
        out: torch.Tensor = shipped_at(self, fused, cells, where)
        spent[current[0]] += time.perf_counter() - t0
        return out
    B, C, H, W = fused.current.shape
    rows = fused.current.permute(0, 2, 3, 1).reshape(-1, C)
    bits = np.empty((len(cells), 9 * C), np.uint16)
    gather_taps_u16(rows.view(torch.int16).numpy().view(np.uint16),
                    cells.to(torch.int64).contiguous().numpy(), H, W, bits)
    patches = torch.from_numpy(bits.view(np.int16)).view(torch.bfloat16)
    if id(self) not in low_weights:
        weight, bias = next((a, b) for k, a, b in head._cached_ops(self.conv, torch.float32)
                            if k == 'taps')
        low_weights[id(self)] = (weight.to(torch.bfloat16), bias)
    weight, bias = low_weights[id(self)]
    v = F.linear(patches, weight).float()
    v += bias
    assert where is not None
    add_tap_spread(v.numpy(), *self._spread(fused.past),
                   where.to(torch.int64).contiguous().numpy(), H, W)
    spent[current[0]] += time.perf_counter() - t0
    return torch.relu_(v)


head.HeadFold.at = at
one_thread = detector.one_thread


@contextmanager
def carry_head_threads(enabled: bool = True) -> Iterator[None]:
    """predict's one_thread: a no-op for ``carry_bf16_all``."""
    if current[0] == 'carry_bf16_all':
        yield
    else:
        with one_thread(enabled):
            yield


detector.one_thread = carry_head_threads
for k, r in runners.items():
    current[0] = k
    r.warm_up()
steps: dict[str, list[float]] = {k: [] for k in runners}
differ = dict.fromkeys(runners, 0)
boxes = 0
for i, args in enumerate(inputs):
    if i == 5:
        spent.clear()
    out = {}
    for k, r in runners.items():
        current[0] = k
        t = time.perf_counter()
        out[k] = r.step(*args).detections
        if i >= 5:
            steps[k].append(time.perf_counter() - t)
    ref = out['carry']
    boxes += len(ref.boxes)
    for k, d in out.items():
        same = (len(d.boxes) == len(ref.boxes)
                and bool(np.all(np.abs(d.boxes - ref.boxes) < 1e-3))
                and bool(np.all(d.labels == ref.labels)))
        differ[k] += 0 if same else 1
p = {k: float(np.median(v)) * 1e3 for k, v in steps.items()}
frames = n - 5
print(f'threads {threads}, {frames} frames (after 5), {boxes} published carry boxes')
for k in runners:
    print(f"{k:15s} step p50 {p[k]:6.2f} ms ({p[k] / p['single']:.3f}x the single frame's), "
          f"first layer {spent[k] / frames * 1e3:.3f} ms a frame, frames whose boxes differ "
          f"from carry's (> 1 mm or label): {differ[k]}")
