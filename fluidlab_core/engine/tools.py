"""Tools (effectors): kinematic rigid bodies given by a signed distance field in their own frame, moved by a
6-D velocity action, coupled to the particles through the grid with the soft contact model of FluidLab.

Kinematics (world frame, SI): pose (p, R); an action (v, ω) in m/s and rad/s, both in the world frame, is
held over the step's substeps: p ← p + v Δt, R ← exp([ω]× Δt) R (`advance_pose`, on the device, in both
solvers). A point x of the tool moves at v + ω × (x − p). Tool poses are bounded by a workspace box on p:
each linear component of an action that would carry the origin past the box over the step becomes
(bound − p)/dt, so that the tool stops at the boundary (`plan`, on the host in float64, for a whole action
sequence before it runs: the origins depend on the actions alone), and the clipping is reported.

Containers that carry fluid (a glass, a cone held by the arm: `keep_out`): after G2P a particle found inside
the tool at its pose at the start of the substep is put back on its surface and loses its velocity into the
tool relative to the tool's motion, as for statics (statics.py); the grid condition alone lets particles creep
through a moving wall.

Contact at a grid node x with velocity u (after gravity and statics), φ = sdf_tool(Rᵀ(x − p)), n = ∇φ:
    u_rel = u − u_tool,  u_n = u_rel·n
    u_t = u_rel − min(u_n, 0) n                                 (inward normal velocity removed)
    u_t ← u_t · max(0, 1 + μ u_n / |u_t|)      if u_n < 0         (Coulomb friction, μ per tool)
    u_c = u_tool + u_t
    hard contact (softness None):  u ← u_c                     where φ < 0
    soft contact (softness k, 1/m): u ← u + s (u_c − u),  s = min(exp(−k φ), 1)   where φ < 5/k
So a larger softness k means a sharper, harder contact: the influence falls by e every 1/k metres outside
the tool (Xian et al. 2023, FluidLab, soft contact). Tools thinner than two grid cells may let particles
through with hard contact; soft contact acts at a distance and holds thin tools.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import taichi as ti
from scipy.spatial.transform import Rotation

from fluidlab_core import shapes as S
from fluidlab_core.engine import statics
from fluidlab_core.engine.svd import rotation_from_rotvec


@dataclass
class ToolSpec:
    """A tool as the scene describes it (see `Scene.add_tool`)."""

    name: str
    shape: S.Shape  # in the tool frame, metres
    position: np.ndarray  # initial tool-frame origin in the world (m)
    quaternion: np.ndarray  # initial orientation (x, y, z, w)
    friction: float
    softness: float | None  # 1/m; None: hard contact
    action_mask: np.ndarray  # (6,) bools: which of (vx, vy, vz, wx, wy, wz) the action drives
    workspace: tuple[np.ndarray, np.ndarray] | None  # bounds on the tool position (m)
    max_speed: float  # m/s, fastest tool point, for the stability check
    color: tuple[float, float, float] = (0.35, 0.35, 0.4)
    keep_out: bool = False  # after each substep, particles inside the tool are put back on its surface


class Tool:
    """The Taichi side of one tool: its SDF in its own frame and the contact law at a grid node (the pose is
    part of the State, state.py)."""

    def __init__(self, spec: ToolSpec, real, dx: float, uploads=None):
        self.spec = spec
        self.sdf_local = statics.sdf_func(spec.shape, real, 0.5 * dx, uploads)
        self.normal_local = statics.sdf_normal(self.sdf_local, 0.01 * dx)
        self.contact_at = self._make_contact()
        self.keep_out = self._make_keep_out()

    def _make_keep_out(self):
        sdf, normal = self.sdf_local, self.normal_local

        @ti.func
        def keep_out(x, v, p, R, lin, ang):
            """A particle at x with velocity v found inside the tool at pose (p, R) moving at (lin, ang) goes back
            onto its surface and loses its velocity into the tool, relative to the tool's motion."""
            xl = R.transpose() @ (x - p)
            phi = sdf(xl)
            if phi < 0.0:
                n = R @ normal(xl)
                x = x - phi * n
                u_tool = lin + ang.cross(x - p)
                vn = (v - u_tool).dot(n)
                if vn < 0.0:
                    v = v - vn * n
            return x, v

        return keep_out

    def _make_contact(self):
        sdf, normal = self.sdf_local, self.normal_local
        friction = self.spec.friction
        hard = self.spec.softness is None
        softness = 0.0 if hard else self.spec.softness
        reach = 0.0 if hard else 5.0 / softness

        @ti.func
        def contact_at(x, u, p, R, lin, ang):
            """Grid velocity u at node x after contact with the tool at pose (p, R) moving at (lin, ang)."""
            r = x - p
            xl = R.transpose() @ r
            phi = sdf(xl)
            if phi < reach:
                n = R @ normal(xl)
                u_tool = lin + ang.cross(r)
                rel = u - u_tool
                un = rel.dot(n)
                rel_t = rel - ti.min(un, 0.0) * n
                if un < 0.0:
                    rt = statics.safe_norm(rel_t)
                    if rt > 1e-12:
                        rel_t *= ti.max(0.0, 1.0 + friction * un / rt)
                u_c = u_tool + rel_t
                if ti.static(hard):
                    u = u_c
                else:
                    u += ti.min(ti.exp(-softness * phi), 1.0) * (u_c - u)
            return u

        return contact_at


