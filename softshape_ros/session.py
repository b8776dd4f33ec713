"""
A data-collection session (paper IV-B), as plain Python: plans, records and the sequence.

Per scene: announce the scene, vent, (on the physical rig: wait for the operator), wait
until the measured pressures are at zero, trigger the rest images; then N actuations at
``period_s``, each sent, held until a measurement sampled after it is within
``tolerance_pa`` of the command (or ``settle_timeout_s``: logged, the sample marked
unsettled) and triggered. Before every trigger a :class:`SampleRecord` says what it is,
so the dataset builder never has to guess. The session always ends venting.

The ``collector`` node is the ROS side: it feeds measurements and frame arrivals into
:class:`RigFeedback` and carries out :class:`RigIO` (publish a command, a scene, a record
and a trigger). Stamps come from ``RigIO.now_ns`` (ROS time, sim time under
``use_sim_time``); waits and timeouts run on the steady clock.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Protocol, Sequence

import numpy as np
import yaml

from softshape_ros.pressure import CommandError, check_command, measured_in_order
from softshape_ros.scene import Scene

__all__ = ['SessionError', 'load_pressure_list', 'CommandPlan', 'SessionSettings',
           'SampleRecord', 'RigFeedback', 'RigIO', 'CollectionSession', 'Stopped']


class SessionError(ValueError):
    """A session or pressure-list file cannot be used; the message names the file."""


class Stopped(Exception):
    """The session was asked to stop: leave the session loop."""


def load_pressure_list(path, limits_pa) -> np.ndarray:
    """
    Read the pressures to replay: YAML ``pressures_pa: [[6 x Pa], ...]`` or a CSV of rows.

    Every row goes through check_command, so a bad row fails here, before any air moves.
    Returns an (N, 6) float array, Pa.
    """
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise SessionError(f'{p}: cannot read pressure list: {exc.strerror or exc}') from None
    if p.suffix.lower() == '.csv':
        rows = [[c for c in line.split(',')] for line in text.splitlines()
                if line.strip() and not line.lstrip().startswith('#')]
    else:
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise SessionError(f'{p}: not valid YAML: {exc}') from None
        if not isinstance(data, dict) or not isinstance(data.get('pressures_pa'), list):
            raise SessionError(f'{p}: expected a mapping with a list under "pressures_pa"')
        rows = data['pressures_pa']
    if not rows:
        raise SessionError(f'{p}: the pressure list is empty')
    out = []
    for i, row in enumerate(rows):
        try:
            checked = check_command(row, limits_pa)
        except CommandError as exc:
            raise SessionError(f'{p}: row {i}: {exc}') from None
        if checked.clamped:
            raise SessionError(f'{p}: row {i}: chambers {list(checked.clamped)} exceed their '
                               f'limits {list(limits_pa)}')
        out.append(checked.pressures_pa)
    return np.asarray(out)


class CommandPlan:
    """Where actuation pressures come from: seeded uniform random, or a replayed list."""

    def __init__(self, limits_pa, seed: int = 0, max_fraction: float = 1.0, replay=None):
        if not 0.0 < max_fraction <= 1.0:
            raise SessionError(f'max_fraction must be in (0, 1], got {max_fraction}')
        self.high = np.asarray(limits_pa, dtype=np.float64) * max_fraction
        self.rng = np.random.default_rng(seed)
        self.replay = replay
        self.used = 0

    @classmethod
    def from_mode(cls, mode: str, limits_pa, seed: int = 0, max_fraction: float = 1.0,
                  pressures_file: str = '') -> 'CommandPlan':
        """Build the plan a collector's ``mode`` asks for ('random' or 'list')."""
        replay = None
        if mode == 'list':
            if not pressures_file:
                raise SessionError('mode list needs the pressures_file parameter')
            replay = load_pressure_list(pressures_file, limits_pa)
        elif mode != 'random':
            raise SessionError(f'mode must be random or list, got {mode!r}')
        return cls(limits_pa, seed, max_fraction, replay)

    def next(self) -> np.ndarray:
        """Return the next command, Pa (six values)."""
        if self.replay is not None:
            if self.used >= len(self.replay):
                raise SessionError(f'the pressure list has only {len(self.replay)} rows; the '
                                   'session needs more')
            row = self.replay[self.used]
        else:
            row = self.rng.uniform(0.0, self.high)
        self.used += 1
        return np.asarray(row, dtype=np.float64)


@dataclass(frozen=True)
class SessionSettings:
    """How a session paces itself (collector parameters, resolved against rig.yaml)."""

    period_s: float                  # between actuations
    tolerance_pa: float              # settled: every chamber within this of the command
    settle_timeout_s: float          # ... or give up, mark the sample unsettled
    rest_delay_s: float = 0.5        # after venting, before the rest trigger
    start_delay_s: float = 0.5       # after the rig is seen, before the first scene
    actuations: int = -1             # per scene; -1 = each scene's own
    wait_for_operator: bool = False  # physical rig: a person places each object
    wait_for_frames: bool = True     # hold the next actuation until every camera answered
    frame_timeout_s: float = 10.0
    next_scene_service: str = 'next_scene'   # named in the operator prompt


