"""Exact cylinders (flat ends, not capsules): signed distances to points, spheres, half-spaces, capsules,
boxes and other cylinders.

A cylinder is given as ``(a (..., 3), b (..., 3), r (...))``: the centres of its two flat faces and its
radius (the style of a capsule). Conventions and signs as in :mod:`diffkin.collision.distances`.

Methods:

* point / sphere – cylinder: the closed-form signed distance field. In the cylinder's frame (axial
  coordinate z, radial distance ρ, half-length h): q = (ρ − r, |z| − h), d = ‖max(q, 0)‖ + min(max(q), 0).
* cylinder – half-space: n·c − offset − |n·e| − r ‖n − (n·u) u‖ (c the centre, e = (b − a)/2, u = e/|e|),
  the support function in closed form.
* capsule / box / cylinder – cylinder: every shape here is centrally symmetric and a Minkowski sum of
  segments (half-vectors E_k: a capsule's or cylinder's half-axis, a box's three scaled axes), flat discs
  (unit normal v, radius ρ: a cylinder's cross-section) and a ball (a capsule's radius). For two convex
  solids A, B the signed distance (positive apart, minus the penetration depth in contact) is the largest
  separation over unit directions n (the separating-axis theorem over all axes; apart it is the distance,
  in contact minus the smallest translation that separates them)::

      d = max_{|n| = 1}  F(n),   F(n) = n·(c_A − c_B) − Σ_k |n·E_k| − Σ_j ρ_j ‖n − (n·v_j) v_j‖ − β

  (E, v, ρ of both solids, β the sum of their ball radii). Every F(n) is a lower bound of d, so the result
  is never optimistic. The maximiser is found without gradient (float64): the three best structural axes
  (the E_k, the v_j, their pairwise cross products, c_A − c_B and its parts perpendicular to the v_j) and
  the three best of 48 Fibonacci directions start a pattern search on the sphere (eight moves around n and
  moves along the kink circles n ⟂ E_k, on which F is not smooth; the step halved when no move improves;
  40 iterations, component-major), the best of the six results is kept (in contact F has several local
  maxima).
  The maximiser is then snapped to the structure it lies on (a disc normal ±v_j, a cross product
  E_i × E_k, the circle n ⟂ E_k, or none) and rebuilt from the differentiable geometry: F at that n is the
  value, and its gradient is the exact one wherever d is differentiable (the envelope theorem on the
  smooth part that remains; where the maximiser sits on a kink the rebuilt n carries the kink's own
  motion). Finite everywhere (safe norms, zero-length vectors masked). Accuracy against coal's GJK/EPA:
  tests/test_collision_cylinders.py.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .._numerics import broadcast_shapes, safe_norm, safe_normalize, tol_for

__all__ = ["point_cylinder", "sphere_cylinder", "cylinder_halfspace", "capsule_cylinder", "box_cylinder",
           "cylinder_cylinder", "cylinder_spheres"]


def _frame(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(centre (..., 3), half-axis e (..., 3), unit axis u (..., 3), half-length h (...))."""
    c, e = 0.5 * (a + b), 0.5 * (b - a)
    ez = torch.zeros_like(e)
    ez[..., 2] = 1.0
    return c, e, safe_normalize(e, fallback=ez), safe_norm(e)


def point_cylinder(p: Tensor, a: Tensor, b: Tensor, r: Tensor) -> Tensor:
    """Signed distance of points ``p (..., 3)`` to cylinders ``a, b (..., 3)``, ``r (...)``: ``(...)``."""
    c, _, u, h = _frame(a, b)
    w = p - c
    z = (w * u).sum(-1)
    rho = safe_norm(w - z.unsqueeze(-1) * u)
    q = torch.stack((rho - r, z.abs() - h), -1)
    return safe_norm(q.clamp(min=0.0)) + q.amax(-1).clamp(max=0.0)


