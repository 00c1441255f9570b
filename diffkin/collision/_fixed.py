"""Which distances no joint motion can change (private): left out of IK's and the sampler's checks.

A geom is *fixed* when its anchor frame is placed independently of q (a link welded to the base; a MuJoCo
body welded to the world): every distance of it to the world, and to another fixed geom, is a constant.

A geom moved only by rotations about axes parallel to a half-space's normal n and translations
perpendicular to n (an arm's first link turning about the vertical above a floor) keeps its distance to
that half-space: such motions form the planar group of the plane ⊥ n, which preserves n·x of every point.
The test is exact, from the joint screws at one configuration q₀: the derivative of the anchor pose F_k
in q_i gives the spatial angular velocity ω = Ṙ Rᵀ and the origin velocity ṗ; the body's points x move
with n·ẋ = n·ṗ + n·(ω × (x − p)), zero for every x iff ω × n = 0 and n·ṗ = 0. If every column passes,
each joint screw lies in the planar group's Lie algebra and so does the product of their exponentials at
every q (the adjoint of the group preserves its algebra). Quaternion (ball, free) joints fail the test,
so they are always checked; a mimic coordinate driving two screws is tested on their sum.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__: list[str] = []


def planar_frames(frames, chain, n: Tensor) -> Tensor:
    """``(K, H)`` bool: anchor frame k's placement keeps n·x for every half-space normal ``n (H, 3)``
    (static anchors trivially do). ``frames``: the model's frame provider (``frames(chain, q) -> (..., K,
    4, 4)``), differentiated at one fixed configuration; tolerance 64 eps of the dtype (times the scale)."""
    q0 = chain.random_configuration((), generator=torch.Generator().manual_seed(0)).detach()
    with torch.enable_grad():
        dF = torch.autograd.functional.jacobian(lambda q: frames.frames(chain, q), q0)  # (K, 4, 4, nq)
    F = frames.frames(chain, q0).detach()
    R, p = F[:, :3, :3], F[:, :3, 3]
    W = dF[:, :3, :3].movedim(-1, 1) @ R.transpose(-1, -2).unsqueeze(1)  # (K, nq, 3, 3): ω^ = Ṙ Rᵀ
    w = torch.stack((W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]), -1)  # (K, nq, 3)
    pdot = dF[:, :3, 3].movedim(-1, 1)  # (K, nq, 3)
    scale = 1.0 + p.abs().amax()
    tol = 64 * torch.finfo(F.dtype).eps * scale
    K, nq, H = w.shape[0], w.shape[1], n.shape[0]
    cross = torch.linalg.cross(w.unsqueeze(2).expand(K, nq, H, 3), n.expand(K, nq, H, 3), dim=-1)
    ok = (cross.norm(dim=-1) <= tol) & ((pdot @ n.T).abs() <= tol)  # (K, nq, H)
    return ok.all(1)


def kept_columns(rc, world, moving_only: bool) -> tuple[Tensor | None, Tensor | None]:
    """The columns of ``rc._distances_at_least`` kept with ``moving_only`` (None: all): the self pairs but
    those of two fixed geoms; the (geom, object) entries, geom-major, but those of a fixed geom and those of
    a geom against a half-space its joints cannot move it towards (:func:`planar_frames`; one world for all
    rows). Remembered on ``rc`` per world half-spaces and chain state (tensor identity and version)."""
    if not moving_only:
        return None, None
    keep_self = rc._moving_pairs if len(rc._moving_pairs) < len(rc.pairs) else None
    if world is None:
        return keep_self, None
    chain = rc.chain
    ts = [*chain.parameters(), *chain.buffers()] if isinstance(chain, torch.nn.Module) else []
    key = [(t, t._version) for t in (world.halfspaces, *ts)]
    memo = rc.__dict__.get("_kept_memo")
    if memo is not None and len(memo[0]) == len(key) and memo[1] == (world.counts, len(world)) and all(
            a is b and u == v for (a, u), (b, v) in zip(memo[0], key)):
        return keep_self, memo[2]
    G, (s, c, b, h, *_) = len(rc.geoms), world.counts
    drop = torch.tensor(rc.fixed, dtype=torch.bool, device="cpu").reshape(G, 1).expand(G, len(world)).clone()
    if h and world.halfspaces.ndim == 2 and chain is not None:
        planar = planar_frames(rc._frames, chain, world.halfspaces[:, :3].detach()).cpu()
        drop[:, s + c + b: s + c + b + h] |= planar[torch.tensor(rc._anchor, device="cpu")]
    keep = (~drop).flatten().nonzero().flatten().to(rc._moving_pairs.device)
    keep = None if len(keep) == drop.numel() else keep
    rc.__dict__["_kept_memo"] = (key, (world.counts, len(world)), keep)
    return keep_self, keep


def distance_names(rc, world, moving_only: bool) -> list[str]:
    """A name per column of ``rc._distances_at_least`` (same arguments): ``"a × b"`` for a self pair,
    ``"geom × world <kind> k"`` for a geom against the world's k-th object of that kind."""
    keep_self, keep_world = kept_columns(rc, world, moving_only)
    names = [f"{a} × {b}" for a, b in rc.pairs]
    names = names if keep_self is None else [names[i] for i in keep_self.tolist()]
    if world is None:
        return names
    kinds = ("sphere", "capsule", "box", "halfspace", "point", "cylinder")
    counts = (*world.counts, *world.object_counts)
    objs = [f"world {kind} {k}" for kind, n in zip((*kinds, *world.objects), counts) for k in range(n)]
    rows = [f"{g.name} × {o}" for g in rc.geoms for o in objs]
    return names + (rows if keep_world is None else [rows[i] for i in keep_world.tolist()])
