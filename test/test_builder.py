"""
build-dataset on a session recorded live: plain rclpy publishers play the rig's contract.

Two scenes, each a rest trigger and five actuations; five actuations are spoiled on
purpose (side frame never sent, capture skew too large, unsettled, a torn main frame, no
measured pressure) and one /rig/sample message is not JSON. The recorder node records
over real DDS; the builder must keep exactly the five good samples, pair each with the
images and pressures published for its stamp, and count every drop by reason. Messages
go out back to back, with no pacing: the builder pairs by stamp, never by arrival time.
"""

import json
import subprocess
import sys

import numpy as np
import pytest
from rclpy.parameter import Parameter

from softshape_ros.config import load_rig_config
from softshape_ros.data import load_dataset
from softshape_ros.data.builder import build_dataset
from softshape_ros.scene import Scene
from softshape_ros.vision.preprocess import preprocess, scale_crop
from waits import wait_matched

W, H = 160, 120
BASE_NS = 1_700_000_000 * 10**9


def frame(stamp: int, cam: str) -> np.ndarray:
    rng = np.random.default_rng([stamp % 2**32, 0 if cam == 'main' else 1])
    return rng.integers(0, 256, (H, W, 3), dtype=np.uint8)


def stamp_msg(ns):
    from builtin_interfaces.msg import Time
    return Time(sec=ns // 10**9, nanosec=ns % 10**9)


class RigPlayer:
    """Publish what collector, cameras and pressure bridge publish, for chosen stamps."""

    def __init__(self, ros, cfg):
        from sensor_msgs.msg import Image, JointState, TimeReference
        from std_msgs.msg import Header, String

        from rclpy.qos import QoSProfile, ReliabilityPolicy

        from softshape_ros.nodes.common import LATCHED_QOS
        self.cfg, t = cfg, cfg.topics
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        n = self.node = ros.node('rig_player')
        self.scene = n.create_publisher(String, t.scene, LATCHED_QOS)
        self.sample = n.create_publisher(String, t.sample, qos)
        self.trigger = n.create_publisher(Header, t.trigger, qos)
        self.pressure = n.create_publisher(JointState, t.pressure_measured, qos)
        self.image = {c: n.create_publisher(Image, t.camera('camera_image', c), qos)
                      for c in cfg.camera_names}
        self.capture = {c: n.create_publisher(TimeReference, t.camera('capture_time', c), qos)
                        for c in cfg.camera_names}
        self.publishers = [self.scene, self.sample, self.trigger, self.pressure,
                           *self.image.values(), *self.capture.values()]
        self.msgs = (Image, JointState, TimeReference, Header, String)
        self.sent = 0
        self.published = {}          # stamp -> {'pressure': [...], 'images': {cam: array}}

    def topics(self):
        t = self.cfg.topics
        return [t.scene, t.sample, t.trigger, t.pressure_measured] + [
            t.camera(k, c) for c in self.cfg.camera_names
            for k in ('camera_image', 'capture_time')]

    def send_scene(self, scene: Scene):
        self.scene.publish(self.msgs[4](data=scene.to_json()))
        self.sent += 1

    def shoot(self, stamp, scene_id, kind, index, settled=True, skip_cam=None, skew_ns=0,
              pressure=True, torn_cam=None):
        Image, JointState, TimeReference, Header, String = self.msgs
        cmd = [float(10000 * (index + 1) + k) for k in range(6)]
        self.sample.publish(String(data=json.dumps({
            'stamp_ns': stamp, 'scene_id': scene_id, 'kind': kind, 'index': index,
            'command_pa': cmd, 'settled': settled})))
        h = Header(frame_id='rig')
        h.stamp = stamp_msg(stamp)
        self.trigger.publish(h)
        self.sent += 2
        rec = {'images': {}, 'pressure': None}
        if pressure:
            js = JointState(name=self.cfg.chamber_names, effort=[p + 123.0 for p in cmd])
            js.header.stamp = stamp_msg(stamp + 4_000_000)        # sampled 4 ms later
            self.pressure.publish(js)
            rec['pressure'] = list(js.effort)
            self.sent += 1
        for i, cam in enumerate(self.cfg.camera_names):
            if cam == skip_cam:
                continue
            img = frame(stamp, cam)
            data = img.tobytes()[: -W * 3 if cam == torn_cam else None]
            m = Image(height=H, width=W, encoding='rgb8', is_bigendian=0, step=W * 3,
                      data=data)
            m.header.stamp = stamp_msg(stamp)
            m.header.frame_id = self.cfg.cameras[cam].frame_id
            self.image[cam].publish(m)
            tr = TimeReference(source=cam)
            tr.header.stamp = stamp_msg(stamp)
            tr.time_ref = stamp_msg(stamp + 1_000_000 + (skew_ns if i else 0))
            self.capture[cam].publish(tr)
            rec['images'][cam] = img
            self.sent += 2
        self.published[stamp] = rec


@pytest.fixture(scope='module')
def cfg():
    return load_rig_config()


@pytest.fixture
def session(ros, cfg, tmp_path):
    """Record a 2-scene session with four spoiled samples; returns (bag, player, spoiled)."""
    from softshape_ros.nodes.recorder import Recorder
    player = RigPlayer(ros, cfg)
    bag = tmp_path / 'session'
    rec = ros.add(Recorder(parameter_overrides=[
        Parameter('output', value=str(bag)), Parameter('discovery_period_s', value=0.1)]))
    ros.wait_for(lambda: set(player.topics()) <= set(rec.subs), timeout=20,
                 what='recorder to subscribe to the rig topics')
    wait_matched(ros, player.publishers, [rec.subs[t] for t in player.topics()])
    spoil = {2: dict(skip_cam='side'), 4: dict(skew_ns=50_000_000),
             7: dict(settled=False), 8: dict(torn_cam='main'), 9: dict(pressure=False)}
    player.sample.publish(player.msgs[4](data='{"stamp_ns": oops'))    # malformed JSON
    player.sent += 1
    stamps = {}
    k = 0
    for scene_id in (0, 1):
        player.send_scene(Scene(id=scene_id, object='cylinder',
                                position_m=(0.01 * scene_id, 0.0, 0.02),
                                dims={'radius_m': 0.005, 'height_m': 0.04}))
        rest = BASE_NS + k * 10**9
        player.shoot(rest, scene_id, 'rest', 0, pressure=True)
        k += 1
        for i in range(5):
            n = len(stamps)
            stamps[n] = (BASE_NS + k * 10**9, scene_id, rest)
            player.shoot(stamps[n][0], scene_id, 'actuation', i, **spoil.get(n, {}))
            k += 1
    topics = set(player.topics())
    ros.wait_for(lambda: sum(v for t, v in rec.recording.received.items() if t in topics)
                 >= player.sent, timeout=20, what='recorder to receive every message')
    rec.recording.stop()
    return bag, player, stamps, spoil


def test_build_dataset_pairs_and_drops_exactly(session, cfg, tmp_path):
    bag, player, stamps, spoil = session
    ds, report = build_dataset([bag], tmp_path / 'ds', cfg, progress=False)
    assert report['dropped'] == {'missing_camera_side': 1, 'capture_skew': 1, 'unsettled': 1,
                                 'bad_image_main': 1, 'no_pressure': 1,
                                 'malformed_sample_json': 1}
    good = [v for n, v in sorted(stamps.items()) if n not in spoil]
    assert len(ds) == len(good) == 5
    ds = load_dataset(tmp_path / 'ds')
    assert ds.initial.shape == (5, 2, 1, 64, 64) and ds.target.dtype == np.uint8
    assert ds.meta['stamps_ns'] == [g[0] for g in good]
    assert ds.meta['kept'] == 5 and ds.meta['triggers'] == 12
    assert ds.meta['dropped'] == report['dropped']
    np.testing.assert_array_equal(ds.max_pressure_pa, cfg.max_pressures_pa)
    # A real rig does not measure contact: no record, and the dataset says why.
    assert ds.contact is None and 'does not measure contact' in ds.meta['contact']['why']

    def expect(stamp, cam):
        cc = cfg.cameras[cam]
        crop = scale_crop(cc.crop_px, (cc.width, cc.height), (W, H))
        return preprocess(player.published[stamp]['images'][cam], crop, 64, True)

    for i, (stamp, scene_id, rest) in enumerate(good):
        assert ds.scene[i] == scene_id
        np.testing.assert_allclose(ds.pressure[i], player.published[stamp]['pressure'])
        for v, cam in enumerate(cfg.camera_names):
            np.testing.assert_array_equal(ds.target[i, v], expect(stamp, cam))
            np.testing.assert_array_equal(ds.initial[i, v], expect(rest, cam))
    # Different samples really differ (pairing is not trivially satisfied).
    assert not np.array_equal(ds.target[0], ds.target[1])
    # Two sessions with the same scene ids keep their scenes apart.
    both, rep2 = build_dataset([bag, bag], tmp_path / 'two', cfg, progress=False)
    assert len(both) == 10 and rep2['triggers'] == 24
    assert list(both.scene) == list(ds.scene) + [s + 2 for s in ds.scene]
    np.testing.assert_array_equal(both.target[5:], ds.target)


def test_build_dataset_cli_and_rgb(session, tmp_path):
    bag, *_ = session
    out = tmp_path / 'rgb'
    proc = subprocess.run([sys.executable, '-m', 'softshape_ros.cli', 'build-dataset', str(bag),
                           '--out', str(out), '--rgb', '--quiet'],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert '5 samples' in proc.stdout and 'unsettled=1' in proc.stdout
    ds = load_dataset(out)
    assert ds.initial.shape == (5, 2, 3, 64, 64)
    again = subprocess.run([sys.executable, '-m', 'softshape_ros.cli', 'build-dataset',
                            str(bag), '--out', str(out), '--quiet'],
                           capture_output=True, text=True, timeout=120)
    assert again.returncode == 2 and 'already exists' in again.stderr


def test_build_dataset_refuses_missing_bag(tmp_path, cfg):
    with pytest.raises(Exception, match='no such bag'):
        build_dataset([tmp_path / 'nope'], tmp_path / 'ds', cfg, progress=False)
