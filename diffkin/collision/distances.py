"""Signed distances between spheres, capsules, points and half-spaces in closed form.

Every function broadcasts over leading dimensions, follows its inputs' dtype and device and returns the
signed distance in the inputs' length unit: positive = the gap, negative = the penetration depth (the
smallest translation that separates the two solids). A sphere is a capsule whose two end points coincide;
a point is a sphere of radius 0.

Gradients. The closest-point parameters (s, t) of two segments minimise ‖p(s) − q(t)‖ over [0, 1]²; they
are found without gradient and attached to the geometry by :func:`envelope`: their values stay those
found, their derivatives are those of the same minimisers rebuilt as smooth functions on their active set
(an interior parameter solves its normal equation, a clamped one is constant). The first derivative of
the distance does not need them (the envelope theorem: they multiply a zero partial derivative at an
interior minimum; the pair kernel :class:`_PairKernel` skips them in a closed-form first-order backward
pass), but the second does (d²D = D_θθ + D_θt t_θ + ...): Hessians, gradgradcheck and the KKT systems
built on them are exact wherever the distance is twice differentiable. Finite everywhere: at parallel and
coincident axes (any minimiser gives a valid one-sided gradient; near-parallel pairs keep the parameter
held), at degenerate (zero length) segments and at coincident centres, where
:func:`~diffkin._numerics.safe_norm` gives a zero gradient instead of 0/0.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .._numerics import broadcast_shapes, safe_norm, safe_sqrt

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


def envelope(values: tuple[Tensor, ...], smooth: tuple[Tensor, ...]) -> tuple[Tensor, ...]:
    """Minimisers of an inner problem: their values ``values`` (found without gradient), their derivatives
    those of ``smooth``, the same minimisers rebuilt as differentiable functions on their active set
    (clamped entries constant). Only the derivatives are taken from ``smooth``, so the values do not move
    by its rounding.

    First-order gradients of an outer function evaluated at them are unchanged by the parameters' term (the
    envelope theorem: it multiplies a zero partial derivative), but second derivatives need it.
    """
    return tuple(v + (m - m.detach()) if m.requires_grad else v for v, m in zip(values, smooth))


def _interior(x: Tensor) -> Tensor:
    """Entries of a clamped parameter strictly inside (0, 1)."""
    return (x > 0) & (x < 1)


def _floor(x: Tensor) -> float:
    """The smallest denominator a differentiated parameter may have (tiny^¼: its derivatives stay finite)."""
    return torch.finfo(x.dtype).tiny ** 0.25


def _smooth_t(p: Tensor, a: Tensor, b: Tensor, t: Tensor) -> Tensor:
    """t of :func:`point_segment_parameter` as a function of p, a, b where it is interior (else ``t``)."""
    d = b - a
    dd = _dot(d, d)
    ok = _interior(t) & (dd.detach() > _floor(dd))
    return torch.where(ok, _dot(p - a, d) / torch.where(ok, dd, torch.ones_like(dd)), t)


def _smooth_st(a: Tensor, e: Tensor, b: Tensor, c: Tensor, f: Tensor, s: Tensor,
               t: Tensor) -> tuple[Tensor, Tensor]:
    """(s, t) of :func:`_closest_from_dots` (detached ``s``, ``t``) as functions of the dot products on their
    active set: both interior, the 2 × 2 normal equations (unless the axes are near parallel, where the
    minimiser is not a smooth function); one interior, its projection for the other held."""
    one = torch.ones_like(a)
    den = a * e - b * b
    si, ti = _interior(s), _interior(t)
    both = si & ti & (den.detach() > torch.finfo(a.dtype).eps ** 0.5 * (a * e).detach())
    only_s = si & ~both & (a.detach() > _floor(a))
    only_t = ti & ~both & (e.detach() > _floor(e))
    den = torch.where(both, den, one)
    s_new = torch.where(both, (b * f - c * e) / den,
                        torch.where(only_s, (b * t - c) / torch.where(only_s, a, one), s))
    t_new = torch.where(both, (a * f - b * c) / den,
                        torch.where(only_t, (b * s + f) / torch.where(only_t, e, one), t))
    return s_new, t_new


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
    return _closest_from_dots(*_dots(a0, a1, b0, b1))


def _dots(a0: Tensor, a1: Tensor, b0: Tensor, b1: Tensor) -> tuple[Tensor, ...]:
    """The dot products of :func:`_closest_from_dots` of two segments."""
    d1, d2, r = a1 - a0, b1 - b0, a0 - b0
    return _dot(d1, d1), _dot(d2, d2), _dot(d1, d2), _dot(d1, r), _dot(d2, r)


def capsule_capsule_pairs(a: Tensor, b: Tensor, r: Tensor, i: Tensor, j: Tensor, pair_kernel=None) -> Tensor:
    """:func:`capsule_capsule` of the pairs (i[p], j[p]) of one set of G capsules: ``a, b (..., G, 3)``,
    ``r (G,)`` or ``(..., G)``, index tensors ``(P,)`` → ``(..., P)``; ``pair_kernel``: another kernel of
    :func:`capsule_pairs_cm`'s signature (the broad phase)."""
    batch = broadcast_shapes(a.shape[:-2], b.shape[:-2], r.shape[:-1])
    cm = lambda x: x.expand(*batch, *x.shape[-2:]).reshape(-1, *x.shape[-2:]).permute(1, 2, 0)  # noqa: E731
    A = cm(a).contiguous()
    R = r.expand(*batch, r.shape[-1]).reshape(-1, r.shape[-1]).T
    return (pair_kernel or capsule_pairs_cm)(A, cm(b) - A, R, i, j).T.reshape(*batch, len(i))


