"""
A differentiable tube renderer: the robot's keypoints in, coverage and shading out.

The robot in an S x S input image is a tube: per view, K backbone points (x = column, y =
row, pixel centres at integer coordinates), the apparent radius and the depth (px further
from the camera than the base) at each; the outline is the union of the capsules between
consecutive points with linearly varying radius (each backbone point a sphere, seen as a
disk). Per pixel, the signed distance to that outline gives the coverage (a 1-pixel ramp:
an area-averaged edge) and the nearest segment gives the surface normal, hence the shading
of a Lambertian tube under a directional light (per view, learned). Batched torch over
pixels and segments at once, no Python loop over either; gradients reach every keypoint.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

#: Keypoint channels: x, y (px), radius (px), depth (px further than the base).
X, Y, R, Z = range(4)


class TubeField(NamedTuple):
    """Per pixel (B x V x P each, P = S*S row-major): distance, normal, depth, radius."""

    sd: torch.Tensor        # px to the outline, negative inside
    nx: torch.Tensor        # unit surface normal facing the camera (camera frame:
    ny: torch.Tensor        # x right, y down, z forward)
    nz: torch.Tensor
    depth: torch.Tensor     # the backbone's depth at the nearest point (px)
    radius: torch.Tensor    # the tube's radius there (px)


def pixel_grid(size: int, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Return (x, y) pixel-centre coordinates, each size*size, row-major."""
    r = torch.arange(size, dtype=like.dtype, device=like.device)
    ys, xs = torch.meshgrid(r, r, indexing='ij')
    return xs.reshape(-1), ys.reshape(-1)


#: Rows (B x V) from which :func:`nearest_segment` takes one segment at a time: with fewer
#: (a prediction's one scene), the loop's per-segment overhead costs more than it saves.
LOOP_ROWS = 16


def _segment_distances(a, e, exy2, qx, qy) -> torch.Tensor:
    """Return the signed distances (px) from the pixels to capsules ``a`` + t ``e``, in place."""
    px, py = qx - a[..., X], qy - a[..., Y]
    t = (px * e[..., X]).addcmul_(py, e[..., Y]).div_(exy2).clamp_(0.0, 1.0)
    px.addcmul_(t, e[..., X], value=-1.0)                            # px, py: offsets from
    py.addcmul_(t, e[..., Y], value=-1.0)                            # the nearest axis point
    sd = px.mul_(px).addcmul_(py, py).add_(1e-6).sqrt_()
    return sd.sub_(a[..., R]).addcmul_(t, e[..., R], value=-1.0)


def nearest_segment(keypoints: torch.Tensor, qx: torch.Tensor, qy: torch.Tensor) -> torch.Tensor:
    """
    Return B x V x P: per pixel (``qx``, ``qy``: :func:`pixel_grid`), the nearest capsule.

    The only pass over every pixel x segment pair, so it runs without autograd and in
    place (a minimum's gradient reaches only the segment it picked anyway): what made the
    tube model's training step slow was this pass's B x V x (K-1) x P temporaries kept for
    the backward pass (docs/model.md, "A faster renderer"). From :data:`LOOP_ROWS` rows on,
    one segment at a time with a running minimum (ties to the first, as ``min`` gives):
    B x V x P temporaries that stay in cache took 0.6 of the time of the one pass over
    B x V x (K-1) x P on two threads, with the same answer to the bit.
    """
    with torch.no_grad():
        kp = keypoints.detach()
        a = kp[:, :, :-1, None, :]                                   # B x V x S x 1 x 4
        e = kp[:, :, 1:, None, :] - a                                # S = K - 1 segments
        exy2 = (e[..., X] ** 2 + e[..., Y] ** 2).clamp_min(1e-6)     # B x V x S x 1
        if torch.compiler.is_compiling():
            # Compiled (training's compiled renderer, ONNX export): every pair at once, one
            # fused reduction that keeps no pair in memory (a loop would be unrolled).
            px, py = qx - a[..., X], qy - a[..., Y]                  # B x V x S x P
            t = ((px * e[..., X] + py * e[..., Y]) / exy2).clamp(0.0, 1.0)
            dx, dy = px - t * e[..., X], py - t * e[..., Y]
            sd = (dx * dx + dy * dy + 1e-6).sqrt() - a[..., R] - t * e[..., R]
            return sd.min(dim=2).indices
        if a.shape[0] * a.shape[1] < LOOP_ROWS:
            return _segment_distances(a, e, exy2, qx, qy).min(dim=2).indices
        best = nearest = None
        for j in range(a.shape[2]):                                  # B x V x P each
            sd = _segment_distances(a[:, :, j], e[:, :, j], exy2[:, :, j], qx, qy)
            if best is None:
                best, nearest = sd, torch.zeros(sd.shape, dtype=torch.long, device=sd.device)
            else:
                closer = sd < best
                best = torch.where(closer, sd, best)
                nearest.masked_fill_(closer, j)
        return nearest


