"""
Inference node: predicted interaction images for each pressure command or query.

Initial images come from the camera topics (the rest images of each ``/rig/scene``, or on
demand via ``~/capture_initial``); each ``/rig/pressure/command`` and ``/softshape/query``
yields ``/softshape/predicted/{view}/image_raw`` (plus an outline overlay). The model runs
on a worker thread that always serves the latest request, so a slow model never blocks
subscriptions and requests never queue without bound.
"""

from __future__ import annotations

import json
import threading
import time
from collections import OrderedDict, deque

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import Trigger

from softshape_ros.model.serving import (InferenceCore, LatestSlot, PredictionError, overlay,
                                         to_hwc)
from softshape_ros.scene import Scene, SceneError
from softshape_ros.vision.preprocess import crop_for
from softshape_ros.nodes.common import (IMAGE_QOS, LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS,
                                        declare_rig_config, image_to_numpy, main_wrapper,
                                        numpy_to_image, stamp_to_ns)
from softshape_ros.nodes.diagnostics import ERROR, OK, WARN, Updater, fill
from softshape_ros.nodes.parameters import Param, declare

PARAMETERS = [
    Param('model', '', 'checkpoint folder (model.safetensors + config.json); required'),
    Param('placement_head', '', 'placement head folder (softshape placement-head): draw what '
          'it predicts for the placement fitted to the rest images (simulated rig only)'),
    Param('placement_from_scene', False, 'with placement_head: tell the head the placement '
          '/rig/scene records instead of fitting one to the rest images (from the next scene)',
          live=True),
    Param('threads', 1, 'torch CPU threads for the model', (1, 256)),
    Param('overlay', True, 'also publish /softshape/predicted/{view}/overlay', live=True),
    Param('reliable_images', True, 'camera subscriptions reliable (false for best-effort '
          'cameras)'),
]


#: Frames kept per view to pair with a rest sample that arrives after them.
RECENT_FRAMES = 8


