"""Collision check of a plan: the arm's links against the table, the task's container and each other.

Geometry
--------
Each link is a union of capsules (robot_models/collision.json: Franka's own coarse self-collision capsules
from franka_description, radii 25-60 mm): a capsule is the set of points within r of a segment [a, b] fixed
in the link's frame. At joint positions q, forward kinematics (Pinocchio, the kinematic URDF) gives each
link frame's pose (R_i(q), p_i(q)) in the base frame and the segment's ends A = p_i + R_i a, B = p_i + R_i b.

Obstacles, in the base frame (`scene_obstacles`):
- the table: the half-space below the plane z = table_height of the scene frame (mounting.json; default 0,
  the plane the arm's base stands on), moved by the task's scene_origin;
- the task's container, a solid cylinder or box from the task's own geometry (fluidlab_core/tasks: the cup of
  the cup tasks and LatteArtPour, radius 45 mm, 60 mm tall; the tank of the Gathering tasks and Transporting,
  160 x 120 x 70 mm; IceCreamStatic's cone in its holder, radius 30 mm, 80 mm tall; IceCreamDynamic's fixed
  nozzle, radius 9 mm from 100 mm above the table up to 160 mm, an assumed length: the machine above it is
  not part of the task). The tasks write their scenes with the container's axis at TASK_SCENE_CENTER =
  (0.5, 0, 0) of the base frame, which is the shipped scene_origin; the obstacle is placed at scene_origin
  (the lab's calibration) with the same offset from it. Pouring has no fixed container (the arm holds the
  glass); a task not known here is checked against the table only;
- the arm itself: the link pairs of collision.json (forearm and wrist, links 5-7, against base and shoulder,
  links 0-2).
The mounted tool is not modelled: it is expected to be inside the container.

Distances: for a capsule (segment S, radius r) and a convex solid O with signed distance function sd_O
(negative inside), the clearance is  min_{x in S} sd_O(x) - r ;  between two capsules it is
min_{x in S1} dist(x, S2) - r1 - r2. Along a segment x(t) = A + t (B - A), t in [0, 1], both functions are
convex in t (the signed distance to a convex set is convex, and so is the distance to a segment), so a
golden-section search finds the minimum to 1e-7 of the segment's length (`_golden_min`, vectorised over all
samples and pairs); the half-space's is exact (min over the two ends). A plan passes if every clearance
stays >= `clearance` (default 10 mm, collision.json) at every sample.

Samples: the plan's positions at every control tick (the arm moves linearly in joint space between them
under the hold model), refined by linear interpolation wherever a capsule end would move more than
`max_step` (2 mm) between two samples, so no more than 2 mm of motion goes unchecked; the report gives the
largest motion between checked samples. Units: m, s, rad. Nothing is computed at import time.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

import robot_models
from fluidlab_ros.frames import pose_to_se3

TASK_SCENE_CENTER = (0.5, 0.0, 0.0)  # m: where the paper's tasks put their container's axis, on the table
_GOLDEN = (np.sqrt(5.0) - 1.0) / 2.0


@dataclass(frozen=True)
class Obstacle:
    """A convex solid in the base frame: `kind` "cylinder" (size: radius, half height; axis = local z),
    "box" (size: half extents) or "halfspace" (the side below the local xy plane; size unused)."""

    name: str
    kind: str
    rotation: np.ndarray  # (3, 3) local axes in the base frame
    center: np.ndarray  # (3,) m
    size: tuple = ()

    def signed_distance(self, p: np.ndarray) -> np.ndarray:
        """Signed distance (m) of points p (..., 3): positive outside, negative inside."""
        x = (np.asarray(p) - self.center) @ self.rotation  # local coordinates
        if self.kind == "halfspace":
            return x[..., 2]
        if self.kind == "cylinder":
            radius, half = self.size
            q = np.stack([np.linalg.norm(x[..., :2], axis=-1) - radius, np.abs(x[..., 2]) - half], axis=-1)
        elif self.kind == "box":
            q = np.abs(x) - np.asarray(self.size)
        else:
            raise ValueError(f"unknown obstacle kind {self.kind!r}")
        return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)


def task_obstacles(task: str) -> list[tuple]:
    """The task's fixed container as (name, kind, center, size) in the task's own coordinates (base frame as
    the simulator has it), from the constants of fluidlab_core/tasks; [] if the task has none or is unknown."""
    from fluidlab_core.tasks import cup_tasks, gathering, pour_tasks

    if task in ("LatteArtStir", "Mixing", "LatteArtPour"):
        h = cup_tasks.CUP_HEIGHT
        return [("cup", "cylinder", (*cup_tasks.CUP_CENTER, 0.5 * h), (cup_tasks.CUP_OUTER_RADIUS, 0.5 * h))]
    if task in ("GatheringEasy", "GatheringHard", "Transporting"):
        lo, hi = np.array(gathering.TANK_LOWER), np.array(gathering.TANK_UPPER)
        return [("tank", "box", tuple(0.5 * (lo + hi)), tuple(0.5 * (hi - lo)))]
    if task == "IceCreamStatic":  # the cone, tip CONE_TIP, in a holder down to the table: a cylinder
        top = pour_tasks.CONE_TIP[2] + pour_tasks.CONE_HEIGHT
        return [("cone", "cylinder", (*pour_tasks.CONE_TIP[:2], 0.5 * top), (pour_tasks.CONE_TOP_RADIUS, 0.5 * top))]
    if task == "IceCreamDynamic":  # the machine's nozzle (radius + 3 mm wall), an assumed 60 mm long
        z0, length = pour_tasks.NOZZLE_TIP[2], 0.06
        return [("nozzle", "cylinder", (*pour_tasks.NOZZLE_TIP[:2], z0 + 0.5 * length),
                 (pour_tasks.NOZZLE_RADIUS + 0.003, 0.5 * length))]
    return []  # Pouring: the glass is the tool; other tasks: no container known


def scene_obstacles(mounting) -> list[Obstacle]:
    """The table and the task's container in the base frame, placed by the mounting's scene_origin."""
    scene = pose_to_se3(mounting.scene_origin)
    out = [Obstacle("table", "halfspace", scene.rotation.copy(),
                    scene.act(np.array([0.0, 0.0, float(mounting.table_height)])))]
    for name, kind, center, size in task_obstacles(mounting.task):
        c = scene.act(np.asarray(center, dtype=float) - np.asarray(TASK_SCENE_CENTER))
        out.append(Obstacle(name, kind, scene.rotation.copy(), c, tuple(float(s) for s in size)))
    return out


def _golden_min(f, n: int, iterations: int = 36):
    """min over t in [0, 1] of a convex function f(t) -> (n,) evaluated elementwise on t (n,); returns the
    minimum (n,) and the minimiser (n,)."""
    a, b = np.zeros(n), np.ones(n)
    c, d = b - _GOLDEN * (b - a), a + _GOLDEN * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(iterations):
        left = fc <= fd  # a minimiser lies in [a, d]
        b = np.where(left, d, b)
        a = np.where(left, a, c)
        new = np.where(left, b - _GOLDEN * (b - a), a + _GOLDEN * (b - a))
        fn = f(new)
        c, d, fc, fd = (np.where(left, new, d), np.where(left, c, new), np.where(left, fn, fd),
                        np.where(left, fc, fn))
    ts = np.stack([np.zeros(n), np.ones(n), c, d])
    vals = np.stack([f(ts[0]), f(ts[1]), fc, fd])
    k = np.argmin(vals, axis=0)
    idx = np.arange(n)
    return vals[k, idx], ts[k, idx]


def point_segment_distance(p, a, b) -> np.ndarray:
    """Distance (m) from points p (..., 3) to segments [a, b] (..., 3)."""
    ab = b - a
    den = np.maximum(np.einsum("...i,...i->...", ab, ab), 1e-300)
    t = np.clip(np.einsum("...i,...i->...", p - a, ab) / den, 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def _refined(exact, lower, upper, floor):
    """Evaluate `exact(mask)` only where the lower bound could still matter: at or below the larger of `floor`
    and the least upper bound (everywhere if floor is None). Elsewhere the lower bound is returned: it exceeds
    both the minimum and floor."""
    out = lower.copy()
    if len(out):
        mask = np.ones(len(out), bool) if floor is None else lower <= max(float(np.min(upper)), floor)
        out[mask] = exact(mask)
    return out


def capsule_capsule(a1, b1, r1, a2, b2, r2, floor: float | None = None) -> np.ndarray:
    """Clearance (m, negative: overlap) between capsules ([a1, b1], r1) and ([a2, b2], r2), rows (n, 3). With
    `floor`, values above both `floor` and the least clearance may be lower bounds instead (faster)."""
    a1, b1, a2, b2 = (np.asarray(v, dtype=float).reshape(-1, 3) for v in (a1, b1, a2, b2))
    r = np.broadcast_to(np.asarray(r1, dtype=float) + np.asarray(r2, dtype=float), (len(a1),))
    m1, m2 = 0.5 * (a1 + b1), 0.5 * (a2 + b2)
    centre = np.linalg.norm(m1 - m2, axis=-1) - r  # distance is 1-Lipschitz in either point
    lower = centre - 0.5 * (np.linalg.norm(b1 - a1, axis=-1) + np.linalg.norm(b2 - a2, axis=-1))

    def exact(m):
        f = lambda t: point_segment_distance(a1[m] + t[:, None] * (b1[m] - a1[m]), a2[m], b2[m])  # noqa: E731
        return _golden_min(f, int(m.sum()))[0] - r[m]

    return _refined(exact, lower, centre, floor)


def capsule_obstacle(a, b, r, obstacle: Obstacle, floor: float | None = None) -> np.ndarray:
    """Clearance (m, negative: penetration) between capsules ([a, b], r), rows (n, 3), and a convex obstacle.
    With `floor`, values above both `floor` and the least clearance may be lower bounds instead (faster)."""
    a, b = (np.asarray(v, dtype=float).reshape(-1, 3) for v in (a, b))
    r = np.broadcast_to(np.asarray(r, dtype=float), (len(a),))
    if obstacle.kind == "halfspace":  # linear along the segment: the minimum is at an end
        return np.minimum(obstacle.signed_distance(a), obstacle.signed_distance(b)) - r
    centre = obstacle.signed_distance(0.5 * (a + b)) - r
    lower = centre - 0.5 * np.linalg.norm(b - a, axis=-1)

    def exact(m):
        f = lambda t: obstacle.signed_distance(a[m] + t[:, None] * (b[m] - a[m]))  # noqa: E731
        return _golden_min(f, int(m.sum()))[0] - r[m]

    return _refined(exact, lower, centre, floor)


@dataclass
class CollisionCheck:
    ok: bool
    violations: list[str]
    clearance: float  # m, required
    minimum: dict = field(default_factory=dict)  # obstacle name or "self" -> least clearance (m) over the plan
    where: dict = field(default_factory=dict)  # same keys -> "fr3_link7 at t = 1.234 s"
    sample_spacing: float = 0.0  # m, largest motion of a capsule end between two checked samples
    samples: int = 0


class CollisionModel:
    """The capsules of a `fluidlab_ros.robot.Robot`'s links, the task's obstacles (a `Mounting`), and the
    required clearance (m; default collision.json's)."""

    def __init__(self, robot, mounting, clearance: float | None = None, max_step: float = 0.002):
        doc = json.loads(robot_models.collision_path().read_text())
        self.robot = robot
        self.clearance = float(doc["clearance"] if clearance is None else clearance)
        if not np.isfinite(self.clearance) or self.clearance < 0:
            raise ValueError(f"clearance must be a finite distance >= 0 m, got {clearance}")
        self.max_step = float(max_step)
        prefix = f"{robot.name}_"
        self.link_of, self.a, self.b, self.r = [], [], [], []
        for link, caps in doc["capsules"].items():
            for cap in caps:
                self.link_of.append(link)
                self.a.append(cap["a"])
                self.b.append(cap["b"])
                self.r.append(float(cap["r"]))
        self.a, self.b, self.r = np.array(self.a), np.array(self.b), np.array(self.r)
        self.joint_of = np.array([int(link[len("link"):]) for link in self.link_of])  # link i moves with joint i
        self.names = [prefix + link for link in self.link_of]
        table_links = set(doc["table_links"])
        self.table_caps = [i for i, link in enumerate(self.link_of) if link in table_links]
        self.pairs = [(i, j) for l1, l2 in doc["self_collision_pairs"]
                      for i, li in enumerate(self.link_of) if li == l1
                      for j, lj in enumerate(self.link_of) if lj == l2]
        self.obstacles = scene_obstacles(mounting)

    def endpoints(self, qs) -> tuple[np.ndarray, np.ndarray]:
        """Capsule ends A, B (N, C, 3) in the base frame for joint positions qs (N, dof)."""
        qs = np.atleast_2d(np.asarray(qs, dtype=float))
        model, data = self.robot.model, self.robot.model.createData()
        nj = model.njoints
        rot = np.empty((len(qs), nj, 3, 3))
        pos = np.empty((len(qs), nj, 3))
        for k, q in enumerate(qs):
            pin.forwardKinematics(model, data, q)
            for j in range(nj):  # joint 0 = the universe: link0's frame is the base frame
                m = data.oMi[j]
                rot[k, j], pos[k, j] = m.rotation, m.translation
        r, p = rot[:, self.joint_of], pos[:, self.joint_of]
        return (p + np.einsum("ncij,cj->nci", r, self.a), p + np.einsum("ncij,cj->nci", r, self.b))

    def _refine(self, qs, times):
        """Insert linearly interpolated samples wherever a capsule end moves more than max_step."""
        A, B = self.endpoints(qs)
        if len(qs) < 2:
            return qs, times, A, B
        travel = np.maximum(np.linalg.norm(np.diff(A, axis=0), axis=-1).max(axis=1),
                            np.linalg.norm(np.diff(B, axis=0), axis=-1).max(axis=1))
        split = np.ceil(travel / self.max_step).astype(int)
        if split.sum() > 2_000_000:
            raise ValueError(f"the samples are too far apart to be a motion: {split.sum()} refined samples "
                             f"would be needed (largest step {travel.max():.3g} m)")
        if np.all(split <= 1):
            return qs, times, A, B
        parts_q, parts_t = [qs[:1]], [times[:1]]
        for k in range(len(qs) - 1):
            s = np.arange(1, split[k] + 1)[:, None] / max(split[k], 1)
            parts_q.append(qs[k] + s * (qs[k + 1] - qs[k]))
            parts_t.append(times[k] + s[:, 0] * (times[k + 1] - times[k]))
        qs, times = np.vstack(parts_q), np.concatenate(parts_t)
        A, B = self.endpoints(qs)
        return qs, times, A, B

    def check(self, qs, times, refine: bool = True) -> CollisionCheck:
        """Clearances of the joint positions qs (N, dof) at times (N,) s: a motion through them (linear in joint
        space in between, refined to max_step), or with refine=False unrelated postures, each on its own."""
        qs = np.atleast_2d(np.asarray(qs, dtype=float))
        times = np.asarray(times, dtype=float)
        if refine:
            qs, times, A, B = self._refine(qs, times)
        else:
            A, B = self.endpoints(qs)
        n, req = len(qs), self.clearance
        res = CollisionCheck(True, [], req, samples=n)
        if n > 1 and refine:
            res.sample_spacing = float(max(np.linalg.norm(np.diff(A, axis=0), axis=-1).max(),
                                           np.linalg.norm(np.diff(B, axis=0), axis=-1).max()))

        def record(key, what, d, labels, pair=False):
            """d (n, m) clearances of m capsules or pairs, labels (m,) -> minimum, where, first violation."""
            k, i = np.unravel_index(np.argmin(d), d.shape)
            res.minimum[key] = float(d[k, i])
            res.where[key] = f"{labels[i]} at t = {times[k]:.3f} s"
            if d[k, i] < req:
                first = int(np.argmax((d < req).any(axis=1)))
                if d[k, i] >= 0:
                    verb = f"{'come' if pair else 'comes'} within {d[k, i] * 1e3:.1f} mm of {what}"
                else:
                    verb = f"{'overlap' if pair else 'overlaps'} {what} by {-d[k, i] * 1e3:.1f} mm"
                res.violations.append(f"{labels[i]} {verb} at t = {times[k]:.3f} s (clearance {req * 1e3:.0f} mm; "
                                      f"closer than that from t = {times[first]:.3f} s)")
                res.ok = False

        for ob in self.obstacles:
            caps = self.table_caps if ob.kind == "halfspace" else list(range(len(self.r)))
            if not caps:
                continue
            a, b = A[:, caps].reshape(-1, 3), B[:, caps].reshape(-1, 3)
            r = np.tile(self.r[caps], n)
            d = capsule_obstacle(a, b, r, ob, floor=req).reshape(n, len(caps))
            record(ob.name, f"the {ob.name}", d, [self.names[c] for c in caps])
        if self.pairs:
            i, j = np.array(self.pairs).T
            d = capsule_capsule(A[:, i].reshape(-1, 3), B[:, i].reshape(-1, 3), np.tile(self.r[i], n),
                                A[:, j].reshape(-1, 3), B[:, j].reshape(-1, 3), np.tile(self.r[j], n), floor=req)
            labels = [f"{self.names[p]} and {self.names[q]}" for p, q in self.pairs]
            record("self", "each other", d.reshape(n, len(self.pairs)), labels, pair=True)
        return res
