"""
What every softshape node shares: start/stop, QoS, image and stamp conversion, diagnostics.

Nodes stay thin adapters (parameters in, core call, message out); the pieces here are
the adapters' adapters, so that each node file reads like ros2/demos' talker/listener.
"""

from __future__ import annotations

import gc
import signal
import sys
import threading
from typing import Callable

import numpy as np
import rclpy
import rclpy.logging
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.executors import (ExternalShutdownException, MultiThreadedExecutor,
                             SingleThreadedExecutor)
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)
from sensor_msgs.msg import Image

from softshape_ros.config import RigConfig, load_rig_config
from softshape_ros.transport import TransportProfileError, configure_transport
from softshape_ros.nodes.parameters import Param, declare
from softshape_ros.vision.image_msg import ENCODINGS, decode_image, stamp_ns

#: The sensor-data profile (best effort, keep last 5), docs/design.md's choice for images.
SENSOR_QOS = qos_profile_sensor_data
#: Camera and predicted images, CameraInfo: keep-last 5 like SENSOR_QOS, but offered reliable.
#: Best-effort subscribers (viewers, SENSOR_QOS) still match; reliable ones (the recorder
#: adapts to its publishers) get every frame: a 640x480 best-effort frame is lost whenever
#: one of its ~15 UDP fragments is (benchmarks/bench_cameras.py measures both).
IMAGE_QOS = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE,
                       history=HistoryPolicy.KEEP_LAST)
#: Commands, measurements, triggers: reliable, modest depth.
RELIABLE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                          history=HistoryPolicy.KEEP_LAST)
#: The scene description is latched so late joiners (recorder, inference) get it.
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL,
                         history=HistoryPolicy.KEEP_LAST)

OK, WARN, ERROR, STALE = (DiagnosticStatus.OK, DiagnosticStatus.WARN,
                          DiagnosticStatus.ERROR, DiagnosticStatus.STALE)


#: Every node's first parameter: which rig.yaml to load.
CONFIG_FILE = Param('config_file', '', "the rig config YAML ('' = the installed config/rig.yaml)")


def declare_rig_config(node: Node) -> RigConfig:
    """Declare the ``config_file`` parameter ('' = the package's rig.yaml) and load it."""
    path = declare(node, [CONFIG_FILE]).config_file
    return load_rig_config(path or None)


#: Stamp conversion and image decoding are shared with the (rclpy-free) dataset builder.
stamp_to_ns = stamp_ns


def ns_to_stamp(ns: int) -> Time:
    return Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def numpy_to_image(array: np.ndarray, stamp: Time, frame_id: str, encoding: str = '') -> Image:
    """H x W (mono8) or H x W x 3 (rgb8) uint8 -> sensor_msgs/Image (no cv_bridge needed)."""
    a = np.ascontiguousarray(array)
    if a.dtype != np.uint8:
        raise ValueError(f'image must be uint8, got {a.dtype}')
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if not encoding:
        encoding = 'mono8' if a.ndim == 2 else 'rgb8'
    ch = ENCODINGS.get(encoding)
    if ch is None or (a.ndim == 2) != (ch == 1) or (a.ndim == 3 and a.shape[2] != ch):
        raise ValueError(f'array of shape {a.shape} does not fit encoding {encoding}')
    msg = Image()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = int(a.shape[0]), int(a.shape[1])
    msg.encoding = encoding
    msg.is_bigendian = 0
    msg.step = msg.width * ch
    msg.data = a.tobytes()
    return msg


def image_to_numpy(msg: Image) -> np.ndarray:
    """sensor_msgs/Image -> H x W or H x W x 3 RGB uint8 (own copy); ValueError if malformed."""
    return decode_image(msg).copy()


def diagnostic_status(name: str, hardware_id: str, level, message: str,
                      values: dict) -> DiagnosticStatus:
    st = DiagnosticStatus()
    st.level = bytes([level]) if isinstance(level, int) else level
    st.name, st.hardware_id, st.message = name, hardware_id, message
    st.values = [KeyValue(key=str(k), value=str(v)) for k, v in values.items()]
    return st


