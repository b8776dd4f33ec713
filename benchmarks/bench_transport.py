"""
Large frames between processes: Fast DDS's defaults against the package's transport profile.

Two cameras (main, side) in one publisher process stream RGB frames at 30 Hz to a subscriber
process holding, per camera, a best-effort subscription (the sensor-data profile of viewers)
and a reliable one (keep-last 5, like the recorder's), for {640x480, 1920x1080} x {publisher
offered reliable, publisher best effort} x {Fast DDS defaults, config/fastdds.xml}. Reported
per case: frames received / published per subscription kind, latency publish-to-callback
(median / p99 / max ms), and each process's CPU share over the stream. Both processes configure
their transport exactly as the nodes do (``configure_transport``), before ``rclpy.init``.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import threading
import time

import numpy as np

from benchmarks.bench_cameras import _stats   # n, median, p99, max (ms)

RATE_HZ = 30.0
SECONDS = 5.0
CAMERAS = ('main', 'side')
SIZES = ((640, 480), (1920, 1080))
DRAIN_S = 2.0


def _qos(kind: str):
    from softshape_ros.nodes.common import IMAGE_QOS, SENSOR_QOS
    return IMAGE_QOS if kind == 'reliable' else SENSOR_QOS


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _init_ros():
    from softshape_ros.transport import configure_transport
    choice = configure_transport()
    import rclpy
    rclpy.init()
    return rclpy, choice


def subscriber_main() -> None:
    """Child: count frames per (camera, QoS kind); print JSON on 'stop' from stdin."""
    rclpy, choice = _init_ros()
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Image
    node = rclpy.create_node('bench_transport_sub')
    lat = {(c, k): [] for c in CAMERAS for k in ('best_effort', 'reliable')}
    lock = threading.Lock()

    def make_cb(key):
        def cb(msg):
            now = time.time_ns()
            sent = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            with lock:
                lat[key].append((now - sent) / 1e6)
        return cb
    subs = [node.create_subscription(Image, f'/bench/{c}/image_raw', make_cb((c, k)), _qos(k))
            for (c, k) in lat]
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    stop = threading.Event()
    cmds = []

    def read_stdin():
        for line in sys.stdin:
            cmds.append(line.strip())
            if line.strip() == 'stop':
                stop.set()
                return
    threading.Thread(target=read_stdin, daemon=True).start()
    print(json.dumps({'ready': True, 'profile': str(choice.profile)}), flush=True)
    cpu0, t0 = None, None
    while not stop.is_set():
        ex.spin_once(timeout_sec=0.05)
        if cpu0 is None and 'start' in cmds:
            cpu0, t0 = _cpu_s(), time.monotonic()
    cpu = (_cpu_s() - cpu0) / (time.monotonic() - t0) if cpu0 is not None else None
    with lock:
        out = {f'{c}/{k}': v for (c, k), v in lat.items()}
    print(json.dumps({'latency_ms': out, 'matched': [s.get_publisher_count() for s in subs],
                      'cpu_share': cpu}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


def publisher_main(width: int, height: int, qos_kind: str) -> None:
    """Child: once matched, publish SECONDS of RATE_HZ frames per camera; print JSON."""
    rclpy, _ = _init_ros()
    from sensor_msgs.msg import Image
    node = rclpy.create_node('bench_transport_pub')
    pubs, msgs = {}, {}
    rng = np.random.default_rng(0)
    for c in CAMERAS:
        pubs[c] = node.create_publisher(Image, f'/bench/{c}/image_raw', _qos(qos_kind))
        m = Image(height=height, width=width, encoding='rgb8', step=width * 3)
        m.header.frame_id = f'camera_{c}_optical_frame'
        m.data = rng.integers(0, 256, height * width * 3, dtype=np.uint8).tobytes()
        msgs[c] = m
    want = 2 if qos_kind == 'reliable' else 1       # a reliable reader ignores a BE writer
    deadline = time.monotonic() + 30
    while (any(p.get_subscription_count() < want for p in pubs.values())
           and time.monotonic() < deadline):
        time.sleep(0.01)
    time.sleep(0.5)                                 # the readers' side of the match, too
    n = int(SECONDS * RATE_HZ)
    cpu0, t0 = _cpu_s(), time.monotonic()
    for i in range(n):
        next_t = t0 + i / RATE_HZ
        delay = next_t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        for c in CAMERAS:
            ns = time.time_ns()
            msgs[c].header.stamp.sec, msgs[c].header.stamp.nanosec = divmod(ns, 10**9)
            pubs[c].publish(msgs[c])
    wall = time.monotonic() - t0
    print(json.dumps({'published': n, 'cpu_share': (_cpu_s() - cpu0) / wall,
                      'rate_hz': round(n / wall, 2)}), flush=True)
    time.sleep(DRAIN_S)          # keep the writers alive while reliable readers catch up
    node.destroy_node()
    rclpy.try_shutdown()


def _child(args: list[str], env: dict) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, '-m', 'benchmarks.bench_transport', *args],
                            env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True,
                            cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def run_case(width: int, height: int, qos_kind: str, profile: str) -> dict:
    env = dict(os.environ)
    env.pop('FASTRTPS_DEFAULT_PROFILES_FILE', None)
    if profile == 'default':
        env['SOFTSHAPE_TRANSPORT_PROFILE'] = 'none'
    elif profile == 'shipped':
        env.pop('SOFTSHAPE_TRANSPORT_PROFILE', None)
    else:                                           # a profile file to compare
        env['SOFTSHAPE_TRANSPORT_PROFILE'] = profile
    sub = _child(['sub'], env)
    try:
        json.loads(sub.stdout.readline())
        pub = _child(['pub', str(width), str(height), qos_kind], env)
        sub.stdin.write('start\n')
        sub.stdin.flush()
        pub_out = json.loads(pub.stdout.readline())
        pub.wait(timeout=60)
        sub.stdin.write('stop\n')
        sub.stdin.flush()
        sub_out = json.loads(sub.stdout.readline())
        sub.wait(timeout=30)
    finally:
        for p in (sub,) + ((pub,) if 'pub' in dir() else ()):
            if p.poll() is None:
                p.kill()
    n = pub_out['published']
    case = {'published_per_camera': n, 'publisher_rate_hz': pub_out['rate_hz'],
            'publisher_cpu_share': round(pub_out['cpu_share'], 3),
            'subscriber_cpu_share': round(sub_out['cpu_share'] or 0.0, 3)}
    for key, values in sub_out['latency_ms'].items():
        cam, kind = key.split('/')
        if qos_kind == 'best_effort' and kind == 'reliable':
            continue                                 # incompatible QoS: no match
        entry = case.setdefault(f'{kind}_subscriber', {'received_fraction': {}})
        entry['received_fraction'][cam] = round(len(values) / n, 4)
        entry.setdefault('latency_ms', {})[cam] = _stats(values)
    return case


def run() -> dict:
    out = {'rate_hz': RATE_HZ, 'seconds': SECONDS, 'cameras': list(CAMERAS),
           'load_average': os.getloadavg()[0]}
    for w, h in SIZES:
        for qos_kind in ('reliable', 'best_effort'):
            for profile in ('default', 'shipped'):
                key = f'{w}x{h}/publisher_{qos_kind}/{profile}'
                out[key] = run_case(w, h, qos_kind, profile)
                print(f'# transport {key}: {out[key]}', file=sys.stderr)
    return out


if __name__ == '__main__':
    if sys.argv[1] == 'sub':
        subscriber_main()
    elif sys.argv[1] == 'pub':
        publisher_main(int(sys.argv[2]), int(sys.argv[3]), sys.argv[4])
