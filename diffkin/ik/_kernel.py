"""Batch-last FK + geometric Jacobian for the IK inner loop (private).

The solver keeps its state as ``(..., m)`` tensors (batch last): joint variables ``(n, m)``, rotation columns
``(3, m)``, like the chains' column kernel, so no transposes happen inside the loop (elementwise ops on a
contiguous trailing batch axis broadcast cheaply; a ``(m, 3) * (m, 1)`` broadcast is ~5x slower on CPU).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .._numerics import cross
from ..chain import KinematicChain


def norm0(v: Tensor) -> Tensor:
    """Euclidean norm over the first axis of ``(k, m)`` (a reduction over a strided axis is slow)."""
    s = v[0] * v[0]
    for i in range(1, v.shape[0]):
        s = s + v[i] * v[i]
    return torch.sqrt(s)


class BatchLastKernel:
    """``kernel(q (n, m)) -> (J (n, 6, m), x, y, z, p)``: Jacobian rows per joint (3.30), EE columns (3, m).

    Runs the chain's own batch-last column kernel (``KinematicChain._column_frames``); ``chain`` must already
    be in the working dtype (the solver passes a float64 copy of a float32 chain).
    """

    def __init__(self, chain: KinematicChain):
        self.chain = chain
        self.n = chain.n_joints
        self.off = chain._axis_offset
        self.all_revolute = all(t == "R" for t in chain.joint_types)
        self.rev = chain.revolute_mask.detach().view(self.n, 1, 1)

    def _frames(self, q: Tensor, with_axes: bool):
        n, off, m = self.n, self.off, q.shape[-1]
        axes, origins = [], []
        for i, frame in enumerate(self.chain._column_frames(q)):
            if with_axes and off <= i < off + n:
                axes.append(frame[2].expand(3, m))
                origins.append(frame[3].expand(3, m))
        x, y, z, p = (c.expand(3, m) for c in frame)
        T = self.chain._ee_transform()
        if T is not None:  # columns of F · T
            x, y, z, p = (
                x * T[0, 0] + y * T[1, 0] + z * T[2, 0],
                x * T[0, 1] + y * T[1, 1] + z * T[2, 1],
                x * T[0, 2] + y * T[1, 2] + z * T[2, 2],
                p + x * T[0, 3] + y * T[1, 3] + z * T[2, 3],
            )
        return axes, origins, x, y, z, p

    def fk(self, q: Tensor):
        """``q (n, m) -> (x, y, z, p)`` each ``(3, m)``."""
        return self._frames(q, False)[2:]

    def __call__(self, q: Tensor):
        """``q (n, m) -> (J (n, 6, m), x, y, z, p)``; row k of J is joint k's [linear; angular] column."""
        axes, origins, x, y, z, p = self._frames(q, True)
        axes, origins = torch.stack(axes), torch.stack(origins)  # (n, 3, m)
        lin = cross(axes, p.unsqueeze(0) - origins, dim=1)  # z_{i-1} x (p_e - p_{i-1})  (3.30)
        if self.all_revolute:
            J = torch.cat((lin, axes), dim=1)
        else:
            J = torch.cat((lin * self.rev + axes * (1 - self.rev), axes * self.rev), dim=1)
        return J, x, y, z, p


class JointMap:
    """Joint limits as a change of variables (batch last): q = c + h sin(u) on bounded joints, else q = u.

    LM then runs unconstrained in u and every iterate lies within the limits (clamping instead stalls seeds
    that hit a limit). Revolute joints whose range spans 2π or more, and every joint when limits are off,
    are unbounded: they are wrapped by 2π towards the centre of their range at the end.
    """

    def __init__(self, chain: KinematicChain, dtype, device, respect_limits: bool):
        lo, hi = (t.detach().to(dtype=dtype, device=device).view(-1, 1) for t in chain.lower_upper())
        self.lo, self.hi = lo, hi
        self.c, self.h = 0.5 * (lo + hi), 0.5 * (hi - lo)
        rev = torch.tensor([t == "R" for t in chain.joint_types], device=device).view(-1, 1)
        self.rev = rev
        limited = chain.q_limits is not None and respect_limits
        bounded = ~(rev & (hi - lo >= 2 * math.pi)) if limited else torch.zeros_like(rev)
        self.bounded = bounded
        self.any_bounded = bool(bounded.any())

    def q_of_u(self, u: Tensor) -> Tensor:
        if not self.any_bounded:
            return u
        return torch.where(self.bounded, self.c + self.h * torch.sin(u), u)

    def dq_du(self, u: Tensor) -> Tensor | None:
        if not self.any_bounded:
            return None
        return torch.where(self.bounded, self.h * torch.cos(u), torch.ones_like(u))

    def u_of_q(self, q: Tensor) -> Tensor:
        """Inverse map for seeds; q is clamped into the limits first (slightly inside, so cos(u) != 0)."""
        if not self.any_bounded:
            return q
        s = ((q - self.c) / self.h).clamp(-1.0, 1.0) * (1.0 - 1e-6)
        return torch.where(self.bounded, torch.asin(s), q)

    def finalize(self, q: Tensor, clamp: bool) -> Tensor:
        """Wrap revolute joints by 2π towards the range centre; clamp into the limits if ``clamp``."""
        two_pi = 2.0 * math.pi
        q = torch.where(self.rev, q - two_pi * torch.round((q - self.c) / two_pi), q)
        return torch.maximum(torch.minimum(q, self.hi), self.lo) if clamp else q

    def sample_u(self, m: int, generator) -> Tensor:
        gdev = self.lo.device if generator is None else generator.device
        r = torch.rand(self.lo.shape[0], m, generator=generator, dtype=self.lo.dtype, device=gdev)
        r = r.to(self.lo.device)
        # uniform in q: u = asin(2r - 1) on bounded joints
        return torch.where(self.bounded, torch.asin((2.0 * r - 1.0) * (1.0 - 1e-6)), self.lo + 2 * self.h * r)
