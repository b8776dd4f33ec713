"""mock_hardware on its own: commands, regulators, watchdog, scenes, noise, free run."""

import threading

import numpy as np
import pytest
from rclpy.parameter import Parameter

pytestmark = pytest.mark.ros


class Probe:
    def __init__(self, ros):
        from diagnostic_msgs.msg import DiagnosticArray
        from sensor_msgs.msg import Image, JointState
        from std_msgs.msg import Float64MultiArray, Header, String

        from softshape_ros.config import load_rig_config
        from softshape_ros.nodes.common import LATCHED_QOS, RELIABLE_QOS
        self.cfg = load_rig_config()
        t = self.cfg.topics
        self.node = ros.node('mock_probe')
        self.lock = threading.Lock()
        self.measured, self.images, self.diags = [], [], {}
        self.cmd = self.node.create_publisher(Float64MultiArray, t.pressure_command,
                                              RELIABLE_QOS)
        self.trig = self.node.create_publisher(Header, t.trigger, RELIABLE_QOS)
        self.scene = self.node.create_publisher(String, t.scene, LATCHED_QOS)
        self.node.create_subscription(JointState, t.pressure_measured,
                                      lambda m: self._add(self.measured, m), RELIABLE_QOS)
        self.node.create_subscription(Image, t.camera('camera_image', 'main'),
                                      lambda m: self._add(self.images, m), RELIABLE_QOS)
        self.node.create_subscription(DiagnosticArray, t.diagnostics, self._diag, RELIABLE_QOS)
        self.F, self.H, self.S = Float64MultiArray, Header, String

    def _add(self, where, m):
        with self.lock:
            where.append(m)

    def _diag(self, m):
        with self.lock:
            for s in m.status:
                self.diags[s.name] = (s.level[0], s.message, {kv.key: kv.value for kv in s.values})

    def last(self):
        with self.lock:
            return np.asarray(self.measured[-1].effort) if self.measured else None

    def send(self, values):
        self.cmd.publish(self.F(data=[float(v) for v in values]))


def _mock(ros, **params):
    from softshape_ros.nodes.mock_hardware import MockHardware
    base = {'tau_s': 0.02, 'free_run_hz': 0.0}         # triggers only unless a test says
    base.update(params)
    return ros.add(MockHardware(parameter_overrides=[Parameter(k, value=v)
                                                     for k, v in base.items()]))


def test_commands_are_validated_clamped_and_followed(ros):
    probe = Probe(ros)
    mock = _mock(ros)
    ros.wait_for(lambda: probe.last() is not None and probe.cmd.get_subscription_count(),
                 what='measured pressures')
    assert list(probe.measured[-1].name) == probe.cfg.chamber_names
    target = [10000.0, 20000.0, 0.0, 0.0, 5000.0, 1.0e6]       # the last one is over its limit
    probe.send(target)
    expect = np.minimum(target, probe.cfg.max_pressures_pa)
    ros.wait_for(lambda: np.allclose(probe.last(), expect, atol=1.0), what='regulators settle')
    for bad in ([1.0] * 5, [float('nan')] + [0.0] * 5, [-1.0] + [0.0] * 5):
        probe.send(bad)
    ros.wait_for(lambda: mock.rejected == 3, what='three rejected commands')
    assert mock.clamped == 1
    assert np.allclose(probe.last(), expect, atol=1.0)          # nothing bad was applied
    ros.wait_for(lambda: probe.diags.get('mock_hardware: pressure', (0,))[0] == 1,
                 what='diagnostics WARN', timeout=5)


def test_watchdog_vents_and_noise_options(ros):
    probe = Probe(ros)
    mock = _mock(ros, command_timeout_s=1.5, pressure_noise_pa=500.0)
    ros.wait_for(lambda: probe.cmd.get_subscription_count(), what='discovery')
    probe.send([50000.0] * 6)
    ros.wait_for(lambda: probe.last() is not None and probe.last().min() > 40000,
                 what='pressurised')
    ros.wait_for(lambda: mock.watchdog_vents == 1, what='watchdog vent', timeout=5)
    ros.wait_for(lambda: probe.last().max() < 5000, what='vented')
    with probe.lock:
        tail = np.array([m.effort for m in probe.measured[-20:]])
    assert tail.std() > 50 and (tail >= 0).all()                 # noisy, never negative


