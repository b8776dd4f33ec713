"""Two camera_trigger processes on file sources answer the same 100 triggers with one stamp."""

import os
import signal
import subprocess
import sys
import threading
import time

import pytest

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

    for c in ('main', 'side'):
        probe.create_subscription(Image, t.camera('camera_image', c),
                                  lambda m, c=c: on_image(c, m), deep)
        probe.create_subscription(TimeReference, t.camera('capture_time', c),
                                  lambda m, c=c: on_time(c, m), deep)
    probe.create_subscription(DiagnosticArray, t.diagnostics, on_diag, RELIABLE_QOS)

    procs = [start_camera(c, video, fps) for c in ('main', 'side')]
    try:
        ros.wait_for(lambda: pub.get_subscription_count() >= 2
                     and probe.count_publishers(t.camera('camera_image', 'side')) >= 1
                     and probe.count_publishers(t.camera('camera_image', 'main')) >= 1
                     and all(p.poll() is None for p in procs),
                     timeout=60, what='both camera processes in the graph')
        time.sleep(1.0)        # let every endpoint pair finish matching
        sent = []
        for i in range(N_TRIGGERS):
            ns = time.time_ns()
            pub.publish(Header(stamp=ns_to_stamp(ns), frame_id=f'trigger {i}'))
            sent.append(ns)
            time.sleep(0.05)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not all(
                len(cap[c]) >= N_TRIGGERS and len(got[c]) >= N_TRIGGERS for c in cap):
            time.sleep(0.05)
        counts = {c: (len(cap[c]), len(got[c])) for c in cap}
        assert all(n == (N_TRIGGERS, N_TRIGGERS) for n in counts.values()), (
            f'(capture times, images) per camera after 100 triggers: {counts}')
        ros.wait_for(lambda: all(diags.get(f'camera_{c}: {c} camera', {}).get('frames')
                                 == str(N_TRIGGERS) for c in ('main', 'side')),
                     timeout=10, what='diagnostics with the final counts')
    finally:
        results = [stop(p) for p in procs]
    for code, out in results:
        assert code == 0, out
    with lock:
        for c in ('main', 'side'):
            assert sorted(got[c]) == sent, f'{c}: stamps differ from the triggers'
            assert all(len(v) == 1 for v in got[c].values()), f'{c}: duplicate frames'
            assert sorted(cap[c]) == sent
        skews = [abs(cap['main'][s] - cap['side'][s]) for s in sent]
        # the frame each camera published is the one playing at its own capture time
        for c in ('main', 'side'):
            for s in sent:
                index = decode_index(image_to_numpy(got[c][s][0]))
                assert index == int(cap[c][s] * fps // 1_000_000_000) % 12
        d = diags['camera_main: main camera']
    assert "'n': 100" in d['pair_skew_ms']            # the node paired every frame with side's
    assert int(d['pairs_over_bound']) == sum(sk > 10_000_000 for sk in skews)
