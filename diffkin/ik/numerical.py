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

from .._numerics import eps_for
from ..chain import KinematicChain
from ..errors import ShapeError
from ..kernels.dls import dls_solve
from ..redundancy import _damped
from ..transforms import _transform_inverse, _transform_points, as_measured_transform
from ..validation import (
    check_count,
    check_given,
    check_nonnegative,
    check_number,
    check_trailing,
    shape_str,
    tensors,
)
from . import _seeds
from ._collision import CollisionConfig, collision_round, constraint_of, free_library
from ._collision_native import solve_batch as native_collision_solve
from ._kernel import BatchLastKernel, JointMap
from ._lm import LMConfig, Targets, run_lm
from ._native_solve import applies as native_applies
from ._native_solve import solve_batch as native_solve_batch
from ._native_solve import solve_one as native_solve_one
from .implicit import attach_solve_gradients
from .residuals import DistanceConstraint, PoseResidual
from .result import IKResult, final_errors

__all__ = ["dls_delta", "dls_step", "solve", "LMConfig"]


def dls_delta(J: Tensor, err: Tensor, damping=2.5e-3) -> Tensor:
    """Damped least-squares joint displacement Δq = Jᵀ(JJᵀ + λI)⁻¹ e  (3.59), λ = k².

    Args:
        J: Jacobian ``(..., r, n)`` (any task dimension r, e.g. 6 or 3).
        err: task-space error or desired displacement ``(..., r)``.
        damping: λ, added to JJᵀ's diagonal, eq. (3.59) (the textbook's k²; the unreleased 0.1.0 took k:
            its default 0.05 is 2.5e-3 here), >= 0, a float or a tensor
            broadcastable to ``(...)``.

    Returns ``(..., n)``; differentiable in J, err and damping. A damping at or below the rounding level of
    JJᵀ (zero included) gives the minimum-norm least-squares step J†e (finite at singular J).
    """
    J, err, lam = tensors(("J", J, (None, None)), ("err", err, None), ("damping", damping, None))
    check_trailing(err, (J.shape[-2],), "err")
    return _dls_delta(J, err, check_nonnegative(lam, "damping"))


def _dls_delta(J: Tensor, err: Tensor, k2: Tensor) -> Tensor:
    """:func:`dls_delta` of validated inputs (λ = k2): the LU solve, or J†e where λ is below rounding."""
    frob2 = (J * J).sum(dim=(-2, -1))
    if torch.compiler.is_compiling():
        # a graph has no data-dependent branch: a damping below rounding is raised to the rounding level
        # (positive, so the solve stays regular), instead of switching to the pseudo-inverse
        floor = (eps_for(J) * frob2).clamp_min(torch.finfo(J.dtype).tiny)
        return dls_solve(J, err, torch.maximum(k2, floor))
    small = k2 <= eps_for(J) * frob2
    if small.numel() and bool(small.any()):
        return (_damped(J, k2) @ err.unsqueeze(-1)).squeeze(-1)
    return dls_solve(J, err, k2)


