"""
The demo's own ROS participant: watches the rig, and drives it for the live stage.

It plays the user's role over DDS (publish a scene, rest trigger, commands, triggers; read
camera and predicted images), so the live comparison measures what a subscriber would see.
"""

from __future__ import annotations

import json
import threading
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import Float64MultiArray, Header, String

from softshape_ros.nodes.common import (IMAGE_QOS, LATCHED_QOS, RELIABLE_QOS, image_to_numpy,
                                        ns_to_stamp, stamp_to_ns)
from softshape_ros.demo.participant import Participant
from softshape_ros.nodes.diagnostics import newest_key, received_key, writers_matched
from softshape_ros.processes import wait_until
from softshape_ros.vision.preprocess import preprocess


#: Rest snaps per scene before the demo gives up, and how long each waits for inference.
REST_ATTEMPTS, REST_WAIT_S = 3, 10.0


class RigClient(Participant):
    """The user's side of the recorded and live stages (a :class:`Participant`)."""

    def __init__(self, cfg, views=None, gray=None):
        self.cfg = cfg
        self.views = list(views or cfg.camera_names)
        self.gray = cfg.dataset.gray if gray is None else gray
        self.size = cfg.dataset.image_size
        self.lock = threading.Lock()
        self.collector_failed = ''
        self.collector_state = ''
        self.inference_state = ''
        self.inference_scene = ''       # the scene inference last said it is on
        self.inference_values: dict = {}
        self.status_values: dict = {}   # diagnostics: status name -> {key: value}
        self.frames = {v: {} for v in self.views}
        self.predicted = {v: [] for v in self.views}
        self.measured = None

    def connect(self, n) -> None:
        """Publish what the user would; watch samples, diagnostics, pressures and images."""
        t = self.cfg.topics
        self.pub_scene = n.create_publisher(String, t.scene, LATCHED_QOS)
        self.pub_sample = n.create_publisher(String, t.sample, RELIABLE_QOS)
        self.pub_trigger = n.create_publisher(Header, t.trigger, RELIABLE_QOS)
        self.pub_command = n.create_publisher(Float64MultiArray, t.pressure_command, RELIABLE_QOS)
        n.create_subscription(DiagnosticArray, t.diagnostics, self._on_diag, RELIABLE_QOS)
        n.create_subscription(JointState, t.pressure_measured, self._on_measured, RELIABLE_QOS)
        for v in self.views:
            n.create_subscription(Image, t.camera('camera_image', v),
                                  lambda m, v=v: self._on_frame(v, m), IMAGE_QOS)
            n.create_subscription(Image, t.camera('predicted_image', v),
                                  lambda m, v=v: self._on_predicted(v, m), IMAGE_QOS)

    # -- callbacks -------------------------------------------------------------------------
    def _on_diag(self, msg):
        for st in msg.status:
            self.status_values[st.name] = {kv.key: kv.value for kv in st.values}
            level = st.level[0] if isinstance(st.level, (bytes, bytearray)) else int(st.level)
            if st.name.endswith(': session'):
                self.collector_state = st.message
                if level == 2 and 'failed' in st.message:
                    self.collector_failed = st.message
            if 'inference' in st.name:
                self.inference_state = st.message
                self.inference_values = {kv.key: kv.value for kv in st.values}
                self.inference_scene = self.inference_values.get('scene', '')

    def _on_measured(self, msg):
        self.measured = np.asarray(msg.effort, dtype=np.float64)

    def _on_frame(self, view, msg):
        with self.lock:
            store = self.frames[view]
            store[stamp_to_ns(msg.header.stamp)] = msg
            while len(store) > 8:
                store.pop(next(iter(store)))

    def _on_predicted(self, view, msg):
        with self.lock:
            self.predicted[view].append((time.perf_counter(), msg))

    # -- queries ---------------------------------------------------------------------------
    def wait_for_node(self, name: str, procs=(), timeout: float = 30.0) -> None:
        wait_until(lambda: name in self.node.get_node_names(), timeout,
                   what=f'{name} in the ROS graph', processes=procs)

    def wait_connected(self, procs=(), timeout: float = 30.0) -> None:
        t = self.cfg.topics

        def ready():
            n = self.node
            return (n.count_subscribers(t.pressure_command) >= 2
                    and n.count_subscribers(t.trigger) >= 1
                    and all(n.count_publishers(t.camera('predicted_image', v)) >= 1
                            for v in self.views))
        wait_until(ready, timeout, what='mock_hardware and inference connections',
                   processes=procs)

    def camera_topics(self) -> list[str]:
        """Every topic the rig's cameras publish: image, info and capture time, per view."""
        t = self.cfg.topics
        return [t.camera(k, v) for v in self.views
                for k in ('camera_image', 'camera_info', 'capture_time')]

    def wait_camera_writers_matched(self, procs=(), timeout: float = 30.0) -> None:
        """
        Wait until mock_hardware's diagnostics say its writers match every reader seen.

        The graph shows a new reader before the writer has matched it, and a frame
        published in between never reaches it.
        """
        topics = self.camera_topics()

        def matched():
            said = {'cameras': self.status_values.get('mock_hardware: cameras', {})}
            return all(min(writers_matched(said, x), default=-1) >= self.node.count_subscribers(x)
                       for x in topics)
        wait_until(matched, timeout, what="mock_hardware's camera writers to match their readers",
                   processes=procs)

    def recorded(self, topic: str) -> tuple[int, int]:
        """Return (messages, newest source stamp ns) of ``topic`` in the recorder's diagnostics."""
        said = self.status_values.get('recorder: bag', {})
        return int(said.get(received_key(topic), 0)), int(said.get(newest_key(topic), 0))

    def wait_recorded_since(self, topics, stamp_ns: int, procs=(), timeout: float = 30.0):
        """
        Wait until the recorder has, on every topic, a message published at ``stamp_ns`` or later.

        A writer delivers in order, so the recorder then holds all that was published before.
        """
        wait_until(lambda: min(self.recorded(x)[1] for x in topics) >= stamp_ns, timeout,
                   what=f'the recorder to have every message of {", ".join(topics)} up to the '
                        'last sample', processes=procs)

    def prepared(self, stamp: int) -> np.ndarray:
        """V x C x S x S of the camera frames with ``stamp`` (as the dataset builder does)."""
        out = []
        for v in self.views:
            frame = image_to_numpy(self.frames[v][stamp])
            out.append(preprocess(frame, self.cfg.cameras[v].crop_px, self.size, self.gray))
        return np.stack(out)

    # -- driving ---------------------------------------------------------------------------
    def _settle(self, target, procs, timeout=None) -> bool:
        tol = self.cfg.collection.settle_tolerance_pa
        timeout = self.cfg.collection.settle_timeout_s if timeout is None else timeout
        try:
            wait_until(lambda: self.measured is not None
                       and np.max(np.abs(self.measured - target)) <= tol,
                       timeout, what='pressures to settle', processes=procs)
            return True
        except TimeoutError:
            return False

    def _snap(self, procs, kind: str, scene_id: int, command) -> int:
        stamp = time.time_ns()
        self.pub_sample.publish(String(data=json.dumps({
            'stamp_ns': stamp, 'scene_id': scene_id, 'kind': kind, 'index': 0,
            'command_pa': [float(x) for x in command], 'settled': True})))
        h = Header()
        h.stamp = ns_to_stamp(stamp)
        self.pub_trigger.publish(h)
        wait_until(lambda: all(stamp in self.frames[v] for v in self.views), 20.0,
                   what='camera frames for the trigger', processes=procs)
        return stamp

    def start_scene(self, scene: dict, procs) -> np.ndarray:
        """Publish a scene, vent, take its rest images; wait until inference has them."""
        zeros = np.zeros(6)
        self.pub_scene.publish(String(data=json.dumps(scene)))
        self.pub_command.publish(Float64MultiArray(data=zeros.tolist()))
        # Inference also says 'waiting' before any scene: wait for it to name this one, with
        # every camera matched to its reader (frames are volatile: a snap before that is lost
        # to it).
        sid = str(scene['id'])
        wait_until(lambda: 'waiting' in self.inference_state and self.inference_scene == sid
                   and int(self.inference_values.get('camera_publishers', 0)) >= 1,
                   30.0, what=f'inference to take scene {sid}', processes=procs)
        self._settle(zeros, procs)
        self.wait_camera_writers_matched(procs=procs)
        # Should a rest snap still not reach inference, snap again, as a user would.
        for attempt in range(REST_ATTEMPTS):
            stamp = self._snap(procs, 'rest', scene['id'], zeros)
            try:
                wait_until(lambda: self.inference_state == 'predicting'
                           and self.inference_scene == sid, REST_WAIT_S,
                           what='inference to take the rest images', processes=procs)
                return self.prepared(stamp)
            except TimeoutError:
                if attempt == REST_ATTEMPTS - 1:
                    raise TimeoutError(f'inference never took the rest images of scene {sid} '
                                       f'({REST_ATTEMPTS} snaps; its last diagnostics: '
                                       f'{self.inference_state!r} {self.inference_values})')
                print(f'  inference has no rest images of scene {sid} after {REST_WAIT_S:g} s: '
                      'snapping them again', flush=True)

    def command_and_snap(self, pressures, procs):
        """Send a command; return (predicted, actual after settling, command->prediction s)."""
        with self.lock:
            before = {v: len(self.predicted[v]) for v in self.views}
        t0 = time.perf_counter()
        self.pub_command.publish(Float64MultiArray(data=[float(x) for x in pressures]))
        wait_until(lambda: all(len(self.predicted[v]) > before[v] for v in self.views), 20.0,
                   what='predicted images', processes=procs)
        with self.lock:
            got = [self.predicted[v][before[v]] for v in self.views]
        latency = max(t for t, _ in got) - t0
        pred = np.stack([image_to_numpy(m)[None] if m.encoding == 'mono8'
                         else image_to_numpy(m).transpose(2, 0, 1) for _, m in got])
        self._settle(np.asarray(pressures), procs)
        stamp = self._snap(procs, 'actuation', -1, pressures)
        return pred, self.prepared(stamp), latency