def publish_diagnostics(node: Node, publisher, statuses: list[DiagnosticStatus]) -> None:
    arr = DiagnosticArray()
    arr.header.stamp = node.get_clock().now().to_msg()
    arr.status = statuses
    publisher.publish(arr)


def log_at(node: Node, level: str, text: str) -> None:
    """
    Log ``text`` at ``level`` ('info', 'warn'/'warning', else error) through the node's logger.

    One call site per severity: rclpy refuses a call site whose severity changes.
    """
    logger = node.get_logger()
    if level == 'info':
        logger.info(text)
    elif level in ('warn', 'warning'):
        logger.warning(text)
    else:
        logger.error(text)


def freeze_heap() -> None:
    """
    Move every object alive now out of the garbage collector's sight (``gc.freeze``).

    A full (generation-2) collection walks every tracked object while holding the GIL. After
    importing torch, rosbags' type store or matplotlib that is 200k-400k objects: 0.1-1 s of
    CPU, seconds of wall time on a busy machine, during which no thread of the process runs
    (timers, callbacks, the serial link's heartbeat). Found with ``py-spy dump --native``
    during such a stall (docs/transport.md). Called once a node is built, later collections
    only walk what the node allocates while it runs.
    """
    gc.collect()
    gc.freeze()


def run_node(factory: Callable[[], Node], args=None, multithreaded: bool = False) -> int:
    """
    Init rclpy, spin the node until SIGINT/SIGTERM, clean up, return the exit code.

    The DDS transport is configured first (``configure_transport``: the package's Fast DDS
    profile unless the user chose one), because Fast DDS reads its profiles once, when the
    process's first participant is created.

    Nodes may define ``on_shutdown()`` (e.g. vent the pressures); it runs after spinning
    stops and before the node is destroyed, whatever stopped it, with the ROS context still
    up so it can publish. For that, rclpy's own signal handlers (which shut the context down
    first) are not installed. While the node is being made SIGINT/SIGTERM raise
    KeyboardInterrupt; once it spins they only end the loop (``_stop_on_signals``), which
    spins in 0.1 s slices so the signal is seen promptly.
    """
    try:
        transport = configure_transport()
    except TransportProfileError as exc:
        rclpy.logging.get_logger('softshape').fatal(str(exc))
        return 2
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    code = 0
    try:
        node = factory()
        node.get_logger().info(
            f'DDS transport: {transport.reason}'
            + (f' ({transport.profile})' if transport.profile else ''))
        executor = MultiThreadedExecutor() if multithreaded else SingleThreadedExecutor()
        executor.add_node(node)
        freeze_heap()
        stop = _stop_on_signals()
        while rclpy.ok() and not stop.is_set():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as exc:  # a clear message, not a traceback wall, and a failing exit code
        name = node.get_name() if node is not None else 'softshape'
        rclpy.logging.get_logger(name).fatal(str(exc))
        code = 1
    finally:
        if node is not None:
            hook = getattr(node, 'on_shutdown', None)
            if hook is not None:
                # A second Ctrl-C or SIGTERM must not cut a vent or a bag finalisation short.
                signal.signal(signal.SIGINT, signal.SIG_IGN)
                signal.signal(signal.SIGTERM, signal.SIG_IGN)
                try:
                    hook()
                except Exception as exc:
                    node.get_logger().error(f'shutdown hook failed: {exc}')
                    code = code or 1
            node.destroy_node()
        if rclpy.ok():
            rclpy.try_shutdown()
    return code


def _stop_on_signals() -> threading.Event:
    """
    Make SIGINT/SIGTERM set the returned event instead of raising KeyboardInterrupt.

    Raised while the executor is inside one of rclpy's C calls (e.g. taking a service
    request), the interrupt comes out as a SystemError ("returned a result with an exception
    set"): a clean Ctrl-C exited 1 now and then. Only the main thread may set handlers.
    """
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    return stop


def main_wrapper(factory: Callable[[], Node]) -> Callable[[], int]:
    """Build a console-script ``main`` that exits with run_node's code (SIGTERM like SIGINT)."""
    def main(args=None) -> int:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, signal.default_int_handler)
        sys.exit(run_node(factory, args=args))
    return main
