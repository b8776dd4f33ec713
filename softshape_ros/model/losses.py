"""
Training losses: the paper's MSE, and a silhouette term that does not reward blur.

Under MSE, a network unsure where an edge goes paints the average of the two shades, a grey
halo that is off everywhere (the paper itself suspected its loss, III-C). The silhouette
term scores the robot mask that the evaluation scores: the predicted image's luminance
through a steep sigmoid around the robot threshold (the dataset's dark-class split,
:class:`~softshape_ros.model.metrics.RobotSilhouette`), binary cross-entropy against the
true robot mask (the Bayes decision per pixel is the one IoU counts). It punishes a ghost
of the resting robot, a blurred tip and robot drawn through the object where MSE sees a
few grey levels. L1 is won by picking one side, but from the copy start it is a trap:
where a pixel changes in few samples the median outcome is "unchanged", and L1 (or Huber,
kept for the design study) drove every ReLU of ``ours`` dead within 20 steps, leaving the
copy baseline. So ``ours`` keeps MSE and adds the silhouette term.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

LOSSES = ('mse', 'mse_silhouette', 'huber', 'huber_silhouette', 'tube', 'keypoints', 'scene')
HUBER_EDGE = 0.02       # [0, 1] units: quadratic below, linear above (5/255)
SOFT_EDGE = 0.02       # sigmoid temperature of the soft robot mask, [0, 1] units (5/255)
LUMA = (0.299, 0.587, 0.114)


def luminance(x: torch.Tensor, channels: int) -> torch.Tensor:
    """B x (V*C) x S x S in [0, 1] -> B x V x S x S brightness (gray as is)."""
    if channels == 1:
        return x
    b, vc, h, w = x.shape
    v = x.view(b, vc // 3, 3, h, w)
    return LUMA[0] * v[:, :, 0] + LUMA[1] * v[:, :, 1] + LUMA[2] * v[:, :, 2]


class ImageLoss:
    """
    One training objective: ``kind`` in LOSSES, evaluated as a mean over the batch's pixels.

    ``robot_threshold`` (in [0, 1]) is needed by ``huber_silhouette``; ``weight`` scales its
    silhouette term against the Huber term.
    """

    def __init__(self, kind: str, channels: int, robot_threshold: float | None = None,
                 weight: float = 0.05):
        if kind not in LOSSES:
            raise ValueError(f'unknown loss {kind!r} (choose from {", ".join(LOSSES)})')
        if kind.endswith('_silhouette') and robot_threshold is None:
            raise ValueError('the silhouette loss needs the robot threshold')
        self.kind, self.channels = kind, channels
        self.threshold, self.weight = robot_threshold, float(weight)

    def __call__(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        if self.kind.startswith('mse'):
            loss = F.mse_loss(pred, target)
        else:
            loss = F.smooth_l1_loss(pred, target, beta=HUBER_EDGE) / HUBER_EDGE
        if self.kind.endswith('_silhouette'):
            logit = (self.threshold - luminance(pred, self.channels)) / SOFT_EDGE
            robot = (luminance(target, self.channels) <= self.threshold).to(pred.dtype)
            loss = loss + self.weight * F.binary_cross_entropy_with_logits(logit, robot)
        return loss


@dataclass(frozen=True)
class TubeWeights:
    """Weights of the tube model's loss terms (keypoints in px, images in [0, 1] units)."""

    keypoints: float = 1.0      # L1 of x, y, radius (and depth x ``depth``) vs the record
    depth: float = 0.1
    free: float = 0.5           # L1 of the free-shape head on samples that touch nothing
    scene: float = 1.0          # squared error of the scene description (in spreads)
    image: float = 20.0         # L1 of the composite from the predicted keypoints
    teacher: float = 20.0       # ... and from the true ones (background, visibility, shade)
    background: float = 20.0    # L1 of the background where the true robot is not
    visibility: float = 1.0     # BCE of the visibility inside the true tube: is it dark?
    objects: float = 1.0        # depth_test: BCE of where the object is + 0.1 x its depth


#: Depth error (px) below which the object's depth term is quadratic (smooth L1).
OBJECT_DEPTH_EDGE_PX = 1.0
#: The depth term's weight per px, per pixel of the image (not per pixel of the object).
OBJECT_DEPTH_WEIGHT = 0.1


def object_loss(occupancy, depth, target) -> torch.Tensor:
    """
    Return the object term: BCE of the occupancy logits + 0.1 x smooth L1 of the depth (px).

    ``target`` B x V x S x S: the object's depth per pixel (inf: no object there,
    :func:`~softshape_ros.model.data.object_depths`); the depth is scored where it is hit.
    """
    hit = torch.isfinite(target)
    loss = F.binary_cross_entropy_with_logits(occupancy, hit.to(occupancy.dtype))
    if bool(hit.any()):
        err = F.smooth_l1_loss(depth[hit], target[hit], beta=OBJECT_DEPTH_EDGE_PX,
                               reduction='sum') / hit.numel()
        loss = loss + OBJECT_DEPTH_WEIGHT * err
    return loss


