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

:func:`velocity_step` is a shorthand: it builds the task and limit objects of :mod:`diffkin.ik.tasks` and
:mod:`diffkin.ik.limits` — one :class:`~diffkin.ik.FrameTask` per end link with ``twist=`` and the costs
W, :class:`~diffkin.ik.ConfigurationLimit` ``(gain=1)`` for ``respect_limits``,
:class:`~diffkin.ik.VelocityLimit` for ``velocity_limit``, :class:`~diffkin.ik.CollisionLimit` for
``collision`` — and solves (V.1)–(V.2) as :func:`~diffkin.ik.solve_velocity` does ((D.1) with Δq = q̇Δt is
(V.1) times Δt²; λ = ``damping`` is the same number in both). The one difference is the
:class:`~diffkin.ik.PostureTask`: here the lower priority (V.3), in ``solve_velocity`` a term of the
weighted sum (mink's semantics); pass the tasks to ``solve_velocity`` for the latter.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from .._numerics import broadcast_shapes, eps_for
from ..errors import ConventionError, DiffkinError, ShapeError
from ..redundancy import _pinv
from ..validation import broadcast_batch, check_nonnegative, check_number, check_positive, shape_str, tensors
from .differential import least_squares, solve_step
from .limits import CollisionLimit, ConfigurationLimit, VelocityLimit, combine_boxes
from .qp import _solve_general
from .tasks import FrameTask, PostureTask, Problem

__all__ = ["FrameTask", "PostureTask", "velocity_step"]


def _frame_tasks(tasks, K: int) -> tuple[list[FrameTask], PostureTask | None]:
    tasks = () if tasks is None else tuple(tasks)
    bad = [t for t in tasks if not isinstance(t, FrameTask | PostureTask)
           or (isinstance(t, FrameTask) and (t.twist is not None or t.target is not None))
           or type(t) not in (FrameTask, PostureTask)]
    if bad:
        raise ConventionError(f"velocity_step: tasks must be FrameTask or PostureTask (a FrameTask without "
                              f"target or twist: the twist argument is its), got {bad[0]!r}; pass other "
                              f"tasks to ik.solve_velocity")
    frames = [t for t in tasks if isinstance(t, FrameTask)] or [FrameTask(end=k) for k in range(K)]
    postures = [t for t in tasks if isinstance(t, PostureTask)]
    if len(postures) > 1:
        raise ConventionError(f"velocity_step: at most one PostureTask, got {len(postures)}")
    for t in frames:
        if isinstance(t.frame, bool) or not isinstance(t.frame, int | str) or (
                isinstance(t.frame, int) and not 0 <= t.frame < K):
            raise ShapeError(f"velocity_step: FrameTask.end must be an end-link index in [0, {K}), got "
                             f"{t.frame!r}")
    return frames, (postures[0] if postures else None)


def _inputs(chain, q, twist, damping, velocity_limit, weight):
    q = chain.check_q(q)
    K, one = chain.n_ends, chain.single_end
    trailing = (6,) if one else (K, 6)
    twist, damping, vmax, weight = tensors(
        ("twist", twist, trailing), ("damping", damping, None), ("velocity_limit", velocity_limit, None),
        ("weight", weight, None), like=chain, finite=(True, True, False, True))
    check_positive(damping, "damping (λ of (V.1) makes the step unique)")
    if vmax is not None:
        check_nonnegative(vmax, "velocity_limit", nan=False)
    if weight is not None and weight.ndim and weight.shape[weight.ndim - len(trailing):] != trailing:
        dims = ", ".join(map(str, trailing))
        raise ShapeError(f"velocity_step: expected weight as a number or (..., {dims}), got "
                         f"{shape_str(weight.shape)}")
    if weight is not None:
        check_nonnegative(weight, "weight")
    return q, twist, damping, vmax, weight


def _frame_objects(twist, weight, frames: list[FrameTask], p: Problem) -> list[FrameTask]:
    """The :class:`FrameTask` objects of (V.1): twist ξ_k, costs W = its costs × ``weight[..., k, :]``."""
    out = []
    for t in frames:
        k = p.end_index(t.frame, "velocity_step: FrameTask.end")
        w = t.cost_vector(p, 6)
        if weight is not None:
            w = w * weight[..., k, :]
        out.append(FrameTask(k, twist=twist[..., k, :], position_cost=w[..., :3], orientation_cost=w[..., 3:],
                             gain=t.gain, lm_damping=t.lm_damping))
    return out


def _posture(chain, q, dt, A, qd1, lo, hi, task: PostureTask, dampers=None):
    """The second stage (V.3); the damper rows, if any, constrain q̇₁ + N z too."""
    nv = A.shape[-1]
    gain = check_number(task.gain, "PostureTask.gain", positive=False)
    q_ref, w = tensors(("PostureTask.q_ref", task.q_ref, (q.shape[-1],)),
                       ("PostureTask.weight", task.weight, None), like=chain)
    if w.ndim and w.shape != (nv,):
        raise ShapeError(f"velocity_step: expected PostureTask.weight as a number or ({nv},), got "
                         f"{shape_str(w.shape)}")
    D = (check_nonnegative(w, "PostureTask.weight") ** 2).expand(nv)
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
    # q̇₁ on several bounds can leave {z: G z ≤ h} without interior, where the interior point stalls: the
    # rows are relaxed by δ = eps^¾ (1 + |h|) (the final clamp restores (V.2) exactly)
    h = h + eps_for(q) ** 0.75 * (1.0 + h.abs())
    if dampers is not None:  # Gd (q̇₁ + N z) ≤ hd
        Gd, hd = dampers
        slack = (hd - (Gd @ qd1.unsqueeze(-1)).squeeze(-1)).clamp(min=0.0)
        batch = broadcast_shapes(slack.shape[:-1], G.shape[:-2], h.shape[:-1])
        G = torch.cat(((Gd @ N).expand(*batch, -1, nv), G.expand(*batch, *G.shape[-2:])), dim=-2)
        h = torch.cat((slack.expand(*batch, -1), h.expand(*batch, h.shape[-1])), dim=-1)
    z = _solve_general(H, g, G, h)
    qd = qd1 + (N @ z.unsqueeze(-1)).squeeze(-1)
    return torch.maximum(torch.minimum(qd, hi), lo)  # (V.2) holds to rounding: make it exact


def velocity_step(chain, q, twist, dt: float, *, damping=1e-3, velocity_limit=None,
                  respect_limits: bool = True, weight=None,
                  tasks: Sequence[FrameTask | PostureTask] | None = None, collision=None, world=None,
                  collision_margin: float = 0.005, collision_detection: float = 0.05,
                  collision_gain: float = 0.85) -> Tensor:
    """Joint velocities q̇ ``(..., nv)`` solving (V.1)–(V.2) exactly per batch row (module docstring).

    Args:
        chain: a :class:`~diffkin.chain.KinematicChain` (one or K end links).
        q: joints ``(..., nq)``.
        twist: desired end-link twists [v; ω] in the base frame (m/s, rad/s): ``(..., 6)`` for a chain,
            ``(..., K, 6)`` for a tree (one per end link, in ``chain.topology.ends`` order).
        dt: the step Δt (s) over which the position limits must hold, > 0.
        damping: λ of (V.1) (= k² of (3.59), the same λ as :func:`~diffkin.ik.solve_velocity`'s), > 0: a
            number or ``(...)`` per row.
        velocity_limit: q̇_max, a number or ``(..., nv)`` per joint (>= 0; inf: none); None: no limit.
        respect_limits: bound q + q̇Δt by ``chain.q_limits`` (joints with ±inf limits are free).
        weight: W of (V.1), diagonal: a number or ``(..., 6)`` / ``(..., K, 6)`` per twist component
            (0 drops a component: ``(1, 1, 1, 0, 0, 0)`` tracks the position only).
        tasks: :class:`FrameTask` s (which end links, each with its own costs; default every end link)
            and at most one :class:`PostureTask` (the lower priority (V.3)).
        collision, world: a :class:`~diffkin.collision.RobotCollision` of the chain (its checked pairs) and
            optionally a :class:`~diffkin.collision.World`: a :class:`~diffkin.ik.CollisionLimit` with
            ``minimum_distance=collision_margin``, ``detection_distance=collision_detection``,
            ``gain=collision_gain``: a distance below the detection distance (m) may shrink over the step by
            at most the gain times its excess over the margin (m), never by a negative amount.

    Returns:
        q̇ ``(..., nv)``, differentiable (KKT gradients of :mod:`diffkin.ik.qp`).

    With ``collision`` the step is the general QP (:func:`diffkin.ik.qp.solve_qp`'s interior point) with
    the bounds and the collision rows as inequalities; without it, the box QP.
    """
    q, twist, damping, vmax, weight = _inputs(chain, q, twist, damping, velocity_limit, weight)
    dt = check_number(dt, "dt", unit=" (s)")
    frames, posture = _frame_tasks(tasks, chain.n_ends)
    _, J = chain.forward_kinematics_and_jacobian(q, check=False)
    if chain.single_end:
        J, twist = J.unsqueeze(-3), twist.unsqueeze(-2)
        if weight is not None and weight.ndim:
            weight = weight.unsqueeze(-2)
    if weight is not None and weight.ndim == 0:  # a plain number (0 included) weights every component
        weight = weight.expand(*twist.shape[-2:])
    broadcast_batch(("q", q, 1), ("twist", twist, 2), ("weight", weight, 2), ("damping", damping, 0),
                    ("velocity_limit", vmax if vmax is not None and vmax.ndim else None, 1))
    nv = J.shape[-1]
    if vmax is not None and vmax.ndim and vmax.shape[-1] != nv:
        raise ShapeError(f"velocity_step: expected velocity_limit as a number or (..., {nv}), got "
                         f"{shape_str(vmax.shape)}")
    limit = None
    if collision is not None:
        limit = CollisionLimit(collision, world, gain=collision_gain, minimum_distance=collision_margin,
                               detection_distance=collision_detection)
    elif world is not None:
        raise DiffkinError("velocity_step: a world needs the robot's collision model (collision=...)")
    return _solve(chain, q, J, twist, weight, dt, damping, vmax, respect_limits, frames, posture, limit)


def _solve(chain, q, J, twist, weight, dt, damping, vmax, respect_limits, frames, posture, collision=None):
    """(V.1)–(V.3) for validated inputs: J ``(..., K, 6, nv)``, twist and weight ``(..., K, 6)``; collision a
    :class:`~diffkin.ik.CollisionLimit` or None."""
    p = Problem(chain, q, dt)
    p._fk = (None, J)  # the twist form reads only the Jacobians
    limits = ([ConfigurationLimit(gain=1.0)] if respect_limits else []) + (
        [VelocityLimit(vmax)] if vmax is not None else []) + ([collision] if collision is not None else [])
    A, b, reg = least_squares(p, _frame_objects(twist, weight, frames, p), damping)
    qd = solve_step(p, A, b, reg, limits) / dt
    if posture is not None:
        box = combine_boxes(limits, p)
        inf = torch.tensor(float("inf"), dtype=q.dtype, device=q.device)
        lo, hi = (box[0] / dt, box[1] / dt) if box is not None else (-inf.expand(A.shape[-1]),
                                                                      inf.expand(A.shape[-1]))
        rows = None if collision is None else collision.rows(p)
        qd = _posture(chain, q, dt, A, qd, lo, hi, posture, None if rows is None else (rows[0], rows[1] / dt))
    return qd
