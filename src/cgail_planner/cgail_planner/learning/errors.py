"""Exceptions and warnings of the learning package (no torch import here)."""


class LearningError(Exception):
    """Base class of every error raised by ``cgail_planner.learning``."""


class ConfigError(LearningError, ValueError):
    """A training configuration key or value is invalid."""


class DemoError(LearningError, ValueError):
    """Demonstrations are missing, empty or do not match the environment."""


class PolicyLoadError(LearningError, ValueError):
    """A checkpoint or ONNX model is missing, corrupt or does not fit the observation size."""


class DemoAnatomyWarning(UserWarning):
    """Demonstrations were recorded in an anatomy whose content hash differs from the current
    one (another CPU's numpy or another commit built the mesh); they still re-simulate within
    the pose tolerance."""
