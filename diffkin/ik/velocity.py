"""Velocity-level IK with hard limits: one batched, differentiable QP step (§3.5 with constraints, §3.7).

:func:`velocity_step` returns the joint velocities q̇ ``(..., nv)`` that solve, per batch row,

    min_q̇  ‖W (J(q) q̇ − v)‖² + λ ‖q̇‖²                                                            (V.1)
    s.t.   max(−q̇_max, (q_min − q)/Δt) ≤ q̇ ≤ min(q̇_max, (q_max − q)/Δt)                            (V.2)

exactly (an active-set solve, not a clamp of the unconstrained step): J is the geometric Jacobian (3.30)
of the chosen end links stacked, v = [v; ω] their desired twists in the base frame, W a diagonal weight
per task row, λ the damping of the damped least-squares inverse (3.59) — (V.1) without (V.2) is
q̇ = J*v. The bounds (V.2) keep q + q̇Δt (3.48) within the joint limits and |q̇| within the velocity
limits; where q is already outside its limits the row moves back at most at q̇_max.

A :class:`PostureTask` is a second, lower priority (§3.5.1): the velocity of (3.54),
q̇ = q̇₁ + (I − A†A) z with A = WJ and q̇₁ the solution of (V.1)–(V.2), chooses z to bring q̇ closest to
the posture velocity q̇_p = k (q_ref − q)/Δt while keeping (V.2):

    min_z  ‖D (q̇₁ + N z − q̇_p)‖² + zᵀ(I − N)z + ε‖z‖²  s.t. (V.2) at q̇ = q̇₁ + N z,  N = I − A†A    (V.3)

so the primary tasks' velocities A q̇ = A q̇₁ are kept exactly (D the posture weights; the (I − N) term
acts only on the part of z that N removes, and ε = √eps·max D² makes z unique where D has zeros).
(V.1) is :func:`diffkin.ik.qp.box_qp` on H = AᵀA + λI, g = Aᵀ W v; (V.3) is :func:`diffkin.ik.qp.solve_qp`.
Both are differentiable (KKT gradients) w.r.t. q (through J and the bounds), v, the limits, the weights and
the damping.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from .._numerics import eps_for
from ..errors import ConventionError, DiffkinError, ShapeError
from ..redundancy import _pinv
from ..validation import broadcast_batch, check_number, shape_str, tensors
from .qp import _solve_box, _solve_general

__all__ = ["FrameTask", "PostureTask", "velocity_step"]


@dataclass(frozen=True, eq=False)
class FrameTask:
    """Track the twist of end link ``end`` (the index into ``chain.topology.ends``; 0 for a chain).

    weight: a number or ``(6,)`` per component of [v; ω] (e.g. ``(1, 1, 1, 0, 0, 0)``: position only);
    it multiplies ``velocity_step``'s ``weight``.
    """

    end: int = 0
    weight: Any = 1.0


@dataclass(frozen=True, eq=False)
class PostureTask:
    """Lower-priority posture (V.3): move towards ``q_ref`` ``(..., n)`` at q̇_p = gain · (q_ref − q)/Δt in
    the primary tasks' null space. weight: a number or ``(nv,)`` per joint (D of (V.3), > 0 somewhere)."""

    q_ref: Any
    weight: Any = 1.0
    gain: float = 1.0


def _frame_tasks(tasks, K: int) -> tuple[list[FrameTask], PostureTask | None]:
    tasks = () if tasks is None else tuple(tasks)
    bad = [t for t in tasks if not isinstance(t, FrameTask | PostureTask)]
    if bad:
        raise ConventionError(f"velocity_step: tasks must be FrameTask or PostureTask, got {bad[0]!r}")
    frames = [t for t in tasks if isinstance(t, FrameTask)] or [FrameTask(end=k) for k in range(K)]
    postures = [t for t in tasks if isinstance(t, PostureTask)]
    if len(postures) > 1:
        raise ConventionError(f"velocity_step: at most one PostureTask, got {len(postures)}")
    for t in frames:
        if isinstance(t.end, bool) or not isinstance(t.end, int) or not 0 <= t.end < K:
            raise ShapeError(f"velocity_step: FrameTask.end must be an end-link index in [0, {K}), got "
                             f"{t.end!r}")
    return frames, (postures[0] if postures else None)


