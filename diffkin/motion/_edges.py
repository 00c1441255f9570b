"""Continuous collision checking of joint-space motions by subdivision with a proven step bound.

**The check.** A motion is sampled so that between consecutive samples every geom point travels at most
2η (η = ``resolution``): a straight edge Δq in ``ceil(Σ_j R_j |Δq_j| / (2η))`` equal steps (:data:`SPACING`;
R_j: :func:`~diffkin.motion._reach.joint_reach`, the bound of every geom point's speed along joint j).
At any instant between two samples each point is within η of where it was at the nearer sample (the bound
grows linearly in the fraction of the step), so a robot–obstacle distance is at most η smaller than at that
sample. So is a robot–robot distance: the joints that move both geoms turn the vector between two of their
points without changing its length, and each remaining joint moves one of the two only (the two links'
own branches of the tree share no joint), so the distance changes by at most Σ_j R_j |Δq_j| over the
joints, the same bound. Samples whose every distance is ≥ margin + η prove the continuous motion clear of
``margin`` (``tests/test_motion.py`` checks both bounds against exact distances).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..collision._values import geometry_key
from ._reach import _reach, _remembered

__all__ = ["EdgeChecker", "SPACING"]

#: the subdivision's step in units of the resolution η: every geom point travels at most SPACING · η between
#: consecutive samples, so each instant is within η of its nearer sample (module docstring)
SPACING = 2.0


class EdgeChecker:
    """Collision decisions for configurations and straight joint-space edges (module docstring)."""

    def __init__(self, collision, world, margin: float, resolution: float, chunk: int = 1 << 16):
        self.collision, self.world, self.margin, self.eta = collision, world, float(margin), float(resolution)
        #: a world with a leading batch dim: one scene per problem (read once: its shape is a broadcast of
        #: every object tensor's, and clear() runs tens of times a plan)
        self.per_row = world is not None and len(world.batch_shape) > 0
        #: per problem its own resolution ``(B,)`` (:meth:`set_row_resolution`; None: ``eta`` for all)
        self.row_eta: Tensor | None = None
        #: the robot's geometry and chain values (:func:`geometry_key`), read once
        self.geometry_key = geometry_key(collision)
        self.reach = _reach(collision, self.geometry_key)
        self.moving = bool(getattr(collision, "skip_fixed", False))
        self.chunk = chunk
        self.checked = 0  # configurations decided so far (a count for the benchmarks)
        #: decide through the C planner's one-call decisions where they serve (False: the torch placement
        #: and RobotCollision._clear, as on CUDA)
        self.use_c = True
        self._native: dict = {}

    def native(self, like: Tensor):
        """The C search's constants (:class:`~diffkin.motion._native_search.NativePlanner`) for tensors like
        ``like``, made once per dtype; None where they do not serve."""
        from ._native_search import NativePlanner

        key = (like.dtype, like.device)
        if key not in self._native:
            self._native[key] = NativePlanner.make(self, like)
        return self._native[key]

    def remembered(self, name: str, make):
        """``make()``, remembered for this robot's geometry and chain values (:func:`geometry_key`) on its
        link frames: shared by the checkers of the copies one robot makes per scene."""
        return _remembered(self.collision, name, self.geometry_key, make)

    def set_row_resolution(self, eta: Tensor) -> None:
        """Give problem b the resolution ``eta[b]`` (``(B,)``, each ≤ η): its edges are subdivided and its
        samples decided with it (a start or goal closer than margin + η to an obstacle gets a finer one)."""
        self.row_eta = eta
        #: its distinct values (a few; one decision per value)
        self._eta_values = torch.unique(eta).tolist()

    def eta_of(self, problem: Tensor) -> Tensor:
        """The resolution ``(...,)`` of each ``problem (...,)``."""
        if self.row_eta is None:
            return torch.full(problem.shape, self.eta, dtype=self.reach.dtype, device=problem.device)
        return self.row_eta[problem]

    def clear(self, q: Tensor, problem: Tensor, slack: float | None = None) -> Tensor:
        """(...,) bool: every distance ≥ margin + ``slack`` (default: each problem's resolution) at q
        (..., nq), each configuration in the world of its ``problem`` (...,) (long; a batched world
        ``(B, ...)`` has one scene per problem, an unbatched one serves all)."""
        if slack is None and self.row_eta is not None and len(self._eta_values) == 1:
            slack = self._eta_values[0]  # one resolution for every problem
        if slack is None and self.row_eta is not None:  # one decision per distinct resolution (a few)
            idx = problem.expand(q.shape[:-1])
            s = self.row_eta[idx]
            out = torch.empty(q.shape[:-1], dtype=torch.bool, device=q.device)
            for v in torch.unique(s).tolist():
                m = s == v
                out[m] = self.clear(q[m], idx[m], slack=v)
            return out
        slack = self.eta if slack is None else slack
        flat = q.reshape(-1, q.shape[-1])
        self.checked += flat.shape[0]
        if flat.shape[0] == 0:
            return torch.ones(q.shape[:-1], dtype=torch.bool, device=q.device)
        per_row = self.per_row
        idx = problem.expand(q.shape[:-1]).reshape(-1)
        planner = self.native(q) if self.use_c else None
        if planner is not None:  # FK, placement and decisions in one C call
            ok = planner.decide(flat, idx if per_row else None, slack)
            if ok is not None:
                return ok.reshape(q.shape[:-1])
        out = torch.cat([self.collision._clear(x, self.world, self.margin, slack, moving_only=self.moving,
                                               world_index=i if per_row else None)
                         for x, i in zip(flat.split(self.chunk), idx.split(self.chunk))])
        return out.reshape(q.shape[:-1])

    def steps(self, dq: Tensor, problem: Tensor | None = None) -> Tensor:
        """Sub-steps (...,) long for straight edges dq (..., nq) of problems ``problem`` (...,):
        ceil(Σ R_j |Δq_j| / (2 η_b)), at least 1 (η_b: the problem's resolution; η without ``problem``; 2:
        :data:`SPACING`, as ``dk_plan``'s steps in C)."""
        L = (dq.abs() * self.reach.to(dq.dtype)).sum(-1)
        eta = self.eta if problem is None else self.eta_of(problem).to(dq.dtype)
        return torch.ceil(L / (SPACING * eta)).clamp(min=1).long()

    def edges(self, qa: Tensor, qb: Tensor, problem: Tensor, prefix: bool = False,
              block: int = 256) -> tuple[Tensor, Tensor]:
        """Straight edges qa → qb (E, nq) of problems ``problem (E,)``: ``free (E,)`` and ``reach (E,)``,
        with ``prefix`` the largest
        fraction λ ∈ [0, 1] such that qa → qa + λ (qb − qa) is proven clear (0 when qa itself is not; without
        ``prefix``: 1 for free edges, 0 otherwise).

        The subdivision samples go in blocks of ``block`` per edge, an edge leaving as soon as one sample
        collides: in order along the edge with ``prefix``, coarse to fine otherwise (indices with more
        trailing zero bits first, so a colliding edge is usually caught in the first block; the C decisions
        take a long edge's rest in order after its coarse samples, and start with blocks of 4; without
        ``prefix`` they decide an edge of 6 sub-steps or more by covers, runs of three samples whose middle,
        clear of margin + 3η, proves its neighbours: the same outcome, fewer and cheaper decisions)."""
        E = qa.shape[0]
        if E == 0:
            z = qa.new_zeros(0)
            return z.bool(), z
        dev = qa.device
        n = self.steps(qb - qa, problem)
        planner = self.native(qa) if self.use_c else None
        if planner is not None:  # the same samples decided in C, edge after edge (no torch op per block)
            got = planner.edges(qa, qb, n, self.eta_of(problem), problem if self.per_row else None, prefix)
            if got is not None:
                first_bad, decided = got
                self.checked += int(decided.sum())
                return self._outcome(first_bad, n, prefix, qa)
        S = int(n.max()) + 1
        i = torch.arange(S, device=dev)
        if not prefix:
            low = torch.where(i == 0, S, i & -i)
            i = i[torch.argsort(-low, stable=True)]
        first_bad = torch.full((E,), S, dtype=torch.long, device=dev)
        active = torch.arange(E, device=dev)
        dq = qb - qa
        for b0 in range(0, S, block):
            if active.numel() == 0:
                break
            pos = i[b0:b0 + block]
            na = n[active]
            valid = pos[None, :] <= na[:, None]  # (A, P)
            r, c = valid.nonzero(as_tuple=True)
            if r.numel() == 0:
                continue
            rows = active[r]
            f = (pos[c] / n[rows]).to(qa.dtype)
            ok = self.clear(qa[rows] + f[:, None] * dq[rows], problem[rows])
            bad_pos = torch.full((active.numel(),), S, dtype=torch.long, device=dev)
            bad_pos.scatter_reduce_(0, r[~ok], pos[c][~ok], reduce="amin")
            first_bad[active] = torch.minimum(first_bad[active], bad_pos)
            active = active[(bad_pos == S) & (na > pos.max() if prefix else True)]
        return self._outcome(first_bad, n, prefix, qa)

    @staticmethod
    def _outcome(first_bad: Tensor, n: Tensor, prefix: bool, like: Tensor) -> tuple[Tensor, Tensor]:
        """``(free, reach)`` of edges of ``n (E,)`` sub-steps from the first colliding sample found on each
        (``first_bad > n``: none)."""
        free = first_bad > n
        if prefix:
            part = ((first_bad - 1).clamp(min=0) / n).to(like.dtype)
            reach = torch.where(free, torch.ones_like(like[:, 0]), part)
        else:
            reach = free.to(like.dtype)
        return free, reach
