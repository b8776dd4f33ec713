"""
Start softshape nodes as separate processes, the way ``ros2 run`` does, and stop them cleanly.

The demo and the benchmarks run the rig as real separate processes (as a user's launch file
would); there is no ``ros2`` CLI or launch_ros here, so this is the small part of them we need.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import yaml

PACKAGE = 'softshape_ros'


def find_executable(name: str) -> list[str]:
    """
    Return the command that runs node ``name``.

    Like ``ros2 run``: the ament index prefix of this package + ``lib/softshape_ros/<name>``.
    Without a colcon install on AMENT_PREFIX_PATH, fall back to the module's ``main`` run
    by this interpreter (same code, source tree).
    """
    try:
        from ament_index_python.packages import get_package_prefix
        exe = Path(get_package_prefix(PACKAGE)) / 'lib' / PACKAGE / name
        if exe.is_file() and os.access(exe, os.X_OK):
            return [str(exe)]
    except Exception:
        pass
    return [sys.executable, '-c', f'from {PACKAGE}.nodes.{name} import main; main()']


def ros_param(value) -> str:
    """Format a Python value for ``-p name:=value`` (YAML syntax)."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(ros_param(v) for v in value) + ']'
    if isinstance(value, str):
        # Quote what YAML would read as another type ('1', 'true', '') so it stays a string.
        return value if value and isinstance(yaml.safe_load(value), str) else f"'{value}'"
    return repr(value)


class NodeProcess:
    """One node in its own process; output goes to a log file; stop() sends SIGINT first."""

    def __init__(self, executable: str, params: dict | None = None, name: str | None = None,
                 log_dir: str | os.PathLike | None = None, env: dict | None = None):
        self.executable, self.name = executable, name or executable
        self.params = dict(params or {})
        self.log_path = Path(log_dir or '.') / f'{self.name}.log'
        self.env = env
        self.proc: subprocess.Popen | None = None

    def command(self) -> list[str]:
        cmd = find_executable(self.executable) + ['--ros-args']
        if self.name != self.executable:
            cmd += ['-r', f'__node:={self.name}']
        for k, v in self.params.items():
            cmd += ['-p', f'{k}:={ros_param(v)}']
        return cmd

    def start(self) -> 'NodeProcess':
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._log = open(self.log_path, 'w')
        env = dict(os.environ if self.env is None else self.env)
        env.setdefault('PYTHONUNBUFFERED', '1')
        self.proc = subprocess.Popen(self.command(), stdout=self._log, stderr=subprocess.STDOUT,
                                     env=env, start_new_session=True)
        return self

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def check_alive(self) -> None:
        if not self.alive():
            raise RuntimeError(f'{self.name} exited with code {self.proc.returncode}; '
                               f'see {self.log_path}:\n{self.tail()}')

    def tail(self, lines: int = 15) -> str:
        try:
            return ''.join(self.log_path.read_text().splitlines(True)[-lines:])
        except OSError:
            return ''

    def stop(self, timeout: float = 20.0) -> int:
        """SIGINT (the node vents/finalises), then SIGTERM, then SIGKILL; return the exit code."""
        if self.proc is None:
            return 0
        for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            if self.proc.poll() is not None:
                break
            try:
                self.proc.send_signal(sig)
            except ProcessLookupError:
                break
            try:
                self.proc.wait(wait)
            except subprocess.TimeoutExpired:
                continue
        self._log.close()
        return self.proc.returncode

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


def wait_until(predicate, timeout: float, period: float = 0.05, what: str = 'condition',
               processes: tuple = ()) -> None:
    """Poll ``predicate``; raise with ``what`` on timeout or if a watched process died."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        for p in processes:
            p.check_alive()
        time.sleep(period)
    raise TimeoutError(f'timed out after {timeout:.0f} s waiting for {what}')


def which_softshape() -> list[str]:
    """Return the command prefix that runs the ``softshape`` CLI with this interpreter."""
    exe = shutil.which('softshape')
    if exe and Path(exe).resolve().parent == Path(sys.executable).resolve().parent:
        return [exe]
    return [sys.executable, '-m', f'{PACKAGE}.cli']
