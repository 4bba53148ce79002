"""SUIT's temporal state: the sparse memory of significant samples, and the dense baseline's map.

Only what significant sampling kept survives a frame: per sample a window of features, their
metric positions, their heatmap probabilities, the decoded box, plus the frame's stamp, frame id
and pose. The ego transform that moves the memory into the next frame is computed in float64.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
import torch
from torch import Tensor

from suit_ros.model.inference import compiled_ok
from suit_ros.ops.geometry import ego_transform


@dataclass
class SparseMemory:
    """Significant samples of one batch of frames (``B`` frames, ``M`` samples, ``P`` cells).

    :param batch_index: ``(M,)`` which frame of the batch each sample belongs to.
    :param cell_xy: ``(M, P, 2)`` metric positions of each relaxed cell, in the LiDAR frame of
        capture.
    :param features: ``(M, P, C)`` BEV features at those cells (zeros where ``mask`` is False).
    :param probs: ``(M, P)`` max-class heatmap probability p(R | I) at each cell.
    :param mask: ``(M, P)`` which window cells belong to the relaxed neighbourhood.
    :param boxes: ``(M, 7)`` box decoded at the sample's centre cell.
    :param velocities: ``(M, 2)`` velocity decoded at the sample's centre cell.
    :param poses: ``(B, 4, 4)`` float64 ``T_odom_base`` of each frame (the model frame's pose).
    :param ages: ``(M,)`` int64 nanoseconds since each sample's object last had returns under
        it (None: all 0; only the carry of :func:`suit_ros.model.sampling.keep_carried` makes
        them grow, by the stamps' gap each frame).
    :param own: ``(M,)`` bool, with a carry branch (``fusion_gate: carry_branch``): the
        samples the model's own memory holds (this frame's, from its own heatmap), the others
        being held by the carry only (None: all are its own).
    """

    batch_index: Tensor
    cell_xy: Tensor
    features: Tensor
    probs: Tensor
    mask: Tensor
    boxes: Tensor
    velocities: Tensor
    stamps_ns: list[int]
    poses: NDArray[np.float64]
    window: int
    ages: Tensor | None = None
    own: Tensor | None = None

    @property
    def num_samples(self) -> int:
        """Number of significant samples ``M``."""
        return int(self.batch_index.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes held by the memory (tensors, poses, stamps)."""
        tensors = (self.batch_index, self.cell_xy, self.features, self.probs, self.mask,
                   self.boxes, self.velocities) + tuple(
                       t for t in (self.ages, self.own) if t is not None)
        return (sum(t.numel() * t.element_size() for t in tensors) + self.poses.nbytes
                + 8 * len(self.stamps_ns))

    def detach(self) -> SparseMemory:
        """Return a copy cut from the autograd graph (truncated backprop through time)."""
        return SparseMemory(self.batch_index, self.cell_xy.detach(), self.features.detach(),
                            self.probs.detach(), self.mask, self.boxes.detach(),
                            self.velocities.detach(), list(self.stamps_ns),
                            self.poses.copy(), self.window, self.ages, self.own)

    def age(self) -> Tensor:
        """``(M,)`` long: :attr:`ages`, zeros when not set."""
        if self.ages is None:
            return torch.zeros_like(self.batch_index)
        return self.ages

    def select(self, index: Tensor) -> SparseMemory:
        """The samples ``index`` (frame stamps and poses unchanged)."""
        return SparseMemory(self.batch_index[index], self.cell_xy[index], self.features[index],
                            self.probs[index], self.mask[index], self.boxes[index],
                            self.velocities[index], self.stamps_ns, self.poses, self.window,
                            None if self.ages is None else self.ages[index],
                            None if self.own is None else self.own[index])

    def owned(self) -> Tensor:
        """``(M,)`` bool: :attr:`own`, all True when not set."""
        if self.own is None:
            return torch.ones_like(self.batch_index, dtype=torch.bool)
        return self.own


@dataclass
class DenseMemory:
    """The dense baseline's state: the whole previous fused BEV map ``(B, C, H, W)``."""

    features: Tensor
    stamps_ns: list[int]
    poses: NDArray[np.float64]

    @property
    def num_samples(self) -> int:
        """Every cell is kept: ``B * H * W``."""
        B, _, H, W = self.features.shape
        return int(B * H * W)

    @property
    def nbytes(self) -> int:
        """Bytes held by the memory."""
        return (self.features.numel() * self.features.element_size() + self.poses.nbytes
                + 8 * len(self.stamps_ns))


def _compiled(memory: SparseMemory, *more: Tensor) -> bool:
    """Whether the memory (with ``more``) moves in a compiled pass (:mod:`suit_ros.ops.
    kernels`): on the CPU, without autograd (inference)."""
    return compiled_ok(memory.cell_xy, memory.boxes, memory.velocities, *more)


def ego_transforms(poses_now: NDArray[np.float64], poses_prev: NDArray[np.float64]
                   ) -> NDArray[np.float64]:
    """Batch of ``T_now_prev = inv(T_odom_now) @ T_odom_prev``, ``(B, 4, 4)`` float64."""
    return np.stack([ego_transform(a, b) for a, b in zip(poses_now, poses_prev)])


def transform_sample_positions(memory: SparseMemory, T_now_prev: NDArray[np.float64]) -> Tensor:
    """Move every sample cell into the current LiDAR frame: ``(M, P, 2)`` metres, float32.

    Each cell is lifted to 3D at its sample's box centre height, transformed in float64 with its
    frame's ``T_now_prev``, and projected back to BEV.
    """
    M, P, _ = memory.cell_xy.shape
    if M == 0:
        return memory.cell_xy.new_zeros((0, P, 2))
    if _compiled(memory):
        from suit_ros.ops.kernels import move_cells
        out = np.empty((M, P, 2), np.float32)
        move_cells(memory.cell_xy.float().contiguous().numpy(),
                   memory.boxes[:, 2].float().contiguous().numpy(),
                   np.ascontiguousarray(T_now_prev, np.float64),
                   memory.batch_index.to(torch.int64).contiguous().numpy(), out)
        return torch.from_numpy(out)
    T = torch.from_numpy(np.ascontiguousarray(T_now_prev)).to(memory.cell_xy.device)
    T = T[memory.batch_index]                                              # (M, 4, 4) f64
    xyz = torch.cat([memory.cell_xy.double(),
                     memory.boxes[:, None, 2:3].double().expand(M, P, 1)], dim=-1)
    moved = torch.einsum('mij,mpj->mpi', T[:, :3, :3], xyz) + T[:, None, :3, 3]
    return moved[..., :2].float()


def rotate_velocities(velocities: Tensor, batch_index: Tensor,
                      T_now_prev: NDArray[np.float64]) -> Tensor:
    """Rotate ``(M, 2)`` velocities from the previous frame's axes into the current frame's."""
    if velocities.shape[0] == 0:
        return velocities
    if compiled_ok(velocities) and velocities.dtype == torch.float32:
        # a few dozen rows: numpy's per-operation cost is a fraction of torch's
        Rn = np.ascontiguousarray(T_now_prev[:, :2, :2]).astype(np.float32)[batch_index.numpy()]
        return torch.from_numpy(np.einsum('mij,mj->mi', Rn, velocities.numpy()))
    R = torch.from_numpy(np.ascontiguousarray(T_now_prev[:, :2, :2])).to(velocities.device)
    R = R[batch_index].to(velocities.dtype)
    return torch.einsum('mij,mj->mi', R, velocities)


def moved_memory(memory: SparseMemory, positions: Tensor, shift: Tensor,
                 T_now_prev: NDArray[np.float64], poses: NDArray[np.float64],
                 stamps_ns: list[int]) -> SparseMemory:
    """The samples of ``memory`` carried into the current frame, older by the gap between
    their frame's stamp and the current one's (nanoseconds, at least 1).

    :param memory: the samples to carry (in their frame of capture).
    :param positions: ``(M, P, 2)`` their cells already moved by the ego transform
        (:func:`transform_sample_positions`); :param shift: ``(M, 2)`` the object's own
        displacement since then (GeoNet's expected displacement, metres), added to cells and
        box centre.
    :param T_now_prev: ``(B, 4, 4)`` per frame of the batch; ``poses``/``stamps_ns``: the
        current frames'.
    """
    if (_compiled(memory, shift)
            and memory.boxes.dtype == memory.velocities.dtype == torch.float32):
        from suit_ros.ops.kernels import move_boxes
        boxes = torch.empty_like(memory.boxes)
        velocities = torch.empty_like(memory.velocities)
        move_boxes(memory.boxes.contiguous().numpy(), memory.velocities.contiguous().numpy(),
                   shift.float().contiguous().numpy(),
                   np.ascontiguousarray(T_now_prev, np.float64),
                   memory.batch_index.to(torch.int64).contiguous().numpy(), boxes.numpy(),
                   velocities.numpy())
    else:
        T = torch.from_numpy(np.ascontiguousarray(T_now_prev)).to(memory.boxes.device)
        T = T[memory.batch_index]                                           # (M, 4, 4) f64
        boxes = memory.boxes.clone()
        if memory.num_samples:
            centre = torch.einsum('mij,mj->mi', T[:, :3, :3], memory.boxes[:, :3].double()) \
                + T[:, :3, 3]
            boxes[:, :3] = centre.to(boxes.dtype)
            boxes[:, :2] += shift.to(boxes.dtype)
            boxes[:, 6] += torch.atan2(T[:, 1, 0], T[:, 0, 0]).to(boxes.dtype)
        velocities = rotate_velocities(memory.velocities, memory.batch_index, T_now_prev)
    return SparseMemory(memory.batch_index, positions + shift[:, None, :].to(positions.dtype),
                        memory.features, memory.probs, memory.mask, boxes, velocities,
                        list(stamps_ns), np.asarray(poses, np.float64).copy(), memory.window,
                        memory.age() + _gaps_ns(memory, stamps_ns))


def _gaps_ns(memory: SparseMemory, stamps_ns: list[int]) -> Tensor:
    """``(M,)`` int64: each sample's gap from its frame's stamp to the current one (at least
    1 ns, so an age grows every frame whatever the stamps say)."""
    if len(memory.stamps_ns) != len(stamps_ns):
        raise ValueError(f'moved_memory: {len(memory.stamps_ns)} frames in the memory, '
                         f'{len(stamps_ns)} now')
    gaps = [max(int(now) - int(then), 1) for now, then in zip(stamps_ns, memory.stamps_ns)]
    return torch.tensor(gaps, dtype=torch.int64,
                        device=memory.batch_index.device)[memory.batch_index]
