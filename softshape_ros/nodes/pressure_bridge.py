"""
The bridge between /rig/pressure/command and the Arduino Due that drives the six regulators.

A managed (lifecycle) node: *configure* opens the port and handshakes (fails, back to
unconfigured, if no Due answers within ``connect_timeout_s``), *activate* accepts commands,
*deactivate* and *shutdown* vent, *cleanup* vents and closes. Commands are checked by the
shared gate (check_command: six finite, non-negative values, clamped to the lower of
rig.yaml, ``max_pressure_pa`` and the firmware's own limits) and sent over a CRC-framed
serial link (softshape_ros.hardware.link). ``max_pressure_pa`` may be lowered at run time
(the Due is told too); a raise is refused with its reason. Measured pressures come back
stamped with the Due's sampling time mapped onto ROS time. No command for
``watchdog_timeout_s`` (steady time): vent. A lost link: diagnostics ERROR and reconnect
with backoff; after a reconnect nothing is applied until a fresh command arrives.
"""

from __future__ import annotations

import time

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from softshape_ros.hardware import protocol as P
from softshape_ros.hardware.link import DueLink, LinkDown
from softshape_ros.pressure import CommandError, check_command
from softshape_ros.nodes.clocks import ros_now_ns, steady_timer
from softshape_ros.nodes.common import RELIABLE_QOS, declare_rig_config, main_wrapper, ns_to_stamp
from softshape_ros.nodes.diagnostics import (ERROR, OK, WARN, Updater, fill,
                                             matched_subscribers, topic_frequency)
from softshape_ros.nodes.parameters import Param, declare


def parameters(cfg) -> list[Param]:
    """List what the bridge takes (limits default to rig.yaml's)."""
    limits = [float(x) for x in cfg.max_pressures_pa]
    return [
        Param('port', '/dev/ttyACM0', "the Due's serial port (a by-id symlink is steadier)"),
        Param('baud', 115200, 'baud rate (ignored by the native USB port)', (1200, 4_000_000)),
        Param('max_pressure_pa', limits, 'per-chamber limit, Pa; may only lower rig.yaml '
              'limits, and only be lowered at run time', (1.0, 1e6), live=True,
              length=len(limits)),
        Param('watchdog_timeout_s', 3.0, 'no command for this long (steady time): vent',
              (0.05, 600.0), live=True),
        Param('firmware_watchdog_s', 0.5, 'the Due vents by itself if the host is silent '
              'this long', (0.02, 10.0)),
        Param('link_timeout_s', 0.5, 'no state frame for this long = link lost, reconnect',
              (0.05, 60.0)),
        Param('connect_timeout_s', 5.0, 'configure fails if no Due handshakes in this time',
              (0.1, 120.0)),
        Param('state_rate_hz', 100, '/rig/pressure/measured rate (the Due streams at it)',
              (1, 1000)),
    ]


