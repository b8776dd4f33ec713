"""Capture sources (no ROS): playback locked to the clock, freshness, clear errors."""

import random
import shutil
import time

import cv2
import numpy as np
import pytest

from softshape_ros.vision.camera_info import (CalibrationError, calibration_from_camera,
                                              calibration_to_yaml, default_calibration_path,
                                              load_calibration)
from softshape_ros.vision.capture import (CaptureError, DeviceSource, ImageFolderSource,
                                          VideoFileSource, open_source)
from softshape_ros.vision.patterns import decode_index, write_folder, write_video
from softshape_ros.vision.sync import SkewTracker


def _check_current(source, n_captures=25, seed=0):
    rng = random.Random(seed)
    seen = set()
    for _ in range(n_captures):
        before = time.time_ns()
        frame = source.capture()
        assert frame.capture_ns >= before               # captured after it was asked for
        assert frame.image.dtype == np.uint8 and frame.image.shape == (120, 160, 3)
        assert decode_index(frame.image) == source.clock.index_at(frame.capture_ns)
        assert frame.image[0, 0].min() > 240                  # the bar is on top: not flipped
        seen.add(frame.index)
        time.sleep(rng.uniform(0.005, 0.08))    # pacing: captures at random moments
    return seen


def test_video_file_plays_frame_current_at_capture_and_loops(tmp_path):
    path = write_video(tmp_path / 'clip.avi', 10, fps=20.0)
    with open_source(str(path)) as src:
        assert isinstance(src, VideoFileSource)
        assert src.clock.fps == 20.0 and src.clock.n == 10
        seen = _check_current(src)
    assert len(seen) >= 5          # the clip looped (0.5 s) and many frames were shown


def test_image_folder_plays_frame_current_at_capture(tmp_path):
    folder = write_folder(tmp_path / 'frames', 8)
    (folder / 'notes.txt').write_text('ignored: not an image')
    with open_source(str(folder), fps=25.0) as src:
        assert isinstance(src, ImageFolderSource) and len(src.files) == 8
        seen = _check_current(src)
    assert len(seen) >= 4


def test_vanished_sources_raise_capture_error(tmp_path):
    folder = write_folder(tmp_path / 'frames', 4)
    src = ImageFolderSource(folder, fps=10.0)
    src.capture()
    shutil.rmtree(folder)
    with pytest.raises(CaptureError, match='cannot read'):
        src.capture()
    video = write_video(tmp_path / 'v.avi', 4, fps=10.0)
    vsrc = VideoFileSource(video)
    vsrc.capture()
    video.unlink()
    with pytest.raises(CaptureError, match='vanished'):
        vsrc.capture()
    vsrc.close()


@pytest.mark.parametrize('spec,match', [
    ('', 'no camera source'),
    ('/dev/video97', 'no such device'),
    ('/nonexistent/clip.avi', 'no such camera'),
    ('97', 'cannot open'),
])
def test_open_source_errors_are_clear(spec, match):
    with pytest.raises(CaptureError, match=match):
        open_source(spec)


def test_empty_folder_and_corrupt_video(tmp_path):
    with pytest.raises(CaptureError, match='no images'):
        open_source(str(tmp_path))
    bad = tmp_path / 'bad.avi'
    bad.write_bytes(b'not a video at all' * 100)
    with pytest.raises(CaptureError):
        open_source(str(bad))


def test_device_source_answers_with_a_later_grab_and_reports_a_dead_stream(tmp_path):
    """A live stream (here OpenCV reading a file as fast as it grabs) that then ends."""
    path = write_video(tmp_path / 'stream.avi', 23, fps=30.0)
    src = DeviceSource(str(path), opener=lambda d: cv2.VideoCapture(d))
    try:
        before = time.time_ns()
        try:
            frame = src.capture(timeout_s=2.0)
        except CaptureError:       # the whole stream was grabbed before we asked: also valid
            frame = None
        if frame is not None:
            assert frame.capture_ns >= before
            assert 0 <= decode_index(frame.image) < 23
        src._thread.join(timeout=5)             # the grab thread ends with the stream
        assert not src._thread.is_alive()
        with pytest.raises(CaptureError, match='grab failed'):
            src.capture(timeout_s=0.5)
    finally:
        src.close()


def test_calibration_round_trip_and_errors(tmp_path):
    from softshape_ros.config import load_rig_config
    cfg = load_rig_config()
    for name, cam in cfg.cameras.items():
        shipped = load_calibration(default_calibration_path(name))
        assert shipped == calibration_from_camera(name, cam)
    cal = calibration_from_camera('main', cfg.cameras['main'])
    p = tmp_path / 'c.yaml'
    p.write_text(calibration_to_yaml(cal))
    assert load_calibration(p) == cal
    half = cal.scaled(cal.width // 2, cal.height // 2)
    assert half.k[0] == cal.k[0] / 2 and half.k[5] == cal.k[5] / 2
    p.write_text(calibration_to_yaml(cal).replace('rows: 3\n  cols: 4', 'rows: 2\n  cols: 4'))
    with pytest.raises(CalibrationError, match='projection_matrix'):
        load_calibration(p)
    with pytest.raises(CalibrationError, match='cannot read'):
        load_calibration(tmp_path / 'missing.yaml')


def test_skew_tracker_pairs_by_stamp_and_flags_over_bound():
    t = SkewTracker(['main', 'side'], bound_s=0.010, max_pending=3)
    assert t.add('main', 100, 1_000_000_000) is None
    skew, flagged = t.add('side', 100, 1_004_000_000)
    assert skew == pytest.approx(0.004) and not flagged
    t.add('side', 200, 2_000_000)
    skew, flagged = t.add('main', 200, 2_000_000 + 15_000_000)
    assert flagged and t.flagged == 1 and t.last_flagged_stamp_ns == 200
    for s in range(300, 800, 100):          # a camera that misses triggers
        t.add('main', s, s)
    assert t.incomplete == 2 and len(t.pending) == 3
    assert t.stats.summary()['n'] == 2