def _nonnegative(x: Tensor, name: str) -> Tensor:
    if bool((x < 0).any()) or bool(torch.isnan(x).any()):
        raise DiffkinError(f"velocity_step: expected {name} >= 0 everywhere, got a negative or NaN entry")
    return x


def _inputs(chain, q, twist, damping, velocity_limit, weight):
    q = chain.check_q(q)
    K, one = chain.n_ends, chain.single_end
    trailing = (6,) if one else (K, 6)
    twist, damping, vmax, weight = tensors(
        ("twist", twist, trailing), ("damping", damping, None), ("velocity_limit", velocity_limit, None),
        ("weight", weight, None), like=chain, finite=(True, True, False, True))
    if not bool((damping > 0).all()):
        raise DiffkinError("velocity_step: expected damping > 0 (λ of (V.1) makes the step unique)")
    if vmax is not None:
        _nonnegative(vmax, "velocity_limit")
    if weight is not None and weight.ndim and weight.shape[weight.ndim - len(trailing):] != trailing:
        dims = ", ".join(map(str, trailing))
        raise ShapeError(f"velocity_step: expected weight as a number or (..., {dims}), got "
                         f"{shape_str(weight.shape)}")
    if weight is not None:
        _nonnegative(weight, "weight")
    return q, twist, damping, vmax, weight


def _stacked_task(J, twist, weight, frames: list[FrameTask], like: Tensor):
    """A = W J ``(..., 6F, nv)`` and b = W v ``(..., 6F)`` over the frame tasks."""
    A, b = [], []
    for t in frames:
        (w,) = tensors(("FrameTask.weight", t.weight, None), like=like)
        if w.ndim and w.shape != (6,):
            raise ShapeError(f"velocity_step: expected FrameTask.weight as a number or (6,), got "
                             f"{shape_str(w.shape)}")
        _nonnegative(w, "FrameTask.weight")
        wk = w.expand(6) if weight is None else w * weight[..., t.end, :]
        A.append(wk[..., :, None] * J[..., t.end, :, :])
        b.append(wk * twist[..., t.end, :])
    return torch.cat(A, dim=-2), torch.cat(torch.broadcast_tensors(*b), dim=-1)


def _bounds(chain, q: Tensor, dt: float, nv: int, vmax: Tensor | None, respect_limits: bool):
    """(lower, upper) of (V.2) ``(..., nv)``; ±inf where a joint has no bound."""
    inf = torch.tensor(float("inf"), dtype=q.dtype, device=q.device)
    lo, hi = -inf.expand(nv), inf.expand(nv)
    if respect_limits and chain.q_limits is not None:
        lim = chain.q_limits.to(q)
        space = chain.configuration_space
        if space.euclidean:
            lo, hi = (lim[:, 0] - q) / dt, (lim[:, 1] - q) / dt
        else:  # ball and free joints: the scalar coordinates have bounds, the rotations none
            sq, sv = list(space.scalar_index("q")), torch.tensor(space.scalar_index("v"), device=q.device)
            lo_s, hi_s = (lim[sq, 0] - q[..., sq]) / dt, (lim[sq, 1] - q[..., sq]) / dt
            batch = q.shape[:-1]
            lo = (-inf).expand(*batch, nv).clone().index_copy(-1, sv, lo_s)
            hi = inf.expand(*batch, nv).clone().index_copy(-1, sv, hi_s)
    if vmax is not None:  # velocity limits win over a position bound that lies beyond them (q outside)
        lo, hi = torch.maximum(torch.minimum(lo, vmax), -vmax), torch.maximum(torch.minimum(hi, vmax), -vmax)
    return lo, hi


