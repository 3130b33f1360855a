"""What optimisers report while they run, and what they return."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Progress:
    """One iteration: the loss of this iteration's parameters (task loss, without DP's attraction term; DP
    reports the loss over its current region, `region` steps), the best loss over the whole horizon so far
    (inf before the first whole-horizon iteration), simulated steps used out of the budget, seconds."""

    method: str
    iteration: int
    loss: float
    best_loss: float
    steps: int
    budget: int
    elapsed: float
    region: int
    best_theta: object = None  # the parameters behind best_loss (for a caller that evaluates them elsewhere)
    parametrisation: object = None  # what turns them into actions: .actions(θ), .tool_position(θ)
    state: object = None  # where the method can resume (DP, DP-H): a callable returning its state after this iteration

    def line(self) -> str:
        best = "-" if not np.isfinite(self.best_loss) else f"{self.best_loss:.5g}"
        return (f"{self.method} it {self.iteration:4d}  loss {self.loss:.5g}  best {best}  steps "
                f"{self.steps}/{self.budget}  {self.elapsed:.1f} s")


@dataclass
class Result:
    """An optimiser's outcome: its parametrisation, best parameters, loss history (one entry per whole-horizon
    evaluation), simulated steps, iterations, seconds and settings."""

    parametrisation: object
    theta: np.ndarray
    history: list
    steps: int
    iterations: int
    seconds: float
    settings: dict = field(default_factory=dict)
