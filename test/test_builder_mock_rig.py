"""
End to end on the simulated rig: collector + mock_hardware -> recorder -> build-dataset.

The real nodes talk over DDS; the recorder writes an MCAP bag; the builder must turn
every settled actuation of the session into one sample whose pressures are the
measured ones near the commanded values and whose images are the simulator's frames
recorded for that trigger.
"""

import time

import numpy as np
import pytest
from rclpy.parameter import Parameter

from softshape_ros.config import load_rig_config
from softshape_ros.data.builder import build_dataset
from softshape_ros.vision.image_msg import decode_image
from softshape_ros.vision.preprocess import preprocess


def _params(**kw):
    return [Parameter(k, value=v) for k, v in kw.items()]


@pytest.mark.ros
def test_mock_rig_session_to_dataset(ros, tmp_path):
    from softshape_ros.nodes.collector import Collector
    from softshape_ros.nodes.mock_hardware import MockHardware
    from softshape_ros.nodes.recorder import Recorder
    cfg = load_rig_config()
    session = tmp_path / 'session.yaml'
    session.write_text(
        'scenes:\n'
        '  - {id: 3, object: sphere, position_m: [0.02, 0.0, 0.02], '
        'dims: {radius_m: 0.006}, actuations: 2}\n'
        '  - {id: 4, object: none, actuations: 2}\n')
    bag = tmp_path / 'mock_session'
    rec = ros.add(Recorder(parameter_overrides=_params(output=str(bag),
                                                       discovery_period_s=0.1)))
    ros.add(MockHardware(parameter_overrides=_params(tau_s=0.02, free_run_hz=0.0)))
    main_topic = cfg.topics.camera('camera_image', 'main')
    ros.wait_for(lambda: {cfg.topics.pressure_measured, main_topic} <= set(rec.subs),
                 timeout=30, what='recorder on the mock topics')
    col = ros.add(Collector(parameter_overrides=_params(
        session_file=str(session), rate_hz=4.0, rest_delay_s=0.1, start_delay_s=1.0,
        max_fraction=0.5, seed=3, settle_timeout_s=5.0)))      # 5 s: busy CI machine
    ros.wait_for(col.done.is_set, timeout=90, what='collection session to finish')
    assert col.state == 'done', col.error
    # Everything the builder reads for a trigger is at the recorder before the bag closes:
    # the trigger, its record, each camera's frame and capture time, and the pressures.
    t = cfg.topics
    per_trigger = [t.trigger, t.sample] + [t.camera(k, c) for c in cfg.camera_names
                                           for k in ('camera_image', 'capture_time')]
    received = rec.recording.received
    ros.wait_for(lambda: all(received[x] >= col.samples for x in per_trigger), timeout=60,
                 what=lambda: f'{col.samples} of each per trigger: '
                 f'{ {x: received[x] for x in per_trigger} }')
    # The simulated rig samples a pressure at each trigger and publishes it before the frames,
    # so before now: once a pressure published after now is in, so are they (one reliable
    # stream, in order).
    now_ns = time.time_ns()
    ros.wait_for(lambda: rec.last_source_ns.get(t.pressure_measured, 0) > now_ns, timeout=20,
                 what='a pressure published after the last frame at the recorder')
    rec.recording.stop()

    ds, report = build_dataset([bag], tmp_path / 'ds', cfg, progress=False)
    settled_actuations = col.samples - 2 - col.unsettled
    assert len(ds) == settled_actuations >= 3
    assert report['dropped'].get('unsettled', 0) == col.unsettled
    assert set(report['dropped']) <= {'unsettled'}, report      # a perfect rig drops no more
    assert set(ds.scene.tolist()) <= {3, 4}
    assert np.all(ds.pressure >= -5000) and np.all(ds.pressure <= ds.max_pressure_pa + 5000)
    assert np.all(np.abs(ds.pressure).sum(axis=1) > 1000)      # actuated, not the rest
    # The stored target is the recorded frame for that stamp, preprocessed.
    from rosbags.rosbag2 import Reader

    from softshape_ros.data.rosbag2_format import jazzy_typestore
    ts = jazzy_typestore()
    stamp0 = ds.meta['stamps_ns'][0]
    with Reader(bag) as r:
        conns = [c for c in r.connections if c.topic == main_topic]
        for _, _, raw in r.messages(connections=conns):
            m = ts.deserialize_cdr(raw, 'sensor_msgs/msg/Image')
            if m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == stamp0:
                want = preprocess(decode_image(m), cfg.cameras['main'].crop_px, 64, True)
                np.testing.assert_array_equal(ds.target[0, 0], want)
                break
        else:
            pytest.fail('the first sample stamp is not a recorded main frame')
    assert not np.array_equal(ds.initial[0], ds.target[0])     # the robot moved
