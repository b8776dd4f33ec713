"""
Shape controller node: reach a goal shape through the learned model, closed loop on the rig.

A goal (target images per view, robot silhouettes per view, or tip pixels as JSON) starts a
loop: plan six pressures through the forward model, publish them on /rig/pressure/command,
wait until the measured pressures settle, trigger the cameras, compare their images with the
goal, correct and re-plan until within tolerance or out of iterations. The reached command
is held (re-sent so the bridge's watchdog does not vent it). A camera that does not answer,
or a model error, stops the loop with the last checked command held or the chambers vented
(``on_error``); nothing is ever commanded that the model did not plan within the limits.
Works with mock_hardware and with pressure_bridge + camera_trigger alike: it uses only their
topics. The core is :mod:`softshape_ros.control` (no ROS).
"""

from __future__ import annotations

import json
import threading
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import Float64MultiArray, Header, String
from std_srvs.srv import Trigger

from softshape_ros.control.controller import Controller
from softshape_ros.control.features import SceneContextError
from softshape_ros.control.goal import CONTACT_MODES, GoalError
from softshape_ros.control.loop import Tolerance
from softshape_ros.control.planner import PlannerConfig
from softshape_ros.pressure import measured_in_order
from softshape_ros.nodes.common import (ERROR, IMAGE_QOS, LATCHED_QOS, OK, RELIABLE_QOS,
                                        SENSOR_QOS, WARN, declare_rig_config, diagnostic_status,
                                        image_to_numpy, main_wrapper, ns_to_stamp,
                                        numpy_to_image, publish_diagnostics, stamp_to_ns)
from softshape_ros.nodes.parameters import Param, declare
from softshape_ros.scene import Scene, SceneError


class Abort(Exception):
    """The loop cannot go on safely (no frames, model error, superseded); says why."""


def parameters(cfg) -> list[Param]:
    """List what the controller takes (limits default to rig.yaml's)."""
    limits = [float(x) for x in cfg.max_pressures_pa]
    return [
        Param('model', '', 'checkpoint folder (model.safetensors + config.json); required'),
        Param('threads', 1, 'torch CPU threads for planning', (1, 256)),
        Param('max_iterations', 3, 'closed-loop iterations (plan, move, film) per goal',
              (1, 100)),
        Param('tip_tolerance_px', 2.0, 'reached: tip within this (64 px network image) in '
              'every view', (0.0, 64.0)),
        Param('iou_tolerance', 0.9, 'reached: robot-silhouette IoU at least this (image and '
              'silhouette goals)', (0.0, 1.0)),
        Param('contact', 'any', 'image/silhouette goals: whether the robot must touch the '
              'object (a tip JSON goal may say)', choices=tuple(CONTACT_MODES)),
        Param('settle_tolerance_pa', -1.0, 'settled: every chamber within this of the command; '
              '< 0 = rig.yaml collection.settle_tolerance_pa', (-1.0, 1e6)),
        Param('settle_timeout_s', -1.0, 'film anyway after this; < 0 = rig.yaml '
              'collection.settle_timeout_s', (-1.0, 600.0)),
        Param('frame_timeout_s', 10.0, 'no frame from a camera this long after a trigger: stop '
              '(on_error)', (0.01, 600.0)),
        Param('on_error', 'hold', 'camera lost or model error: hold the last command, or vent',
              choices=('hold', 'vent')),
        Param('hold_period_s', 1.0, 're-send the held command this often (under the bridge '
              "watchdog's 3 s)", (0.01, 60.0)),
        Param('bank_size', 384, 'actuations predicted once per scene (the planner\'s starts)',
              (1, 100_000)),
        Param('lm_iterations', 4, 'Levenberg-Marquardt steps per plan at most', (0, 100)),
        Param('max_pressure_pa', limits, 'per-chamber limit, Pa; may only lower rig.yaml\'s',
              (0.0, 1e6), length=len(limits)),
        Param('reliable_images', True, 'camera subscriptions reliable (false for best-effort '
              'cameras)'),
    ]


