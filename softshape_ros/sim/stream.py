"""
The simulated cameras' work loop: triggers and scene changes in arrival order, free run between.

``SimCameras`` owns a :class:`~softshape_ros.sim.rig.SimRig` in one worker thread (the
simulator is not thread-safe, and the ROS executor must keep its pressure loop). Triggers
carry the pressures sampled when they arrived; free-run frames sample the current
pressures themselves at a fixed rate (:class:`FreeRunClock`: a late frame is skipped, never
queued, so the stream never falls behind the trigger answers). The shape is solved only
when the scene or the pressures changed; with no image noise the images are reused too.
Every frame set goes to a ``publish`` callback; failures are counted, logged and answered
with no images, never a stale or made-up one. No rclpy here: the node wires this to ROS.
"""

from __future__ import annotations

from dataclasses import dataclass
import queue
import threading
import time
from typing import Callable

import numpy as np

from softshape_ros.vision.sync import RollingStats


@dataclass
class Frames:
    """One simulated exposure of every camera."""

    kind: str                   # 'trigger' or 'free'
    stamp_ns: int               # header stamp: the trigger's, or the capture instant
    sampled_ns: int             # when the pressures were sampled (= capture time)
    pressures_pa: np.ndarray    # (6,) the pressures the shape was solved at
    images: dict                # camera -> H x W x 3 uint8 RGB
    solved: bool                # False: the last shape was reused (same scene and pressures)


