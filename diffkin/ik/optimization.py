"""Optimisation-based IK: minimise a sum of differentiable per-sample cost terms over a batch.

Cost terms are small frozen dataclasses evaluated on a shared :class:`CostContext` (FK and Jacobian are
computed once per evaluation). Terms with a ``residual`` (cost = weight·‖r‖²) can be minimised by
Gauss–Newton / Levenberg–Marquardt on the stacked residuals; any term works with the torch optimisers
(L-BFGS, Adam). Joint limits are enforced by projection after every step.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from .._numerics import broadcast_shapes
from ..errors import ConventionError, NonFiniteError, OptionError, ShapeError
from ..kernels.dls import dls_solve
from ..validation import as_tensor, check_count, check_number, shape_str
from ._collision import CollisionConfig, constraint_of
from ._constrained import active_rows, constrained_step, merit, next_trust
from .implicit import attach_stationary_gradients, wants_gradients
from .numerical import _check_tolerances, _targets, _user_seeds, _valid_targets
from .residuals import CostContext, PoseResidual, _residual_jacobian, _Term
from .result import IKResult, final_errors

__all__ = [
    "optimize",
    "PoseCost",
    "JointLimitCost",
    "RestPostureCost",
    "ManipulabilityCost",
    "CallableCost",
    "OPTIMIZERS",
]

OPTIMIZERS = ("lbfgs", "adam", "gauss_newton")
_LAM_MAX = 1e8  # the largest Levenberg–Marquardt damping λ: a step that fails there is a stationary point


@dataclass(frozen=True)
class PoseCost(_Term):
    """Pose error [p_d − p_e; w_o·θr] (rotation vector of R_dR_eᵀ, base frame); position only for (..., 3)."""

    orientation_weight: float = 0.3

    def residual(self, ctx: CostContext) -> Tensor:
        Td = ctx.T_target
        res = PoseResidual(Td.shape[-1] == 3, self.orientation_weight, exact_near_pi=True)
        return res.error(ctx.T, Td).reshape(*ctx.q.shape[:-1], -1)  # K end links: their rows stacked


@dataclass(frozen=True)
class JointLimitCost(_Term):
    """Quadratic penalty for joints within ``margin`` of a limit (zero inside the safe range): the scalar
    coordinates only (a ball or free joint's quaternion has no limits; its entries are not penalised)."""

    margin: float = 0.05

    def residual(self, ctx: CostContext) -> Tensor:
        lo, hi = ctx.chain.lower_upper()
        q = ctx.q
        space = ctx.chain.configuration_space
        if not space.euclidean:
            idx = list(space.scalar_index("q"))
            lo, hi, q = lo[idx], hi[idx], q[..., idx]
        return torch.relu(lo + self.margin - q) + torch.relu(q - (hi - self.margin))


@dataclass(frozen=True)
class RestPostureCost(_Term):
    """Distance to a rest posture ``q_rest`` (broadcastable to ``(..., nq)``; default: mid-range): the
    residual q ⊖ q_rest ``(..., nv)`` (the geodesic on ball and free joints)."""

    q_rest: Tensor | None = None

    def residual(self, ctx: CostContext) -> Tensor:
        if self.q_rest is None:
            lo, hi = ctx.chain.lower_upper()
            rest = 0.5 * (lo + hi)
        else:
            rest = torch.as_tensor(self.q_rest, dtype=ctx.q.dtype, device=ctx.q.device)
        # q ⊖ rest: q − rest on 1-DOF joints, the rotation vector between the quaternions of ball/free ones
        return ctx.chain.configuration_space.difference(rest.expand_as(ctx.q), ctx.q)


@dataclass(frozen=True)
class ManipulabilityCost(_Term):
    """−weight·w(q), w = sqrt(det JJᵀ) (3.56): rewards configurations away from singularities."""

    def __call__(self, ctx: CostContext) -> Tensor:
        from ..manipulability import manipulability

        return -self.weight * manipulability(ctx.J)


@dataclass(frozen=True)
class CallableCost(_Term):
    """A user term ``fn(q (..., n), T_target) -> (...)`` times ``weight``."""

    fn: Callable[[Tensor, Tensor], Tensor] | None = None

    def __call__(self, ctx: CostContext) -> Tensor:
        return self.weight * self.fn(ctx.q, ctx.T_target)


def _as_terms(costs) -> list[_Term]:
    """``costs`` as cost terms: None (the default ``[PoseCost()]``) or a non-empty list / tuple of cost
    objects and callables; their numeric fields are checked (:func:`_check_term`)."""
    if costs is None:
        return [PoseCost()]
    if isinstance(costs, _Term) or callable(costs) or not isinstance(costs, list | tuple):
        what = type(costs).__name__
        hint = f" (one term: costs=[{what}(...)])" if isinstance(costs, _Term) or callable(costs) else ""
        raise ConventionError(f"expected costs as a list of cost terms, got a {what}{hint}")
    if not costs:
        raise ConventionError("expected costs as a non-empty list of cost terms, got an empty one (None: the "
                              "default [PoseCost()])")
    terms = []
    for c in costs:
        if isinstance(c, _Term):
            terms.append(_check_term(c))
        elif callable(c):
            terms.append(CallableCost(fn=c))
        else:
            raise ConventionError(f"cost terms must be diffkin.ik cost objects or callables(q, T), got {c!r}")
    return terms


def _check_term(term: _Term) -> _Term:
    """A cost term's numeric fields by the one option rule (:func:`~diffkin.validation.check_number`):
    ``weight`` >= 0, ``orientation_weight`` >= 0 (PoseCost), ``margin`` >= 0 (JointLimitCost)."""
    name = type(term).__name__
    check_number(term.weight, f"{name}.weight", positive=False)
    if isinstance(term, PoseCost):
        check_number(term.orientation_weight, "PoseCost.orientation_weight", positive=False,
                     unit=" (metres per radian)")
    if isinstance(term, JointLimitCost):
        check_number(term.margin, "JointLimitCost.margin", positive=False, unit=" (rad or m)")
    if isinstance(term, CallableCost) and not callable(term.fn):
        raise ConventionError(f"expected CallableCost.fn as a callable fn(q, T_target), got {term.fn!r}")
    return term


def _check_options(optimizer, max_iterations, lr, damping, tolerance_change, unroll, collision, world,
                   margin) -> None:
    """The options of :func:`optimize`, each refused with an :class:`~diffkin.errors.OptionError` naming it
    (NaN: a :class:`~diffkin.errors.NonFiniteOptionError`, which is one) before any work."""
    if optimizer not in OPTIMIZERS:
        raise ConventionError(f"unknown optimizer {optimizer!r}; valid: {', '.join(OPTIMIZERS)}")
    if max_iterations is not None:
        # 0: no step, q0 returned (the implicit gradient evaluated exactly at a given stationary point)
        check_count(max_iterations, "max_iterations", minimum=0)
    if lr is not None:
        check_number(lr, "lr")  # 0 was silently the default
    check_number(damping, "damping", positive=False)
    check_number(tolerance_change, "tolerance_change", positive=False)
    if not isinstance(unroll, bool):
        check_count(unroll, "unroll (False, True or a number of steps)", minimum=0)
    if collision is None and world is None and margin != 0.0:
        check_number(margin, "margin", positive=False)
        raise OptionError(f"margin={margin!r} applies to collision checks: give collision= (and world=) with "
                          "it, or leave margin at 0")


def _check_terms_at(chain, terms: list[_Term], q: Tensor, T: Tensor) -> None:
    """Evaluate every term once at the start ``q (..., nq)``: one finite value per sample ``(...)`` each,
    or a typed error naming the term (a cost of the wrong shape, a ``q_rest`` of the wrong length, NaN)."""
    for i, term in enumerate(terms):
        label = f"costs[{i}] ({_term_name(term)})"
        if isinstance(term, RestPostureCost) and term.q_rest is not None:
            rest = as_tensor(term.q_rest, "RestPostureCost.q_rest", dtype=q.dtype, device=q.device)
            try:
                broadcast_shapes(rest.shape, q.shape)
            except RuntimeError:
                raise ShapeError(f"expected RestPostureCost.q_rest of shape (..., {chain.n_joints}) "
                                 f"broadcastable to q {shape_str(q.shape)}, got {shape_str(rest.shape)}"
                                 ) from None
        with torch.no_grad():
            value = term(CostContext(chain, q, T))
        value = torch.as_tensor(value)
        if tuple(value.shape) != tuple(q.shape[:-1]):
            raise ShapeError(f"{label} returned shape {shape_str(value.shape)}; expected one value per "
                             f"sample, shape {shape_str(q.shape[:-1])}")
        bad = ~torch.isfinite(value)
        if bool(bad.any()):
            raise NonFiniteError(f"{label} is NaN or inf at the start q0 for {int(bad.sum())} of "
                                 f"{value.numel()} samples; expected a finite cost")


class _NonFiniteCost(Exception):
    """Raised inside the torch optimisers' closure at a q ``(..., nq)`` where the summed cost is NaN/inf."""

    def __init__(self, q: Tensor):
        super().__init__("non-finite cost")
        self.q = q


def _nonfinite_report(chain, terms: list[_Term], q: Tensor, T: Tensor, optimizer: str) -> NonFiniteError:
    """The typed error for a cost that turned NaN/inf at ``q`` during the iterations, naming the terms."""
    with torch.enable_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ctx = CostContext(chain, q, T)
        bad = [(i, t, ~torch.isfinite(t(ctx).detach())) for i, t in enumerate(terms)]
    names = ", ".join(f"costs[{i}] ({_term_name(t)}) at {int(m.sum())} of {m.numel()} samples"
                      for i, t, m in bad if bool(m.any()))
    return NonFiniteError(f"ik.optimize (optimizer={optimizer!r}): the cost became NaN or inf during the "
                          f"iterations: {names or 'the summed cost'} (finite at q0); give a term that is "
                          "finite wherever the optimiser may step, or use optimizer='gauss_newton', which "
                          "rejects such steps")


def _term_name(term: _Term) -> str:
    if isinstance(term, CallableCost):
        return getattr(term.fn, "__name__", type(term.fn).__name__)
    return type(term).__name__


def _total(chain, terms, q, T) -> Tensor:
    ctx = CostContext(chain, q, T)
    return sum(term(ctx) for term in terms)


def _residuals(chain, terms, q, T) -> Tensor:
    ctx = CostContext(chain, q, T)
    parts = []
    for term in terms:
        r = term.residual(ctx)
        if r is None:
            raise ConventionError(
                f"optimizer='gauss_newton' needs least-squares terms (with a residual); "
                f"{type(term).__name__} has none: use optimizer='lbfgs' or 'adam'"
            )
        parts.append(term.weight**0.5 * r)
    return torch.cat(parts, dim=-1)


def _gauss_newton(chain, terms, q, T, iterations, project, damping, tol_change, constraint=None):
    """Levenberg–Marquardt on the stacked residuals, λ adapted per sample (accept: λ/3, reject: 4λ); with a
    :class:`DistanceConstraint` each step is the constrained QP of :mod:`diffkin.ik._constrained`
    (1-DOF chains) and acceptance compares its merit. Stops when every sample's last step was accepted with
    a gain below ``tol_change`` (relative) or fails at the largest damping; rejected steps only raise λ.
    Returns ``(q, iterations, progressed)``: ``progressed (...)`` bool, False for the samples whose every
    step was rejected before a stationary point was reached (the budget ran out): q0 unmoved, reported as
    failed by :func:`optimize`."""
    lam = torch.full(q.shape[:-1], damping, dtype=q.dtype, device=q.device)
    progressed = torch.zeros(q.shape[:-1], dtype=torch.bool, device=q.device)
    space = chain.configuration_space
    it = 0
    cost = None
    ccfg = CollisionConfig()
    trust = torch.full_like(lam, ccfg.trust)
    for it in range(1, iterations + 1):
        if space.euclidean:
            qv = wrt = q.detach().requires_grad_(True)
        else:  # ball / free joints: the step is a velocity v at q, re-based every iteration (q ⊕ v)
            wrt = q.new_zeros(*q.shape[:-1], space.nv).requires_grad_(True)
            qv = space.integrate(q.detach(), wrt)
        r = _residuals(chain, terms, qv, T)
        Jr = _residual_jacobian(r, wrt)
        r = r.detach()
        cost = (r * r).sum(-1)
        if constraint is None:
            dq = -dls_solve(Jr, r, lam)  # (JᵀJ + λI)⁻¹Jᵀr (3.59), whichever normal system is smaller
        else:
            dq = constrained_step(constraint, Jr, r, lam, q.detach(), trust, ccfg)
            cost = merit(constraint, q.detach(), cost)
        with torch.no_grad():
            q_new = project(space.integrate(q, dq))
            r_new = _residuals(chain, terms, q_new, T)
            cost_new = (r_new * r_new).sum(-1)
            if constraint is not None:
                cost_new = merit(constraint, q_new, cost_new)
            accept = cost_new < cost
            q = torch.where(accept[..., None], q_new, q)
            # the shortest step still fails (or nothing is left to gain): a stationary point
            stuck = ~accept & ((lam >= _LAM_MAX) | (cost <= 0))
            progressed |= accept | stuck
            lam = torch.where(accept, lam / 3.0, lam * 4.0).clamp(1e-12, _LAM_MAX)
            # a rejected step is no sign of convergence (the next, more damped one may well succeed): only
            # an accepted step's small gain, or a step that fails at the largest damping, ends the iteration
            gain = torch.where(accept, cost - cost_new, torch.where(stuck, 0.0, math.inf))
            if constraint is not None:  # a rejected step shrinks the trust region: not yet converged
                trust = next_trust(trust, dq, accept, ccfg)
                gain = torch.where(accept | (trust <= 1e-10), gain, torch.full_like(gain, math.inf))
            if it % 5 == 0 and bool((gain <= tol_change * cost.clamp_min(1.0)).all()):
                break
    return q, it, progressed


def _torch_optimizer(name, chain, terms, q, T, iterations, project, lr, tol_change):
    space, q0 = chain.configuration_space, q.detach()
    if space.euclidean:
        x = q0.clone(memory_format=torch.contiguous_format)  # LBFGS views .grad flat

        def lift(x):
            return x

        project_x = project
    else:  # ball / free joints: optimise v in the chart q0 ⊕ v, so the quaternions stay unit
        x = q0.new_zeros(*q0.shape[:-1], space.nv)

        def lift(x):
            return space.integrate(q0, x)

        def project_x(x):
            return space.difference(q0, project(lift(x)))

    q = x.requires_grad_(True)  # the optimised variable (q itself on chains of 1-DOF joints)
    if name == "lbfgs":
        opt = torch.optim.LBFGS(
            [q], lr=lr or 1.0, max_iter=10, history_size=20, line_search_fn="strong_wolfe",
            tolerance_grad=1e-14, tolerance_change=1e-16,
        )  # fmt: skip
        sched = None
    else:
        opt = torch.optim.Adam([q], lr=lr or 0.05, betas=(0.8, 0.9))
        sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=1e-3 ** (1.0 / max(iterations, 1)))

    def closure():  # the gradient w.r.t. q only: the chain's parameters keep their .grad untouched
        loss = _total(chain, terms, lift(q), T).sum()
        if not torch.isfinite(loss):  # torch's optimisers would carry NaN into q (or crash in a line search)
            raise _NonFiniteCost(lift(q.detach()))
        q.grad = torch.autograd.grad(loss, q)[0].contiguous()
        return loss

    prev, it = None, 0
    for it in range(1, iterations + 1):
        loss = opt.step(closure)
        if sched is not None:
            sched.step()
        with torch.no_grad():
            q.copy_(project_x(q))
        if it % 10 == 0:
            loss = float(loss.detach())
            if prev is not None and abs(prev - loss) <= tol_change * max(abs(loss), 1.0):
                break
            prev = loss
    return lift(q.detach()), it


