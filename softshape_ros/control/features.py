"""
What the controller measures in an image: the robot's silhouette, its tip, the object.

Two versions of each, from the same scene context: hard ones in numpy (the success test,
as ``softshape evaluate`` scores models: :class:`~softshape_ros.model.metrics.RobotSilhouette`)
and soft, differentiable ones in torch (what the planner descends on). The soft mask is a
sigmoid around the robot's dark threshold; the soft tip is the mask-weighted softmax of the
distance from the robot's base, so it follows the hard tip (the silhouette pixel furthest
from the base) but moves smoothly with the pressures.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from softshape_ros.model.metrics import RobotSilhouette, iou, luminance, otsu_thresholds

#: Gray levels over which the soft robot mask goes from 0.27 to 0.73 (sigmoid scale).
MASK_SOFTNESS = 8.0
#: Pixels of distance from the base over which the soft tip's weights fall by e.
TIP_SOFTNESS_PX = 1.0
#: How strongly the soft tip ignores pixels that are not robot (see :func:`soft_tips`).
TIP_MASK_WEIGHT = 20.0
#: A view shows the object if at least this many pixels of its rest image are object.
MIN_OBJECT_PX = 12


class SceneContextError(ValueError):
    """The scene's initial images cannot serve as a reference (no robot, wrong shape)."""


@dataclass
class SceneContext:
    """Per scene: the robot threshold and base, object masks, grids (from rest images)."""

    initial: np.ndarray             # V x C x S x S uint8
    silhouette: RobotSilhouette
    object_mask: np.ndarray         # V x S x S bool: object pixels visible at rest

    @classmethod
    def from_initial(cls, initial: np.ndarray) -> 'SceneContext':
        a = np.asarray(initial)
        bad = a.dtype != np.uint8 or a.ndim != 4
        if bad or a.shape[1] not in (1, 3) or a.shape[-1] != a.shape[-2]:
            raise SceneContextError(
                f'initial images must be V x C x S x S uint8, got {a.shape} {a.dtype}')
        sil = RobotSilhouette.fit(a[None])
        rest = sil.mask(a[None])[0]
        empty = [i for i in range(len(rest)) if rest[i].sum() < 4]
        if empty:
            raise SceneContextError(
                f'no robot in the initial image of view(s) {empty} (threshold '
                f'{sil.threshold:.0f}): cannot plan in this scene')
        return cls(a.copy(), sil, object_masks(a, sil.threshold))

    @property
    def size(self) -> int:
        return int(self.initial.shape[-1])

    @property
    def views(self) -> int:
        return int(self.initial.shape[0])

    def has_object(self) -> np.ndarray:
        """Per view: whether the rest image shows the object at all."""
        return self.object_mask.reshape(self.views, -1).sum(1) >= MIN_OBJECT_PX

    # -- hard (numpy): the success test ------------------------------------------------------
    def masks(self, images: np.ndarray) -> np.ndarray:
        """N x V x C x S x S uint8 -> N x V x S x S robot silhouettes."""
        return self.silhouette.mask(images)

    def tips(self, images: np.ndarray) -> np.ndarray:
        """Return the far-end tip of N x V x C x S x S images: N x V x 2 (row, col), NaN: none."""
        return self.silhouette.tips(images)

    def score(self, images: np.ndarray, target_mask=None, target_tip=None) -> dict:
        """Hard tip error per view (px) and pooled silhouette IoU of one V x C x S x S set."""
        out = {}
        if target_tip is not None:
            tip = self.tips(images[None])[0]
            err = np.linalg.norm(tip - target_tip, axis=-1)
            out['tip_error_px'] = [float(e) if np.isfinite(e) else float('inf') for e in err]
        if target_mask is not None:
            m = self.masks(images[None])[0]
            out['iou'] = iou(m, target_mask)
            out['iou_views'] = [iou(m[v], target_mask[v]) for v in range(len(m))]
        return out

    # -- soft (torch): what the planner descends on --------------------------------------------
    def torch_grids(self, device=None):
        """Return (rows, cols, distance from base) tensors, V x S x S float32."""
        s = self.size
        rr, cc = torch.meshgrid(torch.arange(s, dtype=torch.float32),
                                torch.arange(s, dtype=torch.float32), indexing='ij')
        base = torch.as_tensor(self.silhouette.base_rc, dtype=torch.float32)
        d = torch.sqrt((rr[None] - base[:, 0, None, None]) ** 2
                       + (cc[None] - base[:, 1, None, None]) ** 2)
        return rr.expand(self.views, s, s), cc.expand(self.views, s, s), d


def object_masks(initial: np.ndarray, robot_threshold: float) -> np.ndarray:
    """
    V x S x S: pixels of the rest images in the object's shade (between robot and background).

    The mid class of a three-level Otsu split; opened by one pixel so that the blended edge
    of the robot against the background is not taken for the object.
    """
    lum = luminance(initial[None])[0]
    _, t2 = otsu_thresholds(np.rint(lum))
    light = lum[lum > t2]
    mid = lum[(lum > robot_threshold) & (lum <= t2)]
    # Midway between the object's and the background's typical shade, like the robot's.
    upper = 0.5 * (np.median(mid) + np.median(light)) if len(mid) and len(light) else t2
    out = np.zeros(lum.shape, bool)
    kernel = np.ones((3, 3), np.uint8)
    for v in range(len(lum)):
        m = ((lum[v] > robot_threshold) & (lum[v] <= upper)).astype(np.uint8)
        out[v] = cv2.morphologyEx(m, cv2.MORPH_OPEN, kernel) > 0
    return out


def dilate(masks: np.ndarray, px: int) -> np.ndarray:
    """Grow V x S x S boolean masks by ``px`` pixels (8-neighbourhood)."""
    if px <= 0:
        return masks.copy()
    k = np.ones((2 * px + 1, 2 * px + 1), np.uint8)
    return np.stack([cv2.dilate(m.astype(np.uint8), k) > 0 for m in masks])


def soft_luminance(y: torch.Tensor) -> torch.Tensor:
    """B x V x C x S x S images in [0, 1] -> B x V x S x S brightness on the 0-255 scale."""
    if y.shape[2] == 1:
        return y[:, :, 0] * 255.0
    w = torch.tensor([0.299, 0.587, 0.114], dtype=y.dtype, device=y.device)
    return torch.einsum('bvchw,c->bvhw', y, w) * 255.0


def soft_mask_logits(y: torch.Tensor, threshold: float) -> torch.Tensor:
    """Logits of the soft robot mask (B x V x S x S); sigmoid gives the mask."""
    return (threshold - soft_luminance(y)) / MASK_SOFTNESS


def soft_tips(logits: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor,
              dist: torch.Tensor) -> torch.Tensor:
    """B x V x S x S mask logits -> B x V x 2 soft tips (row, col)."""
    b, v, s, _ = logits.shape
    # The mask's log-weight is scaled up so that no background or object pixel can outweigh
    # the robot by being further from the base (distances span ~90 px, log-weights ~10).
    score = TIP_MASK_WEIGHT * torch.nn.functional.logsigmoid(logits) \
        + dist[None] / TIP_SOFTNESS_PX
    w = torch.softmax(score.reshape(b, v, -1), dim=-1)
    r = (w * rows.reshape(1, v, -1)).sum(-1)
    c = (w * cols.reshape(1, v, -1)).sum(-1)
    return torch.stack([r, c], dim=-1)
