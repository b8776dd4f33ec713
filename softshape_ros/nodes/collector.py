"""
The experiment driver (paper IV-B): scenes, rest images, settled random actuations, triggers.

Parameters in, :class:`softshape_ros.session.CollectionSession` run on a worker thread,
messages out: the node feeds measured pressures and camera capture times into the
session's :class:`~softshape_ros.session.RigFeedback` and publishes what the session asks
for (commands, the latched scene, a JSON record on /rig/sample before each trigger, the
trigger). On the physical rig it waits for the operator (``~/next_scene`` service) between
scenes; it always ends venting. With no ``session`` parameter the node waits idle.
"""

from __future__ import annotations

import threading

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.duration import Duration
from rclpy.node import Node
from sensor_msgs.msg import JointState, TimeReference
from std_msgs.msg import Float64MultiArray, Header, String
from std_srvs.srv import Trigger

from softshape_ros.nodes.common import (LATCHED_QOS, RELIABLE_QOS, declare_rig_config,
                                        log_at, main_wrapper, ns_to_stamp,
                                        stamp_to_ns)
from softshape_ros.nodes.diagnostics import (ERROR, OK, WARN, Updater, fill, subscribers_topic,
                                             writers_matched)
from softshape_ros.nodes.parameters import Param, declare
from softshape_ros.scene import SceneError, load_session
from softshape_ros.session import (CollectionSession, CommandPlan, SampleRecord, SessionError,
                                   SessionSettings, RigFeedback)

_IDLE_DONE = threading.Event()

PARAMETERS = [
    Param('session', '', "a session YAML listing the scenes ('' = wait idle)"),
    Param('session_file', '', 'the first name of `session`, kept working'),
    Param('simulated', True, 'false (physical rig): wait for ~/next_scene before each scene'),
    Param('mode', 'random', 'random (uniform within the limits, seeded) or list (replay)',
          choices=('random', 'list')),
    Param('pressures_file', '', 'list mode: YAML {pressures_pa: [[6 x Pa], ...]} or CSV rows'),
    Param('seed', 0, 'random mode seed', (0, 2**31 - 1)),
    Param('max_fraction', 1.0, 'random commands in [0, max_fraction * chamber limit]',
          (1e-6, 1.0)),
    Param('actuations', -1, "per scene; -1 = each scene's own", (-1, 10**6)),
    Param('rate_hz', 0.0, 'actuations per second; 0 = rig.yaml collection.rate_hz',
          (0.0, 1000.0)),
    Param('settle_tolerance_pa', -1.0, 'settled: every chamber this close to the command; '
          '< 0 = rig.yaml', (-1.0, 1e6)),
    Param('settle_timeout_s', -1.0, 'give up settling after this (steady time); < 0 = rig.yaml',
          (-1.0, 3600.0)),
    Param('rest_delay_s', 0.5, 'after venting, before the rest trigger', (0.0, 3600.0)),
    Param('start_delay_s', 0.5, 'after the rig is seen, before the first scene', (0.0, 3600.0)),
    Param('wait_for_frames', True, 'hold the next actuation until every camera answered'),
    Param('frame_timeout_s', 10.0, '... or this long (logged, counted in diagnostics)',
          (0.0, 3600.0)),
    Param('recorder', '', "a recorder node's name ('' = none): the first scene waits until "
          'it subscribes to the command, trigger and sample topics and they have matched it'),
    Param('wait_rig_writers', True, 'with `recorder`: also until the recorder subscribes to the '
          "measured pressures and every camera topic, and their writers' /diagnostics say "
          "(subscribers <topic>) they matched every reader; false for drivers that do not"),
]


