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

import torch
import torch.nn.functional as F

LOSSES = ('mse', 'mse_silhouette', 'huber', 'huber_silhouette')
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
