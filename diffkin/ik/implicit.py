"""IK as a differentiable layer: gradients of IK solutions by the implicit function theorem (private).

A solver returns q* with F(q*, z) = 0 (:func:`~diffkin.ik.solve`: the pose error) or ∇_q C(q*, z) = 0
(:func:`~diffkin.ik.optimize`: a stationary cost), where z collects what the caller may differentiate: the
targets and the chain's parameters. The iterations run without autograd; the result is attached to the graph
by an autograd Function whose backward differentiates that condition at the solution only:

* solve: dq* = −(∂F/∂q)⁺ ∂F/∂z dz with ∂F/∂q = −J (3.30) at a solution (rows [p; w·θr] per end link, the
  position rows only for ``position_only``), so dq* = J⁺ (∂F/∂z dz): J⁻¹ for a square J, the minimum-norm
  J⁺ = Jᵀ(JJᵀ)⁻¹ for a redundant chain (no null-space component). The backward of a gradient g is one
  batched factorisation, u = (JJᵀ + λI)⁻¹ J g (the kernel's DLS), damped by the rule of ``optimize``:
  λ = k² (1 − (σ_min/k)²) only where σ_min(J) < k (k² = λ̄: the solver's ``damping``, default 9e-6, so
  k = 3e-3), plus a floor of
  10 ε (ε: the dtype's machine epsilon). Where σ_min >= k the gradient is exact up to a relative 10 ε/σ_min²
  (< 3e-10 in float64); below, each direction is scaled by σ/(σ² + λ) = σ/k² <= 1/k instead of 1/σ, so
  ‖u‖ <= ‖g‖/k at singular solutions (no NaN, no blow-up); then one vector–Jacobian product of F w.r.t. z
  with cotangent u — the FK kernel and the pose error differentiate themselves, so every parameter kind (DH,
  Hayati β, URDF origins and axes, base, tool) and the targets get their gradient with no hand-written ∂F/∂z.
* optimize: dq* = −H⁻¹ ∂(∇_q C)/∂z dz with H = ∇²_q C (Hessian–vector products through autograd), damped
  by λ = k² (1 − (σ_min/k)²) only where σ_min(H) < k (k² = ``optimize``'s ``damping``). Costs that are not
  twice differentiable (a user's callable, kinks) can use ``unroll=True`` instead.

Failed targets (``success`` False) get a zero gradient: they satisfy no condition to differentiate.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..kernels.dls import adaptive_damping, dls_solve
from .residuals import PoseResidual

__all__ = ["attach_solve_gradients", "attach_stationary_gradients", "wants_gradients"]


def wants_gradients(chain, T_target: Tensor) -> bool:
    """Grad mode on and the target or some chain parameter requires grad."""
    params = chain.parameters()
    return torch.is_grad_enabled() and (T_target.requires_grad or any(p.requires_grad for p in params))


class _AtSolution(torch.autograd.Function):
    """Forward: the solver's ``q`` (computed outside autograd) as a node whose inputs are the target and the
    parameters; subclasses differentiate the solver's optimality condition in ``backward``."""

    @staticmethod
    def forward(ctx, q: Tensor, T_target: Tensor, spec: tuple, *params: Tensor) -> Tensor:
        ctx.spec = spec
        ctx.save_for_backward(q, T_target)
        return q.clone()


class _ImplicitSolve(_AtSolution):
    @staticmethod
    def backward(ctx, g: Tensor):
        q, T_target = ctx.saved_tensors
        chain, success, residual, lam, params = ctx.spec
        with torch.no_grad():
            J = residual.jacobian(chain, q)  # −∂F/∂q at the solution
            lam = _solve_damping(J, lam)
            g = chain.configuration_space.pullback(q, g)  # dq = (∂q/∂v) dv on ball and free joints
            # u = (J⁺)ᵀ g = (JJᵀ + λI)⁻¹ J g = J (JᵀJ + λI)⁻¹ g: the kernel's DLS solve on Jᵀ
            u = dls_solve(J.transpose(-1, -2), g, lam) * success.unsqueeze(-1).to(g.dtype)
        wrt_T = T_target.requires_grad or ctx.needs_input_grad[1]
        with torch.enable_grad():
            T_d = T_target.detach().requires_grad_(wrt_T)
            F = residual.value(chain, q.detach(), T_d)
            inputs = ([T_d] if wrt_T else []) + list(params)
            grads = torch.autograd.grad(F, inputs, grad_outputs=u, allow_unused=True) if inputs else []
        grad_T = grads[0] if wrt_T else None
        grad_params = grads[1:] if wrt_T else grads
        grad_params = [None if gp is None else gp for gp in grad_params]
        return (None, grad_T, None, *grad_params)


