"""Constitutive models: named parameters and one Taichi function per model, returning (projected F, τ).

Notation: F deformation gradient (after the substep update F ← (I + Δt C) F), C the APIC affine velocity
(≈ ∇v, 1/s), J = det F, F = U Σ Vᵀ its SVD, R = U Vᵀ. Every model returns the Kirchhoff stress τ = J σ
(Pa), which P2G multiplies by the rest volume V⁰.

- fixed_corotated (elastic), (μ, λ):          τ = 2μ (F − R) Fᵀ + λ J (J − 1) I              [Stomakhin 2012]
- rigid (between projections), (λ):           τ = λ J (J − 1) I; rigid.py keeps F = R J^(1/3)
- corotated_box_yield (plastic), (μ, λ, y₁, y₂): Σ ← clamp(Σ, 1 − y₁, 1 + y₂), F ← U Σ Vᵀ, then
                                              fixed-corotated                                [Stomakhin 2013]
- von_mises (ice cream, plasticine), (μ, λ, σ_y): ε = ln Σ, ε̂ = dev ε; if |ε̂| > sqrt(2/3)·σ_y/(2μ)
                                              project ε̂ onto the yield surface (perfect plasticity),
                                              F ← U exp(ε) Vᵀ, τ = U (2μ ε + λ tr(ε) I) Uᵀ   [Klár 2016, Huang 2021]
- liquid (weakly compressible), (λ):          J ← det F, F ← J^(1/3) I, τ = λ J (J − 1) I, i.e. pressure
                                              p = −λ (J − 1)                          [Tampubolon 2017, FluidLab]
- viscous_liquid, (λ, η):                     liquid + τ_v = η J (C + Cᵀ − ⅔ tr(C) I) = 2 η J dev(sym ∇v)
- damped_liquid, (λ, ζ):                      liquid + τ_b = ζ J tr(C) I = ζ J (∇·v) I, a bulk viscosity that
                                              damps the liquid's sound waves (a standing wave of wavenumber k
                                              decays at ζ k²/(2ρ)) and leaves divergence-free flow alone

Parameters are named, in SI units (μ, λ, σ_y in Pa; y₁, y₂ dimensionless; η in Pa·s). A model declares its
parameter names when it is registered, and the solvers keep one Taichi struct field per model present in a
scene (`Model.params`), so a model may have any number of parameters: the kernels read `prm.mu`, never a
position. ζ (bulk viscosity) is in Pa·s. A material (materials.py) names its model and gives the values (`Material.kernel_params()`).

Every model takes the SVD of F as arguments (U, sig, V; zero matrices for models registered with
needs_svd=False), so that the differentiable solver can compute it in a kernel of its own whose gradient is
written by hand (svd.py), while the forward kernels compute it inline, once per particle whatever the number
of models that read it (transfer.stress). The solvers unroll the models present in a scene with `ti.static`,
so a scene of liquids never pays for an SVD.

Adding a model: write the function with Taichi's autodiff rules in mind (whole-matrix updates, no local
written inside a branch, `statics.safe_norm` for norms that can be zero) and register it:

    @constitutive.register("my_model", params=("mu", "lam", "k1"), needs_svd=True)
    @ti.func
    def my_model(F, C, prm, U, sig, V): ...            # -> (F_new, tau)

The differentiable solver then differentiates it with Taichi's reverse mode. Every built-in model also has a
hand-written backward (`backward_of`, the math above the backwards at the end of this file), which the solver
calls instead: Taichi's reverse of a model's matrix products compiled in 5-15 s a model and scene, most of a
gradient scene's compile time. docs/extending.md walks through both.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import taichi as ti


# Singular values below this are clamped before a logarithm (an inverted or crushed element).
_MIN_STRETCH = 0.05


@dataclass(frozen=True)
class ConstitutiveModel:
    """A registered model: its name, its parameter names (the struct the kernels read) and its function."""

    name: str
    params: tuple[str, ...]
    needs_svd: bool
    func: object  # ti.func (F, C, prm, U, sig, V) -> (F_new, tau)
    fluid: bool = False  # a fluid has a velocity field of its own on the grid where it does not touch solids (grid.py)
    # ti.func (F, C, prm, U, sig, V, g_F_new, g_tau) -> (g_F, g_C, g_U, g_sig, g_V), or None: Taichi's reverse mode
    backward: object = None


MODELS: dict[str, ConstitutiveModel] = {}


def register(name: str, params, needs_svd: bool, fluid: bool = False):
    """Decorator registering a Taichi function as constitutive model `name` with the named parameters. A `fluid`
    model (one without shear memory: the liquids) moves with the fluids' velocity field of the grid, the others
    with the solids' one; the two are one where they touch (grid.field_velocity)."""
    params = tuple(params)
    if not params or not all(isinstance(p, str) and p.isidentifier() for p in params):
        raise ValueError(f"constitutive model {name!r}: params must be one or more identifiers, got {params!r}")
    if len(set(params)) != len(params):
        raise ValueError(f"constitutive model {name!r}: repeated parameter names in {params!r}")

    def wrap(func):
        old = MODELS.get(name)
        if old is not None and old.func is not func:
            raise ValueError(f"a constitutive model named {name!r} is already registered")
        MODELS[name] = ConstitutiveModel(name, params, bool(needs_svd), func, bool(fluid))
        return func

    return wrap


