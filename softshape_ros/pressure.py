"""
Pressure command safety and the regulator model: rig-level, for every layer to use.

Every path that turns a number into air (pressure_bridge, mock_hardware, the simulator)
and every path that predicts from one (inference) checks commands the same way: 6 values,
finite, not negative; above a chamber's limit is clamped and reported, never silently
passed on. It sits beside config.py and scene.py, under no layer, so that sim/, model/,
data/ and hardware/ all depend on it and never on each other for it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

N_CHAMBERS = 6


class CommandError(ValueError):
    """A pressure command is unusable (wrong length, NaN/inf, negative); nothing is applied."""


@dataclass(frozen=True)
class CheckedCommand:
    pressures_pa: np.ndarray        # float64[6], clamped to the limits
    clamped: tuple                  # indices of chambers that were clamped


def check_command(values, limits_pa) -> CheckedCommand:
    """Validate a 6-chamber command in Pa and clamp it to ``limits_pa``."""
    try:
        v = [float(x) for x in values]
    except (TypeError, ValueError):
        raise CommandError(f'pressure command must be numbers, got {values!r}') from None
    if len(v) != N_CHAMBERS:
        raise CommandError(f'pressure command needs {N_CHAMBERS} values, got {len(v)}')
    bad = [i for i, x in enumerate(v) if not math.isfinite(x)]
    if bad:
        raise CommandError(f'pressure command has non-finite values at chambers {bad}: {v}')
    neg = [i for i, x in enumerate(v) if x < 0.0]
    if neg:
        raise CommandError(f'pressure command has negative values at chambers {neg}: {v}')
    lim = np.asarray(limits_pa, dtype=np.float64)
    if lim.shape != (N_CHAMBERS,):
        raise CommandError(f'limits need {N_CHAMBERS} values, got {lim.shape}')
    arr = np.asarray(v, dtype=np.float64)
    clamped = tuple(int(i) for i in np.nonzero(arr > lim)[0])
    return CheckedCommand(np.minimum(arr, lim), clamped)


def measured_in_order(names, effort, chamber_names):
    """
    Return measured pressures (JointState name/effort) in config order, or None if unusable.

    Unnamed values are taken in order; named ones must be exactly the configured chambers.
    Used by the collector (live) and the dataset builder (bags) alike.
    """
    values = [float(v) for v in effort]
    names = list(names)
    if names:
        if sorted(names) != sorted(chamber_names) or len(values) != len(names):
            return None
        by = dict(zip(names, values))
        values = [by[n] for n in chamber_names]
    if len(values) != len(chamber_names) or not all(math.isfinite(v) for v in values):
        return None
    return np.asarray(values, dtype=np.float64)


class FirstOrderRegulator:
    """
    Proportional pressure regulators as first-order lags (time constant ``tau_s``).

    Stands in for six Camozzi K8P regulators in the virtual Due and the mock hardware.
    ``resolution_pa`` > 0: a chamber within that of its setpoint holds the setpoint exactly
    (settled, as a regulator stops correcting inside its resolution); 0 is the pure lag,
    which reaches the setpoint only in the limit.
    """

    def __init__(self, tau_s: float = 0.05, n: int = N_CHAMBERS, resolution_pa: float = 0.0):
        if tau_s < 0:
            raise ValueError(f'tau_s must be >= 0, got {tau_s}')
        if not (resolution_pa >= 0 and math.isfinite(resolution_pa)):
            raise ValueError(f'resolution_pa must be finite and >= 0, got {resolution_pa}')
        self.tau_s = float(tau_s)
        self.resolution_pa = float(resolution_pa)
        self.setpoint = np.zeros(n)
        self.pressure = np.zeros(n)

    def step(self, dt: float) -> np.ndarray:
        """Advance ``dt`` seconds (exact discretisation of the lag) and return the pressures."""
        if dt > 0:
            a = 1.0 if self.tau_s == 0 else 1.0 - math.exp(-dt / self.tau_s)
            self.pressure += a * (self.setpoint - self.pressure)
            if self.resolution_pa > 0:
                near = np.abs(self.setpoint - self.pressure) <= self.resolution_pa
                self.pressure[near] = self.setpoint[near]
        return self.pressure.copy()