def dls_step(
    chain: KinematicChain,
    q: Tensor,
    T_target: Tensor,
    damping=2.5e-3,
    position_only: bool = False,
    respect_limits: bool = True,
    step_size: float = 1.0,
) -> Tensor:
    """One damped least-squares step (3.59) from ``q (..., nq)`` toward ``T_target`` -> new ``q (..., nq)``.

    The error is [p_d - p_e; θr] (rotation vector of R_d R_eᵀ, base frame), ``T_target`` ``(..., 4, 4)``,
    or ``(..., 3)`` positions when ``position_only`` (``(..., K, 4, 4)`` / ``(..., K, 3)`` for a chain with K
    end links: their rows stacked). The step Δ ``(..., nv)`` (one entry per Jacobian
    column) is integrated on the configuration manifold, q ⊕ step_size·Δ
    (:meth:`~diffkin.chain.KinematicChain.integrate`: additive on 1-DOF joints, q ⊗ exp(ω/2) on the
    quaternions of ball and free joints). The result is clamped to the joint limits when
    ``respect_limits``. Pure and differentiable; batched over leading dims.

    ``damping`` is λ, added to JJᵀ's diagonal, eq. (3.59): Δ = Jᵀ(JJᵀ + λI)⁻¹ e (the textbook's k²; the
    unreleased 0.1.0 took k: its default 0.05 is 2.5e-3 here), as :func:`dls_delta`'s.
    """
    from ..jacobian import forward_kinematics_and_jacobian

    q = chain.check_q(q)
    check_given(T_target, "T_target", "poses (..., 4, 4) or positions (..., 3)")
    T_target, lam = tensors(("T_target", T_target, None), ("damping", damping, None), like=chain)
    full = T_target.ndim >= 2 and T_target.shape[-2:] == (4, 4)
    if position_only and not full:
        check_trailing(T_target, (3,), "T_target")
    elif not full:
        raise ShapeError(f"expected T_target of shape (..., 4, 4){' or (..., 3)' if position_only else ''}, "
                         f"got {shape_str(T_target.shape)}")
    T_e, J = forward_kinematics_and_jacobian(chain, q, check=False)
    residual = PoseResidual(position_only, 1.0, exact_near_pi=True)  # far from a solution: exact near π
    e, J = residual.error(T_e, T_target), residual.rows(J)
    if not chain.single_end:  # K end links: their rows stacked, e (..., rK), J (..., rK, nv)
        e, J = e.flatten(-2), J.flatten(-3, -2)
    e, J = torch.broadcast_tensors(e, J[..., 0])[0], J.expand(*e.shape[:-1], *J.shape[-2:])
    q_new = chain.configuration_space.integrate(q, step_size * _dls_delta(J, e, lam))  # q ⊕ Δ, Δ (..., nv)
    return chain.clamp_to_limits(q_new, check=False) if respect_limits else q_new


# ------------------------------------------------------------------------------------------- solve
def _targets(chain, T_target, position_only: bool, dtype) -> tuple[tuple[int, ...], Tensor, Targets]:
    """Validated targets (:func:`_valid_targets`) -> (batch, the targets detached (poses re-orthonormalised),
    their batch-last columns in the working dtype)."""
    T_target = T_target.detach()
    K = chain.n_ends
    pos_input, batch = _target_batch(chain, T_target, position_only)
    if pos_input:
        pd = T_target.reshape(-1, K * 3).T.to(dtype)
        return batch, T_target, Targets(pd.contiguous(), None, None, None)
    T_target = as_measured_transform(T_target, "T_target")  # RIGIDITY_TOLERANCE (1e-3), re-orthonormalised
    # the four columns of every end link's pose, batch last: (4, 3K, N) in one copy
    cols = T_target.reshape(-1, K, 4, 4)[:, :, :3].permute(3, 1, 2, 0).to(dtype).reshape(4, 3 * K, -1)
    cols = cols.contiguous().unbind(0)
    if position_only:
        return batch, T_target, Targets(cols[3], None, None, None)
    return batch, T_target, Targets(cols[3], cols[0], cols[1], cols[2])


def _target_batch(chain, T_target: Tensor, position_only: bool) -> tuple[bool, tuple[int, ...]]:
    """(positions given, the batch dims) of targets ``(..., [K,] 4, 4)`` or, with ``position_only``,
    ``(..., [K,] 3)``; :class:`ShapeError` for any other shape."""
    K, tree = chain.n_ends, not chain.single_end
    ends = (K,) if tree else ()
    if position_only and T_target.ndim >= 1 and T_target.shape[-1] == 3:
        if tuple(T_target.shape[-1 - len(ends) : -1]) != ends:
            raise ShapeError(f"expected target positions of shape (..., {K}, 3) for the {K} end links of "
                             f"chain '{chain.name}', got {shape_str(T_target.shape)}")
        return True, tuple(T_target.shape[: T_target.ndim - 1 - len(ends)])
    want = f"(..., {K}, 4, 4)" if tree else "(..., 4, 4)"
    tail = tuple(T_target.shape[max(T_target.ndim - 2 - len(ends), 0) :])
    if T_target.ndim < 2 + len(ends) or tail != (*ends, 4, 4):
        want = f"{want} or {want[:-6]}3)" if position_only else want
        raise ShapeError(f"expected T_target of shape {want}, got {shape_str(T_target.shape)}")
    return False, tuple(T_target.shape[: T_target.ndim - 2 - len(ends)])


