"""
The Due firmware's C++ core (bridge_core.h), compiled with g++ and run on the golden vectors.

The same vectors drive the Python implementation (test_hardware_protocol.py), so the host,
the virtual Due and the real firmware cannot drift apart. Also type-checks the Arduino
sketch against declarations of the Arduino calls it uses (no ARM toolchain here).
"""

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
FW = ROOT / 'firmware'
VECTORS = json.loads((Path(__file__).parent / 'data' / 'protocol_vectors.json').read_text())
GXX = shutil.which('g++')

# A developer machine without g++ skips; CI (CI=true) must compile the firmware core.
pytestmark = pytest.mark.skipif(GXX is None and not os.environ.get('CI'),
                                reason='g++ not installed')


@pytest.fixture(scope='module')
def harness(tmp_path_factory):
    exe = tmp_path_factory.mktemp('fw') / 'harness'
    proc = subprocess.run([GXX, '-std=c++11', '-Wall', '-Wextra', '-Werror', '-O1',
                           '-o', str(exe), str(FW / 'host_test' / 'harness.cpp')],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return exe


def run(harness, lines):
    proc = subprocess.run([str(harness)], input='\n'.join(lines) + '\n', capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout.splitlines()
    assert len(out) == len(lines), proc.stdout
    return out


def test_crc32(harness):
    out = run(harness, [f'crc {c["hex"] or "-"}' for c in VECTORS['crc32']])
    assert [int(x) for x in out] == [c['crc'] for c in VECTORS['crc32']]


def test_golden_frames_parse(harness):
    out = run(harness, [f'parse {c["hex"]}' for c in VECTORS['frames']])
    for case, line in zip(VECTORS['frames'], out):
        payload = case['hex'][8:-8] or '-'
        assert line == f'1 1 0 0 {case["type"]}:{payload}', case['name']


def test_golden_streams(harness):
    out = run(harness, [f'parse {c["hex"] or "-"}' for c in VECTORS['streams']])
    for case, line in zip(VECTORS['streams'], out):
        want = [str(case['before_flush']), str(case['frames_ok']), str(case['bad_crc']),
                str(case['skipped'])]
        want += [f'{t}:{p or "-"}' for t, p in case['frames']]
        assert line.split() == want, case['name']


@pytest.mark.parametrize('case', VECTORS['cores'], ids=lambda c: c['name'])
def test_golden_firmware_behaviour(harness, case):
    lines = ['core ' + ' '.join(str(x) for x in case['fw_limits'])]
    for s in case['steps']:
        if s['op'] == 'measured':
            lines.append(f'measured {s["ch"]} {s["pa"]} {int(s["ok"])}')
        elif s['op'] == 'rx':
            lines.append(f'rx {s["t_us"]} {s["hex"] or "-"}')
        else:
            lines.append(f'tick {s["t_us"]}')
    out = run(harness, lines)
    assert out[0] == 'ok'
    for i, (s, line) in enumerate(zip(case['steps'], out[1:])):
        if s['op'] == 'measured':
            assert line == 'ok'
            continue
        e = s['expect']
        want = ' '.join([e['tx'] or '-'] + [str(x) for x in e['setpoints']] + [str(e['flags'])])
        assert line == want, f'{case["name"]} step {i}: {s}'


def test_sketch_type_checks_against_arduino_api():
    proc = subprocess.run(
        [GXX, '-std=gnu++11', '-Wall', '-Wextra', '-Werror', '-fsyntax-only',
         '-I', str(FW / 'host_test'), '-I', str(FW / 'due_pressure_bridge'), '-x', 'c++',
         '-include', 'Arduino.h', str(FW / 'due_pressure_bridge' / 'due_pressure_bridge.ino')],
        capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr


def test_sketch_pin_table_matches_rig_config():
    from softshape_ros.config import load_rig_config
    text = (FW / 'due_pressure_bridge' / 'due_pressure_bridge.ino').read_text()
    cfg = load_rig_config()
    for ch in cfg.chambers:
        row = next((ln for ln in text.splitlines() if f'{{"{ch.name}"' in ln), None)
        assert row is not None, f'{ch.name} missing from the sketch pin table'
        fw_limit = float(row.rstrip().rstrip('},').split(',')[-1])
        assert fw_limit >= ch.max_pressure_pa, f'{ch.name}: firmware limit below rig.yaml'


def _random_stream(rng):
    """Garbage, good frames, truncated and bit-flipped frames, in random order."""
    from softshape_ros.hardware import protocol as P
    parts = []
    for _ in range(rng.randrange(1, 12)):
        kind = rng.random()
        frame = P.encode_frame(rng.choice([1, 2, 3, 4, 5, 0x81, 0x82, rng.randrange(256)]),
                               bytes(rng.randrange(256) for _ in range(rng.randrange(0, 40))))
        if kind < 0.2:
            parts.append(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 30))))
        elif kind < 0.3:
            parts.append(frame[:rng.randrange(1, len(frame))])
        elif kind < 0.45:
            b = bytearray(frame)
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
            parts.append(bytes(b))
        elif kind < 0.5:
            parts.append(b'\xa5\x5a' + bytes([rng.randrange(256)]))
        else:
            parts.append(frame)
    return b''.join(parts)