class TubeLoss:
    """
    The tube model's objective; ``__call__(model, x, p, t, truth, free, scene) -> (loss, image)``.

    ``truth``: B x V x K x 4 keypoints of the shape record, or None (recorded bags: the image
    term alone); ``free``: B bool, the samples touching nothing (None: unknown); ``scene``:
    B x 17 :func:`~softshape_ros.model.data.scene_targets` of the placements (None: unknown).
    ``keypoints_only``: the keypoint terms alone, nothing drawn (a fast first phase; the
    image is then None); ``x`` may then be B x code scene codes instead of images (the
    encoder frozen, each placement encoded once: ``TrainConfig.freeze_scene``).
    ``scene_only``: the scene term alone (the encoder learns to read the placement before
    anything reads its code; nothing drawn). ``objects``: B x V x S x S object depths
    (:func:`object_loss`; None: unknown) for a ``depth_test`` model's ObjectNet.
    ``threshold``: the robot's luminance threshold ([0, 1] units; None: no visibility
    term): inside the true tube the target shows the robot where it is darker, the object
    where the object is in front.
    """

    def __init__(self, weights: TubeWeights = TubeWeights(), keypoints_only: bool = False,
                 threshold: float | None = None, channels: int = 1, scene_only: bool = False):
        if keypoints_only and scene_only:
            raise ValueError('a tube objective is keypoints_only or scene_only, not both')
        self.w, self.keypoints_only, self.scene_only = weights, keypoints_only, scene_only
        self.threshold, self.channels = threshold, channels

    def _keypoints(self, kp, free_kp, truth, free, dtype):
        w = self.w
        ch = torch.tensor([1.0, 1.0, 1.0, w.depth], dtype=dtype)
        loss = w.keypoints * ((kp - truth).abs() * ch).mean()
        if free is not None and bool(free.any()):
            loss = loss + w.free * ((free_kp[free] - truth[free]).abs() * ch).mean()
        return loss

    def _scene(self, model, described, scene):
        """
        Tell the scene encoder what the placement is, where it is known.

        Squared error in units of the training placements' spread: under L1 the encoder
        settled on the median placement for every scene and stayed there.
        """
        if scene is None or described is None or not self.w.scene:
            return 0.0
        net = getattr(model, 'module', model)                # DDP wraps the network
        spread = net.keypoints.scene.spread
        return self.w.scene * (((described - scene) / spread) ** 2).mean()

    def __call__(self, model, x, p, t, truth=None, free=None, scene=None, objects=None):
        w = self.w
        if self.scene_only:
            if scene is None:
                raise ValueError('the scene loss needs the placements recorded (simulated '
                                 'data, or bags whose session YAML describes the objects)')
            return self._scene(model, model(x, p, parts='keypoints')[2], scene), None
        if self.keypoints_only:
            if truth is None:
                raise ValueError('keypoint training needs a dataset with a shape record')
            # B x code: codes of a frozen encoder (no scene term); else the rest images.
            kp, free_kp, described = model(x, p, parts='codes' if x.dim() == 2 else 'keypoints')
            return (self._keypoints(kp, free_kp, truth, free, x.dtype)
                    + self._scene(model, described, scene)), None
        out = model(x, p, truth, parts=True)
        loss = w.image * F.l1_loss(out.image, t) + self._scene(model, out.scene, scene)
        if objects is not None and out.occupancy is not None and w.objects:
            loss = loss + w.objects * object_loss(out.occupancy, out.object_depth, objects)
        if truth is None:
            return loss, out.image
        loss = loss + self._keypoints(out.keypoints, out.free_keypoints, truth, free, x.dtype)
        loss = loss + w.teacher * F.l1_loss(out.teacher, t)
        # Where the true robot is not (one pixel clear of it) the target is the background.
        b, v, s, _ = out.teacher_coverage.shape
        clear = F.max_pool2d(out.teacher_coverage, 3, 1, 1) == 0            # B x V x S x S
        m = clear[:, :, None].expand(b, v, t.shape[1] // v, s, s).reshape(t.shape)
        err = (out.background - t).abs()
        loss = loss + w.background * (err * m).sum() / m.sum().clamp_min(1)
        if self.threshold is not None and w.visibility:
            inside = (out.teacher_coverage >= 1.0).to(t.dtype)                 # B x V x S x S
            robot = (luminance(t, self.channels) <= self.threshold).to(t.dtype)
            bce = F.binary_cross_entropy_with_logits(out.teacher_visibility, robot,
                                                     reduction='none')
            loss = loss + w.visibility * (bce * inside).sum() / inside.sum().clamp_min(1)
        return loss, out.image


class PixelLoss:
    """An :class:`ImageLoss` as an objective: ``__call__(model, x, p, t, ...) -> (loss, y)``."""

    def __init__(self, loss: ImageLoss):
        self.loss = loss

    def __call__(self, model, x, p, t, truth=None, free=None, scene=None, objects=None):
        y = model(x, p)
        return self.loss(y, t), y
