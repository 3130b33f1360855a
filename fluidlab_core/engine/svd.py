"""The 3×3 SVD: an accurate forward (`svd`) and its backward pass written by hand (Taichi's autodiff cannot
differentiate `ti.svd`'s iterations).

Forward accuracy. `ti.svd` (Sifakis' Jacobi method with approximate Givens rotations) is accurate to about
1e-10 in float64, and its branches make that error jump as F changes. The fixed-corotated stress
2μ (F − R) Fᵀ then has a relative error of 1e-10/strain (1e-5 at a strain of 1e-5) that is not even
continuous, which breaks finite-difference checks and gradient descent alike. `svd` polishes the result:
    R₀ = U₀V₀ᵀ, M = R₀ᵀF, S = sym(M); the exact polar factor is R = R₀ exp([k]×) with
    [k]× S + S [k]× = M − Mᵀ  ⇔  ((tr S) I − S) k = vee(M − Mᵀ)        (one Newton step, error O(|k|²))
then S = sym(RᵀF), V = V₀, Σ = diag(Vᵀ S V), U = R V. R comes out exact to round-off (1e-15 where
ti.svd gave 4e-10); Σ's error is second order in V₀'s.

Backward: A = U Σ Vᵀ with U, V rotations (as `ti.svd` returns them; σ₃ may be negative for det A < 0).
Given the loss gradients G_U, G_Σ (diagonal), G_V, the gradient with respect to A is (Townsend 2016;
PyTorch's svd_backward for square matrices)

    G_A = U (diag(G_σ) + X) Vᵀ,
    X_ij = [a_ij σ_j + σ_i b_ij] / (σ_j² − σ_i²)   (i ≠ j),
    a = UᵀG_U − G_UᵀU,  b = VᵀG_V − G_VᵀV  (both antisymmetric).

Safe form for repeated singular values: split the fraction as
    X_ij = ½(a_ij + b_ij)/(σ_j − σ_i) + ½(a_ij − b_ij)/(σ_i + σ_j).
A function that depends on U and V only through R = UVᵀ (the fixed-corotated stress, the polar
decomposition of the rigid projection) gives b = −a: the first term vanishes and the second is finite, so
the gradient is exact even at σ_i = σ_j (F = I). For other functions the first term is a divided difference:
it is exact while σ_i ≠ σ_j, and |σ_j − σ_i| is clamped at `eps` (keeping its sign); at exactly repeated
values its numerator is exactly 0 and the term is dropped. For the plastic models that drops the symmetric
shear response of a particle whose F is exactly isotropic (cI); every particle starts so, but F⁰ is not a
parameter, and a substep with any velocity gradient makes the values distinct.
"""
from __future__ import annotations

import taichi as ti


@ti.func
def rotation_from_rotvec(w):
    K = ti.Matrix([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    t2 = w.dot(w)
    a = 1.0 - t2 / 6.0  # sin θ / θ
    b = 0.5 - t2 / 24.0  # (1 − cos θ) / θ²
    if t2 > 1e-8:
        t = ti.sqrt(t2)
        a = ti.sin(t) / t
        b = (1.0 - ti.cos(t)) / t2
    return ti.Matrix.identity(float, 3) + a * K + b * (K @ K)


@ti.func
def svd(F):
    """U, Σ (diagonal matrix), V with U, V rotations and F = U Σ Vᵀ, polished as in the module docstring."""
    U0, sig0, V0 = ti.svd(F)
    R0 = U0 @ V0.transpose()
    M = R0.transpose() @ F
    S = 0.5 * (M + M.transpose())
    A = S.trace() * ti.Matrix.identity(float, 3) - S
    R = R0
    det = A.determinant()
    # skip the step for a nearly singular system (an element crushed flat or inverted), keeping ti.svd's R
    if ti.abs(det) > 1e-12 * (ti.abs(S.trace()) ** 3 + 1e-30):
        k = A.inverse() @ ti.Vector([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
        R = R0 @ rotation_from_rotvec(k)
    S = R.transpose() @ F
    S = 0.5 * (S + S.transpose())
    D = V0.transpose() @ S @ V0
    sig = ti.Matrix([[D[0, 0], 0.0, 0.0], [0.0, D[1, 1], 0.0], [0.0, 0.0, D[2, 2]]])
    return R @ V0, sig, V0


def make_backward_svd(eps: float):
    """A Taichi function (G_U, G_Σ, G_V, U, Σ, V) -> G_A; Σ and G_Σ are diagonal 3×3 matrices."""

    @ti.func
    def _away_from_zero(d):
        out = d
        if ti.abs(d) < eps:
            out = eps if d >= 0.0 else -eps
        return out

    @ti.func
    def backward_svd(gU, gsig, gV, U, sig, V):
        a = U.transpose() @ gU - gU.transpose() @ U
        b = V.transpose() @ gV - gV.transpose() @ V
        X = ti.Matrix.zero(float, 3, 3)
        for i, j in ti.static(ti.ndrange(3, 3)):
            if ti.static(i == j):
                X[i, j] = gsig[i, i]
            else:
                diff = _away_from_zero(sig[j, j] - sig[i, i])
                total = _away_from_zero(sig[i, i] + sig[j, j])
                X[i, j] = 0.5 * (a[i, j] + b[i, j]) / diff + 0.5 * (a[i, j] - b[i, j]) / total
        return U @ X @ V.transpose()

    return backward_svd
