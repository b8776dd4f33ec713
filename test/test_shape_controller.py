"""
The shape_controller node over real DDS, closing the loop against mock_hardware.

A plain rclpy probe publishes the scene and the goal and watches every command, trigger
answer, result and diagnostic. The model is the session's briefly trained one: too weak to
reach a 2 px goal, so the tests set tolerances that make the outcome certain and check what
the loop did (rest images, commands within limits and settled, the camera's verdict
recomputed independently, the best command held), not whether this model is good.
"""

import json
import threading

import numpy as np
import pytest
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image
from std_msgs.msg import Float64MultiArray, String
from diagnostic_msgs.msg import DiagnosticArray

from softshape_ros.config import load_rig_config
from softshape_ros.control import SceneContext
from softshape_ros.control.controller import Controller
from softshape_ros.control.objective import Objective
from softshape_ros.nodes.common import (IMAGE_QOS, LATCHED_QOS, RELIABLE_QOS, image_to_numpy,
                                        ns_to_stamp, numpy_to_image, stamp_to_ns)
from softshape_ros.scene import Scene
from softshape_ros.sim import SimRig

pytestmark = pytest.mark.ros

SCENE = Scene(id=41, object='cylinder', position_m=(0.024, 0.004, 0.025),
              dims={'radius_m': 0.007, 'height_m': 0.05})
P_GOAL = np.array([60e3, 0.0, 20e3, 70e3, 0.0, 10e3])


class Probe:
    """The test's own publishers and subscribers."""

    def __init__(self, ros, cfg):
        t = cfg.topics
        self.cfg = cfg
        self.node = ros.node('controller_probe')
        n = self.node
        self.lock = threading.Lock()
        self.results, self.commands, self.diags = [], [], []
        self.frames = {v: {} for v in cfg.camera_names}
        self.scene = n.create_publisher(String, t.scene, LATCHED_QOS)
        self.tip = n.create_publisher(String, t.goal_tip, RELIABLE_QOS)
        self.goal = {v: n.create_publisher(Image, t.camera('goal_image', v), IMAGE_QOS)
                     for v in cfg.camera_names}
        n.create_subscription(String, t.goal_result,
                              lambda m: self._add(self.results, json.loads(m.data)),
                              RELIABLE_QOS)
        n.create_subscription(Float64MultiArray, t.pressure_command,
                              lambda m: self._add(self.commands, list(m.data)), RELIABLE_QOS)
        n.create_subscription(DiagnosticArray, t.diagnostics, self._diag, RELIABLE_QOS)
        for v in cfg.camera_names:
            n.create_subscription(Image, t.camera('camera_image', v),
                                  lambda m, v=v: self._frame(v, m), IMAGE_QOS)

    def _add(self, where, item):
        with self.lock:
            where.append(item)

    def _frame(self, view, msg):
        with self.lock:
            self.frames[view][stamp_to_ns(msg.header.stamp)] = image_to_numpy(msg)

    def _diag(self, msg):
        for st in msg.status:
            if st.name == 'shape_controller: loop':
                self._add(self.diags, (st.level[0], st.message,
                                       {kv.key: kv.value for kv in st.values}))

    def send_goal_images(self, frames: dict, stamp_ns: int = 1_000_000_000_007):
        for v, img in frames.items():
            self.goal[v].publish(numpy_to_image(img, ns_to_stamp(stamp_ns),
                                                self.cfg.cameras[v].frame_id))


def goal_frames(cfg, pressures):
    """Full-resolution camera frames of the simulated rig at ``pressures`` (the goal)."""
    rig = SimRig(cfg)
    rig.set_scene(SCENE)
    return rig.snap(pressures)


@pytest.fixture
def rig(ros, trained_checkpoint):
    from softshape_ros.nodes.mock_hardware import MockHardware
    from softshape_ros.nodes.shape_controller import ShapeController
    cfg = load_rig_config()
    probe = Probe(ros, cfg)
    mock = ros.add(MockHardware(parameter_overrides=[Parameter('tau_s', value=0.02),
                                                     Parameter('free_run_hz', value=0.0)]))

    def start(**params):
        base = {'model': str(trained_checkpoint), 'bank_size': 48, 'lm_iterations': 3,
                'hold_period_s': 0.2, 'frame_timeout_s': 30.0}
        base.update(params)
        node = ros.add(ShapeController(parameter_overrides=[
            Parameter(k, value=v) for k, v in base.items()]))
        ros.wait_for(lambda: probe.node.count_subscribers(cfg.topics.goal_tip) >= 1
                     and node.count_subscribers(cfg.topics.pressure_measured) >= 1
                     and probe.node.count_subscribers(cfg.topics.trigger) >= 1
                     and node.count_publishers(cfg.topics.camera('camera_image', 'side')) >= 1,
                     timeout=20, what='graph connections')
        probe.scene.publish(String(data=SCENE.to_json()))
        ros.wait_for(lambda: mock.scene is not None and mock.scene.id == SCENE.id,
                     what='the mock to take the scene')
        return node
    return cfg, probe, mock, start


def network_images(cfg, frames_by_view):
    ctl_views = list(cfg.camera_names)
    from softshape_ros.vision.preprocess import preprocess
    return np.stack([preprocess(frames_by_view[v], cfg.cameras[v].crop_px, 64, True)
                     for v in ctl_views])