def _targets_in_base(chain, T_target: Tensor, base, position_only: bool) -> Tensor:
    """World targets in the chain's base frame: base⁻¹ T (poses) or Rᵀ (p − t) (positions), per row; the
    K end links of a tree share their row's base. The targets' shape and the base's batch dims are checked
    first (:class:`ShapeError`)."""
    _, batch = _target_batch(chain, T_target, position_only)
    B_inv = _transform_inverse(chain._row_base(base, True, batch, of="T_target"))
    if not chain.single_end:
        B_inv = B_inv.unsqueeze(-3)
    if position_only and T_target.shape[-1] == 3:
        return _transform_points(B_inv, T_target)
    return B_inv @ T_target


def _valid_targets(chain, T_target) -> Tensor:
    """T_target by the rule of :mod:`diffkin.validation`: the chain's dtype and device, finite."""
    check_given(T_target, "T_target", "poses (..., 4, 4) or positions (..., 3)")
    return tensors(("T_target", T_target, None), like=chain)[0]


def _user_seeds(chain, q0, batch: tuple[int, ...], N: int) -> Tensor | None:
    """q0 ``(n,)``, ``(..., n)`` or ``(..., S, n)`` broadcastable to the target batch -> ``(N, S, n)``."""
    if q0 is None:
        return None
    q0 = chain.check_q(q0, "q0")
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
        score = sol.success.to(torch.int8) * 2 + sol.within_limits.to(torch.int8)
        order = torch.argsort(-score, dim=-1, stable=True)
        seeds = torch.take_along_dim(sol.q, order[..., None], dim=-2)
    if q0 is None:
        return seeds
    user = _user_seeds(chain, q0, batch, math.prod(batch))  # the one broadcast rule for seeds, (N, S, n)
    return torch.cat((seeds, user.reshape(*batch, *user.shape[-2:])), dim=-2)


def _check_tolerances(*tols) -> None:
    for t in tols:
        check_number(t, "IK tolerances")


def _compute_dtype(chain, cfg: LMConfig, tol: float) -> torch.dtype:
    if cfg.compute_dtype is not None:
        return cfg.compute_dtype
    return torch.float64 if chain.dtype == torch.float64 or tol < 1e-5 else torch.float32


