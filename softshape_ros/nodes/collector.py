"""
The experiment driver (paper IV-B): scenes, rest images, settled random actuations, triggers.

Per scene: publish /rig/scene (latched), vent, wait until the measured pressures are at
zero, trigger the rest images; then N actuations at ``rate_hz``, each sent, held until the
measured pressures are within ``settle_tolerance_pa`` of the command (or the timeout, which
is logged and marks the sample unsettled) and triggered. Before every trigger a JSON record
on /rig/sample says what the trigger is, so the dataset builder never has to guess. On the
physical rig it waits for the operator (``~/next_scene`` service) between scenes; it always
ends venting. With no ``session`` parameter the node waits idle.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path

import numpy as np
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.duration import Duration
from rclpy.node import Node
from sensor_msgs.msg import JointState, TimeReference
from std_msgs.msg import Float64MultiArray, Header, String
from std_srvs.srv import Trigger

from softshape_ros.pressure import CommandError, check_command, measured_in_order
from softshape_ros.nodes.common import (ERROR, LATCHED_QOS, OK, RELIABLE_QOS, WARN,
                                        declare_rig_config, diagnostic_status, main_wrapper,
                                        publish_diagnostics, stamp_to_ns)
from softshape_ros.scene import SceneError, load_session


class SessionError(ValueError):
    """A session or pressure-list file cannot be used; the message names the file."""


def load_pressure_list(path, limits_pa) -> np.ndarray:
    """
    Read the pressures to replay: YAML ``pressures_pa: [[6 x Pa], ...]`` or a CSV of rows.

    Every row goes through check_command, so a bad row fails here, before any air moves.
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

    def next(self) -> np.ndarray:
        if self.replay is not None:
            if self.used >= len(self.replay):
                raise SessionError(f'the pressure list has only {len(self.replay)} rows; the '
                                   'session needs more')
            row = self.replay[self.used]
        else:
            row = self.rng.uniform(0.0, self.high)
        self.used += 1
        return np.asarray(row, dtype=np.float64)


