"""
The forward models: the paper's encoder-decoder (the baseline), ours, and the tube model.

All map (initial images, normalised pressures) to the images at the actuation, in [0, 1]
units: input ``image`` is B x (V*C) x 64 x 64 float, ``pressure`` is B x 6 (Pa / max Pa),
output is B x (V*C) x 64 x 64. Views are stacked as channels (mono V=1, stereo V=2).
Shapes in the comments: B batch, V views, C channels per view, S = 64 pixels.

``ours`` (:class:`OursNet`) redraws pixels (a FiLM U-Net); ``tube``
(:class:`~softshape_ros.model.tube_net.TubeNet`) moves the robot: keypoints of its backbone
drawn as a tube over the scene (docs/model.md compares them).
"""

from __future__ import annotations

import torch
from torch import nn

from softshape_ros.model.layers import Stage, coordinate_planes, down_conv, up_conv
from softshape_ros.model.tube_net import TubeNet

N_PRESSURES = 6
ARCHS = ('paper', 'ours', 'tube')
OUTPUTS = ('composite', 'residual')


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
            enc += [down_conv(c, w), nn.ReLU()]
            c = w
        dec = []
        for w in list(reversed(widths))[1:]:
            dec += [up_conv(c, w), nn.ReLU()]
            c = w
        self.encoder = nn.Sequential(*enc)
        self.decoder = nn.Sequential(*dec)
        # The regression output: a linear transposed conv back to 64x64 images.
        self.head = up_conv(c, image_channels)

    def forward(self, image: torch.Tensor, pressure: torch.Tensor) -> torch.Tensor:
        b, _, h, w = image.shape                                    # image: B x VC x S x S
        planes = pressure[:, :, None, None].expand(b, N_PRESSURES, h, w)   # B x 6 x S x S
        z = self.encoder(torch.cat([image, planes], 1))             # B x 128 x S/16 x S/16
        return self.head(self.decoder(z))                           # B x VC x S x S


