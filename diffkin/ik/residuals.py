"""The IK residuals as objects (private to :mod:`diffkin.ik`): one encoding of the pose error and of the
collision constraints, shared by :func:`~diffkin.ik.solve` (its torch iteration and the selection of the C
pass), :func:`~diffkin.ik.optimize`, the implicit gradients (:mod:`diffkin.ik.implicit`),
:func:`~diffkin.ik.dls_step` and :func:`~diffkin.ik.velocity_step`.

* :class:`PoseResidual` — F(q) = [p_d − p; √w·θr] per end link (3.78, θr the rotation vector of R_d R_eᵀ),
  the position rows only when ``position_only``; ``value`` ``(..., r)``, ``jacobian`` ∂(p; √w·θ)/∂q (the
  geometric Jacobian rows (3.30) with the same weights, = −∂F/∂q near a solution), ``batch_last`` the same
  error on the solver's batch-last state, ``sqrt_weights`` the row weights the C pass is given.
* :class:`DistanceConstraint` — g(q) = d(q) − margin ≥ 0 for every checked distance of a
  :class:`~diffkin.collision.RobotCollision` (its self pairs, and each geom to each object of a
  :class:`~diffkin.collision.World`); ``value`` ``(..., D)``, ``jacobian`` ∂d/∂q of chosen rows by autograd
  of the closed-form distances.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor

from .._unchecked import fk
from ..errors import DiffkinError
from ..kernels.pose_error import orientation_error
from ._kernel import norm0

__all__ = ["PoseResidual", "DistanceConstraint", "CostContext"]


@dataclass(frozen=True)
class PoseResidual:
    """F(q) = [p_d − p; √w·θr] per end link, flattened ``(..., r)`` (r = 6K, or 3K when ``position_only``).

    ``exact_near_pi``: the rotation vector also near θ = π (far from a solution, :func:`dls_step`); the
    solvers use the plain form (exact where θ is small, its gradient defined up to θ = π).
    """

    position_only: bool = False
    orientation_weight: float = 1.0
    exact_near_pi: bool = False

    def error(self, T: Tensor, T_target: Tensor) -> Tensor:
        """F from end poses ``T (..., [K,] 4, 4)`` and targets (poses, or positions ``(..., [K,] 3)``)."""
        if self.position_only:
            p_d = T_target if T_target.shape[-1] == 3 else T_target[..., :3, 3]
            return p_d - T[..., :3, 3]
        e_o, _ = orientation_error(T_target[..., :3, :3], T[..., :3, :3], "rotvec",
                                   exact_near_pi=self.exact_near_pi)
        e_p, e_o = torch.broadcast_tensors(T_target[..., :3, 3] - T[..., :3, 3], e_o)
        return torch.cat((e_p, self.orientation_weight**0.5 * e_o), dim=-1)

    def value(self, chain, q: Tensor, T_target: Tensor) -> Tensor:
        """F ``(..., r)`` at ``q (..., n)`` (no FK graph unless a chain parameter requires grad)."""
        grad = q.requires_grad or any(p.requires_grad for p in chain.parameters())
        with torch.set_grad_enabled(torch.is_grad_enabled() and grad):
            T = fk(chain, q)
        return self.error(T, T_target).reshape(*T.shape[: q.ndim - 1], -1)

    def rows(self, J: Tensor) -> Tensor:
        """The weighted rows of geometric Jacobians ``(..., [K,] 6, nv)`` matching F: ``(..., r, nv)``."""
        if self.position_only:
            J = J[..., :3, :]
        else:
            J = torch.cat((J[..., :3, :], self.orientation_weight**0.5 * J[..., 3:, :]), dim=-2)
        return J

    def jacobian(self, chain, q: Tensor) -> Tensor:
        """−∂F/∂q near a solution: the geometric Jacobian rows (3.30) of F, ``(..., r, nv)``."""
        J = self.rows(chain.geometric_jacobian(q, check=False))
        return J.reshape(*q.shape[:-1], -1, J.shape[-1])

    def sqrt_weights(self, K: int, dtype, device) -> Tensor:
        """The row weights ``(r, 1)`` (1 on positions, √w on orientations; every end link's block)."""
        w = torch.ones(3 if self.position_only else 6, 1, dtype=dtype, device=device)
        w[3:] = math.sqrt(self.orientation_weight)
        return w.repeat(K, 1)

    def batch_last(self, kernel, u: Tensor, jmap, tg):
        """The solver's state ``u (n, m)`` against its batch-last targets ``tg``: J ``(n, r, m)``
        (unweighted), the unweighted error ``(r, m)`` ([e_p; θr] per end link, or e_p), and the worst
        position and orientation error over the K end links ``(m,)`` each."""
        J, x, y, z, p = kernel(jmap.q_of_u(u))
        ep = tg.pd - p
        K = kernel.K
        pn = norm0(ep) if K == 1 else torch.stack([norm0(ep[3 * k : 3 * k + 3]) for k in range(K)]).amax(0)
        if tg.position_only:
            Jp = J[:, :3] if K == 1 else torch.cat([J[:, 6 * k : 6 * k + 3] for k in range(K)], 1)
            return Jp, ep, pn, torch.zeros_like(pn)
        e, angs = [], []
        for k in range(K):
            blk = slice(3 * k, 3 * k + 3)
            # θr with the gradient up to θ = π; the merit only needs θ, so no exact axis near π
            eo, ang = orientation_error((tg.xd[blk], tg.yd[blk], tg.zd[blk]), (x[blk], y[blk], z[blk]),
                                        "rotvec", layout="columns", exact_near_pi=False)  # fmt: skip
            e += [ep[blk], eo]
            angs.append(ang)
        return J, torch.cat(e, 0), pn, angs[0] if K == 1 else torch.stack(angs).amax(0)


class DistanceConstraint:
    """g(q) = d(q) − margin ≥ 0 for every checked distance of ``collision`` (a
    :class:`~diffkin.collision.RobotCollision`): its self pairs, then, with ``world`` (a
    :class:`~diffkin.collision.World`), each geom to each world object (geom-major), ``(..., D)``. While
    ``collision.skip_fixed`` (the default) the entries no q can change are left out: pairs of two geoms fixed
    to the base and the world rows of such geoms (:attr:`~diffkin.collision.RobotCollision.fixed`)."""

    def __init__(self, collision, world=None, margin: float = 0.0):
        self.collision, self.world, self.margin = collision, world, float(margin)

    def distances(self, q: Tensor, threshold: float | None = None) -> Tensor:
        """The signed distances d ``(..., D)`` (metres; negative: penetration depth), the geoms placed once
        for the self and the world distances. ``threshold``: the broad phase of
        :meth:`~diffkin.collision.RobotCollision._distances_at_least` (exact wherever d or its bound is
        below ``threshold``, >= ``threshold`` elsewhere: the decisions d >= t, t <= threshold, are exact)."""
        # the entries no q can change (geoms fixed to the base) are left out unless the model says otherwise
        moving = bool(getattr(self.collision, "skip_fixed", False))
        return self.collision._distances_at_least(q, self.world, threshold, moving_only=moving)

    def value(self, q: Tensor, slack: float | None = None) -> Tensor:
        """g = d − margin ``(..., D)``; with ``slack`` exact only where g < slack (>= slack elsewhere)."""
        return self.distances(q, None if slack is None else self.margin + slack) - self.margin

    def satisfied(self, q: Tensor, slack: float = 0.0) -> Tensor:
        """Every distance >= margin + slack ``(...)`` (True where there are none), decided by the exact
        distances (the broad phase only skips those its bound proves clear; :meth:`RobotCollision._clear
        <diffkin.collision.RobotCollision._clear>`)."""
        moving = bool(getattr(self.collision, "skip_fixed", False))
        return self.collision._clear(q, self.world, self.margin, slack, moving_only=moving)

    def jacobian(self, q: Tensor, nearest: int | None = None,
                 slack: float | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """(g ``(..., D)`` detached, the rows ``(..., k)`` (indices into D: the ``nearest`` smallest g, or
        all), ∂g/∂q of those rows ``(..., k, n)``) from one evaluation and one vectorised backward pass per
        row (autograd of the closed-form distances), in q's coordinates. ``slack``: as in :meth:`value`
        (rows with g >= slack may hold their bound and its gradient: for constraints inactive there)."""
        with torch.enable_grad():
            qg = q.detach().requires_grad_(True)
            g = self.value(qg, slack)
            D = g.shape[-1]
            k = D if nearest is None else min(int(nearest), D)
            rows = g.detach().topk(k, dim=-1, largest=False).indices if k < D else \
                torch.arange(D, device=g.device).expand(g.shape)
            sel = g.gather(-1, rows)
            if k == 0:
                return g.detach(), rows, q.new_zeros(*sel.shape, q.shape[-1])
            Jg = _residual_jacobian(sel, qg)
        return g.detach(), rows, Jg.detach()

    def to(self, dtype) -> DistanceConstraint:
        """A copy evaluating in ``dtype`` (the collision model, its chain and the world converted)."""
        import copy

        if self.collision.capsule_radius.dtype == dtype:
            return self
        if getattr(self.collision, "chain", None) is None:
            raise DiffkinError("a RobotCollision without a chain evaluates in its own dtype only: build it "
                               "in the solver's dtype")
        coll = copy.deepcopy(self.collision).to(dtype)  # the geometry (the chain is held by reference)
        coll.chain = coll.chain.to(dtype)  # the deep copy's chain, never the user's
        w = None if self.world is None else self.world.to(dtype)
        return DistanceConstraint(coll, w, self.margin)


# ------------------------------------------------------------ cost terms (ik.optimize's residuals)
class CostContext:
    """What cost terms see: ``q (..., n)``, the target, and lazily the FK pose and Jacobian of ``q``."""

    def __init__(self, chain, q: Tensor, T_target: Tensor):
        self.chain, self.q, self.T_target = chain, q, T_target

    @cached_property
    def fk_and_jacobian(self) -> tuple[Tensor, Tensor]:
        from ..jacobian import forward_kinematics_and_jacobian

        return forward_kinematics_and_jacobian(self.chain, self.q, check=False)

    @cached_property
    def T(self) -> Tensor:
        if "fk_and_jacobian" in self.__dict__:
            return self.fk_and_jacobian[0]
        return fk(self.chain, self.q)

    @property
    def J(self) -> Tensor:
        return self.fk_and_jacobian[1]


@dataclass(frozen=True)
class _Term:
    weight: float = 1.0

    def residual(self, ctx: CostContext) -> Tensor | None:
        """Residual ``(..., r)`` with cost = weight·‖r‖², or None for a general (non least-squares) term."""
        return None

    def __call__(self, ctx: CostContext) -> Tensor:
        r = self.residual(ctx)
        return self.weight * (r * r).sum(-1)


def _residual_jacobian(r: Tensor, q: Tensor, create_graph: bool = False) -> Tensor:
    """Per-sample Jacobian ``(..., R, n)`` of ``r (..., R)`` w.r.t. ``q (..., n)`` (independent samples)."""
    R = r.shape[-1]
    eye = torch.eye(R, dtype=r.dtype, device=r.device).view(R, *([1] * (r.ndim - 1)), R).expand(R, *r.shape)
    try:
        (g,) = torch.autograd.grad(r, q, grad_outputs=eye, is_grads_batched=True, retain_graph=True,
                                   create_graph=create_graph)
    except RuntimeError:  # an op without a batching rule: one backward pass per residual row
        g = torch.stack([torch.autograd.grad(r[..., k].sum(), q, retain_graph=True,
                                             create_graph=create_graph)[0] for k in range(R)])
    return g.movedim(0, -2)
