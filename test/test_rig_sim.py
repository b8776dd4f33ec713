"""
The simulated rig end to end over rclpy: collector + mock_hardware, 2 scenes x 5 actuations.

Checks what the dataset builder relies on: one image per camera per trigger under the
trigger's stamp, rest images at zero pressure, every image equal to SimRig's own output
for the measured pressures, and measured pressures within tolerance of the commands.
"""

import json
import threading

import numpy as np
import pytest
from rclpy.parameter import Parameter

pytestmark = pytest.mark.ros

TOL_PA = 2000.0


def small_camera_config(path):
    """Write rig.yaml with 160x120 cameras (same optics scaled): rendering costs 1/16."""
    import yaml

    from softshape_ros.config import default_config_path, load_rig_config
    data = yaml.safe_load(default_config_path().read_text())
    for cam in data['cameras'].values():
        for key in ('width', 'height'):
            cam[key] //= 4
        for key in ('fx', 'fy', 'cx', 'cy'):
            cam[key] /= 4.0
        cam['crop_px'] = [v // 4 for v in cam['crop_px']]
    path.write_text(yaml.safe_dump(data))
    return load_rig_config(path)


def test_collector_and_mock_hardware_two_scenes_five_actuations(ros, tmp_path):
    from sensor_msgs.msg import CameraInfo, Image, JointState, TimeReference
    from std_msgs.msg import Header, String

    from softshape_ros.nodes.collector import Collector
    from softshape_ros.nodes.common import (LATCHED_QOS, RELIABLE_QOS, image_to_numpy,
                                            stamp_to_ns)
    from softshape_ros.nodes.mock_hardware import MockHardware
    from softshape_ros.scene import Scene, load_session
    from softshape_ros.sim import SimRig

    cfg = small_camera_config(tmp_path / 'rig.yaml')
    t = cfg.topics
    cams = cfg.camera_names
    scenes = load_session('config/session_sim.yaml')[:2]
    session = tmp_path / 'session.yaml'
    session.write_text('scenes:\n' + ''.join(
        f'  - {json.dumps(json.loads(s.to_json()))}\n' for s in scenes))

    lock = threading.Lock()
    rec = {'trigger': [], 'sample': [], 'scene': [], 'measured': {}}
    images = {c: {} for c in cams}
    infos = {c: {} for c in cams}
    times = {c: {} for c in cams}
    probe = ros.node('rig_probe')

    def keep(key, value):
        with lock:
            rec[key].append(value)

    def keyed(where, c, m, value):
        with lock:
            where[c].setdefault(stamp_to_ns(m.header.stamp), []).append(value)

    def on_measured(m):
        with lock:
            rec['measured'][stamp_to_ns(m.header.stamp)] = np.asarray(m.effort)

    probe.create_subscription(Header, t.trigger, lambda m: keep('trigger', stamp_to_ns(m.stamp)),
                              RELIABLE_QOS)
    probe.create_subscription(String, t.sample, lambda m: keep('sample', json.loads(m.data)),
                              RELIABLE_QOS)
    probe.create_subscription(String, t.scene, lambda m: keep('scene', m.data), LATCHED_QOS)
    probe.create_subscription(JointState, t.pressure_measured, on_measured, RELIABLE_QOS)
    for c in cams:
        probe.create_subscription(Image, t.camera('camera_image', c),
                                  lambda m, c=c: keyed(images, c, m, m), RELIABLE_QOS)
        probe.create_subscription(CameraInfo, t.camera('camera_info', c),
                                  lambda m, c=c: keyed(infos, c, m, m), RELIABLE_QOS)
        probe.create_subscription(TimeReference, t.camera('capture_time', c),
                                  lambda m, c=c: keyed(times, c, m, stamp_to_ns(m.time_ref)),
                                  RELIABLE_QOS)

    conf = Parameter('config_file', value=str(tmp_path / 'rig.yaml'))
    ros.add(MockHardware(parameter_overrides=[Parameter('tau_s', value=0.02),
                                              Parameter('free_run_hz', value=0.0), conf]))
    params = {'session': str(session), 'simulated': True, 'actuations': 5, 'rate_hz': 3.0,
              'settle_timeout_s': 1.5, 'settle_tolerance_pa': TOL_PA, 'seed': 11,
              'rest_delay_s': 0.3, 'max_fraction': 0.6}
    col = ros.add(Collector(parameter_overrides=[conf] + [Parameter(k, value=v)
                                                          for k, v in params.items()]))
    ros.wait_for(col.done.is_set, timeout=90, what='the session')
    assert col.state == 'done', col.error
    n = 2 * (1 + 5)

    def every_trigger_answered():
        with lock:
            stamps = list(rec['trigger'])
            return len(stamps) == n and all(s in where[c] for s in stamps for c in cams
                                            for where in (images, times, infos))
    ros.wait_for(every_trigger_answered, timeout=30, what='the images of every trigger')

    with lock:
        triggers, samples = list(rec['trigger']), list(rec['sample'])
        measured = dict(rec['measured'])
        scene_msgs = list(rec['scene'])
    assert len(triggers) == n and [s['stamp_ns'] for s in samples] == triggers
    assert [Scene.from_json(x).id for x in scene_msgs] == [s.id for s in scenes]

    by_scene = {s.id: s for s in scenes}
    rig = SimRig(cfg, seed=0)
    current = None
    for sample in samples:
        stamp = sample['stamp_ns']
        # exactly one image (and info, capture time) per camera, under the trigger's stamp
        for c in cams:
            assert len(images[c][stamp]) == 1 and len(infos[c][stamp]) == 1
            assert images[c][stamp][0].header.frame_id == cfg.cameras[c].frame_id
            assert infos[c][stamp][0].k[0] == cfg.cameras[c].fx
        sampled = {times[c][stamp][0] for c in cams}
        assert len(sampled) == 1                      # one simulated instant for both cameras
        p = measured[sampled.pop()]                   # the pressures the images were made at
        command = np.asarray(sample['command_pa'])
        assert sample['settled']
        assert np.abs(p - command).max() <= TOL_PA
        if sample['kind'] == 'rest':
            assert sample['index'] == 0 and np.abs(p).max() < 1.0   # rest = zero pressure
        else:
            assert command.max() > 0 and (command <= 0.6 * np.asarray(cfg.max_pressures_pa)
                                          + 1e-6).all()
        if sample['scene_id'] != current:
            current = sample['scene_id']
            rig.set_scene(by_scene[current])
        expected = rig.snap(p)
        for c in cams:
            got = image_to_numpy(images[c][stamp][0])
            assert got.shape == (cfg.cameras[c].height, cfg.cameras[c].width, 3)
            assert np.array_equal(got, expected[c]), (
                f'{c} @ {sample["kind"]} {sample["index"]} of scene {current}: '
                f'{int((got != expected[c]).any(axis=2).sum())} pixels differ')
    # actuations really move the robot: some actuation image differs from its scene's rest
    rest = image_to_numpy(images['main'][samples[0]['stamp_ns']][0])
    moved = [image_to_numpy(images['main'][s['stamp_ns']][0]) for s in samples[1:6]]
    assert any((m != rest).any(axis=2).sum() > 500 for m in moved)
