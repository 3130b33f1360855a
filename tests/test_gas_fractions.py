"""Solids entering the gas's pressure projection by face fractions (fluidlab_core/engine/gas.py, "Tools and statics
by face fractions"; docs/gas.md): tools, statics and MPM particles, each against whole cells where that shows
the difference, with the divergence after the projection and gradients against central differences. Run with -s
to see the figures each test prints. A file of its own beside tests/test_gas.py, so that the two run on separate
workers under `pytest -n 2 --dist loadfile`.
"""
import numpy as np

import fluidlab_core as fl
from fluidlab_core import losses
from tests.conftest import report
from tests.test_gas import _assert_matches_differences, f64, slab  # noqa: F401 (f64: the float64 fixture)


# --- tools entering by face fractions (tool_faces="fractions") ------------------------------------------------------
def _rotor_slab(tool_faces):
    """The Magnus test's stream past a cylinder tool (D = 8 cells), shorter: 6 D × 4 D."""
    Dc, U, D = 8, 1.0, 0.1
    dx = D / Dc
    nx, ny = 6 * Dc, 4 * Dc
    scene = slab(nx, ny, dx, 0.5 * dx / U, {"x-": (U, 0.0, 0.0), "x+": "open"}, viscosity=U * D / 200,
                 max_cfl=2.5, tool_faces=tool_faces)
    scene.add_tool(fl.Cylinder((0, 0, 0), D / 2, 1.0), pose=(2 * D, 0.5 * ny * dx, 0.5 * dx, 0, 0, 0, 1),
                   name="rotor", max_speed=1.5 * U)
    sim = scene.build()
    start = sim.get_state()
    start.gas.velocity[0][:] = U
    return sim, start, dx


def _after_one_step(sim, start, dy):
    """u_y (nx, ny+1) after one step from a uniform stream, the tool moved by dy (m) across the stream first."""
    s = start.copy()
    s.tool_position = np.asarray(start.tool_position, dtype=float).reshape(-1, 3) + [0.0, dy, 0.0]
    sim.set_state(s)
    sim.step(np.zeros(6))
    return sim.gas_state().velocity[1][:, :, 0].copy()


def test_fractional_tool_faces_move_the_flow_continuously_and_keep_it_divergence_free():
    """A cylinder tool moved across a stream in steps of Δx/64 and Δx/512. With whole cells (the default) the flow
    after one step stays put and then jumps as a cell centre crosses the surface (0.9–1.0 m/s in a stream of
    1 m/s at some face); with face fractions it changes at every step, by an amount that falls with the step
    (measured max change 0.025 and 0.0031 m/s: about linear, away from a face that lies in a tangent plane of
    the cylinder, whose open share goes as the square root of the shift). The stored velocity is each face's
    flux velocity w u + (1 − w) u_solid, so its plain divergence vanishes to the solve's tolerance in every cell
    with an open face."""
    report_rows = {}
    for mode in ("cells", "fractions"):
        sim, start, dx = _rotor_slab(mode)
        changes = {}
        for step in (dx / 64, dx / 512):
            fields = [_after_one_step(sim, start, dx / 4 + k * step) for k in range(5)]
            changes[step] = max(np.abs(b - a).max() for a, b in zip(fields, fields[1:]))
        report_rows[mode] = changes
        if mode == "cells":
            eighths = [_after_one_step(sim, start, k * dx / 8) for k in range(9)]
            jumps = [np.abs(b - a).max() for a, b in zip(eighths, eighths[1:])]
            assert max(jumps) > 0.5 and min(jumps) < 1e-9, jumps  # stays put, then jumps
        else:
            assert changes[dx / 64] < 0.1 and changes[dx / 512] < 0.3 * changes[dx / 64], changes
            _after_one_step(sim, start, 0.3 * dx)
            rep = sim.solver.poisson.last
            open_cells = sim.solver.poisson.flags[0].to_numpy() == 1
            ux, uy, uz = sim.gas_state().velocity
            div = (ux[1:] - ux[:-1]) + (uy[:, 1:] - uy[:, :-1]) + (uz[:, :, 1:] - uz[:, :, :-1])
            assert np.abs(div[open_cells]).max() <= 2e-6 * rep["rhs_norm"], (np.abs(div[open_cells]).max(), rep)
            w = [f.to_numpy() for f in sim.solver.face_w]
            assert any(((wd > 0.05) & (wd < 0.95)).any() for wd in w)  # the cylinder cuts faces
    report("tool faces", **{f"{m}_max_change_step_dx_{int(round(dx / s))}": v
                            for m, ch in report_rows.items() for s, v in ch.items()})


