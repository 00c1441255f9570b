"""Mesh collision geometry: resolving URDF mesh file names and fitting a set of enclosing capsules (trimesh).

A mesh becomes up to ``max_capsules`` capsules (:func:`capsules_of_triangles`), chosen greedily: start with
the one capsule along the principal axis (PCA) of all the triangles' vertices, with the smallest radius
and the shortest axis on that line that enclose them; then, while there are fewer than ``max_capsules``,
split the part whose best cut saves the most capsule volume, if that saving is at least ``min_gain`` of the
part's capsule volume. A cut divides a part's triangles by their centroids' position along the part's own
principal axis, at one of the quantiles 1/8 … 7/8, and keeps the cut with the smallest sum of the two
capsules' volumes. Each triangle belongs whole to one part, so every triangle (and every vertex) lies in
its part's capsule, which is convex: the union contains the mesh surface (conservative). The rule is
deterministic (no random seeds); ``max_capsules=1`` gives the single enclosing capsule.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..errors import OptionError, require
from ..validation import check_count, check_number

__all__ = ["resolve_mesh", "fit_capsules", "capsules_of_triangles", "capsule_of_points"]

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
                 min_gain: float = 0.03) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """``[(a (3,), b (3,), radius)]``: the fitted capsule set of the mesh at ``path`` (mesh frame, scaled;
    the module docstring gives the rule)."""
    trimesh = require("trimesh", "collision", "mesh collision geometry")
    mesh = trimesh.load(str(path), force="mesh")
    v = np.asarray(mesh.vertices, dtype=np.float64) * np.asarray(scale, dtype=np.float64)
    return capsules_of_triangles(v, np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3),
                                 max_capsules=max_capsules, min_gain=min_gain)


def capsules_of_triangles(v: np.ndarray, faces: np.ndarray, *, max_capsules: int = 4,
                          min_gain: float = 0.03) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """The fitted capsule set of the triangles ``faces (F, 3)`` (indices into ``v (N, 3)``); without faces,
    the one enclosing capsule of the points. Module docstring: the rule."""
    max_capsules = check_count(max_capsules, "max_capsules")
    if check_number(min_gain, "min_gain", positive=False) >= 1.0:
        raise OptionError(f"expected min_gain as a fraction in [0, 1), got {min_gain!r}")
    if len(faces) == 0:
        return [capsule_of_points(v)]
    centroids = v[faces].mean(1)
    parts = [_Part(v, faces, np.arange(len(faces)), centroids)]
    while len(parts) < max_capsules:
        best = max(range(len(parts)), key=lambda k: parts[k].gain)
        if parts[best].gain < min_gain * parts[best].volume:
            break
        part = parts.pop(best)
        parts[best:best] = [_Part(v, faces, idx, centroids) for idx in part.split]
    return [p.capsule for p in parts]


class _Part:
    """Triangles (indices) of one part: their capsule, its volume, and the best cut (``split``, ``gain``)."""

    def __init__(self, v, faces, idx, centroids):
        self.capsule = capsule_of_points(v[np.unique(faces[idx])])
        self.volume = _volume(self.capsule)
        self.split, self.gain = None, -math.inf
        if len(idx) < 2:
            return
        c = centroids[idx]
        _, _, vt = np.linalg.svd(c - c.mean(0), full_matrices=False)
        for axis in vt:
            t = (c - c.mean(0)) @ axis
            for cut in np.unique(np.quantile(t, _CUTS)):
                lo, hi = idx[t <= cut], idx[t > cut]
                if len(lo) == 0 or len(hi) == 0:
                    continue
                total = sum(_volume(capsule_of_points(v[np.unique(faces[s])])) for s in (lo, hi))
                if self.volume - total > self.gain:
                    self.split, self.gain = (lo, hi), self.volume - total


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
