"""The collector over real rclpy against a regulator-lag responder: order, records, settling."""

import json
import threading

import numpy as np
import pytest
from rclpy.parameter import Parameter

from waits import wait_matched


class Responder:
    """A bridge stand-in: first-order regulators at 100 Hz, optionally stuck at a fraction."""

    def __init__(self, ros, gain=1.0, reverse=False, sim_time=False):
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64MultiArray, Header, String

        from softshape_ros.config import load_rig_config
        from softshape_ros.pressure import FirstOrderRegulator
        from softshape_ros.nodes.common import LATCHED_QOS, RELIABLE_QOS, stamp_to_ns
        cfg = load_rig_config()
        t = cfg.topics
        import rclpy
        self.node = ros.add(rclpy.create_node(
            'responder', parameter_overrides=[Parameter('use_sim_time', value=sim_time)]))
        self.reg = FirstOrderRegulator(0.01)
        self.lock = threading.Lock()
        self.commands, self.triggers, self.samples, self.scenes = [], [], [], []
        pub = self.node.create_publisher(JointState, t.pressure_measured, RELIABLE_QOS)

        def on_cmd(m):
            with self.lock:
                self.commands.append(list(m.data))
                self.reg.setpoint = np.asarray(m.data) * gain

        def tick():
            p = self.reg.step(0.01)
            names, eff = list(cfg.chamber_names), [float(v) for v in p]
            if reverse:                       # another chamber order on the wire
                names, eff = names[::-1], eff[::-1]
            js = JointState(name=names, effort=eff)
            js.header.stamp = self.node.get_clock().now().to_msg()
            pub.publish(js)

        def on(where, value):
            with self.lock:
                where.append(value)

        self.subs = [
            self.node.create_subscription(Float64MultiArray, t.pressure_command, on_cmd,
                                          RELIABLE_QOS),
            self.node.create_subscription(
                Header, t.trigger, lambda m: on(self.triggers, stamp_to_ns(m.stamp)),
                RELIABLE_QOS)]
        self.node.create_subscription(
            String, t.sample, lambda m: on(self.samples, json.loads(m.data)), RELIABLE_QOS)
        self.node.create_subscription(
            String, t.scene, lambda m: on(self.scenes, json.loads(m.data)), LATCHED_QOS)
        self.node.create_timer(0.01, tick)


def _collector(ros, **params):
    from softshape_ros.nodes.collector import Collector
    base = {'rate_hz': 20.0, 'rest_delay_s': 0.05, 'start_delay_s': 0.1,
            'settle_timeout_s': 5.0, 'wait_for_frames': False, 'simulated': True}   # busy CI
    base.update(params)
    overrides = [Parameter(k, value=v) for k, v in base.items()]
    return ros.add(Collector(parameter_overrides=overrides))


def _session(tmp_path, n_scenes=2, actuations=3):
    lines = ['scenes:'] + [f'  - {{id: {10 + i}, object: sphere, position_m: [0.02, 0, 0.02], '
                           f'dims: {{radius_m: 0.005}}, actuations: {actuations}}}'
                           for i in range(n_scenes)]
    p = tmp_path / 'session.yaml'
    p.write_text('\n'.join(lines) + '\n')
    return p


@pytest.mark.ros
def test_list_mode_session_order_records_and_venting(ros, tmp_path):
    rows = [[1000.0 * (i + 1)] * 3 + [0.0, 500.0 * i, 0.0] for i in range(6)]
    plist = tmp_path / 'p.yaml'
    plist.write_text('pressures_pa: ' + json.dumps(rows) + '\n')
    resp = Responder(ros)
    col = _collector(ros, session=str(_session(tmp_path)), mode='list',
                     pressures_file=str(plist))
    ros.wait_for(col.done.is_set, timeout=30, what='session done')
    ros.wait_for(lambda: len(resp.samples) == 8 and len(resp.triggers) == 8
                 and resp.commands[-1] == [0.0] * 6, what='records and the final vent')
    assert col.state == 'done' and col.samples == 8 and col.unsettled == 0
    with resp.lock:
        samples, triggers = list(resp.samples), list(resp.triggers)
        commands, scenes = list(resp.commands), list(resp.scenes)
    assert [s['stamp_ns'] for s in samples] == triggers
    assert [(s['scene_id'], s['kind'], s['index']) for s in samples] == (
        [(10, 'rest', 0)] + [(10, 'actuation', i) for i in range(3)]
        + [(11, 'rest', 0)] + [(11, 'actuation', i) for i in range(3)])
    acts = [s['command_pa'] for s in samples if s['kind'] == 'actuation']
    assert acts == rows                                  # replayed in order, across scenes
    assert all(s['command_pa'] == [0.0] * 6 for s in samples if s['kind'] == 'rest')
    assert all(s['settled'] for s in samples)
    assert commands[-1] == [0.0] * 6                     # ends venting
    assert [s['id'] for s in scenes][-1] == 11


