"""The task and limit objects as the arguments of :func:`~diffkin.ik.clik` (private).

``clik(chain, q0=q0, dt=dt, steps=n, tasks=[...], limits=[...])`` is ``clik(chain, (x_d, ẋ_d), q0, dt, n,
rows=..., K=..., nullspace=..., k0=..., limits=..., qdot_max=...)``:

* a :class:`~diffkin.ik.FrameTask` with ``target`` x_d ``(..., S, 4, 4)`` (S samples every Δt; a pose
  ``(4, 4)`` alone is one sample, held) is the tracked end link; its costs W (a number or per axis) select
  the task rows (a zero cost drops the row: ``orientation_cost=0`` is the position-only task) and weight
  them (J and the reference velocity rows scaled by W: the weighted laws; costs of 1 are the plain laws);
  its ``gain`` α sets K = α/Δt (α = 1: the error closed in one step; today's default K = 0.5/Δt is α = 0.5),
  unless ``K`` is given;
* a second FrameTask on the same frame with ``twist`` ẋ_d = [ṗ_d; ω_d] ``(..., S, 6)`` is the feed-forward
  velocity (zero without one);
* a :class:`~diffkin.ik.PostureTask` ``(q_ref, cost=c, gain=α)`` is the null-space objective (3.55)
  w(q) = −½ ‖c (q ⊖ q_ref)‖² with k₀ = α/Δt: q̇₀ = (α/Δt) c² (q_ref ⊖ q) (the free joints' columns
  excluded). ``nullspace="joint_limits"`` (3.57) with gain k₀ is this task with q_ref the middle of the
  ranges, c = 1/(√n (q_M − q_m)) and α = k₀Δt;
* :class:`~diffkin.ik.ConfigurationLimit` and :class:`~diffkin.ik.VelocityLimit` are the hard bounds of the
  limited DLS step (``algorithm="dls"``): ``limits=True`` is ``[ConfigurationLimit(gain=1.0)]`` plus
  ``VelocityLimit(qdot_max)`` when ``qdot_max`` is given.

Callable targets, the second-order ẍ_d, position (``(..., S, 3)``) and [p; φ] targets stay arguments.
"""

from __future__ import annotations

from numbers import Number

import torch
from torch import Tensor

from ..errors import ConventionError, DiffkinError
from .limits import ConfigurationLimit, Limit, VelocityLimit, check_limits
from .tasks import FrameTask, PostureTask, Problem, Task

__all__ = ["clik_arguments", "clik_limits"]


def _frame(chain, t: FrameTask) -> None:
    ends = list(getattr(chain, "end_links", None) or [])
    by_name = isinstance(t.frame, str) and ends[:1] == [t.frame]
    ok = (t.frame == 0 and not isinstance(t.frame, bool)) or by_name
    if not (chain.single_end and ok):
        raise ConventionError(f"ik.clik: a FrameTask's frame must be the chain's end link (0 or its name), "
                              f"got {t.frame!r}")


def _number(x, name: str) -> float:
    if isinstance(x, Tensor) and x.numel() == 1:
        x = float(x)
    if not isinstance(x, Number) or isinstance(x, bool):
        raise ConventionError(f"ik.clik: {name} must be a number here, got {x!r}")
    return float(x)


