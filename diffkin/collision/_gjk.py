"""Batched GJK and EPA over support functions (private): the witness features of the signed distance of two
convex solids, without gradient, float64, fully vectorised over N pairs (no Python loop over pairs).

A solid is given by its support map s(d) = argmax_{x in solid} d·x returned as ``(point (N, 3), code (N,))``
(the code names the discrete choice: a vertex index, a box corner, a segment end, a cylinder rim side). The
configuration-space obstacle K = A ⊖ B has the support w(d) = s_A(d) − s_B(−d); the signed distance of A and
B is ‖closest point of K to the origin‖ when the origin is outside K (GJK, Gilbert-Johnson-Keerthi 1988)
and minus the distance of the origin to K's boundary when inside (EPA, van den Bergen 2001).

Both return the *witness*: up to four CSO points p_k = s_A(d_k) − s_B(−d_k) (directions d_k and codes),
barycentric weights λ_k and a sign, such that d = sign · ‖Σ_k λ_k p_k‖. Held constant (detached), the
weights give the exact gradient of d when the points are rebuilt from the differentiable geometry
(:mod:`diffkin.collision.convex`): apart, Σλ p is the closest point of K (the envelope theorem on the
simplex weights); in contact, it is the foot of the perpendicular from the origin on K's nearest face, and
the derivative of that face plane's distance is n·Σλ ṗ_k (the plane's own turning is orthogonal to the foot).

The simplex sub-algorithm is the brute-force form of Johnson's: every non-empty subset of the ≤ 4 points
is projected (its affine hull's closest point to the origin, a ≤ 3 × 3 Gram system), the valid ones (all
weights ≥ 0, non-singular) compared, the nearest kept (smaller subsets first: a tie keeps the smaller).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import torch
from torch import Tensor

__all__ = ["Witness", "signed_witness"]

Support = Callable[..., tuple[Tensor, Tensor]]  # support(args, d (N, 3)) -> point (N, 3), code (N,)
_SUBSETS = [s for k in range(1, 5) for s in itertools.combinations(range(4), k)]
#: the subsets holding point 0, GJK's newest support point (which is always on the new closest face)
_SUBSETS_0 = [s for s in _SUBSETS if 0 in s]


class Witness:
    """The detached witness of :func:`signed_witness`: ``dirs (N, 4, 3)``, ``code_a``, ``code_b (N, 4)``,
    ``lam (N, 4)`` and ``sign (N,)`` (±1)."""

    def __init__(self, dirs: Tensor, code_a: Tensor, code_b: Tensor, lam: Tensor, sign: Tensor):
        self.dirs, self.code_a, self.code_b, self.lam, self.sign = dirs, code_a, code_b, lam, sign


def _project(P: Tensor, scale: Tensor) -> tuple[Tensor, Tensor]:
    """The affine projection of the origin onto the hull of the points ``P (N, k, 3)``: weights ``(N, k)``
    and whether the Gram system G μ = −Dᵀ p_0 (D = [p_i − p_0]) is regular ``(N,)``; solved in closed
    form (Cramer: batched LAPACK calls on 2 × 2 and 3 × 3 systems cost more than the arithmetic)."""
    k = P.shape[1]
    if k == 1:
        return torch.ones_like(P[..., 0]), torch.ones_like(P[:, 0, 0], dtype=torch.bool)
    D = P[:, 1:] - P[:, :1]
    G = D @ D.transpose(1, 2)
    rhs = -(D @ P[:, 0].unsqueeze(-1)).squeeze(-1)
    if k == 2:
        det = G[:, 0, 0]
        mu = (rhs[:, 0] / torch.where(det > 0, det, 1.0)).unsqueeze(-1)
    elif k == 3:
        det = G[:, 0, 0] * G[:, 1, 1] - G[:, 0, 1] * G[:, 1, 0]
        sd = torch.where(det != 0, det, 1.0)
        mu = torch.stack(((rhs[:, 0] * G[:, 1, 1] - G[:, 0, 1] * rhs[:, 1]) / sd,
                          (G[:, 0, 0] * rhs[:, 1] - rhs[:, 0] * G[:, 1, 0]) / sd), -1)
    else:  # Gram of three edges: det = (d0 · d1 × d2)², μ = D⁻ᵀ applied: the solution of D μ' = −p_0 then
        c12 = torch.linalg.cross(D[:, 1], D[:, 2], dim=-1)
        c20 = torch.linalg.cross(D[:, 2], D[:, 0], dim=-1)
        c01 = torch.linalg.cross(D[:, 0], D[:, 1], dim=-1)
        vol = (D[:, 0] * c12).sum(-1)
        det = vol * vol
        sv = torch.where(vol != 0, vol, 1.0).unsqueeze(-1)
        p0 = -P[:, 0]
        mu = torch.stack(((p0 * c12).sum(-1), (p0 * c20).sum(-1), (p0 * c01).sum(-1)), -1) / sv
    ok = det > 1e-24 * scale ** (2 * (k - 1))
    return torch.cat((1.0 - mu.sum(-1, keepdim=True), mu), -1), ok


def _closest(W: Tensor, active: Tensor, scale: Tensor, subsets=_SUBSETS) -> tuple[Tensor, Tensor]:
    """The point of conv(active W) nearest the origin: weights ``(N, 4)`` (0 off its face) and the
    squared norm ``(N,)``. ``W (N, 4, 3)``, ``active (N, 4)``; ``subsets``: the faces tried."""
    N = W.shape[0]
    best = torch.full((N,), math.inf, dtype=W.dtype, device=W.device)
    lam = torch.zeros(N, 4, dtype=W.dtype, device=W.device)
    for s in subsets:
        idx = list(s)
        ls, ok = _project(W[:, idx], scale)
        ok &= active[:, idx].all(-1) & (ls >= -1e-12).all(-1)
        x = (ls.unsqueeze(-1) * W[:, idx]).sum(1)
        n2 = (x * x).sum(-1)
        better = ok & (n2 < best * (1.0 - 1e-12) - 1e-30 * scale * scale)
        best = torch.where(better, n2, best)
        full = torch.zeros_like(lam)
        full[:, idx] = ls.clamp(min=0.0)
        lam = torch.where(better[:, None], full, lam)
    return lam, best


def _cso(A: tuple, B: tuple, d: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The CSO support w(d) = s_A(d) − s_B(−d) of solids given as (support map, args (N, ...))."""
    pa, ca = A[0](A[1], d)
    pb, cb = B[0](B[1], -d)
    return pa - pb, ca, cb


