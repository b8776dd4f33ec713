"""SimCameras (mock_hardware's camera loop, no ROS): order, schedule, shape reuse, errors."""

import dataclasses

import numpy as np
import pytest

from softshape_ros.config import load_rig_config
from softshape_ros.scene import Scene
from softshape_ros.sim import SimRig, SolverError
from softshape_ros.sim.stream import FreeRunClock, SimCameras

CFG = load_rig_config()


def small_rig(**kw) -> SimRig:
    cams = {n: dataclasses.replace(c, width=80, height=60, fx=c.fx / 8, fy=c.fy / 8,
                                   cx=c.cx / 8, cy=c.cy / 8,
                                   crop_px=[v // 8 for v in c.crop_px])
            for n, c in CFG.cameras.items()}
    return SimRig(dataclasses.replace(CFG, cameras=cams), **kw)


class FakeClock:
    """A monotonic clock the test moves by hand (the schedule is then exact)."""

    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_free_run_clock_skips_late_slots_and_never_bursts():
    c = FreeRunClock(10.0, now_s=0.0)
    assert not c.take(0.05) and c.wait_s(0.05) == pytest.approx(0.05)
    assert c.take(0.1) and not c.take(0.1)                 # one frame per slot
    assert c.take(0.35) and c.skipped == 1                 # 0.2 and 0.3 overrun: one lost
    assert not c.take(0.39) and c.take(0.4)
    off = FreeRunClock(0.0, now_s=0.0)
    assert off.wait_s(1e9) == np.inf and not off.take(1e9)
    for bad in (-1.0, float('nan'), float('inf')):
        with pytest.raises(ValueError, match='free-run rate'):
            FreeRunClock(bad, 0.0)


def _cameras(rig, clock, hz=10.0, **kw):
    published, logs = [], []
    pressures = {'p': np.zeros(6)}
    cams = SimCameras(rig, published.append, lambda: (pressures['p'].copy(), int(clock.t * 1e9)),
                      free_run_hz=hz, log=lambda level, msg: logs.append((level, msg)),
                      monotonic=clock, **kw)
    return cams, published, pressures, logs


def counting_rig():
    """Return a small rig and the list of pressures each of its solves was asked for."""
    rig = small_rig()
    calls = []
    solve = rig.solve
    rig.solve = lambda p: calls.append(np.array(p)) or solve(p)
    return rig, calls


def test_triggers_first_free_frames_on_schedule_and_shapes_solved_only_on_change():
    clock = FakeClock()
    rig, calls = counting_rig()
    cams, out, pressures, _ = _cameras(rig, clock)
    assert cams.step(0.0) is None                           # nothing due yet
    clock.t += 0.1
    cams.trigger(7, [1e4, 0, 0, 0, 0, 0], 5)
    assert cams.step(0.0) == 'trigger'                      # queued work before the free frame
    assert cams.step(0.0) == 'free'
    assert [f.kind for f in out] == ['trigger', 'free']
    assert (out[0].stamp_ns, out[0].sampled_ns) == (7, 5)
    assert out[1].stamp_ns == out[1].sampled_ns == int(clock.t * 1e9)
    assert len(calls) == 2 and all(f.solved for f in out)
    # Same pressures: the shape (and, without noise, the images) are reused.
    for _ in range(3):
        clock.t += 0.1
        assert cams.step(0.0) == 'free'
    assert len(calls) == 2 and cams.reused == 3 and not out[-1].solved
    assert out[-1].images is out[1].images
    pressures['p'] = np.array([0, 5e4, 0, 0, 0, 0.0])
    clock.t += 0.1
    cams.step(0.0)
    assert len(calls) == 3 and out[-1].solved
    assert not np.array_equal(out[-1].images['main'], out[1].images['main'])
    # A scene change makes the same pressures a new shape.
    cams.set_scene(Scene(id=3, object='sphere', position_m=(0.03, 0.0, 0.02),
                         dims={'radius_m': 0.006}))
    assert cams.step(0.0) == 'scene' and cams.scene.id == 3
    clock.t += 0.1
    cams.step(0.0)
    assert len(calls) == 4 and cams.frames == 1 and cams.free_frames == 6
    # Late: the slots it overran are skipped, not made up.
    clock.t += 0.35
    assert cams.step(0.0) == 'free' and cams.step(0.0) is None and cams.clock.skipped == 2


def test_noise_gives_fresh_images_and_trigger_only_mode_has_no_free_frames():
    clock = FakeClock()
    cams, out, _, _ = _cameras(small_rig(image_noise_std=3.0), clock)
    clock.t += 0.1
    cams.step(0.0)
    clock.t += 0.1
    cams.step(0.0)
    assert cams.reused == 1 and not np.array_equal(out[0].images['main'], out[1].images['main'])
    off, out_off, _, _ = _cameras(small_rig(), clock, hz=0.0)
    clock.t += 1e6
    assert off.step(0.0) is None and out_off == []


def failing_rig():
    """Return a small rig whose every solve fails."""
    rig = small_rig()

    def fail(p):
        raise SolverError('did not converge (injected)')
    rig.solve = fail
    return rig


def test_failures_give_no_images_and_bad_scenes_keep_the_old_one():
    clock = FakeClock()
    rig = failing_rig()
    cams, out, pressures, logs = _cameras(rig, clock, max_pending=2)
    clock.t += 0.1
    cams.step(0.0)
    clock.t += 0.1
    cams.step(0.0)                                          # same pressures: not retried
    assert out == [] and cams.solver_errors == 1 and 'injected' in cams.last_error
    assert any(level == 'error' and 'no images' in msg for level, msg in logs)
    # Pressures the rig refuses (NaN, negative) on the real solver: no images either.
    real, real_out, _, _ = _cameras(small_rig(), clock)
    for bad in ([float('nan')] + [0.0] * 5, [-1.0] + [0.0] * 5):
        real.trigger(1, bad, 1)
        real.step(0.0)
    assert real_out == [] and real.solver_errors == 2 and 'CommandError' in real.last_error
    # A scene with a camera inside the object cannot be placed: logged, the old one stays.
    good = Scene(id=1, object='none')
    cams.set_scene(good)
    cams.step(0.0)
    cams.set_scene(Scene(id=2, object='sphere', position_m=tuple(CFG.cameras['main'].position_m),
                         dims={'radius_m': 0.01}))
    cams.step(0.0)
    assert cams.scene is good and 'scene 2' in cams.last_error
    # A full queue drops (and counts) instead of growing without bound.
    assert cams.trigger(1, np.zeros(6), 1) and cams.trigger(2, np.zeros(6), 2)
    assert not cams.trigger(3, np.zeros(6), 3) and cams.dropped == 1


def test_worker_thread_streams_and_stops():
    """The real loop on the real clock: frames arrive (counted, not timed), stop joins it."""
    import threading
    got = threading.Event()
    frames = []

    def publish(f):
        frames.append(f)
        if len(frames) >= 5:
            got.set()
    cams = SimCameras(small_rig(), publish, lambda: (np.zeros(6), 0), free_run_hz=100.0)
    cams.start()
    try:
        assert got.wait(60)
    finally:
        cams.stop()
    assert not cams._thread.is_alive() and all(f.kind == 'free' for f in frames)


def test_a_command_is_solved_on_arrival_and_a_trigger_before_it_settled_gets_its_own_shape():
    clock = FakeClock()
    rig, calls = counting_rig()
    cams, out, _, _ = _cameras(rig, clock, hz=0.0)
    target = np.array([3e4, 0, 0, 0, 2e4, 0.0])
    midway = 0.5 * target
    # Queued in arrival order: the command, a trigger while the regulators are on their way,
    # a trigger once they settled on it, then a command superseded before it was served.
    cams.command(target)
    cams.trigger(1, midway, 1)
    cams.trigger(2, target, 2)
    cams.command(np.zeros(6))
    cams.command(target)                                   # replaces the one before it
    assert [j[0] for j in cams.jobs] == ['command', 'trigger', 'trigger', 'command']
    assert cams.step(0.0) == 'command' and cams.command_solves == 1 and cams.solves == 0
    assert cams.step(0.0) == 'trigger'                     # not the commanded shape: solved
    assert cams.solves == 1 and out[-1].solved and np.array_equal(out[-1].pressures_pa, midway)
    assert np.array_equal(calls[-1], midway)
    assert cams.step(0.0) == 'trigger'                     # settled: rendered, not solved
    assert (cams.solves, cams.reused, len(calls)) == (1, 1, 2) and not out[-1].solved
    assert np.array_equal(out[-1].pressures_pa, target)
    # The frame it rendered is the commanded shape's: the same images as a fresh rig's.
    fresh = small_rig()
    assert np.array_equal(out[-1].images['main'], fresh.render(fresh.solve(target))['main'])
    assert cams.step(0.0) == 'command' and cams.command_solves == 1   # that shape is made
    assert cams.step(0.0) is None and cams.idle()
    # A scene change solves the commanded shape in the new scene before the next trigger.
    cams.set_scene(Scene(id=3, object='sphere', position_m=(0.03, 0.0, 0.02),
                         dims={'radius_m': 0.006}))
    assert cams.step(0.0) == 'scene' and cams.command_solves == 2 and len(calls) == 3
    cams.trigger(3, target, 3)
    assert cams.step(0.0) == 'trigger' and (cams.solves, len(calls)) == (1, 3)
    assert not out[-1].solved
    # Commands never fill the queue: triggers and scenes only count.
    small = _cameras(small_rig(), clock, hz=0.0, max_pending=1)[0]
    small.command(target)
    assert small.trigger(1, target, 1) and not small.trigger(2, target, 2)
    small.command(np.zeros(6))
    assert small.dropped == 1 and len(small.jobs) == 3


def test_a_failed_commanded_solve_is_logged_and_the_frame_solves_and_reports_it():
    clock = FakeClock()
    rig = failing_rig()
    cams, out, _, logs = _cameras(rig, clock, hz=0.0)
    cams.command(np.full(6, 1e4))
    cams.trigger(1, np.full(6, 1e4), 1)
    assert cams.step(0.0) == 'command' and cams.solver_errors == 0
    assert any(level == 'warning' and 'not solved' in msg for level, msg in logs)
    assert cams.step(0.0) == 'trigger' and out == [] and cams.solver_errors == 1
