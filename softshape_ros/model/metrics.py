"""
How good a predicted image is, in the paper's terms, the video-prediction field's and the robot's.

All images are N x V x C x S x S uint8 (0-255). The scene has three intensity classes (robot
dark, object mid, background light: the simulator's palette and the rig's thresholded images,
paper IV-C); two thresholds split them, found once per dataset by a two-threshold Otsu split
of the rest images' luminance (:class:`RobotSilhouette`). The object's silhouette is the
object class of the rest image, opened by a 3x3 square so that the robot's anti-aliased rim
(one pixel of mid gray between robot and background) is not taken for an object; the object
does not move, so the rest image shows it everywhere except behind the resting robot.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

YELLOW_THRESHOLD = 10     # paper III-B: off by more than 10 in all channels
CHANGE_THRESHOLD = 10     # a pixel "changed" if the target differs from the initial by more
SSIM_WINDOW, SSIM_SIGMA = 11, 1.5           # Wang et al. 2004, the standard Gaussian window
SSIM_K1, SSIM_K2, PEAK = 0.01, 0.03, 255.0
PSNR_MSE_FLOOR = 1e-2     # identical images: PSNR capped at 10 log10(255^2 / 1e-2) = 68 dB


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


def psnr(pred, target) -> float:
    """
    Return the peak signal-to-noise ratio in dB, the video-prediction convention.

    PSNR of each image (sample and view, all channels) from its own MSE, then the mean over
    images; an exact image is capped by :data:`PSNR_MSE_FLOOR`.
    """
    d = (pred.astype(np.float64) - target.astype(np.float64)) ** 2
    mse = d.reshape(d.shape[0] * d.shape[1], -1).mean(axis=1)
    return float(np.mean(10 * np.log10(PEAK ** 2 / np.maximum(mse, PSNR_MSE_FLOOR))))


def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    """Return the normalised 1-D Gaussian taps of the SSIM window."""
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2
    g = np.exp(-x ** 2 / (2 * sigma ** 2))
    return g / g.sum()


def _filter_valid(x: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Separable 'valid' filtering of the last two axes of ``x`` with taps ``g``."""
    k = len(g)
    rows = sum(g[i] * x[..., i:x.shape[-2] - k + 1 + i, :] for i in range(k))
    return sum(g[i] * rows[..., i:rows.shape[-1] - k + 1 + i] for i in range(k))


def ssim_map(pred, target) -> np.ndarray:
    """
    Return the SSIM map of each image channel (Wang et al. 2004), N x V x C x S-10 x S-10.

    The standard setting: 11x11 Gaussian window (sigma 1.5), K1 = 0.01, K2 = 0.03, dynamic
    range 255, local statistics weighted by the window ('valid' positions only, no padding).
    """
    x, y = pred.astype(np.float64), target.astype(np.float64)
    g = gaussian_window()
    c1, c2 = (SSIM_K1 * PEAK) ** 2, (SSIM_K2 * PEAK) ** 2
    mx, my = _filter_valid(x, g), _filter_valid(y, g)
    sxx = _filter_valid(x * x, g) - mx * mx
    syy = _filter_valid(y * y, g) - my * my
    sxy = _filter_valid(x * y, g) - mx * my
    return ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))


def ssim(pred, target, chunk: int = 128) -> float:
    """Mean SSIM over every image, channel and window position (the convention of the field)."""
    if len(pred) == 0:
        return float('nan')
    total = sum(float(ssim_map(pred[i:i + chunk], target[i:i + chunk]).sum())
                for i in range(0, len(pred), chunk))
    per_image = ssim_map(pred[:1], target[:1]).size
    return total / (per_image * len(pred))


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


#: The tip is the mean of the robot's pixels this close to its largest distance from the base.
TIP_BAND_PX = 1.0


