"""The hand-written backwards against Taichi's autodiff of the same forward functions, on random inputs, float64.

engine/transfer.py differentiates P2G's scatter and G2P's gather by hand (Taichi's reverse of them is slow, and
its reverse of the per-thread-copy scatter does not exist). Each backward is checked here against Taichi's
reverse mode of the forward function it differentiates, written with atomic scatters so that autodiff applies:
every gradient must agree to 1e-10 relative. The SVD's backward (engine/svd.py), which Taichi cannot derive
(ti.svd iterates), is checked against central finite differences instead.
"""
import numpy as np
import pytest
import taichi as ti

import fluidlab_core as fl
from tests import conftest
from fluidlab_core import materials as M
from fluidlab_core.engine import svd as svd3
from fluidlab_core.engine import transfer
from tests.conftest import report

N = 40  # random particles
TOL = 1e-10
backward_svd = svd3.make_backward_svd(1e-10)


@pytest.fixture(scope="module")
def model():
    conftest.init("f64")
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.08, 0.06), grid_res=10, dt=1e-3, substeps=20)
    scene.add_particles(fl.Box((0.02, 0.02, 0.02), (0.08, 0.06, 0.04)), M.WATER, name="water")
    yield scene.build().model
    conftest.init("f32")


def _fields(model, rng):
    """Random particles inside the domain with random velocity, affine velocity and stress."""
    def vec(values):
        f = ti.Vector.field(values.shape[-1], ti.f64, shape=N, needs_grad=True)
        f.from_numpy(values)
        return f

    def mat(values):
        f = ti.Matrix.field(3, 3, ti.f64, shape=N, needs_grad=True)
        f.from_numpy(values)
        return f

    lo, hi = np.array(model.lower) + 0.01, np.array(model.upper) - 0.01
    x = vec(rng.uniform(lo, hi, size=(N, 3)))
    v = vec(rng.normal(scale=0.3, size=(N, 3)))
    C = mat(rng.normal(scale=5.0, size=(N, 3, 3)))
    tau = mat(rng.normal(scale=1e3, size=(N, 3, 3)))
    return x, v, C, tau


def _grid(model, n, needs_grad=True):
    if n == 1:
        return ti.field(ti.f64, shape=model.grid_shape, needs_grad=needs_grad)
    return ti.Vector.field(n, ti.f64, shape=model.grid_shape, needs_grad=needs_grad)


@ti.kernel
def _p2g(model: ti.template(), x: ti.template(), v: ti.template(), C: ti.template(), tau: ti.template(),
         grid_m: ti.template(), grid_mv: ti.template()):
    for p in range(N):
        transfer.scatter(model, grid_m, grid_mv, 0, False, x[p], v[p], C[p], tau[p], p)


@ti.kernel
def _grid_loss(grid_m: ti.template(), grid_mv: ti.template(), a: ti.template(), b: ti.template(),
               loss: ti.template()):
    for I in ti.grouped(grid_m):
        loss[None] += a[I].dot(grid_mv[I]) + b[I] * grid_m[I]


@ti.kernel
def _p2g_by_hand(model: ti.template(), x: ti.template(), v: ti.template(), C: ti.template(), tau: ti.template(),
                 a: ti.template(), b: ti.template(), out: ti.types.ndarray()):
    for p in range(N):
        gx, gv, gC, gtau = transfer.p2g_backward(model, b, a, x[p], v[p], C[p], tau[p], p)
        for i in ti.static(range(3)):
            out[p, 0, i], out[p, 1, i] = gx[i], gv[i]
            for j in ti.static(range(3)):
                out[p, 2 + i, j], out[p, 5 + i, j] = gC[i, j], gtau[i, j]


def _rel(hand, auto):
    return float(np.abs(hand - auto).max() / max(np.abs(auto).max(), 1e-300))


def test_p2g_backward_matches_autodiff(model):
    """L = Σ_i a_i·(mv)_i + b_i m_i after P2G: ∂L/∂x, ∂L/∂v, ∂L/∂C and ∂L/∂τ by hand (transfer.p2g_backward)
    against Taichi's reverse of transfer.scatter (atomic)."""
    rng = np.random.default_rng(0)
    x, v, C, tau = _fields(model, rng)
    grid_m, grid_mv = _grid(model, 1), _grid(model, 3)
    a, b = _grid(model, 3, False), _grid(model, 1, False)
    a.from_numpy(rng.normal(size=model.grid_shape + (3,)))
    b.from_numpy(rng.normal(size=model.grid_shape))
    loss = ti.field(ti.f64, shape=(), needs_grad=True)
    with ti.ad.Tape(loss=loss):
        _p2g(model, x, v, C, tau, grid_m, grid_mv)
        _grid_loss(grid_m, grid_mv, a, b, loss)
    out = np.zeros((N, 8, 3))
    _p2g_by_hand(model, x, v, C, tau, a, b, out)
    errors = {"x": _rel(out[:, 0], x.grad.to_numpy()), "v": _rel(out[:, 1], v.grad.to_numpy()),
              "C": _rel(out[:, 2:5], C.grad.to_numpy()), "tau": _rel(out[:, 5:8], tau.grad.to_numpy())}
    report("P2G backward vs autodiff", **errors)
    assert max(errors.values()) < TOL, errors
    assert np.abs(x.grad.to_numpy()).max() > 0 and np.abs(tau.grad.to_numpy()).max() > 0  # exercised


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


def test_gather_backward_matches_autodiff(model):
    """L = Σ_p a_p·(x_p + Δt v_p) + b_p·v_p + c_p:C_p after G2P: ∂L/∂x and ∂L/∂v_i by hand
    (transfer.gather_backward, reading the node velocities from a time-indexed store as the differentiable
    solver does) against Taichi's reverse of transfer.gather."""
    rng = np.random.default_rng(1)
    x, _, _, _ = _fields(model, rng)
    grid_v = _grid(model, 3)
    values = rng.normal(scale=0.5, size=model.grid_shape + (3,))
    grid_v.from_numpy(values)
    stored_v = ti.Vector.field(3, ti.f64, shape=(1,) + tuple(model.grid_shape))
    stored_v.from_numpy(values[None])
    a, b = (ti.Vector.field(3, ti.f64, shape=N) for _ in range(2))
    c = ti.Matrix.field(3, 3, ti.f64, shape=N)
    a.from_numpy(rng.normal(size=(N, 3)))
    b.from_numpy(rng.normal(size=(N, 3)))
    c.from_numpy(rng.normal(size=(N, 3, 3)))
    loss = ti.field(ti.f64, shape=(), needs_grad=True)
    with ti.ad.Tape(loss=loss):
        _g2p(model, x, grid_v, a, b, c, loss)
    grid_grad = _grid(model, 3, False)
    out = np.zeros((N, 3))
    _g2p_by_hand(model, x, grid_v, stored_v, a, b, c, grid_grad, out)
    errors = {"x": _rel(out, x.grad.to_numpy()), "grid_v": _rel(grid_grad.to_numpy(), grid_v.grad.to_numpy())}
    report("gather backward vs autodiff", **errors)
    assert max(errors.values()) < TOL, errors


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