def optimize(
    chain,
    T_target: Tensor | None = None,
    q0: Tensor | None = None,
    *,
    costs: Sequence | None = None,
    optimizer: str = "lbfgs",
    max_iterations: int | None = None,
    lr: float | None = None,
    damping: float = 1e-6,
    position_tolerance: float = 1e-4,
    orientation_tolerance: float = 1e-3,
    position_only: bool = False,
    respect_limits: bool = True,
    tolerance_change: float = 1e-12,
    unroll: bool | int = False,
    collision=None,
    world=None,
    margin: float = 0.0,
    tasks=None,
    limits=None,
) -> IKResult:
    """Optimisation-based IK: minimise Σ cost terms per sample, from ``q0`` (a local method).

    Args:
        chain: any :class:`~diffkin.chain.KinematicChain`.
        T_target: ``(..., 4, 4)`` poses, or ``(..., 3)`` positions when ``position_only``.
        q0: start ``(..., nq)`` (or ``(nq,)``); default: the middle of the joint range (identity quaternions
            for ball and free joints). Optimisers are local: for far targets start from
            :func:`diffkin.ik.solve` and use this to refine secondary costs. On chains with ball or free
            joints every step moves q on the manifold (q ⊕ v, :mod:`diffkin.kernels.configuration`).
        costs: cost terms (default ``[PoseCost()]``): :class:`PoseCost`, :class:`JointLimitCost`,
            :class:`RestPostureCost`, :class:`ManipulabilityCost`, or callables ``fn(q, T_target) -> (...)``.
        optimizer: ``"lbfgs"`` / ``"adam"`` (torch.optim on the summed cost; q projected onto the limits after
            each step) or ``"gauss_newton"`` (per-sample Levenberg–Marquardt on the stacked residuals of
            least-squares terms).
        max_iterations: optimiser steps (default: L-BFGS 50, each up to 10 inner iterations; Adam 500;
            Gauss–Newton 50).
        lr: step size (L-BFGS 1.0; Adam 0.05, betas (0.8, 0.9), decaying exponentially to 1e-3 of it);
            damping: Gauss–Newton's initial λ, added to JᵀJ's diagonal (the step (JᵀJ + λI)⁻¹Jᵀr, the
            damped least squares of eq. (3.59) in its tall form; the textbook's k²; the unreleased 0.1.0
            took k: its default 1e-3 is 1e-6 here). Adam is the least precise: give it a looser tolerance.
        position_tolerance / orientation_tolerance: thresholds for ``success`` (pose error of the result).
        tolerance_change: stop when the cost changes less than this (relative) over a check.
        unroll: how ``q`` is differentiated (see below): False (default) for the implicit gradient; True (10
            steps) or a number of steps to differentiate through that many Gauss–Newton steps (all terms
            least squares) or gradient steps of size ``lr`` (default 0.05) taken from the solution instead.
        tasks, limits: the problem as objects (:mod:`diffkin.ik._from_tasks`): each task a cost term
            ‖W e(q)‖² (its own error and costs), the pose :class:`~diffkin.ik.FrameTask` s also the targets
            of ``success`` (instead of ``T_target``); limits as in :func:`~diffkin.ik.solve`.
        collision, world, margin: as in :func:`~diffkin.ik.solve`; ``success`` also needs every checked
            distance >= ``margin`` (the exact distances). With ``optimizer="gauss_newton"`` on a chain of
            1-DOF joints the distances are **constraints** of every step (a QP with the nearest distances
            linearised, :mod:`diffkin.ik._constrained`): the result is a KKT point of min Σ costs s.t.
            d >= margin. Otherwise (L-BFGS, Adam, ball or free joints) a :class:`CollisionCost` (a one-sided
            quadratic penalty below margin + 1 cm, :mod:`diffkin.ik.collision_cost`) joins the terms.

    Returns:
        :class:`IKResult`; ``success`` is judged from an exact FK in the chain's dtype (and the limits).
        Gauss–Newton stops only when every sample's last step was accepted with a gain below
        ``tolerance_change`` or fails at the largest damping (a stationary point); a rejected step only raises
        the damping. A sample that accepted no step before the budget ran out (q0 returned unmoved, short of
        a stationary point) has ``success`` False.

    Raises:
        OptionError: an option out of range, named (``max_iterations`` an integer >= 0, ``lr`` > 0,
            ``damping`` and ``tolerance_change`` >= 0, ``unroll`` a bool or an integer >= 0, a cost's
            ``weight`` / ``orientation_weight`` / ``margin`` >= 0, ``margin`` without ``collision``); NaN
            raises its subclass NonFiniteOptionError.
        ConventionError: ``costs`` that is not a non-empty list of terms.
        ShapeError: a term whose value at q0 is not one number per sample, a ``q_rest`` of the wrong length.
        NonFiniteError: the term whose cost is NaN/inf at q0, or turns NaN/inf during L-BFGS or Adam
            (Gauss–Newton rejects such steps).

    **Gradients.** With grad mode on and ``T_target`` or a chain parameter requiring grad, ``q`` is
    differentiable w.r.t. both. By default from the stationarity of the summed cost at the solution,
    ∇_q C(q*, z) = 0 ⇒ dq* = −H⁻¹ ∂(∇_q C)/∂z dz, H = ∇²_q C from Hessian–vector products through
    autograd (damped by ``damping``·I only where H is nearly singular); this needs twice-differentiable
    terms — PoseCost, RestPostureCost and ManipulabilityCost are; JointLimitCost's second derivative jumps
    at the margin and a user's callable may not be: there ``unroll`` differentiates through explicit steps
    instead. Every sample is differentiated (its cost is stationary whether or not the pose meets the
    tolerances). With distance constraints (Gauss–Newton) a constraint held at the boundary with a positive
    multiplier is differentiated as an equality of the KKT point ([∇²L Aᵀ; A 0], L = C − λᵀd, the
    distances' curvature included, :func:`~diffkin.ik.implicit.attach_stationary_gradients`: exact for
    spheres, capsules, boxes and half-spaces, ``tests/test_collision_second_order.py``; the witness
    parameters of convex meshes and of a cylinder's rim search are held constant, so their curvature is
    approximate where those pairs are active); where none
    is active the gradient is that of the unconstrained stationary point. Equal to central differences of
    the solver in both cases (``tests/test_ik_optimize_constraints.py``, ``tests/test_ik_collision.py``).
    """
    if tasks is not None or limits is not None:  # the objects, translated (diffkin.ik._from_tasks)
        from ._from_tasks import optimize_arguments

        T_target, costs, position_only, respect_limits, collision, world, margin = optimize_arguments(
            chain, T_target, tasks, limits, costs, position_only, respect_limits, collision, world, margin)
    _check_options(optimizer, max_iterations, lr, damping, tolerance_change, unroll, collision, world, margin)
    terms = _as_terms(costs)
    constraint = constraint_of(chain, collision, world, margin, None)
    # Gauss–Newton on 1-DOF chains keeps the distances as constraints; the other optimisers (and ball or
    # free chains) minimise the one-sided penalty of CollisionCost
    hard = constraint is not None and optimizer == "gauss_newton" and chain.configuration_space.euclidean
    if constraint is not None and not hard:
        from .collision_cost import CollisionCost

        terms.append(CollisionCost(collision=collision, world=world, margin=constraint.margin))
    _check_tolerances(position_tolerance, orientation_tolerance)
    T_target = _valid_targets(chain, T_target)
    batch, T, _ = _targets(chain, T_target, position_only, chain.dtype)
    T = T.detach()
    if position_only and T.shape[-2:] == (4, 4):
        T = T[..., :3, 3]
    n = chain.n_joints
    seeds = _user_seeds(chain, q0, batch, math.prod(batch))
    if math.prod(batch) == 0:  # an empty batch: empty results
        empty = T.new_zeros(batch)
        return IKResult(q=T.new_zeros(*batch, n),
                        success=torch.zeros(batch, dtype=torch.bool, device=T.device),
                        position_error=empty, orientation_error=empty.clone(),
                        iterations=torch.zeros(batch, dtype=torch.long, device=T.device))
    if seeds is None:
        lo, hi = chain.lower_upper()
        # ball and free joints: the middle of a quaternion's range is 0, normalised to the identity
        q = chain.configuration_space.normalize((0.5 * (lo + hi)).detach().expand(*batch, n).clone())
    else:
        q = seeds[:, 0].reshape(*batch, n).detach().clone()
    clamp = respect_limits and chain.q_limits is not None
    project = (lambda x: chain.clamp_to_limits(x, check=False)) if clamp else (lambda x: x)
    q = project(q)
    with torch.enable_grad():  # terms may differentiate inside (a Jacobian), also under no_grad
        _check_terms_at(chain, terms, q, T)
    if max_iterations is None:
        max_iterations = {"lbfgs": 50, "adam": 500, "gauss_newton": 50}[optimizer]
    with torch.enable_grad():  # the iterations differentiate the cost w.r.t. q, also under no_grad
        if optimizer == "gauss_newton":
            q, it, progressed = _gauss_newton(chain, terms, q, T, max_iterations, project, damping,
                                              tolerance_change, constraint if hard else None)
        else:
            try:
                q, it = _torch_optimizer(optimizer, chain, terms, q, T, max_iterations, project, lr,
                                         tolerance_change)
            except _NonFiniteCost as exc:
                raise _nonfinite_report(chain, terms, exc.q, T, optimizer) from None
            progressed = None
    with torch.no_grad():
        pos_err, ori_err = final_errors(chain, q, T, position_only)
        lost = ~torch.isfinite(q).all(-1)
    if bool(lost.any()):  # a term went NaN or inf on the way (finite at q0: checked above)
        warnings.warn(f"ik.optimize ({optimizer}): the cost became NaN or inf during the optimisation for "
                      f"{int(lost.sum())} of {lost.numel()} samples (a cost term that is not finite "
                      "everywhere); their q is not finite and success is False", RuntimeWarning, stacklevel=2)
    success = (pos_err <= position_tolerance) & ~lost
    if not position_only:
        success &= ori_err <= orientation_tolerance
    if clamp:
        success &= chain.within_limits(q, check=False)
    if progressed is not None:  # Gauss–Newton left q0 unmoved without reaching a stationary point
        success &= progressed
    if constraint is not None:
        with torch.no_grad():
            success &= constraint.satisfied(q)
    iters = torch.full(batch, it, dtype=torch.long, device=q.device)
    T_src = T_target[..., :3, 3] if position_only and T_target.shape[-2:] == (4, 4) else T_target
    space = chain.configuration_space
    if unroll:
        if not space.euclidean:
            raise ConventionError("unroll differentiates additive steps: use the implicit gradient "
                                  "(unroll=False) on chains with ball or free joints")
        q = _unrolled(chain, terms, q, T_src, torch.ones_like(success), 10 if unroll is True else int(unroll),
                      damping, lr)
    elif space.euclidean:
        # every sample: the returned point is stationary whether or not it meets the pose tolerances (a KKT
        # point where a distance constraint is held at the boundary)
        kkt = None
        if hard and wants_gradients(chain, T_src):
            rows, active = active_rows(constraint, q, CollisionConfig())
            if rows.shape[-1]:
                kkt = (lambda qq: constraint.value(qq).gather(-1, rows), active)
        q = attach_stationary_gradients(chain, q, T_src, torch.ones_like(success),
                                        lambda qq, TT: _total(chain, terms, qq, TT), damping, kkt)
    else:  # stationary in the chart v ↦ q* ⊕ v at v = 0; q = q* ⊕ v* carries dq = (∂q/∂v) dv*
        q_star = q.detach()
        v = attach_stationary_gradients(
            chain, q.new_zeros(*q.shape[:-1], space.nv), T_src, torch.ones_like(success),
            lambda vv, TT: _total(chain, terms, space.integrate(q_star, vv), TT), damping)
        q = space.integrate(q_star, v) if v.requires_grad else q
    return IKResult(q=q, success=success, position_error=pos_err, orientation_error=ori_err, iterations=iters)


def _unrolled(chain, terms, q: Tensor, T: Tensor, success: Tensor, steps: int, damping: float, lr) -> Tensor:
    """``steps`` differentiable steps from the solution ``q``: Gauss–Newton on the stacked residuals when
    every term has one, else gradient steps; the graph reaches ``T`` and the chain's parameters."""
    if not wants_gradients(chain, T):
        return q
    least_squares = all(type(t).residual is not _Term.residual for t in terms)
    keep = success.unsqueeze(-1).to(q.dtype)
    q = q.detach().requires_grad_(True)
    for _ in range(steps):
        if least_squares:
            r = _residuals(chain, terms, q, T)
            Jr = _residual_jacobian(r, q, create_graph=True)
            step = dls_solve(Jr, r, damping)
        else:
            (g,) = torch.autograd.grad(_total(chain, terms, q, T).sum(), q, create_graph=True)
            step = (lr or 0.05) * g
        q = q - keep * step
    return q
