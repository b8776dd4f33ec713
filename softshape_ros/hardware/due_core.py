"""
The Due firmware's protocol and safety logic, in Python, step for step as bridge_core.h.

The virtual Due runs this so that what the tests prove about the emulator holds for the
firmware too: both are driven through the same golden vectors
(``test/data/protocol_vectors.json``), byte for byte. Time is the Due's ``micros()``,
a wrapping uint32, and all comparisons are wrap-safe as in C.
"""

from __future__ import annotations

from typing import Callable

from softshape_ros.hardware import protocol as P

FW_MAJOR, FW_MINOR = 1, 0
DEFAULT_STATE_RATE_HZ = 100
DEFAULT_WATCHDOG_MS = 500
MIN_RATE_HZ, MAX_RATE_HZ = 1, 1000
MIN_WATCHDOG_MS, MAX_WATCHDOG_MS = 20, 10000
IDLE_FLUSH_US = 20000      # a partial frame older than this is given up (see FrameParser.flush)

_U32 = 0xFFFFFFFF


def _elapsed(now: int, then: int) -> int:
    """Return ``now - then`` in wrapping uint32 arithmetic, like C's unsigned subtraction."""
    return (now - then) & _U32


def _due(now: int, deadline: int) -> bool:
    """Wrap-safe ``now >= deadline`` (int32 difference), as in C."""
    d = (now - deadline) & _U32
    return d < 0x80000000


class DueCore:
    """Frames in, set-points and frames out; no I/O, no clock of its own."""

    def __init__(self, fw_limits_pa, on_apply: Callable | None = None):
        self.fw_limits = [int(x) for x in fw_limits_pa]
        if len(self.fw_limits) != P.N_CH:
            raise ValueError(f'need {P.N_CH} firmware limits, got {len(self.fw_limits)}')
        self.limits = list(self.fw_limits)
        self.setpoints = [0] * P.N_CH
        self.measured = [0] * P.N_CH
        self.seq = 0
        self.clamped = False
        self.watchdog = False
        self.vented = True
        self.fault = False
        self._fault_bits = 0
        self.rx_errors = 0
        self.armed = False           # watchdog runs once a command has been applied
        self.last_rx = 0
        self.last_byte = 0
        self.next_state = 0
        self.state_period_us = 1_000_000 // DEFAULT_STATE_RATE_HZ
        self.state_rate_hz = DEFAULT_STATE_RATE_HZ
        self.watchdog_us = DEFAULT_WATCHDOG_MS * 1000
        self.parser = P.FrameParser()
        self.tx = bytearray()
        self.on_apply = on_apply

    # -------------------------------------------------------------- helpers
    def flags(self) -> int:
        return ((P.F_CLAMPED if self.clamped else 0) | (P.F_WATCHDOG if self.watchdog else 0)
                | (P.F_VENTED if self.vented else 0) | (P.F_FAULT if self.fault else 0))

    def _apply(self, values, reason: str) -> None:
        self.setpoints = list(values)
        if self.on_apply is not None:
            self.on_apply(tuple(self.setpoints), reason, self.seq)

    def _state(self, now: int, ack: bool) -> None:
        flags = self.flags() | (P.F_ACK if ack else 0)
        self.tx += P.State(self.seq, now & _U32, tuple(self.measured), flags,
                           min(self.rx_errors, 0xFFFF)).encode()

    def _bad(self) -> None:
        self.rx_errors = min(self.rx_errors + 1, 0xFFFF)

    # -------------------------------------------------------------- inputs
    def receive(self, data: bytes, now: int) -> None:
        """Feed bytes from the serial port at Due time ``now`` (microseconds)."""
        if data:
            self.last_byte = now & _U32
        self._frames(self.parser.iter_feed(data), now)

    def _frames(self, frames, now: int) -> None:
        seen = self.parser.bad_crc
        for frame in frames:
            seen = self._count_bad(seen)
            self.on_frame(frame, now)
        self._count_bad(seen)

    def _count_bad(self, seen: int) -> int:
        for _ in range(self.parser.bad_crc - seen):
            self._bad()
        return self.parser.bad_crc

    def on_frame(self, frame: P.Frame, now: int) -> None:
        try:
            msg = P.decode(frame)
        except P.DecodeError:
            self._bad()
            return
        if isinstance(msg, (P.HelloReply, P.State)):   # our own kinds: not from a host
            self._bad()
            return
        self.last_rx = now & _U32
        if isinstance(msg, P.Hello):
            self.tx += P.HelloReply(P.PROTOCOL_VERSION, FW_MAJOR, FW_MINOR, P.N_CH,
                                    self.state_rate_hz, self.watchdog_us // 1000,
                                    tuple(self.limits)).encode()
        elif isinstance(msg, P.Config):
            self.state_rate_hz = min(max(msg.state_rate_hz, MIN_RATE_HZ), MAX_RATE_HZ)
            self.state_period_us = 1_000_000 // self.state_rate_hz
            wd = min(max(msg.watchdog_ms, MIN_WATCHDOG_MS), MAX_WATCHDOG_MS)
            self.watchdog_us = wd * 1000
            # a host may lower the limits, never raise them above the firmware's own
            self.limits = [min(a, b) for a, b in zip(msg.limits_pa, self.fw_limits)]
            self.seq = msg.seq
            if any(s > lim for s, lim in zip(self.setpoints, self.limits)):
                self._apply([min(s, lim) for s, lim in zip(self.setpoints, self.limits)],
                            'config')
            self._state(now, ack=True)
        elif isinstance(msg, P.Command):
            values = [min(v, lim) for v, lim in zip(msg.setpoints_pa, self.limits)]
            self.clamped = any(v > lim for v, lim in zip(msg.setpoints_pa, self.limits))
            self.seq = msg.seq
            self.vented = False
            self.watchdog = False
            self.armed = True
            self._apply(values, 'command')
            self._state(now, ack=True)
        elif isinstance(msg, P.Vent):
            self.seq = msg.seq
            self.vent('vent')
            self._state(now, ack=True)
        # Heartbeat: only feeds the watchdog (last_rx above)

    def set_measured(self, ch: int, pa: int, in_range: bool = True) -> None:
        """Store a calibrated feedback reading; out-of-range channels raise the fault flag."""
        self.measured[ch] = int(pa)
        self._fault_bits = (self._fault_bits & ~(1 << ch)) | (0 if in_range else 1 << ch)
        self.fault = self._fault_bits != 0

    def vent(self, reason: str) -> None:
        self.vented = True
        self.armed = False
        self._apply([0] * P.N_CH, reason)

    def tick(self, now: int) -> None:
        """Run the watchdog and the state stream at Due time ``now``."""
        now &= _U32
        if self.parser.pending() and _elapsed(now, self.last_byte) > IDLE_FLUSH_US:
            self._frames(self.parser.iter_flush(), now)
        if self.armed and _elapsed(now, self.last_rx) > self.watchdog_us:
            self.watchdog = True
            self.vent('watchdog')
        if _due(now, self.next_state):
            self._state(now, ack=False)
            self.next_state = (self.next_state + self.state_period_us) & _U32
            if _due(now, self.next_state):          # fell behind: do not burst
                self.next_state = (now + self.state_period_us) & _U32

    def take_tx(self) -> bytes:
        out = bytes(self.tx)
        self.tx.clear()
        return out
