"""
Building blocks shared by the networks.

Strided (transposed) convolutions, FiLM stages, coordinate planes.
"""

from __future__ import annotations

import torch
from torch import nn


def down_conv(cin: int, cout: int) -> nn.Conv2d:
    """Return a stride-2 4x4 convolution: halves the image side."""
    return nn.Conv2d(in_channels=cin, out_channels=cout, kernel_size=4, stride=2, padding=1)


def up_conv(cin: int, cout: int) -> nn.ConvTranspose2d:
    """Return a stride-2 4x4 transposed convolution: doubles the image side."""
    return nn.ConvTranspose2d(in_channels=cin, out_channels=cout, kernel_size=4, stride=2,
                              padding=1)


class Stage(nn.Module):
    """Conv -> FiLM (per-channel scale and shift from the actuation) -> ReLU."""

    def __init__(self, conv: nn.Module, channels: int):
        super().__init__()
        self.conv, self.channels = conv, channels

    def forward(self, x, gamma, beta):
        return torch.relu(self.conv(x) * (1 + gamma) + beta)


def coordinate_planes(b: int, h: int, w: int, like: torch.Tensor) -> torch.Tensor:
    """Return B x 2 x H x W planes of x and y in [-1, 1] (CoordConv)."""
    kw = {'dtype': like.dtype, 'device': like.device}
    ys = torch.linspace(-1.0, 1.0, h, **kw).view(1, 1, h, 1).expand(b, 1, h, w)
    xs = torch.linspace(-1.0, 1.0, w, **kw).view(1, 1, 1, w).expand(b, 1, h, w)
    return torch.cat([xs, ys], 1)