def backward_of(name: str):
    """Decorator attaching a hand-written backward to registered model `name`: a Taichi function
    (F, C, prm, U, sig, V, g_F_new, g_tau) -> (g_F, g_C, g_U, g_sig, g_V), the gradients of a loss with respect to
    the model's inputs given those of its outputs, U, Σ, V taken as inputs of their own (the differentiable
    solver carries their gradients on through the SVD's backward); zero matrices for inputs it does not read,
    g_sig diagonal. The differentiable solver calls it instead of Taichi's reverse mode of `func`, whose
    matrix products take long to compile (each built-in model's reverse kernel 5-15 s). It must be the exact
    adjoint of `func`: tests/test_transfer_backward.py checks the built-in ones against finite differences."""

    def wrap(func):
        MODELS[name] = replace(get(name), backward=func)
        return func

    return wrap


def get(name: str) -> ConstitutiveModel:
    try:
        return MODELS[name]
    except KeyError:
        raise KeyError(f"unknown constitutive model {name!r}; registered: {', '.join(sorted(MODELS))}") from None


@register("fixed_corotated", params=("mu", "lam"), needs_svd=True)
@ti.func
def fixed_corotated(F, C, prm, U, sig, V):
    """Elastic: F unchanged, fixed-corotated Kirchhoff stress."""
    R = U @ V.transpose()
    J = F.determinant()
    tau = 2.0 * prm.mu * (F - R) @ F.transpose() + ti.Matrix.identity(float, 3) * (prm.lam * J * (J - 1.0))
    return F, tau


@register("corotated_box_yield", params=("mu", "lam", "yield_compression", "yield_stretch"), needs_svd=True)
@ti.func
def corotated_box_yield(F, C, prm, U, sig, V):
    """Plastic: clamp principal stretches to [1 - y1, 1 + y2], then fixed-corotated stress."""
    # clamped stretches built as a new matrix: Taichi's reverse mode mishandles element writes to a local
    s = ti.Vector([ti.min(ti.max(sig[d, d], 1.0 - prm.yield_compression), 1.0 + prm.yield_stretch)
                   for d in ti.static(range(3))])
    Fp = U @ ti.Matrix([[s[0], 0.0, 0.0], [0.0, s[1], 0.0], [0.0, 0.0, s[2]]]) @ V.transpose()
    R = U @ V.transpose()
    J = s[0] * s[1] * s[2]
    tau = 2.0 * prm.mu * (Fp - R) @ Fp.transpose() + ti.Matrix.identity(float, 3) * (prm.lam * J * (J - 1.0))
    return Fp, tau


