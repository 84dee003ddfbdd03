"""theta_max curriculum: lessons that lower the maximum bending angle as the agent improves."""

from __future__ import annotations

from collections import deque
import math

from cgail_learning.config import CurriculumConfig


class Curriculum:
    """Tracks completed episodes and moves to the next lesson when its measure passes.

    The measure (mean episode extrinsic reward, or success rate) is taken over the last
    ``min_lesson_length`` episodes of the current lesson, and only once that many episodes have
    been completed in it (ML-Agents ``min_lesson_length`` + ``threshold``).
    """

    def __init__(self, cfg: CurriculumConfig) -> None:
        self.cfg = cfg
        self.lesson = 0
        self._window: deque[float] = deque(maxlen=cfg.min_lesson_length)

    @property
    def enabled(self) -> bool:
        """Whether any lesson is configured."""
        return len(self.cfg.theta_max_deg) > 0

    @property
    def theta_max(self) -> float | None:
        """theta_max of the current lesson in rad (None when disabled)."""
        if not self.enabled:
            return None
        return math.radians(self.cfg.theta_max_deg[self.lesson])

    def measure(self) -> float:
        """Mean of the window (nan when empty)."""
        return sum(self._window) / len(self._window) if self._window else math.nan

    def record(self, episode_reward: float, success: bool) -> bool:
        """Record one finished episode; return True when the lesson changed."""
        if not self.enabled or self.lesson >= len(self.cfg.theta_max_deg) - 1:
            return False
        self._window.append(float(success) if self.cfg.measure == 'success'
                            else float(episode_reward))
        if (len(self._window) >= self.cfg.min_lesson_length
                and self.measure() >= self.cfg.thresholds[self.lesson]):
            self.lesson += 1
            self._window.clear()
            return True
        return False
