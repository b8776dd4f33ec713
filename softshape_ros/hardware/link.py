"""
The host end of the Due serial link: handshake, commands with acknowledgement, reconnect.

Safety rules this class keeps (docs/design.md "Safety"): it sends only what
:func:`~softshape_ros.pressure.check_command` accepted, clamped to the lower of the
configured and the firmware's limits; every (re)connection ends its handshake with a vent,
so nothing from before a lost link is ever applied again until a fresh command arrives; a
heartbeat keeps the firmware watchdog fed only while this process is alive; close() vents.
No rclpy here: the ``pressure_bridge`` node is a thin adapter over it.
"""

from __future__ import annotations

import collections
import logging
import statistics
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import serial

from softshape_ros.hardware import protocol as P
from softshape_ros.pressure import N_CHAMBERS

_U32 = 1 << 32
_log = logging.getLogger(__name__)


class LinkDown(RuntimeError):
    """The Due is not connected (or not yet handshaken); nothing was sent."""


class LinkError(RuntimeError):
    """The link misbehaved (no reply, wrong protocol, silence); it will be re-opened."""


@dataclass(frozen=True)
class Measurement:
    stamp_ns: int            # host clock, when the Due sampled (see DeviceClock)
    device_us: int           # the Due's micros(), unwrapped to 64 bits
    pressures_pa: np.ndarray
    flags: int
    seq: int


class DeviceClock:
    """
    Map the Due's wrapping microsecond clock onto the host clock.

    Each state frame gives ``host_rx - device_time`` = offset + transport delay, and the
    delay is never negative, so the smallest value over a sliding window (default 2 s) is
    the best offset estimate: it follows crystal drift (tens of ppm) and ignores frames
    that sat in a USB or OS buffer. A mapped stamp is never later than its arrival.
    A device clock jump (firmware reset) restarts the estimate.
    """

    def __init__(self, window_ns: int = 2_000_000_000):
        self.window_ns = int(window_ns)
        self.reset()

    def reset(self) -> None:
        self._raw = None
        self._ext = 0
        self._last_rx = 0
        self._cands = collections.deque()      # (rx_ns, candidate), candidates increasing

    def map(self, device_us: int, rx_ns: int) -> tuple[int, int]:
        """Return ``(stamp_ns, unwrapped_device_us)`` for a frame received at ``rx_ns``."""
        if self._raw is not None:
            delta = (device_us - self._raw) % _U32
            host_elapsed_us = (rx_ns - self._last_rx) / 1000.0
            if abs(delta - host_elapsed_us) > 500_000:     # reset or a jump: start over
                self.reset()
        if self._raw is None:
            self._ext = device_us
        else:
            self._ext += (device_us - self._raw) % _U32
        self._raw, self._last_rx = device_us, rx_ns
        cand = rx_ns - self._ext * 1000
        q = self._cands
        while q and q[-1][1] >= cand:
            q.pop()
        q.append((rx_ns, cand))
        while q[0][0] < rx_ns - self.window_ns:
            q.popleft()
        return self._ext * 1000 + q[0][1], self._ext


