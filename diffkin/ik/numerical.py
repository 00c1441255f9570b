"""Batched numerical IK: damped least squares / Levenberg–Marquardt with joint limits (§3.7, (3.59)).

:func:`solve` runs Levenberg–Marquardt over a compacting set of (target, seed) rows, batch last, with the
joint limits as a change of variables and restarts seeded from a sampled pose library (see :mod:`._lm` and
:mod:`._kernel`). :func:`dls_step` and :func:`dls_delta` are the one-step building blocks that closed-loop
IK and the environments reuse.
"""

from __future__ import annotations

import copy
import dataclasses
import math

import torch
from torch import Tensor

from ..chain import KinematicChain
from ..errors import DTypeError, ShapeError
from ..kernels.dls import dls_solve
from ..transforms import as_measured_transform, pose_error
from ..validation import check_finite, check_shape, check_tensor, shape_str
from ._kernel import BatchLastKernel, JointMap
from ._lm import LMConfig, Targets, library_seeds, run_lm
from .implicit import attach_solve_gradients
from .result import IKResult, final_errors

__all__ = ["dls_delta", "dls_step", "solve", "LMConfig"]


def dls_delta(J: Tensor, err: Tensor, damping=0.05) -> Tensor:
    """Damped least-squares joint displacement Δq = Jᵀ(JJᵀ + k²I)⁻¹ e  (3.59).

    Args:
        J: Jacobian ``(..., r, n)`` (any task dimension r, e.g. 6 or 3).
        err: task-space error or desired displacement ``(..., r)``.
        damping: k, a float or a tensor broadcastable to ``(...)``.

    Returns ``(..., n)``; differentiable in J, err and damping.
    """
    check_tensor(J, "J")
    if J.ndim < 2:
        raise ShapeError(f"expected J of shape (..., r, n), got {shape_str(J.shape)}")
    check_shape(err, (J.shape[-2],), "err")
    return dls_solve(J, err, torch.as_tensor(damping, dtype=J.dtype, device=J.device) ** 2)


def dls_step(
    chain: KinematicChain,
    q: Tensor,
    T_target: Tensor,
    damping=0.05,
    position_only: bool = False,
    respect_limits: bool = True,
    step_size: float = 1.0,
) -> Tensor:
    """One damped least-squares step (3.59) from ``q (..., n)`` toward ``T_target`` -> new ``q (..., n)``.

    The error is [p_d - p_e; θr] (rotation vector of R_d R_eᵀ, base frame), ``T_target`` ``(..., 4, 4)``,
    or ``(..., 3)`` positions when ``position_only``. The result is clamped to the joint limits when
    ``respect_limits``. Pure and differentiable; batched over leading dims.
    """
    from ..jacobian import forward_kinematics_and_jacobian

    T_e, J = forward_kinematics_and_jacobian(chain, q)
    if position_only:
        full = T_target.ndim >= 2 and T_target.shape[-2:] == (4, 4)
        p_d = T_target[..., :3, 3] if full else check_shape(T_target, (3,), "T_target")
        e, J = p_d - T_e[..., :3, 3], J[..., :3, :]
    else:
        e = pose_error(check_shape(T_target, (4, 4), "T_target"), T_e, orientation="rotvec")
    q_new = q + step_size * dls_delta(J, e, damping)
    return chain.clamp_to_limits(q_new) if respect_limits else q_new


# ------------------------------------------------------------------------------------------- solve
def _targets(chain, T_target, position_only: bool, dtype) -> tuple[tuple[int, ...], Tensor, Targets]:
    check_tensor(T_target, "T_target")
    T_target = T_target.detach()
    if T_target.dtype != chain.dtype:
        raise DTypeError(f"T_target has dtype {T_target.dtype} but chain '{chain.name}' is {chain.dtype}")
    if T_target.device != chain.device:
        raise ValueError(f"T_target is on {T_target.device} but chain '{chain.name}' is on {chain.device}")
    K, tree = chain.n_ends, not chain.single_end
    ends = (K,) if tree else ()
    pos_input = position_only and T_target.ndim >= 1 and T_target.shape[-1] == 3
    if pos_input:
        if tuple(T_target.shape[-1 - len(ends) : -1]) != ends:
            raise ShapeError(f"expected target positions of shape (..., {K}, 3) for the {K} end links of "
                             f"chain '{chain.name}', got {shape_str(T_target.shape)}")
        check_finite(T_target, "T_target")
        batch = tuple(T_target.shape[: T_target.ndim - 1 - len(ends)])
        pd = T_target.reshape(-1, K * 3).T.to(dtype)
        return batch, T_target, Targets(pd.contiguous(), None, None, None)
    want = f"(..., {K}, 4, 4)" if tree else "(..., 4, 4)"
    tail = tuple(T_target.shape[max(T_target.ndim - 2 - len(ends), 0) :])
    if T_target.ndim < 2 + len(ends) or tail != (*ends, 4, 4):
        want = f"{want} or {want[:-6]}3)" if position_only else want
        raise ShapeError(f"expected T_target of shape {want}, got {shape_str(T_target.shape)}")
    T_target = as_measured_transform(T_target, "T_target")  # 1e-5 tolerance, re-orthonormalised
    batch = tuple(T_target.shape[: T_target.ndim - 2 - len(ends)])
    Tt = T_target.reshape(-1, K, 4, 4).to(dtype).permute(1, 2, 3, 0)  # (K, 4, 4, N)
    cols = [Tt[:, :3, j].reshape(3 * K, -1).contiguous() for j in range(4)]
    if position_only:
        return batch, T_target, Targets(cols[3], None, None, None)
    return batch, T_target, Targets(cols[3], cols[0], cols[1], cols[2])