@ti.func
def advance_pose(p, R, lin, ang, dt):
    """The tool's pose after dt holding the twist (lin, ang): p + dt lin, exp([ang]× dt) R."""
    return p + dt * lin, rotation_from_rotvec(ang * dt) @ R


# --- the advance's adjoint ------------------------------------------------------------------------------------
# advance_pose: p' = p + Δt v,  R' = E(θ) R  with θ = Δt ω, t = |θ|, K = [θ]× and Rodrigues' formula
#     E = I + a K + b K²,  a = sin t / t,  b = (1 − cos t) / t².
# With a_θi = c θ_i, b_θi = d θ_i (c = a'(t)/t = (t cos t − sin t)/t³, d = b'(t)/t = (t sin t − 2(1 − cos t))/t⁴)
# and G_i = ∂K/∂θ_i = [e_i]×:
#     ∂E/∂θ_i = a G_i + b (G_i K + K G_i) + θ_i (c K + d K²).
# Given p̄' = ∂L/∂p', R̄' = ∂L/∂R', the adjoint is
#     p̄ = p̄',  v̄ = Δt p̄',  R̄ = Eᵀ R̄',  ω̄_i = Δt Σ_jk Ē_jk (∂E/∂θ_i)_jk  with Ē = R̄' Rᵀ.
# Below t = 0.1, a, b, c, d come from their series to t⁶ (the next terms are below 1e-16 of each there): the closed
# forms lose digits to cancellation at small t (c and d entirely in float32 at the substeps' t ~ 1e-4).
# Written by hand because Taichi's reverse mode of the advance (its matrix products) was three quarters of the
# grid update's reverse compile time (GatheringEasy, 15 s of 20 s; docs/engine.md). E itself is the forward's
# (svd.rotation_from_rotvec), so that R̄ = Eᵀ R̄' is the transpose of what the forward applied.
@ti.func
def _rodrigues_coefficients(t2):
    """(a, b, c, d) of the comment above at t² = t2."""
    a = 1.0 - t2 / 6.0 * (1.0 - t2 / 20.0 * (1.0 - t2 / 42.0))
    b = 0.5 - t2 / 24.0 * (1.0 - t2 / 30.0 * (1.0 - t2 / 56.0))
    c = -1.0 / 3.0 + t2 / 30.0 * (1.0 - t2 / 28.0 * (1.0 - t2 / 54.0))
    d = -1.0 / 12.0 + t2 / 180.0 * (1.0 - t2 / 37.333333333333336 * (1.0 - t2 / 67.5))
    if t2 >= 1e-2:
        t = ti.sqrt(t2)
        sn, cs = ti.sin(t), ti.cos(t)
        a = sn / t
        b = (1.0 - cs) / t2
        c = (t * cs - sn) / (t2 * t)
        d = (t * sn - 2.0 * (1.0 - cs)) / (t2 * t2)
    return a, b, c, d


@ti.func
def advance_pose_adjoint(R, ang, dt, g_p1, g_R1):
    """The adjoint of advance_pose (the comment above): (p̄, R̄, v̄, ω̄) from (p̄', R̄') = (g_p1, g_R1), the
    gradients of the advanced pose; R, ang, dt as the forward had them."""
    th = ang * dt
    K = ti.Matrix([[0.0, -th[2], th[1]], [th[2], 0.0, -th[0]], [-th[1], th[0], 0.0]])
    a, b, c, d = _rodrigues_coefficients(th.dot(th))
    E = rotation_from_rotvec(th)
    g_E = g_R1 @ R.transpose()
    g_th = ti.Vector([0.0, 0.0, 0.0])
    for i in ti.static(range(3)):
        G = ti.Matrix.zero(float, 3, 3)
        G[(i + 2) % 3, (i + 1) % 3] = 1.0  # [e_i]×
        G[(i + 1) % 3, (i + 2) % 3] = -1.0
        dE = a * G + b * (G @ K + K @ G) + th[i] * (c * K + d * (K @ K))
        g_th[i] = (g_E * dE).sum()
    return g_p1, E.transpose() @ g_R1, dt * g_p1, dt * g_th


