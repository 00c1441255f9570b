"""The block-banded SPD solve: H x = g for a symmetric positive-definite H of T × T blocks (n × n each)
with two block bands below the diagonal (the normal matrix of a Gauss–Newton problem over a time series
whose residuals couple at most three consecutive frames: acceleration terms).

H is given by its lower blocks: ``D (..., T, n, n)`` the diagonal blocks H_{t,t}, ``E (..., T, n, n)`` the
first sub-diagonal H_{t,t-1} (E[0] unused), ``F (..., T, n, n)`` the second H_{t,t-2} (F[0], F[1]
unused). The block Cholesky factor L (H = L Lᵀ) has the same band:

    B_t = F_t L_{t-2}^{-T},   A_t = (E_t − B_t A_{t-1}ᵀ) L_{t-1}^{-T},   L_t = chol(D_t − B_t B_tᵀ − A_t A_tᵀ)

then forward substitution y_t = L_t^{-1}(g_t − B_t y_{t-2} − A_t y_{t-1}) and back substitution
x_t = L_t^{-T}(y_t − A_{t+1}ᵀ x_{t+1} − B_{t+2}ᵀ x_{t+2}). O(T n³) work and O(T n²) memory instead of the
dense (T n)³; a loop over the T blocks, batched over the leading dims. Differentiable (torch ops only).

:func:`block_banded_cg` solves the same system by conjugate gradients preconditioned with the diagonal
blocks' Cholesky factors (block Jacobi): a fixed number of iterations, each a few batched products over all
T blocks at once, so the sequential depth does not grow with T (the exact solve's loop does: on a busy CPU
or a GPU, where each small operation costs its launch, that loop dominates). An inexact solve is what a
damped Gauss–Newton step needs (truncated Newton).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["block_banded_cg", "block_banded_solve"]


def _right_solve(L: Tensor, M: Tensor) -> Tensor:
    """M L^{-T} for lower-triangular L: X Lᵀ = M."""
    return torch.linalg.solve_triangular(L, M.mT, upper=False).mT


def block_banded_solve(D: Tensor, E: Tensor, F: Tensor, g: Tensor) -> Tensor:
    """x ``(..., T, n)`` with H x = g, H SPD block-banded (module doc); ``D, E, F (..., T, n, n)``,
    ``g (..., T, n)``. A block that is not positive definite gives NaN (no host sync to check it)."""
    T = D.shape[-3]
    L: list[Tensor] = []
    A: list[Tensor | None] = []
    B: list[Tensor | None] = []
    for t in range(T):  # over time (the band), batched over the leading dims
        S = D[..., t, :, :]
        b = a = None
        if t >= 2:
            b = _right_solve(L[t - 2], F[..., t, :, :])
            S = S - b @ b.mT
        if t >= 1:
            e = E[..., t, :, :]
            if b is not None:
                e = e - b @ A[t - 1].mT
            a = _right_solve(L[t - 1], e)
            S = S - a @ a.mT
        L.append(torch.linalg.cholesky_ex(S)[0])
        A.append(a)
        B.append(b)
    y: list[Tensor] = []
    for t in range(T):
        r = g[..., t, :]
        if t >= 1:
            r = r - (A[t] @ y[t - 1].unsqueeze(-1)).squeeze(-1)
        if t >= 2:
            r = r - (B[t] @ y[t - 2].unsqueeze(-1)).squeeze(-1)
        y.append(torch.linalg.solve_triangular(L[t], r.unsqueeze(-1), upper=False).squeeze(-1))
    x: list[Tensor | None] = [None] * T
    for t in range(T - 1, -1, -1):
        r = y[t]
        if t + 1 < T:
            r = r - (A[t + 1].mT @ x[t + 1].unsqueeze(-1)).squeeze(-1)
        if t + 2 < T:
            r = r - (B[t + 2].mT @ x[t + 2].unsqueeze(-1)).squeeze(-1)
        x[t] = torch.linalg.solve_triangular(L[t].mT, r.unsqueeze(-1), upper=True).squeeze(-1)
    return torch.stack(x, -2)


def _banded_matvec(D: Tensor, E: Tensor, F: Tensor, x: Tensor) -> Tensor:
    """H x for the block-banded H of (D, E, F) (module doc); ``x (..., T, n)``."""
    y = (D @ x.unsqueeze(-1)).squeeze(-1)
    if x.shape[-2] > 1:
        ex = (E[..., 1:, :, :] @ x[..., :-1, :].unsqueeze(-1)).squeeze(-1)  # H_{t,t-1} x_{t-1}
        etx = (E[..., 1:, :, :].mT @ x[..., 1:, :].unsqueeze(-1)).squeeze(-1)  # H_{t-1,t} x_t
        y = y + torch.nn.functional.pad(ex, (0, 0, 1, 0)) + torch.nn.functional.pad(etx, (0, 0, 0, 1))
    if x.shape[-2] > 2:
        fx = (F[..., 2:, :, :] @ x[..., :-2, :].unsqueeze(-1)).squeeze(-1)
        ftx = (F[..., 2:, :, :].mT @ x[..., 2:, :].unsqueeze(-1)).squeeze(-1)
        y = y + torch.nn.functional.pad(fx, (0, 0, 2, 0)) + torch.nn.functional.pad(ftx, (0, 0, 0, 2))
    return y


def block_banded_cg(D: Tensor, E: Tensor, F: Tensor, g: Tensor, iterations: int = 30) -> Tensor:
    """x ``(..., T, n)`` approximately solving H x = g (module doc) by ``iterations`` steps of conjugate
    gradients with the block-Jacobi preconditioner; one system per leading index. No host sync."""
    Lc = torch.linalg.cholesky_ex(D)[0]

    def precondition(r: Tensor) -> Tensor:
        return torch.cholesky_solve(r.unsqueeze(-1), Lc).squeeze(-1)

    def dot(a: Tensor, b: Tensor) -> Tensor:
        return (a * b).sum((-1, -2), keepdim=True)

    x = precondition(g)
    r = g - _banded_matvec(D, E, F, x)
    z = precondition(r)
    p = z
    rz = dot(r, z)
    tiny = torch.finfo(g.dtype).tiny
    for _ in range(iterations):
        Hp = _banded_matvec(D, E, F, p)
        pHp = dot(p, Hp)
        alpha = rz / pHp.clamp_min(tiny)
        x = x + alpha * p
        r = r - alpha * Hp
        z = precondition(r)
        rz_new = dot(r, z)
        p = z + (rz_new / rz.clamp_min(tiny)) * p
        rz = rz_new
    return x
