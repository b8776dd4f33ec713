"""
Inference node over DDS: command -> predicted image latency, and the sustained prediction rate.

The node runs as its own process (as ``ros2 run`` starts it) with the default ``ours`` network;
this process plays camera, user and subscriber. Weights are untrained (latency does not depend
on them); the model-only time on one thread is reported beside the DDS figures.
"""

from __future__ import annotations

import tempfile
import threading
import time
from pathlib import Path

import numpy as np

N_LATENCY = 300
RATE_SECONDS = 5.0


def _checkpoint(root: Path, cfg) -> Path:
    from softshape_ros.model.checkpoint import save_checkpoint
    from softshape_ros.model.networks import build_network
    net = build_network('ours', len(cfg.camera_names), 1)
    return save_checkpoint(root / 'model', net, {
        'arch': 'ours', 'arch_params': {}, 'views': cfg.camera_names, 'channels': 1,
        'image_size': 64, 'max_pressure_pa': cfg.max_pressures_pa})


def _model_only_ms(ckpt) -> dict:
    import torch
    from softshape_ros.model import Predictor
    torch.set_num_threads(1)
    pred = Predictor.from_checkpoint(ckpt)
    x = np.zeros(pred.image_shape, np.uint8)
    for _ in range(20):
        pred.predict(x, [0] * 6)
    t = []
    for _ in range(200):
        t0 = time.perf_counter()
        pred.predict(x, [1e4] * 6)
        t.append((time.perf_counter() - t0) * 1e3)
    return {'median': float(np.median(t)), 'p99': float(np.percentile(t, 99))}


def run() -> dict:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Image
    from std_msgs.msg import Float64MultiArray, String

    from softshape_ros.config import load_rig_config
    from softshape_ros.nodes.common import IMAGE_QOS, LATCHED_QOS, RELIABLE_QOS, numpy_to_image
    from softshape_ros.processes import NodeProcess, wait_until

    cfg = load_rig_config()
    tmp = Path(tempfile.mkdtemp(prefix='bench_inference_'))
    ckpt = _checkpoint(tmp, cfg)
    model_ms = _model_only_ms(ckpt)
    rclpy.init()
    node = rclpy.create_node('bench_inference')
    t = cfg.topics
    views = cfg.camera_names
    received = []
    lock = threading.Lock()

    def on_pred(view, msg):
        with lock:
            received.append((time.perf_counter(), view))

    for v in views:
        node.create_subscription(Image, t.camera('predicted_image', v),
                                 lambda m, v=v: on_pred(v, m), IMAGE_QOS)
    cams = {v: node.create_publisher(Image, t.camera('camera_image', v), IMAGE_QOS)
            for v in views}
    scene = node.create_publisher(String, t.scene, LATCHED_QOS)
    cmd = node.create_publisher(Float64MultiArray, t.pressure_command, RELIABLE_QOS)
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    stop = False

    def spin():
        while not stop:
            ex.spin_once(timeout_sec=0.05)
    th = threading.Thread(target=spin, daemon=True)
    th.start()
    proc = NodeProcess('inference', {'model': str(ckpt), 'threads': 1, 'overlay': False},
                       log_dir=tmp).start()
    try:
        wait_until(lambda: node.count_subscribers(t.pressure_command) >= 1
                   and all(node.count_publishers(t.camera('predicted_image', v)) for v in views),
                   60, what='inference node', processes=(proc,))
        scene.publish(String(data='{"id": 0}'))
        time.sleep(0.5)
        frame = np.full((cfg.cameras[views[0]].height, cfg.cameras[views[0]].width, 3), 200,
                        np.uint8)
        for v in views:
            cams[v].publish(numpy_to_image(frame, node.get_clock().now().to_msg(), 'cam'))
        p = Float64MultiArray(data=[1e4] * 6)

        def n_full():
            with lock:
                return min(sum(1 for _, v in received if v == w) for w in views)
        wait_until(lambda: (cmd.publish(p), time.sleep(0.05), n_full() > 0)[2], 30,
                   what='first prediction (initial images taken)', processes=(proc,))
        time.sleep(0.5)
        lat = []
        for i in range(N_LATENCY):
            before = n_full()
            t0 = time.perf_counter()
            cmd.publish(Float64MultiArray(data=[float(i % 50) * 1e3] * 6))
            wait_until(lambda: n_full() > before, 10, period=0.0002, what='prediction')
            with lock:
                t1 = max(tt for tt, _ in received[-len(views):])
            lat.append((t1 - t0) * 1e3)
        before = n_full()
        t0 = time.perf_counter()
        sent = 0
        while time.perf_counter() - t0 < RATE_SECONDS:
            cmd.publish(Float64MultiArray(data=[float(sent % 50) * 1e3] * 6))
            sent += 1
            time.sleep(0.001)
        time.sleep(0.3)
        rate = (n_full() - before) / RATE_SECONDS
    finally:
        code = proc.stop()
        stop = True
        th.join(timeout=2)
        node.destroy_node()
        rclpy.try_shutdown()
    return {
        'command_to_predicted_image_ms': {'median': float(np.median(lat)),
                                          'p99': float(np.percentile(lat, 99)),
                                          'n': len(lat), 'target_median_below': 10.0},
        'sustained_predictions_per_s': {'value': rate, 'commands_sent_per_s': sent / RATE_SECONDS,
                                        'target_at_least': 100.0},
        'model_only_ms_one_thread': model_ms,
        'views': views, 'node_exit_code': code,
        'note': 'inference as its own process; one prediction = both views published; '
                'untrained default ours network (timing does not depend on the weights)',
    }
