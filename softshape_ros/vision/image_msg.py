"""
sensor_msgs/Image <-> numpy without cv_bridge or rclpy.

Works on any object with the message's fields, so live rclpy messages (nodes) and
messages deserialised from bags by rosbags (dataset builder) decode the same way.
"""

from __future__ import annotations

import numpy as np

#: Supported encodings and their channel counts.
ENCODINGS = {'mono8': 1, 'rgb8': 3, 'bgr8': 3}


def stamp_ns(stamp) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def decode_image(msg) -> np.ndarray:
    """Decode to H x W (mono8) or H x W x 3 RGB uint8 (a view); ValueError if malformed."""
    ch = ENCODINGS.get(msg.encoding)
    if ch is None:
        raise ValueError(f'unsupported image encoding {msg.encoding!r} (use mono8/rgb8/bgr8)')
    row = msg.width * ch
    data = np.frombuffer(msg.data, dtype=np.uint8)
    if msg.height == 0 or msg.step < row or data.size < msg.step * msg.height:
        raise ValueError(f'image {msg.width}x{msg.height} {msg.encoding}: step {msg.step} and '
                         f'{data.size} data bytes do not match')
    a = data[: msg.step * msg.height].reshape(msg.height, msg.step)[:, :row]
    if ch == 1:
        return a
    a = a.reshape(msg.height, msg.width, 3)
    return a[:, :, ::-1] if msg.encoding == 'bgr8' else a
