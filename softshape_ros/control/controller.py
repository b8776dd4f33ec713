"""
The shape controller's logic without ROS: scene, goals from camera-format inputs, the loop.

The ``shape_controller`` node is a thin adapter over :class:`Controller`: it turns messages
into the numpy frames and JSON text taken here, and runs the waits (settling, frames)
between :meth:`ShapeLoop.plan` and :meth:`ShapeLoop.observe`.
"""

from __future__ import annotations

import json
import threading

import cv2
import numpy as np

from softshape_ros.config import RigConfig
from softshape_ros.control.features import SceneContext, SceneContextError
from softshape_ros.control.forward import NetworkForward, usable_limits
from softshape_ros.control.goal import Goal, GoalError, GoalSpec, camera_to_model_px
from softshape_ros.control.loop import ShapeLoop, Tolerance
from softshape_ros.control.planner import Bank, Planner, PlannerConfig
from softshape_ros.pressure import CommandError, check_command
from softshape_ros.vision.preprocess import ImageError, crop_for, preprocess


class Controller:
    """One model, one rig: the current scene's reference, goals, and a loop per goal."""

    def __init__(self, predictor, cfg: RigConfig, limits_pa=None,
                 planner: PlannerConfig = PlannerConfig(), tolerance: Tolerance = Tolerance(),
                 max_iterations: int = 3):
        missing = [v for v in predictor.views if v not in cfg.cameras]
        if missing:
            raise ValueError(f'model views {list(predictor.views)} need cameras {missing}, '
                             f'not in {cfg.source} ({cfg.camera_names})')
        if max_iterations < 1:
            raise ValueError(f'max_iterations must be >= 1, got {max_iterations}')
        self.predictor, self.cfg = predictor, cfg
        self.spec = GoalSpec.of(predictor)
        self.gray = self.spec.channels == 1
        rig = np.asarray(cfg.max_pressures_pa, dtype=np.float64)
        lim = rig if limits_pa is None else np.asarray(limits_pa, dtype=np.float64)
        if lim.shape != rig.shape or np.any(lim > rig) or np.any(~np.isfinite(lim)) \
                or np.any(lim < 0):
            raise ValueError(f'limits may only lower {cfg.source} ({rig.tolist()}), got '
                             f'{lim.tolist()}')
        self.limits = usable_limits(lim, predictor.max_pressure_pa)
        self.planner = Planner(planner)
        self.planner_cfg = planner
        self.tolerance, self.max_iterations = tolerance, int(max_iterations)
        self._lock = threading.Lock()
        self.ctx: SceneContext | None = None
        self.forward: NetworkForward | None = None
        self.bank: Bank | None = None

    # -- the scene ---------------------------------------------------------------------------
    def prepare(self, view: str, frame: np.ndarray) -> np.ndarray:
        """Prepare a camera frame (or an S x S network image): C x S x S as the dataset has it."""
        s = self.spec.size
        if frame.shape[:2] == (s, s):
            return preprocess(frame, [0, 0, s, s], s, self.gray)
        crop = crop_for(self.cfg.cameras[view], frame.shape[1], frame.shape[0])
        return preprocess(frame, crop, s, self.gray)

    def _goal_frame(self, view: str, frame: np.ndarray) -> np.ndarray:
        """Refuse a goal image that is neither S x S nor of the camera's shape (any scale)."""
        cam, s = self.cfg.cameras[view], self.spec.size
        h, w = frame.shape[:2]
        if (h, w) != (s, s) and abs(w * cam.height - h * cam.width) > 0.01 * w * cam.height:
            raise GoalError(f'goal image of {view} is {w}x{h}: neither {s}x{s} (network '
                            f'image) nor a {cam.width}x{cam.height} camera frame (any scale)')
        return frame

    def set_initial(self, frames: dict) -> float:
        """Take the rest frames of a scene ({view: frame}); build its bank; return its ms."""
        try:
            initial = np.stack([self.prepare(v, frames[v]) for v in self.spec.views])
        except KeyError as exc:
            raise SceneContextError(f'no rest frame of view {exc}') from None
        except ImageError as exc:
            raise SceneContextError(f'rest frame unusable: {exc}') from None
        ctx = SceneContext.from_initial(initial)
        forward = NetworkForward(self.predictor, initial, self.limits)
        bank = Bank.for_scene(forward, ctx, self.planner_cfg.bank_size, self.planner_cfg.seed)
        with self._lock:
            self.ctx, self.forward, self.bank = ctx, forward, bank
        return bank.build_ms

    def clear_initial(self) -> None:
        with self._lock:
            self.ctx = self.forward = self.bank = None

    @property
    def ready(self) -> bool:
        with self._lock:
            return self.ctx is not None

    # -- goals -------------------------------------------------------------------------------
    def goal_from_images(self, frames: dict, contact: str = 'any') -> Goal:
        """Goal images per view: camera frames (cropped like the dataset) or S x S images."""
        try:
            imgs = np.stack([self.prepare(v, self._goal_frame(v, self._frame(frames, v)))
                             for v in self.spec.views])
        except ImageError as exc:
            raise GoalError(f'goal image unusable: {exc}') from None
        return Goal.images(self.spec, imgs, contact)

    def goal_from_silhouettes(self, frames: dict, contact: str = 'any') -> Goal:
        """Goal silhouettes per view: mono8, nonzero = robot, full frame or S x S."""
        s = self.spec.size
        masks = []
        for v in self.spec.views:
            m = self._goal_frame(v, self._frame(frames, v))
            if m.ndim != 2:
                raise GoalError(f'goal silhouette of {v} must be mono8 (nonzero = robot), '
                                f'got shape {m.shape}')
            if m.shape != (s, s):
                x, y, w, h = crop_for(self.cfg.cameras[v], m.shape[1], m.shape[0])
                if x + w > m.shape[1] or y + h > m.shape[0]:
                    raise GoalError(f'goal silhouette of {v} ({m.shape[1]}x{m.shape[0]}) does '
                                    'not fit the camera crop')
                roi = (m[y:y + h, x:x + w] > 0).astype(np.uint8) * 255
                m = cv2.resize(roi, (s, s), interpolation=cv2.INTER_AREA) > 127
            masks.append(m > 0)
        return Goal.silhouette(self.spec, np.stack(masks), contact)

    def goal_from_tip_json(self, text: str, contact: str = 'any') -> Goal:
        """
        Read a tip goal from JSON: ``{"tips_px": {"main": [u, v], "side": [u, v]}}``.

        Optional keys: ``"frame"``: ``"camera"`` (default; full-resolution pixels, u = column)
        or ``"model"`` (the S x S network image, u = column too); ``"contact"``.
        """
        try:
            d = json.loads(text)
        except (ValueError, RecursionError) as exc:
            raise GoalError(f'tip goal is not JSON: {exc}') from None
        if not isinstance(d, dict) or not isinstance(d.get('tips_px'), dict):
            raise GoalError('tip goal needs {"tips_px": {"<view>": [u, v], ...}}')
        unknown = sorted(set(d) - {'tips_px', 'frame', 'contact'})
        if unknown:
            raise GoalError(f'tip goal: unknown key {unknown[0]!r}')
        frame = d.get('frame', 'camera')
        if frame not in ('camera', 'model'):
            raise GoalError(f'tip goal: frame must be "camera" or "model", got {frame!r}')
        tips = []
        for v in self.spec.views:
            uv = d['tips_px'].get(v)
            if not isinstance(uv, (list, tuple)) or len(uv) != 2:
                raise GoalError(f'tip goal: view {v!r} needs [u, v], got {uv!r}')
            u_px, v_px = uv
            if frame == 'camera':
                cam = self.cfg.cameras[v]
                tips.append(camera_to_model_px(u_px, v_px, cam.crop_px, self.spec.size))
            else:
                for val in (u_px, v_px):
                    if isinstance(val, bool) or not isinstance(val, (int, float)):
                        raise GoalError(f'tip goal: view {v!r} needs numbers, got {uv!r}')
                tips.append((float(v_px), float(u_px)))
        return Goal.tip(self.spec, np.array(tips), d.get('contact', contact))

    def _frame(self, frames: dict, view: str) -> np.ndarray:
        if view not in frames:
            raise GoalError(f'goal has no image for view {view!r} (needs {list(self.spec.views)})')
        return np.asarray(frames[view])

    # -- the loop ----------------------------------------------------------------------------
    def start(self, goal: Goal, tolerance: Tolerance | None = None,
              max_iterations: int | None = None) -> ShapeLoop:
        """Start a closed loop for ``goal`` in the current scene (GoalError if it does not fit)."""
        with self._lock:
            ctx, forward, bank = self.ctx, self.forward, self.bank
        if ctx is None:
            raise SceneContextError('no initial images of the scene yet')
        n = self.max_iterations if max_iterations is None else int(max_iterations)
        if n < 1:
            raise ValueError(f'max_iterations must be >= 1, got {n}')
        return ShapeLoop(forward, ctx, goal, self.planner, bank, tolerance or self.tolerance, n)

    def check(self, pressures_pa) -> np.ndarray:
        """Check a plan before air moves: 6 finite values within this controller's limits."""
        try:
            c = check_command(pressures_pa, self.limits)
        except CommandError as exc:
            raise ValueError(f'planned command refused: {exc}') from None
        if c.clamped:
            raise ValueError(f'planned command beyond the limits at chambers {list(c.clamped)}')
        return c.pressures_pa
