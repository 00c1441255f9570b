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

from .._numerics import eps_for, safe_norm

__all__ = [
    "segment_closest_parameters",
    "point_segment_parameter",
    "sphere_sphere",
    "sphere_capsule",
    "capsule_capsule",
    "sphere_halfspace",
    "capsule_halfspace",
]


def _dot(a: Tensor, b: Tensor) -> Tensor:
    return (a * b).sum(-1)


def _safe_div(num: Tensor, den: Tensor, ok: Tensor) -> Tensor:
    """``num / den`` where ``ok``, else 0 (double where: no inf or NaN on the unused branch)."""
    return torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(num))


@torch.no_grad()
def point_segment_parameter(p: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """The parameter t ∈ [0, 1] of the point of segment a + t (b − a) closest to p: ``(..., 3)`` → ``(...)``.

    t = clamp((p − a)·d / d·d, 0, 1) with d = b − a; t = 0 for a degenerate segment (d = 0). Detached.
    """
    d = b - a
    dd = _dot(d, d)
    ok = dd > eps_for(dd) * (1.0 + _dot(a, a) + _dot(b, b))
    return _safe_div(_dot(p - a, d), dd, ok).clamp(0.0, 1.0)


@torch.no_grad()
def segment_closest_parameters(a0: Tensor, a1: Tensor, b0: Tensor, b1: Tensor) -> tuple[Tensor, Tensor]:
    """Parameters (s, t) ∈ [0, 1]² of the closest points a0 + s (a1 − a0), b0 + t (b1 − b0) of two segments.

    ``(..., 3)`` each → ``(...)``, ``(...)``, detached. The clamped solution of the 2 × 2 normal equations
    (Ericson, *Real-Time Collision Detection*, § 5.1.9): s from the unclamped line–line solution clamped to
    [0, 1] (s = 0 where the axes are parallel, denominator a c − b² ≈ 0), then t for that s clamped, then s
    again for the clamped t. Degenerate segments (zero length) are handled as points.
    """
    d1, d2, r = a1 - a0, b1 - b0, a0 - b0
    a, e = _dot(d1, d1), _dot(d2, d2)
    b, c, f = _dot(d1, d2), _dot(d1, r), _dot(d2, r)
    scale = 1.0 + _dot(a0, a0) + _dot(b0, b0) + a + e
    tiny = eps_for(a) * scale
    ok_a, ok_e = a > tiny, e > tiny
    denom = a * e - b * b
    ok_d = denom > eps_for(a) * a * e * 16.0 + tiny * tiny
    s = _safe_div(b * f - c * e, denom, ok_d & ok_a & ok_e).clamp(0.0, 1.0)
    t = _safe_div(b * s + f, e, ok_e).clamp(0.0, 1.0)
    s = _safe_div(b * t - c, a, ok_a).clamp(0.0, 1.0)
    return s, t


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
