"""
The inference node over real DDS, against the simulated rig (mock_hardware).

A plain rclpy subscriber receives the predicted images; their pixels must equal the offline
model's output for the same rest images and pressures. Bad requests publish nothing and the
node stays up.
"""

import json
import threading

import numpy as np
import pytest
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image
from std_msgs.msg import Float64MultiArray, Header, String
from std_srvs.srv import Trigger

from softshape_ros.config import load_rig_config
from softshape_ros.model import Predictor
from softshape_ros.nodes.common import (IMAGE_QOS, LATCHED_QOS, RELIABLE_QOS, image_to_numpy,
                                        ns_to_stamp, stamp_to_ns)
from softshape_ros.scene import Scene
from softshape_ros.vision.preprocess import preprocess

pytestmark = pytest.mark.ros


class Probe:
    """The test's own plain rclpy publishers and subscribers."""

    def __init__(self, ros, cfg):
        t = cfg.topics
        self.node = ros.node('inference_probe')
        n = self.node
        self.scene = n.create_publisher(String, t.scene, LATCHED_QOS)
        self.sample = n.create_publisher(String, t.sample, RELIABLE_QOS)
        self.trigger = n.create_publisher(Header, t.trigger, RELIABLE_QOS)
        self.command = n.create_publisher(Float64MultiArray, t.pressure_command, RELIABLE_QOS)
        self.query = n.create_publisher(Float64MultiArray, t.query, RELIABLE_QOS)
        self.lock = threading.Lock()
        self.camera = {v: {} for v in cfg.camera_names}
        self.predicted = {v: [] for v in cfg.camera_names}
        self.overlays = {v: [] for v in cfg.camera_names}
        for v in cfg.camera_names:
            n.create_subscription(Image, t.camera('camera_image', v),
                                  lambda m, v=v: self._keep(self.camera[v], m), IMAGE_QOS)
            n.create_subscription(Image, t.camera('predicted_image', v),
                                  lambda m, v=v: self._append(self.predicted[v], m), IMAGE_QOS)
            n.create_subscription(Image, t.camera('predicted_overlay', v),
                                  lambda m, v=v: self._append(self.overlays[v], m), IMAGE_QOS)

    def _keep(self, store, msg):
        with self.lock:
            store[stamp_to_ns(msg.header.stamp)] = image_to_numpy(msg)

    def _append(self, store, msg):
        with self.lock:
            store.append(msg)

    def snap_rest(self, scene_id, stamp_ns):
        self.sample.publish(String(data=json.dumps({
            'stamp_ns': stamp_ns, 'scene_id': scene_id, 'kind': 'rest', 'index': 0,
            'command_pa': [0.0] * 6, 'settled': True})))
        h = Header()
        h.stamp = ns_to_stamp(stamp_ns)
        self.trigger.publish(h)

    def n_predicted(self):
        with self.lock:
            return min(len(v) for v in self.predicted.values())


def start_rig(ros, **params):
    """Start the mock rig, an inference node with ``params`` and the probe; wait for them."""
    from softshape_ros.nodes.inference import InferenceNode
    from softshape_ros.nodes.mock_hardware import MockHardware
    cfg = load_rig_config()
    probe = Probe(ros, cfg)
    mock = ros.add(MockHardware(parameter_overrides=[Parameter('free_run_hz', value=0.0)]))
    node = ros.add(InferenceNode(parameter_overrides=[
        Parameter(k, value=str(v)) for k, v in params.items()]))
    ros.wait_for(lambda: node.count_subscribers(cfg.topics.pressure_command) >= 2
                 and probe.node.count_subscribers(cfg.topics.trigger) >= 1
                 and probe.node.count_publishers(cfg.topics.camera('predicted_image', 'side')),
                 timeout=20, what='graph connections')
    return cfg, probe, node, mock


def show_scene(ros, probe, node, scene, rest_ns):
    """Publish ``scene``, snap its rest images; return once inference and probe have them."""
    probe.scene.publish(String(data=scene.to_json()))
    ros.wait_for(lambda: node.awaiting_rest, what='inference to see the scene')
    probe.snap_rest(scene.id, rest_ns)
    ros.wait_for(lambda: node.core.ready, timeout=20, what='initial images from the rest frames')
    ros.wait_for(lambda: all(rest_ns in probe.camera[v] for v in ('main', 'side')),
                 what='the probe to see the rest frames too')


@pytest.fixture
def rig(ros, trained_checkpoint):
    return start_rig(ros, model=trained_checkpoint)


