"""Losses of a rollout: scalars of the particle and tool states at chosen steps, with their gradients.

A loss is evaluated after steps 1 … N of an N-step rollout (step k: the state after k steps, t = k·dt).
Each term returns its value and, when asked, the gradient of that value with respect to the state it read,
as numpy arrays in SI units (loss units per metre, per m/s). The rollout sums the terms over steps and
hands the gradients to the simulator's backward pass (`Simulator.rollout`).

    L = Σ_k Σ_terms w · term(state_k)

Write a new term by subclassing `Loss` and implementing `evaluate`; `Callable` wraps a plain function.
Terms add (`a + b`) and scale (`2.0 * a`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class StepState:
    """What a loss sees after `step` steps: positions x and velocities v of every particle (N, 3), tool
    origins (T, 3) and rotations (T, 3, 3), all float64 in the world frame (m, m/s).

    In a scene with emitters, `active` (N,) marks the particles that take part: every body's, and the pool
    particles emitted so far (engine/emitters.py); the rows of the others hold parked values that mean
    nothing. A loss must read only active rows (`select`), and the rollout zeroes any gradient it returns on
    the others (`only_active`). `active` is None in a scene without emitters (every row takes part)."""

    step: int
    time: float
    x: np.ndarray
    v: np.ndarray
    tool_position: np.ndarray
    tool_rotation: np.ndarray
    active: np.ndarray | None = None
    gas: object | None = None  # fluidlab_core.gas.GasView in a scene with gas: its fields after the step

    def select(self, particles=None) -> np.ndarray:
        """Row indices of the active particles among `particles` (a slice, an index array, or None for all)."""
        rows = np.arange(len(self.x))[particles if particles is not None else slice(None)]
        return rows if self.active is None else rows[self.active[rows]]

    def only_active(self, grads: dict | None) -> dict | None:
        """The gradients with their rows of inactive particles zeroed."""
        if not grads or self.active is None:
            return grads
        out = dict(grads)
        for key in ("x", "v"):
            if out.get(key) is not None:
                g = np.array(out[key], dtype=np.float64, copy=True)
                g[~self.active] = 0.0
                out[key] = g
        return out


GRAD_KEYS = ("x", "v", "tool_position", "tool_rotation")  # and, in a gas scene, "gas_<field>" (gas.GasView)


class Loss:
    """Base class. `steps`: "final" (only after the last step), "all", or an iterable of step numbers."""

    def __init__(self, steps="final", weight: float = 1.0):
        if not (steps in ("final", "all") or not isinstance(steps, str)):
            raise ValueError(f"steps must be 'final', 'all' or a list of step numbers, got {steps!r}")
        self.steps = steps if isinstance(steps, str) else frozenset(int(k) for k in steps)
        self.weight = float(weight)

    def active(self, step: int, horizon: int) -> bool:
        if self.steps == "final":
            return step == horizon
        if self.steps == "all":
            return True
        return step in self.steps

    def evaluate(self, state: StepState, grad: bool):
        """(value, {key: gradient} or None). Keys from GRAD_KEYS or "gas_<field>" (fields of state.gas: temperature,
        smoke, velocity, named scalars); missing keys mean zero gradient."""
        raise NotImplementedError

    def __call__(self, state: StepState, horizon: int, grad: bool = False):
        """The weighted value at this step (0 if inactive) and its gradients."""
        if not self.active(state.step, horizon):
            return 0.0, {}
        value, grads = self.evaluate(state, grad)
        grads = {k: self.weight * np.asarray(g, dtype=np.float64) for k, g in (grads or {}).items()}
        unknown = {k for k in grads if k not in GRAD_KEYS and not k.startswith("gas_")}
        if unknown:
            raise KeyError(f"loss {type(self).__name__} returned gradients for unknown keys {sorted(unknown)}; "
                           f"allowed: {GRAD_KEYS}")
        return self.weight * float(value), grads

    def __add__(self, other):
        return Sum([self, other])

    def __rmul__(self, factor):
        return Sum([self], factor)

    __mul__ = __rmul__


class Sum(Loss):
    """A weighted sum of terms (each keeps its own steps)."""

    def __init__(self, terms, weight: float = 1.0):
        self.terms = list(terms)
        self.weight = float(weight)
        self.steps = "all"

    def active(self, step, horizon):
        return any(t.active(step, horizon) for t in self.terms)

    def __call__(self, state, horizon, grad=False):
        total, out = 0.0, {}
        for t in self.terms:
            value, grads = t(state, horizon, grad)
            total += value
            for k, g in grads.items():
                out[k] = out[k] + g if k in out else g
        return self.weight * total, {k: self.weight * g for k, g in out.items()}


def _scatter(n, rows, values):
    full = np.zeros((n, 3))
    full[rows] = values
    return full


class MeanSquaredDistance(Loss):
    """mean_p |x_p − target_p|² over the chosen particles (m²); target (3,) or one row per particle.

    particles: a slice or index array (e.g. `sim.handle("water").slice`), None for all."""

    def __init__(self, target, particles=None, steps="final", weight: float = 1.0):
        super().__init__(steps, weight)
        self.target = np.asarray(target, dtype=np.float64)
        self.particles = particles

    def evaluate(self, state, grad):
        chosen = np.arange(len(state.x))[self.particles if self.particles is not None else slice(None)]
        keep = np.ones(len(chosen), dtype=bool) if state.active is None else state.active[chosen]
        rows = chosen[keep]
        if len(rows) == 0:  # nothing emitted yet
            return 0.0, None
        diff = state.x[rows] - (self.target if self.target.ndim == 1 else self.target[keep])
        value = float(np.mean(np.sum(diff * diff, axis=1)))
        if not grad:
            return value, None
        return value, {"x": _scatter(len(state.x), rows, 2.0 * diff / len(rows))}


class CenterOfMassDistance(MeanSquaredDistance):
    """|mean_p x_p − target|² (m²) over the chosen particles (equal masses within a body); target (3,)."""

    def evaluate(self, state, grad):
        rows = state.select(self.particles)
        if len(rows) == 0:  # nothing emitted yet
            return 0.0, None
        d = state.x[rows].mean(axis=0) - self.target
        value = float(d @ d)
        if not grad:
            return value, None
        return value, {"x": _scatter(len(state.x), rows, np.tile(2.0 * d / len(rows), (len(rows), 1)))}


class Linear(Loss):
    """Σ_p (a_p · x_p + b_p · v_p): a linear functional of the state, for tests and probes."""

    def __init__(self, a=None, b=None, steps="final", weight: float = 1.0):
        super().__init__(steps, weight)
        self.a = None if a is None else np.asarray(a, dtype=np.float64)
        self.b = None if b is None else np.asarray(b, dtype=np.float64)

    def evaluate(self, state, grad):
        value = 0.0
        grads = {}
        mask = 1.0 if state.active is None else state.active[:, None].astype(np.float64)
        if self.a is not None:
            value += float(np.sum(mask * self.a * state.x))
            grads["x"] = mask * self.a
        if self.b is not None:
            value += float(np.sum(mask * self.b * state.v))
            grads["v"] = mask * self.b
        return value, (grads if grad else None)


class ToolDistance(Loss):
    """|p_tool − target|² (m²) of one tool's origin."""

    def __init__(self, target, tool: int = 0, steps="final", weight: float = 1.0):
        super().__init__(steps, weight)
        self.target = np.asarray(target, dtype=np.float64)
        self.tool = int(tool)

    def evaluate(self, state, grad):
        d = state.tool_position[self.tool] - self.target
        if not grad:
            return float(d @ d), None
        g = np.zeros_like(state.tool_position)
        g[self.tool] = 2.0 * d
        return float(d @ d), {"tool_position": g}


