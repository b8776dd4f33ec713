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

import time

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image, TimeReference
from std_msgs.msg import Header

from softshape_ros.nodes.common import (ERROR, IMAGE_QOS, OK, RELIABLE_QOS, SENSOR_QOS, WARN,
                                        declare_rig_config, diagnostic_status, main_wrapper,
                                        ns_to_stamp, numpy_to_image, publish_diagnostics,
                                        stamp_to_ns)
from softshape_ros.vision.camera_info import (Calibration, CalibrationError,
                                              default_calibration_path, load_calibration)
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


class CameraTrigger(Node):
    """Trigger-driven camera publisher with reconnect, skew and latency diagnostics."""

    def __init__(self, **kwargs):
        super().__init__('camera_trigger', **kwargs)
        self.cfg = declare_rig_config(self)
        par = self.declare_parameter
        self.camera = par('camera_name', 'main').value
        if self.camera not in self.cfg.cameras:
            raise ValueError(f'camera_name {self.camera!r} is not in {self.cfg.source} '
                             f'(cameras: {", ".join(self.cfg.camera_names)})')
        self.source_spec = str(par('source', '/dev/video0').value)
        self.width = int(par('width', 0).value)
        self.height = int(par('height', 0).value)
        self.fps = float(par('fps', 0.0).value)
        self.pixel_format = str(par('pixel_format', '').value)
        self.free_run = bool(par('free_run', False).value)
        self.capture_timeout_s = float(par('capture_timeout_s', 0.5).value)
        self.max_trigger_age_s = float(par('max_trigger_age_s', 0.5).value)
        self.reconnect_period_s = float(par('reconnect_period_s', 1.0).value)
        bound = float(par('max_capture_skew_s', -1.0).value)
        self.skew_bound_s = bound if bound >= 0 else self.cfg.collection.max_capture_skew_s
        info_url = str(par('camera_info_url', '').value)
        diag_period = float(par('diagnostics_period_s', 1.0).value)

        cam = self.cfg.cameras[self.camera]
        self.frame_id = cam.frame_id
        path = info_url.removeprefix('file://') or str(default_calibration_path(self.camera))
        try:
            self.calibration = load_calibration(path)
        except CalibrationError as exc:
            raise ValueError(f'camera_info_url: {exc}') from None

        topics = self.cfg.topics
        qos = IMAGE_QOS if par('reliable_images', True).value else SENSOR_QOS
        self.pub_image = self.create_publisher(
            Image, topics.camera('camera_image', self.camera), qos)
        self.pub_info = self.create_publisher(
            CameraInfo, topics.camera('camera_info', self.camera), qos)
        self.pub_time = self.create_publisher(
            TimeReference, topics.camera('capture_time', self.camera), RELIABLE_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, topics.diagnostics, RELIABLE_QOS)
        self.create_subscription(Header, topics.trigger, self._on_trigger, RELIABLE_QOS)

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
        self.dropped = 0
        self.reconnects = 0
        self.last_frame_size = None
        self._open_source()
        self.create_timer(max(0.05, self.reconnect_period_s), self._reconnect)
        self.create_timer(max(0.05, diag_period), self._publish_diagnostics)
        if self.free_run:
            rate = self.fps if self.fps > 0 else 30.0
            self.create_timer(1.0 / rate, self._free_run_tick)
        self.get_logger().info(
            f'camera {self.camera}: source {self.source_spec!r}, calibration {path}, '
            f'{"free-run + " if self.free_run else ""}trigger on {topics.trigger}')

    # -- source management -------------------------------------------------------------
    def _open_source(self) -> bool:
        try:
            self.source = open_source(self.source_spec, self.width, self.height, self.fps,
                                      self.pixel_format)
        except CaptureError as exc:
            self.source = None
            if str(exc) != self.error:
                self.get_logger().error(f'camera {self.camera}: {exc}; retrying every '
                                        f'{self.reconnect_period_s:g} s')
            self.error = str(exc)
            return False
        if self.error:
            self.reconnects += 1
            self.get_logger().info(f'camera {self.camera}: {self.source.description} '
                                   f'is back (reconnect {self.reconnects})')
        self.error = ''
        self._publish_diagnostics()
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
        self._publish_diagnostics()

    def _reconnect(self) -> None:
        if self.source is None:
            if self._open_source():
                self._publish_diagnostics()

    def _capture(self):
        if self.source is None:
            return None
        try:
            return self.source.capture(self.capture_timeout_s)
        except CaptureError as exc:
            self._lose_source(exc)
            return None

    # -- publishing ----------------------------------------------------------------------
    def _publish_frame(self, frame, stamp) -> None:
        img = frame.image
        h, w = img.shape[:2]
        cal = self.calibration.scaled(w, h)
        self.last_frame_size = (w, h)
        self.pub_image.publish(numpy_to_image(img, stamp, self.frame_id, 'rgb8'))
        self.pub_info.publish(camera_info_msg(cal, stamp, self.frame_id))
        self.pub_time.publish(time_reference_msg(stamp, frame.capture_ns, self.camera,
                                                 self.frame_id))
        self.frames += 1

    def _on_trigger(self, msg: Header) -> None:
        trig_ns = stamp_to_ns(msg.stamp)
        age = time.time_ns() - trig_ns
        if age > self.max_trigger_age_s * 1e9:
            self.dropped += 1
            self.get_logger().warning(
                f'camera {self.camera}: trigger {trig_ns} arrived {age / 1e9:.3f} s late '
                f'(> {self.max_trigger_age_s:g} s): no frame for it')
            return
        frame = self._capture()
        if frame is None:
            self.dropped += 1
            return
        self._publish_frame(frame, msg.stamp)
        done = time.time_ns()
        self.latency_capture.add((frame.capture_ns - trig_ns) / 1e9)
        self.latency_publish.add((done - trig_ns) / 1e9)
        self._pair(self.camera, trig_ns, frame.capture_ns)

    def _free_run_tick(self) -> None:
        frame = self._capture()
        if frame is not None:
            self._publish_frame(frame, ns_to_stamp(frame.capture_ns))

    def _on_peer_time(self, camera: str, msg: TimeReference) -> None:
        self._pair(camera, stamp_to_ns(msg.header.stamp), stamp_to_ns(msg.time_ref))

    def _pair(self, camera: str, stamp_ns: int, capture_ns: int) -> None:
        res = self.skew.add(camera, stamp_ns, capture_ns)
        if res is not None and res[1]:
            self.get_logger().warning(
                f'camera pair at stamp {stamp_ns}: capture skew {res[0] * 1e3:.1f} ms > '
                f'{self.skew_bound_s * 1e3:g} ms: flagged (the dataset builder drops it)')

    def _publish_diagnostics(self) -> None:
        skew = self.skew.stats.summary()
        values = {
            'source': self.source_spec, 'frames': self.frames, 'dropped_triggers': self.dropped,
            'reconnects': self.reconnects, 'frame_size': self.last_frame_size,
            'trigger_to_capture_ms': self.latency_capture.summary(),
            'trigger_to_publish_ms': self.latency_publish.summary(),
            'pair_skew_ms': skew, 'pairs_over_bound': self.skew.flagged,
            'skew_bound_ms': self.skew_bound_s * 1e3,
            'last_flagged_stamp_ns': self.skew.last_flagged_stamp_ns,
        }
        if self.source is None:
            level, message = ERROR, f'no camera: {self.error}'
        elif self.skew.flagged:
            level, message = WARN, (f'{self.skew.flagged} pair(s) with capture skew over '
                                    f'{self.skew_bound_s * 1e3:g} ms')
        else:
            level, message = OK, f'capturing from {self.source.description}'
        publish_diagnostics(self, self.pub_diag, [diagnostic_status(
            f'camera_trigger: {self.camera}', self.source_spec, level, message, values)])

    def on_shutdown(self) -> None:
        if self.source is not None:
            self.source.close()
            self.source = None


main = main_wrapper(CameraTrigger)
