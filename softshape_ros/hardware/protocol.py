"""
The host <-> Arduino Due wire protocol: framing, CRC-32, message layouts (docs/protocol.md).

The same layouts are implemented in C++ in ``firmware/due_pressure_bridge/bridge_core.h``;
both are checked against ``test/data/protocol_vectors.json`` so the two sides cannot drift.

Frame: ``A5 5A | type u8 | len u8 | payload[len] | crc32 u32 LE`` where the CRC (IEEE,
as zlib) covers type, len and payload. All integers are little endian; pressures are Pa.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

PROTOCOL_VERSION = 1
SYNC = b'\xa5\x5a'
HEADER = 4          # sync(2) + type + len
TRAILER = 4         # crc32
MAX_PAYLOAD = 64
N_CH = 6

# Host -> Due
T_HELLO = 0x01
T_CONFIG = 0x02
T_COMMAND = 0x03
T_VENT = 0x04
T_HEARTBEAT = 0x05
# Due -> host
T_HELLO_REPLY = 0x81
T_STATE = 0x82

# Status flags in STATE frames.
F_CLAMPED = 0x01     # the last command exceeded a firmware limit and was clamped
F_WATCHDOG = 0x02    # the firmware watchdog vented (no host frame in time)
F_VENTED = 0x04      # outputs are at zero (start-up, vent command or watchdog)
F_FAULT = 0x08       # a feedback channel reads outside its calibrated range
F_ACK = 0x10         # this state frame acknowledges the frame with sequence ``seq``

MAX_WIRE_PA = 0xFFFFFFFF


def crc32(data: bytes) -> int:
    """Return the IEEE CRC-32 (zlib's, reflected, init and final xor 0xFFFFFFFF)."""
    return zlib.crc32(data) & 0xFFFFFFFF


def encode_frame(ftype: int, payload: bytes = b'') -> bytes:
    """Wrap ``payload`` in sync, type, length and CRC."""
    if not 0 <= ftype <= 0xFF:
        raise ValueError(f'frame type must be a byte, got {ftype}')
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f'payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}')
    body = bytes((ftype, len(payload))) + bytes(payload)
    return SYNC + body + struct.pack('<I', crc32(body))


@dataclass(frozen=True)
class Frame:
    type: int
    payload: bytes


class FrameParser:
    """
    Stream parser that never raises and only yields frames whose CRC checks.

    After garbage or a bad CRC it drops one byte and rescans what it already holds,
    so it resynchronises on the next good frame even if that frame's start was
    swallowed by a false header. The C++ parser implements the same algorithm, and
    the ``bad_crc`` / ``skipped`` counters match byte for byte.
    """

    def __init__(self):
        self.buf = bytearray()
        self.frames_ok = 0
        self.bad_crc = 0       # candidate frames whose CRC failed (or length too big)
        self.skipped = 0       # bytes discarded while hunting for sync

    def feed(self, data: bytes) -> list[Frame]:
        """Add bytes; return the complete good frames found so far, in order."""
        return list(self.iter_feed(data))

    def iter_feed(self, data: bytes):
        """Add bytes and yield good frames lazily (counters are current at each yield)."""
        self.buf += data
        yield from self._scan()

    def pending(self) -> int:
        """Return how many bytes wait for the rest of a frame."""
        return len(self.buf)

    def flush(self) -> list[Frame]:
        """
        Give up on a partial frame after the line went idle, and rescan what follows it.

        Without this a truncated frame would hold the good frames behind it until enough
        new bytes arrive to prove its CRC wrong.
        """
        return list(self.iter_flush())

    def iter_flush(self):
        """Yield what :meth:`flush` returns, lazily (counters current at each yield)."""
        while self.buf:
            del self.buf[0]
            self.skipped += 1
            yield from self._scan()

    def _scan(self):
        buf = self.buf
        while True:
            if len(buf) < 2:
                if len(buf) == 1 and buf[0] != SYNC[0]:
                    del buf[0]
                    self.skipped += 1
                return
            if buf[0] != SYNC[0] or buf[1] != SYNC[1]:
                i = buf.find(SYNC, 1)
                if i < 0:
                    # keep a trailing first sync byte: its partner may be on its way
                    n = len(buf) - 1 if buf[-1] == SYNC[0] else len(buf)
                else:
                    n = i
                del buf[:n]
                self.skipped += n
                continue
            if len(buf) < HEADER:
                return
            n = buf[3]
            if n > MAX_PAYLOAD:
                self.bad_crc += 1
                del buf[0]
                self.skipped += 1
                continue
            total = HEADER + n + TRAILER
            if len(buf) < total:
                return
            body = bytes(buf[2:HEADER + n])
            (crc,) = struct.unpack_from('<I', buf, HEADER + n)
            if crc != crc32(body):
                self.bad_crc += 1
                del buf[0]
                self.skipped += 1
                continue
            self.frames_ok += 1
            del buf[:total]
            yield Frame(body[0], body[2:])


