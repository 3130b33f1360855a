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

Gradient sharing (FluidLab §5's "gradient sharing within fluid bodies"). A particle that the tool never moves
gets no gradient, so a loss on it steers nothing. These auxiliary terms tie particles to the ones that do move,
in the two forms of the paper's released code (github.com/zhouxian/FluidLab, losses/pouring_loss.py and
losses/transporting_loss.py; we did not have the paper's own equations to compare), L1 distances as there (m):
- within a body, towards its lead particle (Pouring): x* is the body particle nearest its goal (the least
  `score`), K the k particles of the body nearest x*, and f the share of the body not yet where it should be
  (`pending`); x*, K and f are chosen on the host and held constant:
      G = f Σ_{p∈K} |x_p − x*|₁,      ∂G/∂x_p = f sign(x_p − x*)   (p ∈ K)
  The particles next to the one that pours first are pulled after it, so the tilt that makes it pour earns
  their gradient too.
- between bodies (Transporting): the water the jet injects is pulled towards the object it should push,
  the mean over pairs of the L1 distance:
      B = (1/(N M)) Σ_p Σ_q |x_p − y_q|₁,
      ∂B/∂x_p = (1/(N M)) Σ_q sign(x_p − y_q),   ∂B/∂y_q = −(1/(N M)) Σ_p sign(x_p − y_q)
  computed per axis from sorted coordinates (counts below and above, prefix sums) in O((N + M) log(N + M)).
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


class Auxiliary(Loss):
    """An optimiser's helper term, not part of the task loss. It keeps its unweighted value per step in `values`
    (cleared by the caller before a rollout), so that optimisers can report the task loss without it and scale
    its weight."""

    def __init__(self, steps="all", weight: float = 1.0):
        super().__init__(steps=steps, weight=weight)
        self.values: dict[int, float] = {}

    @property
    def total(self) -> float:
        """The weighted sum over the steps seen in the last rollout."""
        return self.weight * float(sum(self.values.values()))


class ToolAttraction(Auxiliary):
    """Squared horizontal distance from the tool origin to a body's centroid (m²), every step."""

    def __init__(self, particles, tool: int = 0, weight: float = 1.0, steps="all"):
        super().__init__(steps=steps, weight=weight)
        self.particles = particles
        self.tool = tool

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


class ShareWithLead(Auxiliary):
    """Gradient sharing within a body (G above, m): its k particles nearest the lead particle x* (the least
    `score(x)`, an (n,) array per particle, lower is nearer the goal) are pulled towards x*, weighted by the
    share of the body for which `pending(x)` ((n,) booleans) holds. Zero once nothing is pending."""

    def __init__(self, particles, score, pending, k: int, steps="final", weight: float = 1.0):
        super().__init__(steps=steps, weight=weight)
        if k < 1:
            raise ValueError(f"k must be at least 1, got {k}")
        self.particles, self.score, self.pending, self.k = particles, score, pending, int(k)

    def evaluate(self, state, grad):
        rows = state.select(self.particles)
        if len(rows) < 2:
            return 0.0, None
        x = state.x[rows]
        share = float(np.mean(self.pending(x)))
        lead = x[int(np.argmin(self.score(x)))]
        k = min(self.k, len(x))
        near = np.argpartition(np.sum((x - lead) ** 2, axis=1), k - 1)[:k]
        d = x[near] - lead
        value = share * float(np.abs(d).sum())
        self.values[state.step] = value
        if not grad:
            return value, None
        full = np.zeros_like(state.x)
        full[rows[near]] = share * np.sign(d)
        return value, {"x": full}


def _l1_pairs(a: np.ndarray, b: np.ndarray):
    """Σ_p Σ_q |a_p − b_q| over 1-D arrays, and its derivatives (Σ_q sign(a_p − b_q), −Σ_p sign(a_p − b_q))."""
    bs = np.sort(b)
    prefix = np.concatenate([[0.0], np.cumsum(bs)])
    below = np.searchsorted(bs, a, side="left")  # b_q < a_p (ties count zero in the sign)
    above = len(b) - np.searchsorted(bs, a, side="right")
    total = float(np.sum(a * below - prefix[below]) + np.sum((prefix[-1] - prefix[len(b) - above]) - a * above))
    ga = (below - above).astype(np.float64)
    as_ = np.sort(a)
    b_below = np.searchsorted(as_, b, side="left")  # a_p < b_q
    b_above = len(a) - np.searchsorted(as_, b, side="right")
    gb = (b_below - b_above).astype(np.float64)  # −Σ_p sign(a_p − b_q) = #(a < b) − #(a > b)
    return total, ga, gb


class BodyAttraction(Auxiliary):
    """Gradient sharing between bodies (B above, m): the mean L1 distance between the particles of `pulled` and
    those of `towards`, so that what the tool moves (the injected water) is drawn to what it should push."""

    def __init__(self, pulled, towards, steps="all", weight: float = 1.0):
        super().__init__(steps=steps, weight=weight)
        self.pulled, self.towards = pulled, towards

    def evaluate(self, state, grad):
        ra, rb = state.select(self.pulled), state.select(self.towards)
        if len(ra) == 0 or len(rb) == 0:
            self.values[state.step] = 0.0
            return 0.0, None
        norm = 1.0 / (len(ra) * len(rb))
        value, ga, gb = 0.0, np.zeros((len(ra), 3)), np.zeros((len(rb), 3))
        for axis in range(3):
            t, a_grad, b_grad = _l1_pairs(state.x[ra, axis], state.x[rb, axis])
            value += t
            ga[:, axis], gb[:, axis] = a_grad, b_grad
        value *= norm
        self.values[state.step] = value
        if not grad:
            return value, None
        full = np.zeros_like(state.x)
        full[ra] += norm * ga
        full[rb] += norm * gb
        return value, {"x": full}


class MeanL1Distance(Loss):
    """Mean over a body's particles of the L1 distance to a target along chosen axes (m): the paper's released
    Pouring loss (the light liquid's height above the table; the heavy liquid's displacement from its start).
        D = (1/N) Σ_i Σ_{a∈axes} |x_ia − t_ia|,   ∂D/∂x_ia = sign(x_ia − t_ia) / N
    target: (3,) for every particle, or one row per particle of the body (a body that is not emitted)."""

    def __init__(self, target, particles, axes=(0, 1, 2), steps="final", weight: float = 1.0):
        super().__init__(steps=steps, weight=weight)
        self.target = np.asarray(target, dtype=np.float64)
        self.particles = particles
        self.axes = list(axes)

    def evaluate(self, state, grad):
        rows = state.select(self.particles)
        if len(rows) == 0:
            return 0.0, None
        if self.target.ndim == 2 and len(self.target) != len(rows):
            raise ValueError(f"{len(self.target)} target rows for {len(rows)} active particles")
        d = (state.x[rows] - self.target)[:, self.axes]
        value = float(np.abs(d).sum(axis=1).mean())
        if not grad:
            return value, None
        full = np.zeros_like(state.x)
        full[np.ix_(rows, self.axes)] = np.sign(d) / len(rows)
        return value, {"x": full}


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
