"""
How good a predicted image is, in the paper's terms and in the robot's.

All images are N x V x C x S x S uint8 (0-255). The robot silhouette is the darkest of the
three intensity classes of the rest images (robot dark, object mid, background light: the
simulator's palette and the rig's thresholded images, paper IV-C); its threshold is found
once per dataset by a two-threshold Otsu split of the initial images' luminance.
"""

from __future__ import annotations

import numpy as np

YELLOW_THRESHOLD = 10     # paper III-B: off by more than 10 in all channels
CHANGE_THRESHOLD = 10     # a pixel "changed" if the target differs from the initial by more


def luminance(images: np.ndarray) -> np.ndarray:
    """Convert N x V x C x S x S images to N x V x S x S float brightness; gray as is."""
    x = images.astype(np.float32)
    if x.shape[2] == 1:
        return x[:, :, 0]
    return 0.299 * x[:, :, 0] + 0.587 * x[:, :, 1] + 0.114 * x[:, :, 2]


def rmse(pred, target, mask=None) -> float:
    """Root mean square error on the 0-255 scale (optionally over ``mask`` pixels only)."""
    d = (pred.astype(np.float64) - target.astype(np.float64)) ** 2
    if mask is not None:
        m = np.broadcast_to(mask, d.shape)
        return float(np.sqrt(d[m].mean())) if m.any() else float('nan')
    return float(np.sqrt(d.mean()))


def changed_mask(initial, target) -> np.ndarray:
    """N x V x 1 x S x S: pixels where the ground truth moved away from the initial image."""
    d = np.abs(initial.astype(np.int16) - target.astype(np.int16))
    return (d > CHANGE_THRESHOLD).any(axis=2, keepdims=True)


def yellow_mask(pred, target) -> np.ndarray:
    """N x V x S x S: the paper's error mask (all channels off by more than 10)."""
    d = np.abs(pred.astype(np.int16) - target.astype(np.int16))
    return (d > YELLOW_THRESHOLD).all(axis=2)


def otsu_thresholds(values: np.ndarray) -> tuple[int, int]:
    """Two thresholds splitting a 0-255 histogram into three classes (max between-variance)."""
    hist = np.bincount(np.clip(values.ravel(), 0, 255).astype(np.int64), minlength=256)
    p = hist / max(hist.sum(), 1)
    levels = np.arange(256)
    w = np.cumsum(p)
    mu = np.cumsum(p * levels)
    total = mu[-1]
    best, arg = -1.0, (85, 170)
    for t1 in range(1, 254):
        w0, m0 = w[t1], mu[t1]
        if w0 <= 0:
            continue
        t2 = np.arange(t1 + 1, 255)
        w1 = w[t2] - w0
        w2 = 1 - w[t2]
        m1 = mu[t2] - m0
        m2 = total - mu[t2]
        with np.errstate(divide='ignore', invalid='ignore'):
            var = m0 ** 2 / w0 + np.where(w1 > 0, m1 ** 2 / w1, 0) + \
                np.where(w2 > 0, m2 ** 2 / w2, 0)
        k = int(np.nanargmax(var))
        if var[k] > best:
            best, arg = float(var[k]), (t1, int(t2[k]))
    return arg


class RobotSilhouette:
    """Dark-class segmentation of the robot and its tip (the pixel furthest from the base)."""

    def __init__(self, threshold: float, base_rc: np.ndarray):
        self.threshold = float(threshold)
        self.base_rc = np.asarray(base_rc, dtype=np.float64)    # V x 2 (row, col)

    @classmethod
    def fit(cls, initial: np.ndarray) -> 'RobotSilhouette':
        """Find the dark threshold and, per view, the robot's base from rest images."""
        lum = luminance(initial)
        sample = np.rint(lum[:: max(1, len(lum) // 200)])
        t1, t2 = otsu_thresholds(sample)
        dark, mid = sample[sample <= t1], sample[(sample > t1) & (sample <= t2)]
        # Midway between the robot's and the object's typical shade: robust to blur.
        thr = 0.5 * (np.median(dark) + np.median(mid)) if len(dark) and len(mid) else t1
        rest = (lum <= thr).mean(axis=0) > 0.5          # V x S x S: robot at rest
        base = []
        for v in range(rest.shape[0]):
            rows, cols = np.nonzero(rest[v])
            if len(rows) == 0:
                base.append((0.0, rest.shape[2] / 2))
                continue
            top = rows <= rows.min() + 1
            base.append((float(rows[top].mean()), float(cols[top].mean())))
        return cls(thr, np.array(base))

    def mask(self, images) -> np.ndarray:
        """N x V x S x S boolean robot silhouettes."""
        return luminance(images) <= self.threshold

    def tips(self, images) -> np.ndarray:
        """N x V x 2 tip (row, col); NaN where no robot pixel is seen."""
        m = self.mask(images)
        n, v, s, _ = m.shape
        rr, cc = np.mgrid[0:s, 0:s]
        out = np.full((n, v, 2), np.nan)
        for j in range(v):
            d = (rr - self.base_rc[j, 0]) ** 2 + (cc - self.base_rc[j, 1]) ** 2
            dm = np.where(m[:, j], d[None], -1.0).reshape(n, -1)
            k = dm.argmax(axis=1)
            ok = dm[np.arange(n), k] >= 0
            out[ok, j, 0], out[ok, j, 1] = rr.ravel()[k[ok]], cc.ravel()[k[ok]]
        return out


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union pooled over all images (1.0 if both are empty)."""
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def evaluate_arrays(initial, target, pred, silhouette: RobotSilhouette) -> dict:
    """Every metric of ``pred`` beside the copy-the-initial-image baseline."""
    changed = changed_mask(initial, target)
    tgt_sil = silhouette.mask(target)
    tgt_tip = silhouette.tips(target)
    out = {'samples': int(len(target)), 'changed_fraction': float(changed.mean())}
    for name, p in (('model', pred), ('copy', initial)):
        tip = silhouette.tips(p)
        err = np.linalg.norm(tip - tgt_tip, axis=-1)
        ok = np.isfinite(err)
        out[name] = {
            'rmse': rmse(p, target),
            'rmse_changed': rmse(p, target, changed),
            'yellow_fraction': float(yellow_mask(p, target).mean()),
            'silhouette_iou': iou(silhouette.mask(p), tgt_sil),
            'tip_error_px': float(err[ok].mean()) if ok.any() else float('nan'),
            'tip_missing': int((~ok).sum()),
        }
    return out
