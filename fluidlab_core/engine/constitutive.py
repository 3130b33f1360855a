"""Constitutive models: one Taichi hook per model, returning the projected F and the Kirchhoff stress.

Notation: F deformation gradient (after the substep update F ← (I + Δt C) F), C the APIC affine velocity
(≈ ∇v, 1/s), J = det F, F = U Σ Vᵀ its SVD, R = U Vᵀ. Parameters (μ, λ, y1, y2, η) come from
`Material.kernel_params()` (Pa, Pa, model-specific, model-specific, Pa·s). Every model returns Kirchhoff
stress τ = J σ (Pa), which P2G multiplies by the rest volume V⁰.

- fixed_corotated (elastic):            τ = 2μ (F − R) Fᵀ + λ J (J − 1) I              [Stomakhin 2012]
- rigid (between projections):          τ = λ J (J − 1) I; rigid.py keeps F = R J^(1/3)
- corotated_box_yield (plastic):        Σ ← clamp(Σ, 1 − y1, 1 + y2), F ← U Σ Vᵀ, then fixed-corotated
                                                                                        [Stomakhin 2013]
- von_mises (ice cream, plasticine):    ε = ln Σ, ε̂ = dev ε; if |ε̂| > sqrt(2/3)·σ_y/(2μ) project ε̂ onto
                                        the yield surface (perfect plasticity), F ← U exp(ε) Vᵀ,
                                        τ = U (2μ ε + λ tr(ε) I) Uᵀ          [Klár 2016, Huang 2021]
- liquid (weakly compressible):         J ← det F, F ← J^(1/3) I, τ = λ J (J − 1) I, i.e. pressure
                                        p = −λ (J − 1)                          [Tampubolon 2017, FluidLab]
- viscous_liquid:                       liquid + τ_v = η J (C + Cᵀ − ⅔ tr(C) I) = 2 η J dev(sym ∇v)

The solver unrolls the models present in a scene with `ti.static`, so a scene of liquids never pays for an
SVD. Every model takes the SVD of F as arguments (U, sig, V; zero matrices for models in `NO_SVD`), so that
the differentiable solver can compute it in a kernel of its own whose gradient is written by hand
(svd.py) while the forward solver computes it inline.
"""
from __future__ import annotations

import taichi as ti

from fluidlab_core.engine import svd as svd3

# Singular values below this are clamped before a logarithm (an inverted or crushed element).
_MIN_STRETCH = 0.05


@ti.func
def fixed_corotated(F, C, prm, U, sig, V):
    """Elastic: F unchanged, fixed-corotated Kirchhoff stress."""
    R = U @ V.transpose()
    J = F.determinant()
    tau = 2.0 * prm[0] * (F - R) @ F.transpose() + ti.Matrix.identity(float, 3) * (prm[1] * J * (J - 1.0))
    return F, tau


@ti.func
def corotated_box_yield(F, C, prm, U, sig, V):
    """Plastic: clamp principal stretches to [1 - y1, 1 + y2], then fixed-corotated stress."""
    # clamped stretches built as a new matrix: Taichi's reverse mode mishandles element writes to a local
    s = ti.Vector([ti.min(ti.max(sig[d, d], 1.0 - prm[2]), 1.0 + prm[3]) for d in ti.static(range(3))])
    Fp = U @ ti.Matrix([[s[0], 0.0, 0.0], [0.0, s[1], 0.0], [0.0, 0.0, s[2]]]) @ V.transpose()
    R = U @ V.transpose()
    J = s[0] * s[1] * s[2]
    tau = 2.0 * prm[0] * (Fp - R) @ Fp.transpose() + ti.Matrix.identity(float, 3) * (prm[1] * J * (J - 1.0))
    return Fp, tau


@ti.func
def von_mises(F, C, prm, U, sig, V):
    """Hencky-strain St. Venant–Kirchhoff with von Mises return mapping (uniaxial yield stress y1)."""
    mu, lam = prm[0], prm[1]
    eps = ti.Vector([ti.log(ti.max(ti.abs(sig[d, d]), _MIN_STRETCH)) for d in ti.static(range(3))])
    eps_hat = eps - eps.sum() / 3.0
    eps_hat_norm = ti.sqrt(eps_hat.dot(eps_hat) + 1e-30)  # finite derivative at 0
    yield_strain = ti.sqrt(2.0 / 3.0) * prm[2] / (2.0 * mu)
    # return mapping without a branch (Taichi's reverse mode mishandles a local updated inside one)
    eps = eps - ti.max(0.0, 1.0 - yield_strain / eps_hat_norm) * eps_hat
    Fp = U @ ti.Matrix([[ti.exp(eps[0]), 0.0, 0.0], [0.0, ti.exp(eps[1]), 0.0], [0.0, 0.0, ti.exp(eps[2])]]) \
        @ V.transpose()
    s = 2.0 * mu * eps + lam * eps.sum()
    tau = U @ ti.Matrix([[s[0], 0.0, 0.0], [0.0, s[1], 0.0], [0.0, 0.0, s[2]]]) @ U.transpose()
    return Fp, tau


@ti.func
def liquid(F, C, prm, U, sig, V):
    """Weakly compressible liquid: keep only the volume part of F; pressure from J."""
    J = F.determinant()
    Fp = ti.Matrix.identity(float, 3) * ti.pow(ti.max(J, 1e-6), 1.0 / 3.0)
    tau = ti.Matrix.identity(float, 3) * (prm[1] * J * (J - 1.0))
    return Fp, tau


@ti.func
def viscous_liquid(F, C, prm, U, sig, V):
    """Liquid plus deviatoric Newtonian viscous stress."""
    Fp, tau = liquid(F, C, prm, U, sig, V)
    J = F.determinant()
    tau += prm[4] * J * (C + C.transpose() - (2.0 / 3.0) * C.trace() * ti.Matrix.identity(float, 3))
    return Fp, tau


@ti.func
def rigid(F, C, prm, U, sig, V):
    """Rigid body particle: F is set by the rigid projection; only its volume change is resisted."""
    J = F.determinant()
    return F, ti.Matrix.identity(float, 3) * (prm[1] * J * (J - 1.0))


MODELS = {
    "rigid": rigid,
    "fixed_corotated": fixed_corotated,
    "corotated_box_yield": corotated_box_yield,
    "von_mises": von_mises,
    "liquid": liquid,
    "viscous_liquid": viscous_liquid,
}

# models whose stress needs no SVD of F (the solvers skip it for them)
NO_SVD = frozenset({"rigid", "liquid", "viscous_liquid"})


def with_svd(name: str):
    """Model `name` as a function of (F, C, prm) that computes the SVD of F itself when it needs one."""
    model = MODELS[name]
    needs_svd = name not in NO_SVD

    @ti.func
    def func(F, C, prm):
        U = ti.Matrix.zero(float, 3, 3)
        sig = ti.Matrix.zero(float, 3, 3)
        V = ti.Matrix.zero(float, 3, 3)
        if ti.static(needs_svd):
            U, sig, V = svd3.svd(F)
        return model(F, C, prm, U, sig, V)

    return func
