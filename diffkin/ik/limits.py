"""IK limits: hard constraints on the step Δq = q̇ Δt, as small frozen objects in mink's vocabulary, batched.

A limit declares box bounds lo ≤ Δq ≤ hi ``(..., nv)`` (:meth:`Limit.box`) and/or rows G Δq ≤ h
``(..., p, nv)``, ``(..., p)`` (:meth:`Limit.rows`; h = inf switches a row off). That is all a limit is:
a new limit is one class.

=====================  =====================================================================================
limit                  constraint on Δq
=====================  =====================================================================================
ConfigurationLimit     γ (q_min + d − q) ≤ Δq ≤ γ (q_max − d − q), limited scalar coordinates    (L.1)
VelocityLimit          −q̇_max Δt ≤ Δq ≤ q̇_max Δt, floating bases included                          (L.2)
CollisionLimit         −J_d Δq ≤ γ max(d − d_min, 0) for every distance d < d_detect                    (L.3)
=====================  =====================================================================================

Where the boxes disagree (q already outside its limits and a velocity limit too small to come back in one
step) the velocity limit wins: each box clamps the ones before it, in the order configuration, velocity.
(L.3) is mink's ``CollisionAvoidanceLimit`` with a bound that is never negative: a pair at or below the
minimum distance may not approach further (the distance over the step shrinks by at most γ times its
excess over d_min), but it is not pushed apart, which would make the problem infeasible where two geoms
touch at rest (a Panda's closed fingers).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from ..errors import ConventionError, DiffkinError, ShapeError
from ..validation import check_nonnegative, check_number, shape_str
from .tasks import Problem, _Frozen, joint_dofs, objects_of

__all__ = ["CollisionLimit", "ConfigurationLimit", "Limit", "VelocityLimit"]


class Limit(_Frozen):
    """The base of every limit: :meth:`box` and :meth:`rows` (either may return None). ``rank``: the order
    in which boxes clamp each other (later ones win)."""

    __slots__ = ()
    rank = 0

    def box(self, p: Problem) -> tuple[Tensor, Tensor] | None:
        return None

    def rows(self, p: Problem) -> tuple[Tensor, Tensor] | None:
        return None


class ConfigurationLimit(Limit):
    """The chain's joint position limits ``chain.q_limits`` (L.1): gain γ ∈ (0, 1] (the fraction of the
    distance to a limit that one step may cover), ``min_distance_from_limits`` d (rad or m; positive
    shrinks the range). Joints without limits (±inf), and the rotations of ball and free joints, are free
    (mink's ``ConfigurationLimit``)."""

    __slots__ = ("gain", "min_distance_from_limits")

    def __init__(self, *, gain=0.95, min_distance_from_limits=0.0):
        gain = check_number(gain, "ConfigurationLimit.gain")
        if gain > 1.0:
            raise DiffkinError(f"ConfigurationLimit: expected gain in (0, 1], got {gain}")
        d = check_number(min_distance_from_limits, "ConfigurationLimit.min_distance_from_limits",
                         positive=False)
        self._set(gain=gain, min_distance_from_limits=d)

    def box(self, p: Problem):
        chain, q = p.chain, p.q
        if chain.q_limits is None:
            return None
        lim = chain.q_limits.to(q)
        lower, upper = lim[:, 0] + self.min_distance_from_limits, lim[:, 1] - self.min_distance_from_limits
        space = chain.configuration_space
        if space.euclidean:
            return self.gain * (lower - q), self.gain * (upper - q)
        sq = list(space.scalar_index("q"))
        sv = torch.tensor(space.scalar_index("v"), device=q.device)
        lo_s, hi_s = self.gain * (lower[sq] - q[..., sq]), self.gain * (upper[sq] - q[..., sq])
        inf = torch.full((*q.shape[:-1], p.nv), float("inf"), dtype=q.dtype, device=q.device)
        return (-inf).index_copy(-1, sv, lo_s), inf.index_copy(-1, sv, hi_s)


class VelocityLimit(Limit):
    """|q̇| ≤ q̇_max (L.2): ``velocity`` a number (every velocity coordinate), ``(..., nv)``, or
    ``{joint name: limit}`` (a number, or one per velocity coordinate of the joint: 3 for a ball joint, 6
    [linear; angular] for a free joint, in the chain's velocity coordinates). Joints not named are free;
    inf: no limit."""

    __slots__ = ("velocity",)
    rank = 1

    def __init__(self, velocity):
        self._set(velocity=velocity)

    def limits(self, p: Problem) -> Tensor:
        """q̇_max ``(..., nv)`` (inf where none)."""
        if isinstance(self.velocity, Mapping):
            joints = {name: cols for name, _, cols in joint_dofs(p.chain)}
            vmax = torch.full((p.nv,), float("inf"), dtype=p.q.dtype, device=p.q.device)
            for name, value in self.velocity.items():
                if name not in joints:
                    raise ConventionError(f"VelocityLimit: {name!r} is not a joint of the chain (its joints: "
                                          f"{list(joints)})")
                v = p.like(f"VelocityLimit[{name!r}]", value, None)
                cols = joints[name]
                if v.ndim and v.shape != (len(cols),):
                    raise ShapeError(f"VelocityLimit: expected the limit of {name!r} as a number or "
                                     f"({len(cols)},), got {shape_str(v.shape)}")
                vmax[cols] = v
            return check_nonnegative(vmax, "VelocityLimit.velocity")
        v = check_nonnegative(p.like("VelocityLimit.velocity", self.velocity, None), "VelocityLimit.velocity")
        if v.ndim == 0:
            return v.expand(p.nv)
        if v.shape[-1] != p.nv:
            raise ShapeError(f"VelocityLimit: expected velocity as a number, (..., {p.nv}) or a dict by "
                             f"joint name, got {shape_str(v.shape)}")
        return v

    def box(self, p: Problem):
        v = self.limits(p) * p.dt
        return -v, v


class CollisionLimit(Limit):
    """Collision avoidance (L.3) for the checked distances of ``collision`` (a
    :class:`~diffkin.collision.RobotCollision` of the chain: its self pairs) and, with ``world`` (a
    :class:`~diffkin.collision.World`), each geom to each world object: every distance d closer than
    ``detection_distance`` (m) may shrink over the step by at most ``gain`` times its excess over
    ``minimum_distance`` (m), never by a negative amount. J_d = ∂d/∂q (autograd of the closed-form
    distances, times the tangent map of q for ball and free joints); the rows are constants of the step
    (their derivatives w.r.t. q do not flow into q̇'s gradient)."""

    __slots__ = ("collision", "world", "gain", "minimum_distance", "detection_distance")

    def __init__(self, collision, world=None, *, gain=0.85, minimum_distance=0.005, detection_distance=0.01):
        if collision is None:
            raise DiffkinError("CollisionLimit: needs the robot's collision model (a RobotCollision)")
        gain = check_number(gain, "CollisionLimit.gain")
        if gain > 1.0:
            raise DiffkinError(f"CollisionLimit: expected gain in (0, 1], got {gain}")
        self._set(collision=collision, world=world, gain=gain,
                  minimum_distance=check_number(minimum_distance, "CollisionLimit.minimum_distance",
                                                positive=False),
                  detection_distance=check_number(detection_distance, "CollisionLimit.detection_distance",
                                                  positive=False))

    def rows(self, p: Problem):
        from .residuals import DistanceConstraint

        d, _, Jd = DistanceConstraint(self.collision, self.world).jacobian(p.q)  # every row (margin 0)
        space = p.chain.configuration_space
        if not space.euclidean:
            Jd = Jd @ space.tangent_map(p.q)
        bound = self.gain * (d - self.minimum_distance).clamp(min=0.0)
        return -Jd, torch.where(d < self.detection_distance, bound, torch.full_like(d, float("inf")))


def combine_boxes(limits, p: Problem) -> tuple[Tensor, Tensor] | None:
    """lo, hi ``(..., nv)`` of every box in ``limits``, each clamping the ones of lower rank."""
    boxes = [(lim.rank, i, b) for i, lim in enumerate(limits) if (b := lim.box(p)) is not None]
    if not boxes:
        return None
    boxes.sort(key=lambda t: (t[0], t[1]))
    lo, hi = boxes[0][2]
    for _, _, (l2, h2) in boxes[1:]:
        lo, hi = torch.minimum(torch.maximum(lo, l2), h2), torch.minimum(torch.maximum(hi, l2), h2)
    return lo, hi


def check_limits(limits: Any) -> tuple[Limit, ...]:
    return objects_of(limits, Limit, "limits", "ConfigurationLimit, VelocityLimit, CollisionLimit")
