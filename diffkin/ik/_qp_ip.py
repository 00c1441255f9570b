"""The interior-point core of :func:`diffkin.ik.qp.solve_qp`: flat batches ``(B, ...)``, no input checks.

Mehrotra's predictor-corrector on  min ½xᵀHx − gᵀx  s.t.  Gx + s = h, s ≥ 0  with multipliers λ ≥ 0:
per iteration the Newton system is reduced to (H + GᵀDG) dx = −r_d − Gᵀ(D r_p − S⁻¹r_c), D = ΛS⁻¹
(Nocedal & Wright §16.6), one LU factorisation shared by the predictor and the corrector. It runs in
float64 whatever the inputs' dtype (the reduced system's condition grows like 1/μ, beyond float32's
range near the end), results cast back. Rows of G whose
h is inf are switched off (a zero row with slack 1). Then a polish: the KKT system of the active set
𝒜 = {λ_i > s_i}, [H G_𝒜ᵀ; G_𝒜 −δI][x; λ_𝒜] = [g; h_𝒜], replaces the interior-point iterate where its
answer is feasible with λ_𝒜 ≥ 0 (exact solutions, as OSQP's polish); the same matrix gives the backward
pass (Q.2). δ (eps^¾ of the system's scale) only matters where active rows are linearly dependent.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .._numerics import eps_for

__all__ = ["ip_solve"]


def _mv(A: Tensor, v: Tensor) -> Tensor:
    return (A @ v.unsqueeze(-1)).squeeze(-1)


def _max_step(v: Tensor, dv: Tensor) -> Tensor:
    """The largest α ≤ 1 with v + α dv ≥ 0, per row ``(B, 1)``."""
    ratio = torch.where(dv < 0, -v / torch.where(dv < 0, dv, -1.0), torch.ones_like(v))
    return ratio.amin(-1, keepdim=True).clamp(max=1.0) if v.shape[-1] else v.new_ones(v.shape[0], 1)


def _newton(lu, G, s, lam, r_d, r_p, r_c):
    """(dx, ds, dλ) of the reduced Newton system for the complementarity residual r_c."""
    D = lam / s
    rhs = -r_d - _mv(G.mT, D * r_p - r_c / s)
    dx = torch.linalg.lu_solve(*lu, rhs.unsqueeze(-1)).squeeze(-1)
    Gdx = _mv(G, dx)
    return dx, -r_p - Gdx, D * (Gdx + r_p) - r_c / s


def _residuals(H, g, G, h, x, s, lam):
    return _mv(H, x) - g + _mv(G.mT, lam), _mv(G, x) + s - h


def _interior_point(H, g, G, h, on, iterations: int):
    """-> (x, s, λ, converged) after at most ``iterations`` predictor-corrector steps."""
    p = max(G.shape[-2], 1)
    x = torch.linalg.solve_ex(H, g.unsqueeze(-1))[0].squeeze(-1)
    s = (h - _mv(G, x)).clamp(min=1.0)
    lam = torch.where(on, 1.0, 0.0).to(g.dtype) + 1e-3  # off rows: λ → 0 under s = 1
    done = torch.zeros(g.shape[0], 1, dtype=torch.bool, device=g.device)
    tol = 16 * eps_for(g)
    scale = 1.0 + g.abs().amax(-1, keepdim=True) + h.abs().amax(-1, keepdim=True)
    for it in range(iterations):
        # every 8 steps, stop once every row has converged (a host sync per 8 steps, as the box QP's
        # CUDA schedule has one per 4): most rows need 12-25 steps, ill-conditioned ones up to ~60
        if it and it % 8 == 0 and bool(done.all()):
            break
        r_d, r_p = _residuals(H, g, G, h, x, s, lam)
        mu = (s * lam).sum(-1, keepdim=True) / p
        done = done | ((torch.maximum(r_d.abs().amax(-1, keepdim=True), r_p.abs().amax(-1, keepdim=True))
                        <= tol * scale) & ((s * lam).amax(-1, keepdim=True) <= tol * scale))
        M = H + G.mT @ ((lam / s).unsqueeze(-1) * G)
        lu = torch.linalg.lu_factor_ex(M)[:2]
        dx, ds, dl = _newton(lu, G, s, lam, r_d, r_p, s * lam)  # predictor (affine scaling)
        a = torch.minimum(_max_step(s, ds), _max_step(lam, dl))
        mu_aff = ((s + a * ds) * (lam + a * dl)).sum(-1, keepdim=True) / p
        sigma = (mu_aff / mu.clamp(min=torch.finfo(g.dtype).tiny)).clamp(0.0, 1.0) ** 3
        dx, ds, dl = _newton(lu, G, s, lam, r_d, r_p, s * lam + ds * dl - sigma * mu)  # corrector
        a = 0.99 * torch.minimum(_max_step(s, ds), _max_step(lam, dl))
        ok = ~done & torch.isfinite(dx).all(-1, keepdim=True) & torch.isfinite(dl).all(-1, keepdim=True)
        a = torch.where(ok, a, torch.zeros_like(a))
        x, s, lam = x + a * torch.where(ok, dx, 0.0), s + a * torch.where(ok, ds, 0.0), \
            lam + a * torch.where(ok, dl, 0.0)
    r_d, r_p = _residuals(H, g, G, h, x, s, lam)
    err = torch.maximum(r_d.abs().amax(-1, keepdim=True), r_p.abs().amax(-1, keepdim=True))
    return x, s, lam, (err <= eps_for(g) ** 0.5 * scale).squeeze(-1)


def _kkt_matrix(H, G, active):
    """[H G_𝒜ᵀ; G_𝒜 −δI − I_off]: inactive rows give λ_i = 0 (their right-hand side is 0)."""
    n, p = H.shape[-1], G.shape[-2]
    Ga = torch.where(active.unsqueeze(-1), G, 0.0)
    delta = eps_for(H) ** 0.75 * (1.0 + H.abs().amax((-2, -1)))
    low = -torch.where(active, delta[..., None], 1.0)
    K = H.new_zeros(H.shape[0], n + p, n + p)
    K[:, :n, :n] = H
    K[:, :n, n:] = Ga.mT
    K[:, n:, :n] = Ga
    K[:, n:, n:] = torch.diag_embed(low)
    return K


def _polish(H, g, G, h, on, x, s, lam):
    """The active-set KKT solution where it is feasible and dual feasible, else the iterate."""
    n = H.shape[-1]
    active = on & (lam > s)
    rhs = torch.cat((g, torch.where(active, h, 0.0)), dim=-1)
    sol = torch.linalg.solve_ex(_kkt_matrix(H, G, active), rhs.unsqueeze(-1))[0].squeeze(-1)
    xp, lp = sol[:, :n], sol[:, n:]
    tol = eps_for(g) ** 0.5 * (1.0 + h.abs().amax(-1, keepdim=True) + xp.abs().amax(-1, keepdim=True))
    good = torch.isfinite(sol).all(-1, keepdim=True) & ((_mv(G, xp) - h) <= tol).all(-1, keepdim=True) & \
        (torch.where(active, lp, 0.0) >= -tol).all(-1, keepdim=True)
    lam_out = torch.where(good, torch.where(active, lp.clamp(min=0.0), 0.0), torch.where(active, lam, 0.0))
    return torch.where(good, xp, x), lam_out, active, good.squeeze(-1)


class _IPQP(torch.autograd.Function):
    @staticmethod
    def forward(ctx, H, g, G, h, iterations):
        dtype = H.dtype  # the Newton systems grow ill-conditioned as μ → 0: float64 inside
        H, g, G, h = (t.double() for t in (H, g, G, h))
        on = torch.isfinite(h)
        G = torch.where(on.unsqueeze(-1), G, 0.0)
        h = torch.where(on, h, 1.0)
        x, s, lam, ok = _interior_point(H, g, G, h, on, iterations)
        x, lam, active, polished = _polish(H, g, G, h, on, x, s, lam)
        ok = ok | polished
        ctx.save_for_backward(H, G, x, lam, active)
        ctx.mark_non_differentiable(active, ok)
        return x.to(dtype), lam.to(dtype), active, ok

    @staticmethod
    def backward(ctx, xbar, *_):
        H, G, x, lam, active = ctx.saved_tensors
        n, dtype, xbar = H.shape[-1], xbar.dtype, xbar.double()
        rhs = torch.cat((xbar, xbar.new_zeros(G.shape[:-1])), dim=-1)
        sol = torch.linalg.solve_ex(_kkt_matrix(H, G, active), rhs.unsqueeze(-1))[0].squeeze(-1)
        a, beta = sol[:, :n], torch.where(active, sol[:, n:], 0.0)
        G_bar = -lam.unsqueeze(-1) * a.unsqueeze(-2) - beta.unsqueeze(-1) * x.unsqueeze(-2)
        grads = (-a.unsqueeze(-1) * x.unsqueeze(-2), a, G_bar, beta)
        return (*(t.to(dtype) for t in grads), None)


def ip_solve(H: Tensor, g: Tensor, G: Tensor, h: Tensor, iterations: int):
    """``H (B, n, n), g (B, n), G (B, p, n), h (B, p)`` -> (x, λ, active, converged)."""
    return _IPQP.apply(H, g, G, h, iterations)
