"""A conservative broad phase for decisions (private): cheap lower bounds of signed distances, and the exact
(expensive) distance evaluated only where the bound does not already prove the distance >= a threshold.

Bound. Every geom lies in a bounding sphere: a capsule a–b of radius r in the sphere at (a + b)/2 of radius
‖b − a‖/2 + r, a box (c, R, h) in the sphere at c of radius ‖h‖. The signed distance of two solids is at
least the signed distance of their bounding spheres, ‖c₁ − c₂‖ − ρ₁ − ρ₂: apart, the solids are at least
as far apart as the spheres; in contact, a translation that separates the spheres separates the solids, so
the solids' penetration depth is at most the spheres'. A capsule against a box also gets the box's three
face normals as separating axes (:func:`capsule_box_bound`): the gap along any axis is at most the signed
distance of two convex solids (their distance apart, minus the penetration depth in contact), and a flat
box (a table) is far tighter in its own frame than in its bounding sphere.

:func:`exact_below` gathers the entries whose bound is below ``threshold + pad`` (``pad`` absorbs the
rounding of the bound: √eps of the dtype times the scale), evaluates the exact distance on them only, and
scatters it back; every other entry keeps its bound, which is then ≥ threshold and ≤ the exact distance.
So the result equals the exact distance wherever either is below the threshold, and decisions
``d >= threshold`` (every distance above a margin) are those of the exact distances. The gather is one
``nonzero`` (a host sync on CUDA): a decision path, not a training path.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from .._numerics import safe_norm, safe_sqrt
from .distances import capsule_pairs_cm

__all__ = ["capsule_spheres", "box_spheres", "sphere_bound", "capsule_box_bound", "capsule_pairs_at_least",
           "exact_below", "group_tables", "pairs_clear"]


def capsule_spheres(a: Tensor, b: Tensor, r: Tensor) -> tuple[Tensor, Tensor]:
    """Bounding spheres of capsules ``a, b (..., 3)``, ``r (...)``: centres ``(..., 3)``, radii ``(...)``."""
    return 0.5 * (a + b), 0.5 * safe_norm(b - a) + r


def box_spheres(c: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
    """Bounding spheres of boxes (centres ``c (..., 3)``, half extents ``h (..., 3)``)."""
    return c, safe_norm(h)


def sphere_bound(c1: Tensor, r1: Tensor, c2: Tensor, r2: Tensor) -> Tensor:
    """‖c₁ − c₂‖ − r₁ − r₂ (broadcast): a lower bound of the signed distance of the enclosed solids."""
    return safe_norm(c1 - c2) - r1 - r2


def capsule_box_bound(a: Tensor, b: Tensor, r: Tensor, c: Tensor, R: Tensor, h: Tensor) -> Tensor:
    """A lower bound of :func:`~diffkin.collision.boxes.capsule_box` (broadcast, ``(...)``): the larger of
    the bounding-sphere bound and the separating-axis gaps along the box's face normals R e_k,
    |u_k| − |e_k| − h_k − r with u = Rᵀ (m − c), e = Rᵀ (b − a)/2 (m the segment's midpoint)."""
    m, rho = capsule_spheres(a, b, r)
    local = lambda v: (v.unsqueeze(-1) * R).sum(-2)  # noqa: E731  Rᵀ v
    gaps = local(m - c).abs() - local(0.5 * (b - a)).abs() - h
    return torch.maximum(sphere_bound(m, rho, c, safe_norm(h)), gaps.amax(-1) - r)


def _sqrt(x: Tensor) -> Tensor:
    """√x of the bounds in the decisions (no gradient there, so not :func:`~diffkin._numerics.safe_sqrt`,
    whose zero gradient at 0 costs three more passes)."""
    return x.sqrt()


def _pad(bound: Tensor, threshold: float) -> float:
    """Room for the rounding of the bound (√eps times the scale of the coordinates, 10 m assumed)."""
    return torch.finfo(bound.dtype).eps ** 0.5 * (10.0 + abs(threshold))


def exact_below(bound: Tensor, threshold: float, fn: Callable[..., Tensor],
                *args: tuple[Tensor, int]) -> Tensor:
    """``bound (...)`` with the entries below ``threshold`` (+ the rounding pad) replaced by
    ``fn(*gathered)``: each arg is ``(tensor, k)``, a tensor whose leading dims broadcast to
    ``bound.shape`` and whose last k dims are its own (``(..., 3)``: k = 1, ``(..., 3, 3)``: k = 2).
    ``fn`` maps flat ``(E, *own)`` arguments to ``(E,)``. Differentiable in both branches."""
    if bound.numel() == 0:
        return bound
    need = bound.detach() < threshold + _pad(bound, threshold)
    idx = need.nonzero(as_tuple=True)
    if idx[0].numel() == 0:
        return bound
    gathered = [x.expand(*bound.shape, *x.shape[x.ndim - k:])[idx] for x, k in args]
    return bound.index_put(idx, fn(*gathered))


def capsule_pairs_at_least(A: Tensor, D: Tensor, R: Tensor, i: Tensor, j: Tensor,
                           threshold: float | None) -> Tensor:
    """:func:`~diffkin.collision.distances.capsule_pairs_cm` (``A, D (G, 3, N)``, ``R (G, N)`` or ``(G,
    1)`` → ``(P, N)``) through the broad phase: the midpoint-sphere bound of every pair, the exact capsule
    distance of the (pair, row) entries below ``threshold`` only (``None``: exact everywhere)."""
    if threshold is None:
        return capsule_pairs_cm(A, D, R, i, j)
    M = torch.addcmul(A, D, D.new_tensor(0.5))
    rho = torch.addcmul(R, safe_sqrt((D * D).sum(1)), R.new_tensor(0.5))  # (G, N)
    v = M.index_select(0, i) - M.index_select(0, j)
    bound = safe_sqrt((v * v).sum(1)) - rho.index_select(0, i) - rho.index_select(0, j)
    need = bound.detach() < threshold + _pad(bound, threshold)
    p, n = need.nonzero(as_tuple=True)
    if p.numel() == 0:
        return bound
    return bound.index_put((p, n), _exact_entries(A, D, R, i[p], j[p], n))


def _exact_entries(A: Tensor, D: Tensor, R: Tensor, ip: Tensor, jp: Tensor, n: Tensor) -> Tensor:
    """The exact distances ``(E,)`` of the entries (capsule ip[e], capsule jp[e], row n[e]): the pair kernel
    on the gathered entries (two "geoms" of E rows), bit for bit :func:`capsule_pairs_cm`'s values."""
    Rn = R.expand(-1, A.shape[-1])
    pick = lambda X: torch.stack((X[ip, :, n], X[jp, :, n])).transpose(1, 2)  # noqa: E731  (2, 3, E)
    two = torch.arange(2, device=A.device)
    return capsule_pairs_cm(pick(A), pick(D), torch.stack((Rn[ip, n], Rn[jp, n])), two[:1], two[1:])[0]


# ------------------------------------------------------------------ decisions only (component-major layout)
def pairs_clear(A: Tensor, D: Tensor, R: Tensor, i: Tensor, j: Tensor, margin: float, slack: float,
                groups: tuple[Tensor, ...]) -> Tensor:
    """Whether every pair (i[p], j[p]) of G capsules (``A, D (G, 3, N)`` as in :func:`capsule_pairs_at_least`,
    ``R (G, 1)``) has d − margin >= slack, ``(N,)``, in three stages, each on the entries the one before
    leaves:

    1. per pair of capsule groups and row (:func:`group_tables`: capsules of one rigid body), the bound of
       two spheres that hold the groups (centred at the mean of a group's capsule midpoints, the radius its
       farthest bounding sphere: the capsules of a rigid group keep their distances, so the sphere holds
       them in every configuration);
    2. per pair and row, the bounding-sphere bound of the two capsules;
    3. the exact distance.

    ``groups``: the tables of :func:`group_tables`."""
    gb, bp, table, mean, members = groups
    thr, (G, N) = margin + slack, A.shape[::2]
    M = torch.addcmul(A, D, D.new_tensor(0.5))  # the capsules' bounding spheres (G, 3, N), (G, N)
    rho = torch.addcmul(R, _sqrt((D * D).sum(1)), R.new_tensor(0.5))
    ok = torch.ones(N, dtype=torch.bool, device=A.device)
    # (a product and a gather, not index_add_ / scatter_reduce_: those take ~0.1 s on two CPU threads)
    C = (mean @ M.reshape(G, -1)).reshape(mean.shape[0], 3, N)  # the groups' centres (B, 3, N)
    e = M - C.index_select(0, gb)
    far = torch.cat((_sqrt((e * e).sum(1)) + rho, rho.new_full((1, N), -math.inf)))  # (G + 1, N)
    rb = far.index_select(0, members.flatten()).reshape(*members.shape, N).amax(1)  # the radii (B, N)
    v = C.index_select(0, bp[:, 0]) - C.index_select(0, bp[:, 1])
    bound = _sqrt((v * v).sum(1)) - rb.index_select(0, bp[:, 0]) - rb.index_select(0, bp[:, 1])
    qq, n = (bound < thr + _pad(bound, thr)).nonzero(as_tuple=True)  # (Q, N) -> E entries
    if n.numel() == 0:
        return ok
    # stage 2 on the flat (capsule, row) index c N + n; a padded slot pairs capsule 0 with a point at
    # infinity (row G), whose bound is +inf
    fi, fj = (((table[k] * N).index_select(0, qq) + n[:, None]).flatten() for k in (0, 1))
    Mf = torch.cat((M.transpose(0, 1), M.new_full((3, 1, N), math.inf)), 1).reshape(3, -1)
    rf = torch.cat((rho, rho.new_zeros(1, N))).reshape(-1)
    v = Mf.index_select(1, fi) - Mf.index_select(1, fj)
    bound = _sqrt((v * v).sum(0)) - rf.index_select(0, fi) - rf.index_select(0, fj)
    keep = (bound < thr + _pad(bound, thr)).nonzero().squeeze(-1)
    if keep.numel() == 0:
        return ok
    fi, fj = fi[keep], fj[keep]
    n = fi % N
    d = _exact_entries(A, D, R, fi // N, fj // N, n)
    return ok.index_fill_(0, n[(d - margin) < slack], False)


def group_tables(body: list[int], pairs: list[tuple[int, int]], dtype, device,
                 size: int = 3) -> tuple[Tensor, ...]:
    """The groups of :func:`pairs_clear` for G capsules on rigid bodies ``body`` (G ints) and their checked
    ``pairs`` (P index pairs): runs of at most ``size`` consecutive capsules of one body (any split of a
    rigid body is valid; smaller groups have tighter spheres but more pairs: 3 halves the cost on the FR3,
    whose links hold a cylinder and its two end spheres, or two of those). Returns (each capsule's group
    ``(G,)`` in 0 … B − 1, the group pairs ``(Q, 2)``, each group pair's capsule pairs as two tables of
    capsule indices ``(2, Q, S)`` (padded with 0 and G), the averaging matrix ``(B, G)`` of each group's
    capsules, their indices ``(B, K)`` (padded with G))."""
    seen: dict[int, int] = {}
    runs = []
    for b in body:
        seen[b] = seen.get(b, -1) + 1
        runs.append((b, seen[b] // size))
    ids = {g: k for k, g in enumerate(dict.fromkeys(runs))}
    gb, G, B = [ids[g] for g in runs], len(body), len(ids)
    members: dict[tuple[int, int], list[int]] = {}
    for p, (a, b) in enumerate(pairs):
        members.setdefault(tuple(sorted((gb[a], gb[b]))), []).append(p)
    S = max((len(v) for v in members.values()), default=0)
    table = [[[pairs[p][k] for p in v] + [k * G] * (S - len(v)) for v in members.values()] for k in (0, 1)]
    of = [[g for g in range(G) if gb[g] == b] for b in range(B)]
    K = max((len(v) for v in of), default=0)
    mean = torch.zeros(B, G, dtype=dtype, device=device)
    for b, v in enumerate(of):
        mean[b, v] = 1.0 / len(v)
    ilong = lambda x: torch.tensor(x, dtype=torch.long, device=device)  # noqa: E731
    Q = len(members)
    return (ilong(gb), ilong(list(members)).reshape(Q, 2), ilong(table).reshape(2, Q, S), mean,
            ilong([v + [G] * (K - len(v)) for v in of]).reshape(B, K))
