"""
The two camera_trigger processes under a trigger train: pair capture skew and latencies.

Two processes (main, side) play the same 640x480 MJPG file (the files stand in for the
cameras: same code path from trigger to publish, minus the USB transfer); a probe sends
200 triggers at 10 Hz and records, per trigger, both capture times (TimeReference) and when
each image reached a reliable subscriber (a second, best-effort subscription counts what
the sensor-data QoS would lose). Reported in ms: the pair's capture skew (median, p99, max; pairs
over the 10 ms bound), trigger-to-capture and trigger-to-publish-received latency, frames
missing. A histogram goes to bench_out/cameras_skew.png.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

N_TRIGGERS = 200
RATE_HZ = 10.0
FIG = Path(__file__).resolve().parent.parent / 'bench_out' / 'cameras_skew.png'


def _stats(values_ms) -> dict:
    a = np.asarray(values_ms, dtype=np.float64)
    if a.size == 0:
        return {'n': 0}
    return {'n': int(a.size), 'median': round(float(np.median(a)), 3),
            'p99': round(float(np.percentile(a, 99)), 3), 'max': round(float(a.max()), 3)}


def _start(camera: str, source: Path) -> subprocess.Popen:
    code = 'from softshape_ros.nodes.camera_trigger import main; main()'
    return subprocess.Popen(
        [sys.executable, '-c', code, '--ros-args', '-r', f'__node:=camera_{camera}',
         '-p', f'camera_name:={camera}', '-p', f'source:={source}', '-p', 'fps:=30.0'],
        env=dict(os.environ), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _figure(skew_ms, bound_ms: float) -> str:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    FIG.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.hist(skew_ms, bins=40, color='tab:blue')
    ax.axvline(bound_ms, color='tab:red', ls='--', label=f'bound {bound_ms:g} ms')
    ax.set_xlabel('capture skew main vs side (ms)')
    ax.set_ylabel('trigger pairs')
    ax.set_title(f'camera_trigger x2, {len(skew_ms)} triggers at {RATE_HZ:g} Hz')
    ax.legend()
    fig.tight_layout()
    fig.savefig(FIG, dpi=100)
    plt.close(fig)
    return str(FIG)


def run() -> dict:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Image, TimeReference
    from std_msgs.msg import Header

    from softshape_ros.config import load_rig_config
    from softshape_ros.nodes.common import RELIABLE_QOS, SENSOR_QOS, ns_to_stamp, stamp_to_ns
    from softshape_ros.vision.patterns import write_video

    cfg = load_rig_config()
    t = cfg.topics
    cams = ('main', 'side')
    tmp = Path(tempfile.mkdtemp(prefix='bench_cameras_'))
    video = write_video(tmp / 'clip.avi', 24, fps=30.0, width=640, height=480)
    capture = {c: {} for c in cams}
    received = {c: {} for c in cams}
    received_best_effort = {c: {} for c in cams}
    lock = threading.Lock()

    rclpy.init()
    node = rclpy.create_node('bench_cameras_probe')
    pub = node.create_publisher(Header, t.trigger, RELIABLE_QOS)

    def on_time(c, m):
        with lock:
            capture[c][stamp_to_ns(m.header.stamp)] = stamp_to_ns(m.time_ref)

    def on_image(c, m, where):
        now = time.time_ns()
        with lock:
            where[c][stamp_to_ns(m.header.stamp)] = now

    for c in cams:
        node.create_subscription(TimeReference, t.camera('capture_time', c),
                                 lambda m, c=c: on_time(c, m), RELIABLE_QOS)
        node.create_subscription(Image, t.camera('camera_image', c),
                                 lambda m, c=c: on_image(c, m, received), RELIABLE_QOS)
        node.create_subscription(Image, t.camera('camera_image', c),
                                 lambda m, c=c: on_image(c, m, received_best_effort),
                                 SENSOR_QOS)
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    stop = threading.Event()
    spinner = threading.Thread(target=lambda: [ex.spin_once(timeout_sec=0.05)
                                               for _ in iter(stop.is_set, True)], daemon=True)
    spinner.start()
    procs = [_start(c, video) for c in cams]
    sent = []
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not (
                pub.get_subscription_count() >= 2
                and all(node.count_publishers(t.camera('camera_image', c)) for c in cams)):
            time.sleep(0.1)
        time.sleep(1.0)
        for _ in range(N_TRIGGERS):
            ns = time.time_ns()
            pub.publish(Header(stamp=ns_to_stamp(ns)))
            sent.append(ns)
            time.sleep(1.0 / RATE_HZ)
        time.sleep(1.0)
    finally:
        for p in procs:
            p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
        stop.set()
        spinner.join(timeout=5)
        node.destroy_node()
        rclpy.try_shutdown()

    with lock:
        pairs = [s for s in sent if all(s in capture[c] for c in cams)]
        skew = [abs(capture['main'][s] - capture['side'][s]) / 1e6 for s in pairs]
        to_capture = [(capture[c][s] - s) / 1e6 for c in cams for s in sent if s in capture[c]]
        to_publish = [(received[c][s] - s) / 1e6 for c in cams for s in sent
                      if s in received[c]]
        missing = {c: sum(s not in received[c] for s in sent) for c in cams}
        missing_be = {c: sum(s not in received_best_effort[c] for s in sent) for c in cams}
    bound_ms = cfg.collection.max_capture_skew_s * 1e3
    return {
        'triggers': N_TRIGGERS, 'rate_hz': RATE_HZ, 'frame': '640x480 rgb8 (MJPG file)',
        'pair_skew_ms': _stats(skew),
        'pairs_over_bound': int(sum(s > bound_ms for s in skew)),
        'trigger_to_capture_ms': _stats(to_capture),
        'trigger_to_image_received_ms': _stats(to_publish),
        'images_missing_reliable_subscriber': missing,
        'images_missing_best_effort_subscriber': missing_be,
        'figure': _figure(skew, bound_ms) if skew else None,
    }


if __name__ == '__main__':
    import json
    print(json.dumps(run(), indent=2))
