"""Exceptions and warnings of the learning package (no torch import here).

:class:`PolicyLoadError` is the planner's (:mod:`cgail_planner.core.errors`, where the ONNX
policy is loaded); the learning code raises the same class for checkpoints."""

from cgail_planner.core.errors import PolicyLoadError

__all__ = ['ConfigError', 'DemoAnatomyWarning', 'DemoError', 'LearningError', 'PolicyLoadError']


class LearningError(Exception):
    """Base class of every error raised by ``cgail_learning``."""


class ConfigError(LearningError, ValueError):
    """A training configuration key or value is invalid."""


class DemoError(LearningError, ValueError):
    """Demonstrations are missing, empty or do not match the environment."""




class DemoAnatomyWarning(UserWarning):
    """Demonstrations were recorded in an anatomy whose content hash differs from the current
    one (another CPU's numpy or another commit built the mesh); they still re-simulate within
    the pose tolerance."""
