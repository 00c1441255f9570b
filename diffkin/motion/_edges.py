"""Continuous collision checking of joint-space motions by subdivision with a proven step bound.

**The bound.** For a chain of revolute joints, the velocity of any point p rigidly attached to a link is
ṗ = Σ_j ω_j × (p − o_j) q̇_j with o_j a point of joint j's axis, so along any motion every geom point travels a
path of length at most Σ_j R_j ∫|q̇_j| dt, where R_j bounds the distance from joint j's axis to every point of
every geom downstream of joint j over all configurations. :func:`joint_reach` computes such R_j from the
rigid structure: each frame has a reference point fixed both in it and in its parent frame (a joint's own
frame: a point of that joint's axis, its origin in a URDF, the joint's ``pos`` in an MJCF body; a frame
rigid on its parent: its origin), so the distance between the reference points of a frame and its parent
never changes, and ``‖p − o_j‖ ≤`` (those distances from joint j's frame down to the geom's frame) ``+`` the
fixed distance of p from its frame's reference point ``+`` the geom's own extent (capsule radius, box
half-diagonal).

**The check.** A motion is sampled so that between consecutive samples every geom point travels at most
2η (η = ``resolution``): a straight edge Δq in ``ceil(Σ_j R_j |Δq_j| / (2η))`` equal steps (:data:`SPACING`).
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
from ..errors import ModelError

__all__ = ["joint_reach", "pairs_apart", "EdgeChecker", "SPACING"]

#: the subdivision's step in units of the resolution η: every geom point travels at most SPACING · η between
#: consecutive samples, so each instant is within η of its nearer sample (module docstring)
SPACING = 2.0


def joint_reach(collision) -> Tensor:
    """R ``(nq,)``: for each joint, a bound on the distance from its axis to every point of every geom it
    moves, in every configuration (module docstring). Revolute (and continuous) joints only.

    Remembered on the model's link frames (shared by the copies :meth:`RobotCollision.allow_collisions
    <diffkin.collision.RobotCollision.allow_collisions>` makes, one per scene) for the geometry's and the
    chain's current values: planning many scenes with one robot finds R once (about 3 ms a plan)."""
    return _reach(collision, geometry_key(collision))


def _reach(collision, key) -> Tensor:
    """:func:`joint_reach` for the geometry key ``key`` (:func:`geometry_key`), a copy of the remembered
    value (the caller may change it)."""
    return _remembered(collision, "reach", key, lambda: _joint_reach(collision)).clone()


def _remembered(collision, name: str, key, make):
    """``make()``, remembered as ``name`` on the model's link frames (shared by its copies) for ``key``
    (:func:`geometry_key`; one value per name: the last key's)."""
    if key is None:
        return make()
    memo = collision._frames.__dict__.setdefault("_geometry_memo", {})
    got = memo.get(name)
    if got is not None and got[0] == key:
        return got[1]
    value = make()
    memo[name] = (key, value)
    return value


def _joint_reach(collision) -> Tensor:
    """:func:`joint_reach`, computed: the largest of :func:`_column_reach` over the columns."""
    total = _column_reach(collision)[0]
    return torch.cat((total, total.new_zeros(total.shape[0], 1)), 1).amax(1)


def _column_reach(collision) -> tuple[Tensor, Tensor, Tensor]:
    """``(reach, moved, turns_axis)``: ``reach`` and ``moved`` ``(nq, C')`` over the capsule ends (``A``
    then ``B``) and box centres: reach[j, c] bounds the distance from joint j's axis to every point of column
    c's geom within reach of that column's point (the point's own extent: a capsule's radius, a box's
    half-diagonal), in every configuration (0 where joint j does not move it); moved[j, c]: whether joint j
    moves it; turns_axis ``(nq, nq)``: turns_axis[j, k], whether joint j moves joint k's axis (k's own
    frame: True for j = k)."""
    chain = collision.chain
    frames = collision._frames
    if collision.convex_vertices.shape[0]:  # the bound below counts capsule ends and box centres only
        raise ModelError("motion planning bounds the motion of capsule, sphere and box geoms; this model has "
                         f"{collision.convex_vertices.shape[0]} convex geoms: build it with "
                         'RobotCollision.from_urdf(..., geometry="capsules") to plan')
    with torch.no_grad():
        dt, dev = collision.capsule_a.dtype, collision.capsule_a.device
        g = torch.Generator().manual_seed(0)
        q0 = (torch.rand(chain.nq, generator=g, dtype=torch.float64, device="cpu") - 0.5).to(dt).to(dev)
        F0 = frames.frames(chain, q0)  # (K, 4, 4)
        K, nq = F0.shape[-3], chain.nq
        eps = 1e-3
        Fp = frames.frames(chain, q0 + eps * torch.eye(nq, dtype=dt, device=dev))  # (nq, K, 4, 4)
        moved = (Fp - F0).abs().flatten(-2).amax(-1) > 1e-7  # (nq, K): frame k moved by joint j
        turned = (Fp[..., :3, :3] - F0[..., :3, :3]).abs().flatten(-2).amax(-1) > 1e-7
        if bool((moved & ~turned).any()) or not bool(moved.any(1).all()):
            raise ModelError("motion planning bounds geom motion for revolute joints only: a joint of "
                             f"{type(chain).__name__} translates a frame without turning it (prismatic)")
        o = F0[..., :3, 3]
        first = torch.where(moved, torch.arange(K, device=dev), K).amin(1)  # joint j's own frame
        movers = moved.T  # (K, nq): the joints moving frame k
        # ancestors: frame m is on the path to frame k when every joint moving m also moves k
        anc = (movers[:, None, :] & ~movers[None, :, :]).any(-1) == 0  # anc[m, k]: movers(m) ⊆ movers(k)
        anc &= movers.any(1)[:, None]
        # the nearest proper ancestor (largest index: frames are in topological order), -1 for none
        idx = torch.arange(K, device=dev)
        cand = anc & (idx[:, None] < idx[None, :])  # cand[m, k]: m a proper ancestor of k
        parent = torch.where(cand, idx[:, None], -1).amax(0) if K else idx
        # each frame's reference point, fixed in it and in its parent: a joint's own frame's is a point of
        # that joint's axis (URDF: the frame's origin; MJCF: the joint's pos in its body, which may lie off
        # the body's origin: then the origin turns about the axis and its distance to the parent's varies),
        # any other frame's (rigid on its parent) its origin
        _, origin, _ = chain.joint_axes_origins(q0)
        if origin.shape[-2] != nq:  # one row per joint frame: more rows than coordinates with mimic joints
            raise ModelError(f"motion planning bounds geom motion where each coordinate turns one joint: "
                             f"{type(chain).__name__} has {origin.shape[-2]} joint frames for {nq} "
                             "coordinates (mimic joints: one coordinate turning joints on two branches can "
                             "change a robot-robot distance twice as fast as the bound)")
        ref = o.clone()
        ref[first.clamp(max=K - 1)] = origin.to(dt)
        link = torch.zeros(K, dtype=dt, device=dev)
        has = parent >= 0
        link[has] = (ref[has] - ref[parent[has]]).norm(dim=-1)
        P = collision._columns(q0)  # (3, C)
        nc, nb = collision._counts
        anchor = collision._col_anchor
        pts = P[:, : 2 * nc + nb].T  # capsule ends, box centres (C', 3)
        a_pts = anchor[: 2 * nc + nb]
        ext = torch.cat((collision.capsule_radius.detach(), collision.capsule_radius.detach(),
                         collision.box_half_extents.detach().norm(dim=-1)))
        own = (pts - ref[a_pts]).norm(dim=-1) + ext  # (C',)
        # R_j: the largest own extent + the fixed links between reference points from the geom's frame k up
        # to joint j's own frame f (f excluded: its reference point is on j's axis; up to the root where f
        # is not above k), over the geoms joint j moves: all
        # (joint, geom) pairs walk up the frame tree together, one level per step, in float64 (the sums as
        # before, link after link), then cast to the chain's dtype
        f64 = torch.float64
        link64, up = link.to(f64), torch.cat((parent, parent.new_full((1,), -1)))  # up[-1]: "none" stays
        total = own.to(f64)[None, :].expand(nq, -1)  # (nq, C')
        m = a_pts.expand(nq, -1)
        f = first[:, None]
        live = m != f
        for _ in range(K):  # over the depth of the frame tree (at most K levels), not over a batch
            total = total + torch.where(live, link64[m.clamp(min=0)], 0.0)
            m = up[m]
            live = live & (m != f) & (m >= 0)
        total = torch.where(moved[:, a_pts], total, 0.0)  # the geoms joint j moves only
        return total.to(dt), moved[:, a_pts], moved[:, first.clamp(max=K - 1)]

#: :func:`pairs_apart` tries the pairs whose distance only this many joints change (each more multiplies the
#: boxes: on the Panda the pairs of 2 joints, about half its 690, take 0.3 s; those of 3, 48 pairs, 0.2 s)
APART_JOINTS = 3
#: :func:`pairs_apart`'s budget: boxes evaluated in all, and halvings of a box at most
APART_BOXES, APART_ROUNDS = 400_000, 40


def pairs_apart(collision, pairs: Tensor, gap: float) -> tuple[Tensor, Tensor, Tensor]:
    """``(apart (P,) bool, lo (nq,), hi (nq,))``: which capsule pairs ``pairs (P, 2)`` (indices of the
    model's capsules) are proven at least ``gap`` apart (surface to surface) in every configuration of the
    box ``lo <= q <= hi``: the chain's limits, one turn about zero where a joint has none (a revolute
    joint's every angle is one of those). A pair not proven may still never come that close: the C search
    decides it as before (:class:`~diffkin.motion._native_search.NativePlanner` leaves the pairs proven
    apart out of its decisions at thresholds up to ``gap``).

    **The bound.** A pair's distance d changes only with the joints J that move one of its two geoms:
    a joint moving both turns them together. Over a box of centre c and half-widths h,
    ``|∂d/∂q_k| ≤ ρ_k(c) + Σ_l h_l R_l`` for k in J: ρ_k(c), the largest distance of the moved geom's
    segment ends from joint k's axis at c, bounds the speed of its points (Siciliano (3.30): a point's
    velocity ω × (p − o)); that distance changes only with the joints l that move the geom but not k's
    axis, by at most R_l (:func:`_column_reach`) a radian. So ``d(q) ≥ d(c) − Σ_k h_k (ρ_k(c) + Σ_l h_l
    R_l)`` on the box: where that is at least ``gap`` the box is proven; where d(c) < ``gap`` the pair is
    not apart; otherwise the box is halved along the joint of the largest term (branch and bound, all
    pairs' boxes at once). Pairs that more than :data:`APART_JOINTS` joints move, and pairs left unproven
    within :data:`APART_BOXES` evaluations, count as not apart.

    Remembered on the model's link frames per pair and ``gap`` (shared by the copies
    :meth:`~diffkin.collision.RobotCollision.allow_collisions` makes, one per scene): a robot pays once,
    about 0.4 s for a Panda's 690 pairs."""
    chain = collision.chain
    lim = chain.q_limits
    dt, dev = collision.capsule_a.dtype, collision.capsule_a.device
    nq = chain.nq
    if lim is None:
        lim = torch.full((nq, 2), torch.inf, dtype=dt, device=dev) * torch.tensor([-1.0, 1.0], dtype=dt,
                                                                                   device=dev)
    lim = lim.to(dt)
    lo = torch.where(lim[:, 0].isfinite(), lim[:, 0], -torch.pi)
    hi = torch.where(lim[:, 1].isfinite(), lim[:, 1], torch.pi)
    G = collision._counts[0]

    def fresh():  # (decided, proven) (G, G): the pairs decided so far and those proven
        return torch.zeros(2, G, G, dtype=torch.bool, device=dev)

    memo = _remembered(collision, f"pairs apart {float(gap)!r}", geometry_key(collision), fresh)
    i, j = pairs[:, 0].long(), pairs[:, 1].long()
    todo = ~memo[0, i, j]
    if bool(todo.any()):
        new = torch.unique(pairs[todo].long(), dim=0)
        got = _prove_apart(collision, new, float(gap), lo, hi)
        memo[0, new[:, 0], new[:, 1]] = True
        memo[1, new[:, 0], new[:, 1]] = got
    return memo[1, i, j].clone(), lo, hi


def _prove_apart(collision, pairs: Tensor, gap: float, lo: Tensor, hi: Tensor) -> Tensor:
    """:func:`pairs_apart`'s branch and bound: ``(P,)`` bool, the pairs proven."""
    with torch.no_grad():
        bound = _PairBound(collision, pairs)
        # a slack for the rounding of d(c): the chain's length unit times 100 ulps of its dtype
        eps = 100 * torch.finfo(lo.dtype).eps * (1.0 + float(bound.R.amax()))
        P, nq = pairs.shape[0], lo.shape[0]
        proven = torch.zeros(P, dtype=torch.bool, device=lo.device)
        tried = bound.J.sum(1) <= APART_JOINTS
        box = tried.nonzero().squeeze(1)  # each box's pair
        blo, bhi = lo.expand(box.numel(), nq).clone(), hi.expand(box.numel(), nq).clone()
        done = ~tried  # decided: proven, not apart, or not tried
        evaluated = 0
        for _ in range(APART_ROUNDS):  # halvings of the boxes, not a loop over a batch
            if box.numel() == 0 or evaluated > APART_BOXES:
                break
            evaluated += box.numel()
            d, term = bound(box, (blo + bhi) / 2, (bhi - blo) / 2)
            near = d < gap + eps  # a configuration closer than gap: the pair is not apart
            done[box[near]] = True
            split = ~done[box] & (d - term.sum(-1) < gap + eps)
            left = torch.zeros(P, dtype=torch.long, device=lo.device).index_add_(0, box[split],
                                                                              torch.ones_like(box[split]))
            proven |= ~done & (left == 0) & tried  # every box of the pair proven
            done |= proven
            box, blo, bhi, term = box[split], blo[split], bhi[split], term[split]
            k = term.argmax(-1)
            m = torch.arange(box.numel(), device=lo.device)
            mid = (blo[m, k] + bhi[m, k]) / 2
            blo2, bhi2 = blo.clone(), bhi.clone()
            bhi[m, k], blo2[m, k] = mid, mid
            box, blo, bhi = torch.cat((box, box)), torch.cat((blo, blo2)), torch.cat((bhi, bhi2))
        return proven


class _PairBound:
    """The bound of :func:`pairs_apart` for the capsule pairs ``pairs (P, 2)``: called with boxes of pairs
    ``which (N,)``, centres ``c (N, nq)`` and half-widths ``h (N, nq)``, it returns ``d (N,)``, the pair's
    distance at c, and ``term (N, nq)``, per joint a bound on how much the distance falls from c within the
    box along that joint: ``d(q) >= d - term.sum(-1)`` for every q of the box."""

    def __init__(self, collision, pairs: Tensor):
        reach, moved, turns = _column_reach(collision)
        self.collision, self.nc = collision, collision._counts[0]
        nc = self.nc
        self.R = torch.maximum(reach[:, :nc], reach[:, nc:2 * nc])  # (nq, G): each geom's, both ends
        M = moved[:, :nc]  # (nq, G): both ends lie in one frame
        self.i, self.j = pairs[:, 0], pairs[:, 1]
        self.J = (M[:, self.i] ^ M[:, self.j]).T  # (P, nq): the joints that change the pair's distance
        self.g = torch.where(M[:, self.i], self.i, self.j).T  # (P, nq): the geom joint k moves (k in J)
        Mg = M[:, self.g].permute(1, 2, 0)  # (P, nq_k, nq_l): joint l moves g_k
        # R_l where joint l moves g_k but not k's axis
        self.Rl = torch.where(Mg & ~turns.T[None], self.R[:, self.g].permute(1, 2, 0), 0.0)
        self.r = collision.capsule_radius.detach()
        # each capsule end's frame and coordinates there (the blocks of RobotCollision._placement): the pair's
        # four ends placed alone, not every geom's
        chain = collision.chain
        F = collision._frames.frames(chain, torch.zeros(chain.nq, dtype=reach.dtype, device=reach.device))
        H = collision._placement(F)  # (K·4, C)
        self.frame = collision._col_anchor[: 2 * nc].long()
        self.local = H.reshape(-1, 4, H.shape[-1])[self.frame, :, torch.arange(2 * nc, device=H.device)]

    def __call__(self, which: Tensor, c: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
        from ..collision.distances import capsule_capsule

        rc, nc, r = self.collision, self.nc, self.r
        n = torch.arange(which.numel(), device=c.device)
        i, j = self.i[which], self.j[which]
        ends = torch.stack((i, nc + i, j, nc + j), 1)  # (N, 4): the pair's capsule ends
        F = rc._frames.frames(rc.chain, c)  # (N, K, 4, 4)
        e = (F[n[:, None], self.frame[ends], :3] @ self.local[ends][..., None]).squeeze(-1)  # (N, 4, 3)
        z, o, _ = rc.chain.joint_axes_origins(c)  # (N, nq, 3)
        d = capsule_capsule(e[:, 0], e[:, 1], r[i], e[:, 2], e[:, 3], r[j])
        # ρ_k(c): the moved geom's segment ends' largest distance from joint k's axis
        moves_i = (self.g[which] == i[:, None])[..., None]  # (N, nq, 1): joint k moves geom i (else j)
        a = torch.where(moves_i, e[:, None, 0], e[:, None, 2])
        b = torch.where(moves_i, e[:, None, 1], e[:, None, 3])
        rho = torch.maximum(torch.linalg.cross(a - o, z).norm(dim=-1),
                            torch.linalg.cross(b - o, z).norm(dim=-1))
        term = torch.where(self.J[which], h * (rho + (self.Rl[which] * h[:, None, :]).sum(-1)), 0.0)
        return d, term


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
