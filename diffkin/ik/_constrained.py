"""Distance constraints in :func:`diffkin.ik.optimize`'s Gauss–Newton (private).

With ``optimizer="gauss_newton"`` and a collision model, each Levenberg–Marquardt step is the QP

    min_Δ ½‖r + J_r Δ‖² + ½λ‖Δ‖²   s.t.   g_i + ∇g_i·Δ ≥ slack   (i: the k nearest within detection),
                                          |Δ_j| ≤ trust   (per sample: :func:`next_trust`),

g = d − margin, the penetration recovered by at most ``push`` metres a step (so the linearisation stays
valid and the QP feasible), solved by the interior point of :mod:`diffkin.ik._qp_ip`; the knobs are those of
:class:`~diffkin.ik._collision.CollisionConfig`. A step is accepted when the merit cost + ρ Σ max(0, −g)²
decreases (ρ = 1e6 m⁻²: a millimetre of penetration outweighs any pose residual below a millimetre), so
feasibility comes first and the pose error is reduced among feasible steps.

At the result, :func:`active_rows` lists the distances held at the boundary (g < 2 slack): the implicit
gradient (:mod:`diffkin.ik.implicit`) treats those with a positive multiplier as equalities of a KKT point.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..kernels.dls import dls_solve
from ._collision import CollisionConfig
from ._qp_ip import ip_solve
from .residuals import DistanceConstraint

__all__ = ["constrained_step", "next_trust", "merit", "active_rows", "VIOLATION_WEIGHT"]

VIOLATION_WEIGHT = 1e6  # ρ of the merit, m⁻²


def constrained_step(constraint: DistanceConstraint, Jr: Tensor, r: Tensor, lam: Tensor, q: Tensor,
                     trust: Tensor, cfg: CollisionConfig) -> Tensor:
    """The step Δ ``(..., n)`` of the module docstring at ``q (..., n)`` for residuals ``r (..., m)`` with
    Jacobian ``Jr (..., m, n)``, damping ``lam (...)`` and trust radius ``trust (...)`` (|Δ_j| ≤ trust)."""
    batch, n = q.shape[:-1], q.shape[-1]
    qf, Jf, rf = q.reshape(-1, n), Jr.reshape(-1, *Jr.shape[-2:]), r.reshape(-1, r.shape[-1])
    lf = lam.reshape(-1)
    tf = trust.reshape(-1, 1)
    g, rows, Jg = constraint.jacobian(qf, cfg.active, max(cfg.detection, cfg.slack))
    gk = g.gather(-1, rows)
    eye = torch.eye(n, dtype=q.dtype, device=q.device)
    H = Jf.mT @ Jf + lf[:, None, None] * eye
    lin = -(Jf.mT @ rf.unsqueeze(-1)).squeeze(-1)  # ip_solve minimises ½ΔᵀHΔ − linᵀΔ
    # g + ∇g·Δ ≥ slack  <=>  −∇g·Δ ≤ g − slack, recovering at most `push` a step; far rows switched off
    rhs = torch.maximum(gk - cfg.slack, gk.new_tensor(-cfg.push))
    rhs = torch.where(gk < cfg.detection, rhs, torch.full_like(rhs, float("inf")))
    B = qf.shape[0]
    G = torch.cat((-Jg, eye.expand(B, n, n), -eye.expand(B, n, n)), dim=-2)
    h = torch.cat((rhs, tf.expand(B, 2 * n)), dim=-1)
    # the unconstrained step where it meets every row (far from obstacles: exactly Gauss–Newton's step)
    free = -dls_solve(Jf, rf, lf)
    fits = ((G @ free.unsqueeze(-1)).squeeze(-1) <= h).all(-1, keepdim=True)
    dq = ip_solve(H, lin, G, h, cfg.qp_iterations)[0]
    dq = torch.where(torch.isfinite(dq), dq, torch.zeros_like(dq))
    dq = torch.where(fits, free, torch.maximum(torch.minimum(dq, tf), -tf))
    return dq.reshape(*batch, n)


def next_trust(trust: Tensor, dq: Tensor, accept: Tensor, cfg: CollisionConfig) -> Tensor:
    """The trust radius after a step: ``cfg.trust`` again when accepted, a quarter of the rejected step's
    largest component otherwise (the linearised distances held too far; near convergence a step rejected
    by rounding must not leave the radius small)."""
    return torch.where(accept, torch.full_like(trust, cfg.trust), 0.25 * dq.abs().amax(-1))


def merit(constraint: DistanceConstraint, q: Tensor, cost: Tensor) -> Tensor:
    """cost + ρ Σ max(0, −g)² ``(...)``, g the exact distances less the margin at ``q``."""
    g = constraint.value(q, 0.0)
    return cost + VIOLATION_WEIGHT * torch.relu(-g).square().sum(-1)


def active_rows(constraint: DistanceConstraint, q: Tensor, cfg: CollisionConfig) -> tuple[Tensor, Tensor]:
    """``(rows (..., k), active (..., k))``: the k nearest distances of ``q`` and which of them are held at
    the boundary (g < 2 slack: the QP's constraint g ≥ slack, met to the iteration's precision)."""
    with torch.no_grad():
        g = constraint.value(q, 2.0 * cfg.slack)
        k = min(cfg.active, g.shape[-1])
        rows = g.topk(k, dim=-1, largest=False).indices
        return rows, g.gather(-1, rows) < 2.0 * cfg.slack
