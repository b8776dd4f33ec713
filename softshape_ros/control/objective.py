"""
How far a predicted (or camera) image is from the goal, as one residual vector.

A residual vector (rather than a scalar) lets the planner take Gauss-Newton steps and lets
the closed loop correct the model by what the camera saw: the residual of the real image
minus the model's at the same pressures is added to every later prediction (modifier
adaptation), so the model only has to be right about how the image *changes*.

Parts, each scaled so that 1 is "just at tolerance": the soft tip per view (per 2 px), the
soft silhouette against the goal's (mismatch over the goal's area), the image itself (for
image goals, per 0.1 RMSE), contact (touch: overlap with the object in every view where it
shows; clear: no overlap in at least one view), and a small pull toward low pressures (so
the common mode of a segment's three chambers, which bends nothing, is not spent).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from softshape_ros.control.features import (SceneContext, dilate, soft_mask_logits, soft_tips)
from softshape_ros.control.goal import Goal, GoalError

TIP_SCALE_PX = 2.0
IMAGE_SCALE = 0.1
CONTACT_OVERLAP_PX = 3.0       # robot pixels on the object's margin that count as touching


@dataclass(frozen=True)
class CostWeights:
    """Relative weights of the residual parts (each part is 1 at its tolerance)."""

    tip: float = 1.0
    silhouette: float = 3.0
    image: float = 0.5
    contact: float = 2.0
    pressure: float = 0.03
    touch_margin_px: int = 1
    clear_margin_px: int = 1


@dataclass
class Features:
    """What the objective needs from a batch of images, computed once per batch."""

    y: torch.Tensor          # B x V x C x S x S in [0, 1]
    mask: torch.Tensor       # B x V x S x S soft robot mask
    tips: torch.Tensor       # B x V x 2 soft tips (row, col)


class Objective:
    """Residuals of images toward one goal in one scene; optionally corrected and anchored."""

    def __init__(self, ctx: SceneContext, goal: Goal, weights: CostWeights = CostWeights()):
        if goal.spec.size != ctx.size or len(goal.spec.views) != ctx.views:
            raise GoalError(f'goal is for {len(goal.spec.views)} views of {goal.spec.size} px, '
                            f'the scene has {ctx.views} of {ctx.size} px')
        self.ctx, self.goal, self.w = ctx, goal, weights
        self.grids = ctx.torch_grids()
        self.threshold = ctx.silhouette.threshold
        self.target_images = None
        self.target_mask = None
        if goal.kind == 'images':
            self.target_images = torch.from_numpy(goal.target_images.astype(np.float32) / 255)
            self.target_mask = ctx.masks(goal.target_images[None])[0]
            ref = self.target_images[None]
            self.target_tip_hard = ctx.tips(goal.target_images[None])[0]
            self.target_tip = soft_tips(soft_mask_logits(ref, self.threshold), *self.grids)[0]
        elif goal.kind == 'silhouette':
            self.target_mask = goal.target_silhouette
            ref = mask_image(ctx, self.target_mask)
            self.target_tip_hard = ctx.tips(ref[None])[0]
            y = torch.from_numpy(ref.astype(np.float32) / 255)[None]
            self.target_tip = soft_tips(soft_mask_logits(y, self.threshold), *self.grids)[0]
        else:
            self.target_tip_hard = goal.target_tip_rc.copy()
            self.target_tip = torch.from_numpy(
                self.target_tip_hard + tip_bias(ctx, self.target_tip_hard)).float()
        if np.any(~np.isfinite(self.target_tip_hard)):
            raise GoalError('the goal shows no robot in some view: no tip to reach')
        self.mask_t = None
        if self.target_mask is not None:
            area = self.target_mask.reshape(ctx.views, -1).sum(1).astype(np.float32)
            if np.any(area < 4):
                raise GoalError('the goal silhouette is (nearly) empty in some view')
            self.mask_t = torch.from_numpy(self.target_mask.astype(np.float32))
            self.mask_scale = torch.from_numpy(1.0 / np.sqrt(area))[:, None, None]
        self.contact_mask = None
        if goal.contact != 'any':
            seen = ctx.has_object()
            if goal.contact == 'touch' and not seen.any():
                raise GoalError('contact "touch": the scene shows no object to touch')
            margin = weights.touch_margin_px if goal.contact == 'touch' \
                else weights.clear_margin_px
            m = dilate(ctx.object_mask, margin) & seen[:, None, None]
            self.contact_mask = torch.from_numpy(m.astype(np.float32))
            self.contact_views = torch.from_numpy(seen)
        self.correction: torch.Tensor | None = None
        self.tip_slope = None            # (u_ref, T x 6): the correction's secant, tip part
        self.anchor: torch.Tensor | None = None
        self.trust = 0.0

    # -- features and residuals --------------------------------------------------------------
    def features(self, y: torch.Tensor) -> Features:
        logits = soft_mask_logits(y, self.threshold)
        return Features(y, torch.sigmoid(logits), soft_tips(logits, *self.grids))

    def residuals(self, f: Features, u: torch.Tensor) -> torch.Tensor:
        """B x R residual vectors (their squared norm is the cost)."""
        w, b = self.w, f.y.shape[0]
        parts = [w.tip * (f.tips - self.target_tip).reshape(b, -1) / TIP_SCALE_PX
                 + self._tip_secant(u)]
        if self.mask_t is not None:
            parts.append(w.silhouette * ((f.mask - self.mask_t) * self.mask_scale)
                         .reshape(b, -1))
        if self.target_images is not None:
            n = self.target_images.numel()
            parts.append(w.image * (f.y - self.target_images).reshape(b, -1)
                         / (IMAGE_SCALE * n ** 0.5))
        parts.append(self.contact_residual(f))
        r = torch.cat(parts, 1)
        if self.correction is not None:
            r = r + self.correction
        extra = [w.pressure * u]
        if self.anchor is not None and self.trust > 0:
            extra.append(self.trust * (u - self.anchor))
        return torch.cat([r] + extra, 1)

    def contact_residual(self, f: Features) -> torch.Tensor:
        b = f.mask.shape[0]
        if self.contact_mask is None:
            return f.mask.new_zeros((b, 0))
        return self._contact_from_overlap((f.mask * self.contact_mask).sum((-1, -2)))

    def _contact_from_overlap(self, overlap: torch.Tensor) -> torch.Tensor:
        """B x V robot pixels on the object's margin -> the contact residual."""
        if self.goal.contact == 'touch':
            short = torch.relu(CONTACT_OVERLAP_PX - overlap) / CONTACT_OVERLAP_PX
            return self.w.contact * short * self.contact_views
        # Clear: separated in one view is enough (projections overlap when bodies do).
        seen = overlap[:, self.contact_views]
        b = overlap.shape[0]
        soft_min = -torch.logsumexp(-seen, dim=1, keepdim=True) if seen.shape[1] \
            else overlap.new_zeros((b, 1))
        return self.w.contact * torch.relu(soft_min) / CONTACT_OVERLAP_PX

    def _tip_secant(self, u: torch.Tensor) -> torch.Tensor:
        """Return the tip correction's change away from where it was measured (B x 2V)."""
        if self.tip_slope is None:
            return u.new_zeros((u.shape[0], 1))
        u_ref, slope = self.tip_slope
        return (u - u_ref) @ slope.T

    def bank_cost(self, bank) -> torch.Tensor:
        """
        Score every bank entry: equal to :meth:`cost`, without forming residuals.

        The silhouette and image parts are affine in the stored masks and images
        (r = a x + b), so their squared norms are a^2 |x|^2 + 2 a x.b + |b|^2: one
        matrix-vector product per part instead of N residual vectors.
        """
        w = self.w
        n, v = bank.tips.shape[:2]
        corr = self.correction[0] if self.correction is not None else None
        at = 0
        rt = w.tip * (bank.tips - self.target_tip).reshape(n, -1) / TIP_SCALE_PX \
            + self._tip_secant(bank.u)
        if corr is not None:
            rt = rt + corr[:rt.shape[1]]
        at += rt.shape[1]
        total = rt.square().sum(1)
        if self.mask_t is not None:
            p = self.mask_t[0].numel()
            a = w.silhouette * self.mask_scale.reshape(v)                   # V
            b = -a[:, None] * self.mask_t.reshape(v, p)                     # V x P
            if corr is not None:
                b = b + corr[at:at + v * p].reshape(v, p)
            at += v * p
            xb = torch.einsum('nvp,vp->nv', bank.mask, b)
            total = total + (a ** 2 * bank.mask_sq + 2 * a * xb).sum(1) + b.square().sum()
        if self.target_images is not None:
            m = self.target_images.numel()
            a = w.image / (IMAGE_SCALE * m ** 0.5)
            b = -a * self.target_images.reshape(-1)
            if corr is not None:
                b = b + corr[at:at + m]
            at += m
            total = total + a ** 2 * bank.y_sq + 2 * a * (bank.y_flat @ b) + b.square().sum()
        if self.contact_mask is not None:
            overlap = torch.einsum('nvp,vp->nv', bank.mask, self.contact_mask.reshape(v, -1))
            rc = self._contact_from_overlap(overlap)
            if corr is not None:
                rc = rc + corr[at:at + rc.shape[1]]
            total = total + rc.square().sum(1)
        extra = w.pressure * bank.u
        if self.anchor is not None and self.trust > 0:
            extra = torch.cat([extra, self.trust * (bank.u - self.anchor)], 1)
        return total + extra.square().sum(1)

    def cost(self, y: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return self.residuals(self.features(y), u).square().sum(1)

    # -- closed loop -------------------------------------------------------------------------
    def _real_residual(self, real: np.ndarray, u) -> torch.Tensor:
        """Image part of the residual of camera images (V x C x S x S uint8) at ``u``."""
        ut = torch.as_tensor(np.asarray(u, dtype=np.float32))[None]
        fr = self.features(torch.from_numpy(real.astype(np.float32) / 255)[None])
        hard = self.ctx.tips(real[None])[0]
        if np.all(np.isfinite(hard)):
            # The tip as success judges it (the hard tip), offset into the soft frame.
            fr.tips = torch.from_numpy((hard - self.target_tip_hard).astype(np.float32)
                                       )[None] + self.target_tip
        saved = self.correction, self.anchor, self.tip_slope
        self.correction = self.anchor = self.tip_slope = None
        try:
            return self.residuals(fr, ut)[:, :-6]
        finally:
            self.correction, self.anchor, self.tip_slope = saved

    def real_cost(self, real: np.ndarray, u) -> float:
        """Score what the camera saw (no model involved): the loop's merit."""
        with torch.no_grad():
            return float(self._real_residual(real, u).square().sum())

    def set_correction(self, real: np.ndarray, predicted: torch.Tensor, u,
                       keep: bool = False) -> torch.Tensor:
        """
        Correct the model by what the camera saw at the same pressures ``u``.

        ``real``: V x C x S x S uint8 camera images; ``predicted``: the model's V x C x S x S
        [0, 1] images at ``u``. The tip part uses the real image's hard tip (what success is
        judged by), so the loop drives exactly that error to zero. Returns the tip part of
        the correction; ``keep``: only return it, the objective stays as it is.
        """
        with torch.no_grad():
            r_real = self._real_residual(real, u)
            saved = self.correction, self.anchor, self.tip_slope
            self.correction = self.anchor = self.tip_slope = None
            try:
                ut = torch.as_tensor(np.asarray(u, dtype=np.float32))[None]
                r_model = self.residuals(self.features(predicted[None]), ut)[:, :-6]
            finally:
                self.correction, self.anchor, self.tip_slope = saved
        if not keep:
            self.correction = (r_real - r_model).detach()
        return (r_real - r_model)[0, :2 * self.ctx.views].detach().clone()

    def set_tip_secant(self, u_ref, slope) -> None:
        """Let the tip correction vary linearly with u around ``u_ref`` (a secant, T x 6)."""
        self.tip_slope = None if slope is None else (
            torch.as_tensor(np.asarray(u_ref, dtype=np.float32))[None],
            torch.as_tensor(np.asarray(slope, dtype=np.float32)))

    def anchor_at(self, u, trust: float) -> None:
        """Keep re-plans near ``u`` (the last command): the correction is local."""
        self.anchor = torch.as_tensor(np.asarray(u, dtype=np.float32))[None]
        self.trust = float(trust)

    def describe(self, images: np.ndarray) -> dict:
        """Hard tip error per view and IoU of V x C x S x S uint8 images against the goal."""
        return self.ctx.score(images, self.target_mask, self.target_tip_hard)


def tip_bias(ctx: SceneContext, tips_hard: np.ndarray) -> np.ndarray:
    """
    Where the soft tip sits relative to the hard one (V x 2), for goals given as pixels.

    Measured on the rest image (the soft tip lies a little inside the far end), turned to
    point from the goal tip toward the base: the robot's end is seen along its axis.
    """
    y = torch.from_numpy(ctx.initial.astype(np.float32) / 255)[None]
    soft = soft_tips(soft_mask_logits(y, ctx.silhouette.threshold), *ctx.torch_grids())[0]
    hard = ctx.tips(ctx.initial[None])[0]
    size = np.linalg.norm(soft.numpy() - hard, axis=-1, keepdims=True)
    to_base = ctx.silhouette.base_rc - tips_hard
    n = np.linalg.norm(to_base, axis=-1, keepdims=True)
    return np.where(n > 0, size * to_base / np.maximum(n, 1e-9), 0.0)


def mask_image(ctx: SceneContext, mask: np.ndarray) -> np.ndarray:
    """Draw a silhouette goal as an image in the scene's shades (robot over the rest image)."""
    lum = ctx.initial.astype(np.float32)
    robot = float(np.median(lum[:, :1][ctx.masks(ctx.initial[None])[0][:, None]]))
    out = lum.copy()
    bg = float(np.median(lum))
    for v in range(len(mask)):
        rest = ctx.masks(ctx.initial[None])[0][v]
        for c in range(out.shape[1]):
            ch = out[v, c]
            ch[rest & ~mask[v]] = bg          # where the robot was and is no more
            ch[mask[v]] = robot
            out[v, c] = cv2.GaussianBlur(ch, (3, 3), 0.6)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)
