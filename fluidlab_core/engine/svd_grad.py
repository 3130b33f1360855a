"""Backward pass of the 3×3 SVD, written by hand (Taichi's autodiff cannot differentiate `ti.svd`'s iterations).

Forward: A = U Σ Vᵀ with U, V rotations (as `ti.svd` returns them; σ₃ may be negative for det A < 0).
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