class ShapeController(Node):
    """Thin adapter: goals in, :class:`Controller` loop, commands and triggers out."""

    def __init__(self, **kwargs):
        super().__init__('shape_controller', **kwargs)
        self.cfg = declare_rig_config(self)
        self.params = p = declare(self, parameters(self.cfg))
        coll = self.cfg.collection
        self.contact = p.contact
        self.settle_tol = coll.settle_tolerance_pa if p.settle_tolerance_pa < 0 \
            else p.settle_tolerance_pa
        self.settle_timeout = coll.settle_timeout_s if p.settle_timeout_s < 0 \
            else p.settle_timeout_s
        self.frame_timeout, self.on_error = p.frame_timeout_s, p.on_error
        self.hold_period = p.hold_period_s
        if not p.model:
            raise ValueError('parameter "model" is empty: give a checkpoint '
                             '(ros2 run softshape_ros shape_controller --ros-args -p model:=PATH)')
        import torch
        torch.set_num_threads(p.threads)
        from softshape_ros.model import Predictor
        self.core = Controller(Predictor.from_checkpoint(p.model), self.cfg, p.max_pressure_pa,
                               PlannerConfig(bank_size=p.bank_size,
                                             lm_iterations=p.lm_iterations),
                               Tolerance(p.tip_tolerance_px, p.iou_tolerance),
                               p.max_iterations)
        self.views = list(self.core.spec.views)
        self.get_logger().info(f'model {p.model}: views {self.views}; limits '
                               f'{[round(x) for x in self.core.limits]} Pa')
        self._make_interfaces(IMAGE_QOS if p.reliable_images else SENSOR_QOS)
        self._init_state()
        self.worker = threading.Thread(target=self.work, name='shape-controller', daemon=True)
        self.worker.start()
        self.create_timer(self.hold_period, self.keep_alive)
        self.create_timer(1.0, self.report)

    def _make_interfaces(self, image_qos) -> None:
        """Create the publishers, subscriptions and services (topics from rig.yaml)."""
        t = self.cfg.topics
        self.pub_command = self.create_publisher(Float64MultiArray, t.pressure_command,
                                                 RELIABLE_QOS)
        self.pub_trigger = self.create_publisher(Header, t.trigger, RELIABLE_QOS)
        self.pub_result = self.create_publisher(String, t.goal_result, RELIABLE_QOS)
        self.pub_plan = {v: self.create_publisher(Image, f'~/plan/{v}/image_raw', IMAGE_QOS)
                         for v in self.views}
        self.pub_diag = self.create_publisher(DiagnosticArray, t.diagnostics, RELIABLE_QOS)
        self.create_subscription(JointState, t.pressure_measured, self.on_measured, RELIABLE_QOS)
        self.create_subscription(String, t.scene, self.on_scene, LATCHED_QOS)
        for view in self.views:
            self.create_subscription(Image, t.camera('camera_image', view),
                                     lambda m, v=view: self.on_frame(v, m), image_qos)
            self.create_subscription(Image, t.camera('goal_image', view),
                                     lambda m, v=view: self.on_goal_part('images', v, m),
                                     IMAGE_QOS)
            self.create_subscription(Image, t.camera('goal_silhouette', view),
                                     lambda m, v=view: self.on_goal_part('silhouette', v, m),
                                     IMAGE_QOS)
        self.create_subscription(String, t.goal_tip, self.on_goal_tip, RELIABLE_QOS)
        self.create_service(Trigger, '~/cancel', self.on_cancel)
        self.create_service(Trigger, '~/vent', self.on_vent)

    def _init_state(self) -> None:
        """Set what the executor callbacks and the worker share (under ``self.cond``)."""
        self.cond = threading.Condition()
        self.measured = None            # (receipt time, pressures in config order)
        self.frames: dict[str, dict] = {v: {} for v in self.views}
        self.goal_parts: dict = {}      # (kind, stamp) -> {view: frame}
        self.pending = None             # (goal id, Goal) waiting for the worker
        self.cancelled = False
        self.held = None                # the command being held (re-sent), or None
        self.goal_count = 0
        self.rest_stamp = None
        self.state, self.last_error = 'idle', ''
        self.status = {'goal': None, 'iteration': 0, 'residual': None, 'tip_error_px': None,
                       'iou': None, 'plan_ms': None}
        self.counts = {'goals': 0, 'reached': 0, 'not_reached': 0, 'aborted': 0,
                       'rejected_goals': 0}
        self.running = True

    # -- inputs (executor thread) -----------------------------------------------------------
    def on_measured(self, msg: JointState) -> None:
        p = measured_in_order(msg.name, msg.effort, self.cfg.chamber_names)
        if p is None:
            return
        with self.cond:
            self.measured = (time.monotonic(), p)
            self.cond.notify_all()

    def on_frame(self, view: str, msg: Image) -> None:
        try:
            frame = image_to_numpy(msg)
        except ValueError as exc:
            self.get_logger().warn(f'{view}: dropping bad camera image: {exc}',
                                   throttle_duration_sec=5.0)
            return
        with self.cond:
            store = self.frames[view]
            store[stamp_to_ns(msg.header.stamp)] = frame
            while len(store) > 4:
                store.pop(next(iter(store)))
            self.cond.notify_all()

    def on_scene(self, msg: String) -> None:
        try:
            scene = Scene.from_json(msg.data)
        except SceneError as exc:
            self.get_logger().error(f'ignoring /rig/scene: {exc}')
            return
        self.core.clear_initial()
        self.get_logger().info(f'scene {scene.id}: rest images will be taken at the next goal')

    def on_goal_part(self, kind: str, view: str, msg: Image) -> None:
        """Collect one view of an image or silhouette goal; all views share one stamp."""
        key = (kind, stamp_to_ns(msg.header.stamp))
        try:
            frame = image_to_numpy(msg)
        except ValueError as exc:
            self.reject_goal(f'{kind} goal, view {view}: {exc}')
            return
        parts = self.goal_parts.setdefault(key, {})
        parts[view] = frame
        for k in [k for k in self.goal_parts if k != key and k[1] < key[1]]:
            del self.goal_parts[k]                 # older incomplete goals are dropped
        if len(parts) < len(self.views):
            return
        del self.goal_parts[key]
        contact = self.get_parameter('contact').value
        try:
            goal = (self.core.goal_from_images(parts, contact) if kind == 'images'
                    else self.core.goal_from_silhouettes(parts, contact))
        except GoalError as exc:
            self.reject_goal(f'{kind} goal: {exc}')
            return
        self.submit(goal)

    def on_goal_tip(self, msg: String) -> None:
        try:
            goal = self.core.goal_from_tip_json(msg.data, self.get_parameter('contact').value)
        except GoalError as exc:
            self.reject_goal(f'tip goal: {exc}')
            return
        self.submit(goal)

    def reject_goal(self, reason: str) -> None:
        self.counts['rejected_goals'] += 1
        self.last_error = reason
        self.get_logger().error(f'goal refused, nothing commanded: {reason}')
        self.publish_result({'goal': None, 'state': 'refused', 'reason': reason})

    def submit(self, goal) -> None:
        with self.cond:
            self.goal_count += 1
            self.pending = (self.goal_count, goal)
            self.cancelled = False
            self.cond.notify_all()
        self.get_logger().info(f'goal {self.goal_count}: {goal.kind}, contact {goal.contact}')

    def on_cancel(self, request, response):
        with self.cond:
            self.cancelled = True
            self.pending = None
            self.cond.notify_all()
        response.success, response.message = True, 'cancelled; holding the last command'
        return response

    def on_vent(self, request, response):
        with self.cond:
            self.cancelled = True
            self.pending = None
            self.cond.notify_all()
        self.command(np.zeros(6))
        self.held = None
        response.success, response.message = True, 'vented'
        return response

    # -- outputs ----------------------------------------------------------------------------
    def command(self, pressures) -> float:
        """Publish a checked command; return when it went out (monotonic)."""
        p = self.core.check(pressures)
        self.held = p
        self.pub_command.publish(Float64MultiArray(data=[float(x) for x in p]))
        return time.monotonic()

    def keep_alive(self) -> None:
        """Re-send the held command (a bridge vents after watchdog_timeout_s of silence)."""
        if self.held is not None and self.state not in ('moving', 'sensing', 'rest'):
            self.pub_command.publish(Float64MultiArray(data=[float(x) for x in self.held]))

    def publish_plan(self, plan) -> None:
        """Publish the images the model expects for the plan (~/plan/{view}/image_raw)."""
        now = self.get_clock().now().to_msg()
        for i, v in enumerate(self.views):
            img = plan.predicted[i]
            hwc = img[0] if img.shape[0] == 1 else np.ascontiguousarray(img.transpose(1, 2, 0))
            self.pub_plan[v].publish(numpy_to_image(hwc, now, self.cfg.cameras[v].frame_id))

    def publish_result(self, result: dict) -> None:
        self.pub_result.publish(String(data=json.dumps(result)))

    # -- the loop (worker thread) -----------------------------------------------------------
    def work(self) -> None:
        while self.running:
            with self.cond:
                self.cond.wait_for(lambda: self.pending is not None or not self.running, 0.5)
                if not self.running or self.pending is None:
                    continue
                goal_id, goal = self.pending
                self.pending = None
            try:
                self.run_goal(goal_id, goal)
            except Abort as exc:
                self.abort(goal_id, str(exc))
            except Exception as exc:  # a model or planner failure: never guess
                self.abort(goal_id, f'{type(exc).__name__}: {exc}')

    def run_goal(self, goal_id: int, goal) -> None:
        self.counts['goals'] += 1
        self.status.update(goal=goal_id, iteration=0, residual=None, tip_error_px=None,
                           iou=None, plan_ms=None)
        if not self.core.ready:
            self.take_rest_images()
        # Tolerances and iterations are read per goal: `ros2 param set` takes effect next goal.
        tol = Tolerance(float(self.get_parameter('tip_tolerance_px').value),
                        float(self.get_parameter('iou_tolerance').value))
        try:
            loop = self.core.start(goal, tol, int(self.get_parameter('max_iterations').value))
        except (GoalError, SceneContextError, ValueError) as exc:
            self.counts['rejected_goals'] += 1
            self.state, self.last_error = 'idle', str(exc)
            self.get_logger().error(f'goal {goal_id} refused: {exc}')
            self.publish_result({'goal': goal_id, 'state': 'refused', 'reason': str(exc)})
            return
        steps = []
        while not loop.done:
            self.state = 'planning'
            plan = loop.plan()
            self.status.update(iteration=loop.iteration + 1, plan_ms=round(plan.plan_ms, 1))
            self.check_superseded()
            self.publish_plan(plan)
            self.state = 'moving'
            sent = self.command(plan.pressures_pa)
            settled = self.wait_settled(plan.pressures_pa, sent)
            self.state = 'sensing'
            stamp, images = self.snap()
            obs = loop.observe(images)
            cost = loop.objective.real_cost(images, plan.u)
            self.status.update(residual=round(cost, 4), tip_error_px=obs.tip_error_px,
                               iou=obs.iou)
            steps.append(dict(obs.to_dict(), settled=settled, plan_ms=plan.plan_ms,
                              predicted_error=plan.predicted_error, residual=cost,
                              trigger_stamp_ns=stamp))
            self.get_logger().info(
                f'goal {goal_id} iteration {obs.iteration}: tip error '
                f'{[round(e, 2) for e in obs.tip_error_px]} px, IoU '
                f'{obs.iou if obs.iou is None else round(obs.iou, 3)}, plan '
                f'{plan.plan_ms:.0f} ms{"" if settled else " (not settled)"}')
        reached = loop.success
        b = loop.best
        if b != len(steps) - 1:
            self.command(loop.plans[b].pressures_pa)     # back to the best command seen
        best = steps[b]
        self.counts['reached' if reached else 'not_reached'] += 1
        self.state = 'reached' if reached else 'not_reached'
        self.publish_result({'goal': goal_id, 'state': self.state, 'kind': goal.kind,
                             'iterations': loop.iteration, 'tip_error_px': best['tip_error_px'],
                             'iou': best['iou'], 'pressures_pa': best['pressures_pa'],
                             'best_iteration': b + 1, 'rest_stamp_ns': self.rest_stamp,
                             'steps': steps})

    def check_superseded(self) -> None:
        with self.cond:
            if self.pending is not None:
                raise Abort('superseded by a newer goal')
            if self.cancelled:
                raise Abort('cancelled')

    def wait_settled(self, target, sent: float) -> bool:
        """Wait for a measurement received after ``sent`` within tolerance of ``target``."""
        target = np.asarray(target)

        def ok():
            m = self.measured
            return (self.pending is not None or self.cancelled or not self.running or (
                m is not None and m[0] > sent and np.max(np.abs(m[1] - target))
                <= self.settle_tol))
        with self.cond:
            done = self.cond.wait_for(ok, self.settle_timeout)
        self.check_superseded()
        if not done:
            self.get_logger().warn(f'pressures not within {self.settle_tol:g} Pa of the command '
                                   f'after {self.settle_timeout:g} s; filming anyway')
        return bool(done)

    def snap(self):
        """Trigger the cameras, wait for their frames: (stamp, V x C x S x S network images)."""
        stamp, frames = self.snap_frames()
        return stamp, np.stack([self.core.prepare(v, frames[v]) for v in self.views])

    def snap_frames(self):
        """Trigger the cameras; (stamp, {view: frame} of that trigger), or Abort."""
        stamp = time.time_ns()
        h = Header()
        h.stamp = ns_to_stamp(stamp)
        self.pub_trigger.publish(h)
        with self.cond:
            self.cond.wait_for(
                lambda: all(stamp in self.frames[v] for v in self.views) or not self.running,
                self.frame_timeout)
            frames = {v: self.frames[v].get(stamp) for v in self.views}
        missing = [v for v, f in frames.items() if f is None]
        if missing:
            raise Abort(f'camera(s) {missing} gave no frame within {self.frame_timeout:g} s '
                        'of the trigger')
        return stamp, frames

    def take_rest_images(self) -> None:
        """Vent, wait until the chambers are at zero, film: the scene's initial images."""
        self.state = 'rest'
        sent = self.command(np.zeros(6))
        if not self.wait_settled(np.zeros(6), sent):
            raise Abort('chambers did not vent to zero: no rest images taken')
        self.rest_stamp, frames = self.snap_frames()
        ms = self.core.set_initial(frames)
        self.get_logger().info(f'rest images taken; scene bank built in {ms:.0f} ms')

    def abort(self, goal_id: int, reason: str) -> None:
        """Stop safely: hold the last checked command or vent (``on_error``); never guess."""
        stopped = reason.startswith('superseded') or reason == 'cancelled'
        if not stopped:
            self.counts['aborted'] += 1
            self.last_error = reason
        if self.held is None or (self.on_error == 'vent' and not stopped):
            try:
                self.command(np.zeros(6))
            except Exception as exc:
                self.get_logger().error(f'vent failed: {exc}')
            action = 'vented'
        else:
            action = 'holding the last command'
        self.state = 'idle' if stopped else 'error'
        (self.get_logger().info if stopped else self.get_logger().error)(
            f'goal {goal_id} stopped: {reason}; {action}')
        self.publish_result({'goal': goal_id, 'state': 'aborted', 'reason': reason,
                             'action': action})

    # -- diagnostics ------------------------------------------------------------------------
    def report(self) -> None:
        level = {'error': ERROR, 'not_reached': WARN}.get(self.state, OK)
        message = f'error: {self.last_error}' if self.state == 'error' else self.state
        values = dict(self.status, state=self.state, **self.counts,
                      held_pa=None if self.held is None else [round(float(x)) for x in self.held],
                      scene_ready=self.core.ready, last_error=self.last_error)
        if not self.worker.is_alive():
            level, message = ERROR, 'controller worker died'
        publish_diagnostics(self, self.pub_diag, [
            diagnostic_status('shape_controller: loop', 'model', level, message, values)])

    def on_shutdown(self) -> None:
        """Stop the loop and vent: nothing is left holding pressure without a controller."""
        with self.cond:
            self.running = False
            self.cond.notify_all()
        self.worker.join(timeout=5.0)
        if self.held is not None:
            self.held = None
            self.pub_command.publish(Float64MultiArray(data=[0.0] * 6))


main = main_wrapper(ShapeController)