def tube_field(keypoints: torch.Tensor, size: int) -> TubeField:
    """
    Return the signed distance to the tube's outline and the tube's normal at each pixel.

    ``keypoints`` B x V x K x 4 (x, y, radius, depth in px). On a segment's side the normal
    is a cylinder's along the segment's 3-D direction, at the rounded ends a sphere's: at
    in-image offset ``rel`` = distance / radius along unit direction ``u`` from the axis,
    ``n = rel u + sqrt(1 - rel^2) w``, ``w`` the unit vector across the axis facing the
    camera, ``(tz e, -|t_xy|)`` for a segment of unit 3-D direction ``t`` (``e`` its unit
    image direction), ``(0, 0, -1)`` for a sphere. The nearest segment is found without
    gradients (:func:`nearest_segment`); everything else, with gradients, for it alone.
    """
    qx, qy = pixel_grid(size, keypoints)                             # P
    k = nearest_segment(keypoints, qx, qy)                           # B x V x P
    idx = k[..., None].expand(*k.shape, keypoints.shape[-1])
    a = torch.gather(keypoints, 2, idx)                              # B x V x P x 4
    e = torch.gather(keypoints, 2, idx + 1) - a
    ex, ey, er, ez = e.unbind(-1)                                    # B x V x P each
    ar, az = a[..., R], a[..., Z]
    exy2 = (ex ** 2 + ey ** 2).clamp_min(1e-6)
    px, py = qx - a[..., X], qy - a[..., Y]
    s = (px * ex + py * ey) / exy2
    t = s.clamp(0.0, 1.0)
    dx, dy = px - t * ex, py - t * ey
    d = torch.sqrt(dx * dx + dy * dy + 1e-6)
    rel = (d / (ar + t * er)).clamp(max=1.0)
    face = torch.sqrt((1.0 - rel * rel).clamp_min(0.0) + 1e-6)
    exy = torch.sqrt(exy2)
    n3 = torch.sqrt(exy2 + ez * ez)
    side = ((s > 0.0) & (s < 1.0)).to(keypoints.dtype)               # else a rounded end
    wx, wy = side * (ez / n3) * (ex / exy), side * (ez / n3) * (ey / exy)
    wz = -(side * exy / n3 + (1.0 - side))
    return TubeField(d - ar - t * er, rel * dx / d + face * wx, rel * dy / d + face * wy,
                     face * wz, az + t * ez, ar + t * er)


def front_depth(field: TubeField) -> torch.Tensor:
    """
    Return B x V x P: the depth (px, as the keypoints') of the tube's near surface per pixel.

    The backbone's depth less the radius along the normal's camera-facing part: the full
    radius at the tube's middle, nothing at its outline. What a depth test compares.
    """
    return field.depth + field.radius * field.nz


def coverage(sd: torch.Tensor) -> torch.Tensor:
    """
    Return the share of each pixel the tube covers: a 1-pixel ramp across the outline.

    What an area-averaged render gives across a straight edge along a pixel row; the exact
    area at other angles (up to sqrt(2) px wide, quadratic ends) changed the simulator's
    images' yellow mask by 0.06 % of the image in a check, not worth its cost.
    """
    return (0.5 - sd).clamp(0.0, 1.0)


class TubeShader(nn.Module):
    """
    Per view: the robot's colour at a pixel from the tube's normal there.

    A Lambertian surface under a directional light ``l`` (camera frame): ``c0 + c1
    max(n . l, 0)`` per channel; ``l`` (a unit vector) and ``c0``, ``c1`` are learned per
    view, starting at the simulator's palette and head light. ``outline`` (``TubeNet(outline=
    True)``, opt-in): per view, how far (px) the drawn outline lies outside the keypoints'
    radius (:meth:`coverage`), learned from zero. Why: drawn from the shape record's own
    keypoints, the simulated robot's edge sat 0.1 px further out than the 1-pixel ramp put
    it, and the silhouette lost a quarter of its rim pixels to that; where the edge lies
    depends on how the images were made (docs/model.md, "The outline").
    """

    def __init__(self, views: int, channels: int, outline: bool = False):
        super().__init__()
        self.views, self.channels = views, channels
        self.light = nn.Parameter(torch.tensor([0.0, -0.5, -0.86]).repeat(views, 1))
        self.c0 = nn.Parameter(torch.full((views, channels), 0.17))
        self.c1 = nn.Parameter(torch.full((views, channels), 0.21))
        self.outline = nn.Parameter(torch.zeros(views)) if outline else None

    def coverage(self, field: TubeField) -> torch.Tensor:
        """Return B x V x P: the share of each pixel the tube covers (:func:`coverage`)."""
        if self.outline is None:
            return coverage(field.sd)
        return coverage(field.sd - self.outline[None, :, None])

    def forward(self, field: TubeField) -> torch.Tensor:
        """Return B x V x C x P robot colour in [0, 1] units."""
        light = self.light / self.light.norm(dim=1, keepdim=True)   # V x 3
        lam = (field.nx * light[None, :, 0, None] + field.ny * light[None, :, 1, None]
               + field.nz * light[None, :, 2, None]).clamp_min(0.0)  # B x V x P
        return self.c0[None, :, :, None] + self.c1[None, :, :, None] * lam[:, :, None]