# ---------------------------------------------------------------- message layouts

class DecodeError(ValueError):
    """A frame with a good CRC but a payload that does not fit its type."""


def _pa_u32(values) -> list[int]:
    out = []
    for v in values:
        iv = int(round(float(v)))
        if not 0 <= iv <= MAX_WIRE_PA:
            raise ValueError(f'pressure {v} Pa does not fit the wire format (0..{MAX_WIRE_PA})')
        out.append(iv)
    if len(out) != N_CH:
        raise ValueError(f'need {N_CH} pressures, got {len(out)}')
    return out


@dataclass(frozen=True)
class Hello:
    version: int = PROTOCOL_VERSION

    def encode(self) -> bytes:
        return encode_frame(T_HELLO, struct.pack('<B', self.version))


@dataclass(frozen=True)
class HelloReply:
    version: int
    fw_major: int
    fw_minor: int
    n_channels: int
    state_rate_hz: int
    watchdog_ms: int
    limits_pa: tuple

    FMT = '<BBBBHH6I'

    def encode(self) -> bytes:
        return encode_frame(T_HELLO_REPLY, struct.pack(
            self.FMT, self.version, self.fw_major, self.fw_minor, self.n_channels,
            self.state_rate_hz, self.watchdog_ms, *_pa_u32(self.limits_pa)))


@dataclass(frozen=True)
class Config:
    seq: int
    state_rate_hz: int
    watchdog_ms: int
    limits_pa: tuple

    FMT = '<HHH6I'

    def encode(self) -> bytes:
        return encode_frame(T_CONFIG, struct.pack(
            self.FMT, self.seq & 0xFFFF, self.state_rate_hz, self.watchdog_ms,
            *_pa_u32(self.limits_pa)))


@dataclass(frozen=True)
class Command:
    seq: int
    setpoints_pa: tuple

    FMT = '<H6I'

    def encode(self) -> bytes:
        return encode_frame(T_COMMAND, struct.pack(self.FMT, self.seq & 0xFFFF,
                                                   *_pa_u32(self.setpoints_pa)))


@dataclass(frozen=True)
class Vent:
    seq: int

    FMT = '<H'

    def encode(self) -> bytes:
        return encode_frame(T_VENT, struct.pack(self.FMT, self.seq & 0xFFFF))


@dataclass(frozen=True)
class Heartbeat:
    def encode(self) -> bytes:
        return encode_frame(T_HEARTBEAT, b'')


@dataclass(frozen=True)
class State:
    seq: int
    t_us: int
    pressures_pa: tuple
    flags: int
    rx_errors: int

    FMT = '<HI6iBH'

    def encode(self) -> bytes:
        p = [int(round(x)) for x in self.pressures_pa]
        return encode_frame(T_STATE, struct.pack(self.FMT, self.seq & 0xFFFF,
                                                 self.t_us & 0xFFFFFFFF, *p, self.flags,
                                                 self.rx_errors))


_LAYOUTS = {
    T_HELLO: (Hello, '<B'),
    T_HELLO_REPLY: (HelloReply, HelloReply.FMT),
    T_CONFIG: (Config, Config.FMT),
    T_COMMAND: (Command, Command.FMT),
    T_VENT: (Vent, Vent.FMT),
    T_HEARTBEAT: (Heartbeat, '<'),
    T_STATE: (State, State.FMT),
}


def decode(frame: Frame):
    """Turn a CRC-checked frame into its message; DecodeError if type or length is wrong."""
    entry = _LAYOUTS.get(frame.type)
    if entry is None:
        raise DecodeError(f'unknown frame type 0x{frame.type:02x}')
    cls, fmt = entry
    if len(frame.payload) != struct.calcsize(fmt):
        raise DecodeError(f'frame type 0x{frame.type:02x} needs {struct.calcsize(fmt)} '
                          f'payload bytes, got {len(frame.payload)}')
    v = struct.unpack(fmt, frame.payload)
    if cls is Hello:
        return Hello(v[0])
    if cls is HelloReply:
        return HelloReply(*v[:6], limits_pa=tuple(v[6:]))
    if cls is Config:
        return Config(*v[:3], limits_pa=tuple(v[3:]))
    if cls is Command:
        return Command(v[0], tuple(v[1:]))
    if cls is Vent:
        return Vent(v[0])
    if cls is Heartbeat:
        return Heartbeat()
    return State(v[0], v[1], tuple(v[2:8]), v[8], v[9])
