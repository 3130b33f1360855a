"""Refusals of the execution pipeline. Every refusal is a `PlanningError` whose message names the problem
(which step or time, joint or link, value and limit); nothing of a refused trajectory may be sent to an arm."""
from __future__ import annotations


class PlanningError(ValueError):
    """A trajectory the pipeline will not execute. `kind` is a short machine-readable reason."""

    kind = "planning"

    def __init__(self, message: str, **details):
        super().__init__(message)
        self.details = details


class InvalidInputError(PlanningError):
    """Malformed input: NaN or infinite values, a frame the robot does not know, an unknown task mounting."""

    kind = "invalid_input"


class UnreachableError(PlanningError):
    """Inverse kinematics cannot reach a pose (outside the workspace, or past a joint limit)."""

    kind = "unreachable"


class LimitError(PlanningError):
    """The trajectory cannot be executed within the arm's limits (with the margin), even after time scaling."""

    kind = "limits"


class CollisionError(PlanningError):
    """An arm link would come closer than the clearance to the table, the task's container or another link."""

    kind = "collision"


class PathError(PlanningError):
    """The executable motion leaves the planned tool path by more than the tolerance."""

    kind = "path"