def sphere_cylinder(c: Tensor, r: Tensor, a: Tensor, b: Tensor, rc: Tensor) -> Tensor:
    """Sphere (c, r) to a cylinder (a–b, rc): point_cylinder − r (exact, penetration included)."""
    return point_cylinder(c, a, b, rc) - r


def cylinder_halfspace(a: Tensor, b: Tensor, r: Tensor, n: Tensor, offset: Tensor) -> Tensor:
    """Cylinder to the half-space {x : n·x ≤ offset} (n unit): n·c − offset − |n·e| − r ‖n − (n·u) u‖."""
    c, e, u, _ = _frame(a, b)
    nu = (n * u).sum(-1, keepdim=True)
    return (n * c).sum(-1) - offset - (n * e).sum(-1).abs() - r * safe_norm(n - nu * u)


def cylinder_spheres(a: Tensor, b: Tensor, r: Tensor) -> tuple[Tensor, Tensor]:
    """Bounding spheres of cylinders (the broad phase): centres ``(..., 3)``, radii √(h² + r²) ``(...)``."""
    return 0.5 * (a + b), safe_norm(torch.cat((0.5 * (b - a), r.unsqueeze(-1)), -1))


# ------------------------------------------------------------------ the support-function search
def _parts_capsule(a: Tensor, b: Tensor, r: Tensor):
    """(centre, segments (..., 1, 3), disc normals (..., 0, 3), disc radii (..., 0), ball radius)."""
    e = 0.5 * (b - a)
    return 0.5 * (a + b), e.unsqueeze(-2), e.new_zeros(*e.shape[:-1], 0, 3), e.new_zeros(*e.shape[:-1], 0), r


def _parts_cylinder(a: Tensor, b: Tensor, r: Tensor):
    c, e, u, _ = _frame(a, b)
    return c, e.unsqueeze(-2), u.unsqueeze(-2), r.unsqueeze(-1), torch.zeros_like(r)


def _parts_box(c: Tensor, R: Tensor, h: Tensor):
    E = (R * h.unsqueeze(-2)).transpose(-1, -2)  # rows: the scaled axes h_k R e_k
    return c, E, c.new_zeros(*c.shape[:-1], 0, 3), c.new_zeros(*c.shape[:-1], 0), torch.zeros_like(c[..., 0])


def _separation(n: Tensor, delta: Tensor, E: Tensor, V: Tensor, rho: Tensor, beta: Tensor) -> Tensor:
    """F(n) for directions ``n (..., M, 3)`` of pairs ``delta (..., 3)``, ``E (..., S, 3)``, ``V (..., D,
    3)``, ``rho (..., D)``, ``beta (...)``: ``(..., M)`` (module docstring)."""
    f = (n * delta.unsqueeze(-2)).sum(-1) - beta.unsqueeze(-1)
    if E.shape[-2]:
        f = f - (n @ E.transpose(-1, -2)).abs().sum(-1)
    if V.shape[-2]:
        nv = n @ V.transpose(-1, -2)  # (..., M, D)
        # ‖n − (n·v) v‖ as a vector norm (√(1 − (n·v)²) loses half the digits near n = ±v), with a finite
        # gradient everywhere
        perp = safe_norm(n.unsqueeze(-2) - nv.unsqueeze(-1) * V.unsqueeze(-3))  # (..., M, D)
        f = f - (perp * rho.unsqueeze(-2)).sum(-1)
    return f


def _fibonacci(m: int, dtype, device) -> Tensor:
    k = torch.arange(m, dtype=torch.float64, device=device) + 0.5
    z = 1.0 - 2.0 * k / m
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    s = (1.0 - z * z).sqrt()
    return torch.stack((s * phi.cos(), s * phi.sin(), z), -1).to(dtype=dtype, device=device)


def _unit(v: Tensor) -> tuple[Tensor, Tensor]:
    """(v / |v| (0 where |v| ≈ 0), usable mask) — differentiable, finite gradients."""
    n = safe_norm(v, keepdim=True)
    ok = n > 1e-9 * (1.0 + v.detach().abs().amax(-1, keepdim=True))
    return v / torch.where(ok, n, torch.ones_like(n)) * ok, ok.squeeze(-1)


