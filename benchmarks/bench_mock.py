"""
mock_hardware benchmark: free run and trigger latency across processes, the record stage.

mock_hardware runs in its own process at the configured 640x480; this process subscribes
(reliable, as the recorder) to both cameras. Reported (never asserted): frames received per
second per camera over a window with free run at 30 Hz; trigger-to-image latency (trigger
stamp to the second camera's image received here; the node's own trigger-to-images-made
figure from its /diagnostics beside it), each trigger after a new random command has
settled (a new shape each; a fresh solve at the trigger unless the node solved the command
on arrival), with free run on and off; the demo's record stage
(mock_hardware + recorder + collector at 2 Hz, ``pipeline.record``) wall time against
triggers / 2 Hz. With MOCK_BENCH_BASELINE=<checkout> the same runs on that checkout's code
(its nodes run from its sources), side by side in one run. MOCK_BENCH_RECORD=0 skips the
record stages (the streams only). Transport: whatever the tree
configures (Fast DDS defaults unless a profile is set). Sizes: MOCK_BENCH_WINDOW_S (10),
MOCK_BENCH_TRIGGERS (40), MOCK_BENCH_SCENES x MOCK_BENCH_ACTUATIONS (3 x 20).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def _env(tree: str | None) -> dict:
    """Return the environment that runs ``tree``'s code (None: this one, as installed)."""
    env = dict(os.environ)
    if tree:
        env['PYTHONPATH'] = tree
        env.pop('AMENT_PREFIX_PATH', None)      # nodes then run from the tree's sources
    return env


def stream(tree: str | None, free_run_hz: float, window_s: float, triggers: int) -> dict:
    """Start mock_hardware from ``tree``; count frames over a window; time triggers."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Image
    from std_msgs.msg import Float64MultiArray, Header

    from softshape_ros.config import load_rig_config
    from softshape_ros.nodes.common import IMAGE_QOS, RELIABLE_QOS, ns_to_stamp, stamp_to_ns
    from softshape_ros.processes import NodeProcess

    cfg = load_rig_config()
    t = cfg.topics
    import softshape_ros
    logs = Path(tempfile.mkdtemp(prefix='bench_mock_'))
    mock = NodeProcess('mock_hardware', {'free_run_hz': free_run_hz, 'tau_s': 0.05},
                       log_dir=logs, env=_env(tree)).start()
    rclpy.init()
    node = rclpy.create_node('bench_mock_probe')
    lock = threading.Lock()
    got = {c: [] for c in cfg.camera_names}               # (stamp_ns, received_ns)

    def on_image(cam, msg):
        now = time.time_ns()
        with lock:
            got[cam].append((stamp_to_ns(msg.header.stamp), now))
    for cam in cfg.camera_names:
        node.create_subscription(Image, t.camera('camera_image', cam),
                                 lambda m, c=cam: on_image(c, m), IMAGE_QOS)
    diag = {}

    def on_diag(msg):
        for st in msg.status:
            if st.name == 'mock_hardware: cameras':
                diag.update({kv.key: kv.value for kv in st.values})
    node.create_subscription(DiagnosticArray, t.diagnostics, on_diag, RELIABLE_QOS)
    cmd = node.create_publisher(Float64MultiArray, t.pressure_command, RELIABLE_QOS)
    trig = node.create_publisher(Header, t.trigger, RELIABLE_QOS)
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    stop = threading.Event()

    def spin_until_stopped():
        while not stop.is_set():
            ex.spin_once(timeout_sec=0.05)
    spin = threading.Thread(target=spin_until_stopped, daemon=True)
    spin.start()
    out = {'free_run_hz': free_run_hz, 'code': softshape_ros.__file__}
    try:
        deadline = time.monotonic() + 120
        while not (cmd.get_subscription_count() and trig.get_subscription_count()):
            mock.check_alive()
            if time.monotonic() > deadline:
                raise RuntimeError('mock_hardware did not connect')
            time.sleep(0.1)
        time.sleep(2.0)                                    # let it start streaming
        if free_run_hz > 0:
            with lock:
                n0 = {c: len(v) for c, v in got.items()}
            t0 = time.monotonic()
            time.sleep(window_s)
            dt = time.monotonic() - t0
            with lock:
                out['received_hz'] = {c: round((len(v) - n0[c]) / dt, 2)
                                      for c, v in got.items()}
        rng = np.random.default_rng(0)
        limits = np.asarray(cfg.max_pressures_pa)
        stamps = []
        for _ in range(triggers):
            cmd.publish(Float64MultiArray(data=(rng.uniform(0, 0.6, 6) * limits).tolist()))
            time.sleep(0.35)                               # 7 tau: settled
            ns = time.time_ns()
            trig.publish(Header(stamp=ns_to_stamp(ns)))
            stamps.append(ns)
        time.sleep(3.0)                                    # diagnostics come every second
        out['node_diagnostics'] = dict(diag)
        with lock:
            seen = {c: dict(v) for c, v in got.items()}
        lat = []
        for ns in stamps:
            if all(ns in seen[c] for c in seen):
                lat.append((max(seen[c][ns] for c in seen) - ns) / 1e6)
        out['triggers'] = len(stamps)
        out['answered'] = len(lat)
        if lat:
            out['trigger_to_image_ms'] = {'median': round(float(np.median(lat)), 1),
                                          'p99': round(float(np.percentile(lat, 99)), 1),
                                          'max': round(float(max(lat)), 1)}
    finally:
        stop.set()
        spin.join(timeout=5)
        out['exit_code'] = mock.stop()
        node.destroy_node()
        rclpy.try_shutdown()
    return out


def record_stage(tree: str | None, scenes: int, actuations: int) -> dict:
    """Run the demo's record stage (its own processes) from ``tree``; return its timing."""
    out_dir = tempfile.mkdtemp(prefix='bench_record_')
    # wall_s: the whole stage, process starts and stops included (comparable between trees
    # whose `seconds` start at different points).
    code = ('import json, sys, time\n'
            'from softshape_ros.config import load_rig_config\n'
            'from softshape_ros.demo.pipeline import DemoSettings, Stage, record\n'
            f's = DemoSettings(out={out_dir!r}, scenes={scenes}, actuations={actuations})\n'
            't0 = time.monotonic()\n'
            'r = record(s, Stage(s, "record", True), load_rig_config())\n'
            'print(json.dumps({"seconds": r["seconds"], "triggers": r["triggers"], '
            '"wall_s": round(time.monotonic() - t0, 1), "exit_codes": r["exit_codes"]}))\n')
    res = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         env=_env(tree), cwd=tree or str(ROOT))
    if res.returncode != 0:
        return {'error': res.stderr[-1500:]}
    r = json.loads(res.stdout.strip().splitlines()[-1])
    floor = r['triggers'] / 2.0
    r.update(floor_s=floor, ratio_to_floor=round(r['seconds'] / floor, 3),
             code=tree or str(ROOT))
    return r


