"""The host link and the virtual Due, without ROS: clock mapping, handshake, faults."""

import os
import time

import numpy as np
import pytest
import serial

from softshape_ros.hardware import protocol as P
from softshape_ros.hardware.link import DeviceClock, DueLink, LinkDown
from softshape_ros.hardware.virtual_due import VirtualDue

LIM = [150000.0] * 6


def test_device_clock_takes_the_least_delayed_offset_and_unwraps():
    c = DeviceClock(window_ns=1_000_000_000)
    base = 10**18
    start = (1 << 32) - 5_000          # 5 ms before the Due's micros() wraps
    delays_ns = [3_000_000, 200_000, 5_000_000, 900_000]
    stamps = []
    for i, d in enumerate(delays_ns * 3):
        dev_us = (start + 10_000 * i) % (1 << 32)
        true_ns = base + 10_000_000 * i
        stamp, ext = c.map(dev_us, true_ns + d)
        assert ext == start + 10_000 * i              # unwrapped across the wrap
        assert stamp <= true_ns + d                   # never after arrival
        stamps.append(stamp - true_ns)
    # once the 200 us sample is seen, every stamp is within 200 us of the truth
    assert all(abs(e - 200_000) == 0 for e in stamps[1:])


def test_device_clock_restarts_after_a_firmware_reset():
    c = DeviceClock()
    c.map(5_000_000, 10**18)
    stamp, ext = c.map(1_000, 10**18 + 10_000_000)    # clock went back: the Due restarted
    assert ext == 1_000 and stamp == 10**18 + 10_000_000


def test_link_refuses_when_nothing_answers(tmp_path):
    master, slave = os.openpty()                     # a serial port with a silent device
    try:
        events = []
        link = DueLink(os.ttyname(slave), LIM, on_event=lambda lv, t: events.append(t),
                       backoff_s=(0.05, 0.1)).start()
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not any('no hello reply' in e for e in events):
            time.sleep(0.05)
        assert any('no hello reply' in e for e in events), events
        with pytest.raises(LinkDown, match='is down: no hello reply'):
            link.send_command([0] * 6)
        link.close()
    finally:
        os.close(master)
        os.close(slave)


def test_link_uses_the_lower_firmware_limits_and_measures_round_trips(tmp_path):
    with VirtualDue([100000, 150000, 150000, 150000, 150000, 50000], noise_pa=0) as vd:
        states = []
        link = DueLink(vd.path, LIM, on_state=states.append).start()
        assert link.wait_connected(5)
        assert link.limits_pa == [100000, 150000, 150000, 150000, 150000, 50000]
        for k in range(20):
            assert link.wait_ack(link.send_command([1000.0 * k] * 6), 1.0)
        seq = link.send_command([1e6] * 6)                # host clamps to the firmware limits
        assert link.wait_ack(seq, 1.0)
        assert vd.applied()[-1].setpoints_pa == (100000, 150000, 150000, 150000, 150000, 50000)
        st = link.status()
        assert st['acks'] == 21 and st['ack_rtt_p99_ms'] > 0
        time.sleep(0.2)
        assert states and all(np.all(s.pressures_pa <= 150000 + 1) for s in states)
        assert link.close()
        assert vd.applied()[-1].reason == 'vent'


def test_link_rejects_unchecked_values():
    link = DueLink('/nonexistent', LIM)
    with pytest.raises(ValueError, match='checked pressures'):
        link.send_command([float('nan')] * 6)
    with pytest.raises(ValueError, match='6 positive limits'):
        DueLink('/x', [1.0] * 5)


def test_virtual_due_faults_are_visible_on_the_wire(tmp_path):
    with VirtualDue(LIM, link=tmp_path / 'due', seed=3) as vd:
        ser = serial.Serial(vd.path, 115200, timeout=0.05)
        parser = P.FrameParser()

        def read_states(seconds):
            t_end, out = time.monotonic() + seconds, []
            while time.monotonic() < t_end:
                out += [f for f in parser.feed(ser.read(4096)) if f.type == P.T_STATE]
            return out

        assert len(read_states(0.3)) >= 15             # 100 Hz stream
        vd.corrupt_tx = 1.0                            # every write corrupted: nothing passes
        read_states(0.05)                              # what was already on its way
        bad0 = parser.bad_crc
        assert read_states(0.2) == [] and parser.bad_crc > bad0
        vd.corrupt_tx = 0.0
        vd.stall(0.4)
        read_states(0.05)
        assert read_states(0.2) == []                  # frozen firmware: silence
        time.sleep(0.3)
        assert read_states(0.2)
        vd.disconnect()
        assert not (tmp_path / 'due').exists()
        with pytest.raises(serial.SerialException):
            for _ in range(50):
                ser.read(100)
        ser.close()
        vd.reconnect(reset=True)
        ser = serial.Serial(vd.path, 115200, timeout=0.05)
        assert read_states(0.2)
        ser.close()


def test_virtual_due_command_line(tmp_path):
    import json
    import subprocess
    import sys

    link_path, log_path = tmp_path / 'ttyDUE', tmp_path / 'applied.jsonl'
    proc = subprocess.Popen([sys.executable, '-m', 'softshape_ros.cli', 'virtual-due',
                             '--link', str(link_path), '--log', str(log_path),
                             '--duration', '4'], stdout=subprocess.PIPE, text=True)
    try:
        assert 'virtual Due on' in proc.stdout.readline()
        link = DueLink(str(link_path), LIM).start()
        assert link.wait_connected(5)
        assert link.wait_ack(link.send_command([1234.0] * 6), 1.0)
        link.close()
        out, _ = proc.communicate(timeout=10)
        assert proc.returncode == 0 and 'set-point changes applied' in out
    finally:
        if proc.poll() is None:
            proc.kill()
    entries = [json.loads(x) for x in log_path.read_text().splitlines()]
    assert [1234] * 6 in [e['setpoints_pa'] for e in entries]
    assert entries[-1]['reason'] == 'vent'


def test_virtual_due_command_line_rejects_bad_probability():
    from softshape_ros.cli import main
    assert main(['virtual-due', '--drop-rx', '2']) == 2


def test_heartbeats_stop_when_the_host_stops_kicking():
    """A hung executor must not keep the firmware fed through the link thread's heartbeats."""
    with VirtualDue(LIM, noise_pa=0) as vd:
        link = DueLink(vd.path, LIM, fw_watchdog_s=0.3).start()
        assert link.wait_connected(5)
        link.kick()
        assert link.wait_ack(link.send_command([20000.0] * 6), 1.0)
        t_end = time.monotonic() + 1.0
        while time.monotonic() < t_end:        # a live host: kicks keep heartbeats going
            link.kick()
            time.sleep(0.05)
        assert vd.applied()[-1].reason == 'command'
        time.sleep(1.0)                        # the host stops kicking
        assert vd.applied()[-1].reason == 'watchdog'
        assert vd.applied()[-1].setpoints_pa == (0,) * 6
        link.close()


def test_feedback_fault_vents():
    with VirtualDue(LIM, noise_pa=0) as vd:
        events = []
        link = DueLink(vd.path, LIM, on_event=lambda lv, t: events.append(t)).start()
        assert link.wait_connected(5)
        assert link.wait_ack(link.send_command([30000.0] * 6), 1.0)
        vd.broken_sensors = {2}
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline and vd.applied()[-1].reason != 'vent':
            time.sleep(0.02)
        assert vd.applied()[-1].reason == 'vent'
        assert vd.applied()[-1].setpoints_pa == (0,) * 6
        assert any('feedback fault' in e for e in events)
        assert link.status()['fault_vents'] == 1
        link.close()
