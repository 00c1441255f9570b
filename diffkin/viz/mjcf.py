"""What the viewer draws of an MJCF model: each body's visual geoms as triangle sets in the body frame.

:func:`mjcf_visuals` reads the model with MuJoCo's own parser (``mujoco.MjSpec``: default classes,
``childclass``, ``<include>``, frames and ``fromto`` all resolved by MuJoCo) and compiles it without its
asset files (:func:`diffkin.models.mjcf.compile_mjcf`'s recipe), so a model whose meshes are absent still
draws. Per geom of the groups MuJoCo's viewer shows by default (0, 1, 2):

* spheres, capsules, cylinders, boxes and ellipsoids become triangle sets of their compiled size;
* meshes whose files resolve (``<compiler meshdir>`` from the model file's folder; STL / OBJ / PLY read by
  trimesh, the ``viz`` extra) become their triangles, scaled as ``<mesh scale>`` says and decimated by
  vertex clustering to at most ``max_faces`` triangles; meshes whose files do not resolve are listed in
  ``missing`` and not drawn (the viewer's skeleton still shows those bodies);
* planes, height fields and SDFs are not drawn.

The vertices are in the geom frame as written in the file (MuJoCo's compiled model re-centres a mesh on its
inertia frame and moves the geom frame to match; before compiling, the file's vertices and the geom's
``pos`` / ``quat`` are the same placement), and ``local`` is the geom's pose in its body's frame. A geom's
world pose is ``body_poses(chain, q)[..., body, :, :] @ local``
(:func:`diffkin.models.mjcf_bodies.body_poses`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DiffkinError

__all__ = ["VisualGeom", "mjcf_visuals"]

_SPHERE, _CAPSULE, _ELLIPSOID, _CYLINDER, _BOX, _MESH = 2, 3, 4, 5, 6, 7
_KINDS = {_SPHERE: "sphere", _CAPSULE: "capsule", _ELLIPSOID: "ellipsoid", _CYLINDER: "cylinder",
          _BOX: "box", _MESH: "mesh"}
_DEFAULT_RGBA = (0.5, 0.5, 0.5, 1.0)  # MuJoCo's geom rgba when none is given: then the material's counts


@dataclass(frozen=True, eq=False)
class VisualGeom:
    """One drawn geom: ``name`` (the MJCF name, unnamed ones ``"<body>/<i>"``), ``body`` (MuJoCo body id),
    ``kind``, ``local`` ``(4, 4)`` (geom in body frame), ``vertices`` ``(V, 3)`` float32 in the geom frame,
    ``faces`` ``(F, 3)`` int32, ``rgb`` (0-255), ``opacity``, ``source`` (the mesh file, for meshes)."""

    name: str
    body: int
    kind: str
    local: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    rgb: tuple[int, int, int]
    opacity: float
    source: str | None = None


def _trimesh():
    try:
        import trimesh
    except ImportError as exc:
        raise DiffkinError("drawing MJCF geoms needs trimesh: pip install 'diffkin[viz]'") from exc
    return trimesh


def _primitive(kind: int, size: np.ndarray):
    """Triangles ``(vertices, faces)`` of a primitive of MuJoCo size ``size``, centred, axis z."""
    tm = _trimesh().creation
    if kind == _SPHERE:
        m = tm.icosphere(subdivisions=2, radius=float(size[0]))
    elif kind == _ELLIPSOID:
        m = tm.icosphere(subdivisions=2, radius=1.0)
        m.vertices = m.vertices * size[:3]
    elif kind == _CAPSULE:  # trimesh: height = distance between the two sphere centres = 2 half-lengths
        m = tm.capsule(height=2.0 * float(size[1]), radius=float(size[0]), count=[16, 16])
    elif kind == _CYLINDER:
        m = tm.cylinder(radius=float(size[0]), height=2.0 * float(size[1]), sections=24)
    else:
        m = tm.box(extents=2.0 * size[:3])
    return np.asarray(m.vertices), np.asarray(m.faces)


def _decimate(vertices: np.ndarray, faces: np.ndarray, max_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """At most ``max_faces`` triangles by vertex clustering (Rossignac and Borrel): vertices in one cell of
    a grid are merged at their mean, collapsed and repeated triangles dropped; the cell doubles until the
    count fits. ``(V, 3)``, ``(F, 3)`` -> the same, float32 / int32."""
    v, f = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    if len(f) <= max_faces or len(v) == 0:
        return v.astype(np.float32), f.astype(np.int32)
    extent = float(np.ptp(v, axis=0).max()) or 1.0
    cell = extent / max(2.0, math.sqrt(max_faces / 2.0))  # a closed surface: ~2 faces per cell on it
    while True:
        keys = np.floor((v - v.min(axis=0)) / cell).astype(np.int64)
        _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        inverse = inverse.reshape(-1)
        merged = np.zeros((len(counts), 3))
        np.add.at(merged, inverse, v)
        merged /= counts[:, None]
        g = inverse[f]
        g = g[(g[:, 0] != g[:, 1]) & (g[:, 1] != g[:, 2]) & (g[:, 0] != g[:, 2])]
        g = np.unique(g, axis=0) if len(g) else g
        if len(g) <= max_faces:
            return merged.astype(np.float32), g.astype(np.int32).reshape(-1, 3)
        cell *= 1.5


def _mesh_files(spec, base: Path) -> dict[str, tuple[Path | None, np.ndarray, object]]:
    """Mesh asset name -> (resolved file or None, scale (3,), the spec mesh)."""
    meshdir = Path(spec.meshdir or "")
    out = {}
    for mesh in spec.meshes:
        found = None
        if mesh.file:
            for cand in (base / meshdir / mesh.file, base / mesh.file):
                if cand.is_file():
                    found = cand
                    break
        out[mesh.name] = (found, np.asarray(mesh.scale, dtype=np.float64), mesh)
    return out


def _mesh_triangles(found: Path | None, scale: np.ndarray, mesh) -> tuple[np.ndarray, np.ndarray] | None:
    """The mesh's triangles in the geom frame as the file (or inline ``vertex``/``face``) gives them."""
    trimesh = _trimesh()
    vert = np.asarray(mesh.uservert, dtype=np.float64).reshape(-1, 3)
    if found is not None:
        try:
            m = trimesh.load(str(found), force="mesh", process=False)
        except Exception:  # a file trimesh cannot read (e.g. MuJoCo's .msh): not drawn
            return None
        v, f = np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces)
    elif len(vert):
        face = np.asarray(mesh.userface, dtype=np.int64).reshape(-1, 3)
        if len(face):
            v, f = vert, face
        else:  # vertices only: MuJoCo uses their convex hull
            hull = trimesh.Trimesh(vert).convex_hull
            v, f = np.asarray(hull.vertices), np.asarray(hull.faces)
    else:
        return None
    if len(v) == 0 or len(f) == 0:
        return None
    v = v * scale
    refpos = np.asarray(mesh.refpos, dtype=np.float64)
    refquat = np.asarray(mesh.refquat, dtype=np.float64)
    if np.any(refpos != 0) or np.any(refquat != (1.0, 0.0, 0.0, 0.0)):  # vertices relative to a frame
        v = (v - refpos) @ _rotation(refquat)  # R^T (v - p), as rows
    return v, f


