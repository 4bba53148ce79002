"""GeoNet (paper section IV-B): where will this object be? A distribution over displacements.

A three-layer CNN looks at a sample's ``Hs x Ws x C`` feature patch and predicts a softmax over
an ``Hw x Hw`` window of displacement bins. Bins are velocities, ``k * velocity_step`` per axis,
and a bin's displacement is its velocity times the real time gap between the two frames, so the
same weights serve a 10 Hz node and a 20 Hz bag.

Motion evidence: the patch features come from multi-sweep input (a moving object leaves a trail
of returns with growing time lags), and, with ``velocity_input``, the velocity the head decoded
at the sample (rotated into the current frame, in units of ``velocity_step``) is appended to the
patch as two constant channels, so GeoNet can weigh the head's estimate against the patch.
"""
from __future__ import annotations

import typing

import torch
from torch import Tensor, nn
import torch.nn.functional as F

from suit_ros.model.fusion import state_key


class GeoNet(nn.Module):
    """``(M, C, Hs, Ws)`` patches (+ velocities) -> ``(M, Hw * Hw)`` displacement-bin logits."""

    def __init__(self, in_channels: int, window: int, bins: int = 7, channels: int = 32,
                 velocity_step: float = 5.0, velocity_input: bool = False) -> None:
        super().__init__()
        self.window = window
        self.bins = bins
        # set on an inference copy (:meth:`as_products`): the layers as matrices over the patch
        self.products = 0
        self.product_key: tuple[typing.Any, ...] = ()
        self.velocity_step = velocity_step
        self.velocity_input = velocity_input
        self.net = nn.Sequential(
            nn.Conv2d(in_channels + (2 if velocity_input else 0), channels, 3, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(channels, channels, 3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(channels, bins * bins, window))
        half = bins // 2
        k = torch.arange(-half, half + 1, dtype=torch.float32) * velocity_step
        vy, vx = torch.meshgrid(k, k, indexing='ij')
        self.register_buffer('bin_velocities', torch.stack([vx.reshape(-1), vy.reshape(-1)], 1),
                             persistent=False)

    def forward(self, patches: Tensor, velocities: Tensor | None = None) -> Tensor:
        """Return logits ``(M, bins * bins)``; bin ``j * bins + i`` is velocity
        ``((i - bins // 2) * step, (j - bins // 2) * step)``.

        :param velocities: ``(M, 2)`` m/s in the current frame; required with
            ``velocity_input``.
        """
        if self.velocity_input:
            if velocities is None:
                raise ValueError("this GeoNet takes the samples' velocities")
            M, _, H, W = patches.shape
            v = (velocities / self.velocity_step)[:, :, None, None].expand(M, 2, H, W)
            patches = torch.cat([patches, v.to(patches)], dim=1)
        if patches.shape[-2:] == (self.window, self.window) and self._products_current():
            M, C, Hs, Ws = patches.shape
            weight = self.get_buffer('product_weight_0')
            h = patches.reshape(M, C * Hs * Ws).to(weight.dtype) @ weight \
                + self.get_buffer('product_bias_0')
            return self._later_products(h)
        out: Tensor = self.net(patches).flatten(1)
        return out

    def memory_logits(self, features: Tensor, mask: Tensor, velocities: Tensor | None = None
                      ) -> Tensor:
        """:meth:`forward` on a memory's samples as they are stored: ``features`` ``(M, P, C)``
        (``P = window^2`` cells, row-major), zero where ``mask`` ``(M, P)`` is False. An
        inference copy (:meth:`as_products`) multiplies the rows as they lie (its first product
        reordered to the memory's layout, the velocity's constant channels summed over the
        window once); otherwise they are laid out as patches for :meth:`forward`."""
        M, P, C = features.shape
        rows = features * mask[..., None].to(features.dtype)
        if P == self.window * self.window and self._products_current():
            weight = self.get_buffer('memory_weight')
            h = rows.reshape(M, P * C).to(weight.dtype) @ weight \
                + self.get_buffer('product_bias_0')
            if self.velocity_input:
                if velocities is None:
                    raise ValueError("this GeoNet takes the samples' velocities")
                h = h + velocities.to(h.dtype) @ self.get_buffer('velocity_weight')
            return self._later_products(h)
        patches = rows.permute(0, 2, 1).reshape(M, C, self.window, self.window)
        logits: Tensor = self(patches, velocities)
        return logits

    def _products_current(self) -> bool:
        """Whether :meth:`as_products` made the products and the convolutions are still the
        ones they were made from (no load or update since)."""
        return bool(self.products) and self.product_key == state_key(self.net)

    def _later_products(self, h: Tensor) -> Tensor:
        """The layers after the first as products: a ReLU, then each one's matrix and bias."""
        for k in range(1, self.products):
            weight = self.get_buffer(f'product_weight_{k}')
            h = torch.relu(h).to(weight.dtype) @ weight + self.get_buffer(f'product_bias_{k}')
        return h

    def as_products(self) -> int:
        """For an inference copy: each convolution over a ``window x window`` patch (the
        only input a memory gives) becomes one matrix product of the flattened patch, composed
        once (the convolution of an identity basis). On a few dozen 3 x 3 patches the three
        convolutions cost the framework far more than their arithmetic; the products give the
        same logits up to float rounding. Returns the number of layers."""
        convs = [m for m in self.net if isinstance(m, nn.Conv2d)]
        # conv, ReLU, conv, ..., conv: plain zero-padded convolutions with a ReLU between
        if not (len(self.net) == 2 * len(convs) - 1
                and all(isinstance(m, nn.Conv2d) and m.padding_mode == 'zeros'
                        for m in list(self.net)[::2])
                and all(isinstance(m, nn.ReLU) for m in list(self.net)[1::2])):
            self.products = 0
            return 0
        first = convs[0]
        shape = (first.in_channels, self.window, self.window)
        with torch.no_grad():
            for k, conv in enumerate(convs):
                n = shape[0] * shape[1] * shape[2]
                basis = torch.eye(n, dtype=conv.weight.dtype, device=conv.weight.device)
                out = F.conv2d(basis.view(n, *shape), conv.weight, None, conv.stride,
                               conv.padding, conv.dilation, conv.groups)
                bias = (conv.bias if conv.bias is not None
                        else conv.weight.new_zeros(conv.out_channels))
                self.register_buffer(f'product_weight_{k}', out.reshape(n, -1).contiguous(),
                                     persistent=False)
                self.register_buffer(f'product_bias_{k}', bias[:, None, None].expand(
                    out.shape[1:]).reshape(-1).contiguous(), persistent=False)
                shape = (out.shape[1], out.shape[2], out.shape[3])
        self.products = len(convs)
        # the first product over a memory's (P, C) rows; the velocity channels' rows summed
        # over the window (a constant there), in units of m/s
        weight0 = self.get_buffer('product_weight_0')                # ((C + v) * P, out)
        P = self.window * self.window
        C = weight0.shape[0] // P - (2 if self.velocity_input else 0)
        by_channel = weight0.view(-1, P, weight0.shape[1])           # (C + v, P, out)
        self.register_buffer('memory_weight', by_channel[:C].permute(1, 0, 2)
                             .reshape(P * C, -1).contiguous(), persistent=False)
        if self.velocity_input:
            self.register_buffer('velocity_weight', by_channel[C:].sum(dim=1)
                                 / self.velocity_step, persistent=False)
        # a load or an update of the convolutions since, and they run instead
        self.product_key = state_key(self.net)
        return self.products


    def target_bins(self, velocities: Tensor) -> Tensor:
        """Bin index ``(M,)`` of velocities ``(M, 2)`` (nearest bin, clipped to the window)."""
        half = self.bins // 2
        idx = torch.round(velocities / self.velocity_step).long().clamp(-half, half) + half
        return idx[:, 1] * self.bins + idx[:, 0]

    def loss(self, logits: Tensor, velocities: Tensor, valid: Tensor | None = None) -> Tensor:
        """Cross-entropy against the bins of the assigned GT velocities (0 when unassigned)."""
        if logits.shape[0] == 0:
            return logits.sum() * 0.0
        target = self.target_bins(velocities)
        if valid is not None:
            target = torch.where(valid, target, self.target_bins(torch.zeros_like(velocities)))
        return F.cross_entropy(logits, target)