class DueLink:
    """
    Keep a link to the Due up, in a background thread, and send it checked commands.

    ``on_state(Measurement)`` is called from the link thread for every state frame;
    ``on_event(level, text)`` with 'info' / 'warn' / 'error' for things a person should see.
    """

    def __init__(self, port: str, limits_pa, baud: int = 115200, state_rate_hz: int = 100,
                 fw_watchdog_s: float = 0.5, clock_ns: Callable[[], int] = time.time_ns,
                 on_state: Callable | None = None, on_event: Callable | None = None,
                 heartbeat_s: float = 0.1, ack_timeout_s: float = 0.05,
                 stale_timeout_s: float = 0.5, backoff_s: tuple = (0.1, 2.0)):
        lim = [float(x) for x in limits_pa]
        if len(lim) != N_CHAMBERS or not all(x > 0 for x in lim):
            raise ValueError(f'need {N_CHAMBERS} positive limits, got {limits_pa}')
        self.port, self.baud = port, int(baud)
        self.host_limits = lim
        self.limits_pa = list(lim)           # effective: min(host, firmware) once connected
        self.state_rate_hz = int(state_rate_hz)
        self.fw_watchdog_ms = int(round(fw_watchdog_s * 1000))
        self.clock_ns = clock_ns
        self._on_state = on_state or (lambda m: None)
        self._on_event = on_event or (lambda level, text: None)
        self.heartbeat_s, self.ack_timeout_s = heartbeat_s, ack_timeout_s
        self.stale_timeout_s, self.backoff_s = stale_timeout_s, backoff_s
        self.clock = DeviceClock()
        self._ser = None
        self._wlock = threading.Lock()
        self._stop = threading.Event()
        self._connected = threading.Event()
        self._thread = None
        self._seq = 0
        self._pending = None                 # (seq, frame bytes, first sent, last sent)
        self._acked = threading.Condition(self._wlock)
        self._last_ack_seq = None
        self.firmware = ''
        self.last_error = 'not started'
        self.last_flags = 0
        self.last_state_mono = 0.0
        self.rtts_s = collections.deque(maxlen=2000)
        self.counters = collections.Counter()
        self._last_kick = None               # host liveness; None = not gated (no kick() yet)

    # ------------------------------------------------------------------ public API
    def start(self) -> 'DueLink':
        self._thread = threading.Thread(target=self._run, name='due_link', daemon=True)
        self._thread.start()
        return self

    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    def wait_connected(self, timeout: float) -> bool:
        return self._connected.wait(timeout)

    def send_command(self, pressures_pa) -> int:
        """Send six already-checked set-points (Pa); return the sequence number."""
        p = np.minimum(np.asarray(pressures_pa, dtype=np.float64), self.limits_pa)
        if p.shape != (N_CHAMBERS,) or not np.all(np.isfinite(p)) or np.any(p < 0):
            raise ValueError(f'send_command needs {N_CHAMBERS} checked pressures, got {p}')
        return self._send(lambda seq: P.Command(seq, tuple(int(round(x)) for x in p)))

    def kick(self) -> None:
        """
        Say the host is alive; once called, heartbeats stop when kicks stop.

        The firmware watchdog is fed by heartbeats from this link thread; a host whose
        executor hangs must not keep the last set-point alive through them.
        """
        self._last_kick = time.monotonic()

    def vent(self) -> int:
        """Ask the firmware to vent all chambers to zero (acknowledged and retried)."""
        return self._send(P.Vent)

    def lower_limits(self, limits_pa) -> int | None:
        """
        Lower the per-chamber limits at run time (never raise them); tell the firmware.

        The host clamps to the new limits at once; when connected, a CONFIG frame carries
        them to the Due, which clamps its current set-point too. Returns that frame's
        sequence number (None when the link is down: the next handshake sends them).
        """
        new = [float(x) for x in limits_pa]
        if len(new) != N_CHAMBERS or not all(np.isfinite(new)) or min(new) <= 0:
            raise ValueError(f'need {N_CHAMBERS} positive limits, got {limits_pa}')
        raised = [i for i, (a, b) in enumerate(zip(new, self.host_limits)) if a > b]
        if raised:
            raise ValueError(f'limits may only be lowered at run time (chambers {raised})')
        self.host_limits = new
        self.limits_pa = [min(a, b) for a, b in zip(new, self.limits_pa)]
        if not self.connected:
            return None
        return self._send(lambda s: P.Config(s, self.state_rate_hz, self.fw_watchdog_ms,
                                             tuple(int(x) for x in self.limits_pa)))

    def wait_ack(self, seq: int, timeout: float) -> bool:
        """Block until the frame ``seq`` is acknowledged (True) or ``timeout`` passes."""
        deadline = time.monotonic() + timeout
        with self._acked:
            while self._last_ack_seq != seq:
                left = deadline - time.monotonic()
                if left <= 0 or not self.connected:
                    return False
                self._acked.wait(left)
            return True

    def close(self, vent: bool = True, timeout: float = 0.5) -> bool:
        """Vent (if ``vent``), wait for the acknowledgement, stop and close; True if vented."""
        vented = False
        if vent and self.connected:
            try:
                vented = self.wait_ack(self.vent(), timeout)
            except LinkDown:
                pass
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._drop_port()
        return vented

    def status(self) -> dict:
        """Counters and state for diagnostics."""
        rtts = sorted(self.rtts_s)
        d = {'port': self.port, 'connected': self.connected, 'firmware': self.firmware,
             'last_error': self.last_error, 'limits_pa': [round(x) for x in self.limits_pa],
             'flags': self.last_flags}
        d.update(self.counters)
        if rtts:
            d['ack_rtt_median_ms'] = round(1e3 * statistics.median(rtts), 3)
            d['ack_rtt_p99_ms'] = round(1e3 * rtts[min(len(rtts) - 1, int(0.99 * len(rtts)))], 3)
        return d

    # A failing callback must never take the link thread (and its heartbeat) down.
    def on_event(self, level: str, text: str) -> None:
        try:
            self._on_event(level, text)
        except Exception as exc:  # noqa: BLE001 - report and keep the link alive
            _log.error('on_event failed: %r (%s: %s)', exc, level, text)

    def on_state(self, m: Measurement) -> None:
        try:
            self._on_state(m)
        except Exception as exc:  # noqa: BLE001
            self.counters['callback_errors'] += 1
            self.last_error = f'on_state failed: {exc!r}'

    # ------------------------------------------------------------------ sending
    def _send(self, make) -> int:
        with self._wlock:
            if not self.connected or self._ser is None:
                raise LinkDown(f'Due link on {self.port} is down: {self.last_error}')
            self._seq = (self._seq + 1) & 0xFFFF
            frame = make(self._seq).encode()
            now = time.monotonic()
            self._pending = (self._seq, frame, now, now)
            self._write(frame)
            self.counters['sent'] += 1
            return self._seq

    def _write(self, data: bytes) -> None:
        """Write under ``_wlock``; a failure drops the link (the thread reconnects)."""
        try:
            self._ser.write(data)
        except (serial.SerialException, OSError) as exc:
            self._connected.clear()
            self.last_error = f'write failed: {exc}'
            raise LinkDown(f'Due link on {self.port}: {self.last_error}') from None
        self._last_tx = time.monotonic()

    # ------------------------------------------------------------------ link thread
    def _run(self) -> None:
        backoff = self.backoff_s[0]
        while not self._stop.is_set():
            try:
                ser = serial.Serial(self.port, self.baud, timeout=0.01,
                                    write_timeout=max(0.5, self.stale_timeout_s))
            except (serial.SerialException, OSError, ValueError) as exc:
                self._down(f'cannot open {self.port}: {exc}', 'error_once')
                self._stop.wait(backoff)
                backoff = min(backoff * 2, self.backoff_s[1])
                continue
            with self._wlock:
                self._ser = ser
            try:
                self._handshake()
                backoff = self.backoff_s[0]
                self._serve()
            except (LinkError, LinkDown, serial.SerialException, OSError) as exc:
                self._down(str(exc), 'error')
            except Exception as exc:  # noqa: BLE001 - never let the link thread die
                self._down(f'unexpected {type(exc).__name__}: {exc}', 'error')
            finally:
                self._drop_port()
            if not self._stop.is_set():
                self._stop.wait(backoff)
                backoff = min(backoff * 2, self.backoff_s[1])

    def _down(self, why: str, level: str) -> None:
        was = self.connected
        self._connected.clear()
        with self._wlock:
            self._pending = None
        if was or level == 'error' or why != self.last_error:
            self.on_event('error', f'Due link down: {why}')
        if was:
            self.counters['disconnects'] += 1
        self.last_error = why

    def _drop_port(self) -> None:
        self._connected.clear()
        with self._wlock:
            ser, self._ser = self._ser, None
            self._pending = None
        if ser is not None:
            try:
                ser.close()
            except (serial.SerialException, OSError):
                pass

    def _read_frames(self, parser: P.FrameParser) -> list:
        ser = self._ser
        data = ser.read(max(1, ser.in_waiting))
        if data:
            self._last_byte = time.monotonic()
            return parser.feed(data)
        if parser.pending() and time.monotonic() - self._last_byte > 0.02:
            return parser.flush()
        return []

    def _await(self, parser, want, deadline: float):
        while time.monotonic() < deadline and not self._stop.is_set():
            for frame in self._read_frames(parser):
                try:
                    msg = P.decode(frame)
                except P.DecodeError:
                    continue
                if want(msg):
                    return msg
        return None

    def _handshake(self) -> None:
        parser = self._parser = P.FrameParser()
        self._last_byte = time.monotonic()
        reply = None
        for _ in range(3):
            with self._wlock:
                self._write(P.Hello().encode())
            reply = self._await(parser, lambda m: isinstance(m, P.HelloReply),
                                time.monotonic() + 0.3)
            if reply is not None or self._stop.is_set():
                break
        if reply is None:
            raise LinkError(f'no hello reply from {self.port} (is it a softshape Due?)')
        if reply.version != P.PROTOCOL_VERSION or reply.n_channels != N_CHAMBERS:
            raise LinkError(f'firmware speaks protocol v{reply.version} with '
                            f'{reply.n_channels} channels; host needs '
                            f'v{P.PROTOCOL_VERSION} with {N_CHAMBERS}')
        self.firmware = f'{reply.fw_major}.{reply.fw_minor}'
        self.limits_pa = [min(h, float(f)) for h, f in zip(self.host_limits, reply.limits_pa)]
        lowered = [i for i, (h, f) in enumerate(zip(self.host_limits, reply.limits_pa)) if f < h]
        if lowered:
            self.on_event('warn', f'firmware limits are below the configured ones at chambers '
                                  f'{lowered}: using {self.limits_pa}')
        # Configure, then vent: after any (re)connection the hardware sits at zero until a
        # fresh command arrives, whatever it was doing before the link broke.
        for make in (lambda s: P.Config(s, self.state_rate_hz, self.fw_watchdog_ms,
                                        tuple(int(x) for x in self.limits_pa)), P.Vent):
            acked = None
            for _ in range(3):
                with self._wlock:
                    self._seq = (self._seq + 1) & 0xFFFF
                    seq = self._seq
                    self._write(make(seq).encode())
                acked = self._await(parser, lambda m: isinstance(m, P.State)
                                    and m.flags & P.F_ACK and m.seq == seq,
                                    time.monotonic() + 0.3)
                if acked is not None:
                    break
            if acked is None:
                raise LinkError(f'handshake with {self.port}: configuration not acknowledged')
        self.clock.reset()
        self.last_state_mono = time.monotonic()
        self._last_tx = time.monotonic()
        self.counters['connects'] += 1
        self.last_error = ''
        self._connected.set()
        self.on_event('info', f'Due link up on {self.port}: firmware {self.firmware}, '
                              f'limits {[round(x) for x in self.limits_pa]} Pa')

    def _serve(self) -> None:
        parser = self._parser
        bad_seen = parser.bad_crc
        while not self._stop.is_set():
            if not self.connected:
                raise LinkError(self.last_error or 'link dropped')
            frames = self._read_frames(parser)
            rx_ns = self.clock_ns()
            for frame in frames:
                self._handle(frame, rx_ns)
            if parser.bad_crc != bad_seen:
                self.counters['bad_frames'] += parser.bad_crc - bad_seen
                bad_seen = parser.bad_crc
            now = time.monotonic()
            if now - self.last_state_mono > self.stale_timeout_s:
                raise LinkError(f'no state from the Due for {now - self.last_state_mono:.2f} s')
            with self._wlock:
                if self._pending is not None and now - self._pending[3] > self.ack_timeout_s:
                    seq, frame, first, _ = self._pending
                    self._pending = (seq, frame, first, now)
                    self.counters['retransmits'] += 1
                    self._write(frame)
                elif now - self._last_tx > self.heartbeat_s and self._host_alive(now):
                    self._write(P.Heartbeat().encode())

    def _host_alive(self, now: float) -> bool:
        return self._last_kick is None or now - self._last_kick < self.fw_watchdog_ms / 1000

    def _handle(self, frame: P.Frame, rx_ns: int) -> None:
        try:
            msg = P.decode(frame)
        except P.DecodeError:
            self.counters['bad_frames'] += 1
            return
        if not isinstance(msg, P.State):
            return
        self.counters['states'] += 1
        self.last_state_mono = time.monotonic()
        if msg.flags & P.F_ACK:
            with self._acked:
                if self._pending is not None and self._pending[0] == msg.seq:
                    self.rtts_s.append(self.last_state_mono - self._pending[2])
                    self._pending = None
                    self.counters['acks'] += 1
                self._last_ack_seq = msg.seq
                self._acked.notify_all()
        changed = (msg.flags ^ self.last_flags) & (P.F_WATCHDOG | P.F_CLAMPED | P.F_FAULT)
        if changed & msg.flags & P.F_WATCHDOG:
            self.on_event('error', 'Due firmware watchdog vented (no host frame in time)')
        if changed & msg.flags & P.F_CLAMPED:
            self.on_event('warn', 'Due firmware clamped a command to its own limits')
        if changed & msg.flags & P.F_FAULT:
            # No trustworthy measurement: do not hold pressure blind; vent and report.
            self.on_event('error', 'Due reports a pressure feedback fault: venting')
            # Counted before it is sent: whoever sees the vent at the Due sees the count.
            self.counters['fault_vents'] += 1
            try:
                self.vent()
            except LinkDown:
                self.counters['fault_vents_unsent'] += 1
        self.last_flags = msg.flags & ~P.F_ACK
        stamp_ns, dev_us = self.clock.map(msg.t_us, rx_ns)
        self.on_state(Measurement(stamp_ns, dev_us, np.asarray(msg.pressures_pa, dtype=float),
                                  msg.flags, msg.seq))
