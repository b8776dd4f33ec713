"""Thin rclpy nodes: each module here with a ``main`` is ``ros2 run softshape_ros <name>``."""
