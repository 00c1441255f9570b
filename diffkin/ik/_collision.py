"""Collision constraints in :func:`diffkin.ik.solve` (private).

1. The seed library keeps collision-free poses only (:func:`free_library`).
2. The solve runs as without collision (the fused C pass included).
3. :func:`collision_round`: the exact distances of every pose-converged result, in the chain's dtype; the
   targets whose result collides are solved again, their colliding solution first, with an acceptance
   test in the LM schedule (:mod:`diffkin.ik._lm`): a harvested row is accepted only if every checked
   distance d is at least ``margin + slack``, else it is re-seeded like a stalled row (dropped when its
   target is out of seeds). With ``LMConfig.collision_refine_calls`` > 0 a rejected row first gets a
   constrained refinement, Gauss–Newton steps on the pose with the k smallest distances as linearised
   inequality constraints, one small QP per row (the interior point of :mod:`diffkin.ik.qp`)

       min_Δ ½‖W(J Δ − e)‖² + ½λ‖Δ‖²   s.t.   d_i + ∇d_i·Δ ≥ margin + 2 slack  (i: the k nearest),
                                              q_lo ≤ q + Δ ≤ q_hi,  |Δ| ≤ trust,

   the penetration recovered by at most ``push`` metres a step (so the linearisation stays valid and the
   QP feasible).
4. Success is decided by the exact distances of the returned q (never a success in collision).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import DiffkinError, ShapeError
from ..validation import check_number
from ._qp_ip import ip_solve
from .residuals import DistanceConstraint, PoseResidual


@dataclass(frozen=True)
class CollisionConfig:
    """Knobs of the refinement: ``slack`` (m) the distances keep above the margin (room for the final
    check in the chain's dtype), ``active`` nearest distances per row as constraints, ``detection`` (m)
    beyond which a distance is no constraint, ``steps``, per-step ``push`` (m) and ``trust`` (rad or m),
    ``qp_iterations`` of the interior point per step; rows penetrating deeper than ``deepest`` (m) are
    re-seeded without a refinement. How many acceptance calls refine is
    :attr:`~diffkin.ik.LMConfig.collision_refine_calls`."""

    slack: float = 1e-4
    active: int = 8
    detection: float = 0.05
    steps: int = 5
    deepest: float = 0.03
    push: float = 0.02
    trust: float = 0.3
    qp_iterations: int = 15


class _Direct:
    """A joint map that is the identity (the refinement works in q)."""

    @staticmethod
    def q_of_u(q: Tensor) -> Tensor:
        return q


class CollisionAcceptance:
    """``accept(idx (m,), u (n, m)) -> (ok (m,), u (n, m))`` for the schedule (module docstring)."""

    def __init__(self, constraint: DistanceConstraint, kernel, jmap, tg, residual: PoseResidual, sqrt_w,
                 tol, lm_cfg, cfg: CollisionConfig | None = None):  # fmt: skip
        self.c, self.kernel, self.jmap, self.tg, self.res = constraint, kernel, jmap, tg, residual
        self.sqrt_w, self.tol, self.lm, self.cfg = sqrt_w, tol, lm_cfg, cfg or CollisionConfig()
        self.calls = 0

    def free(self, q: Tensor) -> Tensor:
        """``q (n, m)`` -> every distance >= margin + slack ``(m,)``."""
        return self.c.satisfied(q.T, self.cfg.slack)

    def __call__(self, idx: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        q = self.jmap.q_of_u(u)
        g = self.c.value(q.T, self.cfg.slack)  # exact below margin + slack: ok and the depths are exact
        ok = (g >= self.cfg.slack).all(-1)
        # deep penetrations are left to re-seeding (a local refinement rarely resolves them)
        bad = (~ok & (g.amin(-1) > -self.cfg.deepest)).nonzero().squeeze(-1)
        self.calls += 1
        if bad.numel() == 0 or self.calls > self.lm.collision_refine_calls:
            return ok, u
        qb, fixed = self.refine(self.tg.take(idx[bad]), q[:, bad])
        u = u.clone()
        u[:, bad] = torch.where(fixed, self.jmap.u_of_q(qb), u[:, bad])
        return ok.index_put((bad,), fixed), u

    def _pose(self, tg, q: Tensor):
        """(A (m, r, n), b (m, r), position error (m,), angle (m,)) of the weighted pose rows."""
        J, e, pn, ang = self.res.batch_last(self.kernel, q, _Direct, tg)
        A = (J * self.sqrt_w).permute(2, 1, 0)
        return A, (e * self.sqrt_w).T, pn, ang

    def _bounds(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Step bounds ``(m, n)``: the joint limits of bounded joints and the trust region."""
        t = self.cfg.trust
        lo = torch.where(self.jmap.bounded, self.jmap.lo - q, -t).clamp_min(-t)
        hi = torch.where(self.jmap.bounded, self.jmap.hi - q, t).clamp_max(t)
        return lo.T, hi.T.maximum(lo.T)

    def _ok(self, g: Tensor, pn: Tensor, ang: Tensor, position_only: bool) -> Tensor:
        (tp, to), mg = self.tol, self.lm.margin
        ok = (pn <= tp * mg) & (g >= self.cfg.slack).all(-1)
        return ok if position_only else ok & (ang <= to * mg)

    def refine(self, tg, q: Tensor) -> tuple[Tensor, Tensor]:
        """Constrained Gauss–Newton from ``q (n, m)``: -> (q (n, m), accepted (m,)); rows leave the loop
        as soon as they are accepted (the loop runs on the rest only)."""
        cfg, lm = self.cfg, self.lm
        m, n = q.shape[1], q.shape[0]
        eye = torch.eye(n, dtype=q.dtype, device=q.device)
        ok = torch.zeros(m, dtype=torch.bool, device=q.device)
        live = torch.arange(m, device=q.device)
        q = q.clone()
        for step in range(cfg.steps + 1):
            ql, tl = q[:, live], tg.take(live)
            # rows beyond `detection` are no constraints: their broad-phase bound is enough
            g, rows, Jg = self.c.jacobian(ql.T, cfg.active, max(cfg.detection, cfg.slack))
            A, b, pn, ang = self._pose(tl, ql)
            now = self._ok(g, pn, ang, tg.position_only)
            ok[live[now]] = True
            keep = (~now).nonzero().squeeze(-1)
            if step == cfg.steps or keep.numel() == 0:
                break
            live, ql = live[keep], ql[:, keep]
            g, rows, Jg, A, b = (t[keep] for t in (g, rows, Jg, A, b))
            gk, mm = g.gather(-1, rows), live.numel()
            lam = lm.damping + lm.error_damping * (b * b).sum(-1)
            H = A.mT @ A + lam[:, None, None] * eye
            grad = (A.mT @ b.unsqueeze(-1)).squeeze(-1)
            # d + ∇d·Δ ≥ margin + 2 slack  <=>  −∇d·Δ ≤ g − 2 slack, recovering at most `push` a step
            rhs = torch.maximum(gk - 2.0 * cfg.slack, gk.new_tensor(-cfg.push))
            rhs = torch.where(gk < cfg.detection, rhs, torch.full_like(rhs, float("inf")))
            lo, hi = self._bounds(ql)
            G = torch.cat((-Jg, eye.expand(mm, n, n), -eye.expand(mm, n, n)), dim=-2)
            dq = ip_solve(H, grad, G, torch.cat((rhs, hi, -lo), dim=-1), cfg.qp_iterations)[0]
            dq = torch.where(torch.isfinite(dq), dq, torch.zeros_like(dq)).clamp(lo, hi)
            q[:, live] = ql + dq.T
        return q, ok


def free_library(lib_q: Tensor, constraint: DistanceConstraint, slack: float, keep: int) -> Tensor:
    """The columns of ``lib_q (n, M)`` whose distances all clear margin + slack, at most ``keep`` (all of
    the first ``keep`` columns when none does).

    Remembered on the collision model between calls: the same library sample (a solve with the same
    ``seed``), margin and slack against an unchanged model give the same columns, so they are reused when
    the sample is equal and every tensor the distances read is the same object at the same version (the
    chain's :meth:`_state_key`, the collision model's parameters and buffers, the world's tensors; the
    cache holds them, so no freed storage can be mistaken for them)."""
    coll = constraint.collision
    state = _model_state(constraint)
    memo = getattr(coll, "_free_library_memo", None)
    if state is not None and memo is not None and _same_state(memo[0], state) \
            and memo[1] == (float(slack), int(keep)) and torch.equal(memo[2], lib_q):
        return memo[3]
    free = constraint.satisfied(lib_q.T, slack)
    idx = free.nonzero().squeeze(-1)[:keep]
    idx = idx if idx.numel() else torch.arange(min(keep, lib_q.shape[1]), device=lib_q.device)
    if state is not None:
        coll._free_library_memo = (state, (float(slack), int(keep)), lib_q.clone(), idx)
    return idx


def _model_state(constraint: DistanceConstraint) -> tuple | None:
    """(chain, its state key, margin, [(tensor, version)] of the collision model and the world) or None
    where the distances may read state that no version tells (a user's ``body_poses`` callable)."""
    from ..collision._poses import LinkFrames

    coll = constraint.collision
    chain = getattr(coll, "chain", None)
    key = None if chain is None or not isinstance(coll._frames, LinkFrames) else chain._state_key()
    if key is None:
        return None
    w = constraint.world
    ts = [*coll.parameters(), *coll.buffers()]
    if w is not None:
        ts += [w.spheres, w.capsules, w.halfspaces, w.points, w.boxes.center, w.boxes.rotation,
               w.boxes.half_extents]
    return chain, key, constraint.margin, [(t, t._version) for t in ts]


def _same_state(a: tuple, b: tuple) -> bool:
    return a[0] is b[0] and a[1] == b[1] and a[2] == b[2] and len(a[3]) == len(b[3]) and all(
        x is y and u == v for (x, u), (y, v) in zip(a[3], b[3]))


def constraint_of(chain, collision, world, margin, base) -> DistanceConstraint | None:
    """The validated collision arguments of :func:`solve` and :func:`~diffkin.ik.optimize` as a
    :class:`DistanceConstraint` (None: none)."""
    if collision is None:
        if world is not None:
            raise DiffkinError("ik: a world needs the robot's collision model (collision=...)")
        return None
    from ..collision import RobotCollision
    from ..collision.world import _check_world

    if not isinstance(collision, RobotCollision):
        raise DiffkinError(f"ik: expected collision as a diffkin.collision.RobotCollision, got "
                           f"{type(collision).__name__}")
    collision._check_chain(chain, "ik")  # the geoms are placed by the collision model's own chain
    margin = check_number(margin, "margin", positive=False)
    if world is not None:
        world = _check_world(world)
        if any(t.ndim > 2 for t in (world.spheres, world.capsules, world.halfspaces, world.points)) or \
                world.boxes.center.ndim > 2:
            raise ShapeError("ik: one world for all targets (objects without batch dims)")
    if base is not None and world is not None:
        raise DiffkinError("ik.solve: a world with per-target bases is not supported (the world is in the "
                           "chain's base frame)")
    return DistanceConstraint(collision, world, float(margin))


def collision_round(prob, constraint: DistanceConstraint, *out):
    """Step 2-4 of the module docstring on the outputs ``out`` of ``prob.run()`` (``prob``: the solve's
    ``_Problem``, :mod:`diffkin.ik.numerical`): success also needs every distance >= margin (the user's
    model, the chain's dtype); targets whose pose converged in collision are solved again from that
    solution with the acceptance test (re-seeding, and the refinement if configured), and checked again."""
    q, success, pos_err, ori_err, iters, seeds = out
    free = constraint.satisfied(q)
    redo = (success & ~free).nonzero().squeeze(-1)
    success = success & free
    if redo.numel():
        jm, dtype = prob.jmap, prob.tg.pd.dtype
        sqrt_w = prob.residual.sqrt_weights(prob.kernel.K, dtype, q.device)
        accept = CollisionAcceptance(prob.constraint, prob.kernel, jm, prob.tg.take(redo), prob.residual,
                                     sqrt_w, prob.tol, prob.cfg)  # fmt: skip
        q2, ok2, pe2, oe2, it2, s2 = prob.run(redo, q[redo].to(dtype), accept)
        ok2 &= constraint.satisfied(q2)
        take = redo[ok2]
        q, success = q.index_copy(0, take, q2[ok2]), success.index_put((take,), ok2[ok2])
        pos_err, ori_err = pos_err.index_copy(0, take, pe2[ok2]), ori_err.index_copy(0, take, oe2[ok2])
        iters, seeds = iters.index_add(0, redo, it2), seeds.index_add(0, redo, s2)
    return q, success, pos_err, ori_err, iters, seeds