@torch.no_grad()
def signed_witness(sa: Support, a_args: tuple, sb: Support, b_args: tuple, d0: Tensor, scale: Tensor,
                   iterations: int = 64, epa_iterations: int = 64) -> Witness:
    """The witness (module docstring) of solids A, B given by their support maps and float64 arguments
    ``(N, ...)`` over N pairs;
    ``d0 (N, 3)`` a first direction (e.g. centre of A − centre of B), ``scale (N,)`` their size (tolerances:
    1e-10 · scale)."""
    N, dev, dt = d0.shape[0], d0.device, d0.dtype
    sa, sb = (sa, a_args), (sb, b_args)
    d0 = torch.where((d0 * d0).sum(-1, keepdim=True) > 0, d0, torch.tensor([1.0, 0, 0], dtype=dt, device=dev))
    W = torch.zeros(N, 4, 3, dtype=dt, device=dev)
    dirs = torch.zeros_like(W)
    ca = torch.zeros(N, 4, dtype=torch.long, device=dev)
    cb = torch.zeros_like(ca)
    w, a, b = _cso(sa, sb, d0)
    W[:, 0], dirs[:, 0], ca[:, 0], cb[:, 0] = w, d0, a, b
    active = torch.zeros(N, 4, dtype=torch.bool, device=dev)
    active[:, 0] = True
    lam = active.to(dt)
    v = w
    done = torch.zeros(N, dtype=torch.bool, device=dev)
    contact = torch.zeros_like(done)
    tol = 1e-10 * scale
    for it in range(iterations):
        d = -v
        w, a, b = _cso(sa, sb, d)
        vn = (v * v).sum(-1).sqrt()
        conv = (vn * vn - (v * w).sum(-1)) <= tol * vn
        done = done | conv
        put = ~done
        # the new point first, then the (at most three) points of the current face: only the faces that
        # hold the new point can be the new closest face
        keep = torch.argsort((~active).to(torch.int8), dim=-1, stable=True)[:, :3]
        pm, pv, k3 = put[:, None], put[:, None, None], keep[..., None].expand(-1, -1, 3)
        W = torch.where(pv, torch.cat((w[:, None], W.gather(1, k3)), 1), W)
        dirs = torch.where(pv, torch.cat((d[:, None], dirs.gather(1, k3)), 1), dirs)
        ca = torch.where(pm, torch.cat((a[:, None], ca.gather(1, keep)), 1), ca)
        cb = torch.where(pm, torch.cat((b[:, None], cb.gather(1, keep)), 1), cb)
        act = torch.cat((torch.ones_like(active[:, :1]), active.gather(1, keep)), 1)
        lam_n, n2 = _closest(W, act, scale, _SUBSETS_0)
        lam = torch.where(pm, lam_n, lam)
        active = torch.where(pm, lam_n > 0, active)
        v = torch.where(pm, (lam[..., None] * W).sum(1), v)
        hit = put & (n2 <= (tol * tol))
        contact = contact | hit
        done = done | hit
        if it % 8 == 7 and bool(done.all()):
            break
    sign = torch.ones(N, dtype=dt, device=dev)
    rows = contact.nonzero().squeeze(-1)
    if len(rows):
        # the contact's simplex: its points with a weight (the origin lies in their hull)
        sub = lambda s: (s[0], tuple(x[rows] for x in s[1]))  # noqa: E731
        ew = _epa(sub(sa), sub(sb), W[rows], dirs[rows], ca[rows], cb[rows], lam[rows], active[rows],
                  scale[rows], epa_iterations)
        dirs, ca, cb, lam = (x.index_copy(0, rows, y) for x, y in zip((dirs, ca, cb, lam), ew))
        sign[rows] = -1.0
    return Witness(dirs, ca, cb, lam, sign)


