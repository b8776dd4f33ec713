"""Hardware (no rclpy): serial protocol, Due link, virtual Due (checks: softshape_ros.pressure)."""
