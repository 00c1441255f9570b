"""Self-collision rows of the whole-clip optimisation (:func:`~diffkin.retarget.optimize_clip`).

For the checked pairs of a :class:`~diffkin.collision.RobotCollision`, the inequality d_p(q_t) ≥ m (m the
margin) enters the Gauss–Newton as the residual

    r_{p,t} = w min(0, d_p(q_t) − m),    ∂r/∂δ = w [d_p < m] ∂d_p/∂q · ∂(q ⊕ δ)/∂δ,

zero while the pair is clear (the same one-sided penalty as the sole's ``penetration`` rows; with a weight
far above the keypoints' the equilibrium depth is ≈ (keypoint pull) / w², sub-millimetre).

Broad phase, once per round: the pairs are screened on the warm start. A pair is kept when it comes within
``m + screen`` in some frame of some clip; each iteration then evaluates only those pairs (the G1 of
Menagerie's MJX scene has 26 self pairs; on the shipped clips 13-22 are kept, the legs' and those of a
hand near a hip or an arm near the torso). The steps can move a limb farther than the screen (a hand
pushed out of the torso onto the hip): :meth:`SelfCollisionRows.extend` screens the result again and adds
the pairs found, and :func:`~diffkin.retarget.optimize_clip` then runs another round of iterations.

The distances are the collision layer's closed forms. Their Jacobian is assembled from the bodies'
geometric Jacobians: with every kept pair given its own copies of its two geoms (so each placed point or
axis x_c belongs to one pair), one backward pass of Σ d over the placed geometry only (no FK in the graph)
gives each pair's g_c = ∂d_p/∂x_c; a point moves as ẋ = v_k + ω_k × (x − o_k) with its body k, an axis as
ω_k × x, so

    ∂d_p/∂δ = Σ_sides F_sᵀ J_v(k_s) + (M_s − o_{k_s} × F_s)ᵀ J_ω(k_s),
    F_s = Σ_points g_c,  M_s = Σ_c x_c × g_c,

the pair's wrench on each of its bodies (for capsules and spheres, nᵀ (J_p(a, p_a) − J_p(b, p_b)) with the
witness points p_a, p_b and the unit normal n). The bodies' poses come from one FK pass of the MJCF
model's every body (:func:`diffkin.models.mjcf_bodies.body_poses`' chain, the fused C kernel on CPU), their
Jacobians from one FK+Jacobian pass over the frames where some pair is within the margin (the others have
no active row; finding them is one host read per evaluation, as the collision layer's broad phase, which
also leaves the exact distance of pairs its bound proves beyond the margin uncomputed). A model placed
otherwise (``body_poses=`` of one's own, another q layout) takes the
autograd path: one batched backward pass per kept pair through all frames' FK (each frame's distance
depends on that frame's q only, so ∂(Σ_t d_{p,t})/∂q_t = ∂d_{p,t}/∂q_t); both give the same rows
(``tests/test_retarget_collision.py``).
"""

from __future__ import annotations

import functools
from pathlib import Path

import torch
from torch import Tensor

from ..errors import ModelError
from ..ik.residuals import _residual_jacobian
from ..models.mjcf_bodies import _companion, body_poses

__all__ = ["G1_MJX_SCENE", "SelfCollisionRows", "g1_collision"]


