"""The hand-written backwards of P2G's scatter, G2P's gather and the SVD against central finite differences of
the same forward functions, on random inputs, float64.

engine/transfer.py differentiates P2G's scatter and G2P's gather by hand (Taichi's reverse of them is slow, and
its reverse of the per-thread-copy scatter does not exist). Each backward is checked here against central
differences of the forward function it differentiates, in several random directions per input: within 1e-7
relative. These tests used Taichi's reverse mode of the same forward kernels as the reference, which agreed to
1e-10 but took 202 s of the suite's time to compile (the scatter's reverse alone 153 s; 2026-12-06, a cold
cache); the differences compile only the forward kernels. The SVD's backward (engine/svd.py), which Taichi
cannot derive (ti.svd iterates), is checked the same way, and so are the other hand-written backwards the
differentiable solver uses instead of Taichi's reverse mode: the tools' pose advance (tools.advance_pose_adjoint)
and each built-in constitutive model's (constitutive.backward_of).
"""
import numpy as np
import pytest
import taichi as ti
from scipy.spatial.transform import Rotation

import fluidlab_core as fl
from tests import conftest
from fluidlab_core import materials as M
from fluidlab_core.engine import svd as svd3
from fluidlab_core.engine import constitutive, tools, transfer
from tests.conftest import report

N = 40  # random particles
TOL = 1e-7  # relative, on directional derivatives (measured 2026-12-06: x 2e-9, the others 1e-11 or less)
backward_svd = svd3.make_backward_svd(1e-10)


@pytest.fixture(scope="module")
def model():
    conftest.init("f64")
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.08, 0.06), grid_res=10, dt=1e-3, substeps=20)
    scene.add_particles(fl.Box((0.02, 0.02, 0.02), (0.08, 0.06, 0.04)), M.WATER, name="water")
    yield scene.build().model
    conftest.init("f32")


def _inputs(model, rng):
    """Random particles inside the domain with random velocity, affine velocity and stress (numpy)."""
    lo, hi = np.array(model.lower) + 0.01, np.array(model.upper) - 0.01
    return {"x": rng.uniform(lo, hi, size=(N, 3)), "v": rng.normal(scale=0.3, size=(N, 3)),
            "C": rng.normal(scale=5.0, size=(N, 3, 3)), "tau": rng.normal(scale=1e3, size=(N, 3, 3))}


def _particle_fields(values):
    return {k: (ti.Vector.field(3, ti.f64, shape=N) if v.ndim == 2 else ti.Matrix.field(3, 3, ti.f64, shape=N))
            for k, v in values.items()}


def _load(fields, values):
    for k, v in values.items():
        fields[k].from_numpy(v)


def _grid(model, n):
    if n == 1:
        return ti.field(ti.f64, shape=model.grid_shape)
    return ti.Vector.field(n, ti.f64, shape=model.grid_shape)


# Central differences: L is linear in v, C, τ and the grid velocities (a step of 1 is exact but for rounding), and a
# piecewise polynomial in x (the quadratic B-spline's weights, times the affine offsets): a step of 1e-7 m (1e-5 of
# a cell) leaves a truncation of about 1e-10 relative, unless a particle sits within the step of a knot of the
# spline, where its second derivative jumps (a chance of about 1e-4 over the 40 particles).
STEPS = {"x": 1e-7, "v": 1.0, "C": 1.0, "tau": 1.0, "grid_v": 1.0}


def _directional(loss, values, name, direction, steps=STEPS):
    """(L(values + h d) − L(values − h d)) / 2h for the input `name`, h = steps[name]."""
    h = steps[name]
    plus, minus = dict(values), dict(values)
    plus[name] = values[name] + h * direction
    minus[name] = values[name] - h * direction
    return (loss(plus) - loss(minus)) / (2 * h)


def _check(title, loss, values, grads, rng, directions=3, steps=STEPS, tol=TOL, masks=None, floor=0.0):
    """The hand-written gradient of every input against central differences in `directions` random directions (times
    masks[name] where given). A loss may be one number or one per sample (the inputs' first axis), each sample then
    compared on its own, relative to max(|fd|, floor · the largest |fd|)."""
    worst = {}
    for name, g in grads.items():
        for _ in range(directions):
            d = rng.normal(size=values[name].shape) * (masks or {}).get(name, 1.0)
            fd = np.atleast_1d(_directional(loss, values, name, d, steps))
            an = np.sum((g * d).reshape(len(fd), -1), axis=1)
            scale = np.maximum(np.abs(fd), max(floor * np.max(np.abs(fd)), 1e-300))
            worst[name] = max(worst.get(name, 0.0), float(np.max(np.abs(fd - an) / scale)))
    report(title, **worst)
    assert max(worst.values()) < tol, worst