@dataclass(frozen=True)
class SampleRecord:
    """What one trigger is (published as JSON on /rig/sample just before it)."""

    stamp_ns: int
    scene_id: int
    kind: str                        # 'rest' | 'actuation'
    index: int
    command_pa: tuple
    settled: bool

    def to_json(self) -> str:
        """Return the record as the JSON the dataset builder reads."""
        d = asdict(self)
        d['command_pa'] = [float(v) for v in self.command_pa]
        return json.dumps(d)


class RigFeedback:
    """
    What the rig reports, shared between the ROS callbacks and the session thread.

    Measured pressures are matched to the chamber order by name; frames are counted per
    trigger stamp (the last 64 stamps).
    """

    def __init__(self, chamber_names: Sequence[str], cameras: Sequence[str]):
        self.chamber_names = list(chamber_names)
        self.cameras = set(cameras)
        self._cond = threading.Condition()
        self._measured: tuple[int, np.ndarray] | None = None
        self._frames: dict[int, set] = {}

    @property
    def has_measured(self) -> bool:
        with self._cond:
            return self._measured is not None

    def add_measured(self, stamp_ns: int, names, values) -> bool:
        """Store one measurement; False (ignored) if names and values do not fit the rig."""
        a = measured_in_order(names, values, self.chamber_names)
        if a is None:
            return False
        with self._cond:
            self._measured = (int(stamp_ns), a)
            self._cond.notify_all()
        return True

    def add_frame(self, camera: str, stamp_ns: int) -> None:
        """Note that ``camera`` answered the trigger stamped ``stamp_ns``."""
        with self._cond:
            self._frames.setdefault(int(stamp_ns), set()).add(camera)
            while len(self._frames) > 64:
                self._frames.pop(next(iter(self._frames)))
            self._cond.notify_all()

    def wake(self) -> None:
        """Wake any waiter (to see a stop request at once)."""
        with self._cond:
            self._cond.notify_all()

    def wait_settled(self, target, since_ns: int, tolerance_pa: float, timeout_s: float,
                     stop: threading.Event) -> tuple[bool, float]:
        """
        Wait for a measurement sampled at or after ``since_ns`` within tolerance of target.

        Returns (settled, the worst chamber error of the last measurement in Pa, nan if none).
        """
        target = np.asarray(target, dtype=np.float64)
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                m = self._measured
                if m is not None and m[0] >= since_ns and \
                        float(np.max(np.abs(m[1] - target))) <= tolerance_pa:
                    return True, float(np.max(np.abs(m[1] - target)))
                left = deadline - time.monotonic()
                if left <= 0 or stop.is_set():
                    break
                self._cond.wait(min(left, 0.05))
        if stop.is_set():
            raise Stopped
        return False, float(np.max(np.abs(m[1] - target))) if m is not None else float('nan')

    def wait_frames(self, stamp_ns: int, timeout_s: float, stop: threading.Event) -> list:
        """Wait until every camera answered ``stamp_ns``; return the cameras still missing."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not self.cameras <= self._frames.get(stamp_ns, set()):
                left = deadline - time.monotonic()
                if left <= 0 or stop.is_set():
                    break
                self._cond.wait(min(left, 0.05))
            missing = sorted(self.cameras - self._frames.get(stamp_ns, set()))
        if stop.is_set():
            raise Stopped
        return missing


class RigIO(Protocol):
    """What a session needs from the rig's transport (the collector node implements it)."""

    def now_ns(self) -> int:
        """Return the stamp for a trigger now (ROS time)."""

    def rig_waiting_for(self) -> str:
        """Return what the rig still lacks before a session may start ('' = ready)."""

    def send(self, pressures_pa: np.ndarray) -> None:
        """Publish one checked command (six Pa)."""

    def publish_scene(self, scene: Scene) -> None:
        """Announce the scene (latched)."""

    def trigger(self, record: SampleRecord) -> None:
        """Publish the record, then the trigger with ``record.stamp_ns``."""

    def log(self, level: str, text: str) -> None:
        """Say something a person should see ('info' | 'warn' | 'error')."""


