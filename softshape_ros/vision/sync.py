"""
Pairing the cameras' frames by trigger stamp and measuring their real capture skew.

Both camera_trigger instances stamp a frame with the trigger's stamp, so pairs match
exactly; what can differ is *when* each camera really captured (TimeReference.time_ref).
A pair further apart than the bound (paper: 10 ms) is flagged so that the recorder and
the dataset builder can drop it. Plain Python so the benchmark and the tests share it.
"""

from __future__ import annotations

from collections import OrderedDict, deque

import numpy as np

__all__ = ['SkewTracker', 'RollingStats']


class RollingStats:
    """Median / p99 / max of the last ``window`` values (latencies, skews), in seconds."""

    def __init__(self, window: int = 1000):
        self.values: deque = deque(maxlen=window)
        self.count = 0

    def add(self, value: float) -> None:
        self.values.append(float(value))
        self.count += 1

    def summary(self, scale: float = 1e3, digits: int = 3) -> dict:
        """Return ``{n, median, p99, max}`` scaled (default: seconds -> ms)."""
        if not self.values:
            return {'n': 0, 'median': None, 'p99': None, 'max': None}
        a = np.asarray(self.values) * scale
        return {'n': self.count, 'median': round(float(np.median(a)), digits),
                'p99': round(float(np.percentile(a, 99)), digits),
                'max': round(float(a.max()), digits)}


class SkewTracker:
    """
    Collect capture times per trigger stamp; when every camera has reported, emit the skew.

    ``add(camera, stamp_ns, capture_ns)`` returns ``(skew_s, flagged)`` once the set for
    that stamp is complete, else None. Incomplete sets older than ``max_pending`` stamps are
    forgotten (a camera missed that trigger) and counted in ``incomplete``.
    """

    def __init__(self, cameras, bound_s: float = 0.010, max_pending: int = 64,
                 window: int = 1000):
        self.cameras = frozenset(cameras)
        if len(self.cameras) < 2:
            raise ValueError(f'need at least two cameras to pair, got {sorted(self.cameras)}')
        self.bound_s = float(bound_s)
        self.max_pending = int(max_pending)
        self.pending: OrderedDict = OrderedDict()
        self.stats = RollingStats(window)
        self.flagged = 0
        self.incomplete = 0
        self.last_flagged_stamp_ns: int | None = None
        self.last_pair_stamp_ns: int | None = None     # the trigger last paired

    def add(self, camera: str, stamp_ns: int, capture_ns: int):
        if camera not in self.cameras:
            return None
        got = self.pending.setdefault(int(stamp_ns), {})
        got[camera] = int(capture_ns)
        if set(got) != self.cameras:
            while len(self.pending) > self.max_pending:
                self.pending.popitem(last=False)
                self.incomplete += 1
            return None
        del self.pending[int(stamp_ns)]
        skew = (max(got.values()) - min(got.values())) / 1e9
        self.stats.add(skew)
        self.last_pair_stamp_ns = int(stamp_ns)
        flagged = skew > self.bound_s
        if flagged:
            self.flagged += 1
            self.last_flagged_stamp_ns = int(stamp_ns)
        return skew, flagged
