"""Command validation and clamping: the one gate between a number and the air supply."""

import math

import numpy as np
import pytest
from hypothesis import given, strategies as st

from softshape_ros.pressure import CommandError, FirstOrderRegulator, check_command

LIM = [100e3] * 3 + [50e3] * 3


def test_clamps_and_reports():
    c = check_command([0, 10e3, 200e3, 0, 60e3, 50e3], LIM)
    assert c.pressures_pa.tolist() == [0, 10e3, 100e3, 0, 50e3, 50e3]
    assert c.clamped == (2, 4)


@pytest.mark.parametrize('bad, match', [
    ([0] * 5, 'needs 6 values, got 5'),
    ([0] * 7, 'needs 6 values, got 7'),
    ([0, 0, float('nan'), 0, 0, 0], 'non-finite values at chambers \\[2\\]'),
    ([0, 0, 0, float('inf'), 0, 0], 'non-finite'),
    ([0, -1, 0, 0, 0, 0], 'negative values at chambers \\[1\\]'),
    (['a'] * 6, 'must be numbers'),
    (None, 'must be numbers'),
])
def test_rejects_bad_commands(bad, match):
    with pytest.raises(CommandError, match=match):
        check_command(bad, LIM)


@given(st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=0, max_size=8))
def test_never_passes_anything_outside_limits(values):
    try:
        c = check_command(values, LIM)
    except CommandError:
        return
    assert np.all(c.pressures_pa >= 0) and np.all(c.pressures_pa <= np.asarray(LIM))


def test_regulator_is_first_order():
    r = FirstOrderRegulator(tau_s=0.1)
    r.setpoint[:] = 1000.0
    p = r.step(0.1)
    assert p[0] == pytest.approx(1000.0 * (1 - math.exp(-1)))
    for _ in range(100):
        p = r.step(0.01)
    assert p[0] == pytest.approx(1000.0, rel=1e-4)


def test_regulator_with_a_resolution_holds_the_setpoint_exactly_once_within_it():
    r = FirstOrderRegulator(tau_s=0.1, n=2, resolution_pa=10.0)
    r.setpoint[:] = [1000.0, 0.0]
    p = r.step(0.1 * math.log(1000.0 / 11.0))              # 11 Pa short: still the lag
    assert 1000.0 - p[0] == pytest.approx(11.0) and p[1] == 0.0
    p = r.step(0.1 * math.log(11.0 / 9.0))                 # 9 Pa short: settled
    assert p[0] == 1000.0 and (r.step(1.0) == [1000.0, 0.0]).all()
    with pytest.raises(ValueError, match='resolution_pa'):
        FirstOrderRegulator(resolution_pa=-1.0)


def test_measured_pressures_are_put_in_config_order_or_refused():
    from softshape_ros.pressure import measured_in_order
    names = ['a', 'b', 'c', 'd', 'e', 'f']
    assert measured_in_order(names[::-1], [6, 5, 4, 3, 2, 1], names).tolist() == [1, 2, 3, 4, 5, 6]
    assert measured_in_order([], [1, 2, 3, 4, 5, 6], names).tolist() == [1, 2, 3, 4, 5, 6]
    assert measured_in_order(names[:5] + ['x'], [1] * 6, names) is None       # unknown name
    assert measured_in_order(names, [1] * 5, names) is None                   # short
    assert measured_in_order([], [1, 2, 3, float('nan'), 5, 6], names) is None