def test_loop_runs_out_of_iterations_and_holds_the_best_command(rig, ros, trained_checkpoint):
    cfg, probe, mock, start = rig
    node = start(tip_tolerance_px=0.0, iou_tolerance=1.0)         # unreachable on purpose
    probe.send_goal_images(goal_frames(cfg, P_GOAL))
    ros.wait_for(lambda: probe.results, timeout=60, what='the result')
    res = probe.results[-1]
    assert res['state'] == 'not_reached' and res['iterations'] == 3, res
    steps = res['steps']
    # First the rest images (vented), then one checked, settled command per iteration.
    with probe.lock:
        cmds = [np.asarray(c) for c in probe.commands]
    assert np.all(cmds[0] == 0.0)
    limits = np.asarray(cfg.max_pressures_pa)
    planned = [np.asarray(s['pressures_pa']) for s in steps]
    for p in planned:
        assert p.shape == (6,) and np.all(p >= 0) and np.all(p <= limits)
        assert any(np.array_equal(p, c) for c in cmds)
    assert all(s['settled'] for s in steps)
    # The camera's verdict, recomputed from the frames the probe saw for the same triggers.
    ctl = Controller(node.core.predictor, cfg)
    rest = network_images(cfg, {v: probe.frames[v][res['rest_stamp_ns']]
                                for v in cfg.camera_names})
    goal = ctl.goal_from_images(goal_frames(cfg, P_GOAL))
    obj = Objective(SceneContext.from_initial(rest), goal)
    for s in steps:
        seen = network_images(cfg, {v: probe.frames[v][s['trigger_stamp_ns']]
                                    for v in cfg.camera_names})
        want = obj.describe(seen)
        np.testing.assert_allclose(s['tip_error_px'], want['tip_error_px'])
        assert s['iou'] == pytest.approx(want['iou'])
    # Not reached: the best command seen is what is left applied, and it is kept alive.
    best = np.asarray(steps[res['best_iteration'] - 1]['pressures_pa'])
    n = len(probe.commands)
    ros.wait_for(lambda: len(probe.commands) >= n + 2, what='the held command re-sent')
    with probe.lock:
        assert all(np.array_equal(np.asarray(c), best) for c in probe.commands[n - 1:])
    ros.wait_for(lambda: probe.diags and probe.diags[-1][2].get('state') == 'not_reached',
                 what='diagnostics')
    level, _, values = probe.diags[-1]
    assert level == 1 and values['iteration'] == '3' and float(values['residual']) >= 0


def test_goal_reached_is_reported_and_held(rig, ros):
    cfg, probe, mock, start = rig
    start(tip_tolerance_px=64.0, iou_tolerance=0.0)               # any plan is within this
    probe.send_goal_images(goal_frames(cfg, P_GOAL))
    ros.wait_for(lambda: probe.results, timeout=60, what='the result')
    res = probe.results[-1]
    assert res['state'] == 'reached' and res['iterations'] == 1, res
    held = np.asarray(res['pressures_pa'])
    n = len(probe.commands)
    ros.wait_for(lambda: len(probe.commands) >= n + 2, what='the held command re-sent')
    assert np.array_equal(np.asarray(probe.commands[-1]), held)
    ros.wait_for(lambda: probe.diags and probe.diags[-1][2].get('state') == 'reached',
                 what='diagnostics')
    assert probe.diags[-1][0] == 0


def test_bad_goals_are_refused_and_nothing_moves(rig, ros):
    cfg, probe, mock, start = rig
    start()
    frames = goal_frames(cfg, P_GOAL)
    probe.send_goal_images({'main': frames['main'][:100, :300], 'side': frames['side'][:100,
                                                                                       :300]})
    probe.tip.publish(String(data='{"tips_px": {"main": [NaN, 3], "side": [300, 300]}}'))
    probe.tip.publish(String(data='{"tips_px": {"main": [320, 400]}}'))
    probe.tip.publish(String(data='not json'))
    bad = Image(height=64, width=64, encoding='16UC1', step=128, data=bytes(64 * 128))
    bad.header.stamp = ns_to_stamp(5)
    probe.goal['main'].publish(bad)
    ros.wait_for(lambda: len(probe.results) >= 5, what='five refusals')
    reasons = ' | '.join(r['reason'] for r in probe.results)
    assert all(r['state'] == 'refused' for r in probe.results)
    for why in ('neither 64x64', 'finite', "'side'", 'not JSON', 'encoding'):
        assert why in reasons, reasons
    assert probe.commands == []                                   # no air moved


def test_lost_camera_vents_and_reports_error(rig, ros):
    cfg, probe, mock, start = rig
    node = start(on_error='vent', frame_timeout_s=1.0)
    real_render = mock.rig.render
    calls = []

    def rest_only(state):             # the cameras answer the rest trigger, then go silent
        calls.append(state)
        if len(calls) > 1:
            raise RuntimeError('camera unplugged (injected)')
        return real_render(state)
    mock.rig.render = rest_only
    probe.send_goal_images(goal_frames(cfg, P_GOAL))
    ros.wait_for(lambda: probe.results, timeout=60, what='the result')
    res = probe.results[-1]
    assert res['state'] == 'aborted' and 'gave no frame' in res['reason'], res
    assert res['action'] == 'vented'
    with probe.lock:
        cmds = [np.asarray(c) for c in probe.commands]
    last_plan = max(i for i, c in enumerate(cmds) if np.any(c > 0))   # the plan went out,
    assert last_plan < len(cmds) - 1                                  # then the vent (and
    assert all(np.all(c == 0) for c in cmds[last_plan + 1:])          # its keep-alives)
    ros.wait_for(lambda: probe.diags and probe.diags[-1][0] == 2, what='diagnostics ERROR')
    assert 'gave no frame' in probe.diags[-1][1]
    assert node.held is not None and np.all(node.held == 0)
