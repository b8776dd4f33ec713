"""Two camera_trigger processes on file sources answer the same 100 triggers with one stamp."""

import os
import re
import signal
import subprocess
import sys
import threading
import time

import pytest

from waits import round_trip

pytestmark = pytest.mark.ros

N_TRIGGERS = 100


def start_camera(camera, source, fps):
    code = 'from softshape_ros.nodes.camera_trigger import main; main()'
    return subprocess.Popen(
        [sys.executable, '-c', code, '--ros-args', '-r', f'__node:=camera_{camera}',
         '-p', f'camera_name:={camera}', '-p', f'source:={source}', '-p', f'fps:={fps}',
         '-p', 'diagnostic_updater.period:=0.5',
         '-p', 'max_trigger_age_s:=10.0'],      # a loaded CI machine delivers late
        env=dict(os.environ), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def stop(proc):
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return proc.returncode, out


def test_two_camera_processes_answer_100_triggers_with_matching_stamps(ros, tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import Image, TimeReference
    from std_msgs.msg import Header

    from softshape_ros.config import load_rig_config
    from softshape_ros.nodes.common import (RELIABLE_QOS, image_to_numpy, ns_to_stamp,
                                            stamp_to_ns)
    from softshape_ros.vision.patterns import decode_index, write_video

    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    # a deep reader queue: a loaded test process must not overwrite unread frames
    deep = QoSProfile(depth=300, reliability=ReliabilityPolicy.RELIABLE,
                      history=HistoryPolicy.KEEP_LAST)
    cfg = load_rig_config()
    t = cfg.topics
    fps = 10.0
    video = write_video(tmp_path / 'clip.avi', 12, fps=fps)
    lock = threading.Lock()
    got = {c: {} for c in ('main', 'side')}
    cap = {c: {} for c in ('main', 'side')}
    diags = {}
    probe = ros.node('pair_probe')
    pub = probe.create_publisher(Header, t.trigger, RELIABLE_QOS)

    def on_image(c, m):
        with lock:
            got[c].setdefault(stamp_to_ns(m.header.stamp), []).append(m)

    def on_time(c, m):
        with lock:
            cap[c][stamp_to_ns(m.header.stamp)] = stamp_to_ns(m.time_ref)

    def on_diag(m):
        with lock:
            for s in m.status:
                diags[s.name] = {kv.key: kv.value for kv in s.values}

    subs = []
    for c in ('main', 'side'):
        subs.append(probe.create_subscription(Image, t.camera('camera_image', c),
                                              lambda m, c=c: on_image(c, m), deep))
        subs.append(probe.create_subscription(TimeReference, t.camera('capture_time', c),
                                              lambda m, c=c: on_time(c, m), deep))
    probe.create_subscription(DiagnosticArray, t.diagnostics, on_diag, RELIABLE_QOS)

    procs = [start_camera(c, video, fps) for c in ('main', 'side')]

    def diag(c, key):
        with lock:
            return diags.get(f'camera_{c}: {c} camera', {}).get(key)
    try:
        ros.wait_for(lambda: pub.get_subscription_count() >= 2
                     and all(s.get_publisher_count() >= 1 for s in subs)
                     and all(p.poll() is None for p in procs),
                     timeout=60, what='both camera processes matched with the probe')
        # A warm-up trigger that comes back, as two frames, two capture times and main's
        # pairing with side's capture time, proves every endpoint pair matched at both ends
        # (the cameras' ends are in their processes). A camera answers every warm-up (the
        # trigger writer matched both), but one that had not matched a reader yet dropped
        # that answer: warm-ups repeat until one comes back whole.
        warm = []

        def warm_up(k):
            warm.append(time.time_ns())
            pub.publish(Header(stamp=ns_to_stamp(warm[-1]), frame_id=f'warm-up {k}'))

        def back():
            with lock:
                whole = all(warm[-1] in got[c] and warm[-1] in cap[c] for c in got)
            return whole and diag('main', 'last_pair_stamp_ns') == str(warm[-1])
        n_warm = round_trip(ros, warm_up, back, 'a warm-up trigger answered by both cameras')
        with lock:            # main paired its last warm-up: earlier ones are settled too
            base = diags['camera_main: main camera']
        sent = []
        for i in range(N_TRIGGERS):
            ns = time.time_ns()
            pub.publish(Header(stamp=ns_to_stamp(ns), frame_id=f'trigger {i}'))
            sent.append(ns)
            time.sleep(0.05)                   # pacing: triggers at 20 Hz

        def answered():
            with lock:
                return {c: (sum(s in cap[c] for s in sent), sum(s in got[c] for s in sent))
                        for c in cap}
        ros.wait_for(lambda: all(n == (N_TRIGGERS, N_TRIGGERS) for n in answered().values()),
                     timeout=20, what=lambda: '(capture times, images) per camera after '
                     f'{N_TRIGGERS} triggers: {answered()}')
        # every camera answered each warm-up and each trigger; main paired the last one
        ros.wait_for(lambda: all(diag(c, 'frames') == str(N_TRIGGERS + n_warm)
                                 for c in ('main', 'side'))
                     and diag('main', 'last_pair_stamp_ns') == str(sent[-1]),
                     timeout=10, what=lambda: 'diagnostics with the final counts: '
                     f"{ {c: diag(c, 'frames') for c in ('main', 'side')} }")
    finally:
        results = [stop(p) for p in procs]
    for code, out in results:
        assert code == 0, out
    with lock:
        for c in ('main', 'side'):
            assert sorted(set(got[c]) - set(warm)) == sent, f'{c}: stamps are not the triggers'
            assert all(len(v) == 1 for v in got[c].values()), f'{c}: duplicate frames'
            assert sorted(set(cap[c]) - set(warm)) == sent
        skews = [abs(cap['main'][s] - cap['side'][s]) for s in sent]
        # the frame each camera published is the one playing at its own capture time
        for c in ('main', 'side'):
            for s in sent:
                index = decode_index(image_to_numpy(got[c][s][0]))
                assert index == int(cap[c][s] * fps // 1_000_000_000) % 12
        d = diags['camera_main: main camera']

    def pairs(status):
        return int(re.search(r"'n': (\d+)", status['pair_skew_ms']).group(1))
    # the node paired every frame with side's, and flagged exactly the pairs over the bound
    assert pairs(d) - pairs(base) == N_TRIGGERS
    assert (int(d['pairs_over_bound']) - int(base['pairs_over_bound'])
            == sum(sk > 10_000_000 for sk in skews))
