"""Task losses (FluidLab appendix), as `fluidlab_core.losses.Loss` terms with analytic gradients, in SI units.

Chamfer distance between the particles x_i (i = 1…N) of a body and goal points g_j (j = 1…M), squared
distances so that the loss is smooth away from ties (m²):
    C(x, g) = (1/N) Σ_i min_j |x_i − g_j|² + (1/M) Σ_j min_i |x_i − g_j|²
    ∂C/∂x_i = (2/N)(x_i − g_nn(i)) + (2/M) Σ_{j: nn'(j) = i} (x_i − g_j)
(nn: nearest goal point of a particle, nn': nearest particle of a goal point; the gradient of a min is that
of its arg-min, which holds almost everywhere).

Spread of a body about its centroid x̄ (m²), negated so that a larger spread is a lower loss:
    S(x) = −(1/N) Σ_i |x_i − x̄|²,   ∂S/∂x_i = −(2/N)(x_i − x̄)      (Σ_i (x_i − x̄) = 0 removes the x̄ term)

Attraction of the tool origin p towards the centroid of a body, in the horizontal plane (m²); the particles
get no gradient from it (it steers the tool, not the fluid):
    A = |P (p − x̄)|²,  ∂A/∂p = 2 P (p − x̄),  P = diag(1, 1, 0)
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from fluidlab_core.losses import Loss


class ChamferToGoal(Loss):
    """Σ over goal steps of the Chamfer distance between body particles and the goal points of that step.

    goal: {step number: (M, 3) goal points (m)}; particles: slice or indices of the body in the full
    particle array. Active at the goal steps (a rollout shorter than the last goal step sees the first ones)."""

    def __init__(self, goal: dict, particles, weight: float = 1.0):
        super().__init__(steps=sorted(goal), weight=weight)
        self.goal = {int(k): np.asarray(v, dtype=np.float64) for k, v in goal.items()}
        # one tree per distinct goal array (a per-step goal repeats each snapshot over several steps)
        built: dict[int, cKDTree] = {}
        self.trees = {}
        for k, v in self.goal.items():
            if id(v) not in built:
                built[id(v)] = cKDTree(v)
            self.trees[k] = built[id(v)]
        self.particles = particles

    def evaluate(self, state, grad):
        rows = state.select(self.particles)  # a body still being emitted: the particles that have left
        g = self.goal[state.step]
        if len(rows) == 0 or len(g) == 0:
            return 0.0, None
        x = state.x[rows]
        d_x, nn = self.trees[state.step].query(x)  # nearest goal point of each particle
        d_g, nn_rev = cKDTree(x).query(g)  # nearest particle of each goal point
        n, m = len(x), len(g)
        value = float(np.mean(d_x ** 2) + np.mean(d_g ** 2))
        if not grad:
            return value, None
        gx = (2.0 / n) * (x - g[nn])
        np.add.at(gx, nn_rev, (2.0 / m) * (x[nn_rev] - g))
        full = np.zeros_like(state.x)
        full[rows] = gx
        return value, {"x": full}


class NegativeSpread(Loss):
    """−(mean squared distance of a body's particles from their centroid) (m²)."""

    def __init__(self, particles, steps="final", weight: float = 1.0):
        super().__init__(steps=steps, weight=weight)
        self.particles = particles

    def evaluate(self, state, grad):
        rows = state.select(self.particles)
        if len(rows) == 0:
            return 0.0, None
        x = state.x[rows]
        r = x - x.mean(axis=0)
        value = -float(np.mean(np.sum(r * r, axis=1)))
        if not grad:
            return value, None
        full = np.zeros_like(state.x)
        full[rows] = (-2.0 / len(x)) * r
        return value, {"x": full}


class ToolAttraction(Loss):
    """Squared horizontal distance from the tool origin to a body's centroid (m²), every step. It keeps its
    unweighted value per step in `values` (cleared by the caller before a rollout), so that optimisers can
    report the task loss without it and scale its weight."""

    def __init__(self, particles, tool: int = 0, weight: float = 1.0, steps="all"):
        super().__init__(steps=steps, weight=weight)
        self.particles = particles
        self.tool = tool
        self.values: dict[int, float] = {}

    def evaluate(self, state, grad):
        rows = state.select(self.particles)
        if len(rows) == 0:
            return 0.0, None
        centroid = state.x[rows].mean(axis=0)
        d = state.tool_position[self.tool] - centroid
        d[2] = 0.0
        value = float(d @ d)
        self.values[state.step] = value
        if not grad:
            return value, None
        g = np.zeros_like(state.tool_position)
        g[self.tool] = 2.0 * d
        return value, {"tool_position": g}

    @property
    def total(self) -> float:
        """The weighted sum over the steps seen in the last rollout."""
        return self.weight * float(sum(self.values.values()))


class MeanDistance(Loss):
    """Mean over a body's particles of the distance |x_i − g| to a goal point (m): the paper's Transporting loss,
    a norm rather than its square, so that particles far from the goal do not dominate.
        D = (1/N) Σ_i |x_i − g|,   ∂D/∂x_i = (x_i − g) / (N |x_i − g|)"""

    def __init__(self, goal, particles, steps="final", weight: float = 1.0):
        super().__init__(steps=steps, weight=weight)
        self.goal = np.asarray(goal, dtype=np.float64)
        self.particles = particles

    def evaluate(self, state, grad):
        rows = state.select(self.particles)
        if len(rows) == 0:
            return 0.0, None
        d = state.x[rows] - self.goal
        r = np.sqrt(np.sum(d * d, axis=1) + 1e-24)
        value = float(r.mean())
        if not grad:
            return value, None
        full = np.zeros_like(state.x)
        full[rows] = d / (len(rows) * r[:, None])
        return value, {"x": full}
