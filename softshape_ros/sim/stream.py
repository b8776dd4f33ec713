"""
The simulated cameras' work loop: commands, scenes, triggers in arrival order, free run between.

``SimCameras`` owns a :class:`~softshape_ros.sim.rig.SimRig` in one worker thread (the
simulator is not thread-safe, and the ROS executor must keep its pressure loop). A command
is solved when it arrives (the robot moves when commanded, not when filmed), so a trigger
at the settled pressures only renders. Triggers carry the pressures sampled when they
arrived: a trigger before the regulators settled gets the shape at its own pressures
(solved then), never the commanded one. Free-run frames sample the current
pressures themselves at a fixed rate (:class:`FreeRunClock`: a late frame is skipped, never
queued, so the stream never falls behind the trigger answers). The shape is solved only
when the scene or the pressures changed; with no image noise the images are reused too.
Every frame set goes to a ``publish`` callback; failures are counted, logged and answered
with no images, never a stale or made-up one. No rclpy here: the node wires this to ROS.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
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
    solved: bool                # False: a shape already solved (same scene and pressures)


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
    Simulated cameras: ``command``, ``trigger``, ``set_scene`` from any thread; frames out.

    ``rig`` (a SimRig) is used only by the worker thread once started; ``publish`` gets each
    :class:`Frames` there; ``sample_pressures()`` returns (pressures (6,), sampled_ns) now,
    for free-run frames; ``free_run_hz`` 0 means triggers only; triggers and scene changes
    queued beyond ``max_pending`` are dropped (counted); a command queued right behind
    another replaces it (never dropped: only the newest is the robot's target);
    ``log(level, message)`` with level
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
        self.max_pending = max(1, int(max_pending))
        self.jobs: deque = deque()  # ('command' | 'scene' | 'trigger', ...), arrival order
        self._pending = 0           # scenes and triggers in ``jobs``
        self._cv = threading.Condition()
        self.scene = None
        self._scene_version = 0
        self._last = None           # (key, state, images or None) of the last good frame
        self._commanded = None      # the last command's pressures
        self._target = None         # (key, state) solved at them on arrival
        self._failed_key = None     # the last (scene, pressures) that failed: not retried
        self.frames = 0             # trigger frame sets published
        self.free_frames = 0
        self.solves = 0             # solved for a frame (its pressures were not solved before)
        self.command_solves = 0     # solved when the command came
        self.reused = 0             # frames whose shape was already solved
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

    def command(self, pressures_pa) -> None:
        """Queue the shape at newly commanded pressures, solved in order before later triggers."""
        job = ('command', np.array(pressures_pa, dtype=float))
        with self._cv:
            if self.jobs and self.jobs[-1][0] == 'command':
                self.jobs[-1] = job     # not solved yet: the newer command supersedes it
            else:
                self.jobs.append(job)
            self._cv.notify()

    def trigger(self, stamp_ns: int, pressures_pa, sampled_ns: int) -> bool:
        """Queue a frame set at ``pressures_pa`` stamped ``stamp_ns``; False if dropped."""
        return self._put(('trigger', int(stamp_ns), np.asarray(pressures_pa, dtype=float),
                          int(sampled_ns), self.monotonic()))

    def idle(self) -> bool:
        """Return True when no command, trigger or scene change is waiting."""
        with self._cv:
            return not self.jobs

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
        with self._cv:
            if self._pending < self.max_pending:
                self.jobs.append(job)
                self._pending += 1
                self._cv.notify()
                return True
        self.dropped += 1
        self.log('error', f'simulator is behind: {job[0]} dropped, no images for it')
        return False

    def _get(self, wait_s: float):
        """Return the oldest job, waiting at most ``wait_s`` for one (None: none came)."""
        with self._cv:
            if not self.jobs and wait_s > 0:
                self._cv.wait_for(lambda: bool(self.jobs), timeout=wait_s)
            if not self.jobs:
                return None
            job = self.jobs.popleft()
            if job[0] != 'command':
                self._pending -= 1
            return job

    def _run(self) -> None:
        while not self._stop.is_set():
            self.step(0.1)

    def step(self, max_wait_s: float) -> str | None:
        """
        Do the next piece of work, waiting at most ``max_wait_s`` for it.

        Returns what was done: 'command', 'scene', 'trigger', 'free' or None. Queued work
        comes first; a free-run frame is taken only when nothing waits.
        """
        job = self._get(min(max_wait_s, self.clock.wait_s(self.monotonic())))
        if job is None:
            if not self.clock.take(self.monotonic()):
                return None
            pressures, sampled_ns = self.sample_pressures()
            self._frame('free', sampled_ns, np.asarray(pressures, dtype=float), sampled_ns,
                        None)
            return 'free'
        if job[0] == 'command':
            self._commanded = job[1]
            self._solve_target()
            return 'command'
        if job[0] == 'scene':
            self._apply_scene(job[1])
            self._solve_target()
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
        self._target = None
        self._failed_key = None
        if scene is not None:
            self.log('info', f'scene {scene.id}: {scene.object}')

    def _solve_target(self) -> None:
        """
        Solve the shape at the commanded pressures in the current scene, unless it is solved.

        A failure is logged only: a frame at these pressures solves again and reports it.
        """
        if self._commanded is None:
            return
        key = self._key(self._commanded)
        if self._target is not None and self._target[0] == key:
            return
        if self._last is not None and self._last[0] == key:
            self._target = (key, self._last[1])
            return
        self._target = None
        try:
            state = self.rig.solve(self._commanded)
        except Exception as exc:  # SolverError, bad pressures: the frame will say so
            self.log('warning', f'commanded shape at {self._commanded.tolist()} Pa not solved '
                                f'({type(exc).__name__}: {exc}); a frame there solves again')
            return
        self.command_solves += 1
        self._target = (key, state)

    def _key(self, pressures) -> tuple:
        """Return what a shape depends on: the scene (its version) and the pressures."""
        return self._scene_version, pressures.tobytes()

    def _frame_images(self, pressures):
        """Return (images, solved): the shape solved only if the scene or pressures changed."""
        key = self._key(pressures)
        if self._last is not None and self._last[0] == key:
            state, images, solved = self._last[1], self._last[2], False
            self.reused += 1
        elif self._target is not None and self._target[0] == key:
            state, images, solved = self._target[1], None, False
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
        key = self._key(pressures)
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