@register("von_mises", params=("mu", "lam", "yield_stress"), needs_svd=True)
@ti.func
def von_mises(F, C, prm, U, sig, V):
    """Hencky-strain St. Venant–Kirchhoff with von Mises return mapping (uniaxial yield stress σ_y)."""
    mu, lam = prm.mu, prm.lam
    eps = ti.Vector([ti.log(ti.max(ti.abs(sig[d, d]), _MIN_STRETCH)) for d in ti.static(range(3))])
    eps_hat = eps - eps.sum() / 3.0
    eps_hat_norm = ti.sqrt(eps_hat.dot(eps_hat) + 1e-30)  # finite derivative at 0
    yield_strain = ti.sqrt(2.0 / 3.0) * prm.yield_stress / (2.0 * mu)
    # return mapping without a branch (Taichi's reverse mode mishandles a local updated inside one)
    eps = eps - ti.max(0.0, 1.0 - yield_strain / eps_hat_norm) * eps_hat
    Fp = U @ ti.Matrix([[ti.exp(eps[0]), 0.0, 0.0], [0.0, ti.exp(eps[1]), 0.0], [0.0, 0.0, ti.exp(eps[2])]]) \
        @ V.transpose()
    s = 2.0 * mu * eps + lam * eps.sum()
    tau = U @ ti.Matrix([[s[0], 0.0, 0.0], [0.0, s[1], 0.0], [0.0, 0.0, s[2]]]) @ U.transpose()
    return Fp, tau


@ti.func
def _liquid(F, lam):
    """Weakly compressible liquid: the volume part of F, and the pressure from J."""
    J = F.determinant()
    Fp = ti.Matrix.identity(float, 3) * ti.pow(ti.max(J, 1e-6), 1.0 / 3.0)
    tau = ti.Matrix.identity(float, 3) * (lam * J * (J - 1.0))
    return Fp, tau


@register("liquid", params=("lam",), needs_svd=False, fluid=True)
@ti.func
def liquid(F, C, prm, U, sig, V):
    """Weakly compressible liquid: keep only the volume part of F; pressure from J."""
    return _liquid(F, prm.lam)


@register("viscous_liquid", params=("lam", "eta"), needs_svd=False, fluid=True)
@ti.func
def viscous_liquid(F, C, prm, U, sig, V):
    """Liquid plus deviatoric Newtonian viscous stress."""
    Fp, tau = _liquid(F, prm.lam)
    J = F.determinant()
    tau += prm.eta * J * (C + C.transpose() - (2.0 / 3.0) * C.trace() * ti.Matrix.identity(float, 3))
    return Fp, tau


@register("damped_liquid", params=("lam", "zeta"), needs_svd=False, fluid=True)
@ti.func
def damped_liquid(F, C, prm, U, sig, V):
    """Liquid plus a bulk viscous stress on the rate of volume change: damps sound waves (the ring of a
    weakly compressible liquid), not shear."""
    Fp, tau = _liquid(F, prm.lam)
    J = F.determinant()
    tau += prm.zeta * J * C.trace() * ti.Matrix.identity(float, 3)
    return Fp, tau


@register("rigid", params=("lam",), needs_svd=False)
@ti.func
def rigid(F, C, prm, U, sig, V):
    """Rigid body particle: F is set by the rigid projection; only its volume change is resisted."""
    J = F.determinant()
    return F, ti.Matrix.identity(float, 3) * (prm.lam * J * (J - 1.0))


# --- hand-written backwards ------------------------------------------------------------------------------------
# Each maps (ḡ_F_new, ḡ_τ) = (∂L/∂F_new, ∂L/∂τ) to the gradients of the model's inputs, U, Σ, V as independent
# inputs (the differentiable solver's SVD backward carries them on to F), with ⟨A, B⟩ = Σ A_ij B_ij:
#   ∂J/∂F = cof F (the cofactor matrix, J F⁻ᵀ where F is invertible);
#   pressure λ J (J − 1) I:           ḡ_J += λ (2J − 1) tr ḡ_τ
#   τ = 2μ (A) Bᵀ:                    ḡ_A = 2μ ḡ_τ B,  ḡ_B = 2μ ḡ_τᵀ A
#   R = U Vᵀ:                         ḡ_U = ḡ_R V,  ḡ_V = ḡ_Rᵀ U
#   M = U D Vᵀ (D diagonal):          ḡ_U = ḡ_M V D,  ḡ_V = ḡ_Mᵀ U D,  ḡ_D = diag(Uᵀ ḡ_M V)
#   τ = U D Uᵀ:                       ḡ_U = (ḡ_τ + ḡ_τᵀ) U D,  ḡ_D = diag(Uᵀ ḡ_τ U)
# Clamps (ti.min, ti.max) pass the gradient to the value they return; the forward's branches are taken as the
# forward takes them.
@ti.func
def cofactor(F):
    """∂ det F / ∂F."""
    return ti.Matrix([[F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1], F[1, 2] * F[2, 0] - F[1, 0] * F[2, 2],
                       F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]],
                      [F[0, 2] * F[2, 1] - F[0, 1] * F[2, 2], F[0, 0] * F[2, 2] - F[0, 2] * F[2, 0],
                       F[0, 1] * F[2, 0] - F[0, 0] * F[2, 1]],
                      [F[0, 1] * F[1, 2] - F[0, 2] * F[1, 1], F[0, 2] * F[1, 0] - F[0, 0] * F[1, 2],
                       F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]]])