def far_end_tips(masks: np.ndarray, base_rc: np.ndarray, band_px: float = TIP_BAND_PX):
    """
    N x V x S x S silhouettes -> N x V x 2 tips (row, col): the mean of the far-end pixels.

    The far end is every silhouette pixel within ``band_px`` of the largest distance from
    the base. The single furthest pixel is ill-posed on a rounded end: its distance falls
    only quadratically along the cap, so pixel rounding (or one anti-aliased pixel more
    where an object's edge blends darker than the background) moves it by several pixels
    between two nearly equal shapes. The band's mean sits on the end's axis, to sub-pixel.
    NaN where a silhouette is empty.
    """
    n, v, s, _ = masks.shape
    rr, cc = np.mgrid[0:s, 0:s].astype(np.float64)
    out = np.full((n, v, 2), np.nan)
    for j in range(v):
        d = np.hypot(rr - base_rc[j, 0], cc - base_rc[j, 1])
        dm = np.where(masks[:, j], d[None], -np.inf).reshape(n, -1)
        far = dm.max(axis=1)
        ok = np.isfinite(far)
        band = dm >= (far - band_px)[:, None]
        count = np.maximum(band.sum(axis=1), 1)
        out[ok, j, 0] = (band @ rr.ravel())[ok] / count[ok]
        out[ok, j, 1] = (band @ cc.ravel())[ok] / count[ok]
    return out