class Collector(Node):
    """Drive a collection session over the rig's topics from a worker thread."""

    def __init__(self, **kwargs):
        super().__init__('collector', **kwargs)
        self.cfg = declare_rig_config(self)
        p = declare(self, PARAMETERS)
        col = self.cfg.collection
        session_file = p.session
        if p.session_file and session_file and p.session_file != session_file:
            raise ValueError(f'session {session_file!r} and session_file {p.session_file!r} '
                             'disagree')
        session_file = session_file or p.session_file
        self.limits = self.cfg.max_pressures_pa
        self.settings = SessionSettings(
            period_s=1.0 / (p.rate_hz if p.rate_hz > 0 else col.rate_hz),
            tolerance_pa=(p.settle_tolerance_pa if p.settle_tolerance_pa >= 0
                          else col.settle_tolerance_pa),
            settle_timeout_s=(p.settle_timeout_s if p.settle_timeout_s >= 0
                              else col.settle_timeout_s),
            rest_delay_s=p.rest_delay_s, start_delay_s=p.start_delay_s,
            actuations=p.actuations,
            # the physical rig needs a person to place each object; the mock reads /rig/scene
            wait_for_operator=not p.simulated,
            wait_for_frames=p.wait_for_frames, frame_timeout_s=p.frame_timeout_s,
            next_scene_service=f'{self.get_fully_qualified_name()}/next_scene')
        self.recorder = p.recorder
        t = self.cfg.topics
        # Topics others write that the recorder must get from the first frame, and what
        # their writers last said of their matched readers: status name -> key -> value.
        self.rig_topics = [t.pressure_measured] + [
            t.camera(name, cam) for cam in self.cfg.camera_names
            for name in ('camera_image', 'camera_info', 'capture_time')
        ] if self.recorder and p.wait_rig_writers else []
        self._writers_said: dict[str, dict[str, str]] = {}
        self.feedback = RigFeedback(self.cfg.chamber_names, self.cfg.camera_names)
        self.session = None
        if session_file:
            try:
                scenes = load_session(session_file)
                plan = CommandPlan.from_mode(p.mode, self.limits, p.seed, p.max_fraction,
                                             p.pressures_file)
            except (SceneError, SessionError) as exc:
                raise ValueError(str(exc)) from None
            self.session = CollectionSession(scenes, plan, self.settings, self, self.feedback,
                                             self.limits)

        self.pub_command = self.create_publisher(Float64MultiArray, t.pressure_command,
                                                 RELIABLE_QOS)
        self.pub_trigger = self.create_publisher(Header, t.trigger, RELIABLE_QOS)
        self.pub_sample = self.create_publisher(String, t.sample, RELIABLE_QOS)
        self.pub_scene = self.create_publisher(String, t.scene, LATCHED_QOS)
        self.create_subscription(JointState, t.pressure_measured, self._on_measured,
                                 RELIABLE_QOS)
        for cam in self.cfg.camera_names:
            self.create_subscription(
                TimeReference, t.camera('capture_time', cam),
                lambda m, c=cam: self.feedback.add_frame(c, stamp_to_ns(m.header.stamp)),
                RELIABLE_QOS)
        self.create_service(Trigger, '~/next_scene', self._on_next_scene)
        if self.rig_topics:
            self.create_subscription(DiagnosticArray, t.diagnostics, self._on_diagnostics,
                                     RELIABLE_QOS)
        self.diagnostics = Updater(self)
        self.diagnostics.setHardwareID('none')
        self.diagnostics.add('session', self._diagnose)

        self.worker = None
        if self.session is not None:
            self.worker = threading.Thread(target=self.session.run_safely, name='collector',
                                           daemon=True)
            self.worker.start()
        else:
            self.get_logger().info('no session parameter: idle (set session to a session YAML '
                                   'such as config/session_sim.yaml to collect)')

    # -- what the session reads ------------------------------------------------------------
    @property
    def state(self) -> str:
        return self.session.state if self.session is not None else 'idle: no session'

    @property
    def done(self) -> threading.Event:
        """Set when the session ended (done, failed or stopped)."""
        return self.session.done if self.session is not None else _IDLE_DONE

    @property
    def samples(self) -> int:
        return self.session.samples if self.session is not None else 0

    @property
    def unsettled(self) -> int:
        return self.session.unsettled if self.session is not None else 0

    def _on_measured(self, msg: JointState) -> None:
        if not self.feedback.add_measured(stamp_to_ns(msg.header.stamp), msg.name, msg.effort):
            self.get_logger().warning(f'malformed measured pressures {list(msg.name)} '
                                      f'{list(msg.effort)}: ignored', throttle_duration_sec=5.0)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            said = {kv.key: kv.value for kv in status.values
                    if subscribers_topic(kv.key) in self.rig_topics}
            if said:
                self._writers_said[status.name] = said

    def _on_next_scene(self, request, response):
        if self.session is not None:
            self.session.operator_ready()
        response.success = True
        response.message = f'continuing ({self.state})'
        return response

    # -- RigIO: what the session asks for ---------------------------------------------------
    def now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def rig_waiting_for(self) -> str:
        missing = []
        if not self.feedback.has_measured:
            missing.append('no measured pressures yet')
        if self.pub_trigger.get_subscription_count() == 0:
            missing.append('nobody subscribes to the trigger')
        if self.recorder:
            missing += self._recorder_missing()
        return '; '.join(missing)

    def _recorder_missing(self) -> list[str]:
        """
        Say which topics the recorder does not yet take everything from.

        The graph shows its subscription before the writer has matched it, and a message
        published in between is not in the bag: so each writer must have matched every
        reader the graph shows (one that never matches, say of an incompatible QoS, keeps
        the session waiting, logged every 5 s). Ours we ask; the rig's writers (the Due
        bridge's measured pressures, the cameras) say it on /diagnostics, at its period.
        """
        out = []
        for pub in (self.pub_command, self.pub_trigger, self.pub_sample):
            readers = self.get_subscriptions_info_by_topic(pub.topic_name)
            matched = pub.get_subscription_count()
            if not any(r.node_name == self.recorder for r in readers):
                out.append(f'{self.recorder} does not subscribe to {pub.topic_name}')
            elif matched < len(readers):
                out.append(f'{pub.topic_name}: {len(readers)} subscribers, {matched} matched')
        said = dict(self._writers_said)
        for topic in self.rig_topics:
            readers = self.get_subscriptions_info_by_topic(topic)
            counts = writers_matched(said, topic)
            if not any(r.node_name == self.recorder for r in readers):
                out.append(f'{self.recorder} does not subscribe to {topic}')
            elif not counts:
                out.append(f'{topic}: no writer says on /diagnostics whom it matched')
            elif min(counts) < len(readers):
                out.append(f'{topic}: {len(readers)} subscribers, {min(counts)} matched by '
                           'its writer')
        return out

    def send(self, pressures_pa) -> None:
        self.pub_command.publish(Float64MultiArray(data=[float(v) for v in pressures_pa]))

    def publish_scene(self, scene) -> None:
        self.pub_scene.publish(String(data=scene.to_json()))

    def trigger(self, record: SampleRecord) -> None:
        self.pub_sample.publish(String(data=record.to_json()))
        h = Header()
        h.stamp = ns_to_stamp(record.stamp_ns)
        h.frame_id = record.kind
        self.pub_trigger.publish(h)

    def log(self, level: str, text: str) -> None:
        log_at(self, level, text)

    # -- status and shutdown -------------------------------------------------------------------
    def _diagnose(self, stat):
        s = self.session
        if s is None:
            return fill(stat, OK, self.state, {'scenes': 0})
        if s.state == 'failed':
            level, msg = ERROR, f'session failed: {s.error}'
        elif s.unsettled or s.missing_frames:
            level, msg = WARN, (f'{s.state}; {s.unsettled} sample(s) unsettled, '
                                f'{s.missing_frames} trigger(s) missing frames')
        else:
            level, msg = OK, s.state
        return fill(stat, level, msg, {
            'scenes': len(s.scenes), 'triggers': s.samples, 'unsettled': s.unsettled,
            'clamped_commands': s.clamped, 'missing_frames': s.missing_frames,
            'tolerance_pa': self.settings.tolerance_pa,
            'settle_timeout_s': self.settings.settle_timeout_s,
            'period_s': self.settings.period_s})

    def on_shutdown(self) -> None:
        """Stop the session and vent, waiting until the vent is delivered."""
        if self.session is not None:
            self.session.stop()
        if self.worker is not None:
            self.worker.join(timeout=5.0)
        try:
            self.send([0.0] * len(self.limits))
            self.pub_command.wait_for_all_acked(Duration(seconds=1.0))
        except Exception as exc:  # context gone: the bridge's watchdog and shutdown vent remain
            self.get_logger().error(f'could not send the vent command: {exc}')


main = main_wrapper(Collector)
