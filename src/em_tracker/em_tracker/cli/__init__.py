"""Command-line tools of ``em_tracker`` (calibration): file I/O around ``em_tracker.core``."""
