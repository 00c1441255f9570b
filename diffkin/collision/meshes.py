"""Mesh collision geometry: resolving URDF mesh file names and fitting a set of enclosing capsules (trimesh).

A mesh becomes up to ``max_capsules`` capsules (:func:`capsules_of_triangles`), chosen greedily. Triangles
with an edge longer than 1/8 of the mesh's extent are first split at their edges' midpoints (the same
surface: a triangle belongs whole to one part, so a long one, as a convex hull has, would stretch its
part). Start with one part, all triangles, and its capsule: along one of the principal axes (PCA) of its
vertices, the one of least volume, with the smallest radius and the shortest axis on that line that
enclose them. A part's best cut divides its triangles by their centroids' position along one of its
principal axes, at one of the quantiles 1/8 … 7/8, choosing the cut whose two capsules cover the least
volume. While there are fewer than ``max_capsules`` parts, make the cut that shrinks the union's volume
most, if it shrinks it by at least ``min_gain`` (default 1 %). Volumes are counted on a fixed 20³ grid
over the mesh's bounding box (grown by a quarter of its size): deterministic, no random seeds.

Each triangle belongs whole to one part, so every triangle (and every vertex) lies in its part's capsule,
which is convex: the union contains the mesh surface, and no distance to the set exceeds the distance to
the mesh (conservative). ``max_capsules=1`` gives the single enclosing capsule. On the Panda's collision
meshes the default set has 2-4 capsules per link, and its distances to points outside a link are a median
8-21 mm below coal's distance to the true mesh (one capsule: 10-39 mm; docs/collision.md).
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np

from ..errors import OptionError, require
from ..validation import check_count, check_number

__all__ = ["resolve_mesh", "fit_capsules", "capsules_of_triangles", "capsule_of_points", "hull_vertices",
           "convex_parts_of_file"]

#: a watertight mesh whose volume is within this fraction of its hull's counts as convex (the Panda's
#: collision meshes, convex but for rounding, are within 3e-4)
CONVEX_VOLUME_FRACTION = 1e-3

_CUTS = np.arange(1, 8) / 8.0  # the candidate cut quantiles along a part's principal axis


def resolve_mesh(filename: str, base_dir: Path | None, package_dirs=()) -> Path | None:
    """The file a URDF ``<mesh filename>`` names, or None if it does not exist here.

    ``package://PKG/rest`` is looked up as ``D/PKG/rest`` and, where D's name is PKG, ``D/rest`` for D in
    ``package_dirs`` and the URDF's directory and its ancestors; ``file://`` and plain paths are taken as
    they are, relative ones from the URDF's directory.
    """
    if filename.startswith("package://"):
        pkg, _, rest = filename[len("package://"):].partition("/")
        roots = [Path(d) for d in package_dirs]
        if base_dir is not None:
            roots += [base_dir, *base_dir.parents]
        for d in roots:
            for cand in (d / pkg / rest, d / rest if d.name == pkg else None):
                if cand is not None and cand.is_file():
                    return cand
        return None
    path = Path(filename[len("file://"):] if filename.startswith("file://") else filename)
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    return path if path.is_file() else None


def fit_capsules(path: Path, scale=(1.0, 1.0, 1.0), *, max_capsules: int = 4,
                 min_gain: float = 0.01) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """``[(a (3,), b (3,), radius)]``: the fitted capsule set of the mesh at ``path`` (mesh frame, scaled;
    the module docstring gives the rule). A file named again (a hand's four fingers) is fitted once while
    it is unchanged."""
    max_capsules = check_count(max_capsules, "max_capsules")
    min_gain = check_number(min_gain, "min_gain", positive=False)  # (the range: capsules_of_triangles)
    key = (str(Path(path).resolve()), Path(path).stat().st_mtime_ns,
           tuple(float(x) for x in np.broadcast_to(np.asarray(scale, dtype=np.float64), 3)))
    return [(a.copy(), b.copy(), r) for a, b, r in _fit_file(*key, max_capsules, min_gain)]


def hull_vertices(path: Path, scale=(1.0, 1.0, 1.0)) -> tuple[np.ndarray, bool]:
    """``(V (M, 3), convex)``: the vertices of the convex hull of the mesh at ``path`` (mesh frame, scaled;
    trimesh's Qhull) and whether the mesh is convex itself (watertight, its volume within
    :data:`CONVEX_VOLUME_FRACTION` of the hull's). Cached per file while it is unchanged."""
    key = (str(Path(path).resolve()), Path(path).stat().st_mtime_ns,
           tuple(float(x) for x in np.broadcast_to(np.asarray(scale, dtype=np.float64), 3)))
    V, convex = _hull_file(*key)
    return V.copy(), convex


def convex_parts_of_file(path: Path, scale=(1.0, 1.0, 1.0), *, tolerance: float = 0.002,
                        max_parts: int = 128):
    """:class:`~diffkin.collision.decompose.ConvexParts` of the mesh at ``path`` (mesh frame, scaled):
    :func:`~diffkin.collision.decompose.convex_parts` of its triangles. Cached per file while it is
    unchanged (the decomposition takes seconds to minutes)."""
    from .decompose import ConvexParts

    key = (str(Path(path).resolve()), Path(path).stat().st_mtime_ns,
           tuple(float(x) for x in np.broadcast_to(np.asarray(scale, dtype=np.float64), 3)))
    r = _parts_file(*key, check_number(tolerance, "tolerance"), check_count(max_parts, "max_parts"))
    return ConvexParts([v.copy() for v in r.parts], r.excess)


@functools.lru_cache(maxsize=64)
def _parts_file(path: str, mtime: int, scale: tuple, tolerance: float, max_parts: int):
    from .decompose import convex_parts

    trimesh = require("trimesh", "collision", "mesh collision geometry")
    mesh = trimesh.load(path, force="mesh")
    mesh.vertices = np.asarray(mesh.vertices, dtype=np.float64) * np.asarray(scale, dtype=np.float64)
    mesh.merge_vertices()
    return convex_parts(mesh.vertices, mesh.faces, tolerance=tolerance, max_parts=max_parts)


@functools.lru_cache(maxsize=256)
def _hull_file(path: str, mtime: int, scale: tuple) -> tuple[np.ndarray, bool]:
    trimesh = require("trimesh", "collision", "mesh collision geometry")
    mesh = trimesh.load(path, force="mesh")
    mesh.vertices = np.asarray(mesh.vertices, dtype=np.float64) * np.asarray(scale, dtype=np.float64)
    mesh.merge_vertices()
    hull = mesh.convex_hull
    convex = bool(mesh.is_watertight) and abs(hull.volume) > 0 and \
        1.0 - abs(mesh.volume) / abs(hull.volume) <= CONVEX_VOLUME_FRACTION
    return np.asarray(hull.vertices, dtype=np.float64), convex


@functools.lru_cache(maxsize=256)
def _fit_file(path: str, mtime: int, scale: tuple, max_capsules: int, min_gain: float) -> tuple:
    trimesh = require("trimesh", "collision", "mesh collision geometry")
    mesh = trimesh.load(path, force="mesh")
    v = np.asarray(mesh.vertices, dtype=np.float64) * np.asarray(scale, dtype=np.float64)
    return tuple(capsules_of_triangles(v, np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3),
                                       max_capsules=max_capsules, min_gain=min_gain))


def capsules_of_triangles(v: np.ndarray, faces: np.ndarray, *, max_capsules: int = 4,
                          min_gain: float = 0.01) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """The fitted capsule set of the triangles ``faces (F, 3)`` (indices into ``v (N, 3)``); without faces,
    the one enclosing capsule of the points. Module docstring: the rule."""
    max_capsules = check_count(max_capsules, "max_capsules")
    if check_number(min_gain, "min_gain", positive=False) >= 1.0:
        raise OptionError(f"expected min_gain as a fraction in [0, 1), got {min_gain!r}")
    if len(faces) == 0:
        return [capsule_of_points(v)]
    v, faces = _subdivided(v, faces, float(np.ptp(v, axis=0).max()) / 8.0)
    grid = _grid(v)
    parts = [_Part(v, faces, np.arange(len(faces)), grid)]
    while len(parts) < max_capsules:
        masks = [p.inside for p in parts]
        covered = np.logical_or.reduce(masks)
        gains = []
        for k, p in enumerate(parts):  # the union's volume (grid points) a part's best cut would remove
            if p.children() is None:
                gains.append(-1)
                continue
            rest = np.logical_or.reduce(masks[:k] + masks[k + 1:] + [c.inside for c in p.children()])
            gains.append(int(covered.sum()) - int(rest.sum()))
        best = int(np.argmax(gains))
        if gains[best] <= 0 or gains[best] < min_gain * covered.sum():
            break
        parts[best:best + 1] = parts[best].children()
    return [p.capsule for p in parts]


def _grid(v: np.ndarray, n: int = 20) -> np.ndarray:
    """``(n³, 3)`` cell centres over the points' bounding box grown by a quarter of its size on each side
    (room for the capsules' caps): the grid that measures the capsules' union volume."""
    lo, hi = v.min(0), v.max(0)
    pad = 0.25 * (hi - lo).max()
    axes = [np.linspace(a - pad, b + pad, n) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def _subdivided(v: np.ndarray, faces: np.ndarray, longest: float) -> tuple[np.ndarray, np.ndarray]:
    """The same surface with no edge longer than ``longest`` (a few rounds of midpoint splits into four):
    a triangle belongs whole to one part, so a long one (a convex hull's) would stretch its part."""
    for _ in range(8):
        tri = v[faces]  # (F, 3, 3)
        long = np.linalg.norm(tri - tri[:, [1, 2, 0]], axis=-1).max(-1) > longest
        if not long.any():
            break
        t = tri[long]
        mid = 0.5 * (t + t[:, [1, 2, 0]])  # midpoints of edges 01, 12, 20
        corners = [(t[:, 0], mid[:, 0], mid[:, 2]), (mid[:, 0], t[:, 1], mid[:, 1]),
                   (mid[:, 2], mid[:, 1], t[:, 2])]
        quads = np.stack([np.stack(c, 1) for c in corners] + [mid], 1).reshape(-1, 3, 3)
        tri = np.concatenate((tri[~long], quads))
        v, faces = np.unique(tri.reshape(-1, 3), axis=0, return_inverse=True)
        faces = faces.reshape(-1, 3)
    return v, faces


class _Part:
    """Triangles (indices ``idx``) of one part: their ``capsule``, the grid points ``inside`` it, and
    (on demand) the two parts of its best cut, the one whose capsules cover the fewest grid points."""

    def __init__(self, v, faces, idx, grid):
        self.v, self.faces, self.idx, self.grid = v, faces, idx, grid
        used = np.zeros(len(v), dtype=bool)  # the part's vertices, in index order (as np.unique, faster)
        used[faces[idx].ravel()] = True
        self.capsule = capsule_of_points(v[used])
        self.inside = _inside(grid, self.capsule)
        self._children: list | None | bool = False

    def children(self) -> list | None:
        if self._children is False:
            self._children = self._best_cut()
        return self._children

    def _best_cut(self) -> list | None:
        if len(self.idx) < 2:
            return None
        c = self.v[self.faces[self.idx]].mean(1)
        _, _, vt = np.linalg.svd(c - c.mean(0), full_matrices=False)
        best, covered = None, math.inf
        for axis in vt:
            t = (c - c.mean(0)) @ axis
            for cut in np.unique(np.quantile(t, _CUTS)):
                lo, hi = self.idx[t <= cut], self.idx[t > cut]
                if len(lo) == 0 or len(hi) == 0:
                    continue
                pair = [_Part(self.v, self.faces, s, self.grid) for s in (lo, hi)]
                n = int((pair[0].inside | pair[1].inside).sum())
                if n < covered:
                    best, covered = pair, n
        return best


def _inside(p: np.ndarray, capsule) -> np.ndarray:
    """Which points ``p (M, 3)`` lie in the capsule (squared distances: no square roots)."""
    a, b, r = capsule
    d = b - a
    pa = p - a
    t = np.clip(pa @ d / max(float(d @ d), 1e-300), 0.0, 1.0)
    e = pa - t[:, None] * d
    return np.einsum("ij,ij->i", e, e) <= r * r


def _volume(capsule) -> float:
    a, b, r = capsule
    return math.pi * r * r * (float(np.linalg.norm(b - a)) + 4.0 * r / 3.0)


def capsule_of_points(v: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The enclosing capsule of points ``(N, 3)`` along their principal axis, with the smallest radius and
    the shortest axis on that line that enclose every point."""
    c = v.mean(0)
    _, _, vt = np.linalg.svd(v - c, full_matrices=False)
    return min((_capsule_along(v, c, u) for u in vt), key=_volume)


def _capsule_along(v: np.ndarray, c: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The enclosing capsule of points ``v`` whose axis lies on the line ``c + t u``."""
    along = (v - c) @ u
    radial = np.linalg.norm((v - c) - along[:, None] * u, axis=1)
    r = float(radial.max())
    reach = np.sqrt(np.maximum(r * r - radial**2, 0.0))
    t0, t1 = float((along + reach).min()), float((along - reach).max())  # every point within r of [t0, t1]
    if t0 > t1:  # shorter than wide: any centre in [t1, t0] is within r of every point (|s - along| <= reach)
        centre = c + 0.5 * (t0 + t1) * u
        return centre, centre, r
    return c + t0 * u, c + t1 * u, r