class Callable(Loss):
    """A loss from a function f(state: StepState, grad: bool) -> (value, {key: gradient} or None)."""

    def __init__(self, func, steps="final", weight: float = 1.0):
        super().__init__(steps, weight)
        self.func = func

    def evaluate(self, state, grad):
        return self.func(state, grad)


def _gas(state):
    if getattr(state, "gas", None) is None:
        raise ValueError("this loss reads the gas, and the states it is given carry none: a scene with gas and no "
                         "particles (Scene.add_gas; a GasSimulator) hands its losses the gas, a scene with particles "
                         "and gas hands them the particles and tools only (docs/gas.md)")
    return state.gas


class GasSensors(Loss):
    """Σ_i |f(x_i) − target_i|^p of a gas field ("temperature" in K, "smoke" in kg/m³ or a named scalar) read at
    sensor points x_i (P, 3) in m by trilinear interpolation of the cell values; p = 1 (default, the FluidLab
    Air Circulation loss) or 2. target: one number or one per sensor."""

    def __init__(self, points, field: str = "temperature", target=0.0, power: int = 1, steps="all",
                 weight: float = 1.0):
        super().__init__(steps, weight)
        self.points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if not np.all(np.isfinite(self.points)):
            raise ValueError("sensor points must be finite (m)")
        if field == "velocity":
            raise ValueError("GasSensors reads a scalar field; use GasVelocity for the velocity")
        if power not in (1, 2):
            raise ValueError(f"power must be 1 or 2, got {power!r}")
        self.field, self.power = field, int(power)
        self.target = np.broadcast_to(np.asarray(target, dtype=np.float64), (len(self.points),)).copy()
        self._weights = None

    def evaluate(self, state, grad):
        gas = _gas(state)
        f = gas.field(self.field)
        if self._weights is None:
            self._weights = gas.weights(self.points)
        idx, w = self._weights
        values = (w * f.reshape(-1)[idx]).sum(axis=1)
        d = values - self.target
        value = float(np.sum(np.abs(d)) if self.power == 1 else np.sum(d * d))
        if not grad:
            return value, None
        dv = np.sign(d) if self.power == 1 else 2.0 * d
        g = np.zeros(f.size)
        np.add.at(g, idx.ravel(), (w * dv[:, None]).ravel())
        return value, {f"gas_{self.field}": g.reshape(f.shape)}


class GasLinear(Loss):
    """Σ_c a_c · f_c over the cells of a gas field (a linear functional, for tests and probes): `fields` maps a
    field name ("temperature", "smoke", "velocity" or a named scalar) to its weights (the field's shape)."""

    def __init__(self, fields: dict, steps="final", weight: float = 1.0):
        super().__init__(steps, weight)
        self.fields = {k: np.asarray(v, dtype=np.float64) for k, v in fields.items()}

    def evaluate(self, state, grad):
        gas = _gas(state)
        value = 0.0
        for name, a in self.fields.items():
            f = gas.field(name)
            if a.shape != f.shape:
                raise ValueError(f"GasLinear weights for {name!r} have shape {a.shape}, the field {f.shape}")
            value += float(np.sum(a * f))
        return value, ({f"gas_{k}": a for k, a in self.fields.items()} if grad else None)
