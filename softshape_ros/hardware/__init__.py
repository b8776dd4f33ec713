"""Hardware (no rclpy): pressure command safety, serial protocol, link, virtual Due."""
