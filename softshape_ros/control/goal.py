"""
What the controller is asked to reach, checked before any air moves.

A goal is one of: target images per view (as the network sees them: V x C x S x S uint8),
a target robot silhouette per view (V x S x S, nonzero = robot), or a target tip pixel per
view (V x 2, row and column in the S x S network image). Each may ask to touch the object
or to stay clear of it. A malformed goal raises :class:`GoalError` saying why; nothing
downstream ever sees NaN, the wrong size or the wrong encoding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

KINDS = ('images', 'silhouette', 'tip')
CONTACT_MODES = ('any', 'touch', 'clear')


class GoalError(ValueError):
    """A goal cannot be planned for (wrong size, encoding, NaN, unknown view); says why."""


@dataclass(frozen=True)
class GoalSpec:
    """The image format the goal must match: the forward model's views, channels, size."""

    views: tuple
    channels: int
    size: int

    @classmethod
    def of(cls, predictor) -> 'GoalSpec':
        return cls(tuple(predictor.views), int(predictor.channels), int(predictor.image_size))


@dataclass(frozen=True)
class Goal:
    """A checked goal; build it with :meth:`images`, :meth:`silhouette` or :meth:`tip`."""

    kind: str
    spec: GoalSpec
    target_images: np.ndarray | None = None     # V x C x S x S uint8
    target_silhouette: np.ndarray | None = None  # V x S x S bool
    target_tip_rc: np.ndarray | None = None      # V x 2 float (row, col), network pixels
    contact: str = 'any'

    @staticmethod
    def _contact(contact: str) -> str:
        if contact not in CONTACT_MODES:
            raise GoalError(f'contact must be one of {CONTACT_MODES}, got {contact!r}')
        return contact

    @classmethod
    def images(cls, spec: GoalSpec, images, contact: str = 'any') -> 'Goal':
        """Target images per view, V x C x S x S uint8 (the network's input format)."""
        a = np.asarray(images)
        want = (len(spec.views), spec.channels, spec.size, spec.size)
        if a.dtype != np.uint8:
            raise GoalError(f'goal images must be uint8 (mono8/rgb8), got {a.dtype}')
        if a.shape != want:
            raise GoalError(f'goal images must be {want} (views {list(spec.views)}, '
                            f'{spec.channels} channel(s), {spec.size}x{spec.size}), '
                            f'got {a.shape}')
        return cls('images', spec, target_images=a.copy(), contact=cls._contact(contact))

    @classmethod
    def silhouette(cls, spec: GoalSpec, masks, contact: str = 'any') -> 'Goal':
        """Target robot silhouettes per view, V x S x S (bool, or uint8 with nonzero = robot)."""
        a = np.asarray(masks)
        want = (len(spec.views), spec.size, spec.size)
        if a.dtype not in (np.bool_, np.uint8):
            raise GoalError(f'goal silhouettes must be bool or uint8 (mono8), got {a.dtype}')
        if a.shape != want:
            raise GoalError(f'goal silhouettes must be {want} (views {list(spec.views)}), '
                            f'got {a.shape}')
        m = a.astype(bool)
        empty = [spec.views[i] for i in range(len(m)) if not m[i].any()]
        if empty:
            raise GoalError(f'goal silhouette of view(s) {empty} is empty: no robot to reach')
        return cls('silhouette', spec, target_silhouette=m, contact=cls._contact(contact))

    @classmethod
    def tip(cls, spec: GoalSpec, tips_rc, contact: str = 'any') -> 'Goal':
        """Target the tip position per view: V x 2 network pixels (row, col), inside the image."""
        try:
            a = np.asarray(tips_rc, dtype=np.float64)
        except (TypeError, ValueError):
            raise GoalError(f'goal tips must be numbers, got {tips_rc!r}') from None
        want = (len(spec.views), 2)
        if a.shape != want:
            raise GoalError(f'goal tips must be {want} (row, col per view {list(spec.views)}), '
                            f'got shape {a.shape}')
        if not np.all(np.isfinite(a)):
            raise GoalError(f'goal tips must be finite, got {a.tolist()}')
        hi = spec.size - 1
        if np.any(a < 0) or np.any(a > hi):
            raise GoalError(f'goal tips must lie in the {spec.size}x{spec.size} image '
                            f'(0..{hi}), got {a.tolist()}')
        return cls('tip', spec, target_tip_rc=a, contact=cls._contact(contact))


def camera_to_model_px(u: float, v: float, crop_px, size: int) -> tuple[float, float]:
    """
    Map a camera pixel (u = column, v = row, full resolution) to network (row, col).

    The network image is the crop ``[x, y, w, h]`` area-resized to ``size``: network pixel
    j covers camera columns ``x + j w / size .. x + (j + 1) w / size``.
    """
    for name, val in (('u', u), ('v', v)):
        if not isinstance(val, (int, float)) or isinstance(val, bool) or not math.isfinite(val):
            raise GoalError(f'tip pixel {name} must be a finite number, got {val!r}')
    x, y, w, h = (float(c) for c in crop_px)
    col = (u + 0.5 - x) * size / w - 0.5
    row = (v + 0.5 - y) * size / h - 0.5
    if not (-0.5 <= col <= size - 0.5 and -0.5 <= row <= size - 0.5):
        raise GoalError(f'tip pixel ({u:g}, {v:g}) lies outside the camera crop {list(crop_px)}')
    # The outermost half network pixel: its centre is the nearest a tip can be.
    return min(max(row, 0.0), size - 1.0), min(max(col, 0.0), size - 1.0)


def model_to_camera_px(row: float, col: float, crop_px, size: int) -> tuple[float, float]:
    """Inverse of :func:`camera_to_model_px`: network (row, col) -> camera (u, v)."""
    x, y, w, h = (float(c) for c in crop_px)
    return (col + 0.5) * w / size - 0.5 + x, (row + 0.5) * h / size - 0.5 + y
