"""Approximate convex decomposition of a triangle mesh: convex parts whose union contains every triangle and
reaches beyond the mesh by at most a tolerance (numpy with scipy's Qhull and k-d tree; offline, once per
mesh file).

The rule (deterministic, no random draws):

1. One part: every triangle of the mesh.
2. A part's **excess** is the largest distance to the mesh surface of a point of its convex hull's boundary
   that lies outside the mesh. Why the boundary suffices: for a point y outside the mesh, the nearest point
   x of the union of the hulls lies on some hull's boundary; if x is outside the mesh,
   d_mesh(y) ≤ |y − x| + d_mesh(x), so d_mesh(y) − d_union(y) ≤ excess; if x is inside, the segment y–x
   crosses the surface and d_mesh(y) ≤ d_union(y). Since every triangle lies in some hull, also
   d_union(y) ≤ d_mesh(y): **0 ≤ d_mesh − d_union ≤ the largest excess** for every point outside.
3. While some part's excess is above ``tolerance`` (and there are fewer than ``max_parts`` parts), the worst
   part is cut. Its worst sample x and the points f of its own triangles nearest to x (ties: the U's slot
   has two walls and a floor) give the gap-facing planes, through f facing x − f (the concavity's wall
   there is cut off: on the U below, first one arm, then the other). The one that moves x farthest out of
   both sides' hulls is taken if it moves x out by half the gap beyond the tolerance, or if its smaller
   side holds at least 1 % of the part's hull volume. Otherwise (a sliver off a rim or a flat panel, which
   leaves x covered: on Panda link6 such cuts spent most parts) the candidates are also the planes through
   f of the mesh's own triangles there, the 3 coordinate axes and the part's 3 principal axes, and the one
   that moves x farthest out of both hulls is taken (least total hull volume among ties). With no worst
   sample, or none that any plane uncovers, the plane among the principal axes at 1/8 … 7/8 of the extent
   whose two sides' hulls have the least total volume. Triangles crossing the plane are clipped, each side
   keeping its piece with the crossing points as vertices (a triangle on the plane goes to the side behind
   its normal), so a part's hull still contains its triangles and the union contains the whole surface
   (conservative).
4. A point of a part's hull on one of its cuts is inside the union, and not measured, where a hull of
   another part holds it from across the cut; when the splitting stops, every part is measured again
   against the final set (a later cut may have uncovered a face), and the splitting resumes if one fails.
   Deep inside a thick mesh, near a point where three cutting planes meet, a small pocket of the solid may
   belong to no hull; it lies farther than the parts' surfaces from any point outside, so distances to the
   outside are unaffected, but an object wholly inside such a pocket is not seen. The bound of 2. is for
   points outside the union: a point outside the mesh but inside a hull (a cavity of the mesh that a hull
   closes over) gets a negative distance, its depth in that hull, which no boundary measure bounds.

Measuring the excess. The hull's triangles are bisected at their longest edge until no edge is longer than
``s = tolerance / 2``; their corners are the samples (every boundary point lies within s/√3 of one). A
sample's distance to the surface is first bounded by its distance to the nearest corner of the mesh's own
triangles bisected the same way (never below the true one; the k-d tree searched only to the limit
first, a far sample's nearest corners being a deep search), and where that is above the limit, taken
exactly to the triangles of the 4 nearest corners (an upper bound still); a sample is outside where the
mesh's generalised winding number (Jacobson, Kavan and Sorkine-Hornung 2013: robust to the cracks and
overlapping shells of real collision meshes) is below 1/2 in magnitude. A part passes when its measured
excess plus s/√3 is within ``tolerance``. Parts are first measured on samples 4× coarser: one sample
outside by more than the limit already condemns a part. Samples and corners are merged within cubes of side
q = 2^-20 of the mesh's extent (a bisection corner is shared by about 6 pieces: 6× fewer points to search),
which costs the limit 2√3 q.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ModelError, NonFiniteError, ShapeError, require
from ..validation import check_count, check_number

__all__ = ["ConvexParts", "convex_parts", "bisected", "point_triangle", "winding_number"]

_CUTS = np.arange(1, 8) / 8.0  # the candidate offsets, as fractions of a part's extent along a normal


@dataclass(frozen=True)
class ConvexParts:
    """The result of :func:`convex_parts`: ``parts`` (list of ``(M_k, 3)`` hull vertices, one array per
    convex part) and ``excess``, the measured bound (m) on how far their union reaches beyond the mesh
    (module docstring: measured excess plus the sampling's s/√3); ``excess <= tolerance`` unless
    ``max_parts`` stopped the splitting first."""

    parts: list
    excess: float


def convex_parts(v, faces, *, tolerance: float = 0.002, max_parts: int = 32) -> ConvexParts:
    """Convex parts of the mesh ``v (N, 3)``, ``faces (F, 3)`` (vertex indices) whose hulls contain every
    triangle and reach beyond the mesh by at most ``tolerance`` (in the mesh's units; module docstring: the
    rule and how the excess is measured), at most ``max_parts`` of them. A convex mesh gives one part, its
    hull."""
    tolerance = check_number(tolerance, "tolerance")
    max_parts = check_count(max_parts, "max_parts")
    v = np.asarray(v, dtype=np.float64)
    faces = np.asarray(faces)
    if v.ndim != 2 or v.shape[-1] != 3 or faces.ndim != 2 or faces.shape[-1] != 3 or len(faces) == 0:
        raise ShapeError(f"convex_parts: expected vertices (N, 3) and faces (F, 3) with F >= 1, got "
                            f"{tuple(v.shape)} and {tuple(faces.shape)}")
    if not np.issubdtype(faces.dtype, np.integer) or faces.min() < 0 or faces.max() >= len(v):
        raise ModelError(f"convex_parts: expected faces as integer indices in [0, {len(v)}), got "
                            f"{faces.dtype} in [{faces.min()}, {faces.max()}]")
    if not np.isfinite(v).all():
        raise NonFiniteError("convex_parts: expected finite vertices, got NaN or inf")
    mesh = _Mesh(v[faces], tolerance)
    parts = mesh.parts = [_Part(mesh, mesh.T)]
    while True:
        while len(parts) < max_parts:
            k = int(np.argmax([p.excess if p.splittable else -1.0 for p in parts]))
            if not parts[k].splittable or parts[k].excess <= tolerance:
                break
            children = parts[k].split()
            if children is None:
                parts[k].splittable = False
                continue
            parts[k:k + 1] = children
        # a part's cut faces were measured against the parts of their time: again against the final ones
        before = [p.excess for p in parts]
        for p in parts:
            p._excess = None
        if len(parts) >= max_parts or all(p.excess <= max(b, tolerance) for p, b in zip(parts, before)):
            break
    return ConvexParts([p.vertices for p in parts], max(p.excess for p in parts))


def bisected(T: np.ndarray, longest: float) -> tuple[np.ndarray, np.ndarray]:
    """``(T' (F', 3, 3), source (F',))``: the triangles ``T (F, 3, 3)`` bisected at the midpoint of their
    longest edge until no edge is longer than ``longest`` (the same surface; about 2·area/longest²
    triangles however thin the input's), and the input triangle each piece comes from."""
    done, src = [], []
    T = np.asarray(T, dtype=np.float64).reshape(-1, 3, 3)
    idx = np.arange(len(T))
    while len(T):
        e = np.linalg.norm(T[:, [1, 2, 0]] - T, axis=-1)  # edge k runs from corner k to corner k + 1
        k = e.argmax(1)
        long = e[np.arange(len(T)), k] > longest
        done.append(T[~long])
        src.append(idx[~long])
        T, k, idx = T[long], k[long], idx[long]
        R = np.take_along_axis(T, ((k[:, None] + np.arange(3)) % 3)[:, :, None], 1)  # longest edge: 0 -> 1
        m = 0.5 * (R[:, 0] + R[:, 1])
        T = np.concatenate((np.stack((R[:, 0], m, R[:, 2]), 1), np.stack((m, R[:, 1], R[:, 2]), 1)))
        idx = np.concatenate((idx, idx))
    return np.concatenate(done) if done else T, np.concatenate(src) if src else idx


def winding_number(p: np.ndarray, T: np.ndarray, *, chunk: int = 1 << 20) -> np.ndarray:
    """The generalised winding number ``(P,)`` of the triangles ``T (F, 3, 3)`` at points ``p (P, 3)``:
    Σ Ω_f / 4π with Ω_f the signed solid angle of triangle f (Van Oosterom and Strackee 1983): ±1 inside a
    closed surface, 0 outside, graded across holes and cracks (Jacobson, Kavan and Sorkine-Hornung 2013)."""
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    out = np.empty(len(p))
    step = max(1, chunk // max(1, len(T)))
    for s in range(0, len(p), step):
        X = T[None] - p[s:s + step, None, None]  # (P, F, 3, 3): the corners seen from each point
        a, b, c = X[..., 0, :], X[..., 1, :], X[..., 2, :]
        la, lb, lc = (np.sqrt(np.einsum("...i,...i->...", x, x)) for x in (a, b, c))
        det = np.einsum("...i,...i->...", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("...i,...i->...", a, b) * lc + np.einsum("...i,...i->...", b, c) * la \
            + np.einsum("...i,...i->...", c, a) * lb
        out[s:s + step] = np.arctan2(det, den).sum(-1) / (2.0 * math.pi)
    return out


class _Mesh:
    """The mesh as measured: its triangles ``T``, the corners of their bisection to edges of at most
    ``s = tolerance / 2`` in a k-d tree (each with the triangle it lies on), and the tolerance; ``s`` is
    also the hulls' sample spacing."""

    def __init__(self, T: np.ndarray, tolerance: float):
        spatial = require("scipy.spatial", "collision", "convex decomposition of meshes")
        self.T, self.tolerance, self.spatial = T, tolerance, spatial
        self.s = tolerance / 2.0
        B, src = bisected(T, self.s)
        #: points closer than this may be merged (:meth:`unique`: 2^-20 of the mesh's extent)
        self.lo = T.reshape(-1, 3).min(0)
        self.q = max(float((T.reshape(-1, 3).max(0) - self.lo).max()), 1e-300) * 2.0 ** -20
        keep = self.unique(B.reshape(-1, 3))  # (a bisection corner is shared by about 6 pieces)
        self.corners = B.reshape(-1, 3)[keep]
        self.source = np.repeat(src, 3)[keep]  # the triangle each corner lies on
        self.tree = spatial.cKDTree(self.corners)
        #: a sample passes within this distance (its sampled excess plus the spacing's s/√3 of the hull and
        #: the merging of points of a cell of side q, √3 q, for the samples and for the corners)
        self.limit = tolerance - self.s / math.sqrt(3.0) - 2.0 * math.sqrt(3.0) * self.q
        self.flat = 1e-9 * (1.0 + float(np.abs(T).max()))  # a sample this close to a cut lies on it

    def unique(self, P: np.ndarray) -> np.ndarray:
        """Indices of one point of ``P (N, 3)`` per occupied cube of side :attr:`q` (a 21-bit grid per
        coordinate over the mesh's box, one int64 key: a sort, not np.unique's row comparison)."""
        g = np.clip(np.floor((P - self.lo) / self.q), 0, (1 << 21) - 1).astype(np.int64)
        return np.unique((g[:, 0] << 42) | (g[:, 1] << 21) | g[:, 2], return_index=True)[1]

    def excess(self, samples: np.ndarray) -> tuple[float, np.ndarray | None]:
        """The largest distance of the ``samples`` to the surface when it is above :attr:`limit`, with the
        mesh point nearest the worst sample; else an upper bound of the largest distance and None.

        The distance to the nearest bisection corner is an upper bound (every surface point lies within
        s/√3 of a corner); where it is above the limit, the distance to the triangles of the 4 nearest
        corners (exact but for a nearest triangle among none of them) replaces it, farthest first: the
        first sample outside the mesh is the worst one."""
        samples = samples[self.unique(samples)]
        # (bounded: a far sample's nearest corner costs a deep search, and the far ones are measured below)
        d, _ = self.tree.query(samples, distance_upper_bound=self.limit)
        far = np.flatnonzero(~np.isfinite(d))
        k = min(4, len(self.corners))
        d4, near4 = (a.reshape(len(far), k) for a in self.tree.query(samples[far], k))
        d[far] = d4[:, 0]
        order = np.argsort(-d[far], kind="stable")
        far, near4 = far[order], near4[order]
        for s in range(0, len(far), 512):
            idx, near = far[s:s + 512], near4[s:s + 512]
            dd, xx = point_triangle(samples[idx, None], self.T[self.source[near]])
            j = dd.argmin(1)
            r = np.arange(len(idx))
            d[idx] = np.minimum(d[idx], dd[r, j])
            bad = d[idx] > self.limit
            if bad.any():  # inside the mesh (a hole's or a crack's far side): not beyond it
                bad[bad] = np.abs(winding_number(samples[idx[bad]], self.T)) < 0.5
            if bad.any():
                i = int(np.argmax(np.where(bad, d[idx], -1.0)))
                return float(d[idx[i]]), (samples[idx[i]], xx[i, j[i]])
        return float(d[d <= self.limit].max(initial=0.0)), None


def point_triangle(p: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(d (...), x (..., 3))``: the distance of points ``p (..., 3)`` to triangles ``T (..., 3, 3)``
    (broadcast) and the nearest point: the foot on the plane where it falls inside the triangle, else the
    nearest of the three edges' nearest points (a degenerate triangle: its edges)."""
    a, b, c = T[..., 0, :], T[..., 1, :], T[..., 2, :]
    n = np.cross(b - a, c - a)
    nn = np.einsum("...i,...i->...", n, n)
    ok = nn > 0
    foot = p - (np.einsum("...i,...i->...", p - a, n) / np.where(ok, nn, 1.0))[..., None] * n
    inside = ok
    for u, w in ((a, b), (b, c), (c, a)):  # the foot on the inner side of every edge
        inside = inside & (np.einsum("...i,...i->...", np.cross(w - u, foot - u), n) >= 0)
    best = np.where(inside[..., None], foot, a)
    dist = np.linalg.norm(p - best, axis=-1)
    for u, w in ((a, b), (b, c), (c, a)):
        e = w - u
        ee = np.einsum("...i,...i->...", e, e)
        t = np.clip(np.einsum("...i,...i->...", p - u, e) / np.where(ee > 0, ee, 1.0), 0.0, 1.0)
        q = u + t[..., None] * e
        dq = np.linalg.norm(p - q, axis=-1)
        closer = ~inside & (dq < dist)
        best, dist = np.where(closer[..., None], q, best), np.where(closer, dq, dist)
    return dist, best


class _Part:
    """A part: its triangles ``T (F, 3, 3)`` (pieces of the mesh's), their hull (``vertices``, ``faces``,
    ``volume``) and, on demand, its ``excess`` and worst sample."""

    def __init__(self, mesh: _Mesh, T: np.ndarray, planes: tuple = ()):
        self.mesh, self.T, self.planes = mesh, T, planes  # planes: the cuts (n, offset) that bound it
        self.points = T.reshape(-1, 3)  # (with repeats: Qhull ignores them)
        self.vertices, self.faces, self.volume, self.equations = _hull(self.points, mesh.spatial)
        self.splittable = len(T) > 1
        self._excess: tuple | None = None

    @property
    def excess(self) -> float:
        if self._excess is None:
            self._excess = self._measure()
        return self._excess[0]

    def _measure(self) -> tuple[float, np.ndarray | None]:
        m = self.mesh
        for s in (4.0 * m.s, m.s):  # coarse first: one sample far outside condemns the part
            samples = np.concatenate((self.vertices, bisected(self.faces, s)[0].reshape(-1, 3)))
            covered = np.zeros(len(samples), dtype=bool)
            for n, off in self.planes:  # a point of a cut's face is inside the union where a part across
                on = np.flatnonzero(np.abs(samples @ n - off) <= m.flat)  # the cut holds it
                if len(on) == 0:
                    continue
                across = samples[on] - math.copysign(m.q, float(self.points.mean(0) @ n - off)) * n
                for q in m.parts:
                    if q is not self and q.equations is not None:
                        eq = q.equations
                        covered[on] |= (across @ eq[:, :3].T + eq[:, 3] <= 0).all(1)
            samples = samples[~covered]
            e, worst = m.excess(samples)
            if worst is not None:
                break
        return e + m.s / math.sqrt(3.0), worst

    def split(self) -> list | None:
        """The two parts of the best cut (module docstring), or None when no plane separates triangles."""
        P = self.points
        _, _, vt = np.linalg.svd(P - P.mean(0), full_matrices=False)
        worst = self._excess[1] if self._excess is not None else None
        best = None
        if worst is not None:
            x = worst[0]  # the worst sample, and the points f of the part's own triangles nearest to it
            dd, ff = point_triangle(x[None], self.T)
            gap = float(dd.min())
            near = dd <= gap + self.mesh.flat  # (ties: the U's slot has two walls and a floor)
            u = (x - ff[near]) / np.maximum(dd[near], 1e-300)[:, None]
            first = [_Cut(self, w, float(f @ w), x) for w, f in zip(u, ff[near])]
            first = [c for c in first if c.ok]
            top = max(first, key=lambda c: (c.cleared, -c.volume), default=None)
            if top is not None and (top.cleared >= 0.5 * (gap - self.mesh.tolerance)
                                    or top.smaller >= 0.01 * self.volume):
                best = top
            else:  # every such plane leaves x covered: the plane through f that uncovers it most
                f = ff[int(dd.argmin())]
                walls = dd <= gap + self.mesh.s  # the mesh's own planes there
                n = np.cross(self.T[walls, 1] - self.T[walls, 0], self.T[walls, 2] - self.T[walls, 0])
                n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
                cuts = first + [_Cut(self, w, float(f @ w), x) for w in (*n, *np.eye(3), *vt)]
                cuts = [c for c in cuts if c.ok and c.cleared > 0]
                if cuts:
                    best = max(cuts, key=lambda c: (c.cleared, -c.volume))
        if best is None:  # no worst sample, or no plane through f uncovers it: the principal axes' cuts
            cuts = []
            for n in vt:
                t = P @ n
                lo, hi = float(t.min()), float(t.max())
                cuts += [_Cut(self, n, float(off)) for off in lo + (hi - lo) * _CUTS]
            cuts = [c for c in cuts if c.ok]
            if not cuts:
                return None
            best = min(cuts, key=lambda c: c.volume)
        planes = self.planes + ((best.n, best.off),)
        return [_Part(self.mesh, T, planes) for T in _clip(self.T, best.n, best.off)]


class _Cut:
    """A candidate cut of a part by the plane n·x = off: ``ok`` (a triangle on each side), the two sides'
    total hull ``volume`` and, given the worst sample x, ``cleared``: x's distance to the nearer side's
    hull (0 where a side's hull still covers it)."""

    def __init__(self, part: _Part, n: np.ndarray, off: float, x: np.ndarray | None = None):
        self.n, self.off = n, off
        sides = _sides(part.T, n, off)
        self.ok = sides is not None
        self.volume, self.cleared, self.smaller = math.inf, 0.0, 0.0
        if not self.ok:
            return
        hulls = [_hull(np.concatenate(s), part.mesh.spatial) for s in sides]
        self.volume = sum(h[2] for h in hulls)
        self.smaller = min(h[2] for h in hulls)
        if x is not None:
            self.cleared = min(_hull_distance(x, h[1], h[3]) for h in hulls)


def _hull(points: np.ndarray, spatial):
    """``(vertices (M, 3), triangles (K, 3, 3), volume, equations (K, 4) or None)`` of the points' convex hull
    (Qhull; its outward facet planes n·x + d ≤ 0 inside); a flat or degenerate set: its points, the fan of
    its planar hull (none when collinear), volume 0 and no planes."""
    try:
        h = spatial.ConvexHull(points)
    except (spatial.QhullError, ValueError):
        return points, _flat_fan(points, spatial), 0.0, None
    return points[h.vertices], points[h.simplices], float(h.volume), h.equations


def _hull_distance(x: np.ndarray, triangles: np.ndarray, equations) -> float:
    """The distance of the point x to a hull of :func:`_hull` (0 inside; a collinear set counts as 0)."""
    if equations is not None and (equations[:, :3] @ x + equations[:, 3] <= 0).all():
        return 0.0
    if len(triangles) == 0:
        return 0.0
    return float(point_triangle(x[None], triangles)[0].min())


def _flat_fan(points: np.ndarray, spatial) -> np.ndarray:
    """The triangles ``(K, 3, 3)`` of a fan over the hull of coplanar points (none if collinear)."""
    c = points.mean(0)
    _, sv, vt = np.linalg.svd(points - c, full_matrices=False)
    if len(sv) < 2 or sv[1] <= 1e-12 * max(float(sv[0]), 1e-300):
        return np.zeros((0, 3, 3))
    try:
        ring = points[spatial.ConvexHull((points - c) @ vt[:2].T).vertices]  # (counter-clockwise in 2D)
    except (spatial.QhullError, ValueError):
        return np.zeros((0, 3, 3))
    return np.stack([np.broadcast_to(ring[0], ring[1:-1].shape), ring[1:-1], ring[2:]], 1)


def _sides(T: np.ndarray, n: np.ndarray, off: float) -> tuple | None:
    """The points of either side of the plane n·x = off as :func:`_clip` divides the triangles (each side's
    corners and the points where edges cross the plane; a triangle on the plane with the side its back
    faces), or None when one side would hold no triangle."""
    s, both, first, second = _divide(T, n, off)
    if not (s > 0).any() or not (s < 0).any():  # (a corner strictly on each side: a piece on each)
        return None
    a, b = T[both], T[both][:, [1, 2, 0]]
    sa, sb = s[both], s[both][:, [1, 2, 0]]
    cross = sa * sb < 0
    x = a[cross] + (sa[cross] / (sa[cross] - sb[cross]))[:, None] * (b[cross] - a[cross])
    return (T[first].reshape(-1, 3), a[sa >= 0], x), (T[second].reshape(-1, 3), a[sa <= 0], x)


def _divide(T: np.ndarray, n: np.ndarray, off: float):
    """``(s (F, 3), crossing, positive, negative)``: the corners' signed offsets from the plane n·x = off,
    the triangles with a corner strictly on each side, and those wholly on the positive and on the negative
    side, where a triangle on the plane goes to the side its back faces (the solid's side of an outward
    normal)."""
    s = T @ n - off
    pos, neg = (s > 0).any(1), (s < 0).any(1)
    both = pos & neg
    flat = ~pos & ~neg & (np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]) @ n > 0)
    return s, both, ~both & ~neg & ~flat, (~both & neg) | flat


def _clip(T: np.ndarray, n: np.ndarray, off: float) -> tuple[np.ndarray, np.ndarray]:
    """The triangles ``T`` clipped by the plane n·x = off: ``(T_pos, T_neg)``, those on each side (a triangle
    on the plane goes to the side behind its normal) with each crossing triangle's two pieces triangulated."""
    s, both, first, second = _divide(T, n, off)
    out = ([T[first]], [T[second]])
    for tri, st in zip(T[both], s[both]):
        for side, sign in ((0, 1.0), (1, -1.0)):
            poly = []
            for k in range(3):  # Sutherland-Hodgman against one half-space
                j = (k + 1) % 3
                a, b, sa, sb = tri[k], tri[j], sign * st[k], sign * st[j]
                if sa >= 0:
                    poly.append(a)
                if sa * sb < 0:
                    poly.append(a + (sa / (sa - sb)) * (b - a))
            poly = np.asarray(poly)
            out[side].append(np.stack([np.broadcast_to(poly[0], poly[1:-1].shape), poly[1:-1], poly[2:]], 1))
    return np.concatenate(out[0]), np.concatenate(out[1])