def _solve_damping(J: Tensor, k2: float) -> Tensor:
    """λ ``(...)`` of the solve backward: the rule of ``optimize``'s (:func:`adaptive_damping`, threshold
    k = √k2) on J, so zero where σ_min(J) >= k, plus 10 ε (a floor: an exactly singular J, or k = 0, stays
    finite)."""
    floor = 10.0 * torch.finfo(J.dtype).eps
    if k2 <= 0.0:
        return torch.full(J.shape[:-2], floor, dtype=J.dtype, device=J.device)
    return adaptive_damping(J, k2, k2**0.5) + floor


def attach_solve_gradients(chain, q: Tensor, T_target: Tensor, success: Tensor, residual: PoseResidual,
                           damping: float) -> Tensor:
    """``q`` with the implicit gradient of :func:`~diffkin.ik.solve` (the condition F = 0 of the pose
    ``residual``, :class:`~diffkin.ik.residuals.PoseResidual`) w.r.t. ``T_target`` and the chain's
    parameters that require grad (no-op when nothing does); ``damping``: the solver's λ̄ = k²."""
    if not wants_gradients(chain, T_target):
        return q
    params = tuple(p for p in chain.parameters() if p.requires_grad)
    spec = (chain, success.detach(), residual, float(damping), params)
    return _ImplicitSolve.apply(q.detach(), T_target, spec, *params)


def _independent(A: Tensor, keep: Tensor) -> Tensor:
    """``keep (..., k)`` less the rows of ``A (..., k, n)`` that depend on kept rows before them
    (Gram–Schmidt, relative tolerance 1e-8): a geom listed twice, or two pairs touching at one point, hold
    the point once."""
    basis, out = [], keep.clone()
    for i in range(A.shape[-2]):
        r = A[..., i, :]
        for b in basis:
            r = r - (r * b).sum(-1, keepdim=True) * b
        norm = r.norm(dim=-1)
        out[..., i] &= norm > 1e-8 * A[..., i, :].norm(dim=-1)
        unit = r / norm.clamp_min(1e-300)[..., None]
        basis.append(torch.where(out[..., i, None], unit, torch.zeros_like(r)))
    return out


def _active_constraints(a_fn, active: Tensor, qv: Tensor, gq: Tensor):
    """(a ``(..., k)``, A = ∂a/∂q ``(..., k, n)`` with create_graph, multipliers λ ``(..., k)`` detached,
    the rows kept): the rows held at the boundary with λ > 0 in ∇C = Aᵀλ (least squares); a row whose
    multiplier is not positive does not hold the point and is dropped (one pass)."""
    a = a_fn(qv)
    A = torch.stack([torch.autograd.grad(a[..., i].sum(), qv, create_graph=True)[0]
                     for i in range(a.shape[-1])], dim=-2)
    keep = _independent(A.detach(), active)
    lam = None
    for _ in range(2):
        Am = (A * keep.unsqueeze(-1).to(A.dtype)).detach()
        eye = torch.eye(a.shape[-1], dtype=A.dtype, device=A.device)
        M = Am @ Am.mT + torch.diag_embed((~keep).to(A.dtype)) + 1e-12 * eye
        lam = torch.linalg.solve(M, (Am @ gq.detach().unsqueeze(-1))).squeeze(-1)
        keep = keep & (lam > 0)
    return a, A, (lam * keep.to(lam.dtype)).detach(), keep


