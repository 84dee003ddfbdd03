"""Pure logic of the simulated rig: the phantom's physics and the true plant (no rclpy)."""