def capsule_pairs_cm(A: Tensor, D: Tensor, R: Tensor, i: Tensor, j: Tensor) -> Tensor:
    """The pair kernel in a component-major layout: end points ``A (G, 3, N)``, axes ``D = B − A (G, 3, N)``
    and radii ``R (G, N)`` (or ``(G, 1)``) of G capsules in N rows → ``(P, N)`` for the pairs (i[p], j[p]).

    The geoms sit on the leading axis so that gathering the pairs copies contiguous rows and every per-pair
    operation runs on contiguous ``(P, N)`` planes; the squared lengths are computed once per geom. With
    gradients it runs as :class:`_PairKernel` (the first-order backward pass in closed form; a
    ``create_graph`` pass through :func:`_pairs_graph`, exact second derivatives).
    """
    if torch._C._are_functorch_transforms_active():  # vmap / jacrev / grad: the graph version, which they
        # trace (an autograd.Function without setup_context cannot run under them)
        _, s0, t0, _ = _pairs_values(A.detach(), D.detach(), R.detach(), i, j)
        return _pairs_graph(A, D, R, i, j, s0, t0)
    if torch.is_grad_enabled() and (A.requires_grad or D.requires_grad or R.requires_grad):
        return _PairKernel.apply(A, D, R, i, j)
    return _pairs_values(A, D, R, i, j)[0]


def _pairs_values(A: Tensor, D: Tensor, R: Tensor, i: Tensor, j: Tensor):
    """(distances ``(P, N)``, s, t, v ``(P, 3, N)``) of :func:`capsule_pairs_cm`, without gradient."""
    with torch.no_grad():
        a0, d1 = A.index_select(0, i), D.index_select(0, i)
        b0, d2 = A.index_select(0, j), D.index_select(0, j)
        rel = a0 - b0
        dd = (D * D).sum(1)  # (G, N)
        s, t = _closest_from_dots(dd.index_select(0, i), dd.index_select(0, j), (d1 * d2).sum(1),
                                  (d1 * rel).sum(1), (d2 * rel).sum(1))
        v = torch.addcmul(torch.addcmul(rel, s.unsqueeze(1), d1), t.unsqueeze(1), d2, value=-1.0)
        return safe_sqrt((v * v).sum(1)) - R.index_select(0, i) - R.index_select(0, j), s, t, v


def _pairs_graph(A: Tensor, D: Tensor, R: Tensor, i: Tensor, j: Tensor, s0: Tensor, t0: Tensor) -> Tensor:
    """:func:`capsule_pairs_cm` as a differentiable function, (s, t) through :func:`envelope`."""
    a0, d1, b0, d2 = A.index_select(0, i), D.index_select(0, i), A.index_select(0, j), D.index_select(0, j)
    rel = a0 - b0
    dd = (D * D).sum(1)  # (G, N)
    dots = (dd.index_select(0, i), dd.index_select(0, j), (d1 * d2).sum(1), (d1 * rel).sum(1),
            (d2 * rel).sum(1))
    s, t = envelope((s0, t0), _smooth_st(*dots, s0, t0))
    v = torch.addcmul(torch.addcmul(rel, s.unsqueeze(1), d1), t.unsqueeze(1), d2, value=-1.0)
    return safe_sqrt((v * v).sum(1)) - R.index_select(0, i) - R.index_select(0, j)


