"""
A virtual Arduino Due on a pseudo-terminal: the firmware logic, six lagging regulators, faults.

It runs :class:`~softshape_ros.hardware.due_core.DueCore` (the Python twin of the C++ core,
both checked against the same golden vectors) behind a real pty, so the host code under
test opens a real serial device. Every set-point the "hardware" applies is logged, which
is what the tests use to prove that only commanded values within limits ever reached it.

Faults: dropped and corrupted bytes in either direction, injected garbage, a stall (the
main loop freezes, as a hung firmware would), a disconnect (the pty disappears, like a USB
cable pulled) and a reconnect (a fresh pty behind the same symlink, like udev's
``/dev/serial/by-id`` names).
"""

from __future__ import annotations

import errno
import os
import random
import select
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path

from softshape_ros.hardware.due_core import DueCore
from softshape_ros.pressure import FirstOrderRegulator


@dataclass(frozen=True)
class Applied:
    """One change of the regulator set-points, as the firmware made it."""

    t: float                 # time.monotonic() when applied
    setpoints_pa: tuple
    reason: str              # command | vent | watchdog | config
    seq: int


class VirtualDue:
    """Emulate the Due firmware on a pty; ``path`` is what the host opens."""

    def __init__(self, fw_limits_pa=None, link: str | os.PathLike | None = None,
                 tau_s: float = 0.03, noise_pa: float = 30.0, seed: int = 0,
                 period_s: float = 0.002):
        if fw_limits_pa is None:
            from softshape_ros.config import load_rig_config
            fw_limits_pa = load_rig_config().max_pressures_pa
        self.fw_limits = [int(x) for x in fw_limits_pa]
        self.link = Path(link) if link is not None else None
        self.tau_s, self.noise_pa, self.period_s = float(tau_s), float(noise_pa), period_s
        self.rng = random.Random(seed)
        # fault knobs (probabilities per byte / per frame), settable at any time
        self.drop_rx = 0.0
        self.drop_tx = 0.0
        self.corrupt_rx = 0.0
        self.corrupt_tx = 0.0
        self.broken_sensors: set[int] = set()   # channels whose feedback reads out of range
        self.log: list[Applied] = []
        self.stats = {'rx_bytes': 0, 'tx_bytes': 0, 'rx_dropped': 0, 'tx_dropped': 0,
                      'rx_corrupted': 0, 'tx_corrupted': 0, 'tx_overflow': 0, 'connects': 0}
        self._lock = threading.RLock()
        self._applied = threading.Condition(self._lock)     # notified at every log entry
        self._garbage = bytearray()
        self._stall_until = 0.0
        self._master = self._slave = None
        self._pty_generation = 0        # changes whenever the pty is opened or closed
        self._slave_name = ''
        self._running = False
        self._thread = None
        self._clock_offset = self.rng.randrange(1 << 32)
        self.core = self._new_core()
        self.regulator = FirstOrderRegulator(self.tau_s)

    # ------------------------------------------------------------------ lifecycle
    def _new_core(self) -> DueCore:
        core = DueCore(self.fw_limits, on_apply=self._on_apply)
        # the real firmware boots with micros() = 0 = its first state deadline; ours boots
        # at a random clock value (to exercise wrap-around), so start the schedule there
        core.next_state = core.last_byte = self.now_us()
        return core

    def _on_apply(self, setpoints, reason, seq) -> None:
        with self._lock:
            self.log.append(Applied(time.monotonic(), tuple(setpoints), reason, seq))
            self._applied.notify_all()

    def start(self) -> 'VirtualDue':
        self._open_pty()
        self._running = True
        self._thread = threading.Thread(target=self._run, name='virtual_due', daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=5)
        self._close_pty()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    @property
    def path(self) -> str:
        """Return the device the host should open: the stable symlink if any, else the pty."""
        return str(self.link) if self.link is not None else self._slave_name

    @property
    def connected(self) -> bool:
        return self._master is not None

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)            # no echo, no line discipline: a UART, not a terminal
        os.set_blocking(master, False)
        name = os.ttyname(slave)
        if self.link is not None:
            tmp = self.link.with_name(self.link.name + '.tmp')
            if tmp.is_symlink() or tmp.exists():
                tmp.unlink()
            tmp.symlink_to(name)
            os.replace(tmp, self.link)
        self._master, self._slave, self._slave_name = master, slave, name
        self._pty_generation += 1
        self.stats['connects'] += 1

    def _close_pty(self) -> None:
        if self.link is not None and self.link.is_symlink():
            self.link.unlink()
        for fd in (self._master, self._slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = None
        self._pty_generation += 1

    # ------------------------------------------------------------------ faults
    def stall(self, seconds: float) -> None:
        """Freeze the main loop (no reading, no watchdog, no state) for ``seconds``."""
        self._stall_until = time.monotonic() + seconds

    def disconnect(self) -> None:
        """Pull the cable: the pty closes and the symlink disappears."""
        with self._lock:
            self._close_pty()

    def reconnect(self, reset: bool = False) -> None:
        """Plug back in on a new pty; ``reset`` also restarts the firmware (vented)."""
        with self._lock:
            if self._master is None:
                if reset:
                    self._clock_offset = self.rng.randrange(1 << 32)
                    self.core = self._new_core()
                self._open_pty()

    def inject(self, data: bytes) -> None:
        """Send raw bytes (garbage) to the host as if from the firmware."""
        with self._lock:
            self._garbage += data

    # ------------------------------------------------------------------ queries
    def applied(self) -> list[Applied]:
        with self._lock:
            return list(self.log)

    def wait_applied(self, predicate, timeout: float) -> bool:
        """Wait until ``predicate(applied log)`` holds; False if ``timeout`` s pass first."""
        with self._applied:
            return bool(self._applied.wait_for(lambda: predicate(list(self.log)), timeout))

    def now_us(self) -> int:
        return (time.monotonic_ns() // 1000 + self._clock_offset) & 0xFFFFFFFF

    # ------------------------------------------------------------------ main loop
    def _mangle(self, data: bytes, drop: float, corrupt: float, kind: str) -> bytes:
        if not data or (drop <= 0 and corrupt <= 0):
            return data
        out = bytearray()
        for b in data:
            if drop > 0 and self.rng.random() < drop:
                self.stats[f'{kind}_dropped'] += 1
                continue
            out.append(b)
        if corrupt > 0 and out and self.rng.random() < corrupt:
            i = self.rng.randrange(len(out))
            out[i] ^= 1 << self.rng.randrange(8)
            self.stats[f'{kind}_corrupted'] += 1
        return bytes(out)

    def _run(self) -> None:
        last = time.monotonic()
        while self._running:
            if time.monotonic() < self._stall_until:
                time.sleep(0.002)
                continue
            master, generation = self._master, self._pty_generation
            if master is None:
                time.sleep(0.005)
                last = time.monotonic()
                continue
            try:
                ready, _, _ = select.select([master], [], [], self.period_s)
            except (OSError, ValueError) as exc:
                if self._pty_generation != generation:  # closed under us by disconnect()
                    continue
                # Nobody here closed it: another part of the process closed this fd number
                # (a double close). Say so instead of going silently deaf.
                raise RuntimeError(f'virtual Due: its pty master (fd {master}) was closed '
                                   f'by someone else: {exc}') from exc
            data = b''
            if ready:
                try:
                    data = os.read(master, 4096)
                except BlockingIOError:
                    data = b''
                except OSError:
                    # EIO: no process has the slave open (host closed it); keep going
                    data = b''
            with self._lock:
                if self._master is None:
                    continue
                now = time.monotonic()
                core = self.core
                # the air moves up to now under the old set-points, then new bytes may
                # change them: a command never acts before it arrived
                p = self.regulator.step(now - last)
                last = now
                for i, v in enumerate(p):
                    noisy = v + self.rng.gauss(0.0, self.noise_pa) if self.noise_pa else v
                    core.set_measured(i, int(round(noisy)), i not in self.broken_sensors)
                if data:
                    self.stats['rx_bytes'] += len(data)
                    data = self._mangle(data, self.drop_rx, self.corrupt_rx, 'rx')
                    core.receive(data, self.now_us())
                self.regulator.setpoint[:] = core.setpoints
                core.tick(self.now_us())
                out = core.take_tx()
                out = self._mangle(out, self.drop_tx, self.corrupt_tx, 'tx')
                if self._garbage:
                    out = bytes(self._garbage) + out
                    self._garbage.clear()
                if out:
                    self._write(out)

    def _write(self, out: bytes) -> None:
        try:
            n = os.write(self._master, out)
            self.stats['tx_bytes'] += n
            if n < len(out):
                self.stats['tx_overflow'] += len(out) - n
        except BlockingIOError:
            self.stats['tx_overflow'] += len(out)   # host not reading: bytes are lost
        except OSError as exc:
            if exc.errno not in (errno.EIO, errno.EBADF):
                raise
