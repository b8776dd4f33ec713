"""
The Due firmware's C++ core (bridge_core.h), compiled with g++ and run on the golden vectors.

The same vectors drive the Python implementation (test_hardware_protocol.py), so the host,
the virtual Due and the real firmware cannot drift apart. Also type-checks the Arduino
sketch against declarations of the Arduino calls it uses (no ARM toolchain here).
"""

import json
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
FW = ROOT / 'firmware'
VECTORS = json.loads((Path(__file__).parent / 'data' / 'protocol_vectors.json').read_text())
GXX = shutil.which('g++')

pytestmark = pytest.mark.skipif(GXX is None, reason='g++ not installed')


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