def solve(
    chain: KinematicChain,
    T_target: Tensor | None = None,
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
    base: Tensor | None = None,
    collision=None,
    world=None,
    margin: float = 0.0,
    tasks=None,
    limits=None,
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
        damping: λ̄, the constant part of the LM damping λ = λ̄ + μ‖e‖² added to JJᵀ's diagonal, eq. (3.59)
            (the textbook's k²; the unreleased 0.1.0 took k: its default 3e-3 is 9e-6 here);
            overrides ``config.damping``.
        config: :class:`LMConfig` (damping, orientation weight, seeding and scheduling knobs).
        generator / seed: randomness for seeds (a fresh generator from ``seed`` if given).
        progress: print one line per scheduling round.
        seeds_from_closed_form: seed with every branch of :func:`~diffkin.ik.closed_form` (valid branches
            within the limits first, then valid ones, then the rest), ahead of ``q0`` if given: exact,
            all-branch-aware solving (LM only polishes). Raises :class:`~diffkin.errors.ModelError` when the
            chain has no closed form (see :func:`~diffkin.ik.identify_structure`).
        base: per-target world poses of the chain's base ``(..., 4, 4)`` (broadcasting with the target
            batch): ``T_target`` is then in the world (robots at different places in one call).
        collision: a :class:`~diffkin.collision.RobotCollision` of the chain: success then also needs
            every checked distance (its self pairs, and with ``world`` every geom to every object of a
            :class:`~diffkin.collision.World` in the base frame, one world for all targets) >= ``margin``
            (m). The distances are constraints of the solve: seeds come from collision-free library
            poses, and targets whose solution collides are solved again from other seeds — on the CPU in
            rounds of the whole C solve, each round checked in one batch
            (:mod:`diffkin.ik._collision_native`), elsewhere or with ``LMConfig(collision_refine_calls=1)``
            in the scheduled loop with an acceptance test and optionally a constrained Gauss–Newton
            refinement (:mod:`diffkin.ik._collision`).
        tasks, limits: the same problem as objects (:mod:`diffkin.ik._from_tasks`): one pose
            :class:`~diffkin.ik.FrameTask` per end link instead of ``T_target`` (orientation costs 0:
            ``position_only``; a zero cost on some axes only is a ConventionError: it leaves rows free,
            which ``ik.optimize`` and ``ik.solve_velocity`` honour and the pose solve cannot);
            :class:`~diffkin.ik.ConfigurationLimit` for ``respect_limits``,
            :class:`~diffkin.ik.CollisionLimit` for ``collision`` / ``world`` / ``margin``.

    Returns:
        :class:`IKResult` with per-target ``q``, ``success``, errors (from an exact FK in the chain's dtype),
        ``iterations`` and ``seeds_tried``. Never raises for unreachable targets and never returns NaN.

    With ``collision`` the success flag is decided by the exact distances of ``collision`` at the returned
    ``q`` in the chain's dtype (``success`` never marks a configuration in collision); the implicit
    gradients are those of the pose condition (exact where no distance constraint is active).

    The iteration runs in the chain's dtype (float64 when a float32 chain is asked for tolerances below
    1e-5; see :class:`LMConfig`); success is decided by an exact FK of the result in the chain's dtype.

    **Gradients.** With grad mode on and ``T_target`` or a chain parameter requiring grad, ``q`` is
    differentiable w.r.t. both by the implicit function theorem at the solution (:mod:`diffkin.ik.implicit`):
    dq = J⁻¹ dx for a square Jacobian, the minimum-norm J⁺ dx for a redundant chain (no null-space part),
    the position rows only with ``position_only``, the K end links stacked for a tree, and
    dq = −J⁺ J_θ dθ for the parameters. Backward costs one batched factorisation with J at the solution
    (damped by λ̄(1 − σ_min²/λ̄) only where σ_min(J) < √λ̄, λ̄ = ``damping``, plus 10 ε: exact up to a
    relative 10 ε/σ_min² where σ_min >= √λ̄, amplification at most 1/√λ̄ at singular solutions); failed targets
    get a zero gradient.
    ``T_target (..., K, 4, 4)`` (or ``(..., K, 3)``) for a chain with K end links: success needs all K.
    """
    if tasks is not None or limits is not None:  # the objects, translated to the arguments below
        from ._from_tasks import solve_arguments

        T_target, position_only, respect_limits, collision, world, margin = solve_arguments(
            chain, T_target, tasks, limits, position_only, respect_limits, collision, world, margin)
    if q0 is None and base is None and config is None and damping is None and collision is None \
            and world is None and not (  # one pose: lean path
            position_only or progress or seeds_from_closed_form or not respect_limits):
        fast = native_solve_one(chain, T_target, generator, seed, num_seeds=num_seeds,
                                       max_iterations=max_iterations,
                                       tol=(position_tolerance, orientation_tolerance))
        if fast is not None:
            return fast
    _check_tolerances(position_tolerance, orientation_tolerance)
    num_seeds = check_count(num_seeds, "num_seeds")
    max_iterations = check_count(max_iterations, "max_iterations")
    if damping is not None:
        check_number(damping, "damping", positive=False)
    cfg = config or LMConfig()
    if damping is not None:
        cfg = dataclasses.replace(cfg, damping=float(damping))
    dtype, device = _compute_dtype(chain, cfg, min(position_tolerance, orientation_tolerance)), chain.device
    T_target = _valid_targets(chain, T_target)
    if base is not None:
        T_target = _targets_in_base(chain, T_target, base, position_only)
    batch, T_orig, tg = _targets(chain, T_target, position_only, dtype)
    N = math.prod(batch)
    if seeds_from_closed_form:
        q0 = _closed_form_seeds(chain, T_target, q0, batch)
    seeds_user = _user_seeds(chain, q0, batch, N)
    if generator is None:
        generator = torch.Generator(device=device)
        generator.manual_seed(seed if seed is not None else int(torch.randint(2**62, (), device="cpu")))
    residual = PoseResidual(position_only, cfg.orientation_weight)
    # the whole solve in one C call (CPU, no autograd)
    if collision is None and world is None and native_applies(chain, T_target, progress):
        out = native_solve_batch(
            chain, tg, batch, T_orig, seeds_user, cfg, generator, dtype, position_only=position_only,
            tol=(position_tolerance, orientation_tolerance), num_seeds=num_seeds,
            max_iterations=max_iterations, respect_limits=respect_limits)  # fmt: skip
        if out is not None:  # gradients at the solution, as below
            return dataclasses.replace(out, q=attach_solve_gradients(
                chain, out.q, T_target, out.success, residual, cfg.damping))
    constraint = constraint_of(chain, collision, world, margin, base)
    native = constraint is not None and cfg.collision_refine_calls == 0
    if native and native_applies(chain, T_target, progress):
        # rounds of the whole C solve, each checked in one batch (ik/_collision_native.py)
        out = native_collision_solve(
            chain, tg, batch, T_orig, seeds_user, cfg, generator, dtype, constraint,
            position_only=position_only, tol=(position_tolerance, orientation_tolerance), num_seeds=num_seeds,
            max_iterations=max_iterations, respect_limits=respect_limits)  # fmt: skip
        if out is not None:
            return dataclasses.replace(out, q=attach_solve_gradients(
                chain, out.q, T_target, out.success, residual, cfg.damping))
    kernel = BatchLastKernel(chain if chain.dtype == dtype else copy.deepcopy(chain).to(dtype))
    jmap = JointMap(chain, dtype, device, respect_limits)
    T_flat = T_orig.reshape(N, *T_orig.shape[len(batch) :])
    prob = _Problem(chain, kernel, jmap, tg, seeds_user, cfg, generator, (position_tolerance,
                    orientation_tolerance), num_seeds, max_iterations, residual, respect_limits, T_flat,
                    progress, None if constraint is None else constraint.to(dtype))  # fmt: skip
    with torch.no_grad():
        if N:
            prob.library()  # the fixed library's nearest poses (ik/_seeds.py)
        q, success, pos_err, ori_err, iters, seeds = prob.run()
        if constraint is not None:
            q, success, pos_err, ori_err, iters, seeds = collision_round(
                prob, constraint, q, success, pos_err, ori_err, iters, seeds)
    q = q.reshape(*batch, chain.n_joints).contiguous()
    success, pos_err, ori_err = (t.reshape(batch) for t in (success, pos_err, ori_err))
    # a differentiable layer: gradients w.r.t. T_target and the chain's parameters by the implicit function
    # theorem at the solution (diffkin.ik.implicit); the iterations above ran without autograd
    q = attach_solve_gradients(chain, q, T_target, success, residual, cfg.damping)
    return IKResult(
        q=q, success=success, position_error=pos_err, orientation_error=ori_err,
        iterations=iters.reshape(batch), seeds_tried=seeds.reshape(batch),
    )  # fmt: skip


@dataclasses.dataclass
class _Problem:
    """One :func:`solve` call's fixed inputs; :meth:`run` solves all targets or a subset of them."""

    chain: KinematicChain
    kernel: BatchLastKernel
    jmap: JointMap
    tg: Targets
    seeds_user: Tensor | None
    cfg: LMConfig
    generator: torch.Generator
    tol: tuple[float, float]
    num_seeds: int
    max_iterations: int
    residual: PoseResidual
    respect_limits: bool
    T_flat: Tensor
    progress: bool
    constraint: DistanceConstraint | None  # in the working dtype
    lib_u: Tensor | None = None
    nn_idx: Tensor | None = None

    def library(self) -> None:
        """The fixed library seeds (:mod:`._seeds`; collision-free ones with a constraint,
        :func:`free_library` of 4 ``library_size`` draws) and each target's nearest ranks."""
        c, cfg, jm = self.constraint, self.cfg, self.jmap
        L = max(cfg.library_size, 0)
        R = _seeds.ranks(L, self.kernel.K, cfg.library_ranks)
        if R == 0:
            return
        if c is None:
            lib_u = _seeds.library_u(jm, L)
        else:
            lib_u = _seeds.library_u(jm, 4 * L)
            lib_u = lib_u[:, free_library(jm.q_of_u(lib_u), c, CollisionConfig.slack, L)]
            R = _seeds.ranks(lib_u.shape[1], self.kernel.K, cfg.library_ranks)
            if R == 0:
                return
        x, y, z, p = self.kernel.fk(jm.q_of_u(lib_u))
        lib_f = _seeds.library_features(x, y, z, p, self.tg.position_only)
        self.lib_u, self.nn_idx = lib_u, _seeds.nearest(self.tg, lib_f, R, cfg.orientation_weight)

    def run(self, sub: Tensor | None = None, first: Tensor | None = None, accept=None):
        """LM on the targets ``sub`` (None: all), ``first (m, n)`` tried before the user's seeds (then the
        library ranks skip their nearest), ``accept`` as in :func:`run_lm` -> (q ``(m, n)`` in the chain's
        dtype, success, position error, orientation error, iterations, seeds tried), each ``(m,)``."""
        chain, jm, tg, seeds, nn = self.chain, self.jmap, self.tg, self.seeds_user, self.nn_idx
        if sub is not None:
            tg, seeds = tg.take(sub), None if seeds is None else seeds[sub]
            nn = None if nn is None else nn[sub].roll(-1, 1)
        if first is not None:
            seeds = first[:, None] if seeds is None else torch.cat((first[:, None], seeds), 1)
        m, num_seeds = tg.pd.shape[1], self.num_seeds + (first is not None)
        user_u = None
        if seeds is not None:
            S = min(seeds.shape[1], max(num_seeds, 1))
            flat = seeds[:, :S].to(tg.pd.dtype).reshape(-1, chain.n_joints).T
            user_u = jm.u_of_q(flat).T.reshape(m, S, chain.n_joints)
        S, R = 0 if user_u is None else user_u.shape[1], 0 if nn is None else nn.shape[1]
        pool = _seeds.draw_pool(self.generator, _seeds.pool_size(m, num_seeds, S, R), jm.space.n_uniform,
                                tg.pd.dtype)
        pool = _seeds.SeedPool(jm, user_u, self.lib_u, nn, pool, num_seeds)
        u, iters, tried = run_lm(
            self.kernel, jm, tg, pool, m, self.cfg, tol=self.tol, num_seeds=num_seeds,
            max_iterations=self.max_iterations, residual=self.residual, accept=accept, progress=self.progress)
        limited = self.respect_limits and chain.q_limits is not None
        q = jm.finalize(jm.q_of_u(u), clamp=limited).T.to(chain.dtype)
        T = self.T_flat if sub is None else self.T_flat[sub]
        pos_err, ori_err = final_errors(chain, q, T, self.residual.position_only)
        success = pos_err <= self.tol[0]
        if not self.residual.position_only:
            success &= ori_err <= self.tol[1]
        if limited:
            success &= chain.within_limits(q, check=False)
        return q, success, pos_err, ori_err, iters, tried
