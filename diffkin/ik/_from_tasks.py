"""The task and limit objects as the arguments of the position-level solver :func:`~diffkin.ik.solve`.

``solve(chain, tasks=[FrameTask(frame, target=T), ...], limits=[ConfigurationLimit(), CollisionLimit(...)])``
is ``solve(chain, T_target, respect_limits=..., collision=..., world=..., margin=...)``: one pose
:class:`~diffkin.ik.FrameTask` per end link (the targets; position only where every orientation cost is 0),
:class:`~diffkin.ik.ConfigurationLimit` for the joint limits (without it, and with ``limits`` given, the
iterates are free), :class:`~diffkin.ik.CollisionLimit` for the collision constraint (its
``minimum_distance`` is the margin). Other tasks have no place in a pose solve (``ik.optimize`` and
``ik.solve_velocity`` take them); a :class:`~diffkin.ik.VelocityLimit` has none either. The pose solve
reaches the whole target (or its position): a zero cost on some axes only (a FrameTask's error rows
log(T_f⁻¹ T_t) left free, per axis of the frame's twist) changes the problem, and is refused with a pointer
to ``ik.optimize`` / ``ik.solve_velocity``, which drop those rows; positive costs do not change an exactly
reached pose and the LM weighs the rows by its own ``LMConfig.orientation_weight``.

``optimize(chain, tasks=..., limits=...)`` takes every task (but the twist form of a FrameTask): each is the
cost term ‖W e(q)‖² (:class:`TaskCost`, the task's own error and costs), the pose FrameTasks also give the
targets its success flags are judged against; the limits as for ``solve``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..errors import ConventionError
from .limits import CollisionLimit, ConfigurationLimit, VelocityLimit, check_limits
from .residuals import CostContext, _Term
from .tasks import FrameTask, Problem, Task, _per_axis

__all__ = ["TaskCost", "optimize_arguments", "solve_arguments"]


@dataclass(frozen=True)
class TaskCost(_Term):
    """A task as a cost term of :func:`~diffkin.ik.optimize`: residual W e(q) ``(..., m)`` (its error and
    cost vector), cost ``weight``·‖W e‖²."""

    task: Any = None

    def residual(self, ctx: CostContext) -> Tensor:
        p = Problem(ctx.chain, ctx.q, 1.0)
        e = self.task.error(p)
        return self.task.cost_vector(p, e.shape[-1]) * e


def _position_only(tasks, p: Problem, strict: bool) -> bool:
    """Whether the pose FrameTasks ask for positions only (every orientation cost 0); ``strict`` (ik.solve):
    a :class:`~diffkin.errors.ConventionError` for zero costs the pose solve cannot honour (some axes or
    some tasks only, or a position cost): the LM's residual has every row. (ik.optimize minimises the
    tasks' own weighted errors: there the flag only chooses the errors ``success`` is judged on.)"""
    zeros = []
    for t in tasks:
        pos = _per_axis(p, t.position_cost, "FrameTask.position_cost", 3)
        ori = _per_axis(p, t.orientation_cost, "FrameTask.orientation_cost", 3)
        if strict and bool((pos == 0).any()):
            raise ConventionError(f"ik.solve reaches every position axis: a zero FrameTask.position_cost "
                                  f"(frame {t.frame!r}) leaves rows free; use ik.optimize(tasks=...) or "
                                  f"ik.solve_velocity, which drop them")
        zeros.append(ori == 0)
    if all(bool(z.all()) for z in zeros):
        return True
    if strict and any(bool(z.any()) for z in zeros):
        raise ConventionError("ik.solve reaches the whole orientation or none: FrameTask.orientation_cost 0 "
                              "on every axis of every task (position only) or on none; for some axes only "
                              "use ik.optimize(tasks=...) or ik.solve_velocity, which drop those rows")
    return False


def optimize_arguments(chain, T_target, tasks, limits, costs, position_only, respect_limits, collision, world,
                       margin):
    """(T_target, costs, position_only, respect_limits, collision, world, margin) of ``optimize``."""
    if tasks is not None:
        tasks = (tasks,) if isinstance(tasks, Task) else tuple(tasks)
        bad = [t for t in tasks
               if not isinstance(t, Task) or (isinstance(t, FrameTask) and t.twist is not None)]
        if bad:
            raise ConventionError(f"ik.optimize: expected Task objects (a FrameTask with a target pose, not "
                                  f"a twist), got {bad[0]!r}")
        poses = [t for t in tasks if type(t) is FrameTask]
        if T_target is None:
            T_target, position_only, *_ = solve_arguments(chain, None, poses, None, position_only,
                                                          respect_limits, collision, world, margin,
                                                          strict=False)
        costs = [TaskCost(task=t) for t in tasks] + list(costs or [])
    _, _, respect_limits, collision, world, margin = solve_arguments(
        chain, T_target, None, limits, position_only, respect_limits, collision, world, margin)
    return T_target, costs, position_only, respect_limits, collision, world, margin


def solve_arguments(chain, T_target, tasks, limits, position_only, respect_limits, collision, world, margin,
                    strict=True):
    """(T_target, position_only, respect_limits, collision, world, margin) of ``solve`` from the objects
    (``strict``: refuse the zero costs the pose solve cannot honour, :func:`_position_only`)."""
    if tasks is not None:
        if T_target is not None:
            raise ConventionError("ik.solve: give the targets once (T_target, or pose FrameTasks in tasks=)")
        tasks = (tasks,) if isinstance(tasks, FrameTask) else tuple(tasks)
        bad = [t for t in tasks if type(t) is not FrameTask or t.target is None]
        if bad or not tasks:
            raise ConventionError(f"ik.solve takes pose FrameTasks (FrameTask(frame, target=T)), one per "
                                  f"end link; got {bad[0] if bad else 'none'!r}: other tasks go to "
                                  f"ik.optimize or ik.solve_velocity")
        p = Problem(chain, torch.zeros(chain.nq, dtype=chain.dtype, device=chain.device), 1.0)
        by_end = {p.end_index(t.frame, "ik.solve: FrameTask.frame"): t for t in tasks}
        if len(by_end) != len(tasks) or sorted(by_end) != list(range(chain.n_ends)):
            raise ConventionError(f"ik.solve: expected one pose FrameTask per end link ({chain.n_ends}), got "
                                  f"frames {[t.frame for t in tasks]}")
        targets = [p.like("FrameTask.target", by_end[k].target, (4, 4)) for k in range(chain.n_ends)]
        targets = torch.broadcast_tensors(*targets)
        T_target = targets[0] if chain.single_end else torch.stack(targets, dim=-3)
        if _position_only(tasks, p, strict):
            position_only = True
            T_target = T_target[..., :3, 3]
    if limits is not None:
        limits = check_limits(limits)
        if any(isinstance(lim, VelocityLimit) for lim in limits):
            raise ConventionError("ik.solve: a VelocityLimit has no meaning for a pose solve (no step Δt)")
        respect_limits = any(isinstance(lim, ConfigurationLimit) for lim in limits)
        cols = [lim for lim in limits if isinstance(lim, CollisionLimit)]
        if len(cols) > 1:
            raise ConventionError("ik.solve: at most one CollisionLimit")
        if cols:
            collision, world, margin = cols[0].collision, cols[0].world, cols[0].minimum_distance
    return T_target, position_only, respect_limits, collision, world, margin