@ti.kernel
def _p2g(model: ti.template(), x: ti.template(), v: ti.template(), C: ti.template(), tau: ti.template(),
         grid_m: ti.template(), grid_mv: ti.template()):
    for p in range(N):
        transfer.scatter(model, grid_m, grid_mv, 0, False, x[p], v[p], C[p], tau[p], p)


@ti.kernel
def _p2g_by_hand(model: ti.template(), x: ti.template(), v: ti.template(), C: ti.template(), tau: ti.template(),
                 a: ti.template(), b: ti.template(), out: ti.types.ndarray()):
    for p in range(N):
        gx, gv, gC, gtau = transfer.p2g_backward(model, b, a, x[p], v[p], C[p], tau[p], p)
        for i in ti.static(range(3)):
            out[p, 0, i], out[p, 1, i] = gx[i], gv[i]
            for j in ti.static(range(3)):
                out[p, 2 + i, j], out[p, 5 + i, j] = gC[i, j], gtau[i, j]


def test_p2g_backward_matches_finite_differences(model):
    """L = Σ_i a_i·(mv)_i + b_i m_i after P2G: ∂L/∂x, ∂L/∂v, ∂L/∂C and ∂L/∂τ by hand (transfer.p2g_backward)
    against central differences of transfer.scatter (atomic), in 3 random directions each."""
    rng = np.random.default_rng(0)
    values = _inputs(model, rng)
    f = _particle_fields(values)
    grid_m, grid_mv = _grid(model, 1), _grid(model, 3)
    a, b = _grid(model, 3), _grid(model, 1)
    a_np, b_np = rng.normal(size=model.grid_shape + (3,)), rng.normal(size=model.grid_shape)
    a.from_numpy(a_np)
    b.from_numpy(b_np)

    def loss(vals):
        _load(f, vals)
        grid_m.fill(0.0)
        grid_mv.fill(0.0)
        _p2g(model, f["x"], f["v"], f["C"], f["tau"], grid_m, grid_mv)
        return float(np.sum(a_np * grid_mv.to_numpy()) + np.sum(b_np * grid_m.to_numpy()))

    _load(f, values)
    out = np.zeros((N, 8, 3))
    _p2g_by_hand(model, f["x"], f["v"], f["C"], f["tau"], a, b, out)
    assert np.abs(out[:, 0]).max() > 0 and np.abs(out[:, 5:8]).max() > 0  # exercised
    _check("P2G backward vs finite differences", loss, values,
           {"x": out[:, 0], "v": out[:, 1], "C": out[:, 2:5], "tau": out[:, 5:8]}, rng)


@ti.kernel
def _g2p(model: ti.template(), x: ti.template(), grid_v: ti.template(), a: ti.template(), b: ti.template(),
         c: ti.template(), loss: ti.template()):
    for p in range(N):
        new_v, new_C = transfer.gather(model, grid_v, x[p])
        x_new = x[p] + model.dt * new_v
        loss[None] += a[p].dot(x_new) + b[p].dot(new_v) + (c[p] * new_C).sum()


@ti.kernel
def _g2p_by_hand(model: ti.template(), x: ti.template(), grid_v: ti.template(), stored_v: ti.template(),
                 a: ti.template(), b: ti.template(), c: ti.template(), grid_grad: ti.template(),
                 out: ti.types.ndarray()):
    for p in range(N):
        v_gathered, _ = transfer.gather(model, grid_v, x[p])
        gf = transfer.gather_backward(model, stored_v, 0, grid_grad, 0, False, x[p], v_gathered, a[p], b[p], c[p])
        g = a[p] + gf
        for i in ti.static(range(3)):
            out[p, i] = g[i]


