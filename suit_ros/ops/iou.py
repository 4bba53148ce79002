"""Rotated bird's-eye-view IoU of ``(x, y, z, l, w, h, yaw)`` boxes, pure torch (vectorised).

The intersection of two rectangles is the convex polygon of their mutually contained corners
and their edge crossings, ordered by angle (:func:`paired_bev_iou`), for all pairs at once with
fixed-size padded polygons.
"""
from __future__ import annotations

import torch
from torch import Tensor

_INSIDE_TOL = 1e-6      # m: a corner on the other box's edge counts as inside
_PARALLEL_TOL = 1e-12   # m^2: edges this close to parallel do not cross (their ends are corners)


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


def _cross(a: Tensor, b: Tensor) -> Tensor:
    """z of the 2-D cross product of ``(..., 2)`` vectors."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def paired_bev_iou(boxes_a: Tensor, boxes_b: Tensor) -> Tensor:
    """Element-wise rotated BEV IoU ``(K,)`` of two ``(K, 7)`` box lists.

    The intersection of two rectangles is convex, and its vertices are among the corners of
    each rectangle that lie inside the other and the crossings of their edges (4 + 4 + 16
    candidates): the valid candidates, sorted by angle around their mean, form the polygon.
    A fixed number of tensor operations for all pairs at once (about half the time of clipping
    one rectangle by the other's four edges, measured on 20-400 pairs).
    """
    K = boxes_a.shape[0]
    if K == 0:
        return boxes_a.new_zeros(0)
    boxes = torch.cat([boxes_a, boxes_b]).double()
    corners = bev_corners(boxes)                                               # (2K, 4, 2)
    ca, cb = corners[:K], corners[K:]
    # each corner in the frame of the other box of its pair
    other = torch.cat([boxes[K:], boxes[:K]])
    d = corners - other[:, None, :2]
    c, s = torch.cos(other[:, 6])[:, None], torch.sin(other[:, 6])[:, None]
    along = (d[..., 0] * c + d[..., 1] * s).abs()
    across = (d[..., 1] * c - d[..., 0] * s).abs()
    inside = ((along <= other[:, None, 3] * 0.5 + _INSIDE_TOL)
              & (across <= other[:, None, 4] * 0.5 + _INSIDE_TOL))
    # edge i of a (p + t r, t in [0, 1]) against edge j of b (q + u v, u in [0, 1])
    r = torch.roll(ca, -1, 1) - ca                                             # (K, 4, 2)
    v = torch.roll(cb, -1, 1) - cb
    qp = cb[:, None, :, :] - ca[:, :, None, :]                                 # (K, 4, 4, 2)
    denom = _cross(r[:, :, None, :], v[:, None, :, :])                         # (K, 4, 4)
    parallel = denom.abs() < _PARALLEL_TOL
    safe = torch.where(parallel, torch.ones_like(denom), denom)
    t = _cross(qp, v[:, None, :, :]) / safe
    u = _cross(qp, r[:, :, None, :]) / safe
    crossing = ~parallel & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
    points = torch.cat([ca, cb, (ca[:, :, None, :] + t[..., None] * r[:, :, None, :])
                        .reshape(K, 16, 2)], dim=1)                            # (K, 24, 2)
    valid = torch.cat([inside[:K], inside[K:], crossing.reshape(K, 16)], dim=1)
    count = valid.sum(1)
    mean = ((points * valid[..., None].to(points.dtype)).sum(1)
            / count.clamp(min=1)[:, None].to(points.dtype))
    rel = points - mean[:, None]
    angle = torch.atan2(rel[..., 1], rel[..., 0]).masked_fill(~valid, 10.0)  # invalid last
    order = torch.argsort(angle, dim=1)
    polygon = torch.gather(points, 1, order[..., None].expand(K, 24, 2))
    inter = _polygon_area(polygon, count).where(count >= 3, points.new_zeros(()))
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
