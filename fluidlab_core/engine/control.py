"""What drives a step: the Control (in the manner of NVIDIA Warp's `warp.sim.Control`).

Today a step is driven by the tools' twists: for each tool, (vx, vy, vz, wx, wy, wz) in m/s and rad/s in the
world frame, held over the step's substeps. A Control is that (n_tools, 6) array, already masked by each
tool's action mask and clipped to its workspace (tools.plan does both for a sequence); a rollout takes a
sequence of them as an (N, n_tools, 6) array. The emitters (emitters.py) run or not per step: emit_on.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Control:
    """The tools' twists for one step, (n_tools, 6), float64, m/s and rad/s in the world frame, and which
    emitters run during it (emit_on (n_emitters,) bools; None: all of them)."""

    twists: np.ndarray
    emit_on: np.ndarray | None = None

    def __post_init__(self):
        tw = np.asarray(self.twists, dtype=np.float64)
        if tw.ndim != 2 or tw.shape[1] != 6:
            raise ValueError(f"a Control holds (n_tools, 6) twists, got shape {tw.shape}")
        if not np.all(np.isfinite(tw)):
            raise ValueError("a Control's twists contain NaN or infinity")
        object.__setattr__(self, "twists", tw)
        if self.emit_on is not None:
            object.__setattr__(self, "emit_on", np.asarray(self.emit_on, dtype=bool).reshape(-1))

    def emitting(self, n_emitters: int) -> np.ndarray:
        """(n_emitters,) bools: which emitters run during the step."""
        if self.emit_on is None:
            return np.ones(n_emitters, dtype=bool)
        if self.emit_on.shape != (n_emitters,):
            raise ValueError(f"a Control switches {self.emit_on.shape[0]} emitters, the scene has {n_emitters}")
        return self.emit_on

    @classmethod
    def still(cls, n_tools: int) -> "Control":
        """Tools at rest."""
        return cls(np.zeros((n_tools, 6)))
