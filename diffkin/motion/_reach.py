"""How fast robot geoms move with the joints, and which self pairs never come close: the bounds under the
continuous collision checks of :mod:`diffkin.motion._edges` and the C planner's decisions.

**The bound.** For a chain of revolute joints, the velocity of any point p rigidly attached to a link is
ṗ = Σ_j ω_j × (p − o_j) q̇_j (Siciliano (3.30)) with o_j a point of joint j's axis, so along any motion every
geom point travels a path of length at most Σ_j R_j ∫|q̇_j| dt, where R_j bounds the distance from joint j's
axis to every point of every geom downstream of joint j over all configurations. :func:`joint_reach` computes
such R_j from the rigid structure: each frame has a reference point fixed both in it and in its parent frame
(a joint's own frame: a point of that joint's axis, its origin in a URDF, the joint's ``pos`` in an MJCF body;
a frame rigid on its parent: its origin), so the distance between the reference points of a frame and its
parent never changes, and ``‖p − o_j‖ ≤`` (those distances from joint j's frame down to the geom's frame)
``+`` the fixed distance of p from its frame's reference point ``+`` the geom's own extent (capsule radius,
box half-diagonal). :func:`pairs_apart` turns the same argument on a pair's distance over a box of joint
space, to prove which self pairs stay apart within the joint limits.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..collision._values import geometry_key
from ..errors import ModelError

__all__ = ["joint_reach", "pairs_apart"]


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
    box ``lo <= q <= hi``: the chain's limits, one turn about zero for a joint with a limit missing (a
    revolute joint's every angle is one of those). A pair not proven may still never come that close: the C
    search decides it as before (:class:`~diffkin.motion._native_search.NativePlanner` leaves the pairs proven
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
        lim = torch.full((nq, 2), torch.inf, dtype=dt, device=dev)
    lim = lim.to(dt)
    # a joint with a limit missing: one turn, whichever (a revolute joint's angles repeat; a one-sided limit
    # past ±π would leave the box empty)
    whole = ~lim.isfinite().all(1)
    lo = torch.where(whole, -torch.pi, lim[:, 0])
    hi = torch.where(whole, torch.pi, lim[:, 1])
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
        # a slack for the rounding of d(c) and of the C decisions' samples at a box's faces (lo + (hi - lo) u
        # may pass a limit by an ulp): 100 ulps of the dtype, times the chain's reach in its length unit
        eps = 100 * torch.finfo(lo.dtype).eps * (1.0 + float(bound.R.amax()))
        P, nq = pairs.shape[0], lo.shape[0]
        proven = torch.zeros(P, dtype=torch.bool, device=lo.device)
        tried = bound.J.sum(1) <= APART_JOINTS
        pair_of = tried.nonzero().squeeze(1)  # each box's pair
        blo, bhi = lo.expand(pair_of.numel(), nq).clone(), hi.expand(pair_of.numel(), nq).clone()
        done = ~tried  # decided: proven, not apart, or not tried
        evaluated = 0
        for _ in range(APART_ROUNDS):  # halvings of the boxes, not a loop over a batch
            if pair_of.numel() == 0 or evaluated > APART_BOXES:
                break
            evaluated += pair_of.numel()
            d, term = bound(pair_of, (blo + bhi) / 2, (bhi - blo) / 2)
            near = ~(d >= gap + eps)  # a configuration closer than gap (or NaN): the pair is not apart
            done[pair_of[near]] = True
            split = ~done[pair_of] & ~(d - term.sum(-1) >= gap + eps)  # not proven (NaN: not proven either)
            left = torch.bincount(pair_of[split], minlength=P)
            proven |= ~done & (left == 0) & tried  # every box of the pair proven
            done |= proven
            pair_of, blo, bhi, term = pair_of[split], blo[split], bhi[split], term[split]
            k = term.argmax(-1)
            m = torch.arange(pair_of.numel(), device=lo.device)
            mid = (blo[m, k] + bhi[m, k]) / 2
            blo2, bhi2 = blo.clone(), bhi.clone()
            bhi[m, k], blo2[m, k] = mid, mid
            pair_of = torch.cat((pair_of, pair_of))
            blo, bhi = torch.cat((blo, blo2)), torch.cat((bhi, bhi2))
        return proven


def capsule_end_frames(collision, dtype) -> tuple[Tensor, Tensor]:
    """``(frame (2G,), local (2G, 4))``: each capsule end's frame (the first G the ends A, then B; an index
    of the model's link frames) and its homogeneous coordinates there, in ``dtype`` (the blocks of
    :meth:`RobotCollision._placement <diffkin.collision.RobotCollision>`): the robot's alone, so the C planner
    remembers them for the copies one robot makes per scene."""
    chain, nc = collision.chain, collision._counts[0]
    F = collision._frames.frames(chain, torch.zeros(chain.nq, dtype=dtype, device=collision.capsule_a.device))
    H = collision._placement(F)  # (K·4, C): column c's block is its frame's
    frame = collision._col_anchor[: 2 * nc].to(torch.int64).contiguous()
    local = H.reshape(-1, 4, H.shape[-1])[frame, :, torch.arange(2 * nc, device=H.device)]
    return frame, local.to(dtype).contiguous()


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
        # each capsule end's frame and coordinates there: the pair's four ends placed alone, not every geom's
        self.frame, self.local = capsule_end_frames(collision, reach.dtype)

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