class SelfCollisionRows:
    """The screened pairs of ``collision`` for the warm start ``q (B, T, nq)`` and their residual rows.

    ``pairs``: the names of the kept pairs (those within ``margin + screen`` in some frame at the warm
    start, and at each :meth:`extend`), ``count``: how many.
    """

    def __init__(self, collision, chain, q: Tensor, margin: float, screen: float):
        if not hasattr(collision, "self_distances") or not hasattr(collision, "_pair_index"):
            raise ModelError(f"collision must be a diffkin.collision.RobotCollision of the chain, got "
                             f"{type(collision).__name__}")
        collision._check_chain(chain, "retarget (collision=)")
        self.chain, self.collision, self.margin, self.screen = chain, collision, float(margin), float(screen)
        self.index: list[int] = []
        self.pairs: list[tuple[str, str]] = []
        self.count, self.model = 0, None
        self._bodies = _bodies_chain(collision, chain)
        self.extend(q)

    def extend(self, q: Tensor) -> bool:
        """Screen ``q (B, T, nq)`` (every pair of the collision model, one evaluation and one host read) and
        keep the pairs within ``margin + screen`` in some frame besides those kept; True when some were
        added."""
        B, T, nq = q.shape
        with torch.no_grad():
            d = self.collision.self_distances(q.reshape(B * T, nq))  # (B T, P)
            near = (d < self.margin + self.screen).any(0).nonzero().flatten().tolist()
        new = sorted(set(near) - set(self.index))
        if not new:
            return False
        self.index = sorted(set(self.index) | set(new))
        c = self.collision
        self.pairs = [c.pairs[i] for i in self.index]
        self.count = len(self.index)
        self.model = c._with_pairs([c._pair_index[i] for i in self.index]).requires_grad_(False)
        self._split = _per_pair(c, [c._pair_index[i] for i in self.index])
        return True

    def distances(self, q: Tensor) -> Tensor:
        """The kept pairs' signed distances ``(B, T, P_kept)`` (metres; negative: penetration)."""
        B, T, nq = q.shape
        if self.model is None:
            return q.new_zeros(B, T, 0)
        return self.model.self_distances(q.reshape(B * T, nq)).reshape(B, T, -1)

    def rows(self, q: Tensor, weight: float) -> tuple[Tensor, Tensor]:
        """The residuals ``(B, T, P_kept)`` and their Jacobians ``(B, T, P_kept, nv)`` w.r.t. the step δ of
        :meth:`~diffkin.kernels.configuration.ConfigurationSpace.integrate` (module doc)."""
        B, T, nq = q.shape
        nv = self.chain.nv
        if self.model is None:
            return q.new_zeros(B, T, 0), q.new_zeros(B, T, 0, nv)
        d, J = self.jacobian(q.detach().reshape(B * T, nq), below=self.margin)
        active = (d < self.margin).to(q.dtype) * weight
        r = active * (d - self.margin)
        J = active.unsqueeze(-1) * J.detach()
        return r.reshape(B, T, -1), J.reshape(B, T, -1, nv)

    def jacobian(self, q: Tensor, autograd: bool = False,
                 below: float | None = None) -> tuple[Tensor, Tensor]:
        """The kept pairs' distances ``(N, P_kept)`` and their Jacobians ``(N, P_kept, nv)`` w.r.t. the step δ
        at ``q (N, nq)``, detached: from the bodies' Jacobians where the model's bodies are the MJCF
        chain's (module doc), else (or with ``autograd``) by autograd through every frame's FK. ``below``:
        exact only where d < ``below``; elsewhere d >= ``below`` (the collision layer's broad phase: the
        exact box distances are most of the cost) with finite rows, zero in the frames where no pair is
        below (their bodies' Jacobians are not computed). The rows need no more."""
        if self.model is None:  # no pair kept
            return q.new_zeros(q.shape[0], 0), q.new_zeros(q.shape[0], 0, self.chain.nv)
        full = None if autograd else self._bodies
        if full is None:
            with torch.enable_grad():
                qg = q.detach().requires_grad_(True)
                d = self.model.self_distances(qg)  # (N, P)
                Jq = _residual_jacobian(d, qg)  # (N, P, nq)
            space = self.chain.configuration_space
            J = Jq if space.euclidean else Jq @ space.tangent_map(q)  # (N, P, nv)
            return d.detach(), J.detach()
        split, point, group, anchor, bodies, slot = self._split
        T = full.forward_kinematics(q, check=False)  # (N, nbody − 1, 4, 4): every body but the world
        F = torch.cat((torch.eye(4, dtype=q.dtype, device=q.device).expand(q.shape[0], 1, 4, 4), T), 1)
        with torch.enable_grad():
            P = split._columns_at(F).detach().requires_grad_(True)  # (N, 3, C): each column one pair's
            d = split._self_from(P, threshold=below)  # (N, P)
            (g,) = torch.autograd.grad(d.sum(), P)
        d = d.detach()
        J = q.new_zeros(*d.shape, self.chain.nv)
        if below is not None:  # the frames with a pair below (one host read): their rows only
            rows = (d < below).any(-1).nonzero().flatten()
            if rows.numel() == 0:
                return d, J
            P, g, F, q = P.index_select(0, rows), g.index_select(0, rows), F.index_select(0, rows), q[rows]
        N, C, S, K = P.shape[0], P.shape[-1], group.shape[0], len(bodies)
        X, g = P.detach().permute(2, 0, 1), g.permute(2, 0, 1)  # (C, N, 3): columns first, for one product
        # per moving side (pair, side): F_s (points only) and M_s about the world origin, summed over its
        # columns, then M_s about its body's origin o_k
        w = torch.cat((g * point.unsqueeze(-1), torch.linalg.cross(X, g, dim=-1)), -1)  # (C, N, 6)
        f, m = (group @ w.reshape(C, -1)).view(S, N, 6).split(3, -1)
        o = F[:, anchor, :3, 3].transpose(0, 1)  # (S, N, 3)
        w = torch.cat((f, m - torch.linalg.cross(o, f, dim=-1)), -1)
        # each side's wrench in its pair's slot for its body (both sides of a pair may share one), then one
        # batched product with those bodies' stacked Jacobians (N, K·6, nv): no Jacobian gathered per side
        W = w.new_zeros(d.shape[-1] * K, N, 6).index_add_(0, slot, w)
        W = W.view(-1, K, N, 6).permute(2, 0, 1, 3).reshape(N, -1, 6 * K)  # (N, P, K·6)
        _, JF = full.forward_kinematics_and_jacobian(q, check=False)  # (N, nbody − 1, 6, nv)
        Jr = torch.bmm(W, JF.index_select(1, bodies - 1).reshape(N, 6 * K, -1))  # (N, P, nv)
        return d, (Jr if below is None else J.index_copy_(0, rows, Jr))