def test_scene_and_trigger_give_images_and_bad_scene_is_ignored(ros):
    from softshape_ros.nodes.common import image_to_numpy, ns_to_stamp, stamp_to_ns
    from softshape_ros.scene import Scene
    from softshape_ros.sim import SimRig
    probe = Probe(ros)
    mock = _mock(ros, image_noise_std=4.0)
    ros.wait_for(lambda: probe.trig.get_subscription_count()
                 and probe.scene.get_subscription_count(), what='discovery')
    scene = Scene(id=7, object='sphere', position_m=(0.02, 0.0, 0.02),
                  dims={'radius_m': 0.006})
    probe.scene.publish(probe.S(data=scene.to_json()))
    ros.wait_for(lambda: mock.scene is not None and mock.scene.id == 7, what='scene applied')
    probe.scene.publish(probe.S(data='{"id": 8, "object": "teapot"}'))
    probe.scene.publish(probe.S(data='not json'))
    import time
    ns = time.time_ns()
    probe.trig.publish(probe.H(stamp=ns_to_stamp(ns)))
    ros.wait_for(lambda: len(probe.images) == 1 and mock.cameras.idle(), what='image',
                 timeout=20)
    assert mock.scene.id == 7 and 'malformed' in mock.last_error   # both bad ones ignored
    msg = probe.images[0]
    assert stamp_to_ns(msg.header.stamp) == ns
    assert msg.header.frame_id == 'camera_main_optical_frame'
    img = image_to_numpy(msg)
    rig = SimRig(probe.cfg, seed=1)
    rig.set_scene(scene)
    clean = rig.snap(np.zeros(6))['main']
    diff = img.astype(int) - clean.astype(int)
    assert img.shape == clean.shape and 2.0 < diff.std() < 6.0   # the noise, nothing else
    assert abs(diff.mean()) < 1.0
    # The cameras' diagnostics say how many readers each camera writer has matched: the
    # probe's on the main image, none on the others (what a recorder's user waits on).
    from softshape_ros.nodes.diagnostics import subscribers_key
    t = probe.cfg.topics
    key = subscribers_key(t.camera('camera_image', 'main'))
    ros.wait_for(lambda: key in probe.diags.get('mock_hardware: cameras', ((), '', {}))[2],
                 what='camera diagnostics past starting up')
    said = probe.diags['mock_hardware: cameras'][2]
    assert said[key] == '1'
    for topic in (t.camera('camera_image', 'side'), t.camera('camera_info', 'main'),
                  t.camera('capture_time', 'side')):
        assert said[subscribers_key(topic)] == '0'
    ros.wait_for(lambda: subscribers_key(t.pressure_measured) in probe.diags.get(
        'mock_hardware: pressure', ((), '', {}))[2], what='pressure diagnostics')
    assert probe.diags['mock_hardware: pressure'][2][subscribers_key(t.pressure_measured)] == '1'


def test_solver_error_gives_no_images_and_diagnostics_error(ros):
    import time

    from softshape_ros.nodes.common import ns_to_stamp
    from softshape_ros.sim import SolverError
    probe = Probe(ros)
    mock = _mock(ros)

    def fail(pressures):
        raise SolverError('did not converge (injected)')
    mock.rig.solve = fail                     # the simulator failing, as it can at extremes
    ros.wait_for(lambda: probe.trig.get_subscription_count(), what='discovery')
    probe.send([2.0e4] + [0.0] * 5)           # a new shape (the rest one is already made)
    ros.wait_for(lambda: probe.last() is not None and probe.last()[0] > 1.0e4,
                 what='pressurised')
    probe.trig.publish(probe.H(stamp=ns_to_stamp(time.time_ns())))
    ros.wait_for(lambda: mock.solver_errors == 1, what='the solver error')
    ros.wait_for(lambda: probe.diags.get('mock_hardware: cameras', (0,))[0] == 2,
                 what='diagnostics ERROR', timeout=5)
    assert 'injected' in probe.diags['mock_hardware: cameras'][1]
    assert probe.images == [] and mock.frames == 0