def _structural(delta: Tensor, E: Tensor, V: Tensor) -> tuple[Tensor, Tensor, list[tuple[str, int]]]:
    """The structural directions ``(..., K, 3)``, their usable mask and their kinds ("disc", "vertex",
    "ridge" are built from m later; here: the seeds)."""
    S, D = E.shape[-2], V.shape[-2]
    cand = [delta.unsqueeze(-2), E, V]
    if S > 1:
        i, k = torch.triu_indices(S, S, 1, device=E.device)
        cand.append(torch.linalg.cross(E[..., i, :], E[..., k, :], dim=-1))
    if S and D:
        ev = torch.linalg.cross(E.unsqueeze(-2).expand(*E.shape[:-1], D, 3),
                                V.unsqueeze(-3).expand(*V.shape[:-2], S, D, 3), dim=-1)
        cand.append(ev.flatten(-3, -2))
    if D > 1:
        cand.append(torch.linalg.cross(V[..., :1, :], V[..., 1:, :], dim=-1))
    if D:  # delta's part perpendicular to each disc normal (a rim against a flat side)
        cand.append(delta.unsqueeze(-2) - (delta.unsqueeze(-2) * V).sum(-1, keepdim=True) * V)
    return _unit(torch.cat(cand, -2))


@torch.no_grad()
def _search(delta: Tensor, E: Tensor, V: Tensor, rho: Tensor, beta: Tensor, iterations: int = 40,
            fib: int = 48, starts: int = 3) -> Tensor:
    """The maximiser n* ``(..., 3)`` of F (module docstring), detached, float64: the pattern search from the
    ``starts`` best structural seeds and the ``starts`` best Fibonacci seeds (in contact F has several local
    maxima; starts from both sets keep apart basins), the best result."""
    f64 = lambda x: x.detach().to(torch.float64)  # noqa: E731
    delta, E, V, rho, beta = map(f64, (delta, E, V, rho, beta))
    seeds, ok = _structural(delta, E, V)
    fibs = _fibonacci(fib, seeds.dtype, seeds.device).expand(*seeds.shape[:-2], fib, 3)
    seeds = torch.cat((seeds, fibs), -2)
    ok = torch.cat((ok, torch.ones_like(ok[..., :1]).expand(*ok.shape[:-1], fib)), -1)
    # F(n) - F(-n) = 2 n·delta: the sign facing delta is never worse
    seeds = torch.where((seeds * delta.unsqueeze(-2)).sum(-1, keepdim=True) < 0, -seeds, seeds)
    f = _separation(seeds, delta, E, V, rho, beta).masked_fill(~ok, -math.inf)
    ns = f.shape[-1] - fib
    b_s, t_s = f[..., :ns].topk(min(starts, ns), -1)
    b_f, t_f = f[..., ns:].topk(min(starts, fib), -1)
    best, top = torch.cat((b_s, b_f), -1), torch.cat((t_s, t_f + ns), -1)  # (..., K)
    n = seeds.gather(-2, top.unsqueeze(-1).expand(*top.shape, 3))  # (..., K, 3)
    # the loop runs component-major (x, y, z as separate (..., K, M) tensors: no reductions over a last axis
    # of 3); the pair's data gets (K, M) axes
    col = lambda t: [t[..., k, None, None] for k in range(3)]  # noqa: E731
    dl = col(delta)
    Eu = _unit(E)[0]
    segs = [(col(E[..., s, :]), col(Eu[..., s, :])) for s in range(E.shape[-2])]
    discs = [(col(V[..., j, :]), rho[..., j, None, None]) for j in range(V.shape[-2])]
    b1 = beta[..., None, None]

    def sep(x, y, z):
        f = x * dl[0] + y * dl[1] + z * dl[2] - b1
        for (ex, ey, ez), _ in segs:
            f = f - (x * ex + y * ey + z * ez).abs()
        for (vx, vy, vz), r in discs:  # ‖n × v‖ = ‖n − (n·v) v‖, accurate near n = ±v
            cx, cy, cz = y * vz - z * vy, z * vx - x * vz, x * vy - y * vx
            f = f - r * (cx * cx + cy * cy + cz * cz).sqrt()
        return f

    def unit(x, y, z):
        n = (x * x + y * y + z * z).sqrt().clamp_min(1e-300)
        return x / n, y / n, z / n

    nx, ny, nz = (n[..., k] for k in range(3))  # (..., K)
    step = torch.full_like(best, 0.3)
    ang = torch.arange(8, dtype=n.dtype, device=n.device) * (math.pi / 4)
    for it in range(iterations):
        big = nx.abs() > 0.9  # a tangent basis: t1 = n × e_x (n × e_y near ±e_x), t2 = n × t1
        t1 = unit(torch.where(big, -nz, torch.zeros_like(nz)), torch.where(big, torch.zeros_like(nz), nz),
                  torch.where(big, nx, -ny))
        t2 = (ny * t1[2] - nz * t1[1], nz * t1[0] - nx * t1[2], nx * t1[1] - ny * t1[0])
        th = ang + 0.37 * it  # a turning stencil: no ridge stays between its moves
        c, s_ = th.cos(), th.sin()
        sk = step[..., None]
        moves = [[nk[..., None] + sk * (c * a1[..., None] + s_ * a2[..., None])] for nk, a1, a2 in
                 zip((nx, ny, nz), t1, t2)]
        for _, (ux, uy, uz) in segs:  # onto each kink circle n ⟂ E_k, and along it
            ux, uy, uz = ux[..., 0], uy[..., 0], uz[..., 0]
            d = nx * ux + ny * uy + nz * uz
            on = unit(nx - d * ux, ny - d * uy, nz - d * uz)
            al = (uy * on[2] - uz * on[1], uz * on[0] - ux * on[2], ux * on[1] - uy * on[0])
            for k in range(3):
                o, a_ = on[k][..., None], al[k][..., None]
                moves[k].append(torch.cat((o, o + sk * a_, o - sk * a_), -1))
        mx, my, mz = (torch.cat(m, -1) for m in moves)
        cx, cy, cz = unit(mx, my, mz)
        fc = sep(cx, cy, cz).masked_fill(mx * mx + my * my + mz * mz < 1e-24, -math.inf)  # (0: no direction)
        fb, ib = fc.max(-1)
        better = fb > best
        ib = ib[..., None]
        nx, ny, nz = (torch.where(better, ck.gather(-1, ib).squeeze(-1), nk) for ck, nk in
                      zip((cx, cy, cz), (nx, ny, nz)))
        best = torch.where(better, fb, best)
        step = torch.where(better, step, 0.5 * step)
    n = torch.stack((nx, ny, nz), -1)
    return n.gather(-2, best.argmax(-1)[..., None, None].expand(*best.shape[:-1], 1, 3)).squeeze(-2)