def test_gather_backward_matches_finite_differences(model):
    """L = Σ_p a_p·(x_p + Δt v_p) + b_p·v_p + c_p:C_p after G2P: ∂L/∂x and ∂L/∂v_i by hand
    (transfer.gather_backward, reading the node velocities from a time-indexed store as the differentiable
    solver does) against central differences of transfer.gather, in 3 random directions each."""
    rng = np.random.default_rng(1)
    values = {"x": _inputs(model, rng)["x"], "grid_v": rng.normal(scale=0.5, size=model.grid_shape + (3,))}
    x, grid_v = ti.Vector.field(3, ti.f64, shape=N), _grid(model, 3)
    stored_v = ti.Vector.field(3, ti.f64, shape=(1,) + tuple(model.grid_shape))
    a, b = (ti.Vector.field(3, ti.f64, shape=N) for _ in range(2))
    c = ti.Matrix.field(3, 3, ti.f64, shape=N)
    a.from_numpy(rng.normal(size=(N, 3)))
    b.from_numpy(rng.normal(size=(N, 3)))
    c.from_numpy(rng.normal(size=(N, 3, 3)))
    total = ti.field(ti.f64, shape=())

    def loss(vals):
        x.from_numpy(vals["x"])
        grid_v.from_numpy(vals["grid_v"])
        total[None] = 0.0
        _g2p(model, x, grid_v, a, b, c, total)
        return float(total[None])

    x.from_numpy(values["x"])
    grid_v.from_numpy(values["grid_v"])
    stored_v.from_numpy(values["grid_v"][None])
    grid_grad = _grid(model, 3)
    out = np.zeros((N, 3))
    _g2p_by_hand(model, x, grid_v, stored_v, a, b, c, grid_grad, out)
    _check("gather backward vs finite differences", loss, values, {"x": out, "grid_v": grid_grad.to_numpy()}, rng)


@ti.kernel
def _svd_loss(F: ti.types.ndarray(), w: ti.types.ndarray()) -> ti.f64:
    A = ti.Matrix([[F[i, j] for j in ti.static(range(3))] for i in ti.static(range(3))])
    U, sig, V = svd3.svd(A)
    total = 0.0
    for i, j in ti.static(ti.ndrange(3, 3)):
        total += w[0, i, j] * U[i, j] + w[2, i, j] * V[i, j]
    for i in ti.static(range(3)):
        total += w[1, i, i] * sig[i, i]
    return total


@ti.kernel
def _svd_grad(F: ti.types.ndarray(), w: ti.types.ndarray(), out: ti.types.ndarray()):
    A = ti.Matrix([[F[i, j] for j in ti.static(range(3))] for i in ti.static(range(3))])
    U, sig, V = svd3.svd(A)
    gU = ti.Matrix([[w[0, i, j] for j in ti.static(range(3))] for i in ti.static(range(3))])
    gV = ti.Matrix([[w[2, i, j] for j in ti.static(range(3))] for i in ti.static(range(3))])
    gsig = ti.Matrix([[w[1, 0, 0], 0.0, 0.0], [0.0, w[1, 1, 1], 0.0], [0.0, 0.0, w[1, 2, 2]]])
    G = backward_svd(gU, gsig, gV, U, sig, V)
    for i, j in ti.static(ti.ndrange(3, 3)):
        out[i, j] = G[i, j]


def test_svd_backward_matches_finite_differences(model):
    """L = Σ a∘U + b∘Σ + c∘V of F = U Σ Vᵀ with distinct singular values: the hand-written backward
    (svd.make_backward_svd) against central differences (ε = 1e-6) in random directions."""
    rng = np.random.default_rng(2)
    worst = 0.0
    for _ in range(5):
        F = np.eye(3) + 0.3 * rng.normal(size=(3, 3))
        w = rng.normal(size=(3, 3, 3))
        G = np.zeros((3, 3))
        _svd_grad(F, w, G)
        for _ in range(3):
            d = rng.normal(size=(3, 3))
            fd = (_svd_loss(F + 1e-6 * d, w) - _svd_loss(F - 1e-6 * d, w)) / 2e-6
            worst = max(worst, abs(fd - np.sum(G * d)) / max(abs(fd), 1e-12))
    report("SVD backward vs finite differences", max_rel_error=worst)
    assert worst < 1e-6


