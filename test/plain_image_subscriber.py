"""
A plain best-effort image subscriber in a process of its own (test_transport).

What a lab's viewer is: rclpy, a single-threaded spin, the sensor-data QoS, and Fast DDS's own
defaults (no profile of this package). It also subscribes to the camera's capture_time
(reliable, small) to know which frames were captured, and stops once it has received ``count``
captured frames in a row from the first image it got (before that, discovery may not have
matched the image writer with this reader yet) or at ``timeout_s``. It prints one JSON line:
``{"captured": n, "received": n, "window": [...], "missing": [...]}`` (stamps in ns).

Usage: ``python plain_image_subscriber.py IMAGE_TOPIC TIME_TOPIC COUNT TIMEOUT_S``
"""

import json
import sys
import time

import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import Image, TimeReference


def stamp_ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def main(argv) -> int:
    image_topic, time_topic, count, timeout_s = argv[0], argv[1], int(argv[2]), float(argv[3])
    rclpy.init()
    node = rclpy.create_node('plain_image_subscriber')
    received, captured = set(), []
    node.create_subscription(Image, image_topic, lambda m: received.add(stamp_ns(m.header.stamp)),
                             qos_profile_sensor_data)
    node.create_subscription(TimeReference, time_topic,
                             lambda m: captured.append(stamp_ns(m.header.stamp)),
                             QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))

    def window():
        return [s for s in captured if received and s >= min(received)][:count]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not (len(window()) == count
                                               and set(window()) <= received):
        rclpy.spin_once(node, timeout_sec=0.1)
    stamps = window()
    print(json.dumps({'captured': len(captured), 'received': len(received), 'window': stamps,
                      'missing': sorted(set(stamps) - received)}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
