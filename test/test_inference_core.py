"""InferenceCore without ROS: same preprocessing as the dataset, refusals, latest-only slot."""

import threading

import numpy as np
import pytest

from softshape_ros.config import load_rig_config
from softshape_ros.model import Predictor
from softshape_ros.model.serving import (InferenceCore, LatestSlot, ModelMismatchError,
                                         PredictionError, overlay)
from softshape_ros.vision.preprocess import preprocess


@pytest.fixture
def ckpt(trained_checkpoint):
    return trained_checkpoint


@pytest.fixture
def core(ckpt):
    return InferenceCore(Predictor.from_checkpoint(ckpt), load_rig_config(), str(ckpt))


def frame(seed, h=480, w=640):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_predicts_what_the_offline_model_predicts(core):
    cfg = load_rig_config()
    frames = {'main': frame(1), 'side': frame(2)}
    for v, f in frames.items():
        core.set_initial(v, f)
    initial = np.stack([preprocess(frames[v], cfg.cameras[v].crop_px, 64, gray=True)
                        for v in ('main', 'side')])
    p = [10e3, 0, 50e3, 0, 20e3, 0]
    got = core.predict(p)
    want = core.predictor.predict(initial, p)
    assert got['main'].shape == (1, 64, 64)
    np.testing.assert_array_equal(got['main'], want[0])
    np.testing.assert_array_equal(got['side'], want[1])


def test_frames_of_another_resolution_are_cropped_proportionally(core):
    big = frame(3)
    small = big[::2, ::2].copy()
    a, b = core.prepare('main', big), core.prepare('main', small)
    assert a.shape == b.shape == (1, 64, 64)


@pytest.mark.parametrize('bad, match', [
    ([0] * 5, 'needs 6 values'),
    ([0, 0, float('nan'), 0, 0, 0], 'non-finite'),
    ([0, -5, 0, 0, 0, 0], 'negative'),
    ([0, 0, 0, 0, 0, 1e9], 'beyond the configured limits'),
])
def test_bad_requests_are_refused(core, bad, match):
    core.set_initial('main', frame(1))
    core.set_initial('side', frame(2))
    with pytest.raises(PredictionError, match=match):
        core.predict(bad)


def test_no_initial_images_is_refused(core):
    core.clear_initial()
    core.set_initial('main', frame(1))
    with pytest.raises(PredictionError, match="no initial image yet for \\['side'\\]"):
        core.predict([0] * 6)


def test_model_for_other_cameras_is_a_mismatch_naming_the_file(ckpt):
    pred = Predictor.from_checkpoint(ckpt)
    pred.views = ['main', 'top']
    with pytest.raises(ModelMismatchError, match=f"{ckpt}.*'top'"):
        InferenceCore(pred, load_rig_config(), str(ckpt))


def test_overlay_draws_inside_the_crop_only():
    cfg = load_rig_config()
    f = np.full((480, 640, 3), 200, np.uint8)
    pred = np.full((1, 64, 64), 230, np.uint8)
    pred[0, 20:44, 28:36] = 40
    out = overlay(f, pred, cfg.cameras['main'].crop_px)
    x, y, w, h = cfg.cameras['main'].crop_px
    changed = np.any(out != f, axis=2)
    assert changed[y:y + h, x:x + w].sum() > 100
    outside = changed.copy()
    outside[y:y + h, x:x + w] = False
    assert not outside.any()


def test_latest_slot_keeps_only_the_newest():
    slot = LatestSlot()
    for i in range(5):
        slot.put(i)
    assert slot.get(timeout=0.1) == 4
    assert slot.superseded == 4
    assert slot.get(timeout=0.05) is None
    t = threading.Thread(target=lambda: slot.put('late'))
    t.start()
    assert slot.get(timeout=2.0) == 'late'
    t.join()
    slot.close()
    assert slot.get(timeout=5.0) is None