def _snapped(m: Tensor, delta: Tensor, E: Tensor, V: Tensor, rho: Tensor, beta: Tensor) -> Tensor:
    """The maximiser ``m`` (detached) rebuilt from the differentiable geometry on the structure it lies on
    (a disc normal, a cross product of two segments, a kink circle, or m itself): the one of these with the
    largest F (ties: the most constrained), ``(..., 3)``."""
    S, D = E.shape[-2], V.shape[-2]
    sgn = lambda x: torch.where((x.detach() * m.unsqueeze(-2)).sum(-1, keepdim=True) < 0, -x, x)  # noqa: E731
    cand, ok = [m.unsqueeze(-2)], [torch.ones_like(m[..., :1], dtype=torch.bool)]
    if S:
        Eu, oku = _unit(E)
        on, okon = _unit(m.unsqueeze(-2) - (m.unsqueeze(-2) * Eu).sum(-1, keepdim=True) * Eu)
        cand.append(on)
        ok.append(okon & oku)
    if S > 1:
        i, k = torch.triu_indices(S, S, 1, device=E.device)
        x, okx = _unit(torch.linalg.cross(E[..., i, :], E[..., k, :], dim=-1))
        cand.append(sgn(x))
        ok.append(okx)
    if D:
        cand.append(sgn(V))
        ok.append(torch.ones_like(V[..., 0], dtype=torch.bool))
    cand, ok = torch.cat(cand, -2), torch.cat(ok, -1)
    with torch.no_grad():
        f = _separation(cand.detach().to(torch.float64), delta.detach().double(), E.detach().double(),
                        V.detach().double(), rho.detach().double(), beta.detach().double())
        f = f.masked_fill(~ok, -math.inf)
        scale = 1.0 + delta.detach().double().abs().amax(-1, keepdim=True) + E.detach().double().abs().sum(
            (-1, -2)).unsqueeze(-1)
        tol = tol_for(m, 1e-10, 1e-5) * scale
        # the most constrained candidate within tol of the best (later candidates are more constrained)
        good = f >= f.amax(-1, keepdim=True) - tol
        idx = torch.arange(f.shape[-1], device=f.device).expand_as(f)
        # a row with NaN inputs has no good candidate: it takes candidate 0 and its distance stays NaN
        pick = torch.where(good, idx, torch.full_like(idx, -1)).amax(-1).clamp(min=0)
    return cand.gather(-2, pick[..., None, None].expand(*pick.shape, 1, 3)).squeeze(-2)


