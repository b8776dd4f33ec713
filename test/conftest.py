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

from softshape_ros.transport import configure_transport  # noqa: E402

# The transport every node uses (the package's Fast DDS profile, unless the environment names
# another): set before rclpy starts, inherited by the nodes a test starts as processes.
TRANSPORT = configure_transport()

#: Deadlines for failure, not waits: a wait returns as soon as its condition holds. On a loaded
#: CI machine work takes longer than on a quiet one, so every deadline is stretched by this.
TIMEOUT_SCALE = float(os.environ.get('SOFTSHAPE_TEST_TIMEOUT_SCALE', '3'))


def _import_and_freeze() -> None:
    """
    Import what the ROS tests use, then take it out of the garbage collector's sight.

    This process hosts many nodes, torch and a virtual Due thread at once; a full collection
    over its ~400k import-time objects held the GIL for seconds on a busy machine and froze
    every thread (the stalls seen as "no state from the Due for 3 s"; docs/transport.md).
    The nodes do the same once built (``nodes.common.freeze_heap``).
    """
    import importlib
    import pkgutil

    import matplotlib.pyplot  # noqa: F401
    import torch  # noqa: F401

    import softshape_ros.nodes
    for m in pkgutil.iter_modules(softshape_ros.nodes.__path__):
        importlib.import_module(f'softshape_ros.nodes.{m.name}')
    import softshape_ros.model.train  # noqa: F401
    from softshape_ros.data.rosbag2_format import jazzy_typestore
    from softshape_ros.nodes.common import freeze_heap
    jazzy_typestore()
    freeze_heap()


#: Unfrozen objects over which a ROS test first freezes the heap again (what earlier tests
#: imported or built for the session, e.g. a trained model; a collection over ~20k objects
#: takes milliseconds).
REFREEZE_OBJECTS = 20_000


@pytest.fixture(scope='session')
def rclpy_session():
    """One rclpy context for the whole run (init once, shut down at the end)."""
    import rclpy
    _import_and_freeze()
    rclpy.init()
    yield rclpy
    rclpy.try_shutdown()


@pytest.fixture
def ros(rclpy_session):
    """
    Spin a single-threaded executor in a thread; add nodes with ``ros.add(node)``.

    Not rclpy's MultiThreadedExecutor: with a few 100 Hz streams it kept this process at 100 %
    of a core (its spin loop re-submits entities whose callbacks are still running), and the
    threads the nodes run beside it (the simulated cameras, the virtual Due) waited for the
    interpreter: mock_hardware's 20 Hz free run here skipped 40-105 of its slots, solve and
    render taking 0.8 ms of CPU and up to 640 ms of wall time. Single-threaded, the same test
    took 0.4 s of CPU in 1.4 s and skipped none. No node of the package needs a second
    executor thread: what blocks runs on the node's own worker thread.
    """
    import gc

    from rclpy.executors import SingleThreadedExecutor

    from softshape_ros.nodes.common import freeze_heap
    if len(gc.get_objects()) > REFREEZE_OBJECTS:
        freeze_heap()

    class Ros:
        def __init__(self):
            self.executor = SingleThreadedExecutor()
            self.nodes = []
            # Notified after every executor iteration: waits re-check their condition when
            # something may have changed (a callback ran, or the 50 ms spin slice ended).
            self.changed = threading.Condition()
            self._stop = threading.Event()
            self.thread = threading.Thread(target=self._spin, daemon=True)
            self.thread.start()

        def _spin(self):
            while not self._stop.is_set():
                self.executor.spin_once(timeout_sec=0.05)
                with self.changed:
                    self.changed.notify_all()

        def add(self, node):
            self.nodes.append(node)
            self.executor.add_node(node)
            return node

        def node(self, name):
            return self.add(rclpy_session.create_node(name))

        def until(self, predicate, timeout: float):
            """
            Return ``predicate()`` once true, or None after ``timeout`` (unscaled) seconds.

            Re-checked after every executor iteration; a timeout is an answer here, not a
            failure (for retrying something that may legitimately be lost).
            """
            deadline = time.monotonic() + timeout
            with self.changed:
                while True:
                    value = predicate()
                    if value:
                        return value
                    left = deadline - time.monotonic()
                    if left <= 0:
                        return None
                    self.changed.wait(min(left, 0.1))

        def wait_for(self, predicate, timeout: float = 10.0, what='condition'):
            """
            Return ``predicate()`` once true; fail the test with ``what`` past the deadline.

            ``what`` may be a callable, called at the deadline to say what was seen instead.
            """
            value = self.until(predicate, timeout * TIMEOUT_SCALE)
            if not value:
                pytest.fail(f'timed out after {timeout * TIMEOUT_SCALE:.1f} s '
                            f'waiting for {what() if callable(what) else what}')
            return value

        def close(self):
            self._stop.set()
            self.thread.join(timeout=5)
            # Callbacks still running in the executor's pool finish before their node goes.
            self.executor.shutdown(timeout_sec=5)
            for n in reversed(self.nodes):
                hook = getattr(n, 'on_shutdown', None)
                if hook:
                    hook()
                n.destroy_node()

    r = Ros()
    yield r
    r.close()


@pytest.fixture(scope='session')
def trained_checkpoint(tmp_path_factory):
    """Train a stereo gray ``ours`` model (briefly, for real) on simulated data."""
    from inference_fixtures import make_trained_checkpoint
    return make_trained_checkpoint(tmp_path_factory.mktemp('trained'))
