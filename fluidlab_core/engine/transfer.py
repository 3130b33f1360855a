"""Particle–grid transfers of MLS-MPM (APIC, quadratic B-splines) and their hand-written backwards.

One substep of length Δt (Hu et al. 2018, "A moving least squares material point method"; Jiang et al.
2015 for APIC), SI units:
    P2G   F_trial = (I + Δt C_p) F_p;  (F_p, τ_p) ← model(F_trial, C_p)               (constitutive.py)
          A_p = −Δt V⁰_p (4/Δx²) τ_p + m_p C_p
          m_i += w_ip m_p,  (mv)_i += w_ip (m_p v_p + A_p (x_i − x_p))
    grid  v_i from m_i, (mv)_i and the boundary conditions                             (grid.py)
    G2P   v_p = Σ w_ip v_i,  C_p = (4/Δx²) Σ w_ip v_i (x_i − x_p)ᵀ,  x_p ← x_p + Δt v_p

AFLIP (Fei et al. 2021, "Revisiting integration in the material point method", §4), for the liquids' particles
when the Scene's `flip` α > 0 (forward solver only). APIC's round trip v_p → grid → v_p keeps only the part of
the particles' velocities that the grid's affine fit holds; the rest is smoothed away at every transfer, a
numerical viscosity that grows with the number of substeps. AFLIP gives a share α of it back:
    P2G   also (mv⁰)_i += w_ip m_p (v_p + C_p (x_i − x_p)),  v⁰_i = (mv⁰)_i / m_i   (the transfer alone, no stress)
    G2P   v_PIC = Σ w_ip v_i,  C_p as APIC,  x_p ← x_p + Δt v_PIC            (positions advected by PIC)
          v_p ← v_PIC + α (v_p − Σ w_ip v⁰_i)                                 (FLIP's increment, share α)
α = 0 is APIC; α → 1 is FLIP with APIC's affine part, which keeps modes the grid cannot see (noise) and
needs a little PIC (α ≤ 0.99). Cost: a second momentum scatter and a velocity gather (bench/transfer_remedies.py).

J-bar, for the liquids' particles when the Scene's `jbar` is set (forward solver only): before each substep the
particles' J = det F is averaged through the grid and each liquid particle's F rescaled to it,
    J_i = Σ_p w_ip m_p J_p / Σ_p w_ip m_p,   J̄_p = Σ_i w_ip J_i,   F_p ← (J̄_p / J_p)^(1/3) F_p,
which removes the particle-to-particle pattern of J that a divergence-free flow otherwise builds up (J is
integrated from the grid's divergence, tr C, which depends on where a particle sits between the nodes; docs/engine.md,
"the vortex's decay and the liquid's J") and keeps the patterns the grid resolves.
`jbar="affine"` fits J at each node by weighted least squares, J ≈ c₀ + c·(x − x_i)/Δx with the normal equations
Σ_p w_ip m_p φ φᵀ c = Σ_p w_ip m_p J_p φ, φ = (1, (x_p − x_i)/Δx) (solved in float64; a node whose particles do not
span the three axes keeps the plain mean), and reads J̄_p = Σ_i w_ip (c₀ + c·(x_p − x_i)/Δx): exact for a J linear in
x, also where the liquid ends (the plain mean is not, which bends the hydrostatic pressure); Σ m J is kept by the
fit's first equation. Its scatter is atomic on every backend for now (20 numbers a node; slower on the CPU).

Scatter targets: on the CPU each thread scatters its share of particles into a grid copy of its own
(`private`: plain read-modify-writes, no atomic float adds, which are compare-and-swap loops on x64 and cost
~88 % of a substep) and the copies are summed per node (`reduce_copies`); on a GPU the scatter is atomic.
Sums over copies in a fixed order also make the differentiable solver's gradients the same run to run.

Backwards by hand, next to what they differentiate (Taichi's reverse of the unrolled P2G adds atomically
into every particle gradient at every node, and its reverse of the gather cost ~5× the gather):
`p2g_backward` and `gather_backward` (formulas in their docstrings). tests/test_transfer_backward.py checks
each against central differences of the forward function on random inputs in float64 (it compared them with
Taichi's autodiff until 2026-12-06, which agreed to 1e-10 but took minutes to compile).

Every function takes the Model (model.py) as a template argument; both solvers call them.
"""

import taichi as ti

from fluidlab_core.engine import svd as svd3
from fluidlab_core.engine.grid import stencil


@ti.func
def trial_strain(model: ti.template(), C, F):
    """F_trial = (I + Δt C) F, the deformation gradient before the constitutive model."""
    return (ti.Matrix.identity(float, 3) + model.dt * C) @ F