def _user_seeds(chain, q0, batch: tuple[int, ...], N: int) -> Tensor | None:
    """q0 ``(n,)``, ``(..., n)`` or ``(..., S, n)`` broadcastable to the target batch -> ``(N, S, n)``."""
    if q0 is None:
        return None
    chain.check_q(q0, "q0")
    n = chain.n_joints
    nb = len(batch)
    if q0.ndim - 1 <= nb:
        q0 = q0.unsqueeze(-2)
    elif q0.ndim - 2 != nb:
        raise ShapeError(
            f"expected q0 of shape (..., {n}) or (..., S, {n}) with leading dims broadcastable to the target "
            f"batch {shape_str(batch)}, got {shape_str(q0.shape)}"
        )
    try:
        q0 = q0.expand(*batch, q0.shape[-2], n)
    except RuntimeError:
        raise ShapeError(
            f"q0 of shape {shape_str(q0.shape)} does not broadcast to the target batch "
            f"{shape_str(batch)} (expected (..., {n}) or (..., S, {n}))"
        ) from None
    return q0.reshape(N, q0.shape[-2], n)


def _closed_form_seeds(chain, T_target, q0, batch) -> Tensor:
    """Closed-form branches ``(..., k, n)`` ordered valid-and-within-limits first, then ``q0``'s seeds."""
    from .analytic import closed_form

    with torch.no_grad():
        sol = closed_form(chain, T_target.detach())
        score = sol.valid.to(torch.int8) * 2 + sol.within_limits.to(torch.int8)
        order = torch.argsort(-score, dim=-1, stable=True)
        seeds = torch.take_along_dim(sol.q, order[..., None], dim=-2)
    if q0 is None:
        return seeds
    user = _user_seeds(chain, q0, batch, math.prod(batch))  # the one broadcast rule for seeds, (N, S, n)
    return torch.cat((seeds, user.reshape(*batch, *user.shape[-2:])), dim=-2)


def _compute_dtype(chain, cfg: LMConfig, tol: float) -> torch.dtype:
    if cfg.compute_dtype is not None:
        return cfg.compute_dtype
    return torch.float64 if chain.dtype == torch.float64 or tol < 1e-5 else torch.float32