def test_parsers_agree_on_random_streams(harness):
    """Differential test: the C++ and Python parsers split any stream identically."""
    import random

    from softshape_ros.hardware import protocol as P
    rng = random.Random(1234)
    streams = [_random_stream(rng) for _ in range(400)]
    out = run(harness, [f'parse {s.hex() or "-"}' for s in streams])
    for s, line in zip(streams, out):
        p = P.FrameParser()
        got = p.feed(s)
        n = len(got)
        got += p.flush()
        want = [str(n), str(p.frames_ok), str(p.bad_crc), str(p.skipped)]
        want += [f'{f.type}:{f.payload.hex() or "-"}' for f in got]
        assert line.split() == want, s.hex()


def test_firmware_cores_agree_on_random_sessions(harness):
    """Differential test: random host traffic and clocks through both firmware cores."""
    import random

    from softshape_ros.hardware import protocol as P
    from softshape_ros.hardware.due_core import DueCore
    rng = random.Random(99)
    for session in range(20):
        limits = [rng.randrange(1, 200000) for _ in range(6)]
        core = DueCore(limits)
        lines, expect = ['core ' + ' '.join(map(str, limits))], ['ok']
        t = rng.randrange(1 << 32)
        for _ in range(150):
            t = (t + rng.choice([0, 50, 900, 5000, 30000, 400000, 700000])) & 0xFFFFFFFF
            r = rng.random()
            if r < 0.3:
                core.tick(t)
                lines.append(f'tick {t}')
            elif r < 0.35:
                ch, pa, ok = rng.randrange(6), rng.randrange(-50000, 250000), rng.random() < .8
                core.set_measured(ch, pa, ok)
                lines.append(f'measured {ch} {pa} {int(ok)}')
                expect.append('ok')
                continue
            else:
                seq = rng.randrange(1 << 16)
                msg = rng.choice([
                    P.Command(seq, tuple(rng.randrange(0, 300000) for _ in range(6))),
                    P.Vent(seq), P.Heartbeat(), P.Hello(rng.choice([1, 2])),
                    P.Config(seq, rng.randrange(0, 3000), rng.randrange(0, 20000),
                             tuple(rng.randrange(0, 300000) for _ in range(6)))])
                data = bytearray(msg.encode())
                if rng.random() < 0.2:
                    data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
                if rng.random() < 0.2:
                    data = data[:rng.randrange(len(data))]
                core.receive(bytes(data), t)
                lines.append(f'rx {t} {bytes(data).hex() or "-"}')
            expect.append(' '.join([core.take_tx().hex() or '-'] + [str(x) for x in core.setpoints]
                                   + [str(core.flags())]))
        out = run(harness, lines)
        for i, (line, want) in enumerate(zip(out, expect)):
            assert line == want, f'session {session} step {i}: {lines[i]}'