def test_gradients_with_fractional_tool_faces_match_finite_differences(f64):
    """float64, a 10 × 8 × 6 room with an inflow wall, an open wall and a box paddle (a tool that blocks the gas
    by face fractions) moving and turning through it, 4 steps, a loss on the flow at three sensors. The gradient
    with respect to the actions and the paddle's start position includes the faces' open shares moving with
    the paddle: through the blend w u + (1 − w) u_solid and through the operator L = D W Dᵀ (w̄_f = g_f ((Dᵀ y')_f −
    ḡ_f), g the forward solve's Dᵀ y, y' the adjoint's), and through each share's SDF corners. Against central
    differences within 5e-3."""
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.5, 0.4, 0.3), grid_res=10, dt=0.03)
    scene.add_gas(resolution=10, walls={"x-": (0.2, 0, 0), "x+": "open"}, viscosity=1e-3, tolerance=1e-12,
                  max_iterations=500, tool_faces="fractions")
    scene.add_tool(fl.Box((-0.06, -0.04, -0.05), (0.06, 0.04, 0.05)), pose=(0.27, 0.21, 0.14, 0, 0, 0.2, 0.98),
                   name="paddle", action_mask=(1, 1, 0, 0, 0, 1), max_speed=0.3)
    sim = scene.build(requires_grad=True)
    rng = np.random.default_rng(1)
    c = sim.cell_centers()
    s0 = sim.get_state()
    s0.gas.scalars[0] = 293.15 + 2.0 * np.sin(7 * c[..., 0] + 3 * c[..., 1]) * np.cos(5 * c[..., 2])
    n = 4
    acts = np.zeros((n, 6))
    acts[:, 0], acts[:, 1] = 0.1 * rng.standard_normal(n), 0.1 * rng.standard_normal(n)
    acts[:, 5] = 0.6 + 0.3 * rng.standard_normal(n)
    sensors = np.array([[0.1, 0.1, 0.1], [0.4, 0.3, 0.1], [0.42, 0.12, 0.2]])
    loss = losses.GasSensors(sensors, "temperature", target=280.0, power=2)
    sim.set_state(s0)
    res = sim.rollout(acts, loss, grad=True)

    def run(state=s0, actions=acts):
        sim.set_state(state)
        return sim.rollout(actions, loss).loss

    eps = 1e-6
    d = rng.standard_normal(acts.shape) * [1, 1, 0, 0, 0, 1]
    dp = np.array([1.0, -0.5, 0.3])
    checks = {
        "actions": ((run(actions=acts + eps * d) - run(actions=acts - eps * d)) / (2 * eps),
                    float((res.grad_actions[:, 0] * d).sum())),
        "paddle start position": ((run(s0.replace(tool_position=s0.tool_position + eps * dp))
                                   - run(s0.replace(tool_position=s0.tool_position - eps * dp))) / (2 * eps),
                                  float(res.grad_tool_position[0] @ dp)),
    }
    _assert_matches_differences("gas gradient, fractional tool faces", checks)