@ti.func
def needs_svd(model: ti.template(), p):
    """Whether particle p's constitutive model reads the SVD of F_trial."""
    need = False
    for k in ti.static(model.svd_models):
        if model.model[p] == k:
            need = True
    return need


@ti.func
def is_fluid(model: ti.template(), p):
    """Whether particle p moves with the fluids' velocity field (grid.py: two velocity fields)."""
    out = False
    for k in ti.static(model.fluid_models):
        if model.model[p] == k:
            out = True
    return out


@ti.func
def stress(model: ti.template(), p, F_trial, C):
    """(F_new, τ) of particle p's constitutive model, unrolled over the models present. The SVD is computed at
    one place for every model that needs it: one inlined copy per model made a scene with three such models
    (elastic, two plastics) compile three SVDs into each substep kernel (a float64 forward kernel took 211 s
    to compile, most of it the copies)."""
    Fp = F_trial
    tau = ti.Matrix.zero(float, 3, 3)
    U = ti.Matrix.zero(float, 3, 3)
    sig = ti.Matrix.zero(float, 3, 3)
    V = ti.Matrix.zero(float, 3, 3)
    if ti.static(len(model.svd_models) > 0):
        if needs_svd(model, p):
            U, sig, V = svd3.svd(F_trial)
    for k in ti.static(range(len(model.constitutive))):
        if model.model[p] == k:
            Fp, tau = model.constitutive[k].func(F_trial, C, model.params[k][model.material[p]], U, sig, V)
    return Fp, tau


@ti.func
def stress_factor(model: ti.template(), p):
    """k_τ = −Δt V⁰ 4/Δx²: A = k_τ τ + m C."""
    return -model.dt * model.rest_volume[p] * 4.0 * model.inv_dx * model.inv_dx


@ti.func
def scatter(model: ti.template(), target_m: ti.template(), target_mv: ti.template(), c, private: ti.template(),
            xp, vp, Cp, tau, p):
    """P2G of particle p at xp with velocity vp, affine velocity Cp and stress τ: into grid copy c of the
    `private` targets (fields with a leading copy axis) or atomically into the grid."""
    base, fx, w = stencil(model, xp)
    mp = model.mass[p]
    affine = stress_factor(model, p) * tau + mp * Cp
    momentum = mp * vp
    for offset in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
        dpos = (offset - fx) * model.dx
        weight = w[offset[0]][0] * w[offset[1]][1] * w[offset[2]][2]
        if ti.static(private):
            i, j, k = base[0] + offset[0], base[1] + offset[1], base[2] + offset[2]
            target_mv[c, i, j, k] = target_mv[c, i, j, k] + weight * (momentum + affine @ dpos)
            target_m[c, i, j, k] = target_m[c, i, j, k] + weight * mp
        else:
            target_mv[base + offset] += weight * (momentum + affine @ dpos)
            target_m[base + offset] += weight * mp


@ti.func
def scatter_momentum(model: ti.template(), target_mv: ti.template(), c, private: ti.template(), xp, vp, Cp, p):
    """AFLIP's transfer momentum of particle p: w m_p (v_p + C_p (x_i − x_p)), without the stress."""
    base, fx, w = stencil(model, xp)
    mp = model.mass[p]
    affine = mp * Cp
    momentum = mp * vp
    for offset in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
        dpos = (offset - fx) * model.dx
        weight = w[offset[0]][0] * w[offset[1]][1] * w[offset[2]][2]
        if ti.static(private):
            i, j, k = base[0] + offset[0], base[1] + offset[1], base[2] + offset[2]
            target_mv[c, i, j, k] = target_mv[c, i, j, k] + weight * (momentum + affine @ dpos)
        else:
            target_mv[base + offset] += weight * (momentum + affine @ dpos)


@ti.func
def scatter_scalar(model: ti.template(), target: ti.template(), c, private: ti.template(), xp, value):
    """w_ip value onto the nodes of the stencil at xp (J-bar's m_p J_p and m_p)."""
    base, fx, w = stencil(model, xp)
    for offset in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
        weight = w[offset[0]][0] * w[offset[1]][1] * w[offset[2]][2]
        if ti.static(private):
            i, j, k = base[0] + offset[0], base[1] + offset[1], base[2] + offset[2]
            target[c, i, j, k] = target[c, i, j, k] + weight * value
        else:
            target[base + offset] += weight * value