def _posture(chain, q, dt, A, qd1, lo, hi, task: PostureTask, dampers=None):
    """The second stage (V.3); the damper rows, if any, constrain q̇₁ + N z too."""
    nv = A.shape[-1]
    gain = check_number(task.gain, "PostureTask.gain", positive=False)
    q_ref, w = tensors(("PostureTask.q_ref", task.q_ref, (q.shape[-1],)),
                       ("PostureTask.weight", task.weight, None), like=chain)
    if w.ndim and w.shape != (nv,):
        raise ShapeError(f"velocity_step: expected PostureTask.weight as a number or ({nv},), got "
                         f"{shape_str(w.shape)}")
    D = (_nonnegative(w, "PostureTask.weight") ** 2).expand(nv)
    if not bool((D > 0).any()):
        raise DiffkinError("velocity_step: PostureTask.weight must be > 0 for some joint")
    # q_ref ⊖ q: q_ref − q on 1-DOF joints, the rotation vector between quaternions on ball / free ones
    target = gain * chain.configuration_space.difference(q, q_ref.expand_as(q)) / dt
    N = torch.eye(nv, dtype=q.dtype, device=q.device) - _pinv(A) @ A  # (3.54)
    eye = torch.eye(nv, dtype=q.dtype, device=q.device)
    # z's components in range(Aᵀ) change neither q̇ nor the constraints: curvature 1 there keeps the
    # interior point's systems well conditioned (their optimum is z = 0 whatever the curvature)
    H = N @ (D[:, None] * N) + (eye - N) + eps_for(q) ** 0.5 * D.amax() * eye
    g = (N @ (D * (target - qd1)).unsqueeze(-1)).squeeze(-1)
    G = torch.cat((N, -N), dim=-2)
    h = torch.cat(((hi - qd1).clamp(min=0.0), (qd1 - lo).clamp(min=0.0)), dim=-1)
    if dampers is not None:  # Gd (q̇₁ + N z) ≤ hd
        Gd, hd = dampers
        slack = (hd - (Gd @ qd1.unsqueeze(-1)).squeeze(-1)).clamp(min=0.0)
        batch = torch.broadcast_shapes(slack.shape[:-1], G.shape[:-2], h.shape[:-1])
        G = torch.cat(((Gd @ N).expand(*batch, -1, nv), G.expand(*batch, *G.shape[-2:])), dim=-2)
        h = torch.cat((slack.expand(*batch, -1), h.expand(*batch, h.shape[-1])), dim=-1)
    z = _solve_general(H, g, G, h)
    qd = qd1 + (N @ z.unsqueeze(-1)).squeeze(-1)
    return torch.maximum(torch.minimum(qd, hi), lo)  # (V.2) holds to rounding: make it exact


def _damper_rows(chain, q: Tensor, dt: float, collision, world, margin: float, detection: float,
                 gain: float) -> tuple[Tensor, Tensor]:
    """Collision velocity dampers as G q̇ ≤ h (mink's ``CollisionAvoidanceLimit``): every checked distance d
    (the pairs of ``collision``, and each geom to each object of ``world``) closer than ``detection`` may
    shrink by at most ``gain (d − margin)`` over the step, ḋ = J_d q̇ ≥ −gain (d − margin)/Δt, i.e.
    −J_d q̇ ≤ gain (d − margin)/Δt; rows farther off are inactive (h = inf). J_d = ∂d/∂q (autograd of the
    closed-form distances) times the tangent map of q for ball and free joints: ``(..., D, nv)``,
    ``(..., D)``."""
    from .residuals import DistanceConstraint

    d, _, Jd = DistanceConstraint(collision, world).jacobian(q)  # every row (margin 0: g = d)
    space = chain.configuration_space
    if not space.euclidean:
        Jd = Jd @ space.tangent_map(q)
    inf = torch.full_like(d, float("inf"))
    return -Jd, torch.where(d < detection, gain * (d - margin) / dt, inf)


