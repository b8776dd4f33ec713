"""
One camera of the rig: on each /rig/trigger, publish the freshest frame under the trigger's stamp.

Run one instance per camera (``camera_name:=main|side``). Besides the image and CameraInfo
it publishes a TimeReference per frame (header.stamp = trigger stamp, time_ref = when the
frame was really captured) so the pair's capture skew can be measured, and it pairs its own
capture times with the other cameras' to report that skew and flag pairs beyond the bound.
A missing or dying camera gives a diagnostics ERROR and reconnect attempts, never a crash
and never a frame under a stamp it does not belong to.
"""

from __future__ import annotations

from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image, TimeReference
from sensor_msgs.srv import SetCameraInfo
from std_msgs.msg import Header

from softshape_ros.nodes.clocks import ros_now_ns, steady_timer, wall_to_ros_ns
from softshape_ros.nodes.common import (IMAGE_QOS, RELIABLE_QOS, SENSOR_QOS, declare_rig_config,
                                        main_wrapper, ns_to_stamp, numpy_to_image, stamp_to_ns)
from softshape_ros.nodes.diagnostics import (ERROR, OK, WARN, TriggeredRate, Updater, fill,
                                             matched_subscribers, topic_frequency)
from softshape_ros.nodes.parameters import Param, declare
from softshape_ros.vision.camera_info import (Calibration, CalibrationError, load_calibration,
                                              resolve_url, save_calibration)
from softshape_ros.vision.capture import CaptureError, open_source
from softshape_ros.vision.sync import RollingStats, SkewTracker

#: Peer capture times: a deep reader queue so a busy moment does not lose pairings.
PEER_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                      history=HistoryPolicy.KEEP_LAST)


def camera_info_msg(cal: Calibration, stamp, frame_id: str) -> CameraInfo:
    """Build a CameraInfo from a calibration (shared with mock_hardware)."""
    msg = CameraInfo()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.width, msg.height = int(cal.width), int(cal.height)
    msg.distortion_model = cal.distortion_model
    msg.d = [float(v) for v in cal.d]
    msg.k = [float(v) for v in cal.k]
    msg.r = [float(v) for v in cal.r]
    msg.p = [float(v) for v in cal.p]
    return msg


def time_reference_msg(stamp, capture_ns: int, camera: str, frame_id: str) -> TimeReference:
    """Build the per-frame capture-time record (shared with mock_hardware)."""
    msg = TimeReference()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.time_ref = ns_to_stamp(capture_ns)
    msg.source = camera
    return msg


def parameters(cfg) -> list[Param]:
    """List what the camera node takes (choices and defaults from rig.yaml)."""
    return [
        Param('camera_name', 'main', 'which camera of rig.yaml this is',
              choices=tuple(cfg.camera_names)),
        Param('source', '/dev/video0', 'a device index (0), /dev/video*, a video file or an '
              'image folder', dynamic=True),
        Param('width', 0, 'device width, px (0 = driver default)', (0, 16384)),
        Param('height', 0, 'device height, px (0 = driver default)', (0, 16384)),
        Param('fps', 0.0, 'device rate; playback rate of files and folders (0 = own / 10)',
              (0.0, 1000.0)),
        Param('pixel_format', '', "device FOURCC, e.g. MJPG or YUYV ('' = driver default)"),
        Param('camera_info_url', '', "calibration URL: file://, package://, ${NAME} ('' = "
              'config/camera_info/<camera_name>.yaml)'),
        Param('reliable_images', True, 'offer images reliably (best-effort viewers still '
              'match); false: the plain sensor-data profile'),
        Param('free_run', False, 'also publish at the camera rate (stamp = capture time)'),
        Param('capture_timeout_s', 0.5, 'a trigger with no frame in this time gets none',
              (0.01, 60.0), live=True),
        Param('max_trigger_age_s', 0.5, 'older triggers (ROS time) are dropped, not answered '
              'late', (0.0, 3600.0), live=True),
        Param('reconnect_period_s', 1.0, 'retry a missing camera this often', (0.05, 3600.0)),
        Param('max_capture_skew_s', -1.0, 'pair skew bound; < 0 = rig.yaml '
              'collection.max_capture_skew_s', (-1.0, 10.0)),
    ]


