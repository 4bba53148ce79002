"""The 2D BEV backbone and neck: strided conv blocks, upsampling, concatenation (SECOND RPN)."""
from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn


def _conv_bn(cin: int, cout: int, stride: int = 1) -> list[nn.Module]:
    return [nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False),
            nn.BatchNorm2d(cout, eps=1e-3, momentum=0.01), nn.ReLU(inplace=True)]


class BEVBackbone(nn.Module):
    """``(B, C_in, ny, nx)`` -> ``(B, sum(num_upsample_filters), ny / s0, nx / s0)``.

    Block ``i`` is a strided 3x3 conv followed by ``layer_nums[i]`` 3x3 convs; each block's
    output is brought to the first block's resolution (1x1 conv or transposed conv) and all are
    concatenated.
    """

    def __init__(self, in_channels: int, layer_nums: Sequence[int],
                 layer_strides: Sequence[int], num_filters: Sequence[int],
                 upsample_strides: Sequence[int], num_upsample_filters: Sequence[int]) -> None:
        super().__init__()
        self.blocks = nn.ModuleList()
        self.deblocks = nn.ModuleList()
        cin = in_channels
        for n, s, c, u, cu in zip(layer_nums, layer_strides, num_filters, upsample_strides,
                                  num_upsample_filters):
            layers = _conv_bn(cin, c, s)
            for _ in range(n):
                layers += _conv_bn(c, c)
            self.blocks.append(nn.Sequential(*layers))
            if u == 1:
                up: nn.Module = nn.Conv2d(c, cu, 1, bias=False)
            else:
                up = nn.ConvTranspose2d(c, cu, u, stride=u, bias=False)
            self.deblocks.append(nn.Sequential(up, nn.BatchNorm2d(cu, eps=1e-3, momentum=0.01),
                                               nn.ReLU(inplace=True)))
            cin = c
        self.out_channels = int(sum(num_upsample_filters))

    def forward(self, x: Tensor) -> Tensor:
        """Run the blocks and the neck."""
        ups = []
        for block, deblock in zip(self.blocks, self.deblocks):
            x = block(x)
            ups.append(deblock(x))
        return torch.cat(ups, dim=1)
