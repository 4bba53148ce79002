"""Keeping ordinary frames as they were while the memory learns to carry (self-distillation).

Training the temporal modules and the head on clips with outages teaches the memory to carry
objects, but it also moves the outputs on ordinary frames (measured: mAP 0.745 -> 0.680 in
``reference/memory-carry-trial.md``). :class:`Distiller` holds a frozen copy of the starting
model's output stage (the fusion's current-frame conv and the head) and, on frames without an
outage, pulls the student's heatmap and regression maps toward what that copy computes from the
same current features, without a memory. On ordinary frames the memory then adds only what
the loss asks for, and on outage frames (not distilled) the ground truth teaches carrying.
"""
from __future__ import annotations

import copy

import torch
from torch import Tensor, nn

from suit_ros.model.head import REG_SLICES


class Distiller(nn.Module):
    """A frozen teacher: ``head(current_conv(F_t))`` of the model it was built from."""

    def __init__(self, head: nn.Module, current: nn.Module | None, weight: float,
                 floor: float = 0.1) -> None:
        super().__init__()
        self.head = copy.deepcopy(head).eval().requires_grad_(False)
        self.current = (copy.deepcopy(current).eval().requires_grad_(False)
                        if current is not None else None)
        self.weight = weight
        self.floor = floor

    def train(self, mode: bool = True) -> Distiller:
        """The teacher stays in eval mode."""
        return super().train(False)

    def loss(self, features: Tensor, preds: dict[str, Tensor], ordinary: Tensor,
             cells: Tensor | None = None) -> Tensor:
        """Distillation loss over the frames of the batch flagged ``ordinary`` ``(B,)``, and
        within them over ``cells`` ``(B, H, W)`` bool when given (with the memory gate: the
        cells with returns, where the memory adds nothing and the output must stay).

        Heatmap: squared difference of the probabilities summed over cells, divided by the
        number of cells where the teacher sees an object (max probability over ``floor``).
        Regression: L1 weighted by the teacher's max probability, normalised by its sum.
        """
        if not bool(ordinary.any()):
            return features.new_zeros(())
        with torch.no_grad():
            x = features[ordinary]
            if self.current is not None:
                x = self.current(x)
            teacher = self.head(x)
            t_prob = torch.sigmoid(teacher['heatmap'].float())
            keep = (torch.ones_like(t_prob[:, :1]) if cells is None
                    else cells[ordinary][:, None].to(t_prob.dtype))           # (b, 1, H, W)
            w = t_prob.amax(dim=1, keepdim=True) * keep
        s_prob = torch.sigmoid(preds['heatmap'][ordinary].float())
        hm = (((s_prob - t_prob) ** 2) * keep).sum() / (w > self.floor).sum().clamp(min=1)
        s_reg = torch.cat([preds[n][ordinary] for n in REG_SLICES], dim=1).float()
        t_reg = torch.cat([teacher[n] for n in REG_SLICES], dim=1).float()
        reg = ((s_reg - t_reg).abs() * w).sum() / (w.sum() * s_reg.shape[1]).clamp(min=1e-6)
        return self.weight * (hm + reg)