class CameraTrigger(Node):
    """Trigger-driven camera publisher with reconnect, skew and latency diagnostics."""

    def __init__(self, **kwargs):
        super().__init__('camera_trigger', **kwargs)
        self.cfg = declare_rig_config(self)
        self.params = p = declare(self, parameters(self.cfg))
        self.camera = p.camera_name
        self.source_spec = str(p.source)          # an index arrives as an integer
        bound = p.max_capture_skew_s
        self.skew_bound_s = bound if bound >= 0 else self.cfg.collection.max_capture_skew_s

        cam = self.cfg.cameras[self.camera]
        self.frame_id = cam.frame_id
        try:
            self.calibration_path = resolve_url(p.camera_info_url, self.camera)
            self.calibration = load_calibration(self.calibration_path)
        except CalibrationError as exc:
            raise ValueError(f'camera_info_url: {exc}') from None

        topics = self.cfg.topics
        qos = IMAGE_QOS if p.reliable_images else SENSOR_QOS
        self.image_topic = topics.camera('camera_image', self.camera)
        self.pub_image = self.create_publisher(Image, self.image_topic, qos)
        self.pub_info = self.create_publisher(
            CameraInfo, topics.camera('camera_info', self.camera), qos)
        self.pub_time = self.create_publisher(
            TimeReference, topics.camera('capture_time', self.camera), RELIABLE_QOS)
        self.create_subscription(Header, topics.trigger, self._on_trigger, RELIABLE_QOS)
        # camera_calibration commits here; the name is camera_info_manager's
        self.create_service(SetCameraInfo, '~/set_camera_info', self._on_set_camera_info)

        self.skew = SkewTracker(self.cfg.camera_names, self.skew_bound_s)
        for other in self.cfg.camera_names:
            if other != self.camera:
                self.create_subscription(
                    TimeReference, topics.camera('capture_time', other),
                    lambda m, o=other: self._on_peer_time(o, m), PEER_QOS)

        self.latency_capture = RollingStats()
        self.latency_publish = RollingStats()
        self.source = None
        self.error = ''
        self.frames = 0
        self.triggers = 0
        self.dropped = 0
        self.reconnects = 0
        self.last_frame_size = None
        self.diagnostics = Updater(self)
        self.diagnostics.setHardwareID(self.source_spec)
        self.diagnostics.add(f'{self.camera} camera', self._diagnose_camera)
        if p.free_run:
            rate = p.fps if p.fps > 0 else 30.0
            self.image_rate = topic_frequency(self.diagnostics, self.image_topic, rate)
        else:
            self.image_rate = TriggeredRate(self.diagnostics, self.image_topic)
        self._open_source()
        steady_timer(self, p.reconnect_period_s, self._reconnect)
        if p.free_run:
            steady_timer(self, 1.0 / rate, self._free_run_tick)
        self.get_logger().info(
            f'camera {self.camera}: source {self.source_spec!r}, calibration '
            f'{self.calibration_path}, {"free-run + " if p.free_run else ""}trigger on '
            f'{topics.trigger}')

    # -- source management -------------------------------------------------------------
    def _open_source(self) -> bool:
        p = self.params
        try:
            self.source = open_source(self.source_spec, p.width, p.height, p.fps,
                                      p.pixel_format)
        except CaptureError as exc:
            self.source = None
            if str(exc) != self.error:
                self.get_logger().error(f'camera {self.camera}: {exc}; retrying every '
                                        f'{p.reconnect_period_s:g} s')
            self.error = str(exc)
            return False
        if self.error:
            self.reconnects += 1
            self.get_logger().info(f'camera {self.camera}: {self.source.description} '
                                   f'is back (reconnect {self.reconnects})')
        self.error = ''
        self.diagnostics.force_update()
        return True

    def _lose_source(self, exc: Exception) -> None:
        self.get_logger().error(f'camera {self.camera}: {exc}; closing and reconnecting')
        self.error = str(exc)
        if self.source is not None:
            try:
                self.source.close()
            except Exception:  # a dying device may fail to close; it is gone either way
                pass
        self.source = None
        self.diagnostics.force_update()

    def _reconnect(self) -> None:
        if self.source is None:
            self._open_source()

    def _capture(self):
        if self.source is None:
            return None
        try:
            return self.source.capture(self.params.capture_timeout_s)
        except CaptureError as exc:
            self._lose_source(exc)
            return None

    # -- publishing ----------------------------------------------------------------------
    def _publish_frame(self, frame, stamp, capture_ns: int) -> None:
        img = frame.image
        h, w = img.shape[:2]
        cal = self.calibration.scaled(w, h)
        self.last_frame_size = (w, h)
        self.pub_image.publish(numpy_to_image(img, stamp, self.frame_id, 'rgb8'))
        self.pub_info.publish(camera_info_msg(cal, stamp, self.frame_id))
        self.pub_time.publish(time_reference_msg(stamp, capture_ns, self.camera,
                                                 self.frame_id))
        self.image_rate.tick()
        self.frames += 1

    def _on_trigger(self, msg: Header) -> None:
        trig_ns = stamp_to_ns(msg.stamp)
        self.triggers += 1
        age = ros_now_ns(self) - trig_ns          # both ROS time (sim time under use_sim_time)
        max_age = self.params.max_trigger_age_s
        if age > max_age * 1e9:
            self._missed()
            self.get_logger().warning(
                f'camera {self.camera}: trigger {trig_ns} arrived {age / 1e9:.3f} s late '
                f'(> {max_age:g} s): no frame for it')
            return
        frame = self._capture()
        if frame is None:
            self._missed()
            return
        capture_ns = wall_to_ros_ns(self, frame.capture_ns)
        self._publish_frame(frame, msg.stamp, capture_ns)
        done = ros_now_ns(self)
        self.latency_capture.add((capture_ns - trig_ns) / 1e9)
        self.latency_publish.add((done - trig_ns) / 1e9)
        self._pair(self.camera, trig_ns, capture_ns)

    def _missed(self) -> None:
        self.dropped += 1
        if isinstance(self.image_rate, TriggeredRate):
            self.image_rate.miss()

    def _free_run_tick(self) -> None:
        frame = self._capture()
        if frame is not None:
            capture_ns = wall_to_ros_ns(self, frame.capture_ns)
            self._publish_frame(frame, ns_to_stamp(capture_ns), capture_ns)

    def _on_peer_time(self, camera: str, msg: TimeReference) -> None:
        self._pair(camera, stamp_to_ns(msg.header.stamp), stamp_to_ns(msg.time_ref))

    def _pair(self, camera: str, stamp_ns: int, capture_ns: int) -> None:
        res = self.skew.add(camera, stamp_ns, capture_ns)
        if res is not None and res[1]:
            self.get_logger().warning(
                f'camera pair at stamp {stamp_ns}: capture skew {res[0] * 1e3:.1f} ms > '
                f'{self.skew_bound_s * 1e3:g} ms: flagged (the dataset builder drops it)')

    def _on_set_camera_info(self, request, response):
        """Store a new calibration (camera_calibration's commit): write the YAML, use it."""
        m = request.camera_info
        cal = Calibration(self.camera, int(m.width), int(m.height), tuple(m.k), tuple(m.d),
                          tuple(m.r), tuple(m.p), m.distortion_model or 'plumb_bob')
        try:
            path = save_calibration(cal, self.calibration_path)
        except CalibrationError as exc:
            response.success, response.status_message = False, str(exc)
            self.get_logger().error(f'set_camera_info refused: {exc}')
            return response
        self.calibration = cal
        response.success, response.status_message = True, f'calibration written to {path}'
        self.get_logger().info(response.status_message)
        return response

    def _diagnose_camera(self, stat):
        skew = self.skew.stats.summary()
        values = {
            'source': self.source_spec, 'frames': self.frames, 'triggers': self.triggers,
            'dropped_triggers': self.dropped, 'reconnects': self.reconnects,
            'frame_size': self.last_frame_size, 'calibration': self.calibration_path,
            'trigger_to_capture_ms': self.latency_capture.summary(),
            'trigger_to_publish_ms': self.latency_publish.summary(),
            'pair_skew_ms': skew, 'last_pair_stamp_ns': self.skew.last_pair_stamp_ns,
            'pairs_over_bound': self.skew.flagged,
            'skew_bound_ms': self.skew_bound_s * 1e3,
            'last_flagged_stamp_ns': self.skew.last_flagged_stamp_ns,
            **matched_subscribers([self.pub_image, self.pub_info, self.pub_time]),
        }
        if self.source is None:
            level, message = ERROR, f'no camera: {self.error}'
        elif self.skew.flagged:
            level, message = WARN, (f'{self.skew.flagged} pair(s) with capture skew over '
                                    f'{self.skew_bound_s * 1e3:g} ms')
        else:
            level, message = OK, f'capturing from {self.source.description}'
        return fill(stat, level, message, values)

    def on_shutdown(self) -> None:
        if self.source is not None:
            self.source.close()
            self.source = None


main = main_wrapper(CameraTrigger)