def _support_distance(A: tuple, B: tuple) -> Tensor:
    """d of two solids given as parts (centre, segments, disc normals, disc radii, ball): ``(...)``."""
    cA, EA, VA, rA, bA = A
    cB, EB, VB, rB, bB = B
    batch = broadcast_shapes(cA.shape[:-1], cB.shape[:-1], EA.shape[:-2], EB.shape[:-2], VA.shape[:-2],
                                   VB.shape[:-2], rA.shape[:-1], rB.shape[:-1], bA.shape, bB.shape)
    x = lambda t, k: t.expand(torch.Size(batch) + t.shape[t.ndim - k:])  # noqa: E731
    delta = x(cA, 1) - x(cB, 1)
    E = torch.cat((x(EA, 2), x(EB, 2)), -2)
    V = torch.cat((x(VA, 2), x(VB, 2)), -2)
    rho = torch.cat((x(rA, 1), x(rB, 1)), -1)
    beta = x(bA, 0) + x(bB, 0)
    m = _search(delta, E, V, rho, beta).to(delta.dtype)
    n = _snapped(m, delta, E, V, rho, beta)
    return _separation(n.unsqueeze(-2), delta, E, V, rho, beta).squeeze(-1)


def capsule_cylinder(a0: Tensor, a1: Tensor, ra: Tensor, b0: Tensor, b1: Tensor, rb: Tensor) -> Tensor:
    """Capsule (a0–a1, ra) to cylinder (b0–b1, rb), ``(...)`` (support-function search, module docstring)."""
    return _support_distance(_parts_capsule(a0, a1, ra), _parts_cylinder(b0, b1, rb))


def box_cylinder(c: Tensor, R: Tensor, h: Tensor, a: Tensor, b: Tensor, r: Tensor) -> Tensor:
    """Box (c, R, h) to cylinder (a–b, r), ``(...)`` (support-function search, module docstring)."""
    return _support_distance(_parts_box(c, R, h), _parts_cylinder(a, b, r))


def cylinder_cylinder(a0: Tensor, a1: Tensor, ra: Tensor, b0: Tensor, b1: Tensor, rb: Tensor) -> Tensor:
    """Cylinder (a0–a1, ra) to cylinder (b0–b1, rb), ``(...)`` (support-function search, module docstring)."""
    return _support_distance(_parts_cylinder(a0, a1, ra), _parts_cylinder(b0, b1, rb))
