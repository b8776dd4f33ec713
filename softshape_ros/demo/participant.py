"""The demo's ROS participants share this: one rclpy node spun in a background thread."""

from __future__ import annotations

import threading


class Participant:
    """
    Context manager: ``connect(node)`` creates the publishers and subscriptions, then spin.

    Owns the rclpy context only if none was running when it entered (a test's stays).
    """

    node_name = 'softshape_demo'

    def connect(self, node) -> None:
        """Create this participant's publishers and subscriptions on ``node``."""
        raise NotImplementedError

    def __enter__(self):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        self._owns_context = not rclpy.ok()
        if self._owns_context:
            rclpy.init()
        self.node = rclpy.create_node(self.node_name)
        self.connect(self.node)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self._stop = False
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()
        return self

    def _spin(self) -> None:
        while not self._stop:
            self.executor.spin_once(timeout_sec=0.05)

    def __exit__(self, *exc):
        import rclpy
        self._stop = True
        self.thread.join(timeout=5)
        self.executor.remove_node(self.node)
        self.node.destroy_node()
        if self._owns_context:
            rclpy.try_shutdown()
