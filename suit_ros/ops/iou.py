"""Rotated bird's-eye-view IoU of ``(x, y, z, l, w, h, yaw)`` boxes, pure torch (vectorised).

The intersection of two convex quadrilaterals is computed by Sutherland-Hodgman clipping of A
against the four edges of B, for all pairs at once, with fixed-size padded polygons.
"""
from __future__ import annotations

import torch
from torch import Tensor


def bev_corners(boxes: Tensor) -> Tensor:
    """Return the BEV corners ``(N, 4, 2)`` counter-clockwise of ``(N, 7)`` boxes."""
    x, y, l, w, yaw = boxes[:, 0], boxes[:, 1], boxes[:, 3], boxes[:, 4], boxes[:, 6]
    dx = torch.stack([l, -l, -l, l], dim=1) * 0.5
    dy = torch.stack([w, w, -w, -w], dim=1) * 0.5
    c, s = torch.cos(yaw)[:, None], torch.sin(yaw)[:, None]
    # (+l,+w), (-l,+w), (-l,-w), (+l,-w): counter-clockwise, as the clipping expects
    px = x[:, None] + c * dx - s * dy
    py = y[:, None] + s * dx + c * dy
    return torch.stack([px, py], dim=-1)


def _polygon_area(poly: Tensor, valid: Tensor) -> Tensor:
    """Shoelace area of padded polygons ``(..., P, 2)`` whose first ``valid`` points count."""
    P = poly.shape[-2]
    idx = torch.arange(P, device=poly.device)
    n = valid.unsqueeze(-1)
    mask = idx < n
    nxt = torch.where(idx + 1 < n, idx + 1, torch.zeros_like(idx)).expand(poly.shape[:-1])
    q = torch.gather(poly, -2, nxt.unsqueeze(-1).expand(poly.shape))
    cross = poly[..., 0] * q[..., 1] - poly[..., 1] * q[..., 0]
    return 0.5 * (cross * mask).sum(-1).abs()


def _clip(subject: Tensor, count: Tensor, a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """Clip padded polygons ``(K, P, 2)`` (``count`` valid points) by the half-plane left of a->b.

    Returns new padded polygons ``(K, P + 1 ... )`` with at most P + 1 points (capped at 8).
    """
    K, P, _ = subject.shape
    idx = torch.arange(P, device=subject.device)
    valid = idx[None] < count[:, None]
    nxt = torch.where(idx[None] + 1 < count[:, None], idx[None] + 1, torch.zeros_like(idx[None]))
    cur = subject
    nex = torch.gather(subject, 1, nxt.unsqueeze(-1).expand(K, P, 2))
    e = (b - a)[:, None, :]

    def side(p: Tensor) -> Tensor:
        return e[..., 0] * (p[..., 1] - a[:, None, 1]) - e[..., 1] * (p[..., 0] - a[:, None, 0])

    sc, sn = side(cur), side(nex)
    inc, inn = sc >= 0, sn >= 0
    t = sc / torch.where((sc - sn).abs() < 1e-12, torch.full_like(sc, 1e-12), sc - sn)
    inter = cur + t.unsqueeze(-1) * (nex - cur)
    # each edge emits: (cur if inside) then (intersection if it crosses)
    emit_cur = inc & valid
    emit_int = (inc != inn) & valid
    pts = torch.stack([cur, inter], dim=2).reshape(K, 2 * P, 2)
    keep = torch.stack([emit_cur, emit_int], dim=2).reshape(K, 2 * P)
    order = torch.argsort((~keep).to(torch.int8), dim=1, stable=True)
    pts = torch.gather(pts, 1, order.unsqueeze(-1).expand(K, 2 * P, 2))[:, :8]
    new_count = keep.sum(1).clamp(max=8)
    return pts, new_count


def paired_bev_iou(boxes_a: Tensor, boxes_b: Tensor) -> Tensor:
    """Element-wise rotated BEV IoU ``(K,)`` of two ``(K, 7)`` box lists."""
    K = boxes_a.shape[0]
    if K == 0:
        return boxes_a.new_zeros(0)
    subject = bev_corners(boxes_a.double())
    subject = torch.cat([subject, subject.new_zeros(K, 4, 2)], dim=1)
    count = torch.full((K,), 4, dtype=torch.long, device=boxes_a.device)
    clip = bev_corners(boxes_b.double())
    for k in range(4):
        subject, count = _clip(subject, count, clip[:, k], clip[:, (k + 1) % 4])
    inter = _polygon_area(subject, count).where(count >= 3, subject.new_zeros(()))
    area_a = (boxes_a[:, 3] * boxes_a[:, 4]).double()
    area_b = (boxes_b[:, 3] * boxes_b[:, 4]).double()
    iou = inter / (area_a + area_b - inter).clamp(min=1e-9)
    return iou.clamp(0.0, 1.0).to(boxes_a.dtype)


def bev_iou(boxes_a: Tensor, boxes_b: Tensor) -> Tensor:
    """Pairwise rotated BEV IoU ``(N, M)`` of ``(N, 7)`` and ``(M, 7)`` boxes.

    Only pairs whose circumscribed circles intersect are clipped; the rest are 0.
    """
    N, M = boxes_a.shape[0], boxes_b.shape[0]
    out = boxes_a.new_zeros((N, M))
    if N == 0 or M == 0:
        return out
    ra = 0.5 * torch.hypot(boxes_a[:, 3], boxes_a[:, 4])
    rb = 0.5 * torch.hypot(boxes_b[:, 3], boxes_b[:, 4])
    dist = torch.cdist(boxes_a[:, :2].double(), boxes_b[:, :2].double())
    i, j = torch.nonzero(dist < (ra[:, None] + rb[None]).double(), as_tuple=True)
    out[i, j] = paired_bev_iou(boxes_a[i], boxes_b[j])
    return out