class _ImplicitStationary(_AtSolution):
    @staticmethod
    def backward(ctx, g: Tensor):
        q, T_target = ctx.saved_tensors
        cost_fn, success, lam, params, kkt = ctx.spec
        wrt_T = T_target.requires_grad or ctx.needs_input_grad[1]
        n = q.shape[-1]
        with torch.enable_grad():
            qv = q.detach().requires_grad_(True)
            T_d = T_target.detach().requires_grad_(wrt_T)
            (gq,) = torch.autograd.grad(cost_fn(qv, T_d).sum(), qv, create_graph=True)
            if kkt is not None:  # ∇_q L of the Lagrangian L = C − λᵀa at the KKT point
                a, A, mult, keep = _active_constraints(*kkt, qv, gq)
                gq = gq - (A.mT @ mult.unsqueeze(-1)).squeeze(-1)
            # H = ∇²_q C (or ∇²_q L) by n Hessian-vector products (samples are independent: one pass a column)
            cols = [torch.autograd.grad(gq[..., i].sum(), qv, retain_graph=True)[0] for i in range(n)]
            H = torch.stack(cols, dim=-1)
            H = 0.5 * (H + H.transpose(-1, -2))
            # damped only where H is nearly singular (σ_min < k): exact elsewhere, bounded there
            lam = adaptive_damping(H.detach(), lam, lam**0.5)[..., None, None]
            eye = torch.eye(n, dtype=q.dtype, device=q.device)
            keep_u = success.unsqueeze(-1).to(q.dtype)
            if kkt is None:
                u = torch.linalg.solve(H + lam * eye, g.unsqueeze(-1)).squeeze(-1) * keep_u
                outputs, cotangents = gq, -u
            else:  # [H Aᵀ; A 0][u; v] = [g; 0] on the kept rows (an identity block on the others: v = 0)
                Am = A.detach() * keep.unsqueeze(-1).to(q.dtype)
                K = torch.cat((torch.cat((H + lam * eye, Am.mT), -1),
                               torch.cat((Am, -torch.diag_embed((~keep).to(q.dtype))), -1)), -2)
                rhs = torch.cat((g, g.new_zeros(*g.shape[:-1], Am.shape[-2])), -1)
                uv = torch.linalg.solve(K, rhs.unsqueeze(-1)).squeeze(-1) * success.unsqueeze(-1).to(q.dtype)
                outputs, cotangents = (gq, a), (-uv[..., :n], -uv[..., n:] * keep.to(q.dtype))
            inputs = ([T_d] if wrt_T else []) + list(params)
            grads = torch.autograd.grad(outputs, inputs, grad_outputs=cotangents, allow_unused=True) \
                if inputs else []
        grad_T = grads[0] if wrt_T else None
        grad_params = grads[1:] if wrt_T else grads
        return (None, grad_T, None, *grad_params)


def attach_stationary_gradients(chain, q: Tensor, T_target: Tensor, success: Tensor, cost_fn,
                                damping: float, kkt=None) -> Tensor:
    """``q`` with the implicit gradient of a stationary point of ``cost_fn(q, T) -> (...)`` (per sample)
    w.r.t. ``T_target`` and the chain's parameters that require grad (no-op when nothing does);
    ``damping``: optimize's λ = k².

    ``kkt = (a_fn, active)``: q is a KKT point of min C s.t. a(q) ≥ const, ``a_fn(q) -> (..., k)`` the
    constraint rows (differentiable in q and the parameters) and ``active (..., k)`` those held at the
    boundary; the rows with a positive multiplier are differentiated as equalities:
    [∇²L Aᵀ; A 0][dq; dν] = −[∂_z∇_q L dz; ∂_z a dz], L = C − λᵀa (the constraints' curvature included)."""
    if not wants_gradients(chain, T_target):
        return q
    params = tuple(p for p in chain.parameters() if p.requires_grad)
    spec = (cost_fn, success.detach(), float(damping), params, kkt)
    return _ImplicitStationary.apply(q.detach(), T_target, spec, *params)
