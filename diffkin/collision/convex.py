"""Convex meshes as a primitive: the convex hull of a vertex set, and its signed distances to spheres,
capsules, boxes, cylinders, half-spaces and other convex meshes.

A convex mesh is given by its vertices ``V (..., M, 3)`` (any points: the solid is their convex hull, so
interior points and repeats, as padding, change nothing). Conventions and signs as in
:mod:`diffkin.collision.distances`: positive the gap, negative minus the penetration depth.

Method. Every solid here is a *core* with a support map plus a ball radius (a capsule: its segment and r; a
sphere: a point and r; a box, a cylinder and a convex mesh: themselves and 0). The signed distance of the
cores is found by GJK when apart and EPA in contact (:mod:`diffkin.collision._gjk`, no gradient, float64),
which return witness weights λ_k and support directions d_k; the value is then rebuilt from the
differentiable geometry as d = ±‖Σ_k λ_k (s_A(d_k) − s_B(−d_k))‖ − r_A − r_B (the support points are
re-evaluated: a vertex by its index, a box corner by its signs, a cylinder's rim point from the detached
direction), whose gradient is the exact one wherever d is differentiable (the envelope theorem: the
module docstring of :mod:`._gjk`). The ball radii add exactly (the Minkowski sum with a ball). Tolerances:
GJK to 1e-10 of the scale; EPA converges finitely for polytopes (meshes, boxes, segments) and to a few
1e-7 m for a cylinder's curved side (64 steps). Convex mesh – half-space is closed form:
min_k n·v_k − offset. Accuracy against coal: tests/test_collision_convex.py.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .._numerics import broadcast_shapes, safe_norm
from ._gjk import signed_witness
from .cylinders import _frame, _unit

__all__ = ["convex_spheres", "convex_halfspace", "convex_convex", "capsule_convex", "box_convex",
           "cylinder_convex"]


def convex_spheres(V: Tensor) -> tuple[Tensor, Tensor]:
    """Bounding spheres of convex meshes ``V (..., M, 3)``: the centre of the vertices' bounding box
    ``(..., 3)`` and the largest distance of a vertex to it ``(...)``."""
    c = 0.5 * (V.amax(-2) + V.amin(-2))
    return c, safe_norm(V - c.unsqueeze(-2)).amax(-1)


def convex_halfspace(V: Tensor, n: Tensor, offset: Tensor) -> Tensor:
    """Convex mesh ``V (..., M, 3)`` to the half-space {x : n·x ≤ offset} (n unit): min_k n·v_k − offset."""
    return (V * n.unsqueeze(-2)).sum(-1).amin(-1) - offset


# ------------------------------------------------------------ support maps (float64, flat (N, ...) args)
def _s_convex(args, d):
    V, Vx, Vy, Vz = args  # the vertices and their coordinate planes (N, M) (three fused multiply-adds on
    # contiguous planes: about 3x a batched (M, 3) @ (3, 1) product)
    i = (Vx * d[:, :1]).addcmul_(Vy, d[:, 1:2]).addcmul_(Vz, d[:, 2:3]).argmax(-1)
    return V[torch.arange(len(V), device=V.device), i], i


def _s_segment(args, d):
    a, b = args
    hi = (d * (b - a)).sum(-1) > 0
    return torch.where(hi[:, None], b, a), hi.long()


def _s_box(args, d):
    c, R, h = args
    s = torch.where((d.unsqueeze(-2) @ R).squeeze(-2) >= 0, 1.0, -1.0).to(d.dtype)  # (N, 3): signs of Rᵀd
    code = ((s > 0).long() * torch.tensor([1, 2, 4], device=d.device)).sum(-1)
    return c + (R @ (h * s).unsqueeze(-1)).squeeze(-1), code


def _s_cylinder(args, d):
    a, b, r = args
    c, e, u, _ = _frame(a, b)
    top = (d * e).sum(-1) >= 0
    w, _ = _unit(d - (d * u).sum(-1, keepdim=True) * u)
    return c + torch.where(top[:, None], e, -e) + r[:, None] * w, top.long()


# ------------------------------------------------ the same points, differentiable, at (..., K) witnesses
def _p_convex(args, d, code):
    (V,) = args
    return V.gather(-2, code.unsqueeze(-1).expand(*code.shape, 3))


def _p_segment(args, d, code):
    a, b = args
    return torch.where(code.unsqueeze(-1) > 0, b.unsqueeze(-2), a.unsqueeze(-2))


def _p_box(args, d, code):
    c, R, h = args
    bits = torch.stack([(code >> k) & 1 for k in range(3)], -1)  # (..., K, 3)
    s = bits.to(c.dtype) * 2.0 - 1.0
    return c.unsqueeze(-2) + ((h.unsqueeze(-2) * s).unsqueeze(-2) * R.unsqueeze(-3)).sum(-1)


def _p_cylinder(args, d, code):
    a, b, r = args
    c, e, u, _ = _frame(a, b)
    c, e, u = c.unsqueeze(-2), e.unsqueeze(-2), u.unsqueeze(-2)
    w, _ = _unit(d - (d * u).sum(-1, keepdim=True) * u)
    return c + torch.where(code.unsqueeze(-1) > 0, e, -e) + r[..., None, None] * w


#: per core kind: (support map, differentiable point, own dims of the core's args)
_CORES = {
    "convex": (_s_convex, _p_convex, (2,)),
    "segment": (_s_segment, _p_segment, (1, 1)),
    "box": (_s_box, _p_box, (1, 2, 1)),
    "cylinder": (_s_cylinder, _p_cylinder, (1, 1, 0)),
}


def _signed(ka: str, A: tuple, ra: Tensor | None, kb: str, B: tuple, rb: Tensor | None) -> Tensor:
    """d = ±‖Σλ (s_A − s_B)‖ − r_A − r_B of cores ``A`` of kind ``ka`` and ``B`` of ``kb`` (args that
    broadcast; module docstring)."""
    sa, pa, own_a = _CORES[ka]
    sb, pb, own_b = _CORES[kb]
    shapes = [x.shape[: x.ndim - k] for x, k in zip(A + B, own_a + own_b)]
    shapes += [x.shape for x in (ra, rb) if x is not None]
    batch = broadcast_shapes(*shapes)
    N = batch.numel()
    ref = A[0]
    with torch.no_grad():
        flat = lambda xs, own: tuple(  # noqa: E731
            _flat(x, k, batch)
            for x, k in zip(xs, own))
        A64, B64 = flat(A, own_a), flat(B, own_b)
        A64, B64 = (x + tuple(x[0][..., k].contiguous() for k in range(3)) if k_ == "convex" else x
                    for x, k_ in ((A64, ka), (B64, kb)))
        ca, cb = _centre(ka, A64), _centre(kb, B64)
        scale = 1.0 + torch.cat([x.abs().reshape(N, -1) for x in A64[:len(A)] + B64[:len(B)]], -1).amax(-1)
        wit = signed_witness(sa, A64, sb, B64, ca - cb, scale)
    dirs = wit.dirs.to(ref.dtype).reshape(*batch, 4, 3)
    lam = wit.lam.to(ref.dtype).reshape(*batch, 4, 1)
    A = tuple(x.expand(torch.Size((*batch, *x.shape[x.ndim - k:]))) for x, k in zip(A, own_a))
    B = tuple(x.expand(torch.Size((*batch, *x.shape[x.ndim - k:]))) for x, k in zip(B, own_b))
    sa_k = pa(A, dirs, wit.code_a.reshape(*batch, 4))
    p = (lam * (sa_k - pb(B, -dirs, wit.code_b.reshape(*batch, 4)))).sum(-2)
    d = wit.sign.to(ref.dtype).reshape(batch) * safe_norm(p)
    for r in (ra, rb):
        if r is not None:
            d = d - r
    # NaN in, NaN out (the house rule of every distance): the witness search runs without the inputs' NaN
    # (a NaN end of a segment may never be a support point), so the value would look finite
    bad = torch.zeros(batch, dtype=torch.bool, device=d.device)
    for x, k in zip(A + B, own_a + own_b):
        bad = bad | torch.isnan(x).flatten(x.ndim - k).any(-1) if k else bad | torch.isnan(x)
    for r in (ra, rb):
        if r is not None:
            bad = bad | torch.isnan(r)
    return torch.where(bad, torch.full_like(d, float("nan")), d)


def _flat(x: Tensor, k: int, batch: torch.Size) -> Tensor:
    """``x`` detached in float64, expanded to ``batch`` and flattened to ``(N, own dims)``."""
    own = x.shape[x.ndim - k:]
    return x.detach().to(torch.float64).expand(torch.Size((*batch, *own))).reshape(batch.numel(), *own)


def _centre(kind: str, args: tuple) -> Tensor:
    if kind == "convex":
        return args[0].mean(-2)
    if kind == "box":
        return args[0]
    return 0.5 * (args[0] + args[1])


def convex_convex(V1: Tensor, V2: Tensor) -> Tensor:
    """Convex mesh ``V1 (..., M1, 3)`` to convex mesh ``V2 (..., M2, 3)``: ``(...)`` (module docstring)."""
    return _signed("convex", (V1,), None, "convex", (V2,), None)


def capsule_convex(a: Tensor, b: Tensor, r: Tensor, V: Tensor) -> Tensor:
    """Capsule (a–b ``(..., 3)``, r ``(...)``; a sphere: a = b) to a convex mesh ``V (..., M, 3)``."""
    return _signed("segment", (a, b), r, "convex", (V,), None)


def box_convex(c: Tensor, R: Tensor, h: Tensor, V: Tensor) -> Tensor:
    """Box (c ``(..., 3)``, R ``(..., 3, 3)``, h ``(..., 3)``) to a convex mesh ``V (..., M, 3)``."""
    return _signed("box", (c, R, h), None, "convex", (V,), None)


def cylinder_convex(a: Tensor, b: Tensor, r: Tensor, V: Tensor) -> Tensor:
    """Cylinder (a–b ``(..., 3)``, r ``(...)``) to a convex mesh ``V (..., M, 3)``."""
    return _signed("cylinder", (a, b, r), None, "convex", (V,), None)
