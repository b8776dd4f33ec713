"""
The wire protocol and the firmware logic in Python, against the shared golden vectors.

test_hardware_firmware.py runs the same vectors through the C++ core the Due runs.
"""

import json
import struct
from pathlib import Path

import pytest
from hypothesis import given, settings, strategies as st

from softshape_ros.hardware import protocol as P
from softshape_ros.hardware.due_core import DueCore

VECTORS = json.loads((Path(__file__).parent / 'data' / 'protocol_vectors.json').read_text())


def test_vectors_match_protocol_version():
    assert VECTORS['protocol_version'] == P.PROTOCOL_VERSION


@pytest.mark.parametrize('case', VECTORS['crc32'], ids=lambda c: c['hex'] or 'empty')
def test_crc32_check_values(case):
    assert P.crc32(bytes.fromhex(case['hex'])) == case['crc']


@pytest.mark.parametrize('case', VECTORS['frames'], ids=lambda c: c['name'])
def test_golden_frames_encode_and_decode(case):
    cls = getattr(P, case['message'])
    fields = {k: tuple(v) if isinstance(v, list) else v for k, v in case['fields'].items()}
    msg = cls(**fields)
    assert msg.encode().hex() == case['hex']
    frames = P.FrameParser().feed(bytes.fromhex(case['hex']))
    assert len(frames) == 1 and frames[0].type == case['type']
    assert P.decode(frames[0]) == msg


@pytest.mark.parametrize('case', VECTORS['streams'], ids=lambda c: c['name'])
def test_golden_streams(case):
    p = P.FrameParser()
    got = p.feed(bytes.fromhex(case['hex']))
    assert len(got) == case['before_flush']
    got += p.flush()
    assert [[f.type, f.payload.hex()] for f in got] == case['frames']
    assert (p.frames_ok, p.bad_crc, p.skipped) == (case['frames_ok'], case['bad_crc'],
                                                   case['skipped'])


@pytest.mark.parametrize('case', VECTORS['cores'], ids=lambda c: c['name'])
def test_golden_firmware_behaviour(case):
    core = DueCore(case['fw_limits'])
    for i, s in enumerate(case['steps']):
        if s['op'] == 'measured':
            core.set_measured(s['ch'], s['pa'], s['ok'])
            continue
        if s['op'] == 'rx':
            core.receive(bytes.fromhex(s['hex']), s['t_us'])
        else:
            core.tick(s['t_us'])
        got = {'tx': core.take_tx().hex(), 'setpoints': core.setpoints, 'flags': core.flags()}
        assert got == s['expect'], f'step {i}: {s}'


def test_decode_rejects_wrong_lengths_and_types():
    with pytest.raises(P.DecodeError, match='needs 26 payload bytes, got 3'):
        P.decode(P.Frame(P.T_COMMAND, b'abc'))
    with pytest.raises(P.DecodeError, match='unknown frame type 0x77'):
        P.decode(P.Frame(0x77, b''))


def test_encoders_refuse_unrepresentable_pressures():
    with pytest.raises(ValueError, match='does not fit'):
        P.Command(1, (-1, 0, 0, 0, 0, 0)).encode()
    with pytest.raises(ValueError, match='need 6 pressures'):
        P.Command(1, (0,) * 5).encode()
    with pytest.raises(ValueError, match='exceeds 64'):
        P.encode_frame(1, bytes(65))


def test_firmware_limits_are_enforced_whatever_the_host_sends():
    applied = []
    core = DueCore([1000, 2000, 3000, 4000, 5000, 6000],
                   on_apply=lambda sp, why, seq: applied.append(sp))
    core.receive(P.Command(1, (10**9,) * 6).encode(), 0)
    core.receive(P.Config(2, 100, 500, (10**9,) * 6).encode(), 10)   # tries to raise
    core.receive(P.Command(3, (10**9,) * 6).encode(), 20)
    assert applied == [(1000, 2000, 3000, 4000, 5000, 6000)] * 2


# ------------------------------------------------------------------ property tests

good_frames = st.lists(
    st.tuples(st.integers(0, 255), st.binary(max_size=P.MAX_PAYLOAD)), max_size=4
).map(lambda fs: [P.encode_frame(t, p) for t, p in fs])


def _is_good(frame: P.Frame) -> bool:
    raw = P.encode_frame(frame.type, frame.payload)
    body = raw[2:-4]
    return struct.unpack('<I', raw[-4:])[0] == P.crc32(body)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=400), st.lists(st.integers(1, 50), max_size=8))
def test_any_byte_stream_never_raises_and_yields_only_checked_frames(data, cuts):
    p = P.FrameParser()
    out, pos = [], 0
    for c in cuts + [len(data)]:
        out += p.feed(data[pos:pos + c])
        pos += c
    out += p.flush()
    # every frame yielded is a byte-exact, CRC-valid substring of the input
    for f in out:
        assert _is_good(f)
        assert P.encode_frame(f.type, f.payload) in data
    assert p.pending() == 0


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200), good_frames, st.integers(1, 64))
def test_resynchronises_on_the_next_good_frame(garbage, frames, chunk):
    stream = garbage + b''.join(frames)
    p = P.FrameParser()
    out = []
    for i in range(0, len(stream), chunk):
        out += p.feed(stream[i:i + chunk])
    out += p.flush()
    tail = out[len(out) - len(frames):] if frames else []
    assert [P.encode_frame(f.type, f.payload) for f in tail] == frames


@settings(max_examples=200, deadline=None)
@given(good_frames, st.data())
def test_single_bit_errors_never_pass(frames, data):
    stream = bytearray(b''.join(frames))
    if not stream:
        return
    bit = data.draw(st.integers(0, len(stream) * 8 - 1))
    stream[bit // 8] ^= 1 << (bit % 8)
    p = P.FrameParser()
    out = p.feed(bytes(stream)) + p.flush()
    for f in out:
        assert P.encode_frame(f.type, f.payload) in frames
