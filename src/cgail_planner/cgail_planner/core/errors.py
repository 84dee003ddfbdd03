"""The exception tree of the planner core and of the nodes that wrap it.

Every error is a ``ValueError`` whose message reads "expected ..., found ...":

* :class:`PlannerError` - planning refused or failed;
  * :class:`InvalidInputError` - a pose, goal or message value is unusable;
  * :class:`NoPathError` - the planner ran but found no path (carries the rolled-out points);
  * :class:`ContractError` - a setting disagrees with the policy's contract
    (:class:`cgail_sim.ftl_model.PolicyContract`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


class PlannerError(ValueError):
    """Planning refused or failed; the message says what was wrong and what was expected."""


class InvalidInputError(PlannerError):
    """A pose or goal is unusable (NaN/inf, not a rotation, goal outside the lumen)."""


class NoPathError(PlannerError):
    """The planner ran but found no path to the goal (rollout collided, exited or timed out).

    Args:
        message: what happened.
        points: (K, 3) the tip positions rolled out before the failure, m (None when the
            failure is not a rollout's); kept as :attr:`points` for diagnostics.
        reason: how a rollout ended: ``collided``, ``left`` (an exit disc or bounding box),
            ``limit`` (step limit) or ``bad_action``; for the RRT the limit that ran out,
            ``max_iterations`` or ``time_limit``; None otherwise.
        step: the step it ended at (the RRT: the iterations it used; None otherwise).
    """

    def __init__(self, message: str, points: NDArray[np.float64] | None = None,
                 reason: str | None = None, step: int | None = None) -> None:
        super().__init__(message)
        self.points = points
        self.reason = reason
        self.step = step


class ContractError(PlannerError):
    """A planner setting (e.g. a ROS parameter) disagrees with the policy's contract."""


class PolicyLoadError(ValueError):
    """A checkpoint or ONNX policy is missing, corrupt or does not fit the observation size.

    The planner's (it loads the ONNX policy); ``cgail_learning`` raises it for checkpoints too.
    Not a :class:`PlannerError`: it is raised while a policy is loaded, never by a plan."""