class OursNet(nn.Module):
    """
    U-Net with FiLM conditioning at every stage, drawing only what the actuation changes.

    Why: the paper's constant pressure planes only bias the first layer, and its bottleneck
    must re-draw the static background and object from a 4x4 latent. Skips carry the scene
    at full detail, FiLM lets the actuation steer every scale. FiLM is a per-channel
    modulation, the same at every pixel, so two coordinate planes (CoordConv) join the input:
    where the tip goes depends on the actuation, and the network needs to know where it is
    drawing. All FiLM parameters come from one linear projection of the actuation embedding.

    Output ``residual`` (the default): ``out = initial + change``, the change drawn by a
    zero-initialised head, so training starts as the copy baseline and only what moves is
    drawn. Output ``composite`` (tried, lost at a fixed budget: docs/model.md, design
    study): per view an alpha ``a`` and colours ``c``, ``out = a c + (1 - a) initial``, so
    unchanged pixels are copied exactly and a sigmoid ``a`` makes an edge a choice.
    """

    def __init__(self, views: int, channels: int, widths=(16, 32, 64, 64), cond: int = 64,
                 coords: bool = True, output: str = 'residual'):
        super().__init__()
        if output not in OUTPUTS:
            raise ValueError(f'unknown output {output!r} (choose from {", ".join(OUTPUTS)})')
        self.views, self.channels, self.output = int(views), int(channels), output
        self.coords = bool(coords)
        image_channels = self.views * self.channels
        self.cond = nn.Sequential(nn.Linear(N_PRESSURES, cond), nn.ReLU(),
                                  nn.Linear(cond, cond), nn.ReLU())
        self.down = nn.ModuleList()
        c = image_channels + N_PRESSURES + (2 if self.coords else 0)
        for w in widths:
            self.down.append(Stage(down_conv(c, w), w))
            c = w
        self.up = nn.ModuleList()
        self.merge = nn.ModuleList()
        for w in reversed(widths[:-1]):
            self.up.append(Stage(up_conv(c, w), w))
            self.merge.append(Stage(nn.Conv2d(in_channels=2 * w, out_channels=w, kernel_size=3,
                                              padding=1), w))
            c = w
        # In the order forward() uses them: down stages, then (up, merge) per scale.
        stages = [*self.down, *[st for pair in zip(self.up, self.merge) for st in pair]]
        self._film_split = [2 * st.channels for st in stages]
        # Zero init: every stage starts as a plain conv + ReLU.
        self.film = nn.Linear(cond, sum(self._film_split))
        nn.init.zeros_(self.film.weight)
        nn.init.zeros_(self.film.bias)
        # The last up-step draws at full resolution directly (no 64x64 convs: they would
        # triple the cost for little gain at this image size). Composite: V alphas, VC colours.
        extra = self.views if output == 'composite' else 0
        self.head = up_conv(c, image_channels + extra)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        if output == 'composite':
            # Start as the copy baseline: alpha = sigmoid(-4) ~ 0.02 everywhere.
            with torch.no_grad():
                self.head.bias[:self.views] = -4.0

    def inputs(self, image: torch.Tensor, pressure: torch.Tensor) -> torch.Tensor:
        """Return the first stage's input: images, pressure planes (and coordinates)."""
        b, _, h, w = image.shape
        parts = [image, pressure[:, :, None, None].expand(b, N_PRESSURES, h, w)]
        if self.coords:
            parts.append(coordinate_planes(b, h, w, image))
        return torch.cat(parts, 1)

    def films(self, cond: torch.Tensor):
        """Return an iterator of (gamma, beta) per stage, in the order forward() runs them."""
        return (f.chunk(2, 1) for f in self.film(cond)[:, :, None, None]
                .split(self._film_split, 1))

    def compose(self, image: torch.Tensor, head: torch.Tensor) -> torch.Tensor:
        """Turn the head's output into the image: composite or residual (see the class)."""
        if self.output == 'residual':
            return image + head                                     # B x VC x S x S
        b, _, h, w = image.shape
        v, c = self.views, self.channels
        alpha = torch.sigmoid(head[:, :v]).view(b, v, 1, h, w)      # B x V x 1 x S x S
        colour = torch.sigmoid(head[:, v:]).view(b, v, c, h, w)     # B x V x C x S x S
        out = alpha * colour + (1 - alpha) * image.view(b, v, c, h, w)
        return out.view(b, v * c, h, w)                             # B x VC x S x S

    def forward(self, image: torch.Tensor, pressure: torch.Tensor) -> torch.Tensor:
        films = self.films(self.cond(pressure))                     # per stage: B x 2w x 1 x 1

        def run(stage, x):
            return stage(x, *next(films))

        x = self.inputs(image, pressure)                            # B x (VC+6+2) x S x S
        skips = []
        for stage in self.down:                                     # S/2, S/4, S/8, S/16
            x = run(stage, x)                                       # B x w_i x S/2^i x S/2^i
            skips.append(x)
        skips.pop()                                                 # the bottleneck itself
        for up, merge in zip(self.up, self.merge):                  # S/8, S/4, S/2
            x = run(up, x)                                          # B x w x s x s
            x = run(merge, torch.cat([x, skips.pop()], 1))          # B x 2w -> w x s x s
        return self.compose(image, self.head(x))                    # B x VC x S x S


def build_network(arch: str, views: int, channels: int, **params) -> nn.Module:
    """Construct ``arch`` (one of ``ARCHS``) for ``views`` x ``channels`` images."""
    if arch == 'paper':
        return PaperNet(views * channels, **params)
    if arch == 'ours':
        return OursNet(views, channels, **params)
    if arch == 'tube':
        return TubeNet(views, channels, **params)
    raise ValueError(f'unknown architecture {arch!r} (choose from {", ".join(ARCHS)})')