class Collector(Node):
    """Drive a collection session over the rig's topics from a worker thread."""

    def __init__(self, **kwargs):
        super().__init__('collector', **kwargs)
        self.cfg = declare_rig_config(self)
        par = self.declare_parameter
        col = self.cfg.collection
        session_file = str(par('session', '').value)
        alias = str(par('session_file', '').value)      # the first name, kept working
        if alias and session_file and alias != session_file:
            raise ValueError(f'session {session_file!r} and session_file {alias!r} disagree')
        session_file = session_file or alias
        mode = str(par('mode', 'random').value)
        pressures_file = str(par('pressures_file', '').value)
        seed = int(par('seed', 0).value)
        max_fraction = float(par('max_fraction', 1.0).value)
        rate = float(par('rate_hz', 0.0).value)
        self.period_s = 1.0 / (rate if rate > 0 else col.rate_hz)
        tol = float(par('settle_tolerance_pa', -1.0).value)
        self.tolerance_pa = tol if tol >= 0 else col.settle_tolerance_pa
        tout = float(par('settle_timeout_s', -1.0).value)
        self.settle_timeout_s = tout if tout >= 0 else col.settle_timeout_s
        self.rest_delay_s = float(par('rest_delay_s', 0.5).value)
        self.actuations_override = int(par('actuations', -1).value)
        # the physical rig needs a person to place each object; the mock reads /rig/scene
        self.wait_for_operator = not bool(par('simulated', True).value)
        self.start_delay_s = float(par('start_delay_s', 0.5).value)
        self.wait_for_frames = bool(par('wait_for_frames', True).value)
        self.frame_timeout_s = float(par('frame_timeout_s', 10.0).value)

        self.limits = self.cfg.max_pressures_pa
        self.scenes = []
        self.plan = None
        self.error = ''
        if session_file:
            try:
                self.scenes = load_session(session_file)
                replay = None
                if mode == 'list':
                    if not pressures_file:
                        raise SessionError('mode list needs the pressures_file parameter')
                    replay = load_pressure_list(pressures_file, self.limits)
                elif mode != 'random':
                    raise SessionError(f'mode must be random or list, got {mode!r}')
                self.plan = CommandPlan(self.limits, seed, max_fraction, replay)
            except (SceneError, SessionError) as exc:
                raise ValueError(str(exc)) from None

        t = self.cfg.topics
        self.pub_command = self.create_publisher(Float64MultiArray, t.pressure_command,
                                                 RELIABLE_QOS)
        self.pub_trigger = self.create_publisher(Header, t.trigger, RELIABLE_QOS)
        self.pub_sample = self.create_publisher(String, t.sample, RELIABLE_QOS)
        self.pub_scene = self.create_publisher(String, t.scene, LATCHED_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, t.diagnostics, RELIABLE_QOS)
        self.create_subscription(JointState, t.pressure_measured, self._on_measured,
                                 RELIABLE_QOS)
        for cam in self.cfg.camera_names:
            self.create_subscription(TimeReference, t.camera('capture_time', cam),
                                     lambda m, c=cam: self._on_frame(c, m), RELIABLE_QOS)
        self.create_service(Trigger, '~/next_scene', self._on_next_scene)
        self.create_timer(1.0, self._publish_diagnostics)

        self._cond = threading.Condition()
        self._measured = None          # (stamp_ns, np.ndarray)
        self._frames: dict = {}        # trigger stamp_ns -> cameras that answered it
        self._operator_ready = threading.Event()
        self._stop = threading.Event()
        self.state = 'idle: no session' if not self.scenes else 'starting'
        self.samples = 0
        self.unsettled = 0
        self.clamped = 0
        self.missing_frames = 0
        self.done = threading.Event()
        self.worker = None
        if self.scenes:
            self.worker = threading.Thread(target=self._run_safely, name='collector',
                                           daemon=True)
            self.worker.start()
        else:
            self.get_logger().info('no session parameter: idle (set session to a session YAML '
                                   'such as config/session_sim.yaml to collect)')

    # -- inputs ---------------------------------------------------------------------------
    def _on_measured(self, msg: JointState) -> None:
        a = measured_in_order(msg.name, msg.effort, self.cfg.chamber_names)
        if a is None:
            self.get_logger().warning(f'malformed measured pressures {list(msg.name)} '
                                      f'{list(msg.effort)}: ignored', throttle_duration_sec=5.0)
            return
        with self._cond:
            self._measured = (stamp_to_ns(msg.header.stamp), a)
            self._cond.notify_all()

    def _on_frame(self, camera: str, msg: TimeReference) -> None:
        with self._cond:
            self._frames.setdefault(stamp_to_ns(msg.header.stamp), set()).add(camera)
            while len(self._frames) > 64:
                self._frames.pop(next(iter(self._frames)))
            self._cond.notify_all()

    def _wait_frames(self, stamp_ns: int) -> None:
        """Hold the next actuation until every camera answered (the simulator can be slow)."""
        want = set(self.cfg.camera_names)
        deadline = time.monotonic() + self.frame_timeout_s
        with self._cond:
            while not want <= self._frames.get(stamp_ns, set()):
                left = deadline - time.monotonic()
                if left <= 0 or self._stop.is_set():
                    break
                self._cond.wait(min(left, 0.05))
            missing = sorted(want - self._frames.get(stamp_ns, set()))
        if self._stop.is_set():
            raise _Stopped
        if missing:
            self.missing_frames += 1
            self.get_logger().warning(f'trigger {stamp_ns}: no frame from {", ".join(missing)} '
                                      f'within {self.frame_timeout_s:g} s')

    def _on_next_scene(self, request, response):
        self._operator_ready.set()
        response.success = True
        response.message = f'continuing ({self.state})'
        return response

    # -- the session ------------------------------------------------------------------------
    def _run_safely(self) -> None:
        try:
            self._run()
        except _Stopped:
            self.state = 'stopped'
        except Exception as exc:  # a clear error, vent, stay alive for diagnostics
            self.error = str(exc)
            self.state = 'failed'
            self.get_logger().error(f'session failed: {exc}; venting')
            self._vent()
        finally:
            self.done.set()

    def _sleep(self, seconds: float) -> None:
        if self._stop.wait(max(0.0, seconds)):
            raise _Stopped

    def _wait_for_rig(self) -> None:
        start = time.monotonic()
        while True:
            with self._cond:
                have = self._measured is not None
            if have and self.pub_trigger.get_subscription_count() > 0:
                return
            if time.monotonic() - start > 5.0:
                self.get_logger().warning(
                    'waiting for the rig: ' + ('no measured pressures yet; ' if not have else '')
                    + ('nobody subscribes to the trigger'
                       if not self.pub_trigger.get_subscription_count() else ''))
                start = time.monotonic()
            self._sleep(0.05)

    def _send(self, pressures) -> np.ndarray:
        checked = check_command(pressures, self.limits)
        if checked.clamped:
            self.clamped += 1
            self.get_logger().warning(f'command clamped at chambers {list(checked.clamped)}')
        self.pub_command.publish(Float64MultiArray(data=[float(v) for v in checked.pressures_pa]))
        return checked.pressures_pa

    def _vent(self, wait_acked: bool = False) -> None:
        try:
            self.pub_command.publish(Float64MultiArray(data=[0.0] * len(self.limits)))
            if wait_acked:          # the process is about to exit: see the vent delivered
                self.pub_command.wait_for_all_acked(Duration(seconds=1.0))
        except Exception as exc:  # context gone: the bridge's watchdog and shutdown vent remain
            print(f'[collector] could not send the vent command: {exc}', file=sys.stderr)

    def _wait_settled(self, target, sent_ns: int) -> bool:
        """Wait for a measurement sampled after ``sent_ns`` within tolerance of ``target``."""
        deadline = time.monotonic() + self.settle_timeout_s
        with self._cond:
            while True:
                m = self._measured
                if m is not None and m[0] >= sent_ns and \
                        float(np.max(np.abs(m[1] - target))) <= self.tolerance_pa:
                    return True
                left = deadline - time.monotonic()
                if left <= 0 or self._stop.is_set():
                    break
                self._cond.wait(min(left, 0.05))
        if self._stop.is_set():
            raise _Stopped
        err = float(np.max(np.abs(m[1] - target))) if m is not None else float('nan')
        self.get_logger().warning(f'not settled within {self.settle_timeout_s:g} s '
                                  f'(worst chamber off by {err:.0f} Pa): sample marked unsettled')
        return False

    def _trigger(self, scene_id, kind, index, command, settled) -> int:
        now = self.get_clock().now()
        ns = now.nanoseconds
        record = {'stamp_ns': ns, 'scene_id': int(scene_id), 'kind': kind, 'index': int(index),
                  'command_pa': [float(v) for v in command], 'settled': bool(settled)}
        self.pub_sample.publish(String(data=json.dumps(record)))
        h = Header()
        h.stamp = now.to_msg()
        h.frame_id = kind
        self.pub_trigger.publish(h)
        self.samples += 1
        self.unsettled += 0 if settled else 1
        return ns

    def _after_trigger(self, stamp_ns: int) -> None:
        if self.wait_for_frames:
            self._wait_frames(stamp_ns)

    def _run(self) -> None:
        log = self.get_logger()
        self.state = 'waiting for the rig'
        self._wait_for_rig()
        self._sleep(self.start_delay_s)
        zeros = np.zeros(len(self.limits))
        S = len(self.scenes)
        for k, scene in enumerate(self.scenes, 1):
            n = scene.actuations if self.actuations_override < 0 else self.actuations_override
            self._operator_ready.clear()     # before the state says we wait: no lost call
            self.state = f'scene {k}/{S}: rest'
            self.pub_scene.publish(String(data=scene.to_json()))
            sent = time.time_ns()
            self._send(zeros)
            if self.wait_for_operator:
                self.state = f'scene {k}/{S}: waiting for the operator'
                log.info(f'scene {k}/{S} (id {scene.id}): place the {scene.object} '
                         f'"{scene.label}" at {list(scene.position_m)} m, then call '
                         f'{self.get_fully_qualified_name()}/next_scene')
                while not self._operator_ready.is_set():
                    self._sleep(0.05)
                sent = time.time_ns()
            settled = self._wait_settled(zeros, sent)
            self._sleep(self.rest_delay_s)
            self._after_trigger(self._trigger(scene.id, 'rest', 0, zeros, settled))
            log.info(f'scene {k}/{S} (id {scene.id}, {scene.object}): rest images, '
                     f'{n} actuations to go')
            next_t = time.monotonic()
            for i in range(n):
                self._sleep(next_t - time.monotonic())
                next_t = time.monotonic() + self.period_s
                self.state = f'scene {k}/{S}: sample {i + 1}/{n}'
                sent = time.time_ns()
                cmd = self._send(self.plan.next())
                settled = self._wait_settled(cmd, sent)
                self._after_trigger(self._trigger(scene.id, 'actuation', i, cmd, settled))
                log.info(f'scene {k}/{S} sample {i + 1}/{n}'
                         + ('' if settled else ' (unsettled)'))
            self._sleep(next_t - time.monotonic())   # the last frame is taken before venting
            self._send(zeros)
        self._send(zeros)
        self.state = 'done'
        log.info(f'session done: {S} scenes, {self.samples} triggers '
                 f'({self.unsettled} unsettled); vented')

    # -- status and shutdown -------------------------------------------------------------------
    def _publish_diagnostics(self) -> None:
        if self.state == 'failed':
            level, msg = ERROR, f'session failed: {self.error}'
        elif self.unsettled or self.missing_frames:
            level, msg = WARN, (f'{self.state}; {self.unsettled} sample(s) unsettled, '
                                f'{self.missing_frames} trigger(s) missing frames')
        else:
            level, msg = OK, self.state
        publish_diagnostics(self, self.pub_diag, [diagnostic_status(
            'collector', 'session', level, msg,
            {'scenes': len(self.scenes), 'triggers': self.samples, 'unsettled': self.unsettled,
             'clamped_commands': self.clamped, 'missing_frames': self.missing_frames,
             'tolerance_pa': self.tolerance_pa, 'settle_timeout_s': self.settle_timeout_s,
             'period_s': self.period_s})])

    def on_shutdown(self) -> None:
        self._stop.set()
        if self.worker is not None:
            self.worker.join(timeout=5.0)
        self._vent(wait_acked=True)


class _Stopped(Exception):
    """The node is shutting down: leave the session loop."""


main = main_wrapper(Collector)