def _rotation(wxyz) -> np.ndarray:
    """MuJoCo's (w, x, y, z) quaternion as a rotation matrix (normalised first, as MuJoCo does)."""
    import torch

    from ..rotations import quaternion_to_matrix

    q = torch.as_tensor(np.asarray(wxyz, dtype=np.float64))
    return quaternion_to_matrix(q / q.norm()).numpy()


def _pose(pos, quat) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = _rotation(quat), pos
    return T


def _colour(m, g: int) -> tuple[tuple[int, int, int], float]:
    rgba = np.asarray(m.geom_rgba[g], dtype=np.float64)
    mat = int(m.geom_matid[g])
    if mat >= 0 and np.allclose(rgba, _DEFAULT_RGBA):
        rgba = np.asarray(m.mat_rgba[mat], dtype=np.float64)
    rgb = tuple(int(round(255 * float(c))) for c in np.clip(rgba[:3], 0.0, 1.0))
    return rgb, float(np.clip(rgba[3], 0.0, 1.0))


def mjcf_visuals(source, *, meshes: bool = True, groups=(0, 1, 2), fallback: bool = True,
                 max_faces: int = 2000) -> tuple[list[VisualGeom], list[str]]:
    """``(geoms, missing)``: the drawn geoms of an MJCF model (a path, XML text, or an
    :class:`~diffkin.models.mjcf.MJCFChain`, whose source is used) and the ``"geom (file)"`` of the mesh geoms
    not drawn because their files do not resolve (or ``meshes=False``). ``groups``: the geom groups drawn
    (MuJoCo's viewer shows 0-2 by default; Menagerie's collision geoms are group 3). ``fallback``: a body
    with a missing mesh also shows its primitive geoms of the other groups (its collision shapes), so a
    model shipped without meshes still has bodies. ``max_faces``: the triangle budget of each mesh. See
    the module doc for what is drawn and in which frame."""
    import mujoco

    from ..models.mjcf import _read_source, _strip_assets

    chain_source = getattr(source, "source_path", None) or getattr(source, "source_text", None)
    text, path = _read_source(chain_source if chain_source is not None else source)
    spec = mujoco.MjSpec.from_file(path) if path else mujoco.MjSpec.from_string(text)
    files = _mesh_files(spec, Path(path).resolve().parent if path else Path.cwd())
    mesh_of = [g.meshname if g.type == mujoco.mjtGeom.mjGEOM_MESH else None for g in spec.geoms]
    _strip_assets(spec)
    m = spec.compile()
    if len(mesh_of) != m.ngeom:  # MuJoCo compiles the spec's geoms in order; refuse to guess otherwise
        raise DiffkinError(f"MJCF geoms: {len(mesh_of)} in the spec, {m.ngeom} compiled")
    names, per_body = [], {}
    for g in range(m.ngeom):
        body = int(m.geom_bodyid[g])
        k = per_body.setdefault(body, 0)
        per_body[body] = k + 1
        names.append(m.geom(g).name or f"{m.body(body).name or f'body{body}'}/{k}")
    drawn, missing, lacking = {}, [], set()
    for g in range(m.ngeom):
        kind = _MESH if mesh_of[g] is not None else int(m.geom_type[g])  # stripped meshes compile as spheres
        if kind not in _KINDS or int(m.geom_group[g]) not in groups:
            continue
        geom = _visual(m, g, names[g], kind, files.get(mesh_of[g]) if meshes else None, max_faces)
        if geom is None:
            mesh = files.get(mesh_of[g])
            missing.append(f"{names[g]} ({mesh[2].file if mesh is not None else mesh_of[g]})")
            lacking.add(int(m.geom_bodyid[g]))
        else:
            drawn[g] = geom
    for g in range(m.ngeom) if fallback else ():
        kind = int(m.geom_type[g])
        if (int(m.geom_bodyid[g]) in lacking and mesh_of[g] is None and kind in _KINDS
                and int(m.geom_group[g]) not in groups):
            drawn[g] = _visual(m, g, names[g], kind, None, max_faces)
    return [drawn[g] for g in sorted(drawn)], missing


def _visual(m, g: int, name: str, kind: int, mesh_file, max_faces: int) -> VisualGeom | None:
    """Geom g of the compiled model as a :class:`VisualGeom`; None for a mesh that does not resolve."""
    source_file = None
    if kind == _MESH:
        tri = _mesh_triangles(*mesh_file) if mesh_file is not None else None
        if tri is None:
            return None
        v, f = _decimate(*tri, max_faces)
        source_file = str(mesh_file[0]) if mesh_file[0] is not None else None
    else:
        v, f = _primitive(kind, np.asarray(m.geom_size[g], dtype=np.float64))
    rgb, alpha = _colour(m, g)
    return VisualGeom(name, int(m.geom_bodyid[g]), _KINDS[kind], _pose(m.geom_pos[g], m.geom_quat[g]),
                      np.asarray(v, dtype=np.float32), np.asarray(f, dtype=np.int32), rgb, alpha, source_file)