@ti.func
def _diag(d):
    return ti.Matrix([[d[0], 0.0, 0.0], [0.0, d[1], 0.0], [0.0, 0.0, d[2]]])


@ti.func
def _diagonal(M):
    return ti.Vector([M[0, 0], M[1, 1], M[2, 2]])


@backward_of("fixed_corotated")
@ti.func
def fixed_corotated_backward(F, C, prm, U, sig, V, g_Fn, g_tau):
    """τ = 2μ (F − R) Fᵀ + λ J (J − 1) I, F_new = F."""
    R = U @ V.transpose()
    J = F.determinant()
    g_A = 2.0 * prm.mu * g_tau @ F  # A = F − R
    g_F = g_Fn + g_A + 2.0 * prm.mu * g_tau.transpose() @ (F - R) \
        + (prm.lam * (2.0 * J - 1.0) * g_tau.trace()) * cofactor(F)
    zero = ti.Matrix.zero(float, 3, 3)
    return g_F, zero, -g_A @ V, zero, -g_A.transpose() @ U


@backward_of("corotated_box_yield")
@ti.func
def corotated_box_yield_backward(F, C, prm, U, sig, V, g_Fn, g_tau):
    """s = clamp(Σ, 1 − y₁, 1 + y₂), Fp = U diag(s) Vᵀ, τ = 2μ (Fp − R) Fpᵀ + λ J (J − 1) I with J = s₀s₁s₂."""
    lo, hi = 1.0 - prm.yield_compression, 1.0 + prm.yield_stretch
    s = ti.Vector([ti.min(ti.max(sig[d, d], lo), hi) for d in ti.static(range(3))])
    S = _diag(s)
    Fp = U @ S @ V.transpose()
    R = U @ V.transpose()
    J = s[0] * s[1] * s[2]
    g_R = -2.0 * prm.mu * g_tau @ Fp
    g_Fp = g_Fn - g_R + 2.0 * prm.mu * g_tau.transpose() @ (Fp - R)
    g_J = prm.lam * (2.0 * J - 1.0) * g_tau.trace()
    g_s = _diagonal(U.transpose() @ g_Fp @ V) + g_J * ti.Vector([s[1] * s[2], s[0] * s[2], s[0] * s[1]])
    g_sig = ti.Vector([0.0, 0.0, 0.0])
    for d in ti.static(range(3)):
        if lo < sig[d, d] and sig[d, d] < hi:
            g_sig[d] = g_s[d]
    g_U = g_Fp @ V @ S + g_R @ V
    g_V = g_Fp.transpose() @ U @ S + g_R.transpose() @ U
    return ti.Matrix.zero(float, 3, 3), ti.Matrix.zero(float, 3, 3), g_U, _diag(g_sig), g_V


