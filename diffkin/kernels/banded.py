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

:func:`tridiagonal_solve` is the scalar (not necessarily symmetric) tridiagonal system of the cubic splines
(the knot slopes or accelerations of §4.2.2), small enough (N path points) for a dense batched LU.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .._numerics import broadcast_shapes
from . import native

__all__ = ["block_banded_cg", "block_banded_solve", "tridiagonal_solve"]


def _right_solve(L: Tensor, M: Tensor) -> Tensor:
    """M L^{-T} for lower-triangular L: X Lᵀ = M."""
    return torch.linalg.solve_triangular(L, M.mT, upper=False).mT


def _regroup(D: Tensor, E: Tensor, F: Tensor, g: Tensor, k: int):
    """The same H as a block-*tridiagonal* matrix of k-frame super-blocks ``(..., m, k n, k n)`` (diagonal
    and first sub-diagonal) and g ``(..., m, k n)``, m = ⌈T / k⌉ (k ≥ 2, so that the two bands couple
    neighbouring super-blocks only); padding frames are identity rows."""
    *lead, T, n, _ = D.shape
    m = -(-T // k)
    pad = m * k - T
    eye = torch.eye(n, dtype=D.dtype, device=D.device)
    if pad:
        D = torch.cat((D, eye.expand(*lead, pad, n, n)), -3)
        E = torch.nn.functional.pad(E, (0, 0, 0, 0, 0, pad))
        F = torch.nn.functional.pad(F, (0, 0, 0, 0, 0, pad))
        g = torch.nn.functional.pad(g, (0, 0, 0, pad))
    first = torch.ones(m * k, 1, 1, dtype=D.dtype, device=D.device)
    first[0] = 0.0
    E = E * first  # E[0], F[0], F[1] are outside the matrix
    first[1] = 0.0
    F = F * first
    Dd = D.new_zeros(*lead, m, k, n, k, n)
    Ee = D.new_zeros(*lead, m, k, n, k, n)
    for a in range(k):  # over the k frame positions in a super-block (not over T)
        Dd[..., a, :, a, :] = D[..., a::k, :, :]
        if a >= 1:
            Dd[..., a, :, a - 1, :] = E[..., a::k, :, :]
            Dd[..., a - 1, :, a, :] = E[..., a::k, :, :].mT
        if a >= 2:
            Dd[..., a, :, a - 2, :] = F[..., a::k, :, :]
            Dd[..., a - 2, :, a, :] = F[..., a::k, :, :].mT
    Ee[..., 0, :, k - 1, :] = E[..., 0::k, :, :]  # frame sk with sk - 1
    Ee[..., 0, :, k - 2, :] = F[..., 0::k, :, :]  # frame sk with sk - 2
    Ee[..., 1, :, k - 1, :] = F[..., 1::k, :, :]  # frame sk + 1 with sk - 1
    return Dd.flatten(-4, -3).flatten(-2, -1), Ee.flatten(-4, -3).flatten(-2, -1), g.reshape(*lead, m, k * n)


def block_banded_solve(D: Tensor, E: Tensor, F: Tensor, g: Tensor, frames_per_block: int | None = None,
                       shift: Tensor | None = None) -> Tensor:
    """x ``(..., T, n)`` with H x = g, H SPD block-banded (module doc); ``D, E, F (..., T, n, n)``,
    ``g (..., T, n)``; ``shift (...)`` (optional): H + shift I per system (a Levenberg–Marquardt damping; the
    C path adds it as it copies D, no copy of D is made for it). A block that is not positive definite
    gives NaN (no host sync to check it).

    ``frames_per_block`` k ≥ 2 regroups the frames into ⌈T/k⌉ super-blocks of k frames, which makes H
    block-tridiagonal: k times fewer sequential steps of k n × k n blocks (k² times the flops of the
    band, k times fewer small operations: for a GPU, where each launch costs more than its flops). None
    or 1 (default): the two-band recursion frame by frame; on CPU tensors without autograd in C
    (:func:`diffkin.kernels.native.banded_solve`, the same recursion; the torch loop below where the
    native kernel is not built)."""
    T = D.shape[-3]
    k = 1 if frames_per_block is None else int(frames_per_block)
    if k < 2:  # CPU without autograd: the same recursion in C (native.banded_solve), else torch's below
        x = native.banded_solve(D, E, F, g, shift)
        if x is not None:
            return x
    if shift is not None:
        D = D + shift[..., None, None, None] * torch.eye(D.shape[-1], dtype=D.dtype, device=D.device)
    if k >= 2:
        Dk, Ek, gk = _regroup(D, E, F, g, k)
        x = _band_cholesky_solve(Dk, Ek, None, gk)
        return x.reshape(*g.shape[:-2], -1, g.shape[-1])[..., :T, :]
    return _band_cholesky_solve(D, E, F, g)


def _band_cholesky_solve(D: Tensor, E: Tensor, F: Tensor | None, g: Tensor) -> Tensor:
    """The block Cholesky recursion of the module doc, a loop over the T blocks (the band), batched over the
    leading dims; ``F`` None: block-tridiagonal (the regrouped super-blocks), the second band skipped."""
    T = D.shape[-3]
    L: list[Tensor] = []
    A: list[Tensor | None] = []
    B: list[Tensor | None] = []
    for t in range(T):  # over time (the band), batched over the leading dims
        S = D[..., t, :, :]
        b = a = None
        if t >= 2 and F is not None:
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
        if B[t] is not None:
            r = r - (B[t] @ y[t - 2].unsqueeze(-1)).squeeze(-1)
        y.append(torch.linalg.solve_triangular(L[t], r.unsqueeze(-1), upper=False).squeeze(-1))
    x: list[Tensor | None] = [None] * T
    for t in range(T - 1, -1, -1):
        r = y[t]
        if t + 1 < T:
            r = r - (A[t + 1].mT @ x[t + 1].unsqueeze(-1)).squeeze(-1)
        if t + 2 < T and B[t + 2] is not None:
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


#: above this N a diagonally dominant system is eliminated along its band (O(N)), not as a dense N x N
DENSE_MAX = 48


def tridiagonal_solve(sub: Tensor, diag: Tensor, sup: Tensor, rhs: Tensor, dominant: bool = False) -> Tensor:
    """x ``(..., N, k)`` with A x = rhs for the tridiagonal A of diagonal ``diag (..., N)``, sub-diagonal
    ``sub (..., N-1)`` (A_{i+1,i}) and super-diagonal ``sup (..., N-1)`` (A_{i,i+1}); ``rhs (..., N, k)``,
    batch dims broadcast. A need not be symmetric (a spline's not-a-knot or virtual-point rows are not):
    LU with partial pivoting on the dense matrix (``torch.linalg.solve``), differentiable. ``dominant``: the
    caller's word that A is diagonally dominant (a clamped spline's rows), so that elimination without
    pivoting is stable: above :data:`DENSE_MAX` rows it runs along the band (the Thomas algorithm, O(N) per
    system, a loop over N), since the dense LU's O(N³) per system grows past everything else for the long,
    refined paths of a planner's batch (every row padded to the longest)."""
    if dominant and diag.shape[-1] > DENSE_MAX:
        return _thomas(sub, diag, sup, rhs)
    A = torch.diag_embed(diag) + torch.diag_embed(sub, offset=-1) + torch.diag_embed(sup, offset=1)
    batch = broadcast_shapes(A.shape[:-2], rhs.shape[:-2])  # explicit: rhs is never read as vectors
    return torch.linalg.solve(A.expand(*batch, *A.shape[-2:]), rhs.expand(*batch, *rhs.shape[-2:]))


def _thomas(sub: Tensor, diag: Tensor, sup: Tensor, rhs: Tensor) -> Tensor:
    """:func:`tridiagonal_solve` by elimination along the band without pivoting (for a diagonally dominant
    A): forward c_i = sup_i / m_i, y_i = (rhs_i − sub_{i−1} y_{i−1}) / m_i with m_i = diag_i − sub_{i−1}
    c_{i−1}, then x_i = y_i − c_i x_{i+1}; a loop over N of batched ops (differentiable)."""
    batch = broadcast_shapes(diag.shape[:-1], sub.shape[:-1], sup.shape[:-1], rhs.shape[:-2])
    N = diag.shape[-1]
    diag, rhs = diag.expand(*batch, N), rhs.expand(*batch, *rhs.shape[-2:])
    sub, sup = sub.expand(*batch, N - 1), sup.expand(*batch, N - 1)
    c, y = [], []
    m = diag[..., 0]
    for i in range(N):
        if i:
            m = diag[..., i] - sub[..., i - 1] * c[-1]
            y.append((rhs[..., i, :] - sub[..., i - 1, None] * y[-1]) / m[..., None])
        else:
            y.append(rhs[..., 0, :] / m[..., None])
        if i < N - 1:
            c.append(sup[..., i] / m)
    x = [y[-1]]
    for i in range(N - 2, -1, -1):
        x.append(y[i] - c[i][..., None] * x[-1])
    return torch.stack(x[::-1], -2)