def parse_action(specs, action) -> np.ndarray:
    """(n_tools, 6) twists from None, a (6,) array (one tool), an (n, 6) array or a {name: (6,)} dict;
    dimensions outside each tool's action mask are zeroed."""
    n = len(specs)
    out = np.zeros((n, 6))
    if action is None:
        return out
    if isinstance(action, dict):
        names = [s.name for s in specs]
        for key, value in action.items():
            if key not in names:
                raise KeyError(f"no tool named {key!r}; tools: {', '.join(names)}")
            arr = np.asarray(value, dtype=np.float64)
            if arr.shape != (6,):
                raise ValueError(f"action for tool {key!r} must be 6 numbers (vx, vy, vz, wx, wy, wz), got "
                                 f"{arr.shape}")
            out[names.index(key)] = arr
    else:
        arr = np.asarray(action, dtype=np.float64)
        if arr.shape == (6,) and n == 1:
            arr = arr[None]
        if arr.shape != (n, 6):
            raise ValueError(f"action must have shape (6,) for one tool or ({n}, 6), got {arr.shape}")
        out[:] = arr
    if not np.all(np.isfinite(out)):
        raise ValueError("action contains NaN or infinity")
    return out * action_masks(specs)


def action_sequence(specs, actions) -> np.ndarray:
    """(N, n_tools, 6) masked twists from what a rollout accepts: (N, 6) for one tool, (N, n_tools, 6), or an
    integer N for a scene without tools (steps with no action)."""
    n_tools = len(specs)
    if isinstance(actions, (int, np.integer)):
        if actions < 1:
            raise ValueError(f"a rollout needs at least one step, got {actions}")
        return np.zeros((int(actions), n_tools, 6))
    arr = np.asarray(actions, dtype=np.float64)
    if n_tools == 0:
        raise ValueError("this scene has no tools: pass the number of steps as actions")
    if arr.ndim == 2 and n_tools == 1:
        arr = arr[:, None, :]
    if arr.ndim != 3 or arr.shape[1:] != (n_tools, 6) or len(arr) < 1:
        raise ValueError(f"actions must have shape (N, 6) for one tool or (N, {n_tools}, 6), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise ValueError(f"actions contain NaN or infinity (first at step {bad[0]})")
    return arr * action_masks(specs)


def action_masks(specs) -> np.ndarray:
    """(n_tools, 6) of 0/1: which twist components each tool's action drives."""
    return np.array([s.action_mask for s in specs], dtype=np.float64).reshape(len(specs), 6)


def pose_of(position, rotation) -> np.ndarray:
    """(x, y, z, qx, qy, qz, qw) of a tool frame from its origin and rotation matrix."""
    return np.concatenate([position, Rotation.from_matrix(rotation).as_quat()])


def clip_twists(specs, position: np.ndarray, twist: np.ndarray, dt: float):
    """Workspace clipping of one step's twists (n_tools, 6) from tool origins `position` (n_tools, 3): each
    linear component that would carry the origin past the workspace over dt becomes (bound − p)/dt. Returns
    the clipped twists and which linear components were clipped (n_tools, 3)."""
    out = np.array(twist, dtype=np.float64, copy=True)
    dims = np.zeros((len(specs), 3), dtype=bool)
    for i, spec in enumerate(specs):
        if spec.workspace is not None:
            lo, hi = spec.workspace
            end = position[i] + out[i, :3] * dt
            inside = np.clip(end, lo, hi)
            dims[i] = np.abs(inside - end) > 1e-12
            out[i, :3] = np.where(dims[i], (inside - position[i]) / dt, out[i, :3])
    return out, dims


def plan(specs, position, twists: np.ndarray, dt: float, substeps: int):
    """Workspace clipping of a sequence of steps: twists (N, n_tools, 6) from tool origins `position`
    (n_tools, 3). The origins depend on the twists alone, so they are predicted here in float64, substep by
    substep as the solvers advance them (p ← p + v Δt). Returns the clipped twists (N, n_tools, 6) and which
    linear components were clipped (N, n_tools, 3)."""
    applied = np.zeros_like(twists, dtype=np.float64)
    clipped = np.zeros((len(twists), len(specs), 3), dtype=bool)
    if not specs:
        return applied, clipped
    p = np.array(position, dtype=np.float64).reshape(len(specs), 3)
    sub_dt = dt / substeps
    for g in range(len(twists)):
        applied[g], clipped[g] = clip_twists(specs, p, twists[g], dt)
        for _ in range(substeps):
            p += applied[g, :, :3] * sub_dt
    return applied, clipped


def plan_poses(specs, position, rotation, applied: np.ndarray, dt: float):
    """The tools' poses at the step boundaries of a planned sequence (after tools.plan): origins (N + 1, T, 3)
    and rotations (N + 1, T, 3, 3), float64, from `position` (T, 3) and `rotation` (T, 3, 3). A twist held over
    a step advances R by exp([ω]× dt) whatever the number of substeps."""
    n, t = len(applied), len(specs)
    pos = np.zeros((n + 1, t, 3))
    rot = np.zeros((n + 1, t, 3, 3))
    if not t:
        return pos, rot
    pos[0] = np.asarray(position, dtype=np.float64).reshape(t, 3)
    rot[0] = np.asarray(rotation, dtype=np.float64).reshape(t, 3, 3)
    for g in range(n):
        pos[g + 1] = pos[g] + applied[g, :, :3] * dt
        rot[g + 1] = Rotation.from_rotvec(applied[g, :, 3:] * dt).as_matrix() @ rot[g]
    return pos, rot
