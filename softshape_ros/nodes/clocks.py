"""
Which clock for what: steady time for timeouts and watchdogs, ROS time for every stamp.

With ``use_sim_time`` the node clock follows ``/clock``; a watchdog on it would stop with
the simulation (or never start), so watchdogs and retry loops run on a steady timer.
Stamps, on the other hand, must all be ROS time, or a sim-time trigger compared with a
wall-clock capture looks hours late. Device capture times are wall-clock instants; they
are moved onto ROS time by the age they had when read.
"""

from __future__ import annotations

import time

from rclpy.clock import Clock, ClockType
from rclpy.node import Node

__all__ = ['steady_timer', 'ros_now_ns', 'wall_to_ros_ns']

_STEADY = Clock(clock_type=ClockType.STEADY_TIME)


def steady_timer(node: Node, period_s: float, callback, callback_group=None):
    """Create a timer on the steady clock (runs whatever ``use_sim_time`` says)."""
    return node.create_timer(period_s, callback, callback_group=callback_group, clock=_STEADY)


def ros_now_ns(node: Node) -> int:
    """Return the node's ROS time (sim time under ``use_sim_time``) in nanoseconds."""
    return node.get_clock().now().nanoseconds


def wall_to_ros_ns(node: Node, wall_ns: int) -> int:
    """
    Map a wall-clock instant (``time.time_ns()``) onto the node's ROS time.

    Without sim time the two are the same clock and the instant is returned unchanged;
    with it, the instant keeps its age relative to now.
    """
    clock = node.get_clock()
    if not clock.ros_time_is_active:
        return int(wall_ns)
    return clock.now().nanoseconds - (time.time_ns() - int(wall_ns))