def test_a_trigger_after_the_command_settled_renders_the_shape_solved_on_arrival(ros):
    """Counted in the node's diagnostics: the command is solved once, the trigger reuses it."""
    import time

    from softshape_ros.nodes.common import image_to_numpy, ns_to_stamp
    from softshape_ros.sim import SimRig
    probe = Probe(ros)
    mock = _mock(ros)
    ros.wait_for(lambda: probe.trig.get_subscription_count(), what='discovery')
    command = [2.0e4, 0.0, 0.0, 0.0, 3.0e4, 0.0]
    probe.send(command)
    ros.wait_for(lambda: probe.last() is not None and probe.last().tolist() == command,
                 what='settled exactly on the command (within the regulator resolution)')
    ros.wait_for(lambda: mock.cameras.command_solves == 1, what='the commanded shape solved')
    probe.trig.publish(probe.H(stamp=ns_to_stamp(time.time_ns())))
    ros.wait_for(lambda: probe.diags.get('mock_hardware: cameras', (0, '', {}))[2]
                 .get('frames') == '1', what='diagnostics after the trigger', timeout=10)
    values = probe.diags['mock_hardware: cameras'][2]
    # The warm-up (rest shape) is the only solve for a frame; the trigger rendered the shape
    # solved when the command came.
    assert (values['solves'], values['command_solves'], values['reused_shapes']) == ('1', '1',
                                                                                     '1')
    rig = SimRig(probe.cfg)
    want = rig.snap(command)['main']
    assert np.array_equal(image_to_numpy(probe.images[0]), want)


def test_free_run_streams_both_cameras_at_the_rate_and_still_answers_triggers(ros, tmp_path):
    """
    Free-run rate by message count over a window of capture stamps (not a timed assertion).

    20 Hz at a small resolution: frames arrive stamped with their capture instants (late
    slots skipped, never bunched), from both cameras, showing the current pressures'
    shape; a trigger in between is answered under its own stamp. The rate's upper bound
    catches bursts (a late frame must not be made up), the lower one a stalled stream.
    """
    import time

    from sensor_msgs.msg import Image

    from softshape_ros.nodes.common import RELIABLE_QOS, image_to_numpy, ns_to_stamp, stamp_to_ns
    from softshape_ros.sim import SimRig
    from test_rig_sim import small_camera_config

    cfg = small_camera_config(tmp_path / 'rig.yaml')
    probe = Probe(ros)
    side = []
    probe.node.create_subscription(Image, cfg.topics.camera('camera_image', 'side'),
                                   lambda m: probe._add(side, m), RELIABLE_QOS)
    mock = _mock(ros, free_run_hz=20.0, config_file=str(tmp_path / 'rig.yaml'))
    ros.wait_for(lambda: probe.trig.get_subscription_count(), what='discovery')
    probe.send([0.0, 6.0e4, 0.0, 0.0, 0.0, 0.0])
    ros.wait_for(lambda: probe.last() is not None and abs(probe.last()[1] - 6.0e4) < 1.0,
                 what='pressurised', timeout=10)
    trig_ns = time.time_ns()
    probe.trig.publish(probe.H(stamp=ns_to_stamp(trig_ns)))
    n = 30
    ros.wait_for(lambda: len(probe.images) >= n + 1 and len(side) >= n + 1, timeout=30,
                 what=f'{n} free-run frames from each camera')
    with probe.lock:
        main, side_msgs = list(probe.images), list(side)
    stamps = sorted(stamp_to_ns(m.header.stamp) for m in main)
    assert trig_ns in stamps                                   # the trigger was answered
    free = [s for s in stamps if s != trig_ns]
    window_s = (free[-1] - free[0]) / 1e9
    rate = (len(free) - 1) / window_s
    assert 10.0 <= rate <= 21.0, rate                          # 20 Hz, a few skipped at most
    assert {stamp_to_ns(m.header.stamp) for m in side_msgs} >= set(free[:n // 2])
    # The picture is the shape at the current pressures.
    rig = SimRig(cfg)
    want = rig.snap([0.0, 6.0e4, 0.0, 0.0, 0.0, 0.0])['main']
    got = image_to_numpy(main[-1])
    assert np.abs(got.astype(int) - want).mean() < 0.5
    assert mock.cameras.free_frames >= n and mock.cameras.solves < mock.cameras.free_frames
