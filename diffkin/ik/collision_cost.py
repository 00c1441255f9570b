"""The collision term of :func:`diffkin.ik.optimize`: a one-sided quadratic penalty on the checked distances.

r_i = max(0, margin + buffer − d_i) for every distance of a :class:`~diffkin.ik.residuals.DistanceConstraint`
(self pairs, and each geom to each world object), cost = weight·Σ r_i² (least squares: Gauss–Newton uses
it too). Where every distance exceeds margin + buffer (the constraints are inactive) the term and all its
derivatives vanish in a neighbourhood, so the implicit gradient of the stationary point
(:mod:`diffkin.ik.implicit`) is exactly that of the pose problem; where a distance is within the buffer
the term is active and the gradient is that of the penalised stationary point (the compromise between pose
and clearance at this weight), not of a hard-constrained KKT point; the second derivative of r² jumps where
d crosses margin + buffer (the gradient is one-sided there). ``optimize``'s ``success`` checks the hard
condition d >= margin with the exact distances.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .residuals import CostContext, DistanceConstraint, _Term

__all__ = ["CollisionCost"]


@dataclass(frozen=True, eq=False)
class CollisionCost(_Term):
    """weight·Σ max(0, margin + buffer − d)² over the distances of ``collision`` (a
    :class:`~diffkin.collision.RobotCollision`) and, with ``world``, its geoms to the world's objects."""

    weight: float = 100.0
    collision: object = None
    world: object = None
    margin: float = 0.0
    buffer: float = 0.01

    def residual(self, ctx: CostContext) -> Tensor:
        check = getattr(self.collision, "_check_chain", None)
        if check is not None:  # the geoms are placed by the collision model's chain: it must be ctx's
            check(ctx.chain, "ik.optimize (CollisionCost)")
        d = DistanceConstraint(self.collision, self.world).distances(ctx.q)
        return torch.relu(self.margin + self.buffer - d).expand(*ctx.q.shape[:-1], d.shape[-1])
