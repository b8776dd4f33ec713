"""
Regenerate test/data/protocol_vectors.json from the Python implementation.

Run only for an intentional protocol change (then bump PROTOCOL_VERSION): the file is the
contract that both the Python side and the C++ firmware core are tested against, so a
change here must be reviewed as a wire-format change. Usage:
    .venv/bin/python firmware/host_test/make_vectors.py
"""

import json
from pathlib import Path

from softshape_ros.hardware import protocol as P
from softshape_ros.hardware.due_core import DueCore

OUT = Path(__file__).resolve().parents[2] / 'test' / 'data' / 'protocol_vectors.json'
LIM = [150000] * 6


def frames():
    msgs = [
        ('hello', P.Hello(1)),
        ('hello_reply', P.HelloReply(1, 1, 0, 6, 100, 500, tuple(LIM))),
        ('config', P.Config(7, 200, 250, (100000, 120000, 150000, 150000, 90000, 60000))),
        ('command', P.Command(42, (0, 1000, 25000, 50000, 100000, 150000))),
        ('command_seq_wrap', P.Command(65535, (1, 2, 3, 4, 5, 6))),
        ('vent', P.Vent(43)),
        ('heartbeat', P.Heartbeat()),
        ('state', P.State(42, 123456789, (0, -150, 25010, 49990, 100000, 149000),
                          P.F_ACK | P.F_CLAMPED, 3)),
    ]
    out = []
    for name, m in msgs:
        f = m.encode()
        fields = {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(m).items()}
        out.append({'name': name, 'message': type(m).__name__, 'type': f[2], 'fields': fields,
                    'hex': f.hex()})
    return out


def streams():
    cmd = P.Command(1, (10, 20, 30, 40, 50, 60)).encode()
    vent = P.Vent(2).encode()
    hb = P.Heartbeat().encode()
    bad = bytearray(cmd)
    bad[10] ^= 0x04
    cases = {
        'garbage_then_frames': b'\x00\xff\x13hello' + cmd + vent,
        'frame_split_by_false_header': b'\xa5\x5a\x03\x20' + cmd + vent + hb,
        'length_too_big': b'\xa5\x5a\x03\xff' + vent,
        'corrupted_then_good': bytes(bad) + cmd,
        'truncated_then_good': cmd[:9] + vent,
        'lone_sync_bytes': b'\xa5\xa5\xa5\x5a\x5a' + hb + b'\xa5',
        'sync_inside_payload': P.Command(0x5aa5, (0xa55a, 0x5aa5, 0, 0, 0, 0)).encode() + hb,
        'only_garbage': bytes(range(256)),
    }
    out = []
    for name, data in cases.items():
        p = P.FrameParser()
        got = p.feed(data)
        before_flush = len(got)
        got += p.flush()
        out.append({'name': name, 'hex': data.hex(), 'before_flush': before_flush,
                    'frames': [[f.type, f.payload.hex()] for f in got],
                    'frames_ok': p.frames_ok, 'bad_crc': p.bad_crc, 'skipped': p.skipped})
    return out


def scenario(name, steps, limits=LIM):
    core = DueCore(limits)
    out = []
    for s in steps:
        s = dict(s)
        if s['op'] == 'measured':
            core.set_measured(s['ch'], s['pa'], s['ok'])
        else:
            if s['op'] == 'rx':
                core.receive(bytes.fromhex(s['hex']), s['t_us'])
            else:
                core.tick(s['t_us'])
            s['expect'] = {'tx': core.take_tx().hex(), 'setpoints': list(core.setpoints),
                           'flags': core.flags()}
        out.append(s)
    return {'name': name, 'fw_limits': list(limits), 'steps': out}


def rx(t, *msgs):
    data = b''.join(m if isinstance(m, bytes) else m.encode() for m in msgs)
    return {'op': 'rx', 't_us': t, 'hex': data.hex()}


def tick(t):
    return {'op': 'tick', 't_us': t}


def cores():
    c = P.Command
    bad = bytearray(c(5, (1000,) * 6).encode())
    bad[12] ^= 0x80
    return [
        scenario('hello_and_first_state', [rx(0, P.Hello()), tick(0), tick(9999), tick(10000)]),
        scenario('command_ack', [tick(0), rx(100, c(1, (0, 1000, 2000, 3000, 4000, 5000))),
                                 tick(200)]),
        scenario('command_clamped', [rx(50, c(2, (200000, 1000, 150000, 150001, 0, 10**9)))]),
        scenario('config_lowers_never_raises', [
            rx(0, P.Config(3, 50, 100, (100000, 200000, 150000, 0, 80000, 150000))),
            rx(10, P.Hello()),
            rx(20, c(4, (150000,) * 6)),
            rx(30, c(5, (150000,) * 6)),
            rx(40, P.Config(6, 5000, 5, (50000,) * 6)),
            tick(50), tick(20049), tick(20050)]),
        scenario('watchdog_vents', [
            rx(1000, c(1, (5000,) * 6)),
            rx(300000, P.Heartbeat()),
            tick(700000), tick(800000), tick(800001), tick(900000),
            rx(910000, c(2, (7000,) * 6))], limits=[20000] * 6),
        scenario('no_watchdog_before_first_command', [rx(0, P.Heartbeat()), tick(5_000_000)]),
        scenario('vent_command', [rx(0, c(1, (9000,) * 6)), rx(10, P.Vent(2)), tick(20)]),
        scenario('corrupted_command_ignored', [rx(0, c(1, (3000,) * 6)), rx(10, bytes(bad)),
                                               tick(20), rx(30, b'\xa5\x5a\x03\xff\x00')]),
        scenario('wrong_types_and_lengths', [
            rx(0, P.State(1, 2, (0,) * 6, 0, 0)),
            rx(1, P.encode_frame(P.T_COMMAND, b'\x01\x00' + b'\x00' * 20)),
            rx(2, P.encode_frame(0x77, b'')),
            tick(3)]),
        scenario('stream_rate_and_catch_up', [
            rx(0, P.Config(1, 200, 500, tuple(LIM))),
            tick(0), tick(4999), tick(5000), tick(10001), tick(50000), tick(54999),
            tick(55000)]),
        scenario('clock_wrap', [
            tick(4294960000), rx(4294967000, c(9, (100,) * 6)), tick(2000), tick(3000),
            tick(400000), tick(501001)]),
        scenario('truncated_command_flushed_when_idle', [
            rx(0, c(1, (100,) * 6).encode()[:12]), rx(5000, P.Vent(2)), tick(15000),
            tick(25001), tick(25002)]),
        scenario('measured_and_fault', [
            {'op': 'measured', 'ch': 0, 'pa': 12345, 'ok': True},
            {'op': 'measured', 'ch': 5, 'pa': -4000, 'ok': False},
            tick(0),
            {'op': 'measured', 'ch': 5, 'pa': 100, 'ok': True},
            tick(10000)]),
    ]


def main():
    data = {
        'comment': 'Golden vectors shared by the Python protocol/due_core tests and the C++ '
                   'bridge_core.h host test. Regenerate only for a reviewed wire-format '
                   'change: firmware/host_test/make_vectors.py.',
        'protocol_version': P.PROTOCOL_VERSION,
        'crc32': [{'hex': b'123456789'.hex(), 'crc': 0xCBF43926},
                  {'hex': '', 'crc': 0}],
        'frames': frames(),
        'streams': streams(),
        'cores': cores(),
    }
    OUT.write_text(json.dumps(data, indent=1) + '\n')
    print(f'wrote {OUT}')


if __name__ == '__main__':
    main()