def velocity_step(chain, q, twist, dt: float, *, damping=1e-3, velocity_limit=None,
                  respect_limits: bool = True, weight=None,
                  tasks: Sequence[FrameTask | PostureTask] | None = None, collision=None, world=None,
                  collision_margin: float = 0.005, collision_detection: float = 0.05,
                  collision_gain: float = 0.85) -> Tensor:
    """Joint velocities q̇ ``(..., nv)`` solving (V.1)–(V.2) exactly per batch row (module docstring).

    Args:
        chain: a :class:`~diffkin.chain.KinematicChain` (one or K end links).
        q: joints ``(..., n)``.
        twist: desired end-link twists [v; ω] in the base frame (m/s, rad/s): ``(..., 6)`` for a chain,
            ``(..., K, 6)`` for a tree (one per end link, in ``chain.topology.ends`` order).
        dt: the step Δt (s) over which the position limits must hold, > 0.
        damping: λ of (V.1), > 0: a number or ``(...)`` per row.
        velocity_limit: q̇_max, a number or ``(..., nv)`` per joint (>= 0; inf: none); None: no limit.
        respect_limits: bound q + q̇Δt by ``chain.q_limits`` (joints with ±inf limits are free).
        weight: W of (V.1), diagonal: a number or ``(..., 6)`` / ``(..., K, 6)`` per twist component
            (0 drops a component: ``(1, 1, 1, 0, 0, 0)`` tracks the position only).
        tasks: :class:`FrameTask` s (which end links, each with its own weight; default every end link)
            and at most one :class:`PostureTask` (the lower priority (V.3)).
        collision, world: a :class:`~diffkin.collision.RobotCollision` of the chain (its checked pairs) and
            optionally a :class:`~diffkin.collision.World`: velocity dampers as extra inequalities
            (:func:`_damper_rows`): a distance below ``collision_detection`` (m) may shrink over the step
            by at most ``collision_gain`` times its excess over ``collision_margin`` (m), so no checked
            distance is driven below the margin. The damper rows are constants of the step (their
            derivatives w.r.t. q do not flow into q̇'s gradient).

    Returns:
        q̇ ``(..., nv)``, differentiable (KKT gradients of :mod:`diffkin.ik.qp`).

    With ``collision`` the step is the general QP (:func:`diffkin.ik.qp.solve_qp`'s interior point) with
    the bounds and the damper rows as inequalities; without it, the box QP.
    """
    q, twist, damping, vmax, weight = _inputs(chain, q, twist, damping, velocity_limit, weight)
    dt = check_number(dt, "dt", unit=" (s)")
    frames, posture = _frame_tasks(tasks, chain.n_ends)
    _, J = chain.forward_kinematics_and_jacobian(q, check=False)
    if chain.single_end:
        J, twist = J.unsqueeze(-3), twist.unsqueeze(-2)
        weight = None if weight is None or weight.ndim == 0 else weight.unsqueeze(-2)
    if weight is not None and weight.ndim == 0:
        weight = weight.expand(*twist.shape[-2:])
    broadcast_batch(("q", q, 1), ("twist", twist, 2), ("weight", weight, 2), ("damping", damping, 0),
                    ("velocity_limit", vmax if vmax is not None and vmax.ndim else None, 1))
    nv = J.shape[-1]
    if vmax is not None and vmax.ndim and vmax.shape[-1] != nv:
        raise ShapeError(f"velocity_step: expected velocity_limit as a number or (..., {nv}), got "
                         f"{shape_str(vmax.shape)}")
    dampers = None
    if collision is not None:
        for name, value in (("collision_margin", collision_margin), ("collision_detection",
                                                                      collision_detection),
                            ("collision_gain", collision_gain)):
            check_number(value, name, positive=False)
        dampers = _damper_rows(chain, q, dt, collision, world, float(collision_margin),
                               float(collision_detection), float(collision_gain))
    elif world is not None:
        raise DiffkinError("velocity_step: a world needs the robot's collision model (collision=...)")
    return _solve(chain, q, J, twist, weight, dt, damping, vmax, respect_limits, frames, posture, dampers)


def _solve(chain, q, J, twist, weight, dt, damping, vmax, respect_limits, frames, posture, dampers=None):
    """(V.1)–(V.3) for validated inputs: J ``(..., K, 6, nv)``, twist and weight ``(..., K, 6)``; dampers
    ``(G (..., D, nv), h (..., D))`` or None."""
    nv = J.shape[-1]
    A, b = _stacked_task(J, twist, weight, frames, q)
    eye = torch.eye(nv, dtype=q.dtype, device=q.device)
    H = A.mT @ A + damping[..., None, None] * eye
    g = (A.mT @ b.unsqueeze(-1)).squeeze(-1)
    lo, hi = _bounds(chain, q, dt, nv, vmax, respect_limits)
    if dampers is None:
        qd = _solve_box(H, g, lo, hi)
    else:  # the bounds as rows beside the dampers: [G; I; −I] q̇ ≤ [h; hi; −lo] (inf rows are off)
        Gd, hd = dampers
        batch = torch.broadcast_shapes(Gd.shape[:-2], lo.shape[:-1], hi.shape[:-1])
        I = eye.expand(*batch, nv, nv)
        G = torch.cat((Gd.expand(*batch, *Gd.shape[-2:]), I, -I), dim=-2)
        h = torch.cat((hd.expand(*batch, hd.shape[-1]), hi.expand(*batch, nv), -lo.expand(*batch, nv)),
                      dim=-1)
        qd = _solve_general(H, g, G, h)
        qd = torch.maximum(torch.minimum(qd, hi), lo)  # the bounds exactly (rounding of the interior point)
    if posture is not None:
        qd = _posture(chain, q, dt, A, qd, lo, hi, posture, dampers)
    return qd