# --- statics entering by face fractions (static_faces="fractions") --------------------------------------------------
def test_fractional_static_faces_give_a_gap_its_true_width_and_their_gradients_match_finite_differences(f64):
    """A stream of U = 1 m/s (inflow wall x−, open x+) through a 2 × 1 m slab (16 × 8 cells of 0.125 m) narrowed by
    two static boxes over 0.5 ≤ x ≤ 1.5 m to a gap 0.30 ≤ y ≤ 0.72 m whose walls lie between cell centres. Inviscid and
    incompressible, the flow in the middle of the gap moves at U · 1 m / 0.42 m = 2.381 m/s (continuity; the
    entrance's disturbance decays as exp(−π x / 0.42 m), 2 % at the section's middle). With whole cells the gap is
    four cells, 0.5 m, and the flow 2.00 m/s (16 % slow); by fractions the faces at the gap's walls are open by 0.6
    and 0.76 of their area and the speed in their open part, u / w, is within 1 % of 2.381 on every face of the
    cross-section (measured 2.376–2.392). D u = 0 in every cell with an open face. The statics' shares are fixed:
    the backward pass uses the weighted operator without the shares' extra solve; the gradient of a linear loss on
    the velocity after three steps with respect to the initial velocity matches central differences within 5e-3."""
    U, dx, nx, ny = 1.0, 0.125, 16, 8
    a, b = 0.30, 0.72
    speed = U * ny * dx / (b - a)
    sims = {}
    for mode in ("cells", "fractions"):
        scene = slab(nx, ny, dx, 0.2 * dx / U, {"x-": (U, 0.0, 0.0), "x+": "open"}, tolerance=1e-11,
                     max_iterations=500, static_faces=mode)
        scene.add_static(fl.Box((0.5, -0.1, -0.1), (1.5, a, dx + 0.1)), name="low")
        scene.add_static(fl.Box((0.5, b, -0.1), (1.5, 1.1, dx + 0.1)), name="high")
        sim = scene.build(requires_grad=mode == "fractions")
        s = sim.get_state()
        s.gas.velocity[0][:] = U
        sim.set_state(s)
        sim.step()
        sims[mode] = sim, s
    ux_cells = sims["cells"][0].gas_state().velocity[0][8, :, 0]  # the faces at x = 1 m, the section's middle
    sim, s0 = sims["fractions"]
    ux, uy, uz = sim.gas_state().velocity
    w = sim.solver.face_w[0].to_numpy()[8, :, 0]
    open_speed = ux[8, w > 0, 0] / w[w > 0]
    report("static faces: the speed in a gap of 0.42 m", expected=speed, cells=float(ux_cells.max()),
           fractions_min=float(open_speed.min()), fractions_max=float(open_speed.max()),
           shares=" ".join(f"{v:.3f}" for v in w))
    assert abs(ux_cells.max() / speed - 1) > 0.1  # the staircase: 4 cells = 0.5 m
    np.testing.assert_allclose(w[[2, 5]], [0.6, 0.76], atol=1e-6)  # (0.375 − 0.30) / 0.125, (0.72 − 0.625) / 0.125
    np.testing.assert_allclose(open_speed, speed, rtol=0.01)
    open_cells = sim.solver.poisson.flags[0].to_numpy() == 1
    div = (ux[1:] - ux[:-1]) + (uy[:, 1:] - uy[:, :-1]) + (uz[:, :, 1:] - uz[:, :, :-1])
    assert np.abs(div[open_cells]).max() <= 1e-9, np.abs(div[open_cells]).max()

    # gradients: a non-uniform start (the MacCormack clamp has no derivative at the ties of a flat field)
    rng = np.random.default_rng(3)
    g0 = s0.gas.copy()
    g0.velocity = tuple(u + 0.1 * np.sin(np.arange(u.size).reshape(u.shape) * 0.7 + d)
                        for d, u in enumerate(g0.velocity))
    loss = losses.GasLinear({"velocity": rng.standard_normal((nx, ny, 1, 3))})
    d_gas = tuple(rng.standard_normal(u.shape) for u in g0.velocity)

    def run(e=0.0, grad=False):
        st = s0.copy()
        st.gas.velocity = tuple(u + e * du for u, du in zip(g0.velocity, d_gas))
        sim.set_state(st)
        return sim.rollout(3, loss, grad=True) if grad else sim.rollout(3, loss).loss

    res = run(grad=True)
    eps = 1e-6
    _assert_matches_differences("gas gradient, fractional static faces", {
        "initial velocity": ((run(eps) - run(-eps)) / (2 * eps),
                             float(sum((g * du).sum() for g, du in zip(res.grad_velocity, d_gas))))})