@pytest.mark.ros
def test_the_first_scene_waits_until_the_named_recorder_is_matched(ros, tmp_path):
    """
    A recorder started beside the collector (as the launch files do) misses nothing.

    The collector's own writers it asks; the rig's (measured pressures, cameras) it believes
    on /diagnostics, here said by a stand-in, first too few, then every reader.
    """
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from sensor_msgs.msg import CameraInfo, Image, JointState, TimeReference
    from std_msgs.msg import Float64MultiArray, Header, String

    from softshape_ros.nodes.common import RELIABLE_QOS
    from softshape_ros.nodes.diagnostics import subscribers_key
    resp = Responder(ros)
    col = _collector(ros, session=str(_session(tmp_path, 1, 2)), recorder='bag_probe')
    own = ['/rig/pressure/command', '/rig/trigger', '/rig/sample']
    rig = col.rig_topics
    assert len(rig) == 1 + 3 * len(col.cfg.camera_names)     # measured; image, info, time

    def waits_for(*reasons):
        return lambda: col.rig_waiting_for() == '; '.join(reasons)
    # The rig is there (pressures, a trigger subscriber): only the recorder is missing.
    ros.wait_for(waits_for(*(f'bag_probe does not subscribe to {t}' for t in own + rig)),
                 what=lambda: f'waiting for the recorder alone: {col.rig_waiting_for()!r}')
    assert col.state == 'waiting for the rig' and col.samples == 0 and resp.scenes == []
    probe = ros.add(rclpy.create_node('bag_probe'))
    got = {'command': [], 'trigger': [], 'sample': []}
    for key, cls in (('command', Float64MultiArray), ('trigger', Header), ('sample', String)):
        topic = {'command': '/rig/pressure/command'}.get(key, f'/rig/{key}')
        probe.create_subscription(cls, topic, got[key].append, RELIABLE_QOS)
    types = {'measured': JointState, 'image': Image, 'info': CameraInfo, 'time': TimeReference}
    for topic in rig:
        cls = next(c for k, c in types.items() if k in topic)
        probe.create_subscription(cls, topic, lambda m: None, RELIABLE_QOS)
    ros.wait_for(waits_for(*(f'{t}: no writer says on /diagnostics whom it matched'
                             for t in rig)),
                 what=lambda: f'the rig writers unsaid: {col.rig_waiting_for()!r}')
    said = {t: 0 for t in rig}
    writers = ros.add(rclpy.create_node('rig_writers'))
    pub = writers.create_publisher(DiagnosticArray, '/diagnostics', 1)
    writers.create_timer(0.05, lambda: pub.publish(DiagnosticArray(status=[DiagnosticStatus(
        name='rig_writers: stand-in', values=[KeyValue(key=subscribers_key(t), value=str(n))
                                              for t, n in said.items()])])))
    ros.wait_for(lambda: col.rig_waiting_for() == '; '.join(
        f'{t}: {col.count_subscribers(t)} subscribers, 0 matched by its writer' for t in rig),
        what=lambda: f'too few matched: {col.rig_waiting_for()!r}')
    assert col.samples == 0 and resp.scenes == []
    said.update({t: col.count_subscribers(t) for t in rig})
    ros.wait_for(col.done.is_set, timeout=30, what='session done')
    ros.wait_for(lambda: len(got['sample']) == 3 and len(got['trigger']) == 3,
                 what=lambda: f'all three samples at the probe: {len(got["sample"])}')
    assert json.loads(got['sample'][0].data)['kind'] == 'rest'
    ros.wait_for(lambda: len(got['command']) == len(resp.commands) >= 4,
                 what='every command at the probe too, the first vent included')


@pytest.mark.ros
def test_unsettled_samples_are_marked_and_reported(ros, tmp_path):
    resp = Responder(ros, gain=0.5)                      # regulators that never reach
    col = _collector(ros, session=str(_session(tmp_path, 1, 2)), settle_timeout_s=0.2,
                     seed=1)
    ros.wait_for(col.done.is_set, timeout=30, what='session done')
    ros.wait_for(lambda: len(resp.samples) == 3, what='records')
    assert [s['settled'] for s in resp.samples] == [True, False, False]  # rest is at zero
    assert col.unsettled == 2


@pytest.mark.ros
def test_operator_mode_waits_for_next_scene_service(ros, tmp_path):
    from std_srvs.srv import Trigger
    resp = Responder(ros)
    col = _collector(ros, session=str(_session(tmp_path, 1, 1)), simulated=False)
    ros.wait_for(lambda: 'operator' in col.state, what='waiting for the operator')
    client = resp.node.create_client(Trigger, '/collector/next_scene')
    assert client.wait_for_service(timeout_sec=5)
    assert resp.triggers == []
    fut = client.call_async(Trigger.Request())
    ros.wait_for(fut.done, what='service answer')
    assert fut.result().success
    ros.wait_for(col.done.is_set, timeout=30, what='session done')
    ros.wait_for(lambda: len(resp.samples) == 2, what='both records')
    assert [s['kind'] for s in resp.samples] == ['rest', 'actuation']


