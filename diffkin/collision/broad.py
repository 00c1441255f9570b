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

from collections.abc import Callable

import torch
from torch import Tensor

from .._numerics import safe_norm, safe_sqrt
from .distances import capsule_pairs_cm

__all__ = ["capsule_spheres", "box_spheres", "sphere_bound", "capsule_box_bound", "capsule_pairs_at_least",
           "exact_below"]


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
    # the same kernel on the gathered entries (two "geoms" of E rows): bit for bit the exact distances
    Rn, ip, jp = R.expand(-1, A.shape[-1]), i[p], j[p]
    pick = lambda X: torch.stack((X[ip, :, n], X[jp, :, n])).transpose(1, 2)  # noqa: E731  (2, 3, E)
    two = torch.arange(2, device=A.device)
    d = capsule_pairs_cm(pick(A), pick(D), torch.stack((Rn[ip, n], Rn[jp, n])), two[:1], two[1:])[0]
    return bound.index_put((p, n), d)
