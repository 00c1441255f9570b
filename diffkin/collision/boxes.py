"""Oriented boxes: the :func:`box` constructor and signed distances of points, segments (spheres,
capsules), half-spaces and other boxes to them.

A box is ``(center (..., 3), R (..., 3, 3), half_extents (..., 3))``: the points c + R u with
|u_k| ≤ h_k. Conventions and gradients as in :mod:`diffkin.collision.distances`.

Methods (all exact up to the stated tolerance):

* point–box: the closed-form signed distance field (outside: the norm of the excess over the half extents;
  inside: minus the distance to the nearest face).
* segment–box (capsules, spheres): apart, the distance is min over t ∈ [0, 1] of the box's distance field
  at a + t (b − a); its square is a convex piecewise quadratic in t with at most six knots, minimised in
  closed form (the stationary point of each piece, clamped to it), then evaluated at that minimiser, found
  without gradient and differentiated as the stationary point of its piece
  (:func:`~diffkin.collision.distances.envelope`: exact first and second derivatives). In contact, the
  penetration depth is the separating-axis minimum over the six axes of the segment–box Minkowski
  difference (the box's face normals and segment × box edges), exact.
* box–box: apart, min over the 24 edges of either box of the edge–other-box distance (one closest point of
  two convex polyhedra always lies on an edge of one of them), exact; in contact, the separating-axis
  minimum over the 15 axes (face normals of both, 9 edge × edge), the exact penetration depth.
* box–half-space: n·c − offset − Σ_k h_k |n·R e_k|, exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .._numerics import broadcast_shapes, eps_for, safe_norm
from ..errors import ModelError
from ..kernels.joints import origin_transform
from ..transforms import RIGIDITY_TOLERANCE, _make_transform, _nearest_rigid, _transform_deviations
from ..validation import broadcast_batch, check_lower_bound, tensors
from .distances import envelope

__all__ = ["Box", "box", "point_box", "segment_box", "capsule_box", "sphere_box", "box_halfspace", "box_box"]

@dataclass(frozen=True)
class Box:
    """One box or a stack: ``center (..., 3)``, ``rotation (..., 3, 3)``, ``half_extents (..., 3)``."""

    center: Tensor
    rotation: Tensor
    half_extents: Tensor

    @property
    def shape(self) -> torch.Size:
        """The leading (stack / batch) shape."""
        return self.center.shape[:-1]


def box(center, half_extents, rpy=None, *, dtype: torch.dtype | None = None, device=None) -> Box:
    """An oriented box, or a stack of them: ``center (..., 3)``, ``half_extents (..., 3)`` (≥ 0) and
    ``rpy (..., 3)`` (URDF roll-pitch-yaw, R = Rz(y) Ry(p) Rx(r); default: axis-aligned). Leading dims
    broadcast. Numbers and arrays become tensors of ``dtype`` / ``device`` (tensors must already be of
    them). Differentiable in all three.
    """
    like = None if dtype is None and device is None else torch.empty(
        0, dtype=dtype or torch.get_default_dtype(), device=device)
    c, h, r = tensors(("center", center, (3,)), ("half_extents", half_extents, (3,)), ("rpy", rpy, (3,)),
                      like=like)
    check_lower_bound(h, "half_extents", cls=ModelError)
    r = torch.zeros_like(c) if r is None else r
    batch = broadcast_batch(("center", c, 1), ("half_extents", h, 1), ("rpy", r, 1))
    R = origin_transform(torch.zeros_like(r), r)[..., :3, :3]
    return Box(c.expand(*batch, 3), R.expand(*batch, 3, 3), h.expand(*batch, 3))


def checked_boxes(B: Box, like=None) -> Box:
    """A :class:`Box` built directly (not by :func:`box`) by the same rule (private: :class:`World` calls
    it): tensors or numbers of one dtype and device (``like``'s, if given) with trailing shapes ``(3,)``,
    ``(3, 3)``, ``(3,)`` and batch dims that broadcast (:class:`~diffkin.errors.ShapeError`), finite
    (:class:`~diffkin.errors.NonFiniteError`), half extents >= 0 and rotations that are rotations by the one
    rule of :data:`~diffkin.transforms.RIGIDITY_TOLERANCE` (:class:`~diffkin.errors.ModelError`;
    re-orthonormalised within it). Returns the box expanded to one batch shape."""
    c, R, h = tensors(("boxes.center", B.center, (3,)), ("boxes.rotation", B.rotation, (3, 3)),
                      ("boxes.half_extents", B.half_extents, (3,)), like=like)
    batch = broadcast_batch(("boxes.center", c, 1), ("boxes.rotation", R, 2), ("boxes.half_extents", h, 1))
    check_lower_bound(h, "boxes.half_extents", cls=ModelError)
    T = _make_transform(R, c)
    dev = _transform_deviations(T, "boxes.rotation", RIGIDITY_TOLERANCE, error=ModelError)
    exact = _nearest_rigid(T, *dev)
    R = R if exact is T else exact[..., :3, :3]
    return Box(c.expand(*batch, 3), R.expand(*batch, 3, 3), h.expand(*batch, 3))


def _broadcast(vectors: list[Tensor], matrices: list[Tensor]) -> tuple[list[Tensor], list[Tensor]]:
    """Expand ``(..., 3)`` vectors and ``(..., 3, 3)`` matrices to one batch shape."""
    batch = broadcast_shapes(*(v.shape[:-1] for v in vectors), *(m.shape[:-2] for m in matrices))
    return [v.expand(*batch, 3) for v in vectors], [m.expand(*batch, 3, 3) for m in matrices]


def _local(p: Tensor, c: Tensor, R: Tensor) -> Tensor:
    """Rᵀ (p − c): a point in the box frame, ``(..., 3)``."""
    return ((p - c).unsqueeze(-1) * R).sum(-2)


def _sdf_local(u: Tensor, h: Tensor) -> Tensor:
    """Signed distance of the box-frame point u to the box |u_k| ≤ h_k."""
    excess = u.abs() - h
    outside = safe_norm(excess.clamp(min=0.0))
    return outside + excess.amax(-1).clamp(max=0.0)


def point_box(p: Tensor, center: Tensor, R: Tensor, h: Tensor) -> Tensor:
    """Signed distance of points ``(..., 3)`` to boxes: ``(...)``."""
    return _sdf_local(_local(p, center, R), h)


def sphere_box(c: Tensor, r: Tensor, center: Tensor, R: Tensor, h: Tensor) -> Tensor:
    """Sphere (c, r) to a box: point_box − r (exact, penetration included)."""
    return point_box(c, center, R, h) - r


def _project_radius(n: Tensor, R: Tensor, h: Tensor) -> Tensor:
    """Support half-width of boxes along unit axes n ``(..., A, 3)``: Σ_k h_k |n·R e_k| → ``(..., A)``."""
    return (torch.einsum("...ai,...ik->...ak", n, R).abs() * h.unsqueeze(-2)).sum(-1)


def _unit_axes(v: Tensor) -> tuple[Tensor, Tensor]:
    """(v / |v| with e_x where |v| ≈ 0, mask of the usable axes): ``(..., A, 3)``."""
    n = safe_norm(v, keepdim=True)
    ok = n > eps_for(v) ** 0.5 * (1.0 + v.detach().abs().amax(-1, keepdim=True))
    e = torch.zeros_like(v)
    e[..., 0] = 1.0
    return torch.where(ok, v / torch.where(ok, n, torch.ones_like(n)), e), ok.squeeze(-1)


def _sat(gap: Tensor, ok: Tensor) -> Tensor:
    """Max over usable axes of the separations ``(..., A)`` (unusable axes never win)."""
    low = torch.finfo(gap.dtype).min
    return torch.where(ok, gap, torch.full_like(gap, low)).amax(-1)


def _segment_box_sat(a: Tensor, b: Tensor, c: Tensor, R: Tensor, h: Tensor) -> Tensor:
    """Separating-axis value of a segment and a box (negative: minus the penetration depth)."""
    e = 0.5 * (b - a)
    m = 0.5 * (a + b)
    axes = R.transpose(-1, -2)  # rows: the face normals
    cross = torch.linalg.cross(e.unsqueeze(-2).expand_as(axes), axes, dim=-1)
    n_c, ok_c = _unit_axes(cross)
    n = torch.cat((axes, n_c), -2)
    ok = torch.cat((torch.ones_like(ok_c), ok_c), -1)
    gap = ((n * (m - c).unsqueeze(-2)).sum(-1).abs() - (n * e.unsqueeze(-2)).sum(-1).abs()
           - _project_radius(n, R, h))
    return _sat(gap, ok)


@torch.no_grad()
def _segment_box_parameter(a: Tensor, b: Tensor, c: Tensor, R: Tensor, h: Tensor) -> Tensor:
    """argmin over t ∈ [0, 1] of the squared distance from a + t (b − a) to the box, in closed form, detached.

    In the box frame u(t) = u_a + t e, the squared distance Σ_k max(|u_k(t)| − h_k, 0)² is a convex
    piecewise quadratic whose pieces change where some u_k(t) = ±h_k (at most six knots in [0, 1]). On
    each of the seven intervals between the sorted knots (0 and 1 included) the set of coordinates outside
    the slab, and their side s_k, is fixed: the piece Σ_active (u_k(t) − s_k h_k)² has its stationary
    point at t = −Σ e_k (u_a,k − s_k h_k) / Σ e_k², clamped to the interval. The best of those seven
    candidates is the exact minimiser (used where the segment misses the box; where it meets it the
    separating-axis depth decides).
    """
    ua, ub = _local(a, c, R), _local(b, c, R)
    # component-major (3, ...): the elementwise work runs on long contiguous rows, not on triples
    ua, e, hh = ua.movedim(-1, 0).contiguous(), (ub - ua).movedim(-1, 0).contiguous(), \
        h.expand_as(ua).movedim(-1, 0).contiguous()
    tiny = torch.finfo(e.dtype).tiny
    safe_e = torch.where(e.abs() > tiny, e, torch.full_like(e, tiny))
    ends = torch.stack((torch.zeros_like(e[0]), torch.ones_like(e[0])))
    knots = torch.cat(((hh - ua) / safe_e, (-hh - ua) / safe_e, ends), 0)
    knots = knots.clamp(0.0, 1.0).sort(0).values  # (8, ...)
    lo, hi = knots[:-1], knots[1:]  # (7, ...) intervals
    mid = 0.5 * (lo + hi)
    ua7, e7, h7 = ua.unsqueeze(1), e.unsqueeze(1), hh.unsqueeze(1)  # (3, 1, ...)
    um = torch.addcmul(ua7, mid, e7)  # (3, 7, ...)
    side = (um > h7).to(e.dtype) - (um < -h7).to(e.dtype)  # s_k, 0 inside the slab
    ee = e7 * side.abs()
    num = (ee * (ua7 - side * h7)).sum(0)
    t = (-num / (ee * ee).sum(0).clamp_min(tiny)).clamp(lo, hi)  # (7, ...)
    f = (torch.addcmul(ua7, t, e7).abs() - h7).clamp(min=0.0).square().sum(0)
    return t.gather(0, f.argmin(0, keepdim=True)).squeeze(0)


def _smooth_segment_box_parameter(a: Tensor, b: Tensor, c: Tensor, R: Tensor, h: Tensor, t: Tensor) -> Tensor:
    """The minimiser ``t`` of :func:`_segment_box_parameter` as a differentiable function where it is
    interior: the stationary point t = −Σ e_k (u_a,k − s_k h_k) / Σ e_k² of its piece (the coordinates
    outside the slab at t, their sides s_k held); ``t`` itself where it is clamped to 0 or 1 or the piece
    is flat."""
    ua = _local(a, c, R)
    e = _local(b, c, R) - ua
    with torch.no_grad():
        u = ua + t.unsqueeze(-1) * e
        side = (u > h).to(u.dtype) - (u < -h).to(u.dtype)
    ee = e * side.abs()
    den = (ee * ee).sum(-1)
    ok = (t > 0) & (t < 1) & (den.detach() > torch.finfo(den.dtype).eps * (e * e).sum(-1).detach())
    return torch.where(ok, -(ee * (ua - side * h)).sum(-1) / torch.where(ok, den, torch.ones_like(den)), t)


def segment_box(a: Tensor, b: Tensor, c: Tensor, R: Tensor, h: Tensor) -> Tensor:
    """Signed distance of segments a–b ``(..., 3)`` to boxes ``(..., 3)``, ``(..., 3, 3)``, ``(..., 3)``."""
    (a, b, c, h), (R,) = _broadcast([a, b, c, h], [R])
    t0 = _segment_box_parameter(a, b, c, R, h)
    t = _smooth_segment_box_parameter(a, b, c, R, h, t0) if torch.is_grad_enabled() else t0
    (t,) = envelope((t0,), (t,))
    apart = point_box(a + t.unsqueeze(-1) * (b - a), c, R, h)
    sat = _segment_box_sat(a, b, c, R, h)
    return torch.where(sat > 0, apart, sat)


def capsule_box(a: Tensor, b: Tensor, r: Tensor, c: Tensor, R: Tensor, h: Tensor) -> Tensor:
    """Capsule (a–b, r) to a box: segment_box − r (the Minkowski sum with a ball adds r to both the
    distance and the penetration depth, so this is exact)."""
    return segment_box(a, b, c, R, h) - r


def box_halfspace(c: Tensor, R: Tensor, h: Tensor, n: Tensor, offset: Tensor) -> Tensor:
    """Box to the half-space {x : n·x ≤ offset}: n·c − offset − Σ h_k |n·R e_k|, ``(...)``."""
    return (n * c).sum(-1) - offset - _project_radius(n.unsqueeze(-2), R, h).squeeze(-1)


_SIGNS = torch.tensor([[-1, -1], [-1, 1], [1, -1], [1, 1]], dtype=torch.float64)


def _edges(c: Tensor, R: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
    """The 12 edges of boxes as end points ``(..., 12, 3)`` each."""
    starts, ends = [], []
    signs = _SIGNS.to(c)
    for k in range(3):  # edges along axis k: the four sign choices of the other two axes
        i, j = [m for m in range(3) if m != k]
        u = torch.zeros(4, 3, dtype=c.dtype, device=c.device)
        u[:, i], u[:, j] = signs[:, 0], signs[:, 1]
        lo, hi = u.clone(), u.clone()
        lo[:, k], hi[:, k] = -1.0, 1.0
        starts.append(lo)
        ends.append(hi)
    lo, hi = torch.cat(starts), torch.cat(ends)  # (12, 3) in units of the half extents
    world = lambda u: c.unsqueeze(-2) + torch.einsum("...ik,...ek->...ei", R, u * h.unsqueeze(-2))  # noqa: E731
    return world(lo), world(hi)


def _box_box_sat(c1: Tensor, R1: Tensor, h1: Tensor, c2: Tensor, R2: Tensor, h2: Tensor) -> Tensor:
    A, B = R1.transpose(-1, -2), R2.transpose(-1, -2)  # rows: axes
    cross = torch.linalg.cross(A.unsqueeze(-2).expand(*A.shape[:-1], 3, 3),
                               B.unsqueeze(-3).expand(*B.shape[:-2], 3, 3, 3), dim=-1)
    n_c, ok_c = _unit_axes(cross.flatten(-3, -2))
    n = torch.cat((A, B, n_c), -2)
    ok = torch.cat((torch.ones_like(ok_c[..., :6]), ok_c), -1)
    gap = ((n * (c2 - c1).unsqueeze(-2)).sum(-1).abs() - _project_radius(n, R1, h1)
           - _project_radius(n, R2, h2))
    return _sat(gap, ok)


def box_box(c1: Tensor, R1: Tensor, h1: Tensor, c2: Tensor, R2: Tensor, h2: Tensor) -> Tensor:
    """Signed distance of two boxes (see the module docstring): ``(...)``."""
    (c1, h1, c2, h2), (R1, R2) = _broadcast([c1, h1, c2, h2], [R1, R2])
    a1, b1 = _edges(c1, R1, h1)
    a2, b2 = _edges(c2, R2, h2)
    v, m = (lambda x: x.unsqueeze(-2)), (lambda x: x.unsqueeze(-3))  # noqa: E731  (over the 12 edges)
    d12 = segment_box(a1, b1, v(c2), m(R2), v(h2)).amin(-1)
    d21 = segment_box(a2, b2, v(c1), m(R1), v(h1)).amin(-1)
    sat = _box_box_sat(c1, R1, h1, c2, R2, h2)
    return torch.where(sat > 0, torch.minimum(d12, d21), sat)
