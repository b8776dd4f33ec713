"""
Serving the forward model on a live rig (no rclpy): initial images, command checks, overlays.

The inference node is a thin adapter over :class:`InferenceCore`; keeping the logic here lets
it be tested without ROS and keeps the node's preprocessing identical to the dataset
builder's (both call :func:`softshape_ros.vision.preprocess.preprocess`).
"""

from __future__ import annotations

import threading

import cv2
import numpy as np

from softshape_ros.config import RigConfig
from softshape_ros.pressure import CommandError, check_command
from softshape_ros.vision.preprocess import crop_for, preprocess


class PredictionError(ValueError):
    """A request cannot be served (bad command, no initial images yet); nothing is published."""


class ModelMismatchError(ValueError):
    """The model does not fit the rig's cameras; the message names the file and the mismatch."""


class InferenceCore:
    """Hold a predictor and the current scene's initial images; answer pressure requests."""

    def __init__(self, predictor, cfg: RigConfig, model_path: str = '<model>'):
        self.predictor, self.cfg = predictor, cfg
        views = list(predictor.views)
        missing = [v for v in views if v not in cfg.cameras]
        if missing:
            raise ModelMismatchError(
                f'{model_path}: model views {views} need cameras {missing}, but the rig config '
                f'{cfg.source} has only {cfg.camera_names}')
        if predictor.channels not in (1, 3):
            raise ModelMismatchError(f'{model_path}: model expects {predictor.channels} channels')
        if len(predictor.max_pressure_pa) != 6:
            raise ModelMismatchError(f'{model_path}: model normalises '
                                     f'{len(predictor.max_pressure_pa)} pressures, the rig has 6')
        self.views = views
        self.gray = predictor.channels == 1
        self.size = int(predictor.image_size)
        self.limits = np.asarray(cfg.max_pressures_pa, dtype=np.float64)
        self._initial: dict[str, np.ndarray | None] = {v: None for v in views}
        self._lock = threading.Lock()

    def prepare(self, view: str, frame: np.ndarray) -> np.ndarray:
        """Camera frame -> C x S x S exactly as the dataset builder prepares it."""
        crop = crop_for(self.cfg.cameras[view], frame.shape[1], frame.shape[0])
        return preprocess(frame, crop, size=self.size, gray=self.gray)

    def set_initial(self, view: str, frame: np.ndarray) -> None:
        img = self.prepare(view, frame)
        with self._lock:
            self._initial[view] = img

    def clear_initial(self) -> None:
        with self._lock:
            self._initial = {v: None for v in self.views}

    @property
    def ready(self) -> bool:
        with self._lock:
            return all(v is not None for v in self._initial.values())

    def initial(self) -> np.ndarray:
        with self._lock:
            missing = [v for v, img in self._initial.items() if img is None]
            if missing:
                raise PredictionError(f'no initial image yet for {missing} (waiting for the '
                                      'rest images of a scene, or call ~/capture_initial)')
            return np.stack([self._initial[v] for v in self.views])

    def check(self, values) -> np.ndarray:
        """Validate a 6-chamber request; beyond-limit values are refused, not clamped."""
        try:
            c = check_command(values, self.limits)
        except CommandError as exc:
            raise PredictionError(str(exc)) from None
        if c.clamped:
            raise PredictionError(f'pressure beyond the configured limits at chambers '
                                  f'{list(c.clamped)}: {list(values)} > {self.limits.tolist()}')
        return c.pressures_pa

    def predict(self, values) -> dict[str, np.ndarray]:
        """Return {view: C x S x S uint8} for a checked pressure request."""
        p = self.check(values)
        out = self.predictor.predict(self.initial(), p)
        return {v: out[i] for i, v in enumerate(self.views)}


def to_hwc(img: np.ndarray) -> np.ndarray:
    """C x H x W -> H x W (gray) or H x W x 3 for publishing."""
    return img[0] if img.shape[0] == 1 else np.ascontiguousarray(img.transpose(1, 2, 0))


def overlay(frame: np.ndarray, predicted: np.ndarray, crop_px, color=(255, 220, 0)) -> np.ndarray:
    """
    Draw the predicted silhouette's outline over the current camera frame.

    The prediction (C x S x S) is upscaled to the crop region; its edges are drawn in
    ``color`` so a viewer sees where the model puts the robot against where it is.
    """
    rgb = frame if frame.ndim == 3 else cv2.cvtColor(frame, cv2.COLOR_GRAY2RGB)
    out = np.ascontiguousarray(rgb.copy())
    x, y, w, h = (int(v) for v in crop_px)
    pred = to_hwc(predicted)
    if pred.ndim == 3:
        pred = cv2.cvtColor(pred, cv2.COLOR_RGB2GRAY)
    up = cv2.resize(pred, (w, h), interpolation=cv2.INTER_LINEAR)
    edges = cv2.Canny(up, 30, 90) > 0
    edges = cv2.dilate(edges.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    region = out[y:y + h, x:x + w]
    region[edges] = color
    cv2.rectangle(out, (x, y), (x + w - 1, y + h - 1), (0, 160, 255), 1)
    return out


class LatestSlot:
    """A one-item mailbox: a new request replaces an unserved one (counted as superseded)."""

    def __init__(self):
        self._cond = threading.Condition()
        self._item = None
        self._closed = False
        self.superseded = 0

    def put(self, item) -> None:
        with self._cond:
            if self._item is not None:
                self.superseded += 1
            self._item = item
            self._cond.notify()

    def get(self, timeout: float | None = None):
        """Take the latest item; ``None`` on timeout or after :meth:`close`."""
        with self._cond:
            if self._item is None and not self._closed:
                self._cond.wait(timeout)
            item, self._item = self._item, None
            return item

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
