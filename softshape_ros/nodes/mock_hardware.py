"""
The simulated rig on the real rig's topics: pressure bridge + both cameras, backed by SimRig.

Commands are checked and clamped exactly as the bridge does (check_command); six
first-order regulators follow them and the measured pressures go out at ~100 Hz. On each
trigger the pressures are sampled (and published, stamped with that instant), the
simulator is solved at them in the current scene (from the latched /rig/scene) and both
camera images go out under the trigger's stamp, with CameraInfo of the simulated pinhole
cameras and a TimeReference saying when the pressures were sampled. Each accepted command
is solved when it arrives, so a trigger once the regulators have settled on it (within
``regulator_resolution_pa``) only renders; a trigger before that is solved at its own
pressures. Between triggers both
cameras free-run at ``free_run_hz`` (0: triggers only), stamped with their capture instant,
showing the current pressures' shape. The work loop is
:class:`~softshape_ros.sim.stream.SimCameras` (core, no rclpy) in a worker thread, so the
pressure loop keeps its rate; commands, scene changes and triggers are served in arrival
order.
"""

from __future__ import annotations

import threading
import time

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, JointState, TimeReference
from std_msgs.msg import Float64MultiArray, Header, String

from softshape_ros.nodes.camera_trigger import camera_info_msg, time_reference_msg
from softshape_ros.nodes.common import (IMAGE_QOS, LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS,
                                        declare_rig_config, log_at, main_wrapper, ns_to_stamp,
                                        numpy_to_image, stamp_to_ns)
from softshape_ros.nodes.diagnostics import (ERROR, OK, WARN, Updater, fill, matched_subscribers,
                                             topic_frequency)
from softshape_ros.nodes.parameters import Param, declare
from softshape_ros.pressure import CommandError, FirstOrderRegulator, check_command
from softshape_ros.scene import Scene, SceneError
from softshape_ros.sim import SimRig
from softshape_ros.sim.stream import Frames, SimCameras
from softshape_ros.vision.camera_info import calibration_from_camera


PARAMETERS = [
    Param('tau_s', 0.05, 'regulator first-order time constant, s', (0.0, 60.0)),
    Param('regulator_resolution_pa', 150.0, 'a chamber within this of its command holds the '
          'command exactly (settled; 0 = the pure lag, never exactly there)', (0.0, 1e5)),
    Param('publish_rate_hz', 100.0, '/rig/pressure/measured rate', (0.1, 10000.0)),
    Param('pressure_noise_pa', 0.0, 'Gaussian sensor noise on the measured pressures, Pa',
          (0.0, 1e5)),
    Param('image_noise_std', 0.0, 'Gaussian pixel noise (0-255 scale) on the images',
          (0.0, 255.0)),
    Param('seed', 0, 'noise seed', (0, 2**31 - 1)),
    Param('command_timeout_s', 3.0, 'vent when no command came for this long (0 = off)',
          (0.0, 3600.0)),
    Param('max_pending_triggers', 8, 'triggers queued for the simulator beyond this are '
          'dropped', (1, 10000)),
    Param('reliable_images', True, 'as camera_trigger: offered reliable, best-effort viewers '
          'match'),
    Param('free_run_hz', 30.0, 'both cameras stream at this rate besides triggers (0 = '
          'triggers only)', (0.0, 1000.0)),
]


