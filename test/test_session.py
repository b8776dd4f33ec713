"""The collection session as plain Python: pressure lists, command plans, the scene sequence."""

import itertools
import threading

import numpy as np
import pytest

from softshape_ros.scene import Scene
from softshape_ros.session import (CollectionSession, CommandPlan, RigFeedback, SessionError,
                                   SessionSettings, load_pressure_list)

LIMITS = [150000.0] * 6
NAMES = [f'ch{i}' for i in range(6)]


def test_pressure_list_loads_yaml_and_csv_and_rejects_bad_rows(tmp_path):
    y = tmp_path / 'p.yaml'
    y.write_text('pressures_pa:\n  - [0, 1000, 2000, 0, 0, 0]\n  - [5e+4, 0, 0, 0, 0, 1]\n')
    assert load_pressure_list(y, LIMITS).tolist() == [[0, 1000, 2000, 0, 0, 0],
                                                      [50000, 0, 0, 0, 0, 1]]
    c = tmp_path / 'p.csv'
    c.write_text('# six chambers, Pa\n1,2,3,4,5,6\n')
    assert load_pressure_list(c, LIMITS).tolist() == [[1, 2, 3, 4, 5, 6]]
    for text, match in [('pressures_pa: [[1, 2, 3]]', 'row 0: .*needs 6'),
                        ('pressures_pa: [[0, 0, 0, 0, 0, -1]]', 'negative'),
                        ('pressures_pa: [[0, 0, 0, 0, 0, .nan]]', 'non-finite'),
                        ('pressures_pa: [[0, 0, 0, 0, 0, 2.0e+5]]', 'exceed their limits'),
                        ('pressures_pa: []', 'empty'), ('foo: 1', 'pressures_pa')]:
        y.write_text(text)
        with pytest.raises(SessionError, match=match):
            load_pressure_list(y, LIMITS)
    with pytest.raises(SessionError, match='cannot read'):
        load_pressure_list(tmp_path / 'none.yaml', LIMITS)


def test_random_plan_is_seeded_uniform_within_limits():
    first = CommandPlan(LIMITS, seed=3, max_fraction=0.5).next()
    p1 = CommandPlan(LIMITS, seed=3, max_fraction=0.5)
    p2 = CommandPlan(LIMITS, seed=3, max_fraction=0.5)
    s1 = np.array([p1.next() for _ in range(400)])
    s2 = np.array([p2.next() for _ in range(400)])
    assert np.array_equal(s1, s2) and np.array_equal(first, s1[0])
    assert s1.min() >= 0 and s1.max() <= 75000.0
    assert s1.mean() == pytest.approx(37500.0, rel=0.1)       # uniform, not a constant
    replay = CommandPlan(LIMITS, replay=np.zeros((1, 6)))
    replay.next()
    with pytest.raises(SessionError, match='only 1 rows'):
        replay.next()


class InstantRig:
    """A RigIO whose regulators reach every command at once; records what it is asked."""

    def __init__(self, feedback, stop_after=None):
        self.feedback, self.stop_after = feedback, stop_after
        self.clock = itertools.count(1_000, 1_000)
        self.sent, self.records, self.scenes, self.logs = [], [], [], []
        self.session = None

    def now_ns(self):
        return next(self.clock)

    def rig_waiting_for(self):
        return ''

    def send(self, pressures_pa):
        self.sent.append([float(v) for v in pressures_pa])
        self.feedback.add_measured(self.now_ns(), NAMES, pressures_pa)

    def publish_scene(self, scene):
        self.scenes.append(scene.id)

    def trigger(self, record):
        self.records.append(record)
        for cam in ('main', 'side'):
            self.feedback.add_frame(cam, record.stamp_ns)
        if self.stop_after is not None and len(self.records) >= self.stop_after:
            self.session.stop()

    def log(self, level, text):
        self.logs.append((level, text))


def _session(rig_kwargs=None, n_scenes=2, actuations=2, n_rows=None):
    feedback = RigFeedback(NAMES, ['main', 'side'])
    rig = InstantRig(feedback, **(rig_kwargs or {}))
    scenes = [Scene.from_json(f'{{"id": {i}, "object": "sphere", "position_m": [0.02, 0, 0.02],'
                              f' "dims": {{"radius_m": 0.005}}, "actuations": {actuations}}}')
              for i in range(n_scenes)]
    n_rows = n_scenes * actuations if n_rows is None else n_rows
    rows = np.arange(1.0, 1.0 + 6 * n_rows).reshape(-1, 6) * 1000.0
    settings = SessionSettings(period_s=0.0, tolerance_pa=1.0, settle_timeout_s=1.0,
                               rest_delay_s=0.0, start_delay_s=0.0)
    session = CollectionSession(scenes, CommandPlan(LIMITS, replay=rows), settings, rig,
                                feedback, LIMITS)
    rig.session = session
    return session, rig, rows


def test_the_sequence_rest_then_actuations_per_scene_then_vent():
    session, rig, rows = _session()
    session.run_safely()
    assert session.state == 'done' and session.samples == 6 and session.unsettled == 0
    assert [(r.scene_id, r.kind, r.index) for r in rig.records] == [
        (0, 'rest', 0), (0, 'actuation', 0), (0, 'actuation', 1),
        (1, 'rest', 0), (1, 'actuation', 0), (1, 'actuation', 1)]
    assert [list(r.command_pa) for r in rig.records if r.kind == 'actuation'] == rows.tolist()
    assert all(r.settled for r in rig.records) and rig.scenes == [0, 1]
    assert rig.sent[-1] == [0.0] * 6
    stamps = [r.stamp_ns for r in rig.records]
    assert stamps == sorted(stamps)
    assert '"kind": "rest"' in rig.records[0].to_json()


def test_stop_ends_the_session_and_a_failure_vents():
    session, rig, _ = _session({'stop_after': 2})
    worker = threading.Thread(target=session.run_safely)
    worker.start()
    worker.join(timeout=10)
    assert session.done.is_set() and session.state == 'stopped' and len(rig.records) == 2
    session, rig, _ = _session(n_rows=3)              # the replay list runs out
    session.run_safely()
    assert session.state == 'failed' and 'only 3 rows' in session.error
    assert rig.sent[-1] == [0.0] * 6