class FreeRunClock:
    """
    Frame deadlines at a fixed rate on a monotonic clock (rate 0: never due).

    A frame taken late moves the next deadline to the first slot after now, so a slow
    frame costs the slots it overran (counted in ``skipped``), never a burst of frames.
    """

    def __init__(self, rate_hz: float, now_s: float):
        if not (rate_hz >= 0.0 and np.isfinite(rate_hz)):
            raise ValueError(f'free-run rate must be a finite number >= 0 Hz, got {rate_hz!r}')
        self.period_s = 1.0 / rate_hz if rate_hz > 0 else np.inf
        self.next_s = now_s + self.period_s
        self.skipped = 0

    def wait_s(self, now_s: float) -> float:
        """Return the seconds until the next frame is due (0 when due, inf when off)."""
        return max(0.0, self.next_s - now_s)

    def take(self, now_s: float) -> bool:
        """Take the frame if it is due; return whether it was."""
        if now_s < self.next_s:
            return False
        late = int((now_s - self.next_s) // self.period_s)
        self.skipped += late
        self.next_s += (late + 1) * self.period_s
        return True


class SimCameras:
    """
    Simulated cameras: ``trigger()`` and ``set_scene()`` from any thread, frames to ``publish``.

    ``rig`` (a SimRig) is used only by the worker thread once started; ``publish`` gets each
    :class:`Frames` there; ``sample_pressures()`` returns (pressures (6,), sampled_ns) now,
    for free-run frames; ``free_run_hz`` 0 means triggers only; triggers and scene changes
    queued beyond ``max_pending`` are dropped (counted); ``log(level, message)`` with level
    'info', 'warning' or 'error'; ``monotonic`` is the scheduling clock (seconds).
    """

    def __init__(self, rig, publish: Callable[[Frames], None],
                 sample_pressures: Callable[[], tuple], free_run_hz: float = 0.0,
                 max_pending: int = 8, log: Callable[[str, str], None] | None = None,
                 monotonic: Callable[[], float] = time.monotonic):
        self.rig = rig
        self.publish = publish
        self.sample_pressures = sample_pressures
        self.monotonic = monotonic
        self.clock = FreeRunClock(float(free_run_hz), monotonic())
        self.free_run_hz = float(free_run_hz)
        self.log = log or (lambda level, message: None)
        self.jobs: queue.Queue = queue.Queue(maxsize=max(1, int(max_pending)))
        self.scene = None
        self._scene_version = 0
        self._last = None           # (key, state, images or None) of the last good frame
        self._failed_key = None     # the last (scene, pressures) that failed: not retried
        self.frames = 0             # trigger frame sets published
        self.free_frames = 0
        self.solves = 0
        self.reused = 0
        self.solver_errors = 0
        self.dropped = 0
        self.last_error = ''
        self.trigger_latency = RollingStats()   # trigger sampled -> images ready (s)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- from any thread --------------------------------------------------------------------
    def set_scene(self, scene) -> bool:
        """Queue a scene change (applied in order with the triggers); False if dropped."""
        return self._put(('scene', scene))

    def trigger(self, stamp_ns: int, pressures_pa, sampled_ns: int) -> bool:
        """Queue a frame set at ``pressures_pa`` stamped ``stamp_ns``; False if dropped."""
        return self._put(('trigger', int(stamp_ns), np.asarray(pressures_pa, dtype=float),
                          int(sampled_ns), self.monotonic()))

    def idle(self) -> bool:
        """Return True when no trigger or scene change is waiting."""
        return self.jobs.empty()

    def warm_up(self, pressures_pa) -> None:
        """
        Solve and render once now, in the calling thread (compiles or loads the kernels).

        Call before anything else runs: the first frame otherwise pays numba's compile
        (seconds, holding the interpreter) while triggers wait. The result is kept, so the
        first frame at these pressures is free.
        """
        self._frame_images(np.asarray(pressures_pa, dtype=float))

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name='sim-cameras', daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout)

    # -- the worker ------------------------------------------------------------------------
    def _put(self, job) -> bool:
        try:
            self.jobs.put_nowait(job)
            return True
        except queue.Full:
            self.dropped += 1
            self.log('error', f'simulator is behind: {job[0]} dropped, no images for it')
            return False

    def _run(self) -> None:
        while not self._stop.is_set():
            self.step(0.1)

    def step(self, max_wait_s: float) -> str | None:
        """
        Do the next piece of work, waiting at most ``max_wait_s`` for it.

        Returns what was done: 'scene', 'trigger', 'free' or None. Queued work comes first;
        a free-run frame is taken only when nothing waits.
        """
        wait = min(max_wait_s, self.clock.wait_s(self.monotonic()))
        try:
            job = self.jobs.get(timeout=wait) if wait > 0 else self.jobs.get_nowait()
        except queue.Empty:
            job = None
        if job is None:
            if not self.clock.take(self.monotonic()):
                return None
            pressures, sampled_ns = self.sample_pressures()
            self._frame('free', sampled_ns, np.asarray(pressures, dtype=float), sampled_ns,
                        None)
            return 'free'
        if job[0] == 'scene':
            self._apply_scene(job[1])
            return 'scene'
        _, stamp_ns, pressures, sampled_ns, queued_s = job
        self._frame('trigger', stamp_ns, pressures, sampled_ns, queued_s)
        return 'trigger'

    def _apply_scene(self, scene) -> None:
        try:
            self.rig.set_scene(scene)
            self.rig.check_views()        # a camera inside the object: no honest image
        except Exception as exc:  # a scene the simulator cannot place: keep the old one
            label = getattr(scene, 'id', '?')
            self.last_error = f'scene {label}: {exc}'
            self.log('error', f'scene {label} not applied, keeping the previous one: {exc}')
            self.rig.set_scene(self.scene)
            return
        self.scene = scene
        self._scene_version += 1
        self._last = None
        self._failed_key = None
        if scene is not None:
            self.log('info', f'scene {scene.id}: {scene.object}')

    def _frame_images(self, pressures):
        """Return (images, solved): the shape solved only if the scene or pressures changed."""
        key = (self._scene_version, pressures.tobytes())
        if self._last is not None and self._last[0] == key:
            state, images, solved = self._last[1], self._last[2], False
            self.reused += 1
        else:
            state, images, solved = self.rig.solve(pressures), None, True
            self.solves += 1
        if images is None:
            images = self.rig.render(state)
        noisy = getattr(self.rig, 'image_noise_std', 0.0) > 0
        self._last = (key, state, None if noisy else images)
        return images, solved

    def _frame(self, kind, stamp_ns, pressures, sampled_ns, queued_s) -> None:
        key = (self._scene_version, pressures.tobytes())
        if kind == 'free' and key == self._failed_key:
            return                  # it failed at exactly these pressures: wait for a change
        try:
            images, solved = self._frame_images(pressures)
        except Exception as exc:  # SolverError, RenderError, bad pressures: no images
            self.solver_errors += 1
            self._failed_key = key
            self.last_error = f'{type(exc).__name__}: {exc}'
            self.log('error', f'simulator failed at {pressures.tolist()} Pa ({kind}): '
                              f'{self.last_error}; no images')
            return
        self._failed_key = None
        if queued_s is not None:
            self.trigger_latency.add(self.monotonic() - queued_s)
        try:
            self.publish(Frames(kind, stamp_ns, sampled_ns, pressures, images, solved))
        except Exception as exc:  # e.g. publishing while the context shuts down
            self.last_error = f'publish failed: {exc}'
            return
        if kind == 'trigger':
            self.frames += 1
        else:
            self.free_frames += 1
