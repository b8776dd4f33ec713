"""
The two forward models: the paper's encoder-decoder (the baseline) and ours.

Both map (initial images, normalised pressures) to the images at the actuation, in [0, 1]
units: input ``image`` is B x (V*C) x 64 x 64 float, ``pressure`` is B x 6 (Pa / max Pa),
output is B x (V*C) x 64 x 64. Views are stacked as channels (mono V=1, stereo V=2).
"""

from __future__ import annotations

import torch
from torch import nn

N_PRESSURES = 6
ARCHS = ('paper', 'ours')


class PaperNet(nn.Module):
    """
    Section II-B, Fig. 2: pressures broadcast to 64x64 planes, concatenated to the images.

    Encoder of strided conv + ReLU down to a 4x4 latent, decoder of transposed conv + ReLU
    back up, the last transposed conv (linear) being the regression output at 64x64.
    """

    def __init__(self, image_channels: int, widths=(16, 32, 64, 128)):
        super().__init__()
        enc, c = [], image_channels + N_PRESSURES
        for w in widths:
            enc += [nn.Conv2d(c, w, 4, 2, 1), nn.ReLU()]
            c = w
        dec = []
        for w in list(reversed(widths))[1:]:
            dec += [nn.ConvTranspose2d(c, w, 4, 2, 1), nn.ReLU()]
            c = w
        self.encoder = nn.Sequential(*enc)
        self.decoder = nn.Sequential(*dec)
        # The regression output: a linear transposed conv back to 64x64 images.
        self.head = nn.ConvTranspose2d(c, image_channels, 4, 2, 1)

    def forward(self, image: torch.Tensor, pressure: torch.Tensor) -> torch.Tensor:
        b, _, h, w = image.shape
        planes = pressure[:, :, None, None].expand(b, N_PRESSURES, h, w)
        return self.head(self.decoder(self.encoder(torch.cat([image, planes], 1))))


class FiLM(nn.Module):
    """Per-channel scale and shift from the actuation: every stage sees the pressures."""

    def __init__(self, cond: int, channels: int):
        super().__init__()
        self.proj = nn.Linear(cond, 2 * channels)
        nn.init.zeros_(self.proj.weight)
        nn.init.zeros_(self.proj.bias)

    def forward(self, x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        gamma, beta = self.proj(c)[:, :, None, None].chunk(2, 1)
        return x * (1 + gamma) + beta


class Stage(nn.Module):
    """Conv -> FiLM(actuation) -> ReLU."""

    def __init__(self, conv: nn.Module, cond: int, channels: int):
        super().__init__()
        self.conv, self.film = conv, FiLM(cond, channels)

    def forward(self, x, c):
        return torch.relu(self.film(self.conv(x), c))


class OursNet(nn.Module):
    """
    U-Net with FiLM conditioning at every stage, predicting the change from the initial image.

    Why: the paper's constant pressure planes only bias the first layer, and its bottleneck
    must re-draw the static background and object from a 4x4 latent. Skips carry the scene
    at full detail, FiLM lets the actuation steer every scale, and the residual output means
    the network only has to draw what moves.
    """

    def __init__(self, image_channels: int, widths=(16, 32, 64, 64), cond: int = 64):
        super().__init__()
        self.cond = nn.Sequential(nn.Linear(N_PRESSURES, cond), nn.ReLU(),
                                  nn.Linear(cond, cond), nn.ReLU())
        self.down = nn.ModuleList()
        c = image_channels + N_PRESSURES
        for w in widths:
            self.down.append(Stage(nn.Conv2d(c, w, 4, 2, 1), cond, w))
            c = w
        self.up = nn.ModuleList()
        self.merge = nn.ModuleList()
        for w in reversed(widths[:-1]):
            self.up.append(Stage(nn.ConvTranspose2d(c, w, 4, 2, 1), cond, w))
            self.merge.append(Stage(nn.Conv2d(2 * w, w, 3, 1, 1), cond, w))
            c = w
        # The last up-step draws the change at full resolution directly (no 64x64 convs:
        # they would triple the cost for little gain at this image size).
        self.head = nn.ConvTranspose2d(c, image_channels, 4, 2, 1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, image: torch.Tensor, pressure: torch.Tensor) -> torch.Tensor:
        b, _, h, w = image.shape
        c = self.cond(pressure)
        x = torch.cat([image, pressure[:, :, None, None].expand(b, N_PRESSURES, h, w)], 1)
        skips = []
        for stage in self.down:
            x = stage(x, c)
            skips.append(x)
        skips.pop()
        for up, merge in zip(self.up, self.merge):
            x = up(x, c)
            x = merge(torch.cat([x, skips.pop()], 1), c)
        return image + self.head(x)


def build_network(arch: str, views: int, channels: int, **params) -> nn.Module:
    """Construct ``arch`` ('paper' or 'ours') for ``views`` x ``channels`` images."""
    if arch == 'paper':
        return PaperNet(views * channels, **params)
    if arch == 'ours':
        return OursNet(views * channels, **params)
    raise ValueError(f'unknown architecture {arch!r} (choose from {", ".join(ARCHS)})')