class MockHardware(Node):
    """Bridge + cameras stand-in: regulators, watchdog, SimRig images per trigger."""

    def __init__(self, **kwargs):
        super().__init__('mock_hardware', **kwargs)
        self.cfg = declare_rig_config(self)
        p = declare(self, PARAMETERS)
        tau_s, rate = p.tau_s, p.publish_rate_hz
        self.pressure_noise_pa = p.pressure_noise_pa
        image_noise_std, seed = p.image_noise_std, p.seed
        self.command_timeout_s = p.command_timeout_s
        max_queue, free_run_hz = p.max_pending_triggers, p.free_run_hz

        self.limits = self.cfg.max_pressures_pa
        self.regulator = FirstOrderRegulator(tau_s, len(self.limits),
                                             resolution_pa=p.regulator_resolution_pa)
        self.rng = np.random.default_rng(seed)
        self.rig = SimRig(self.cfg, seed=seed, image_noise_std=image_noise_std,
                          pressure_noise_pa=0.0)
        self.rig.set_scene(None)
        self.calibrations = {n: calibration_from_camera(n, c) for n, c in self.cfg.cameras.items()}

        t = self.cfg.topics
        self.pub_measured = self.create_publisher(JointState, t.pressure_measured, RELIABLE_QOS)
        qos = IMAGE_QOS if p.reliable_images else SENSOR_QOS
        self.pub_image, self.pub_info, self.pub_time = {}, {}, {}
        for cam in self.cfg.camera_names:
            self.pub_image[cam] = self.create_publisher(
                Image, t.camera('camera_image', cam), qos)
            self.pub_info[cam] = self.create_publisher(
                CameraInfo, t.camera('camera_info', cam), qos)
            self.pub_time[cam] = self.create_publisher(
                TimeReference, t.camera('capture_time', cam), RELIABLE_QOS)
        # The trigger subscription first: rclpy serves the subscriptions that are ready in one
        # wait in creation order, so a trigger waiting beside a newer command samples the
        # pressures before that command moves the regulators (as the trigger came first).
        self.create_subscription(Header, t.trigger, self._on_trigger, RELIABLE_QOS)
        self.create_subscription(Float64MultiArray, t.pressure_command, self._on_command,
                                 RELIABLE_QOS)
        self.create_subscription(String, t.scene, self._on_scene, LATCHED_QOS)

        self.rejected = 0
        self.clamped = 0
        self.watchdog_vents = 0
        self.last_error = ''
        self.last_command = time.monotonic()
        self._last_step = time.monotonic()
        self._lock = threading.Lock()           # the regulators: executor and camera thread
        self.cameras = SimCameras(self.rig, self._publish_frames, self._sample_free_run,
                                  free_run_hz, max_queue, self._log)
        self.cameras.warm_up(np.zeros(len(self.limits)))
        self.cameras.start()
        self.create_timer(1.0 / rate, self._tick)
        self.diagnostics = Updater(self)
        self.diagnostics.setHardwareID('simulated')
        self.diagnostics.add('pressure', self._diagnose_pressure)
        self.diagnostics.add('cameras', self._diagnose_cameras)
        self.measured_rate = topic_frequency(self.diagnostics, t.pressure_measured, rate)
        self.get_logger().info(f'simulated rig: regulators tau {tau_s:g} s, measured at '
                               f'{rate:g} Hz, cameras {", ".join(self.cfg.camera_names)} '
                               + (f'free-running at {free_run_hz:g} Hz + ' if free_run_hz
                                  else '') + 'on trigger')

    # Counters of the camera loop, as attributes (tests and diagnostics read them).
    frames = property(lambda self: self.cameras.frames)
    solver_errors = property(lambda self: self.cameras.solver_errors)
    dropped = property(lambda self: self.cameras.dropped)
    scene = property(lambda self: self.cameras.scene)

    # -- pressures --------------------------------------------------------------------------
    def _on_command(self, msg: Float64MultiArray) -> None:
        try:
            checked = check_command(msg.data, self.limits)
        except CommandError as exc:
            self.rejected += 1
            self.last_error = str(exc)
            self.get_logger().error(f'command rejected, nothing applied: {exc}')
            return
        if checked.clamped:
            self.clamped += 1
            self.get_logger().warning(f'command clamped to the limits at chambers '
                                      f'{list(checked.clamped)}')
        with self._lock:
            self._advance()
            self.regulator.setpoint = checked.pressures_pa.copy()
            self.cameras.command(checked.pressures_pa)     # in order with the triggers
        self.last_command = time.monotonic()

    def _advance(self) -> np.ndarray:
        """Step the regulators to now (hold ``_lock``)."""
        now = time.monotonic()
        p = self.regulator.step(now - self._last_step)
        self._last_step = now
        return p

    def _measure(self, stamp_ns: int) -> np.ndarray:
        with self._lock:
            p = self._advance()
        if self.pressure_noise_pa > 0:
            p = np.clip(p + self.rng.normal(0.0, self.pressure_noise_pa, p.shape), 0.0, None)
        msg = JointState()
        msg.header.stamp = ns_to_stamp(stamp_ns)
        msg.name = list(self.cfg.chamber_names)
        msg.effort = [float(v) for v in p]
        self.pub_measured.publish(msg)
        self.measured_rate.tick()
        return p

    def _tick(self) -> None:
        if (self.command_timeout_s > 0 and np.any(self.regulator.setpoint > 0)
                and time.monotonic() - self.last_command > self.command_timeout_s):
            with self._lock:
                self.regulator.setpoint[:] = 0.0
                self.cameras.command(self.regulator.setpoint)
            self.watchdog_vents += 1
            self.get_logger().warning(f'no command for {self.command_timeout_s:g} s: venting')
        self._measure(self.get_clock().now().nanoseconds)

    # -- scene and cameras ---------------------------------------------------------------------
    def _on_scene(self, msg: String) -> None:
        try:
            scene = Scene.from_json(msg.data)
        except SceneError as exc:
            self.last_error = str(exc)
            self.get_logger().error(f'scene ignored, keeping the previous one: {exc}')
            return
        self.cameras.set_scene(scene)

    def _on_trigger(self, msg: Header) -> None:
        sampled_ns = self.get_clock().now().nanoseconds
        pressures = self._measure(sampled_ns)
        self.cameras.trigger(stamp_to_ns(msg.stamp), pressures, sampled_ns)

    def _sample_free_run(self) -> tuple:
        """Return the regulators' pressures now (the shape, without sensor noise) and now."""
        sampled_ns = self.get_clock().now().nanoseconds
        with self._lock:
            return self._advance(), sampled_ns

    def _log(self, level: str, message: str) -> None:
        log_at(self, level, message)

    def _publish_frames(self, f: Frames) -> None:
        stamp = ns_to_stamp(f.stamp_ns)
        for cam in self.cfg.camera_names:
            frame_id = self.cfg.cameras[cam].frame_id
            self.pub_image[cam].publish(numpy_to_image(f.images[cam], stamp, frame_id))
            self.pub_info[cam].publish(camera_info_msg(self.calibrations[cam], stamp, frame_id))
            self.pub_time[cam].publish(time_reference_msg(stamp, f.sampled_ns, cam, frame_id))

    def _diagnose_pressure(self, stat):
        bad = self.rejected or self.clamped
        return fill(stat, WARN if bad else OK, self.last_error if self.rejected else 'regulating',
                    {'measured_pa': [round(float(v)) for v in self.regulator.pressure],
                     'rejected_commands': self.rejected, 'clamped_commands': self.clamped,
                     'watchdog_vents': self.watchdog_vents,
                     **matched_subscribers([self.pub_measured])}, 'simulated regulators')

    def _diagnose_cameras(self, stat):
        c = self.cameras
        if c.solver_errors or c.dropped:
            level = ERROR
        elif self.rejected or self.clamped:
            level = WARN
        else:
            level = OK
        return fill(stat, level, c.last_error if level == ERROR else 'simulating',
                    {'frames': c.frames, 'solver_errors': c.solver_errors,
                     'dropped_triggers': c.dropped,
                     'free_run_hz': c.free_run_hz, 'free_frames': c.free_frames,
                     'skipped_free_frames': c.clock.skipped,
                     'solves': c.solves, 'command_solves': c.command_solves,
                     'reused_shapes': c.reused,
                     'trigger_to_image_ms': c.trigger_latency.summary(),
                     'scene': c.scene.id if c.scene else None,
                     **self._matched_subscribers()}, 'SimRig')

    def _matched_subscribers(self) -> dict:
        """Return each camera writer's matched readers (what the collector's wait reads)."""
        return matched_subscribers(pub for pubs in (self.pub_image, self.pub_info, self.pub_time)
                                   for pub in pubs.values())

    def on_shutdown(self) -> None:
        self.cameras.stop()
        with self._lock:
            self.regulator.setpoint[:] = 0.0


main = main_wrapper(MockHardware)