def test_predictions_equal_offline_model_and_bad_input_publishes_nothing(rig, trained_checkpoint,
                                                                         ros):
    cfg, probe, node, _ = rig
    cmd = lambda values: Float64MultiArray(data=[float(v) for v in values])  # noqa: E731

    # Before any scene: no initial images -> refused, nothing published.
    probe.query.publish(cmd([0] * 6))
    ros.wait_for(lambda: node.counts['rejected'] >= 1, what='refusal without initial images')

    scene = Scene(id=7, object='cylinder', position_m=[0.024, 0.0, 0.02],
                  dims={'radius_m': 0.008, 'height_m': 0.05})
    rest_ns = 1_000_000_000_123
    show_scene(ros, probe, node, scene, rest_ns)
    # Diagnostics name the scene the initial images are of (a client tells a stale
    # 'waiting' from before the scene from one after it), and the cameras matched to each
    # view's reader (the mock rig's, one a view: a client snaps rest images once it is).
    from softshape_ros.nodes.diagnostics import DiagnosticStatusWrapper
    stat = node.report(DiagnosticStatusWrapper())
    assert stat.message == 'predicting'
    values = {kv.key: kv.value for kv in stat.values}
    assert values['scene'] == '7' and values['camera_publishers'] == '1', values

    # Bad requests: wrong length, NaN, beyond limits -> nothing published, node stays up.
    before = node.counts['rejected']
    for bad in ([0] * 5, [0, 0, float('nan'), 0, 0, 0], [0, 0, 0, 0, 0, 1e9]):
        probe.query.publish(cmd(bad))
    ros.wait_for(lambda: node.counts['rejected'] >= before + 3, what='three refusals')
    assert probe.n_predicted() == 0

    # A real command: predicted images equal the offline model on the same inputs.
    pressures = [40e3, 0.0, 0.0, 60e3, 0.0, 10e3]
    probe.command.publish(cmd(pressures))
    ros.wait_for(lambda: probe.n_predicted() >= 1, timeout=20, what='predicted images')
    pred = Predictor.from_checkpoint(trained_checkpoint)
    initial = np.stack([preprocess(probe.camera[v][rest_ns], cfg.cameras[v].crop_px, 64,
                                   gray=True) for v in ('main', 'side')])
    want = pred.predict(initial, pressures)
    for i, v in enumerate(('main', 'side')):
        msg = probe.predicted[v][0]
        assert msg.header.frame_id == cfg.cameras[v].frame_id
        assert msg.encoding == 'mono8' and (msg.height, msg.width) == (64, 64)
        np.testing.assert_array_equal(image_to_numpy(msg), want[i, 0])
    ros.wait_for(lambda: all(probe.overlays[v] for v in ('main', 'side')), what='overlays')
    assert (probe.overlays['main'][0].height, probe.overlays['main'][0].width) == (480, 640)

    # A query works the same way (and the node is still serving after the bad inputs).
    probe.query.publish(cmd([0, 0, 0, 0, 0, 0]))
    ros.wait_for(lambda: probe.n_predicted() >= 2, what='prediction for a query')


def test_rest_sample_arriving_after_its_frames_is_still_taken(rig, ros):
    """The sample comes from the collector, the frames from the cameras: either may be first."""
    cfg, probe, node, _ = rig
    scene = Scene(id=8, object='none')
    probe.scene.publish(String(data=scene.to_json()))
    ros.wait_for(lambda: node.awaiting_rest, what='inference to see the scene')
    probe.sample.publish(String(data=json.dumps({          # samples are flowing
        'stamp_ns': 1, 'scene_id': 8, 'kind': 'actuation', 'index': 0,
        'command_pa': [0.0] * 6, 'settled': True})))
    ros.wait_for(lambda: node.seen_samples, what='the first sample')
    rest_ns = 3_000_000_000_000
    h = Header()
    h.stamp = ns_to_stamp(rest_ns)
    probe.trigger.publish(h)                               # frames first ...
    ros.wait_for(lambda: all(rest_ns in node.recent[v] for v in ('main', 'side')),
                 timeout=20, what='the rest frames at the inference node')
    assert not node.core.ready                             # not a rest stamp (yet)
    probe.sample.publish(String(data=json.dumps({          # ... then the sample naming them
        'stamp_ns': rest_ns, 'scene_id': 8, 'kind': 'rest', 'index': 0,
        'command_pa': [0.0] * 6, 'settled': True})))
    ros.wait_for(lambda: node.core.ready, what='initial images from the earlier frames')
    assert not node.awaiting_rest


def test_capture_initial_service(rig, ros):
    cfg, probe, node, _ = rig
    client = probe.node.create_client(Trigger, '/inference/capture_initial')
    assert client.wait_for_service(timeout_sec=10)
    res = client.call(Trigger.Request(), timeout_sec=10)
    assert not res.success and 'no camera frame yet' in res.message
    h = Header()
    h.stamp = ns_to_stamp(2_000_000_000_000)
    probe.trigger.publish(h)   # mock snaps; inference keeps the frames as 'latest'
    ros.wait_for(lambda: all(v in node.latest_frame for v in ('main', 'side')), timeout=20,
                 what='camera frames')
    res = client.call(Trigger.Request(), timeout_sec=10)
    assert res.success, res.message
    assert node.core.ready


def test_missing_or_corrupt_model_fails_at_start_naming_the_file(
        rclpy_session, tmp_path, trained_checkpoint):
    from softshape_ros.nodes.inference import InferenceNode
    with pytest.raises(ValueError, match='parameter "model" is empty'):
        InferenceNode()
    with pytest.raises(ValueError, match=str(tmp_path / 'nope')):
        InferenceNode(parameter_overrides=[Parameter('model', value=str(tmp_path / 'nope'))])
    import shutil
    bad = tmp_path / 'tampered'
    shutil.copytree(trained_checkpoint, bad)
    w = bad / 'model.safetensors'
    w.write_bytes(w.read_bytes()[:-100])
    with pytest.raises(ValueError, match='model.safetensors'):
        InferenceNode(parameter_overrides=[Parameter('model', value=str(bad))])