class PressureBridge(LifecycleNode):
    """Thin adapter: ROS topics, services and lifecycle transitions <-> DueLink."""

    def __init__(self, **kwargs):
        super().__init__('pressure_bridge', **kwargs)
        self._refuse_unavailable_transitions()
        self.cfg = declare_rig_config(self)
        self.params = declare(self, parameters(self.cfg), check=self._check_params,
                              apply=self._apply_params)
        cfg_lim = [float(x) for x in self.cfg.max_pressures_pa]
        lim = list(self.params.max_pressure_pa)
        if any(a > b for a, b in zip(lim, cfg_lim)):
            self.get_logger().warning(f'max_pressure_pa {lim} exceeds {self.cfg.source} limits '
                                      f'{cfg_lim}; a parameter may only lower them')
        self.limits = [min(a, b) for a, b in zip(lim, cfg_lim)]
        self.port = self.params.port
        self.ack_wait_s = self.params.link_timeout_s   # as long as silence means link loss
        self.names = list(self.cfg.chamber_names)
        t = self.cfg.topics

        self.link: DueLink | None = None
        self.lifecycle = 'unconfigured'  # mirrors the state machine's primary state
        self.config_error = ''
        self.active = False              # lifecycle state active: commands are accepted
        self.holding = False             # a command is applied and the watchdog is running
        self.last_command = 0.0
        self.counts = {'commands': 0, 'rejected': 0, 'clamped': 0, 'not_applied': 0,
                       'watchdog_vents': 0, 'measured': 0}
        self.last_reject = ''
        self.last_event = ''
        self.pub_measured = self.create_publisher(JointState, t.pressure_measured, RELIABLE_QOS)
        self.create_subscription(Float64MultiArray, t.pressure_command, self._on_command,
                                 RELIABLE_QOS)
        self.create_service(Trigger, '~/vent', self._on_vent)
        steady_timer(self, 0.05, self._watchdog)

        self.diagnostics = Updater(self)
        self.diagnostics.setHardwareID(self.port)
        self.diagnostics.add('Due link', self._diagnose_link)
        self.measured_rate = topic_frequency(self.diagnostics, t.pressure_measured,
                                             float(self.params.state_rate_hz))
        self.get_logger().info(f'pressure bridge for {self.port}: unconfigured (configure '
                               'opens the port, activate accepts commands)')

    # ------------------------------------------------------------------ lifecycle
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Open the port and handshake; fail (and close) if no Due answers in time."""
        p = self.params
        self.link = DueLink(self.port, self.limits, baud=p.baud, state_rate_hz=p.state_rate_hz,
                            fw_watchdog_s=p.firmware_watchdog_s,
                            stale_timeout_s=p.link_timeout_s,
                            clock_ns=lambda: ros_now_ns(self),
                            on_state=self._on_state, on_event=self._on_event)
        self.link.start()
        if not self.link.wait_connected(p.connect_timeout_s):
            why = self.link.last_error
            self.link.close(vent=False)
            self.get_logger().error(f'configure failed: no Due handshake on {self.port} in '
                                    f'{p.connect_timeout_s:g} s ({why})')
            self.link, self.config_error = None, f'Due link down: {why}'
            self.diagnostics.force_update()
            return TransitionCallbackReturn.FAILURE
        self.config_error = ''
        self.lifecycle = 'inactive'
        self.get_logger().info(f'configured: Due on {self.port}, limits '
                               f'{[round(x) for x in self.link.limits_pa]} Pa, watchdog '
                               f'{p.watchdog_timeout_s} s')
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Accept commands from now on (the Due sits vented until one arrives)."""
        self.active, self.lifecycle = True, 'active'
        self.get_logger().info('active: accepting pressure commands')
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop accepting commands and vent."""
        self.active, self.lifecycle = False, 'inactive'
        ok, text = self._vent('deactivated')
        self._log(ok, text)
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Vent and close the port."""
        self._close('cleanup')
        self.lifecycle = 'unconfigured'
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState | None = None) -> TransitionCallbackReturn:
        """
        Vent, then close the port: the lifecycle shutdown transition.

        run_node also calls ``on_shutdown()`` (no state) on SIGINT/SIGTERM; that takes the
        node through the lifecycle shutdown transition, which lands here again.
        """
        if state is None:
            if self.lifecycle != 'finalized':
                self.trigger_shutdown()
            return TransitionCallbackReturn.SUCCESS
        self.active, self.lifecycle = False, 'finalized'
        self._close('shutdown')
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Vent and close after a transition raised (back to unconfigured)."""
        self.get_logger().error(f'lifecycle error in {state.label}: venting and closing')
        self.active, self.lifecycle = False, 'unconfigured'
        self._close('error')
        return TransitionCallbackReturn.SUCCESS

    def _close(self, why: str) -> None:
        if self.link is None:
            return
        connected = self.link.connected
        vented = self.link.close(vent=True, timeout=self.ack_wait_s)
        self.link, self.holding = None, False
        if vented:
            self.get_logger().info(f'{why}: vented')
        elif connected:
            self.get_logger().error(f'{why}: vent not acknowledged (the firmware watchdog '
                                    'vents on its own)')
        else:
            self.get_logger().warning(f'{why}: could not vent (link down; the firmware '
                                      'watchdog vents on its own)')

    # ------------------------------------------------------------------ parameters
    def _check_params(self, changes: dict) -> str:
        new = changes.get('max_pressure_pa')
        if new is None:
            return ''
        raised = [(i, old, v) for i, (old, v) in enumerate(zip(self.limits, new)) if v > old]
        if raised:
            i, old, v = raised[0]
            return (f'max_pressure_pa may only be lowered at run time: chamber {i} from '
                    f'{old:g} to {v:g} Pa refused')
        return ''

    def _apply_params(self, changes: dict) -> None:
        if 'max_pressure_pa' in changes:
            self.limits = [min(a, b) for a, b in zip(self.limits, changes['max_pressure_pa'])]
            if self.link is not None:
                try:
                    seq = self.link.lower_limits(self.limits)
                except LinkDown as exc:
                    seq = None
                    self.get_logger().warning(f'limits lowered here; the Due gets them at the '
                                              f'next handshake ({exc})')
                if seq is not None and not self.link.wait_ack(seq, self.ack_wait_s):
                    self.get_logger().warning('the Due did not acknowledge the lowered limits '
                                              'yet (the host clamps to them already)')
            self.get_logger().warning(f'limits lowered to {[round(x) for x in self.limits]} Pa')
        if 'watchdog_timeout_s' in changes:
            self.get_logger().info(f'watchdog {changes["watchdog_timeout_s"]:g} s')

    # ------------------------------------------------------------------ link callbacks
    def _on_event(self, level: str, text: str) -> None:
        self.last_event = text
        # rclpy wants one severity per call site
        if level == 'info':
            self.get_logger().info(text)
        elif level == 'warn':
            self.get_logger().warning(text)
        else:
            self.get_logger().error(text)

    def _on_state(self, m) -> None:
        msg = JointState()
        msg.header.stamp = ns_to_stamp(m.stamp_ns)
        msg.name = self.names            # pressures are not in a TF frame: frame_id stays ''
        msg.effort = [float(x) for x in m.pressures_pa]
        self.pub_measured.publish(msg)
        self.measured_rate.tick()
        self.counts['measured'] += 1

    # ------------------------------------------------------------------ commands
    def _reject(self, why: str) -> None:
        self.counts['rejected'] += 1
        self.last_reject = why
        self.get_logger().error(f'pressure command rejected: {why}', throttle_duration_sec=1.0)

    def _on_command(self, msg: Float64MultiArray) -> None:
        link = self.link
        if not self.active or link is None:
            self._reject('the bridge is not active (lifecycle: configure, then activate)')
            return
        try:
            checked = check_command(msg.data, [min(a, b) for a, b in
                                               zip(self.limits, link.limits_pa)])
        except CommandError as exc:
            self._reject(str(exc))
            return
        if checked.clamped:
            self.counts['clamped'] += 1
            self.get_logger().warning(
                f'pressure command clamped at chambers {list(checked.clamped)} to '
                f'{[round(x) for x in checked.pressures_pa]} Pa', throttle_duration_sec=1.0)
        try:
            link.send_command(checked.pressures_pa)
        except (LinkDown, ValueError) as exc:
            self.counts['not_applied'] += 1
            self.get_logger().warning(f'pressure command not applied: {exc}',
                                      throttle_duration_sec=1.0)
            return
        self.counts['commands'] += 1
        self.last_command = time.monotonic()
        self.holding = True

    def _vent(self, why: str) -> tuple[bool, str]:
        self.holding = False
        link = self.link
        if link is None:
            return False, f'{why}: not configured, no port open (nothing to vent through)'
        try:
            ok = link.wait_ack(link.vent(), self.ack_wait_s)
        except LinkDown as exc:
            return False, f'{why}: cannot vent, {exc} (the firmware watchdog vents on its own)'
        return ok, (f'{why}: vented' if ok else
                    f'{why}: vent sent, not acknowledged in {self.ack_wait_s} s')

    def _log(self, ok: bool, text: str) -> None:
        if ok:
            self.get_logger().warning(text)
        else:
            self.get_logger().error(text)

    def _watchdog(self) -> None:
        link = self.link
        if link is None:
            return
        link.kick()             # the executor is alive: heartbeats may keep the firmware fed
        timeout = self.params.watchdog_timeout_s
        if self.holding and time.monotonic() - self.last_command > timeout:
            self.counts['watchdog_vents'] += 1
            self._log(*self._vent(f'no command for {timeout:g} s'))

    def _on_vent(self, request, response):
        response.success, response.message = self._vent('vent requested')
        self.get_logger().warning(response.message)
        return response

    # ------------------------------------------------------------------ diagnostics
    def _diagnose_link(self, stat):
        link, lifecycle = self.link, self.lifecycle
        if link is None:
            values = {'lifecycle': lifecycle, 'port': self.port,
                      'limits_pa': [round(x) for x in self.limits],
                      **matched_subscribers([self.pub_measured])}
            if self.config_error:
                return fill(stat, ERROR, f'{self.config_error} (configure failed)', values)
            return fill(stat, WARN, f'{lifecycle}: port closed', values)
        st = link.status()
        flags = link.last_flags
        if not st['connected']:
            level, text = ERROR, f'Due link down: {st["last_error"]}'
        elif flags & P.F_FAULT:
            level, text = ERROR, 'Due reports a pressure feedback fault'
        elif flags & P.F_WATCHDOG:
            level, text = WARN, 'firmware watchdog vented'
        elif not self.active:
            level, text = WARN, f'{lifecycle}: connected, not accepting commands'
        elif self.counts['rejected'] or self.counts['clamped'] or flags & P.F_CLAMPED:
            level, text = WARN, 'connected; commands rejected or clamped (see values)'
        else:
            level, text = OK, 'connected'
        values = dict(st)
        values.update(self.counts)
        values.update({'lifecycle': lifecycle, 'holding': self.holding,
                       'last_reject': self.last_reject, 'last_event': self.last_event,
                       'watchdog_timeout_s': self.params.watchdog_timeout_s,
                       **matched_subscribers([self.pub_measured])})
        return fill(stat, level, text, values)

    def _refuse_unavailable_transitions(self) -> None:
        """
        Answer a transition the current state does not offer with success=False, as rclcpp does.

        rclpy's own change_state handler raises on it (ros2/rclpy#1209, fixed upstream by
        #1319 but not in every Jazzy build), and the exception ends the node: a repeated
        ``ros2 lifecycle set configure``, or a client resending a request whose answer was
        lost, vented and killed the bridge.
        """
        service = self._service_change_state
        handle = service.callback

        def change_state(request, response):
            t = request.transition
            offered = [d[0] for d in self._state_machine.available_transitions]
            if not t.label and t.id not in offered:
                state = self._state_machine.current_state[1]
                self.get_logger().warning(
                    f'transition {t.id} is not available in state {state}: refused')
                response.success = False
                return response
            return handle(request, response)
        service.callback = change_state


main = main_wrapper(PressureBridge)
