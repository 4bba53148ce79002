"""Non-maximum suppression in pure torch: circle NMS (centre distance) and rotated BEV-IoU NMS.

Both are greedy in descending score order, like their CUDA counterparts, but vectorised: the
pairwise suppression matrix is computed once (rotated IoU only for the pairs the greedy pass
reads: a later box of the same class whose circumscribed circle meets), then a short loop over
the kept boxes resolves it (N is at most a few hundred after top-K). Float32 boxes on the CPU
(inference, and training on the CPU) take a compiled pass instead
(:func:`compiled_rotated_nms`): the same boxes kept (centre distances in float64, where the
tensor path's float32 ``cdist`` could round one at its threshold the other way), in one call
instead of a few dozen tensor operations.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from suit_ros.ops.iou import paired_bev_iou
from suit_ros.ops.kernels import greedy_bev_nms, suppress_near_kernel
from suit_ros.ops.kernels import paired_bev_iou as compiled_iou


def greedy_suppression(suppress: Tensor, order: Tensor) -> Tensor:
    """Greedy NMS over a boolean ``(N, N)`` suppression matrix given in score order."""
    sup = suppress.cpu().numpy()
    removed = np.zeros(sup.shape[0], dtype=bool)
    keep: list[int] = []
    for i in range(sup.shape[0]):
        if removed[i]:
            continue
        keep.append(i)
        removed |= sup[i]
    return order[torch.tensor(keep, dtype=torch.long, device=order.device)]


def circle_nms(centers: Tensor, scores: Tensor, radius: float | Tensor) -> Tensor:
    """Keep the highest-scoring centre within each ``radius`` (metres) neighbourhood.

    :param centers: ``(N, 2)`` BEV centres.
    :param scores: ``(N,)``.
    :param radius: suppression radius, scalar or per box ``(N,)`` (the kept box's radius).
    :return: kept indices ``(K,)`` in descending score order.
    """
    if centers.shape[0] == 0:
        return torch.zeros(0, dtype=torch.long, device=centers.device)
    order = torch.argsort(scores, descending=True, stable=True)
    c = centers[order]
    r = torch.as_tensor(radius, dtype=c.dtype, device=c.device)
    r = r[order] if r.ndim else r.expand(c.shape[0])
    d2 = torch.cdist(c.double(), c.double()).pow(2)
    suppress = d2 <= (r[:, None].double() ** 2)
    suppress.fill_diagonal_(False)
    return greedy_suppression(suppress, order)


def rotated_suppression(b: Tensor, candidates: Tensor, iou_threshold: float) -> Tensor:
    """``(N, N)`` IoU > threshold of boxes in score order, computed only for the pairs a
    greedy pass (:func:`greedy_suppression`) reads (``i < j``, ``candidates[i, j]``) whose
    circumscribed circles meet; every other entry is False."""
    N = b.shape[0]
    r = 0.5 * torch.hypot(b[:, 3], b[:, 4]).double()
    near = torch.cdist(b[:, :2].double(), b[:, :2].double()) < r[:, None] + r[None]
    i, j = torch.nonzero(torch.triu(near & candidates, diagonal=1), as_tuple=True)
    suppress = torch.zeros((N, N), dtype=torch.bool, device=b.device)
    if len(i):
        suppress[i, j] = pair_iou(b[i], b[j]) > iou_threshold
    return suppress


def pair_iou(a: Tensor, b: Tensor) -> Tensor:
    """:func:`~suit_ros.ops.iou.paired_bev_iou`, compiled for float32 boxes on the CPU
    (:func:`suit_ros.ops.kernels.paired_bev_iou`)."""
    if a.device.type == 'cpu' and a.dtype == torch.float32 and b.dtype == torch.float32:
        return torch.from_numpy(compiled_iou(a.detach().contiguous().numpy(),
                                             b.detach().contiguous().numpy()))
    return paired_bev_iou(a, b)


def compiled_rotated_nms(b: Tensor, group: Tensor, order: Tensor, iou_threshold: float,
                         min_distance: float = 0.0) -> Tensor | None:
    """Greedy rotated-IoU NMS of boxes ``b`` in score order (``order``: their indices) by
    the compiled kernel (:func:`suit_ros.ops.kernels.greedy_bev_nms`): boxes of different
    ``group`` never suppress each other, a kept box drops later ones whose centre lies closer
    than ``min_distance`` or whose IoU exceeds ``iou_threshold``; returns the kept indices, or
    None where the kernel does not apply (not float32 boxes on the CPU: the tensor path)."""
    if b.device.type != 'cpu' or b.dtype != torch.float32:
        return None
    keep = greedy_bev_nms(b.detach().contiguous().numpy(),
                          group.detach().to(torch.int64).contiguous().numpy(),
                          np.float32(iou_threshold), float(min_distance))
    return order[torch.from_numpy(keep)]


def rotated_nms(boxes: Tensor, scores: Tensor, iou_threshold: float) -> Tensor:
    """Greedy NMS on rotated BEV IoU of ``(N, 7)`` boxes; returns kept indices."""
    if boxes.shape[0] == 0:
        return torch.zeros(0, dtype=torch.long, device=boxes.device)
    order = torch.argsort(scores, descending=True, stable=True)
    b = boxes[order]
    kept = compiled_rotated_nms(b, torch.zeros_like(order), order, iou_threshold)
    if kept is not None:
        return kept
    full = torch.ones((b.shape[0], b.shape[0]), dtype=torch.bool, device=b.device)
    suppress = rotated_suppression(b, full, iou_threshold)
    return greedy_suppression(suppress, order)


def batched_nms(boxes: Tensor, scores: Tensor, labels: Tensor, kind: str = 'rotated',
                iou_threshold: float = 0.2, radius: Tensor | None = None) -> Tensor:
    """Class-aware NMS: boxes of different labels never suppress each other.

    :param kind: ``'rotated'`` (BEV IoU > ``iou_threshold``) or ``'circle'`` (``radius`` per
        class, a ``(num_classes,)`` tensor in metres).
    :return: kept indices in descending score order.
    """
    if boxes.shape[0] == 0:
        return torch.zeros(0, dtype=torch.long, device=boxes.device)
    order = torch.argsort(scores, descending=True, stable=True)
    b, lab = boxes[order], labels[order]
    if kind == 'rotated':
        kept = compiled_rotated_nms(b, lab, order, iou_threshold)
        if kept is not None:
            return kept
    same = lab[:, None] == lab[None, :]
    if kind == 'rotated':
        suppress = rotated_suppression(b, same, iou_threshold)
    elif kind == 'circle':
        if radius is None:
            raise ValueError('circle NMS needs per-class radii')
        r = radius.to(b.dtype)[lab]
        d2 = torch.cdist(b[:, :2].double(), b[:, :2].double()).pow(2)
        suppress = (d2 <= r[:, None].double() ** 2) & same
    else:
        raise ValueError(f"unknown NMS kind {kind!r}: use 'rotated' or 'circle'")
    suppress.fill_diagonal_(False)
    return greedy_suppression(suppress, order)


def suppress_near(centers: Tensor, labels: Tensor, movable: Tensor, radius: Tensor) -> Tensor:
    """Which of ``N`` boxes in descending score order stay when each ``movable`` one goes if a
    kept box of its class (any, movable or not) lies within its class's ``radius`` (metres).

    A box that is not movable always stays. :param centers: ``(N, 2)`` BEV centres;
    ``labels`` ``(N,)``; ``movable`` ``(N,)`` bool; ``radius`` ``(num_classes,)``.
    :return: ``(N,)`` bool.
    """
    n = centers.shape[0]
    keep = torch.ones(n, dtype=torch.bool, device=centers.device)
    if n == 0 or not bool(movable.any()):
        return keep
    r = radius.double().cpu()[labels.cpu()]
    kept = suppress_near_kernel(centers.detach().double().cpu().contiguous().numpy(),
                                labels.cpu().to(torch.int64).contiguous().numpy(),
                                movable.cpu().contiguous().numpy(), r.contiguous().numpy())
    return torch.from_numpy(kept).to(centers.device)