def _epa(sA, sB, W, dirs, ca, cb, lam0, active, scale, iterations):
    """EPA from GJK's final simplex for the contact ``rows``: (dirs, code_a, code_b, lam) of the nearest
    face of K's boundary (module docstring). A simplex of four points is a tetrahedron around the origin;
    three or two become a bipyramid around the origin (below); one (a support point, so on K's boundary)
    gives depth 0 there (GJK's witness)."""
    n, dev, dt = W.shape[0], W.device, W.dtype
    V = 6 + iterations
    F = 2 * V
    P = torch.zeros(n, V, 3, dtype=dt, device=dev)
    D = torch.zeros_like(P)
    CA = torch.zeros(n, V, dtype=torch.long, device=dev)
    CB = torch.zeros_like(CA)
    k = active.sum(-1)
    order = torch.argsort((~active).to(torch.int8), dim=-1, stable=True)  # active points first
    g = lambda x: x.gather(1, order.view(n, 4, *([1] * (x.ndim - 2))).expand_as(x))  # noqa: E731
    P[:, :4], D[:, :4], CA[:, :4], CB[:, :4] = g(W), g(dirs), g(ca), g(cb)
    # fewer than four points: a triangular bipyramid (equator: vertices 0-2, apexes: 3 and 4) around the
    # origin. Three points (the origin on a triangle) are the equator, the supports along ± its normal the
    # apexes; two (the origin on a segment, e.g. coincident solids) are the apexes, the supports along
    # three directions at 120° about the segment the equator (libccd's simplexToPolytope2).
    tri, seg = k == 3, k == 2
    nrm = torch.linalg.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], dim=-1)
    axis = P[:, 1] - P[:, 0]
    ex, ey = torch.eye(3, dtype=dt, device=dev)[:2]
    ref = torch.where(axis[:, :1].abs() < 0.9 * axis.norm(dim=-1, keepdim=True), ex, ey)
    n1 = torch.linalg.cross(axis, ref, dim=-1)
    n2 = torch.linalg.cross(axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-300), n1, dim=-1)
    seg_pts = {i: (P[:, i].clone(), D[:, i].clone(), CA[:, i].clone(), CB[:, i].clone()) for i in (0, 1)}

    def put(slot, mask, d, point=None):
        w, a, b = _cso(sA, sB, d) if point is None else point
        m = mask[:, None]
        P[:, slot], D[:, slot] = torch.where(m, w, P[:, slot]), torch.where(m, d, D[:, slot])
        CA[:, slot], CB[:, slot] = torch.where(mask, a, CA[:, slot]), torch.where(mask, b, CB[:, slot])

    put(3, tri, nrm)
    put(4, tri, -nrm)
    for slot, ang in ((0, 0.0), (1, 2.0943951023931957), (2, 4.1887902047863905)):
        put(slot, seg, math.cos(ang) * n1 + math.sin(ang) * n2)
    for slot, i in ((3, 0), (4, 1)):
        w, d, a, b = seg_pts[i]
        put(slot, seg, d, (w, a, b))
    faces = torch.zeros(n, F, 3, dtype=torch.long, device=dev)
    valid = torch.zeros(n, F, dtype=torch.bool, device=dev)
    tet = torch.tensor([[0, 1, 2], [0, 3, 1], [1, 3, 2], [0, 2, 3]], device=dev)
    bip = torch.tensor([[0, 1, 3], [1, 2, 3], [2, 0, 3], [1, 0, 4], [2, 1, 4], [0, 2, 4]], device=dev)
    four = (k == 4)[:, None, None]
    faces[:, :6] = torch.where(four, torch.cat((tet, tet[:2])), bip)
    valid[:, :6] = torch.where(four[:, :, 0], torch.arange(6, device=dev) < 4, torch.ones(6, dtype=torch.bool,
                                                                                         device=dev))
    nv = torch.where(k == 4, 4, 5)
    # orient every face outward: the centroid of the start polytope inside
    cen = torch.where(four[:, :, 0], P[:, :4].mean(1), P[:, :5].mean(1))
    fp = P.gather(1, faces.flatten(1)[..., None].expand(-1, -1, 3)).view(n, F, 3, 3)
    fn = torch.linalg.cross(fp[:, :, 1] - fp[:, :, 0], fp[:, :, 2] - fp[:, :, 0], dim=-1)
    flip = (fn * (fp[:, :, 0] - cen[:, None])).sum(-1) < 0
    faces = torch.where(flip[..., None], faces[..., [0, 2, 1]], faces)
    done = k < 2
    tol = 1e-10 * scale
    best_f = torch.zeros(n, dtype=torch.long, device=dev)
    ar = torch.arange(n, device=dev)
    for _ in range(iterations + 1):
        fp = P.gather(1, faces.flatten(1)[..., None].expand(-1, -1, 3)).view(n, F, 3, 3)
        fn = torch.linalg.cross(fp[:, :, 1] - fp[:, :, 0], fp[:, :, 2] - fp[:, :, 0], dim=-1)
        fl = fn.norm(dim=-1)
        ok = valid & (fl > 1e-30)
        un = fn / fl.clamp_min(1e-300)[..., None]
        dist = torch.where(ok, (un * fp[:, :, 0]).sum(-1), torch.full_like(fl, math.inf))
        best, f = dist.min(-1)
        best_f = torch.where(done, best_f, f)
        nb = un[ar, f]
        w, a, b = _cso(sA, sB, nb)
        conv = ((w * nb).sum(-1) - best <= tol) | (nv >= V) | ~torch.isfinite(best)
        done = done | conv
        if bool(done.all()):
            break
        act = ~done
        P[ar, nv.clamp(max=V - 1)] = torch.where(act[:, None], w, P[ar, nv.clamp(max=V - 1)])
        D[ar, nv.clamp(max=V - 1)] = torch.where(act[:, None], nb, D[ar, nv.clamp(max=V - 1)])
        CA[ar, nv.clamp(max=V - 1)] = torch.where(act, a, CA[ar, nv.clamp(max=V - 1)])
        CB[ar, nv.clamp(max=V - 1)] = torch.where(act, b, CB[ar, nv.clamp(max=V - 1)])
        visible = ok & ((un * (w[:, None] - fp[:, :, 0])).sum(-1) > tol[:, None]) & act[:, None]
        ea, eb = faces.flatten(1), faces[..., [1, 2, 0]].flatten(1)  # (n, 3F) directed edges
        key, rkey = ea * V + eb, eb * V + ea
        vis3 = visible.repeat_interleave(3, 1)
        keep3 = (valid & ~visible).repeat_interleave(3, 1)
        # the owner of every directed edge (1: a kept face): a dense (V·V) table per row, looked up reversed
        owner = torch.zeros(n, V * V + 1, dtype=torch.bool, device=dev)
        owner.scatter_(1, torch.where(keep3, key, V * V), True)
        owner[:, V * V] = False
        horizon = vis3 & owner.gather(1, rkey)
        kept = valid & ~visible
        rank = horizon.long().cumsum(-1) - 1
        free_slots = torch.argsort(kept.to(torch.int8), dim=-1, stable=True)  # free slots first
        nfree = (~kept).sum(-1)
        over = (horizon.sum(-1) > nfree) & act
        done = done | over
        put = horizon & act[:, None] & ~over[:, None]
        slot = free_slots.gather(1, rank.clamp(min=0, max=F - 1))
        slot = torch.where(put, slot, F)  # F: a dummy slot dropped below
        newf = torch.stack((ea, eb, nv[:, None].expand_as(ea)), -1)
        faces_x = torch.cat((faces, faces[:, :1]), 1).scatter(1, slot[..., None].expand(-1, -1, 3), newf)
        valid_x = torch.cat((torch.where(act[:, None] & ~over[:, None], kept, valid),
                             valid[:, :1]), 1).scatter(1, slot, put)
        faces, valid = faces_x[:, :F], valid_x[:, :F]
        nv = torch.where(act & ~over, nv + 1, nv)
    idx = faces[ar, best_f]  # (n, 3)
    tri = P.gather(1, idx[..., None].expand(-1, -1, 3))
    lam3, _ = _project(tri, scale)
    lam = torch.cat((lam3, torch.zeros_like(lam3[:, :1])), -1)
    idx4 = torch.cat((idx, idx[:, :1]), -1)
    pick = lambda x: x.gather(1, idx4.view(n, 4, *([1] * (x.ndim - 2))).expand(n, 4, *x.shape[2:]))  # noqa: E731
    few = k < 2  # GJK's own witness: the origin is its one point, on K's boundary: depth 0
    sel = lambda a, b: torch.where(few.view(n, *([1] * (a.ndim - 1))), b, a)  # noqa: E731
    return sel(pick(D), dirs), sel(pick(CA), ca), sel(pick(CB), cb), sel(lam, lam0)