def test_the_placement_path_serves_what_it_predicts_offline(ros, trained_checkpoint, tmp_path,
                                                            monkeypatch):
    """With ``placement_head``: the tube model draws the head's robot for the fitted placement."""
    from softshape_ros.data import load_dataset
    from softshape_ros.demo.pipeline import PRETRAINED
    from softshape_ros.experiments.placement_head import train_shape_predictor
    from softshape_ros.experiments.placement_predictor import PlacementPredictor
    from softshape_ros.nodes.inference import InferenceNode
    cfg = load_rig_config()
    # A head learnt briefly from the inference fixtures' small dataset: the test is that the
    # node serves the placement path, not how good this head is.
    ds = load_dataset(trained_checkpoint.parent / 'dataset')
    head, _ = train_shape_predictor(ds, cfg, ['main', 'side'], steps=50, batch=32,
                                    progress=False)
    head_dir = head.save(tmp_path / 'head')
    _, probe, node, _ = start_rig(ros, model=PRETRAINED, placement_head=head_dir)
    assert isinstance(node.core.predictor, PlacementPredictor)
    scene = Scene(id=3, object='cylinder', position_m=[0.026, 0.0, 0.02],
                  dims={'radius_m': 0.008, 'height_m': 0.05})
    rest_ns = 2_000_000_000_123
    show_scene(ros, probe, node, scene, rest_ns)
    pressures = [0.0, 90e3, 0.0, 0.0, 90e3, 0.0]
    probe.command.publish(Float64MultiArray(data=pressures))
    ros.wait_for(lambda: probe.n_predicted() >= 1, timeout=60, what='predicted images')
    fitted = node.core.predictor.placement(node.core.initial())
    assert np.abs(np.subtract(fitted.position_m, scene.position_m))[:2].max() < 5e-4
    initial = np.stack([preprocess(probe.camera[v][rest_ns], cfg.cameras[v].crop_px, 64,
                                   gray=True) for v in ('main', 'side')])
    want = node.core.predictor.predict(initial, pressures)
    for i, v in enumerate(('main', 'side')):
        np.testing.assert_array_equal(image_to_numpy(probe.predicted[v][0]), want[i, 0])
    assert node.placement_source() == 'fitted to rest images'
    assert node.placement.alone == ''
    node.placement.alone = 'hidden in side'     # as for an object behind the robot
    assert node.placement_source() == 'fitted to rest images; hidden in side: tube model alone'
    node.placement.alone = ''
    # Told to take the placement /rig/scene records, from the next scene on it fits nothing.
    node.set_parameters([Parameter('placement_from_scene', value=True)])
    monkeypatch.setattr(node.placement.fit, 'fit', lambda *a, **k: pytest.fail('fitted'))
    known = Scene(id=4, object='prism', position_m=[0.0, -0.027, 0.025], rpy_rad=[0, 0, -1.6],
                  dims={'width_m': 0.01, 'depth_m': 0.01, 'height_m': 0.05, 'skew_rad': 0.1})
    show_scene(ros, probe, node, known, rest_ns + 1)
    assert node.placement.placement(node.core.initial()) == known
    assert node.placement_source() == 'from /rig/scene'
    probe.command.publish(Float64MultiArray(data=pressures))
    ros.wait_for(lambda: probe.n_predicted() >= 2, timeout=60, what='predictions, told')
    initial = np.stack([preprocess(probe.camera[v][rest_ns + 1], cfg.cameras[v].crop_px, 64,
                                   gray=True) for v in ('main', 'side')])
    want = node.core.predictor.predict(initial, pressures)
    for i, v in enumerate(('main', 'side')):
        np.testing.assert_array_equal(image_to_numpy(probe.predicted[v][-1]), want[i, 0])
    # An object the head does not know: the placement is fitted again, and the log says so.
    probe.scene.publish(String(data=Scene(id=5, object='sphere', position_m=[0.0, 0.03, 0.02],
                                          dims={'radius_m': 0.01}).to_json()))
    ros.wait_for(lambda: node.scene_id == 5, what='inference to see the sphere')
    assert node.placement.known is None
    # A head made for other cameras is refused at start, naming the file.
    import dataclasses
    moved = dataclasses.replace(head, projection=type(head.projection)(
        dataclasses.replace(cfg, cameras=dict(cfg.cameras, side=dataclasses.replace(
            cfg.cameras['side'], fx=1300.0))), ['main', 'side'], 64))
    other = moved.save(tmp_path / 'other_head')
    with pytest.raises(ValueError, match="other_head: trained for another camera 'side'"):
        InferenceNode(parameter_overrides=[Parameter('model', value=str(PRETRAINED)),
                                           Parameter('placement_head', value=str(other))])