@ti.func
def gather_scalar(model: ti.template(), field: ti.template(), xp):
    """Σ w_ip f_i at position xp."""
    base, fx, w = stencil(model, xp)
    out = 0.0
    for offset in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
        weight = w[offset[0]][0] * w[offset[1]][1] * w[offset[2]][2]
        out += weight * field[base + offset]
    return out


@ti.func
def scatter_volume(model: ti.template(), target: ti.template(), c, private: ti.template(), xp, vol):
    """The particle volume vol (m³) at xp onto the nodes of its stencil (the contact test of grid.py)."""
    base, fx, w = stencil(model, xp)
    for offset in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
        weight = w[offset[0]][0] * w[offset[1]][1] * w[offset[2]][2]
        if ti.static(private):
            i, j, k = base[0] + offset[0], base[1] + offset[1], base[2] + offset[2]
            target[c, i, j, k] = target[c, i, j, k] + weight * vol
        else:
            target[base + offset] += weight * vol


@ti.func
def reduce_scalar_copies(copies: ti.template(), n_copies: ti.template(), I):
    """Node I of a scalar field summed over its grid copies, which are zeroed for the next substep."""
    out = 0.0
    for c in range(n_copies):
        out += copies[c, I[0], I[1], I[2]]
        copies[c, I[0], I[1], I[2]] = 0.0
    return out


@ti.func
def reduce_copies(copies_m: ti.template(), copies_mv: ti.template(), n_copies: ti.template(), I):
    """Node I's mass and momentum summed over the grid copies, which are zeroed for the next substep."""
    m = 0.0
    mv = ti.Vector.zero(float, 3)
    for c in range(n_copies):
        m += copies_m[c, I[0], I[1], I[2]]
        mv += copies_mv[c, I[0], I[1], I[2]]
        copies_m[c, I[0], I[1], I[2]] = 0.0
        copies_mv[c, I[0], I[1], I[2]] = ti.Vector.zero(float, 3)
    return m, mv


@ti.func
def reduce_vector_copies(copies: ti.template(), n_copies: ti.template(), I):
    """Node I of a vector field summed over its grid copies, which are zeroed for the next substep."""
    out = ti.Vector.zero(float, 3)
    for c in range(n_copies):
        out += copies[c, I[0], I[1], I[2]]
        copies[c, I[0], I[1], I[2]] = ti.Vector.zero(float, 3)
    return out


@ti.func
def gather_velocity(model: ti.template(), grid_v: ti.template(), xp):
    """Σ w_ip v_i at position xp (AFLIP's grid velocity before the update)."""
    base, fx, w = stencil(model, xp)
    out = ti.Vector.zero(float, 3)
    for offset in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
        weight = w[offset[0]][0] * w[offset[1]][1] * w[offset[2]][2]
        out += weight * grid_v[base + offset]
    return out


@ti.func
def gather(model: ti.template(), grid_v: ti.template(), xp):
    """G2P's gather at position xp: v_p = Σ w_ip v_i and C_p = (4/Δx²) Σ w_ip v_i (x_i − x_p)ᵀ."""
    base, fx, w = stencil(model, xp)
    new_v = ti.Vector.zero(float, 3)
    new_C = ti.Matrix.zero(float, 3, 3)
    for offset in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
        dpos = offset - fx
        weight = w[offset[0]][0] * w[offset[1]][1] * w[offset[2]][2]
        g_v = grid_v[base + offset]
        new_v += weight * g_v
        new_C += (4.0 * model.inv_dx * weight) * g_v.outer_product(dpos)
    return new_v, new_C


