"""Signed distances between spheres, capsules, points and half-spaces in closed form.

Every function broadcasts over leading dimensions, follows its inputs' dtype and device and returns the
signed distance in the inputs' length unit: positive = the gap, negative = the penetration depth (the
smallest translation that separates the two solids). A sphere is a capsule whose two end points coincide;
a point is a sphere of radius 0.

Gradients. The closest-point parameters (s, t) of two segments minimise ‖p(s) − q(t)‖ over [0, 1]²; the
distance is evaluated at those parameters *held constant* (detached). By the envelope theorem this is the
exact gradient of the minimum wherever it is differentiable (the parameters' own derivatives multiply a
zero partial derivative at an interior minimum and are zero where clamped), and it is finite everywhere:
at parallel and coincident axes (any minimiser gives a valid one-sided gradient), at degenerate (zero
length) segments and at coincident centres, where :func:`~diffkin._numerics.safe_norm` gives a zero
gradient instead of 0/0.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .._numerics import safe_norm, safe_sqrt

__all__ = [
    "segment_closest_parameters",
    "point_segment_parameter",
    "sphere_sphere",
    "sphere_capsule",
    "capsule_capsule",
    "capsule_capsule_pairs",
    "sphere_halfspace",
    "capsule_halfspace",
]


def _dot(a: Tensor, b: Tensor) -> Tensor:
    return (a * b).sum(-1)


@torch.no_grad()
def point_segment_parameter(p: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """The parameter t ∈ [0, 1] of the point of segment a + t (b − a) closest to p: ``(..., 3)`` → ``(...)``.

    t = clamp((p − a)·d / d·d, 0, 1) with d = b − a; t = 0 for a degenerate segment (d = 0: the numerator
    vanishes exactly and the denominator is floored at the dtype's smallest normal number). Detached.
    """
    d = b - a
    return (_dot(p - a, d) / _dot(d, d).clamp_min(torch.finfo(d.dtype).tiny)).clamp(0.0, 1.0)


def _closest_from_dots(a: Tensor, e: Tensor, b: Tensor, c: Tensor, f: Tensor) -> tuple[Tensor, Tensor]:
    """(s, t) from a = d1·d1, e = d2·d2, b = d1·d2, c = d1·r, f = d2·r (r = a0 − b0).

    Ericson's clamped solution without branches: s from the line–line solution, t for that s, s again for
    the clamped t, each clamped to [0, 1]. The denominators are floored at the dtype's smallest normal
    number instead of tested: where they vanish (a degenerate segment, d = 0) the numerators vanish exactly
    too, and for parallel axes (a e − b² ≈ 0) any first s is refined by the two projections into a pair of
    closest points, so no NaN or inf reaches the result.
    """
    tiny = torch.finfo(a.dtype).tiny
    s = ((b * f - c * e) / (a * e - b * b).clamp_min(tiny)).clamp(0.0, 1.0)
    t = (torch.addcmul(f, b, s) / e.clamp_min(tiny)).clamp(0.0, 1.0)
    s = (torch.addcmul(-c, b, t) / a.clamp_min(tiny)).clamp(0.0, 1.0)
    return s, t


@torch.no_grad()
def segment_closest_parameters(a0: Tensor, a1: Tensor, b0: Tensor, b1: Tensor) -> tuple[Tensor, Tensor]:
    """Parameters (s, t) ∈ [0, 1]² of the closest points a0 + s (a1 − a0), b0 + t (b1 − b0) of two segments.

    ``(..., 3)`` each → ``(...)``, ``(...)``, detached. The clamped solution of the 2 × 2 normal equations
    (Ericson, *Real-Time Collision Detection*, § 5.1.9); parallel axes and degenerate (zero-length)
    segments included.
    """
    d1, d2, r = a1 - a0, b1 - b0, a0 - b0
    return _closest_from_dots(_dot(d1, d1), _dot(d2, d2), _dot(d1, d2), _dot(d1, r), _dot(d2, r))


def capsule_capsule_pairs(a: Tensor, b: Tensor, r: Tensor, i: Tensor, j: Tensor, pair_kernel=None) -> Tensor:
    """:func:`capsule_capsule` of the pairs (i[p], j[p]) of one set of G capsules: ``a, b (..., G, 3)``,
    ``r (G,)`` or ``(..., G)``, index tensors ``(P,)`` → ``(..., P)``; ``pair_kernel``: another kernel of
    :func:`capsule_pairs_cm`'s signature (the broad phase)."""
    batch = torch.broadcast_shapes(a.shape[:-2], b.shape[:-2], r.shape[:-1])
    cm = lambda x: x.expand(*batch, *x.shape[-2:]).reshape(-1, *x.shape[-2:]).permute(1, 2, 0)  # noqa: E731
    A = cm(a).contiguous()
    R = r.expand(*batch, r.shape[-1]).reshape(-1, r.shape[-1]).T
    return (pair_kernel or capsule_pairs_cm)(A, cm(b) - A, R, i, j).T.reshape(*batch, len(i))


def capsule_pairs_cm(A: Tensor, D: Tensor, R: Tensor, i: Tensor, j: Tensor) -> Tensor:
    """The pair kernel in a component-major layout: end points ``A (G, 3, N)``, axes ``D = B − A (G, 3, N)``
    and radii ``R (G, N)`` (or ``(G, 1)``) of G capsules in N rows → ``(P, N)`` for the pairs (i[p], j[p]).

    The geoms sit on the leading axis so that gathering the pairs copies contiguous rows and every per-pair
    operation runs on contiguous ``(P, N)`` planes; the squared lengths are computed once per geom.
    """
    a0, d1, b0, d2 = A.index_select(0, i), D.index_select(0, i), A.index_select(0, j), D.index_select(0, j)
    rel = a0 - b0
    with torch.no_grad():
        dd = (D * D).sum(1)  # (G, N)
        s, t = _closest_from_dots(dd.index_select(0, i), dd.index_select(0, j), (d1 * d2).sum(1),
                                  (d1 * rel).sum(1), (d2 * rel).sum(1))
    v = torch.addcmul(torch.addcmul(rel, s.unsqueeze(1), d1), t.unsqueeze(1), d2, value=-1.0)
    return safe_sqrt((v * v).sum(1)) - R.index_select(0, i) - R.index_select(0, j)


def sphere_sphere(ca: Tensor, ra: Tensor, cb: Tensor, rb: Tensor) -> Tensor:
    """‖ca − cb‖ − ra − rb: centres ``(..., 3)``, radii ``(...)`` → ``(...)``."""
    return safe_norm(ca - cb) - ra - rb


def sphere_capsule(c: Tensor, r: Tensor, b0: Tensor, b1: Tensor, rb: Tensor) -> Tensor:
    """Sphere (c, r) to the capsule with axis b0–b1 and radius rb: ``(..., 3)``, ``(...)`` → ``(...)``."""
    t = point_segment_parameter(c, b0, b1).unsqueeze(-1)
    return safe_norm(c - (b0 + t * (b1 - b0))) - r - rb


def capsule_capsule(a0: Tensor, a1: Tensor, ra: Tensor, b0: Tensor, b1: Tensor, rb: Tensor) -> Tensor:
    """Capsule (a0–a1, ra) to capsule (b0–b1, rb): the distance of the axes minus both radii.

    End points ``(..., 3)``, radii ``(...)`` → ``(...)``. Exact, penetration included: two segments that
    touch can always be separated by an arbitrarily small move, so the penetration depth of the capsules
    is ra + rb − ‖p − q‖.
    """
    s, t = segment_closest_parameters(a0, a1, b0, b1)
    p = a0 + s.unsqueeze(-1) * (a1 - a0)
    q = b0 + t.unsqueeze(-1) * (b1 - b0)
    return safe_norm(p - q) - ra - rb


def sphere_halfspace(c: Tensor, r: Tensor, n: Tensor, offset: Tensor) -> Tensor:
    """Sphere to the half-space {x : n·x ≤ offset} (n unit): n·c − offset − r, ``(..., 3)`` → ``(...)``."""
    return _dot(n, c) - offset - r


def capsule_halfspace(a0: Tensor, a1: Tensor, r: Tensor, n: Tensor, offset: Tensor) -> Tensor:
    """Capsule to the half-space {x : n·x ≤ offset}: min(n·a0, n·a1) − offset − r, ``(...)``."""
    return torch.minimum(_dot(n, a0), _dot(n, a1)) - offset - r
