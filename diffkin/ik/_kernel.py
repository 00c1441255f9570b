"""Batch-last FK + geometric Jacobian for the IK inner loop (private).

The solver keeps its state as ``(..., m)`` tensors (batch last): joint variables ``(n, m)``, rotation columns
``(3, m)``, like the chains' column kernel, so no transposes happen inside the loop (elementwise ops on a
contiguous trailing batch axis broadcast cheaply; a ``(m, 3) * (m, 1)`` broadcast is ~5x slower on CPU).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..chain import KinematicChain


def norm0(v: Tensor) -> Tensor:
    """Euclidean norm over the first axis of ``(k, m)`` (a reduction over a strided axis is slow)."""
    s = v[0] * v[0]
    for i in range(1, v.shape[0]):
        s = s + v[i] * v[i]
    return torch.sqrt(s)


class BatchLastKernel:
    """``kernel(q (n, m)) -> (J (n, 6K, m), x, y, z, p)``: the chain's batch-last kernel for the IK loop.

    Row block k of J (rows 6k..6k+5) is the Jacobian (3.30) of end link k; the end-link columns ``x, y, z,
    p`` are ``(3K, m)``, the K ends' columns stacked (K = 1 for a serial chain). ``chain`` must already be
    in the working dtype (the solver passes a float64 copy of a float32 chain).
    """

    def __init__(self, chain: KinematicChain):
        self.chain = chain
        self.n = chain.n_joints
        self.K = chain.n_ends

    def _stack(self, ends, m: int):
        cols = [[c.expand(3, m) for c in frame] for frame in ends]
        if self.K == 1:
            return tuple(cols[0])
        return tuple(torch.cat([f[i] for f in cols], 0) for i in range(4))

    def fk(self, q: Tensor):
        """``q (n, m) -> (x, y, z, p)`` each ``(3K, m)``."""
        return self._stack(self.chain.batch_last(q, check=False)[1], q.shape[-1])

    def __call__(self, q: Tensor):
        """``q (n, m) -> (J (n, 6K, m), x, y, z, p)``."""
        J, ends = self.chain.batch_last(q, with_jacobian=True, check=False)
        return (J, *self._stack(ends, q.shape[-1]))


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
        # bounded: a finite range that is not a full turn (quaternions and free positions have none)
        finite = torch.isfinite(chain.q_limits).all(-1).view(-1, 1).to(device) if limited else None
        bounded = (~(rev & (hi - lo >= 2 * math.pi)) & finite) if limited else torch.zeros_like(rev)
        self.bounded = bounded
        self.any_bounded = bool(bounded.any())
        # ball and free joints: LM steps v (nv) move u on the manifold (u = q there: unit quaternions)
        self.space = chain.configuration_space
        self.euclidean = self.space.euclidean
        self.nv = chain.nv
        self._v_of_q = torch.tensor(self.space.scalar_index("q"), device=device)  # q rows of scalar columns
        self._sv = torch.tensor(self.space.scalar_index("v"), device=device)

    def q_of_u(self, u: Tensor) -> Tensor:
        if not self.any_bounded:
            return u
        return torch.where(self.bounded, self.c + self.h * torch.sin(u), u)

    def dq_du(self, u: Tensor) -> Tensor | None:
        """The chain rule factor of each Jacobian column ``(nv, m)`` (None: all ones)."""
        if not self.any_bounded:
            return None
        d = torch.where(self.bounded, self.h * torch.cos(u), torch.ones_like(u))
        if self.euclidean:
            return d
        out = torch.ones(self.nv, u.shape[1], dtype=u.dtype, device=u.device)
        return out.index_copy(0, self._sv, d.index_select(0, self._v_of_q))

    def step(self, u: Tensor, du: Tensor) -> Tensor:
        """u ⊕ du for an LM step ``du (nv, m)``: u + du on 1-DOF chains, the configuration space's
        integrate on chains with ball or free joints (batch last)."""
        if self.euclidean:
            return u + du
        return self.space.integrate(u.T, du.T).T

    def u_of_q(self, q: Tensor) -> Tensor:
        """Inverse map for seeds; q is clamped into the limits first (slightly inside, so cos(u) != 0)."""
        if not self.euclidean:
            q = self.space.normalize(q.T).T
        if not self.any_bounded:
            return q
        s = ((q - self.c) / self.h).clamp(-1.0, 1.0) * (1.0 - 1e-6)
        return torch.where(self.bounded, torch.asin(s), q)

    def finalize(self, q: Tensor, clamp: bool) -> Tensor:
        """Wrap revolute joints by 2π towards the range centre; clamp into the limits if ``clamp``."""
        two_pi = 2.0 * math.pi
        q = torch.where(self.rev, q - two_pi * torch.round((q - self.c) / two_pi), q)
        if not self.euclidean:
            q = self.space.normalize(q.T).T
        return torch.where(self.bounded, torch.maximum(torch.minimum(q, self.hi), self.lo), q) if clamp else q

    def sample_u(self, m: int, generator) -> Tensor:
        """``m`` random seeds in u ``(nq, m)``: the one sampler's configurations (uniform in q within the
        ranges, quaternions uniform on S³) mapped by :meth:`u_of_q` (u = asin(2r - 1) on bounded joints)."""
        s = list(self.space.scalar_index())
        q = self.space.sample(self.lo[s, 0], self.hi[s, 0], (m,), generator)
        return self.u_of_q(q.T)