def clik_arguments(chain, T_target, tasks, dt: float, orientation, rows, K, nullspace, k0):
    """(T_target, orientation, rows, weights ``(..., 6)`` or None, K, nullspace, k0) from the objects."""
    if T_target is not None:
        raise ConventionError("ik.clik: give the target once (T_target, or a FrameTask with target= in "
                              "tasks=)")
    if rows is not None:
        raise ConventionError("ik.clik: with tasks=, the FrameTask's costs select the rows (0 drops one)")
    tasks = (tasks,) if isinstance(tasks, Task) else tuple(tasks)
    bad = [t for t in tasks if type(t) not in (FrameTask, PostureTask)]
    if bad:
        raise ConventionError(f"ik.clik takes FrameTask and PostureTask objects, got {bad[0]!r}")
    poses = [t for t in tasks if type(t) is FrameTask and t.target is not None]
    twists = [t for t in tasks if type(t) is FrameTask and t.twist is not None]
    postures = [t for t in tasks if type(t) is PostureTask]
    if len(poses) != 1 or len(twists) > 1 or len(postures) > 1:
        raise ConventionError(f"ik.clik: expected one FrameTask with a target, at most one with a twist (its "
                              f"feed-forward) and at most one PostureTask; got {len(poses)}, {len(twists)}, "
                              f"{len(postures)}")
    task = poses[0]
    for t in poses + twists:
        _frame(chain, t)
        if _number(t.lm_damping, "FrameTask.lm_damping") != 0.0:
            raise ConventionError("ik.clik: FrameTask.lm_damping has no place in CLIK; use damping=")
    p = Problem(chain, torch.zeros(chain.nq, dtype=chain.dtype, device=chain.device), dt)
    w = task.cost_vector(p, 6)
    keep = (w != 0).reshape(-1, 6).any(0).tolist()
    if not any(keep[3:]):
        orientation = None
    elif orientation is None:
        raise ConventionError("ik.clik: orientation=None tracks the position only; give the FrameTask "
                              "orientation_cost=0, or choose an orientation error")
    size = 3 if orientation is None else 6
    rows = [i for i in range(size) if keep[i]]
    if not rows:
        raise DiffkinError("ik.clik: every cost of the FrameTask is 0: nothing to track")
    weights = None if bool((w == 1).all()) else w
    x_d = p.like("FrameTask.target", task.target, (4, 4))
    x_d = x_d.unsqueeze(-3) if x_d.ndim == 2 else x_d
    target = (x_d,)
    if twists:
        if orientation == "euler":
            raise ConventionError("ik.clik: a twist [v; ω] is no feed-forward for orientation='euler' (whose "
                                  "ẋ_d is [ṗ; φ̇]): pass T_target=(x_d, xdot_d) instead")
        target = (x_d, p.like("FrameTask.twist", twists[0].twist, (6,)))
    if K is None:
        K = _number(task.gain, "FrameTask.gain") / dt
    if postures:
        if nullspace is not None:
            raise ConventionError("ik.clik: give the null-space objective once (nullspace=, or a "
                                  "PostureTask)")
        nullspace, k0 = _posture_objective(chain, postures[0], p), _number(postures[0].gain,
                                                                          "PostureTask.gain") / dt
    return target, orientation, tuple(rows), weights, K, nullspace, k0


def _posture_objective(chain, task: PostureTask, p: Problem):
    """w(q) = −½ ‖c (q ⊖ q_ref)‖² of a :class:`PostureTask` (its error: the free joints' columns 0)."""

    def w(q: Tensor) -> Tensor:
        pq = Problem(chain, q, p.dt)
        e = task.error(pq)
        return -0.5 * ((task.cost_vector(pq, e.shape[-1]) * e) ** 2).sum(-1)

    return w


def clik_limits(limits, qdot_max) -> tuple[Limit, ...] | None:
    """The limit objects of the limited DLS step: ``limits=True`` is ``[ConfigurationLimit(gain=1.0)]`` (+
    ``VelocityLimit(qdot_max)``); objects are checked (Configuration and Velocity limits only); None: off."""
    if limits is False or limits is None:
        return None
    if limits is True:
        return (ConfigurationLimit(gain=1.0),) + (() if qdot_max is None else (VelocityLimit(qdot_max),))
    objs = check_limits(limits)
    bad = [x for x in objs if type(x) not in (ConfigurationLimit, VelocityLimit)]
    if bad:
        raise ConventionError(f"ik.clik takes ConfigurationLimit and VelocityLimit objects, got {bad[0]!r} "
                              f"(collision limits: ik.solve_velocity)")
    if qdot_max is not None:
        raise ConventionError("ik.clik: with limit objects, give the velocity bound as a VelocityLimit, not "
                              "qdot_max")
    return objs or None