@backward_of("von_mises")
@ti.func
def von_mises_backward(F, C, prm, U, sig, V, g_Fn, g_tau):
    """ε₀ = ln max(|Σ|, m), ε̂ = dev ε₀, n = (|ε̂|² + 1e-30)^½, f = max(0, 1 − ε_y/n), ε = ε₀ − f ε̂,
    Fp = U exp(ε) Vᵀ, τ = U diag(2μ ε + λ tr ε) Uᵀ."""
    mu, lam = prm.mu, prm.lam
    a = ti.Vector([ti.abs(sig[d, d]) for d in ti.static(range(3))])
    eps0 = ti.Vector([ti.log(ti.max(a[d], _MIN_STRETCH)) for d in ti.static(range(3))])
    eps_hat = eps0 - eps0.sum() / 3.0
    n = ti.sqrt(eps_hat.dot(eps_hat) + 1e-30)
    yield_strain = ti.sqrt(2.0 / 3.0) * prm.yield_stress / (2.0 * mu)
    f = ti.max(0.0, 1.0 - yield_strain / n)
    eps = eps0 - f * eps_hat
    E = ti.Vector([ti.exp(eps[d]) for d in ti.static(range(3))])
    s = 2.0 * mu * eps + lam * eps.sum()
    # τ = U diag(s) Uᵀ and Fp = U diag(E) Vᵀ
    g_s = _diagonal(U.transpose() @ g_tau @ U)
    g_U = (g_tau + g_tau.transpose()) @ U @ _diag(s) + g_Fn @ V @ _diag(E)
    g_V = g_Fn.transpose() @ U @ _diag(E)
    g_eps = 2.0 * mu * g_s + lam * g_s.sum() + _diagonal(U.transpose() @ g_Fn @ V) * E
    # ε = ε₀ − f ε̂
    g_eps_hat = -f * g_eps
    if 1.0 - yield_strain / n > 0.0:
        g_n = -g_eps.dot(eps_hat) * yield_strain / (n * n)
        g_eps_hat += g_n / n * eps_hat
    g_eps0 = g_eps + g_eps_hat - g_eps_hat.sum() / 3.0
    g_sig = ti.Vector([0.0, 0.0, 0.0])
    for d in ti.static(range(3)):
        if a[d] > _MIN_STRETCH:
            g_sig[d] = g_eps0[d] / sig[d, d]  # d ln|σ| / dσ = 1/σ
    return ti.Matrix.zero(float, 3, 3), ti.Matrix.zero(float, 3, 3), g_U, _diag(g_sig), g_V


@ti.func
def _liquid_backward(F, lam, g_Fn, g_tau, g_J_more, g_C):
    """The liquids' gradients: ∂L/∂J through _liquid (Fp = max(J, 1e-6)^⅓ I, τ = λ J (J − 1) I) plus g_J_more
    (what a model adds to τ through J) on to F by the cofactor, and g_C (what it adds through C)."""
    J = F.determinant()
    g_J = lam * (2.0 * J - 1.0) * g_tau.trace() + g_J_more
    if J > 1e-6:
        g_J += g_Fn.trace() / 3.0 * ti.pow(J, -2.0 / 3.0)
    zero = ti.Matrix.zero(float, 3, 3)
    return g_J * cofactor(F), g_C, zero, zero, zero


@backward_of("liquid")
@ti.func
def liquid_backward(F, C, prm, U, sig, V, g_Fn, g_tau):
    return _liquid_backward(F, prm.lam, g_Fn, g_tau, 0.0, ti.Matrix.zero(float, 3, 3))


@backward_of("viscous_liquid")
@ti.func
def viscous_liquid_backward(F, C, prm, U, sig, V, g_Fn, g_tau):
    """+ τ_v = η J D, D = C + Cᵀ − ⅔ tr(C) I."""
    eye = ti.Matrix.identity(float, 3)
    D = C + C.transpose() - (2.0 / 3.0) * C.trace() * eye
    g_C = prm.eta * F.determinant() * (g_tau + g_tau.transpose() - (2.0 / 3.0) * g_tau.trace() * eye)
    return _liquid_backward(F, prm.lam, g_Fn, g_tau, prm.eta * (g_tau * D).sum(), g_C)


@backward_of("damped_liquid")
@ti.func
def damped_liquid_backward(F, C, prm, U, sig, V, g_Fn, g_tau):
    """+ τ_b = ζ J tr(C) I."""
    g_C = (prm.zeta * F.determinant() * g_tau.trace()) * ti.Matrix.identity(float, 3)
    return _liquid_backward(F, prm.lam, g_Fn, g_tau, prm.zeta * C.trace() * g_tau.trace(), g_C)


@backward_of("rigid")
@ti.func
def rigid_backward(F, C, prm, U, sig, V, g_Fn, g_tau):
    """τ = λ J (J − 1) I, F_new = F."""
    J = F.determinant()
    zero = ti.Matrix.zero(float, 3, 3)
    return g_Fn + (prm.lam * (2.0 * J - 1.0) * g_tau.trace()) * cofactor(F), zero, zero, zero, zero
