"""
Camera frame -> network input, exactly as the paper (IV-B): crop, gray, resize 64x64.

The dataset builder, the simulator's dataset writer and the inference node all call
:func:`preprocess`, so a model never sees images prepared two different ways.
"""

from __future__ import annotations

import cv2
import numpy as np


class ImageError(ValueError):
    """A frame cannot be preprocessed (wrong shape, dtype or crop)."""


def to_gray(image: np.ndarray) -> np.ndarray:
    """H x W x 3 RGB (or H x W) uint8 -> H x W uint8 luminance."""
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    raise ImageError(f'expected H x W or H x W x 3 image, got shape {image.shape}')


def preprocess(image: np.ndarray, crop_px, size: int = 64, gray: bool = True) -> np.ndarray:
    """
    Crop ``[x, y, w, h]`` (full-resolution pixels), convert, area-resize.

    Returns C x size x size uint8 (C = 1 for gray, 3 for RGB). For a frame of another
    resolution than the configured one, pass the crop through :func:`scale_crop`.
    """
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ImageError(f'expected uint8 image, got {img.dtype}')
    if img.ndim not in (2, 3):
        raise ImageError(f'expected H x W or H x W x C image, got shape {img.shape}')
    x, y, w, h = (int(v) for v in crop_px)
    H, W = img.shape[:2]
    if w <= 0 or h <= 0 or x < 0 or y < 0 or x + w > W or y + h > H:
        raise ImageError(f'crop {list(crop_px)} does not fit a {W}x{H} frame')
    roi = img[y:y + h, x:x + w]
    if gray:
        roi = to_gray(roi)
    elif roi.ndim == 2 or roi.shape[2] == 1:
        roi = np.repeat(roi.reshape(h, w, 1), 3, axis=2)
    interp = cv2.INTER_AREA if (w >= size and h >= size) else cv2.INTER_LINEAR
    out = cv2.resize(np.ascontiguousarray(roi), (size, size), interpolation=interp)
    if out.ndim == 2:
        return out[None]
    return np.ascontiguousarray(out.transpose(2, 0, 1))


def crop_for(camera, width: int, height: int) -> list:
    """Return the camera's configured crop, scaled when the frame has another resolution."""
    if (width, height) == (camera.width, camera.height):
        return list(camera.crop_px)
    return scale_crop(camera.crop_px, (camera.width, camera.height), (width, height))


def scale_crop(crop_px, configured_wh, actual_wh):
    """Scale a crop defined at the configured resolution to a frame of another size."""
    cw, ch = configured_wh
    aw, ah = actual_wh
    sx, sy = aw / cw, ah / ch
    x, y, w, h = crop_px
    return [int(round(x * sx)), int(round(y * sy)), int(round(w * sx)), int(round(h * sy))]