class _PairKernel(torch.autograd.Function):
    """:func:`capsule_pairs_cm` with its first-order backward pass in closed form: with n = v / ‖v‖ (0 where
    v = 0, as :func:`~diffkin._numerics.safe_sqrt`), ∂d/∂a0 = n, ∂d/∂b0 = −n, ∂d/∂d1 = s n, ∂d/∂d2 = −t n,
    ∂d/∂r = −1 (s, t held: the envelope theorem). Under ``create_graph`` the backward pass differentiates
    :func:`_pairs_graph` instead, so that second derivatives are exact."""

    @staticmethod
    def forward(ctx, A, D, R, i, j):
        d, s, t, v = _pairs_values(A, D, R, i, j)
        ctx.save_for_backward(A, D, R, i, j, s, t, v)
        return d

    @staticmethod
    def backward(ctx, g):
        A, D, R, i, j, s, t, v = ctx.saved_tensors
        if torch.is_grad_enabled():  # create_graph: differentiate the graph version
            # fresh views: D may be a function of A (D = B − A), and each input takes its partial derivative
            # only
            A, D, R = (x.view_as(x) for x in (A, D, R))
            want = [x for x in (A, D, R) if x.requires_grad]
            got = iter(torch.autograd.grad(_pairs_graph(A, D, R, i, j, s, t), want, g, create_graph=True,
                                           allow_unused=True))
            out = [next(got) if x.requires_grad else None for x in (A, D, R)]
            return (*out, None, None)
        nv = safe_sqrt((v * v).sum(1, keepdim=True))
        gn = v * (g.unsqueeze(1) / torch.where(nv > 0, nv, torch.ones_like(nv)))  # (P, 3, N)
        gn = torch.where(nv > 0, gn, torch.zeros_like(gn))
        gA = gD = gR = None  # out-of-place index_add: the backward pass may run under vmap
        if ctx.needs_input_grad[0]:
            gA = torch.zeros_like(A).index_add(0, i, gn).index_add(0, j, gn, alpha=-1.0)
        if ctx.needs_input_grad[1]:
            gD = torch.zeros_like(D).index_add(0, i, gn * s.unsqueeze(1)).index_add(
                0, j, gn * t.unsqueeze(1), alpha=-1.0)
        if ctx.needs_input_grad[2]:
            gR = torch.zeros(R.shape[0], g.shape[1], dtype=g.dtype, device=g.device).index_add(
                0, i, g, alpha=-1.0).index_add(0, j, g, alpha=-1.0).sum_to_size(R.shape)
        return gA, gD, gR, None, None


def sphere_sphere(ca: Tensor, ra: Tensor, cb: Tensor, rb: Tensor) -> Tensor:
    """‖ca − cb‖ − ra − rb: centres ``(..., 3)``, radii ``(...)`` → ``(...)``."""
    return safe_norm(ca - cb) - ra - rb


def sphere_capsule(c: Tensor, r: Tensor, b0: Tensor, b1: Tensor, rb: Tensor) -> Tensor:
    """Sphere (c, r) to the capsule with axis b0–b1 and radius rb: ``(..., 3)``, ``(...)`` → ``(...)``."""
    t0 = point_segment_parameter(c, b0, b1)
    t = _smooth_t(c, b0, b1, t0) if torch.is_grad_enabled() else t0
    (t,) = envelope((t0,), (t,))
    return safe_norm(c - (b0 + t.unsqueeze(-1) * (b1 - b0))) - r - rb


def capsule_capsule(a0: Tensor, a1: Tensor, ra: Tensor, b0: Tensor, b1: Tensor, rb: Tensor) -> Tensor:
    """Capsule (a0–a1, ra) to capsule (b0–b1, rb): the distance of the axes minus both radii.

    End points ``(..., 3)``, radii ``(...)`` → ``(...)``. Exact, penetration included: two segments that
    touch can always be separated by an arbitrarily small move, so the penetration depth of the capsules
    is ra + rb − ‖p − q‖.
    """
    dots = _dots(a0, a1, b0, b1)
    with torch.no_grad():
        s0, t0 = _closest_from_dots(*dots)
    s, t = envelope((s0, t0), _smooth_st(*dots, s0, t0)) if dots[0].requires_grad else (s0, t0)
    p = a0 + s.unsqueeze(-1) * (a1 - a0)
    q = b0 + t.unsqueeze(-1) * (b1 - b0)
    return safe_norm(p - q) - ra - rb


def sphere_halfspace(c: Tensor, r: Tensor, n: Tensor, offset: Tensor) -> Tensor:
    """Sphere to the half-space {x : n·x ≤ offset} (n unit): n·c − offset − r, ``(..., 3)`` → ``(...)``."""
    return _dot(n, c) - offset - r


def capsule_halfspace(a0: Tensor, a1: Tensor, r: Tensor, n: Tensor, offset: Tensor) -> Tensor:
    """Capsule to the half-space {x : n·x ≤ offset}: min(n·a0, n·a1) − offset − r, ``(...)``."""
    return torch.minimum(_dot(n, a0), _dot(n, a1)) - offset - r
