"""Test-wide ROS set-up: DDS stays on localhost, one domain per run, an in-process executor."""

import os
import threading
import time

# Before anything can import rclpy: discovery must not leave this machine, and parallel
# runs must not see each other. The Makefile sets a per-run domain; a bare pytest picks one.
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('ROS_DOMAIN_ID', str(os.getpid() % 100 + 101))
os.environ.setdefault('PYTHONUNBUFFERED', '1')

import pytest  # noqa: E402


#: Waits return as soon as their condition holds; on a loaded CI machine they may take longer
#: than on a quiet one, so every timeout is stretched by this factor (failures take longer).
TIMEOUT_SCALE = float(os.environ.get('SOFTSHAPE_TEST_TIMEOUT_SCALE', '3'))


def wait_for(predicate, timeout: float = 10.0, period: float = 0.01, what: str = 'condition'):
    """Poll ``predicate`` until true; fail the test with ``what`` on timeout."""
    timeout *= TIMEOUT_SCALE
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(period)
    pytest.fail(f'timed out after {timeout:.1f} s waiting for {what}')


@pytest.fixture(scope='session')
def rclpy_session():
    """One rclpy context for the whole run (init once, shut down at the end)."""
    import rclpy
    rclpy.init()
    yield rclpy
    rclpy.try_shutdown()


@pytest.fixture
def ros(rclpy_session):
    """Spin a multithreaded executor in a thread; add nodes with ``ros.add(node)``."""
    from rclpy.executors import MultiThreadedExecutor

    class Ros:
        def __init__(self):
            self.executor = MultiThreadedExecutor(num_threads=4)
            self.nodes = []
            self.thread = threading.Thread(target=self._spin, daemon=True)
            self._stop = False
            self.thread.start()

        def _spin(self):
            while not self._stop:
                self.executor.spin_once(timeout_sec=0.05)

        def add(self, node):
            self.nodes.append(node)
            self.executor.add_node(node)
            return node

        def node(self, name):
            return self.add(rclpy_session.create_node(name))

        wait_for = staticmethod(wait_for)

        def close(self):
            self._stop = True
            self.thread.join(timeout=5)
            for n in reversed(self.nodes):
                hook = getattr(n, 'on_shutdown', None)
                if hook:
                    hook()
                self.executor.remove_node(n)
                n.destroy_node()
            self.executor.shutdown()

    r = Ros()
    yield r
    r.close()


@pytest.fixture(scope='session')
def trained_checkpoint(tmp_path_factory):
    """Train a stereo gray ``ours`` model (briefly, for real) on simulated data."""
    from inference_fixtures import make_trained_checkpoint
    return make_trained_checkpoint(tmp_path_factory.mktemp('trained'))
