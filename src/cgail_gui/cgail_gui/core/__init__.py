"""Pure logic of the guidance displays: the phantom -> CT frame of the Slicer bridge (no rclpy)."""