@ti.func
def p2g_backward(model: ti.template(), grid_m_grad: ti.template(), grid_mv_grad: ti.template(), xp, vp, Cp,
                 tau, p):
    """Backward of `scatter` for particle p. With f the stencil offset, d_i = (offset − f) Δx,
    G_i = ∂L/∂(mv)_i and g_i = ∂L/∂m_i:
        ḡ = Σ_i w G_i,  ∂L/∂v = m ḡ,  ∂L/∂A = Σ_i w G_i d_iᵀ → ∂L/∂τ = k_τ ∂L/∂A, ∂L/∂C = m ∂L/∂A
        ∂L/∂f = Σ_i (G_i·(m v + A d_i) + m g_i) ∇_f w − Δx Aᵀ ḡ,  ∂L/∂x = ∂L/∂f / Δx
    with the quadratic B-spline derivatives w₀' = f − 1.5, w₁' = −2(f − 1), w₂' = f − 0.5.
    Returns (∂L/∂x, ∂L/∂v, ∂L/∂C, ∂L/∂τ).

    The stencil loop is nested by axis, with d_i split into a per-particle part and the integer offset:
    m v + A d_i = q + Δx A offset with q = m v − Δx A f, and Σ_i w G_i d_iᵀ = Δx (Σ_i w G_i offsetᵀ − ḡ fᵀ)
    (measured 20 % faster than the flat loop)."""
    base, fx, w = stencil(model, xp)
    mp = model.mass[p]
    k_tau = stress_factor(model, p)
    affine = k_tau * tau + mp * Cp
    momentum = mp * vp
    dw = [fx - 1.5, -2.0 * (fx - 1.0), fx - 0.5]
    A_dx = model.dx * affine
    q = momentum - A_dx @ fx
    g_mom = ti.Vector.zero(float, 3)
    g_off = ti.Matrix.zero(float, 3, 3)  # Σ_i w G_i offsetᵀ
    g_f = ti.Vector.zero(float, 3)
    for a in ti.static(range(3)):
        q_a = q + a * A_dx[:, 0]
        for b in ti.static(range(3)):
            w_ab = w[a][0] * w[b][1]
            dw_a, dw_b = dw[a][0] * w[b][1], w[a][0] * dw[b][1]
            q_ab = q_a + b * A_dx[:, 1]
            for c in ti.static(range(3)):
                I = base + ti.Vector([a, b, c])
                G = grid_mv_grad[I]
                wG = (w_ab * w[c][2]) * G
                g_mom += wG
                for d, o in ti.static(enumerate((a, b, c))):
                    if ti.static(o > 0):
                        g_off[:, d] += o * wG
                g_weight = G.dot(q_ab + c * A_dx[:, 2]) + grid_m_grad[I] * mp
                g_f += g_weight * ti.Vector([dw_a * w[c][2], dw_b * w[c][2], w_ab * dw[c][2]])
    g_A = model.dx * (g_off - g_mom.outer_product(fx))
    g_f -= model.dx * (affine.transpose() @ g_mom)
    return model.inv_dx * g_f, mp * g_mom, mp * g_A, k_tau * g_A


@ti.func
def gather_backward(model: ti.template(), stored_v: ti.template(), s, target: ti.template(), c,
                    private: ti.template(), xp, v_gathered, g_x, g_v, g_C):
    """Backward of `gather` followed by the advection x + Δt v, for a particle at xp whose gather gave
    v_gathered. With X = (x − origin)/Δx, f = X − base, weights w = w₀(f₀) w₁(f₁) w₂(f₂) and d = offset − f:
        x_new = x + Δt v,  v = Σ w g_i,  C = (4/Δx) Σ w g_i dᵀ
    so, with ḡv = ∂L/∂v + Δt ∂L/∂x_new (g_v, g_x) and Ḡ = ∂L/∂C (g_C):
        ∂L/∂g_i += w (ḡv + (4/Δx) Ḡ d)         into grid copy c of `target` (or atomically into it)
        ∂L/∂f   = Σ_i [g_i·(ḡv + (4/Δx) Ḡ d) ∇_f w − (4/Δx) w Ḡᵀ g_i]
        ∂L/∂x   = ∂L/∂x_new + ∂L/∂f / Δx      (the second term is returned)
    with the node velocities g_i = stored_v[s, i] (substep s's, kept by the forward). Nested by axis as
    p2g_backward, with h = ḡv + (4/Δx) Ḡ (offset − f) built up axis by axis."""
    base, fx, w = stencil(model, xp)
    gv = g_v + model.dt * g_x
    dw = [fx - 1.5, -2.0 * (fx - 1.0), fx - 0.5]
    gC4 = 4.0 * model.inv_dx * g_C
    h0 = gv - gC4 @ fx
    gf = ti.Vector.zero(float, 3)
    for a in ti.static(range(3)):
        h_a = h0 + a * gC4[:, 0]
        for b in ti.static(range(3)):
            w_ab = w[a][0] * w[b][1]
            dw_a, dw_b = dw[a][0] * w[b][1], w[a][0] * dw[b][1]
            h_ab = h_a + b * gC4[:, 1]
            for cc in ti.static(range(3)):
                h = h_ab + cc * gC4[:, 2]
                i, j, k = base[0] + a, base[1] + b, base[2] + cc
                g_i = stored_v[s, i, j, k]
                weight = w_ab * w[cc][2]
                if ti.static(private):
                    target[c, i, j, k] = target[c, i, j, k] + weight * h
                else:
                    target[i, j, k] += weight * h
                gf += g_i.dot(h) * ti.Vector([dw_a * w[cc][2], dw_b * w[cc][2], w_ab * dw[cc][2]])
    gf -= gC4.transpose() @ v_gathered  # Σ_i w g_i = v
    return model.inv_dx * gf