class CollectionSession:
    """Run the scenes of a session over a :class:`RigIO`, from one worker thread."""

    def __init__(self, scenes: Sequence[Scene], plan: CommandPlan, settings: SessionSettings,
                 io: RigIO, feedback: RigFeedback, limits_pa):
        self.scenes = list(scenes)
        self.plan, self.settings, self.io, self.feedback = plan, settings, io, feedback
        self.limits = [float(x) for x in limits_pa]
        self.state = 'starting'
        self.error = ''
        self.samples = self.unsettled = self.clamped = self.missing_frames = 0
        self.done = threading.Event()
        self._stop = threading.Event()
        self._operator_ready = threading.Event()

    # -- control ---------------------------------------------------------------------------
    def stop(self) -> None:
        """Ask the session to stop; waits return at once."""
        self._stop.set()
        self.feedback.wake()

    def operator_ready(self) -> None:
        """Continue after the operator placed the object (physical rig)."""
        self._operator_ready.set()

    def run_safely(self) -> None:
        """Run; on an error say why, vent and stay inspectable (``state`` 'failed')."""
        try:
            self.run()
        except Stopped:
            self.state = 'stopped'
        except Exception as exc:  # a clear error, vent, keep the node alive for diagnostics
            self.error = str(exc)
            self.state = 'failed'
            self.io.log('error', f'session failed: {exc}; venting')
            try:
                self.io.send(np.zeros(len(self.limits)))
            except Exception as vent_exc:  # the transport is gone: the bridge's watchdog vents
                self.io.log('error', f'could not send the vent command: {vent_exc}')
        finally:
            self.done.set()

    # -- steps ---------------------------------------------------------------------------------
    def _sleep(self, seconds: float) -> None:
        if self._stop.wait(max(0.0, seconds)):
            raise Stopped

    def _wait_for_rig(self) -> None:
        start = time.monotonic()
        while True:
            why = self.io.rig_waiting_for()
            if not why:
                return
            if time.monotonic() - start > 5.0:
                self.io.log('warn', f'waiting for the rig: {why}')
                start = time.monotonic()
            self._sleep(0.05)

    def _send(self, pressures) -> np.ndarray:
        checked = check_command(pressures, self.limits)
        if checked.clamped:
            self.clamped += 1
            self.io.log('warn', f'command clamped at chambers {list(checked.clamped)}')
        self.io.send(checked.pressures_pa)
        return checked.pressures_pa

    def _settle(self, target, since_ns: int) -> bool:
        s = self.settings
        ok, err = self.feedback.wait_settled(target, since_ns, s.tolerance_pa,
                                             s.settle_timeout_s, self._stop)
        if not ok:
            self.io.log('warn', f'not settled within {s.settle_timeout_s:g} s (worst chamber '
                                f'off by {err:.0f} Pa): sample marked unsettled')
        return ok

    def _trigger(self, scene_id, kind: str, index: int, command, settled: bool) -> None:
        record = SampleRecord(int(self.io.now_ns()), int(scene_id), kind, int(index),
                              tuple(float(v) for v in command), bool(settled))
        self.io.trigger(record)
        self.samples += 1
        self.unsettled += 0 if settled else 1
        if self.settings.wait_for_frames:
            missing = self.feedback.wait_frames(record.stamp_ns, self.settings.frame_timeout_s,
                                                self._stop)
            if missing:
                self.missing_frames += 1
                self.io.log('warn', f'trigger {record.stamp_ns}: no frame from '
                                    f'{", ".join(missing)} within '
                                    f'{self.settings.frame_timeout_s:g} s')

    def run(self) -> None:
        """Run every scene, then vent; raises Stopped when asked to stop."""
        s, io = self.settings, self.io
        self.state = 'waiting for the rig'
        self._wait_for_rig()
        self._sleep(s.start_delay_s)
        zeros = np.zeros(len(self.limits))
        n_scenes = len(self.scenes)
        for k, scene in enumerate(self.scenes, 1):
            n = scene.actuations if s.actuations < 0 else s.actuations
            self._operator_ready.clear()     # before the state says we wait: no lost call
            self.state = f'scene {k}/{n_scenes}: rest'
            io.publish_scene(scene)
            sent = io.now_ns()
            self._send(zeros)
            if s.wait_for_operator:
                self.state = f'scene {k}/{n_scenes}: waiting for the operator'
                io.log('info', f'scene {k}/{n_scenes} (id {scene.id}): place the '
                               f'{scene.object} "{scene.label}" at {list(scene.position_m)} m, '
                               f'then call {s.next_scene_service}')
                while not self._operator_ready.is_set():
                    self._sleep(0.05)
                sent = io.now_ns()
            settled = self._settle(zeros, sent)
            self._sleep(s.rest_delay_s)
            self._trigger(scene.id, 'rest', 0, zeros, settled)
            io.log('info', f'scene {k}/{n_scenes} (id {scene.id}, {scene.object}): rest '
                           f'images, {n} actuations to go')
            next_t = time.monotonic()
            for i in range(n):
                self._sleep(next_t - time.monotonic())
                next_t = time.monotonic() + s.period_s
                self.state = f'scene {k}/{n_scenes}: sample {i + 1}/{n}'
                sent = io.now_ns()
                cmd = self._send(self.plan.next())
                settled = self._settle(cmd, sent)
                self._trigger(scene.id, 'actuation', i, cmd, settled)
                io.log('info', f'scene {k}/{n_scenes} sample {i + 1}/{n}'
                               + ('' if settled else ' (unsettled)'))
            self._sleep(next_t - time.monotonic())   # the last frame is taken before venting
            self._send(zeros)
        self._send(zeros)
        self.state = 'done'
        io.log('info', f'session done: {n_scenes} scenes, {self.samples} triggers '
                       f'({self.unsettled} unsettled); vented')