class InferenceNode(Node):
    """Thin adapter: parameters in, :class:`InferenceCore` call, images out."""

    def __init__(self, **kwargs):
        super().__init__('inference', **kwargs)
        self.cfg = declare_rig_config(self)
        self.params = p = declare(self, PARAMETERS)
        model_path, threads = p.model, p.threads
        # Camera images: reliable like camera_trigger/mock_hardware publish them (a best-effort
        # subscription would silently lose rest images under load); false for best-effort cameras.
        image_qos = IMAGE_QOS if p.reliable_images else SENSOR_QOS
        if not model_path:
            raise ValueError('parameter "model" is empty: give a checkpoint '
                             '(ros2 run softshape_ros inference --ros-args -p model:=PATH)')
        import torch
        torch.set_num_threads(max(1, threads))
        self.placement = None               # the placement path's predictor, if served
        if p.placement_head:
            from softshape_ros.experiments.placement_predictor import PlacementPredictor
            predictor = self.placement = PlacementPredictor.from_paths(
                model_path, p.placement_head, self.cfg)
        else:
            from softshape_ros.model import Predictor
            predictor = Predictor.from_checkpoint(model_path)
        self.core = InferenceCore(predictor, self.cfg, model_path)
        self.get_logger().info(f'model {model_path}: views {self.core.views}, '
                               f'{"gray" if self.core.gray else "RGB"} {self.core.size}px')
        t = self.cfg.topics
        self.pub_pred = {v: self.create_publisher(Image, t.camera('predicted_image', v), IMAGE_QOS)
                         for v in self.core.views}
        self.pub_overlay = {v: self.create_publisher(Image, t.camera('predicted_overlay', v),
                                                     IMAGE_QOS) for v in self.core.views}
        self.latest_frame: dict[str, np.ndarray] = {}
        # The last few frames by stamp: a rest sample and its frames come from different
        # publishers, and either may arrive first.
        self.recent: dict[str, OrderedDict] = {v: OrderedDict() for v in self.core.views}
        self.rest_stamps: set[int] = set()
        self.seen_samples = False
        self.awaiting_rest = False
        self.scene_id: int | None = None
        self.camera_subs = [self.create_subscription(
            Image, t.camera('camera_image', v), lambda msg, v=v: self.on_image(v, msg), image_qos)
            for v in self.core.views]
        self.create_subscription(String, t.scene, self.on_scene, LATCHED_QOS)
        self.create_subscription(String, t.sample, self.on_sample, RELIABLE_QOS)
        self.create_subscription(Float64MultiArray, t.pressure_command,
                                 lambda m: self.on_request(m, 'command'), RELIABLE_QOS)
        self.create_subscription(Float64MultiArray, t.query,
                                 lambda m: self.on_request(m, 'query'), RELIABLE_QOS)
        self.create_service(Trigger, '~/capture_initial', self.on_capture_initial)
        # frames: camera images received (all views); rest_samples: rest samples seen
        self.counts = {'requests': 0, 'published': 0, 'rejected': 0, 'frames': 0,
                       'rest_samples': 0}
        self.last_error = ''
        self.latency_ms: deque = deque(maxlen=500)
        self.slot = LatestSlot()
        self.worker = threading.Thread(target=self.serve, name='inference-worker', daemon=True)
        self.running = True
        self.worker.start()
        self.diagnostics = Updater(self)
        self.diagnostics.setHardwareID(str(model_path))
        self.diagnostics.add('model', self.report)

    # -- inputs ---------------------------------------------------------------------------
    def on_scene(self, msg: String) -> None:
        try:
            scene = Scene.from_json(msg.data)
        except SceneError as exc:
            self.get_logger().error(f'ignoring /rig/scene: {exc}; keeping initial images')
            return
        self.core.clear_initial()
        self.awaiting_rest = True
        self.scene_id = scene.id
        if self.placement is not None:
            from softshape_ros.experiments.placement_head import PlacementHeadError
            try:
                self.placement.know(scene if self.params.placement_from_scene else None)
            except PlacementHeadError as exc:
                self.placement.know(None)
                self.get_logger().warn(f'{exc}: fitting its placement to the rest images')
        self.get_logger().info(f'scene {scene.id}: waiting for its rest images')

    def on_sample(self, msg: String) -> None:
        try:
            sample = json.loads(msg.data)
            rest = sample.get('kind') == 'rest'
            stamp = int(sample['stamp_ns']) if rest else None
            self.seen_samples = True
        except (json.JSONDecodeError, KeyError, TypeError, ValueError, AttributeError) as exc:
            self.get_logger().warn(f'ignoring malformed /rig/sample: {exc}')
            return
        if rest:
            self.counts['rest_samples'] += 1
            self.rest_stamps.add(stamp)
            for v, frames in self.recent.items():       # its frames may already be here
                if stamp in frames:
                    self.take_rest(v, stamp, frames[stamp])

    def on_image(self, view: str, msg: Image) -> None:
        try:
            frame = image_to_numpy(msg)
        except ValueError as exc:
            self.get_logger().warn(f'{view}: dropping bad image: {exc}')
            return
        self.counts['frames'] += 1
        self.latest_frame[view] = frame
        stamp = stamp_to_ns(msg.header.stamp)
        recent = self.recent[view]
        recent[stamp] = frame
        while len(recent) > RECENT_FRAMES:
            recent.popitem(last=False)
        self.take_rest(view, stamp, frame)

    def take_rest(self, view: str, stamp: int, frame: np.ndarray) -> None:
        """Use ``frame`` as the view's initial image if the scene waits for it."""
        if not self.awaiting_rest or (self.seen_samples and stamp not in self.rest_stamps):
            return
        try:
            self.core.set_initial(view, frame)
        except ValueError as exc:
            self.get_logger().error(f'{view}: cannot use rest image: {exc}')
            return
        if self.core.ready:
            self.awaiting_rest = False
            self.get_logger().info('initial images captured')

    def on_capture_initial(self, request, response):
        missing = [v for v in self.core.views if v not in self.latest_frame]
        if missing:
            response.success, response.message = False, f'no camera frame yet from {missing}'
            return response
        try:
            for v in self.core.views:
                self.core.set_initial(v, self.latest_frame[v])
        except ValueError as exc:
            response.success, response.message = False, str(exc)
            return response
        self.awaiting_rest = False
        response.success, response.message = True, f'initial images set from {self.core.views}'
        return response

    def on_request(self, msg: Float64MultiArray, source: str) -> None:
        self.counts['requests'] += 1
        stamp = self.get_clock().now()
        try:
            pressures = self.core.check(msg.data)
            if not self.core.ready:
                self.core.initial()  # raises with the reason
        except PredictionError as exc:
            self.reject(f'{source}: {exc}')
            return
        self.slot.put((pressures, stamp, time.perf_counter()))

    def reject(self, reason: str) -> None:
        self.counts['rejected'] += 1
        self.last_error = reason
        self.get_logger().warn(f'not predicting: {reason}', throttle_duration_sec=1.0)

    # -- worker ---------------------------------------------------------------------------
    def serve(self) -> None:
        while self.running:
            item = self.slot.get(timeout=0.2)
            if item is None:
                continue
            try:
                self.answer(*item)
            except PredictionError as exc:
                self.reject(str(exc))
            except Exception as exc:  # keep serving; say what failed
                self.reject(f'prediction failed: {type(exc).__name__}: {exc}')

    def answer(self, pressures, stamp, t0) -> None:
        """Predict for one request and publish the images and overlays."""
        images = self.core.predict(pressures)
        msg_stamp = stamp.to_msg()
        for v, img in images.items():
            frame_id = self.cfg.cameras[v].frame_id
            self.pub_pred[v].publish(numpy_to_image(to_hwc(img), msg_stamp, frame_id))
            frame = self.latest_frame.get(v)
            if self.params.overlay and frame is not None:
                crop = crop_for(self.cfg.cameras[v], frame.shape[1], frame.shape[0])
                self.pub_overlay[v].publish(
                    numpy_to_image(overlay(frame, img, crop), msg_stamp, frame_id))
        self.counts['published'] += 1
        self.latency_ms.append((time.perf_counter() - t0) * 1e3)

    def report(self, stat):
        lat = np.asarray(self.latency_ms) if self.latency_ms else np.zeros(1)
        level, message = OK, 'predicting'
        if not self.core.ready:
            level, message = WARN, 'waiting for initial images'
        if not self.worker.is_alive():
            level, message = ERROR, 'inference worker died'
        # 'scene': the placement its initial images are (to be) of; '' before any /rig/scene.
        # 'placement': where the placement head's placement comes from ('' without one).
        # 'camera_publishers': the fewest cameras matched on any view's image topic; a rest
        # snap taken before it is 1 reaches the camera's other readers but not this one.
        values = dict(self.counts, superseded=self.slot.superseded,
                      scene='' if self.scene_id is None else str(self.scene_id),
                      placement=self.placement_source(),
                      camera_publishers=min(s.get_publisher_count() for s in self.camera_subs),
                      latency_ms_median=f'{np.median(lat):.2f}',
                      latency_ms_p99=f'{np.percentile(lat, 99):.2f}', last_error=self.last_error)
        return fill(stat, level, message, values)

    def placement_source(self) -> str:
        """Say where the placement the head is told comes from ('' without the head)."""
        if self.placement is None:
            return ''
        source = 'from /rig/scene' if self.placement.known is not None else \
            'fitted to rest images'
        why = self.placement.alone
        return source if not why else f'{source}; {why}: tube model alone'

    def on_shutdown(self) -> None:
        self.running = False
        self.slot.close()
        self.worker.join(timeout=2.0)


main = main_wrapper(InferenceNode)