class RobotSilhouette:
    """
    Three-class segmentation: the robot (dark) and its tip, the object (mid), the background.

    ``threshold`` splits robot from object, ``object_threshold`` object from background;
    the tip is the robot pixel furthest from the robot's base.
    """

    def __init__(self, threshold: float, base_rc: np.ndarray,
                 object_threshold: float | None = None):
        self.threshold = float(threshold)
        self.base_rc = np.asarray(base_rc, dtype=np.float64)    # V x 2 (row, col)
        self.object_threshold = None if object_threshold is None else float(object_threshold)

    @classmethod
    def fit(cls, initial: np.ndarray) -> 'RobotSilhouette':
        """Find both thresholds and, per view, the robot's base from rest images."""
        lum = luminance(initial)
        sample = np.rint(lum[:: max(1, len(lum) // 200)])
        t1, t2 = otsu_thresholds(sample)
        dark, mid = sample[sample <= t1], sample[(sample > t1) & (sample <= t2)]
        light = sample[sample > t2]
        # Robot | object midway between their typical shades (robust to blur and shading);
        # object | background nearer the flat background, as objects' lit sides are light.
        thr = 0.5 * (np.median(dark) + np.median(mid)) if len(dark) and len(mid) else t1
        obj = 0.25 * np.median(mid) + 0.75 * np.median(light) if len(mid) and len(light) \
            else t2
        rest = (lum <= thr).mean(axis=0) > 0.5          # V x S x S: robot at rest
        base = []
        for v in range(rest.shape[0]):
            rows, cols = np.nonzero(rest[v])
            if len(rows) == 0:
                base.append((0.0, rest.shape[2] / 2))
                continue
            top = rows <= rows.min() + 1
            base.append((float(rows[top].mean()), float(cols[top].mean())))
        return cls(thr, np.array(base), obj)

    def views(self, n: int) -> 'RobotSilhouette':
        """Keep the first ``n`` views' bases (mono = the main view)."""
        return RobotSilhouette(self.threshold, self.base_rc[:n], self.object_threshold)

    def mask(self, images) -> np.ndarray:
        """N x V x S x S boolean robot silhouettes."""
        return luminance(images) <= self.threshold

    def object_mask(self, initial) -> np.ndarray:
        """N x V x S x S boolean object silhouettes from rest images (see the module notes)."""
        if self.object_threshold is None:
            raise ValueError('this segmentation has no object threshold (fit it on rest images)')
        lum = luminance(initial)
        mid = (lum > self.threshold) & (lum <= self.object_threshold)
        return ndimage.binary_opening(mid, structure=np.ones((1, 1, 3, 3), bool))

    def tips(self, images) -> np.ndarray:
        """N x V x 2 tip (row, col) of the silhouettes (:func:`far_end_tips`); NaN: none."""
        return far_end_tips(self.mask(images), self.base_rc)

    def to_json(self) -> dict:
        """Return the segmentation as JSON-able numbers (stored in checkpoints)."""
        return {'threshold': self.threshold, 'object_threshold': self.object_threshold,
                'base_rc': self.base_rc.tolist()}

    @classmethod
    def from_json(cls, d: dict) -> 'RobotSilhouette':
        """Rebuild a segmentation written by :meth:`to_json`."""
        return cls(d['threshold'], np.asarray(d['base_rc']), d.get('object_threshold'))


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union pooled over all images (1.0 if both are empty)."""
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def intrusion(pred_robot, true_robot, object_sil) -> float:
    """
    Return the share of the object's pixels that the prediction paints as robot wrongly.

    Predicted robot pixels inside the object's silhouette where the true robot is not (the
    robot drawn through the object), over all the object's pixels (pooled; 0.0 if no object).
    """
    n_obj = object_sil.sum()
    if not n_obj:
        return 0.0
    return float((pred_robot & object_sil & ~true_robot).sum() / n_obj)


def image_metrics(pred, target, changed, tgt_sil, tgt_tip, obj_sil, silhouette) -> dict:
    """Every metric of one prediction set against the ground truth (see evaluate_arrays)."""
    sil = silhouette.mask(pred)
    err = np.linalg.norm(silhouette.tips(pred) - tgt_tip, axis=-1)
    ok = np.isfinite(err)
    out = {
        'rmse': rmse(pred, target),
        'rmse_changed': rmse(pred, target, changed),
        'yellow_fraction': float(yellow_mask(pred, target).mean()),
        'ssim': ssim(pred, target),
        'psnr_db': psnr(pred, target),
        'silhouette_iou': iou(sil, tgt_sil),
        'tip_error_px': float(err[ok].mean()) if ok.any() else float('nan'),
        'tip_error_median_px': float(np.median(err[ok])) if ok.any() else float('nan'),
        'tip_missing': int((~ok).sum()),
    }
    if obj_sil is not None:
        out['intrusion'] = intrusion(sil, tgt_sil, obj_sil)
    return out


def evaluate_arrays(initial, target, pred, silhouette: RobotSilhouette,
                    touching=None, no_split_why: str = 'no contact record') -> dict:
    """
    Every metric of ``pred`` beside the copy-the-initial-image baseline.

    With ``touching`` (N bool: the sample's robot touches the object), the same metrics
    again over the touching and the free samples (``touching`` / ``free`` sections, each
    with its own ``model`` and ``copy``); without it, ``split`` says why there is none
    (``no_split_why``).
    """
    initial, target, pred = (np.asarray(a) for a in (initial, target, pred))
    out = _evaluate_set(initial, target, pred, silhouette)
    if touching is None:
        out['split'] = f'none: {no_split_why}'
        return out
    touching = np.asarray(touching, dtype=bool)
    if touching.shape != (len(target),):
        raise ValueError(f'touching must be {len(target)} flags, got shape {touching.shape}')
    out['split'] = 'touching / free from the dataset contact record'
    out['touching_share'] = float(touching.mean()) if len(touching) else float('nan')
    for name, rows in (('touching', touching), ('free', ~touching)):
        out[name] = (_evaluate_set(initial[rows], target[rows], pred[rows], silhouette)
                     if rows.any() else {'samples': 0})
    return out


def _evaluate_set(initial, target, pred, silhouette) -> dict:
    changed = changed_mask(initial, target)
    tgt_sil = silhouette.mask(target)
    tgt_tip = silhouette.tips(target)
    obj_sil = silhouette.object_mask(initial) if silhouette.object_threshold is not None \
        else None
    out = {'samples': int(len(target)), 'changed_fraction': float(changed.mean())}
    if obj_sil is not None:
        out['object_fraction'] = float(obj_sil.mean())
    for name, p in (('model', pred), ('copy', initial)):
        out[name] = image_metrics(p, target, changed, tgt_sil, tgt_tip, obj_sil, silhouette)
    return out