def solve(
    chain: KinematicChain,
    T_target: Tensor,
    q0: Tensor | None = None,
    *,
    num_seeds: int = 64,
    max_iterations: int = 16,
    position_tolerance: float = 1e-4,
    orientation_tolerance: float = 1e-3,
    position_only: bool = False,
    respect_limits: bool = True,
    damping: float | None = None,
    config: LMConfig | None = None,
    generator: torch.Generator | None = None,
    seed: int | None = None,
    progress: bool = False,
    seeds_from_closed_form: bool = False,
) -> IKResult:
    """Batched inverse kinematics by Levenberg–Marquardt with joint limits and restarts.

    Args:
        chain: any :class:`~diffkin.chain.KinematicChain`.
        T_target: target poses ``(..., 4, 4)`` (any leading dims, ``()`` included), or target positions
            ``(..., 3)`` when ``position_only``; ``(..., K, 4, 4)`` / ``(..., K, 3)`` for K end links.
        q0: optional seeds tried first: ``(n,)``, ``(..., n)`` (one per target) or ``(..., S, n)`` (S per
            target), leading dims broadcastable to the target batch.
        num_seeds: most seeds per target (user seeds, then nearest poses of a sampled library, then random).
        max_iterations: most LM iterations per seed (a seed that stops improving is dropped sooner).
        position_tolerance / orientation_tolerance: success thresholds [m] / [rad, angle of R_eᵀR_d].
        position_only: solve for the position only (3 rows of the Jacobian).
        respect_limits: keep every iterate within the chain's joint limits (q = c + h sin u).
        damping: constant LM damping k (λ = k² + μ‖e‖²); overrides ``config.damping``.
        config: :class:`LMConfig` (damping, orientation weight, seeding and scheduling knobs).
        generator / seed: randomness for seeds (a fresh generator from ``seed`` if given).
        progress: print one line per scheduling round.
        seeds_from_closed_form: seed with every branch of :func:`~diffkin.ik.closed_form` (valid branches
            within the limits first, then valid ones, then the rest), ahead of ``q0`` if given: exact,
            all-branch-aware solving (LM only polishes). Raises :class:`~diffkin.errors.ModelError` when the
            chain has no closed form (see :func:`~diffkin.ik.identify_structure`).

    Returns:
        :class:`IKResult` with per-target ``q``, ``success``, errors (from an exact FK in the chain's dtype),
        ``iterations`` and ``seeds_tried``. Never raises for unreachable targets and never returns NaN.

    The iteration runs in the chain's dtype (float64 when a float32 chain is asked for tolerances below
    1e-5; see :class:`LMConfig`); success is decided by an exact FK of the result in the chain's dtype.

    **Gradients.** With grad mode on and ``T_target`` or a chain parameter requiring grad, ``q`` is
    differentiable w.r.t. both by the implicit function theorem at the solution (:mod:`diffkin.ik.implicit`):
    dq = J⁻¹ dx for a square Jacobian, the minimum-norm J⁺ dx for a redundant chain (no null-space part),
    the position rows only with ``position_only``, the K end links stacked for a tree, and
    dq = −J⁺ J_θ dθ for the parameters. Backward costs one batched factorisation with J at the solution
    (damped by λ = (damping/100)² + 10 ε: negligible away from singularities, finite at them); failed targets
    get a zero gradient.
    ``T_target (..., K, 4, 4)`` (or ``(..., K, 3)``) for a chain with K end links: success needs all K.
    """
    cfg = config or LMConfig()
    if damping is not None:
        cfg = dataclasses.replace(cfg, damping=float(damping))
    dtype, device = _compute_dtype(chain, cfg, min(position_tolerance, orientation_tolerance)), chain.device
    batch, T_orig, tg = _targets(chain, T_target, position_only, dtype)
    N = math.prod(batch)
    if seeds_from_closed_form:
        q0 = _closed_form_seeds(chain, T_target, q0, batch)
    seeds_user = _user_seeds(chain, q0, batch, N)
    if generator is None:
        generator = torch.Generator(device=device)
        generator.manual_seed(seed if seed is not None else int(torch.randint(2**62, ()).item()))
    kernel = BatchLastKernel(chain if chain.dtype == dtype else copy.deepcopy(chain).to(dtype))
    jmap = JointMap(chain, dtype, device, respect_limits)
    n = chain.n_joints
    with torch.no_grad():
        lib_u, nn_idx = library_seeds(kernel, jmap, tg, cfg, generator) if N else (None, None)
        u_best, iters, seeds = run_lm(
            kernel, jmap, tg, seeds_user, lib_u, nn_idx, N, cfg, generator,
            tol=(position_tolerance, orientation_tolerance), num_seeds=num_seeds,
            max_iterations=max_iterations, progress=progress,
        )  # fmt: skip
        q = jmap.finalize(jmap.q_of_u(u_best), clamp=respect_limits and chain.q_limits is not None)
        q = q.T.to(chain.dtype).reshape(*batch, n).contiguous()
        pos_err, ori_err = final_errors(chain, q, T_orig, position_only)
    success = pos_err <= position_tolerance
    if not position_only:
        success &= ori_err <= orientation_tolerance
    if respect_limits and chain.q_limits is not None:
        success &= chain.within_limits(q)
    # a differentiable layer: gradients w.r.t. T_target and the chain's parameters by the implicit function
    # theorem at the solution (diffkin.ik.implicit); the iterations above ran without autograd
    q = attach_solve_gradients(chain, q, T_target, success, position_only, cfg.orientation_weight,
                               cfg.damping)
    return IKResult(
        q=q, success=success, position_error=pos_err, orientation_error=ori_err,
        iterations=iters.reshape(batch), seeds_tried=seeds.reshape(batch),
    )  # fmt: skip
