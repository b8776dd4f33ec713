"""Vision (no rclpy): capture sources, preprocessing, overlays."""
