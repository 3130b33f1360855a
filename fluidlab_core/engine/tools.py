"""Tools (effectors): kinematic rigid bodies given by a signed distance field in their own frame, moved by a
6-D velocity action, coupled to the particles through the grid with the soft contact model of FluidLab.

Kinematics (world frame, SI): pose (p, R); an action (v, ω) in m/s and rad/s, both in the world frame, is
held over the step's substeps: p ← p + v Δt, R ← exp([ω]× Δt) R. A point x of the tool moves at
v + ω × (x − p). Tool poses are bounded by a workspace box on p: an action that would leave it is scaled
back to stop at the boundary, and the clipping is reported in the step's info.

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


@ti.data_oriented
class Tool:
    """The Taichi side of one tool: its current pose and velocity, and the contact hook for the grid."""

    def __init__(self, spec: ToolSpec, real, dx: float):
        self.spec = spec
        self.position = ti.Vector.field(3, real, shape=())  # tool origin p (m)
        self.rotation = ti.Matrix.field(3, 3, real, shape=())  # R, tool frame to world
        self.linear_velocity = ti.Vector.field(3, real, shape=())  # v (m/s)
        self.angular_velocity = ti.Vector.field(3, real, shape=())  # ω (rad/s)
        self.sdf_local = statics.sdf_func(spec.shape, real, 0.5 * dx)
        self.normal_local = statics.sdf_normal(self.sdf_local, 0.01 * dx)
        self.contact = self._make_contact()

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

        self.contact_at = contact_at
        position, rotation = self.position, self.rotation
        lin, ang = self.linear_velocity, self.angular_velocity

        @ti.func
        def contact(x, u):
            return contact_at(x, u, position[None], rotation[None], lin[None], ang[None])

        return contact


class ToolState:
    """Tool poses on the host (numpy), advanced substep by substep; the kernels read them from `Tool`."""

    def __init__(self, specs: list[ToolSpec]):
        self.specs = specs
        self.position = np.array([s.position for s in specs], dtype=np.float64).reshape(-1, 3)
        self.rotation = np.array([Rotation.from_quat(s.quaternion).as_matrix() for s in specs]).reshape(-1, 3, 3)

    def parse_action(self, action) -> np.ndarray:
        """(n_tools, 6) velocities from None, a (6,) array (one tool), an (n, 6) array or a {name: (6,)} dict;
        dimensions outside each tool's action mask are zeroed."""
        n = len(self.specs)
        out = np.zeros((n, 6))
        if action is None:
            return out
        if isinstance(action, dict):
            names = [s.name for s in self.specs]
            for key, value in action.items():
                if key not in names:
                    raise KeyError(f"no tool named {key!r}; tools: {', '.join(names)}")
                out[names.index(key)] = self._vector(value, key)
        else:
            arr = np.asarray(action, dtype=np.float64)
            if arr.shape == (6,) and n == 1:
                arr = arr[None]
            if arr.shape != (n, 6):
                raise ValueError(f"action must have shape (6,) for one tool or ({n}, 6), got {arr.shape}")
            out[:] = arr
        if not np.all(np.isfinite(out)):
            raise ValueError("action contains NaN or infinity")
        return out * np.array([s.action_mask for s in self.specs], dtype=np.float64)

    @staticmethod
    def _vector(value, name):
        arr = np.asarray(value, dtype=np.float64)
        if arr.shape != (6,):
            raise ValueError(f"action for tool {name!r} must be 6 numbers (vx, vy, vz, wx, wy, wz), got {arr.shape}")
        return arr

    def clip(self, velocities: np.ndarray, dt: float) -> tuple[np.ndarray, list[bool]]:
        """Scale each tool's linear velocity back so that its position stays in its workspace over dt."""
        out, dims = clip_twists(self.specs, self.position, velocities, dt)
        return out, [bool(d.any()) for d in dims]

    @staticmethod
    def turns(velocities: np.ndarray, dt: float) -> np.ndarray:
        """(n_tools, 3, 3) rotations exp([ω]× dt) of the angular velocities over dt."""
        return Rotation.from_rotvec(velocities[:, 3:] * dt).as_matrix().reshape(-1, 3, 3)

    def advance(self, velocities: np.ndarray, dt: float, turns: np.ndarray | None = None):
        """p ← p + v dt, R ← exp([ω]× dt) R; `turns` (from `turns(velocities, dt)`) saves recomputing the
        rotations when several substeps hold the same twist."""
        if not len(self.specs):
            return
        if turns is None:
            turns = self.turns(velocities, dt)
        self.position += velocities[:, :3] * dt
        self.rotation = turns @ self.rotation

    def pose(self, i: int) -> np.ndarray:
        """(x, y, z, qx, qy, qz, qw) of tool i."""
        return np.concatenate([self.position[i], Rotation.from_matrix(self.rotation[i]).as_quat()])


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