def _isolated(fn: str, tree: str | None, *args) -> dict:
    """
    Run ``fn(tree, *args)`` of this file in a fresh interpreter running ``tree``'s code.

    A fresh process each time: rclpy is initialised once per process, and the node it starts
    must come from the same tree (no colcon install on the path for another checkout).
    """
    code = ('import importlib.util, json, sys\n'
            'spec = importlib.util.spec_from_file_location("bench_mock", sys.argv[1])\n'
            'b = importlib.util.module_from_spec(spec); spec.loader.exec_module(b)\n'
            f'print(json.dumps(b.{fn}(*json.loads(sys.argv[2]))))\n')
    res = subprocess.run([sys.executable, '-c', code, __file__, json.dumps((tree,) + args)],
                         capture_output=True, text=True, env=_env(tree), cwd=tree or str(ROOT))
    if res.returncode != 0:
        return {'error': res.stderr[-1500:]}
    return json.loads(res.stdout.strip().splitlines()[-1])


def run() -> dict:
    window = float(os.environ.get('MOCK_BENCH_WINDOW_S', '10'))
    triggers = int(os.environ.get('MOCK_BENCH_TRIGGERS', '40'))
    scenes = int(os.environ.get('MOCK_BENCH_SCENES', '3'))
    actuations = int(os.environ.get('MOCK_BENCH_ACTUATIONS', '20'))
    base = os.environ.get('MOCK_BENCH_BASELINE')
    out = {'load_average': os.getloadavg(),
           'transport': os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE')
           or os.environ.get('FASTDDS_DEFAULT_PROFILES_FILE') or 'Fast DDS defaults'}
    out['free_run_30hz'] = _isolated('stream', None, 30.0, window, triggers)
    out['triggers_only'] = _isolated('stream', None, 0.0, window, triggers)
    record = os.environ.get('MOCK_BENCH_RECORD', '1') != '0'
    if record:
        out['record_stage'] = record_stage(None, scenes, actuations)
    if base:
        out['baseline_triggers'] = _isolated('stream', base, 30.0, window, triggers)
        out['baseline_triggers_only'] = _isolated('stream', base, 0.0, window, triggers)
        if record:
            out['baseline_record_stage'] = record_stage(base, scenes, actuations)
    out['load_average_after'] = os.getloadavg()
    return out