@ti.kernel
def _advance_loss(p: ti.types.ndarray(), R: ti.types.ndarray(), v: ti.types.ndarray(), w: ti.types.ndarray(),
                  dt: ti.f64, g: ti.types.ndarray(), out: ti.types.ndarray()):
    """out[n] = ḡ_p·p' + ḡ_R∘R' for pose n advanced by tools.advance_pose."""
    for n in range(p.shape[0]):
        p1, R1 = tools.advance_pose(ti.Vector([p[n, i] for i in ti.static(range(3))]),
                                    ti.Matrix([[R[n, i, j] for j in ti.static(range(3))] for i in ti.static(range(3))]),
                                    ti.Vector([v[n, i] for i in ti.static(range(3))]),
                                    ti.Vector([w[n, i] for i in ti.static(range(3))]), dt)
        acc = 0.0
        for i in ti.static(range(3)):
            acc += g[n, 0, i] * p1[i]
            for j in ti.static(range(3)):
                acc += g[n, 1 + i, j] * R1[i, j]
        out[n] = acc


@ti.kernel
def _advance_adjoint(R: ti.types.ndarray(), w: ti.types.ndarray(), dt: ti.f64, g: ti.types.ndarray(),
                     out: ti.types.ndarray()):
    """out[n] = (p̄; R̄; v̄; ω̄) of tools.advance_pose_adjoint, rows 0, 1-3, 4, 5."""
    for n in range(R.shape[0]):
        g_p, g_R, g_v, g_w = tools.advance_pose_adjoint(
            ti.Matrix([[R[n, i, j] for j in ti.static(range(3))] for i in ti.static(range(3))]),
            ti.Vector([w[n, i] for i in ti.static(range(3))]), dt,
            ti.Vector([g[n, 0, i] for i in ti.static(range(3))]),
            ti.Matrix([[g[n, 1 + i, j] for j in ti.static(range(3))] for i in ti.static(range(3))]))
        for i in ti.static(range(3)):
            out[n, 0, i] = g_p[i]
            out[n, 4, i] = g_v[i]
            out[n, 5, i] = g_w[i]
            for j in ti.static(range(3)):
                out[n, 1 + i, j] = g_R[i, j]


def test_tool_advance_adjoint_matches_finite_differences(model):
    """L = ḡ_p·p' + ḡ_R∘R' of the tools' advance p' = p + Δt v, R' = exp([ω]× Δt) R: the hand-written adjoint
    (tools.advance_pose_adjoint, which the differentiable solver uses instead of Taichi's reverse mode) against
    central differences, at rotation angles t = |ω| Δt from 1e-6 (the forward's series) across 0.1 (where the
    adjoint's coefficients leave their series) to 2.5 rad. L is linear in p, v, R (a step of 1 is exact but for
    rounding); in ω a step of 1e-4 rad/s moves t by 1e-7 (truncation about 1e-14 relative)."""
    rng = np.random.default_rng(3)
    dt = 1e-3
    angles = np.array([1e-6, 1e-4, 3e-3, 0.05, 0.0999, 0.1001, 0.5, 2.5])
    n = len(angles)
    axes = rng.normal(size=(n, 3))
    values = {"p": rng.normal(size=(n, 3)), "R": Rotation.random(n, random_state=4).as_matrix(),
              "v": rng.normal(size=(n, 3)), "w": axes / np.linalg.norm(axes, axis=1)[:, None] * (angles / dt)[:, None]}
    g = rng.normal(size=(n, 4, 3))

    def loss(vals):
        out = np.zeros(n)
        _advance_loss(vals["p"], vals["R"], vals["v"], vals["w"], dt, g, out)
        return out

    adj = np.zeros((n, 6, 3))
    _advance_adjoint(values["R"], values["w"], dt, g, adj)
    grads = {"p": adj[:, 0], "R": adj[:, 1:4], "v": adj[:, 4], "w": adj[:, 5]}
    _check("tools' advance adjoint vs finite differences", loss, values, grads, rng,
           steps={"p": 1.0, "R": 1.0, "v": 1.0, "w": 1e-4})


# --- the constitutive models' hand-written backwards ------------------------------------------------------------
# Parameters per model (SI), chosen so that each branch of the model is taken by some samples: the box yield's
# clamp and the von Mises return mapping act on the larger strains below and not on the smaller.
MODEL_PARAMS = {
    "fixed_corotated": {"mu": 3e4, "lam": 5e4},
    "corotated_box_yield": {"mu": 3e4, "lam": 5e4, "yield_compression": 0.05, "yield_stretch": 0.03},
    "von_mises": {"mu": 3e4, "lam": 5e4, "yield_stress": 2e3},
    "liquid": {"lam": 2e5},
    "viscous_liquid": {"lam": 2e5, "eta": 3.0},
    "damped_liquid": {"lam": 2e5, "zeta": 5.0},
    "rigid": {"lam": 2e5},
}
M_SAMPLES = 12