def _bodies_chain(collision, chain):
    """The chain from the world to every MuJoCo body that places ``collision``'s geoms
    (:func:`~diffkin.models.mjcf_bodies.body_poses` of ``chain``, its default for an MJCF chain) where its
    coordinates are ``chain``'s own (the same joints, q and δ layout: its Jacobians are then in ``chain``'s
    δ); None otherwise (a model placed by another ``body_poses``)."""
    poses = getattr(collision._frames, "_poses", None)
    if not (isinstance(poses, functools.partial) and poses.func is body_poses and poses.args == (chain,)):
        return None
    full = _companion(chain)
    # the same joints at the same qpos addresses: full.from_qpos(chain.to_qpos(q)) is q itself
    same = full.joint_names == chain.joint_names and (full.nq, full.nv) == (chain.nq, chain.nv) \
        and list(full._qpos_index) == list(chain._qpos_index)
    return full if same else None


def _per_pair(collision, pairs: list[tuple[int, int]]):
    """The model of ``pairs`` (geom indices into ``collision``) with each pair's own copies of its two geoms
    (geoms 2p and 2p + 1), so every column of its placement product belongs to one pair, and the column
    tables of :meth:`SelfCollisionRows.jacobian`: ``point (C, 1)`` 1 on point columns (0 on box axes);
    for the S sides (pair p's side s, copy 2p + s) on a moving body: ``group (S, C)`` their incidence with
    the columns, ``anchor (S,)`` their bodies, ``bodies (K,)`` those bodies (ascending), ``slot (S,)``
    p K + (the body's place in ``bodies``)."""
    c = collision
    kind = {}  # geom index -> its values, as the constructor takes them
    for shape, values in zip(("capsule", "box", "convex"), c._geometry_values()):
        kind.update(zip((k for k, geom in enumerate(c.geoms) if geom.shape == shape), values))
    own = [g for pair in pairs for g in pair]  # copy 2p + s of geom pairs[p][s]
    geoms = [c.geoms[g] for g in own]
    by = lambda shape: [kind[g] for g in own if c.geoms[g].shape == shape]  # noqa: E731
    split = type(c)(c.chain, geoms, [g.link for g in geoms], by("capsule"), by("box"),
                    [(2 * p, 2 * p + 1) for p in range(len(pairs))], convexes=by("convex"), frames=c._frames,
                    dtype=c.capsule_a.dtype, device=c.capsule_a.device).requires_grad_(False)
    split.skip_fixed = c.skip_fixed
    # the column -> copy map of RobotCollision's placement product (capsule starts, ends, box centres, box
    # axes, convex vertices)
    of = lambda shape: [k for k, geom in enumerate(geoms) if geom.shape == shape]  # noqa: E731
    cap, bx, cv = of("capsule"), of("box"), of("convex")
    M = split.convex_vertices.shape[1]
    col = cap * 2 + bx + [g for g in bx for _ in range(3)] + [g for g in cv for _ in range(M)]
    point = torch.ones(len(col), 1, dtype=c.capsule_a.dtype, device=c.capsule_a.device)
    point[2 * len(cap) + len(bx):2 * len(cap) + 4 * len(bx)] = 0
    group = point.new_zeros(len(geoms), len(col))
    group[col, torch.arange(len(col), device=point.device)] = 1
    # the sides on a moving body (one on the world body, 0, contributes nothing), those bodies, and each
    # side's slot p K + k among them
    moving = [k for k, a in enumerate(split._anchor) if a != 0]
    used = sorted({split._anchor[k] for k in moving})
    slot = [(k // 2) * len(used) + used.index(split._anchor[k]) for k in moving]
    long = lambda x: torch.tensor(x, dtype=torch.long, device=point.device)  # noqa: E731
    return split, point, group[moving], long([split._anchor[k] for k in moving]), long(used), long(slot)


#: MuJoCo Menagerie's MJX G1 (29 DoF, rev 1.0): primitive colliders and the self pairs of its scene
#: (``diffkin/retarget/data/unitree_g1_mjx``, README there).
G1_MJX_SCENE = Path(__file__).resolve().parent / "data" / "unitree_g1_mjx" / "scene_mjx.xml"


def g1_collision(chain):
    """The self-collision model of the 29-DoF G1 for ``chain`` (an MJCF chain of Menagerie's current G1,
    e.g. ``models.from_mjcf(models.model_path("g1"), mapping.frames)``): the capsules, spheres and foot
    boxes of Menagerie's ``g1_mjx.xml`` and the 26 robot–robot ``<pair>``s of its ``scene_mjx.xml`` (legs
    against legs, hands against hips and thighs, the arms against the torso), placed by the chain's bodies.
    Its body tree must be that model's (same bodies, same order): :class:`~diffkin.errors.ModelError`
    otherwise. Pass it as ``retarget.clip(..., collision=)``."""
    import warnings

    from ..collision import RobotCollision
    from ..collision.mjcf import load_model

    if getattr(chain, "source_text", None) is None:
        raise ModelError(f"g1_collision needs an MJCF chain of the G1 (models.from_mjcf), got "
                         f"{type(chain).__name__}")
    with warnings.catch_warnings():  # the floor plane of the scene is not a robot geom: skipped
        warnings.simplefilter("ignore")
        scene = load_model(G1_MJX_SCENE)
        own = load_model(chain.source_path or chain.source_text)
    ours = [scene.body(b).name for b in range(scene.nbody)]
    theirs = [own.body(b).name for b in range(own.nbody)]
    if ours != theirs:
        raise ModelError(f"g1_collision: the chain's model has the bodies {theirs[1:4]}... ({len(theirs)}), "
                         f"not the 29-DoF G1's {ours[1:4]}... ({len(ours)})")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return RobotCollision.from_mjcf(scene, chain).requires_grad_(False)