@pytest.mark.ros
def test_no_session_waits_idle(ros):
    """
    With no session the collector sends nothing, and an operator's ~/next_scene starts nothing.

    Instead of watching nothing arrive for a while: with its publishers and the responder
    matched at both ends, the collector answers ~/next_scene and then reports itself idle on
    /diagnostics; anything it had sent before that report (in one process, delivered as it
    is published) would have reached the responder by the time the report is read.
    """
    from diagnostic_msgs.msg import DiagnosticArray
    from std_srvs.srv import Trigger
    resp = Responder(ros)
    col = _collector(ros, **{'diagnostic_updater.period': 0.1})
    assert col.worker is None and col.state.startswith('idle')
    wait_matched(ros, [col.pub_command, col.pub_trigger], resp.subs)
    client = resp.node.create_client(Trigger, '/collector/next_scene')
    assert client.wait_for_service(timeout_sec=5)
    fut = client.call_async(Trigger.Request())
    ros.wait_for(fut.done, what='service answer')
    assert fut.result().success and 'idle' in fut.result().message
    reports = []
    resp.node.create_subscription(
        DiagnosticArray, '/diagnostics',
        lambda a: reports.extend(s.message for s in a.status if s.name == 'collector: session'),
        10)
    ros.wait_for(lambda: reports, what='the collector reporting on /diagnostics')
    assert reports[-1] == 'idle: no session' and col.worker is None
    assert resp.triggers == [] and resp.commands == []


@pytest.mark.ros
def test_sigint_mid_session_vents(ros, tmp_path):
    """SIGINT shuts the node's context down first; the collector still vents on its way out."""
    import os
    import signal
    import subprocess
    import sys
    resp = Responder(ros)
    proc = subprocess.Popen(
        [sys.executable, '-c', 'from softshape_ros.nodes.collector import main; main()',
         '--ros-args', '-p', f'session:={_session(tmp_path, 1, 50)}', '-p', 'rate_hz:=5.0',
         '-p', 'start_delay_s:=0.1', '-p', 'rest_delay_s:=0.05',
         '-p', 'wait_for_frames:=false', '-p', 'simulated:=true'],
        env=dict(os.environ), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        ros.wait_for(lambda: any(any(c) for c in resp.commands), timeout=60,
                     what='an actuation command')
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, out
    ros.wait_for(lambda: resp.commands[-1] == [0.0] * 6, what='the vent command', timeout=5)
    assert len(resp.samples) < 50


@pytest.mark.ros
def test_bad_session_parameters_fail_clearly(ros, tmp_path):
    from softshape_ros.nodes.collector import Collector
    with pytest.raises(ValueError, match='disagree'):
        Collector(parameter_overrides=[Parameter('session', value='a.yaml'),
                                       Parameter('session_file', value='b.yaml')])
    with pytest.raises(ValueError, match='cannot read session'):
        Collector(parameter_overrides=[Parameter('session', value=str(tmp_path / 'no.yaml'))])
    with pytest.raises(ValueError, match='needs the pressures_file'):
        Collector(parameter_overrides=[Parameter('session', value=str(_session(tmp_path))),
                                       Parameter('mode', value='list')])


@pytest.mark.ros
def test_measured_pressures_are_matched_by_chamber_name(ros, tmp_path):
    Responder(ros, reverse=True)
    col = _collector(ros, session=str(_session(tmp_path, 1, 2)))   # unmatched: never settles
    ros.wait_for(col.done.is_set, timeout=30, what='session done')
    assert col.unsettled == 0 and col.samples == 3       # reordered by name, so it settles


@pytest.mark.ros
def test_under_sim_time_samples_settle_on_the_clock_topic(ros, tmp_path):
    """Stamps on /clock time throughout: commands settle against sim-time measurements."""
    from rclpy.clock import Clock as RclClock, ClockType
    from rosgraph_msgs.msg import Clock

    from softshape_ros.nodes.common import ns_to_stamp
    sim = {'ns': 2_000 * 10**9}                           # far from wall time
    clock_node = ros.node('sim_clock')
    clock_pub = clock_node.create_publisher(Clock, '/clock', 10)

    def advance():                                        # sim time at wall rate
        sim['ns'] += 5_000_000
        clock_pub.publish(Clock(clock=ns_to_stamp(sim['ns'])))
    clock_node.create_timer(0.005, advance, clock=RclClock(clock_type=ClockType.STEADY_TIME))
    resp = Responder(ros, sim_time=True)
    col = _collector(ros, session=str(_session(tmp_path, 1, 3)), use_sim_time=True,
                     settle_timeout_s=2.0)
    ros.wait_for(col.done.is_set, timeout=30, what='session done')
    ros.wait_for(lambda: len(resp.samples) == 4, what='records')
    assert col.state == 'done'
    assert [s['settled'] for s in resp.samples] == [True] * 4
    stamps = [s['stamp_ns'] for s in resp.samples]
    assert all(abs(s - sim['ns']) < 60 * 10**9 for s in stamps), stamps   # sim time, not wall
    assert stamps == sorted(stamps) and resp.triggers == stamps
