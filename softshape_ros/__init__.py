"""
softshape_ros: drive, film, record, learn and predict a soft continuum robot over ROS 2.

The core (sim, hardware, vision, data, model) is plain Python; ``nodes`` adapts it to rclpy.
"""

__version__ = '0.1.0'