# --- particles entering by face fractions (particle_faces="fractions") ----------------------------------------------
def test_fractional_particle_faces_move_the_gas_continuously_and_pass_gradients_to_the_particles(f64):
    """float64, the coupling test's box (0.2 × 0.1 × 0.1 m, 2 cm gas cells, a 0.3 m/s inflow wall, gravity off): a
    water blob moving across the wind blocks the gas by face fractions (each face shut by the blob's volume share
    α there, deposited with trilinear weights: w = max(w_g − α, 0), the shut part moving at the blob's mean
    velocity), and a light foam body upstream rides in the gas (drag k = 20 /s).
    - Continuity: the blob moved across the wind in steps of Δx/64 and Δx/512 before one step changes the gas by
      amounts that fall with the step (measured at most 0.0058 and 0.0007 m/s: linear); whole cells would change
      nothing and then jump as a cell's share crosses ½. D u = 0 in every cell with an open face (1e-13); the
      blob cuts faces (76 with 0.05 < w < 0.95).
    - Gradients: with the shares continuous in the particles' positions, the blob's initial positions have a
      gradient through the gas (a loss on the foam's velocities: blob positions → shares → wind → drag → foam),
      which whole cells cannot give (zero almost everywhere). It and the blob's initial velocities against central
      differences within 5e-3 (measured 1.2e-5 and 1e-8)."""
    from fluidlab_core import materials as M

    scene = fl.Scene(lower=(0, 0, 0), upper=(0.2, 0.1, 0.1), grid_res=10, dt=4e-3, substeps=1, gravity=(0, 0, 0))
    scene.add_gas(resolution=10, walls={"x-": (0.3, 0.0, 0.0), "x+": "open"}, particles_block=True,
                  particle_faces="fractions", particle_drag=20.0, drag_bodies=["foam"], tolerance=1e-12,
                  max_iterations=500)
    foam = scene.add_particles(fl.Box((0.03, 0.035, 0.035), (0.05, 0.065, 0.065)), M.MILK_FOAM, name="foam",
                               velocity=(0.03, 0.02, -0.015))
    blob = scene.add_particles(fl.Box((0.08, 0.03, 0.025), (0.12, 0.07, 0.065)), M.WATER, name="blob",
                               velocity=(0.02, 0.05, 0.1))
    scene.substeps = scene.stable_substeps()
    sim = scene.build(requires_grad=True)
    s0, g0 = sim.get_state(), sim.gas_state()
    dx = 0.02
    rows = slice(blob.start, blob.start + blob.count)

    def after_one_step(dy):
        x = s0.x.copy()
        x[rows, 1] += dy
        sim.set_state(s0.replace(x=x))
        sim.set_gas_state(g0)
        sim.step()
        return np.concatenate([u.ravel() for u in sim.gas_state().velocity])

    changes = {}
    for step in (dx / 64, dx / 512):
        fields = [after_one_step(dx / 5 + k * step) for k in range(4)]
        changes[step] = max(np.abs(b - a).max() for a, b in zip(fields, fields[1:]))
    ux, uy, uz = sim.gas_state().velocity
    w = [f.to_numpy() for f in sim.gas.face_w]
    open_cells = sim.gas.poisson.flags[0].to_numpy() == 1
    div = (ux[1:] - ux[:-1]) + (uy[:, 1:] - uy[:, :-1]) + (uz[:, :, 1:] - uz[:, :, :-1])
    report("particle faces", max_change_step_dx_64=changes[dx / 64], max_change_step_dx_512=changes[dx / 512],
           cut_faces=int(sum(((wd > 0.05) & (wd < 0.95)).sum() for wd in w)),
           shut_faces=int(sum((wd == 0).sum() for wd in w)),
           max_divergence=float(np.abs(div[open_cells]).max()))
    assert 0.0 < changes[dx / 512] < 0.3 * changes[dx / 64] and changes[dx / 64] < 0.05, changes
    assert np.abs(div[open_cells]).max() <= 1e-9
    assert any(((wd > 0.05) & (wd < 0.95)).any() for wd in w)

    rng = np.random.default_rng(5)
    n, n_steps = sim.n_particles, 3
    foam_rows = np.zeros((n, 1))
    foam_rows[foam.start:foam.start + foam.count] = 1.0
    loss = losses.Linear(a=np.zeros((n, 3)), b=foam_rows * rng.normal(size=(n, 3)), steps="all")

    def run(state=s0, grad=False):
        sim.set_state(state)
        sim.set_gas_state(g0)
        return sim.rollout(n_steps, loss, grad=True) if grad else sim.rollout(n_steps, loss).loss

    res = run(grad=True)
    eps = 1e-6
    d_x = np.zeros((n, 3))
    d_x[rows] = rng.standard_normal((blob.count, 3))
    d_v = np.zeros((n, 3))
    d_v[rows] = rng.standard_normal((blob.count, 3))
    _assert_matches_differences("gas gradient, fractional particle faces", {
        "blob initial positions (loss on the foam)": (
            (run(s0.replace(x=s0.x + eps * d_x)) - run(s0.replace(x=s0.x - eps * d_x))) / (2 * eps),
            float((res.grad_positions * d_x).sum())),
        "blob initial velocities (loss on the foam)": (
            (run(s0.replace(v=s0.v + eps * d_v)) - run(s0.replace(v=s0.v - eps * d_v))) / (2 * eps),
            float((res.grad_velocities * d_v).sum()))})
