"""The host link and the virtual Due, without ROS: clock mapping, handshake, faults."""

import os
import threading
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
        events, refused = [], threading.Event()

        def on_event(level, text):
            events.append(text)
            if 'no hello reply' in text:
                refused.set()
        link = DueLink(os.ttyname(slave), LIM, on_event=on_event, backoff_s=(0.05, 0.1)).start()
        assert refused.wait(10), events
        with pytest.raises(LinkDown, match='is down: no hello reply'):
            link.send_command([0] * 6)
        link.close()
    finally:
        os.close(master)
        os.close(slave)


def test_link_uses_the_lower_firmware_limits_and_measures_round_trips(tmp_path):
    with VirtualDue([100000, 150000, 150000, 150000, 150000, 50000], noise_pa=0) as vd:
        states, new_state = [], threading.Condition()

        def on_state(m):
            with new_state:
                states.append(m)
                new_state.notify_all()
        link = DueLink(vd.path, LIM, on_state=on_state).start()
        assert link.wait_connected(5)
        assert link.limits_pa == [100000, 150000, 150000, 150000, 150000, 50000]
        for k in range(20):
            assert link.wait_ack(link.send_command([1000.0 * k] * 6), 1.0)
        seq = link.send_command([1e6] * 6)                # host clamps to the firmware limits
        assert link.wait_ack(seq, 1.0)
        assert vd.applied()[-1].setpoints_pa == (100000, 150000, 150000, 150000, 150000, 50000)
        st = link.status()
        assert st['acks'] == 21 and st['ack_rtt_p99_ms'] > 0
        with new_state:          # ten more states, measured under the clamped set-point
            n = len(states)
            assert new_state.wait_for(lambda: len(states) >= n + 10, 10), len(states)
        assert all(np.all(s.pressures_pa <= 150000 + 1) for s in states)
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

        def read_until(done, timeout=10.0):
            """Read states until ``done(states)``; each comes with the bad CRCs seen before it."""
            deadline, out = time.monotonic() + timeout, []
            while not done(out):
                assert time.monotonic() < deadline, (len(out), parser.bad_crc)
                out += [(P.decode(f), parser.bad_crc) for f in parser.iter_feed(ser.read(4096))
                        if f.type == P.T_STATE]
            return out

        def later(t_us, than_us):                      # on the Due's wrapping 32-bit clock
            return 0 <= (t_us - than_us) & 0xFFFFFFFF < 1 << 31

        clean = read_until(lambda s: len(s) >= 15)     # the state stream, in Due-time order
        assert all(later(b.t_us, a.t_us) and b.t_us != a.t_us
                   for (a, _), (b, _) in zip(clean, clean[1:]))
        assert parser.bad_crc == 0                     # a clean line
        vd.corrupt_tx = 1.0                            # every write corrupted: nothing passes
        bad0 = parser.bad_crc
        got = read_until(lambda s: parser.bad_crc >= bad0 + 10)
        assert all(bad == bad0 for _, bad in got)      # only what was on its way before it
        vd.corrupt_tx = 0.0
        read_until(lambda s: s)                        # good states again
        start_us = vd.now_us()
        vd.stall(0.4)                                  # frozen firmware: silence
        end_us = (start_us + 400_000) & 0xFFFFFFFF
        got = read_until(lambda s: s and later(s[-1][0].t_us, end_us))     # and it resumes
        during = [st for st, _ in got if later(st.t_us, start_us) and not later(st.t_us, end_us)]
        assert len(during) <= 1                        # the loop pass already under way
        vd.disconnect()
        assert not (tmp_path / 'due').exists()
        with pytest.raises(serial.SerialException):
            for _ in range(50):
                ser.read(100)
        ser.close()
        vd.reconnect(reset=True)
        ser = serial.Serial(vd.path, 115200, timeout=0.05)
        assert read_until(lambda s: s)
        ser.close()


def test_virtual_due_command_line(tmp_path):
    import json
    import signal
    import subprocess
    import sys

    link_path, log_path = tmp_path / 'ttyDUE', tmp_path / 'applied.jsonl'
    proc = subprocess.Popen([sys.executable, '-m', 'softshape_ros.cli', 'virtual-due',
                             '--link', str(link_path), '--log', str(log_path),
                             '--duration', '0'], stdout=subprocess.PIPE, text=True)

    def logged():
        text = log_path.read_text() if log_path.exists() else ''
        return [json.loads(x) for x in text.splitlines()]
    try:
        assert 'virtual Due on' in proc.stdout.readline()
        link = DueLink(str(link_path), LIM).start()
        assert link.wait_connected(5)
        assert link.wait_ack(link.send_command([1234.0] * 6), 1.0)
        link.close()
        # The host gone, the Due vents; the log shows it while the emulator still runs.
        t_end = time.monotonic() + 10
        while not ((entries := logged()) and entries[-1]['reason'] == 'vent'):
            assert time.monotonic() < t_end and proc.poll() is None, entries
            time.sleep(0.05)                   # polling the log file for the vent
        proc.send_signal(signal.SIGINT)        # runs until stopped (--duration 0)
        out, _ = proc.communicate(timeout=10)
        assert proc.returncode == 0 and 'set-point changes applied' in out
    finally:
        if proc.poll() is None:
            proc.kill()
    entries = logged()
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
            time.sleep(0.05)                   # pacing: an executor's 20 Hz kicks
        assert vd.applied()[-1].reason == 'command'
        # the host stops kicking: the next change at the Due is the firmware's watchdog vent
        assert vd.wait_applied(lambda log: log[-1].reason != 'command', 10)
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
        assert vd.wait_applied(lambda log: log[-1].reason != 'command', 10)
        assert vd.applied()[-1].reason == 'vent'
        assert vd.applied()[-1].setpoints_pa == (0,) * 6
        assert any('feedback fault' in e for e in events)
        assert link.status()['fault_vents'] == 1
        link.close()
