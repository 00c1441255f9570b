"""Mesh collision geometry: resolving URDF mesh file names and fitting enclosing capsules (trimesh).

A mesh becomes one capsule along the principal axis of its convex hull's vertices (PCA), with the smallest
radius and the shortest axis on that line that enclose every vertex: conservative (the capsule contains the
mesh's convex hull), exact for a capsule-shaped mesh, loose for flat or L-shaped ones (the docs quote the
volume ratio for the Panda's meshes).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import require

__all__ = ["resolve_mesh", "fit_capsule"]


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


def fit_capsule(path: Path, scale=(1.0, 1.0, 1.0)) -> tuple[np.ndarray, np.ndarray, float]:
    """``(a (3,), b (3,), radius)``: the enclosing capsule of the mesh at ``path`` (mesh frame, scaled)."""
    trimesh = require("trimesh", "collision", "mesh collision geometry")
    mesh = trimesh.load(str(path), force="mesh")
    v = np.asarray(mesh.vertices, dtype=np.float64) * np.asarray(scale, dtype=np.float64)
    if len(v) >= 4:
        try:
            v = np.asarray(mesh.convex_hull.vertices, dtype=np.float64) * np.asarray(scale)
        except Exception:  # a degenerate (flat) hull: the vertices themselves
            pass
    return capsule_of_points(v)


def capsule_of_points(v: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The enclosing capsule of points ``(N, 3)`` along their principal axis (see the module docstring)."""
    c = v.mean(0)
    _, _, vt = np.linalg.svd(v - c, full_matrices=False)
    u = vt[0]
    along = (v - c) @ u
    radial = np.linalg.norm((v - c) - along[:, None] * u, axis=1)
    r = float(radial.max())
    reach = np.sqrt(np.maximum(r * r - radial**2, 0.0))
    t0, t1 = float((along + reach).min()), float((along - reach).max())  # every point within r of [t0, t1]
    if t0 > t1:  # shorter than wide: any centre in [t1, t0] is within r of every point (|s - along| <= reach)
        centre = c + 0.5 * (t0 + t1) * u
        return centre, centre, r
    return c + t0 * u, c + t1 * u, r
