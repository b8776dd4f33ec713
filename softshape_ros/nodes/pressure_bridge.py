"""
The bridge between /rig/pressure/command and the Arduino Due that drives the six regulators.

Commands are checked by the shared gate (check_command: six finite, non-negative values,
clamped to the lower of rig.yaml, this node's ``max_pressure_pa`` and the firmware's own
limits) and sent over a CRC-framed serial link (softshape_ros.hardware.link). Measured
pressures come back stamped with the Due's sampling time mapped onto ROS time. No command
for ``watchdog_timeout_s``: vent. No Due: diagnostics ERROR and reconnect with backoff;
after a reconnect nothing is applied until a fresh command arrives. Shutdown vents.
"""

from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import SetBool, Trigger

from softshape_ros.hardware import protocol as P
from softshape_ros.hardware.link import DueLink, LinkDown
from softshape_ros.pressure import CommandError, check_command
from softshape_ros.nodes.common import (ERROR, OK, RELIABLE_QOS, WARN, declare_rig_config,
                                        diagnostic_status, main_wrapper, ns_to_stamp,
                                        publish_diagnostics)


class PressureBridge(Node):
    """Thin adapter: ROS topics and services <-> DueLink."""

    def __init__(self, **kwargs):
        super().__init__('pressure_bridge', **kwargs)
        self.cfg = declare_rig_config(self)
        par = self.declare_parameter
        self.port = str(par('port', '/dev/ttyACM0').value)
        baud = int(par('baud', 115200).value)
        cfg_lim = [float(x) for x in self.cfg.max_pressures_pa]
        lim = [float(x) for x in par('max_pressure_pa', cfg_lim).value]
        if len(lim) != len(cfg_lim):
            raise ValueError(f'max_pressure_pa needs {len(cfg_lim)} values, got {len(lim)}')
        if any(a > b for a, b in zip(lim, cfg_lim)):
            self.get_logger().warn(f'max_pressure_pa {lim} exceeds {self.cfg.source} limits '
                                   f'{cfg_lim}; a parameter may only lower them')
        self.limits = [min(a, b) for a, b in zip(lim, cfg_lim)]
        self.watchdog_timeout_s = float(par('watchdog_timeout_s', 3.0).value)
        fw_watchdog_s = float(par('firmware_watchdog_s', 0.5).value)
        link_timeout_s = float(par('link_timeout_s', 0.5).value)
        state_rate = int(par('state_rate_hz', 100).value)
        diag_period = float(par('diagnostics_period_s', 1.0).value)
        self.frame_id = str(par('frame_id', 'due').value)
        self.ack_wait_s = link_timeout_s     # as long as silence takes to count as link loss
        # The firmware's CONFIG frame carries these as u16; check them here with a clear message.
        for name, value, lo, hi in (('firmware_watchdog_s', fw_watchdog_s, 0.02, 10.0),
                                    ('state_rate_hz', state_rate, 1, 1000),
                                    ('watchdog_timeout_s', self.watchdog_timeout_s, 0.05, 600.0),
                                    ('link_timeout_s', link_timeout_s, 0.05, 60.0)):
            if not lo <= value <= hi:
                raise ValueError(f'parameter {name} = {value} is outside [{lo}, {hi}]')

        t = self.cfg.topics
        self.names = list(self.cfg.chamber_names)
        self.pub_measured = self.create_publisher(JointState, t.pressure_measured, RELIABLE_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, t.diagnostics, 10)
        self.create_subscription(Float64MultiArray, t.pressure_command, self._on_command,
                                 RELIABLE_QOS)
        self.create_service(Trigger, '~/vent', self._on_vent)
        self.create_service(SetBool, '~/enable', self._on_enable)

        self.enabled = True
        self.active = False              # a command is applied and the watchdog is running
        self.last_command = 0.0
        self.counts = {'commands': 0, 'rejected': 0, 'clamped': 0, 'not_applied': 0,
                       'watchdog_vents': 0, 'measured': 0}
        self.last_reject = ''
        self.last_event = ''
        self.link = DueLink(self.port, self.limits, baud=baud, state_rate_hz=state_rate,
                            fw_watchdog_s=fw_watchdog_s, stale_timeout_s=link_timeout_s,
                            clock_ns=lambda: self.get_clock().now().nanoseconds,
                            on_state=self._on_state, on_event=self._on_event)
        self.link.start()
        self.create_timer(0.05, self._watchdog)
        self.create_timer(diag_period, self._publish_diagnostics)
        self.get_logger().info(f'pressure bridge on {self.port} @ {baud}, limits '
                               f'{[round(x) for x in self.limits]} Pa, watchdog '
                               f'{self.watchdog_timeout_s} s')

    # ------------------------------------------------------------------ link callbacks
    def _on_event(self, level: str, text: str) -> None:
        self.last_event = text
        # rclpy wants one severity per call site
        if level == 'info':
            self.get_logger().info(text)
        elif level == 'warn':
            self.get_logger().warn(text)
        else:
            self.get_logger().error(text)

    def _on_state(self, m) -> None:
        msg = JointState()
        msg.header.stamp = ns_to_stamp(m.stamp_ns)
        msg.header.frame_id = self.frame_id
        msg.name = self.names
        msg.effort = [float(x) for x in m.pressures_pa]
        self.pub_measured.publish(msg)
        self.counts['measured'] += 1

    # ------------------------------------------------------------------ commands
    def _reject(self, why: str) -> None:
        self.counts['rejected'] += 1
        self.last_reject = why
        self.get_logger().error(f'pressure command rejected: {why}', throttle_duration_sec=1.0)

    def _on_command(self, msg: Float64MultiArray) -> None:
        if not self.enabled:
            self._reject('output disabled (call ~/enable true, then command again)')
            return
        try:
            checked = check_command(msg.data, self.link.limits_pa)
        except CommandError as exc:
            self._reject(str(exc))
            return
        if checked.clamped:
            self.counts['clamped'] += 1
            self.get_logger().warn(
                f'pressure command clamped at chambers {list(checked.clamped)} to '
                f'{[round(x) for x in checked.pressures_pa]} Pa', throttle_duration_sec=1.0)
        try:
            self.link.send_command(checked.pressures_pa)
        except (LinkDown, ValueError) as exc:
            self.counts['not_applied'] += 1
            self.get_logger().warn(f'pressure command not applied: {exc}',
                                   throttle_duration_sec=1.0)
            return
        self.counts['commands'] += 1
        self.last_command = time.monotonic()
        self.active = True

    def _vent(self, why: str) -> tuple[bool, str]:
        self.active = False
        try:
            ok = self.link.wait_ack(self.link.vent(), self.ack_wait_s)
        except LinkDown as exc:
            return False, f'{why}: cannot vent, {exc} (the firmware watchdog vents on its own)'
        return ok, (f'{why}: vented' if ok else
                    f'{why}: vent sent, not acknowledged in {self.ack_wait_s} s')

    def _watchdog(self) -> None:
        self.link.kick()        # the executor is alive: heartbeats may keep the firmware fed
        if self.active and time.monotonic() - self.last_command > self.watchdog_timeout_s:
            self.counts['watchdog_vents'] += 1
            ok, text = self._vent(f'no command for {self.watchdog_timeout_s} s')
            if ok:
                self.get_logger().warn(text)
            else:
                self.get_logger().error(text)

    def _on_vent(self, request, response):
        response.success, response.message = self._vent('vent requested')
        self.get_logger().warn(response.message)
        return response

    def _on_enable(self, request, response):
        self.enabled = bool(request.data)
        if self.enabled:
            response.success, response.message = True, 'output enabled; waiting for a command'
        else:
            ok, text = self._vent('output disabled')
            response.success, response.message = ok, text
        self.get_logger().info(response.message)
        return response

    # ------------------------------------------------------------------ diagnostics
    def _publish_diagnostics(self) -> None:
        st = self.link.status()
        flags = self.link.last_flags
        if not st['connected']:
            level, text = ERROR, f'Due link down: {st["last_error"]}'
        elif flags & P.F_FAULT:
            level, text = ERROR, 'Due reports a pressure feedback fault'
        elif flags & P.F_WATCHDOG:
            level, text = WARN, 'firmware watchdog vented'
        elif not self.enabled:
            level, text = WARN, 'output disabled'
        elif self.counts['rejected'] or self.counts['clamped'] or flags & P.F_CLAMPED:
            level, text = WARN, 'connected; commands rejected or clamped (see values)'
        else:
            level, text = OK, 'connected'
        values = dict(st)
        values.update(self.counts)
        values.update({'enabled': self.enabled, 'active': self.active,
                       'last_reject': self.last_reject, 'last_event': self.last_event,
                       'watchdog_timeout_s': self.watchdog_timeout_s})
        publish_diagnostics(self, self.pub_diag, [diagnostic_status(
            f'{self.get_name()}: Due link', self.port, level, text, values)])

    def on_shutdown(self) -> None:
        """Vent, then close the port (run_node calls this on SIGINT/SIGTERM)."""
        vented = self.link.close(vent=True)
        msg = 'shutdown: vented' if vented else 'shutdown: could not vent (link down)'
        print(f'[pressure_bridge] {msg}', flush=True)


main = main_wrapper(PressureBridge)