def _model_kernels(cm):
    """Kernels for registered model `cm`: its loss L = Σ ⟨a, F_new⟩ + ⟨b, τ⟩ / μ₀ per sample, and its backward."""
    prm_type = ti.types.struct(**{name: ti.f64 for name in cm.params})

    @ti.func
    def mat(A: ti.template(), n, off: ti.template()):
        return ti.Matrix([[A[n, off, i, j] for j in ti.static(range(3))] for i in ti.static(range(3))])

    prm = prm_type.field(shape=())
    prm[None] = MODEL_PARAMS[cm.name]

    @ti.kernel
    def loss(X: ti.types.ndarray(), W: ti.types.ndarray(), out: ti.types.ndarray()):
        for n in range(X.shape[0]):
            F_new, tau = cm.func(mat(X, n, 0), mat(X, n, 1), prm[None], mat(X, n, 2), mat(X, n, 3), mat(X, n, 4))
            out[n] = (mat(W, n, 0) * F_new).sum() + (mat(W, n, 1) * tau).sum() / 1e4

    @ti.kernel
    def backward(X: ti.types.ndarray(), W: ti.types.ndarray(), out: ti.types.ndarray()):
        for n in range(X.shape[0]):
            grads = cm.backward(mat(X, n, 0), mat(X, n, 1), prm[None], mat(X, n, 2), mat(X, n, 3), mat(X, n, 4),
                                mat(W, n, 0), mat(W, n, 1) / 1e4)
            for g in ti.static(range(5)):
                for i, j in ti.static(ti.ndrange(3, 3)):
                    out[n, g, i, j] = grads[g][i, j]

    return loss, backward


def _model_inputs(rng):
    """(M_SAMPLES, 5, 3, 3): F, C, U, Σ, V per sample; half the samples strained by 1 %, half by 12 %."""
    X = np.zeros((M_SAMPLES, 5, 3, 3))
    for n in range(M_SAMPLES):
        strain = 0.01 if n % 2 else 0.12
        X[n, 0] = np.eye(3) + strain * rng.normal(size=(3, 3))
        X[n, 1] = 5.0 * rng.normal(size=(3, 3))
        X[n, 2] = Rotation.random(random_state=rng.integers(1 << 30)).as_matrix()
        X[n, 3] = np.diag(1.0 + strain * rng.normal(size=3))
        X[n, 4] = Rotation.random(random_state=rng.integers(1 << 30)).as_matrix()
    return X


@pytest.mark.parametrize("name", list(MODEL_PARAMS))
def test_constitutive_backward_matches_finite_differences(model, name):
    """Each built-in model's hand-written backward (constitutive.backward_of), which the differentiable solver
    uses instead of Taichi's reverse mode, against central differences of its forward function in F, C, U, Σ
    and V taken as independent inputs (as the solver's SVD backward takes them), in random directions, at small
    and large strains. A step of 1e-6 on O(1) inputs (truncation about 1e-12 relative); of 1 in C, in which
    every built-in model is linear (with 1e-6 the viscous terms, 1e-4 of the loss, read 1.5e-5 of round-off). The clamps' kinks (box
    yield, the stretch floor, the yield surface) are met with probability about 1e-5 per sample."""
    cm = constitutive.get(name)
    assert cm.backward is not None
    loss_kernel, backward_kernel = _model_kernels(cm)
    rng = np.random.default_rng(5)
    X = _model_inputs(rng)
    W = rng.normal(size=(M_SAMPLES, 2, 3, 3))
    G = np.zeros((M_SAMPLES, 5, 3, 3))
    backward_kernel(X, W, G)
    names = ("F", "C", "U", "sig", "V")

    def loss(vals):
        out = np.zeros(M_SAMPLES)
        loss_kernel(np.ascontiguousarray(np.stack([vals[k] for k in names], axis=1)), W, out)
        return out

    # the built-in models are linear in C (the viscous stresses): a step of 1 there
    _check(f"{name} backward vs finite differences", loss, {k: X[:, i] for i, k in enumerate(names)},
           {k: G[:, i] for i, k in enumerate(names)}, rng, steps={"F": 1e-6, "C": 1.0, "U": 1e-6, "sig": 1e-6, "V": 1e-6},
           tol=1e-6, masks={"sig": np.eye(3)}, floor=1e-6)
