"""Collision geoms and pairs of an MJCF model, read from MuJoCo's compiled ``MjModel`` (no XML rules
re-implemented): ``geom_type``, ``geom_size``, ``geom_pos``, ``geom_quat``, ``geom_bodyid``,
``contype`` / ``conaffinity``, ``<contact><exclude>`` (``exclude_signature``), explicit ``<contact><pair>``
and MuJoCo's weld and parent–child filters.

Body frames come from a callable ``body_poses(q) -> (..., nbody, 4, 4)`` (MuJoCo's body order, the world body
first): the MJCF model's frames once it provides them (``chain.body_poses``), or any differentiable FK.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch

from ..errors import ModelError, require
from ..rotations import _matrix_to_euler, quaternion_to_matrix
from .meshes import capsule_of_points, capsules_of_triangles

__all__ = ["BodyFrames", "mjcf_geoms"]

_SPHERE, _CAPSULE, _CYLINDER, _BOX, _MESH = 2, 3, 5, 6, 7
_KINDS = {_SPHERE: "sphere", _CAPSULE: "capsule", _CYLINDER: "cylinder", _BOX: "box", _MESH: "mesh"}
_DSBL_FILTERPARENT = 1 << 10


class BodyFrames:
    """The frame provider of :class:`~diffkin.collision.RobotCollision` for MuJoCo bodies: each body is its
    own anchor, with identity offsets, posed by ``body_poses(q)``."""

    def __init__(self, names: list[str], body_poses):
        self.links = list(names)
        self.index = {k: i for i, k in enumerate(self.links)}
        self.bodies = list(range(len(self.links)))
        self._poses = body_poses

    def frames(self, chain, q: torch.Tensor) -> torch.Tensor:
        T = self._poses(q)
        if T.shape[-3:] != (len(self.links), 4, 4):
            raise ModelError(f"body_poses(q) must return (..., {len(self.links)}, 4, 4) (MuJoCo's bodies), "
                             f"got {tuple(T.shape)}")
        return T

    def offsets(self, chain, dtype: torch.dtype, device) -> torch.Tensor:
        return torch.eye(4, dtype=dtype, device=device).expand(len(self.links), 4, 4)


def load_model(source):
    """A compiled ``mujoco.MjModel`` from a path, XML text or an ``MjModel``. A model whose mesh files do
    not resolve still loads: its mesh geoms are skipped (and file textures dropped), as the kinematic reader
    does (:func:`diffkin.models.mjcf.compile_mjcf`), with a warning naming those that would have been
    checked (visual meshes and the world body's are never collided: skipping them loses nothing)."""
    mujoco = require("mujoco", "collision", "RobotCollision.from_mjcf")
    if isinstance(source, mujoco.MjModel):
        return source
    if isinstance(source, str) and "<" in source:
        where, parse = "<MJCF text>", lambda: mujoco.MjSpec.from_string(source)
    elif isinstance(source, (str, Path)) and Path(source).is_file():
        where, parse = str(source), lambda: mujoco.MjSpec.from_file(str(source))
    else:
        raise ModelError(f"MJCF source must be a path, XML text or a mujoco.MjModel, got {source!r:.80}")
    try:
        return parse().compile()
    except ValueError:  # a file asset does not resolve: compile again without the meshes
        pass
    except mujoco.FatalError as exc:
        raise ModelError(f"{where}: MuJoCo could not compile the model: {exc}") from None
    from ..models.mjcf import _strip_assets

    spec = parse()
    meshes = [g for g in spec.geoms if g.type == mujoco.mjtGeom.mjGEOM_MESH]
    # the warning names only the meshes mjcf_geoms would have checked: not visual ones (contype =
    # conaffinity = 0 outside every <pair>: MuJoCo never collides them) nor the world body's
    paired = {n for p in spec.pairs for n in (p.geomname1, p.geomname2)}
    names = [g.name or f"{g.parent.name}/{g.meshname}" for g in meshes
             if g.parent.name != spec.worldbody.name and (g.contype or g.conaffinity or
                                                          (g.name and g.name in paired))]
    for g in meshes:
        spec.delete(g)
    _strip_assets(spec)
    try:
        model = spec.compile()
    except (ValueError, mujoco.FatalError) as exc:
        raise ModelError(f"{where}: MuJoCo could not compile the model: {exc}") from None
    if names:
        warnings.warn(f"{where}: mesh files do not resolve; {len(names)} mesh geoms skipped: "
                      f"{', '.join(names[:12])}{' ...' if len(names) > 12 else ''}", stacklevel=3)
    return model


def _rotation(quat) -> np.ndarray:
    """MuJoCo's (w, x, y, z) geom quaternion as a rotation matrix (scalar first, as the book's (2.33))."""
    return quaternion_to_matrix(torch.tensor(quat, dtype=torch.float64)).numpy()


def _geom_data(m, g: int, kind: int, pos: np.ndarray, R: np.ndarray, mesh_capsules: int) -> list:
    """[(shape, body-frame data)] of geom g: capsules (a, b, r), boxes (centre, rpy, half extents); a
    mesh gives its fitted capsule set."""
    size = m.geom_size[g]
    if kind == _SPHERE:
        return [("capsule", (pos.tolist(), pos.tolist(), float(size[0])))]
    if kind in (_CAPSULE, _CYLINDER):  # a cylinder: its enclosing capsule (docs/collision.md: the error)
        half = R[:, 2] * size[1]
        return [("capsule", ((pos - half).tolist(), (pos + half).tolist(), float(size[0])))]
    if kind == _BOX:
        rpy = _matrix_to_euler(torch.from_numpy(R), "RPY").flip(-1)
        return [("box", (pos.tolist(), rpy.tolist(), size[:3].tolist()))]
    return [("capsule", ((pos + R @ a).tolist(), (pos + R @ b).tolist(), r))
            for a, b, r in _mesh_capsules(m, int(m.geom_dataid[g]), mesh_capsules)]


def _mesh_capsules(m, k: int, mesh_capsules: int) -> list:
    """The fitted capsule set (geom frame) of mesh k's convex hull, MuJoCo's own (``mesh_graph``): MuJoCo
    collides a mesh as its hull, so the set contains what MuJoCo's distances see. Without a hull (a flat
    mesh), the one enclosing capsule of the vertices."""
    v = m.mesh_vert[m.mesh_vertadr[k]: m.mesh_vertadr[k] + m.mesh_vertnum[k]].astype(np.float64)
    adr = int(m.mesh_graphadr[k])
    if adr < 0:
        return [capsule_of_points(v)]
    # mesh_graph: numvert, numface, vert_edgeadr[numvert], vert_globalid[numvert],
    # edge_localid[numvert + 3 numface], face_globalid[3 numface] (face corners as mesh vertex indices)
    nv, nf = int(m.mesh_graph[adr]), int(m.mesh_graph[adr + 1])
    start = adr + 2 + nv + nv + nv + 3 * nf
    faces = m.mesh_graph[start: start + 3 * nf].astype(np.int64).reshape(nf, 3)
    return capsules_of_triangles(v, faces, max_capsules=mesh_capsules)


def mjcf_geoms(m, mesh_capsules: int = 4):
    """``(geoms [(name, body, kind, shape, data)], MuJoCo geom ids)`` of the bodies' geoms that MuJoCo can
    collide (the world body's geoms are surroundings, not the robot's; geoms with contype = conaffinity = 0
    outside every ``<pair>`` are visual); types without a distance here are skipped with one warning.
    A mesh fitted by several capsules gives geoms ``name/0``, ``name/1``, ... with the same MuJoCo id."""
    out, skipped, ids, per_body = [], [], [], {}
    paired = {int(g) for g in np.concatenate((m.pair_geom1[: m.npair], m.pair_geom2[: m.npair]))}
    for g in range(m.ngeom):
        body = int(m.geom_bodyid[g])
        if body == 0:
            continue
        k = per_body.setdefault(body, 0)
        per_body[body] = k + 1
        if not (m.geom_contype[g] or m.geom_conaffinity[g]) and g not in paired:
            continue  # a visual geom: MuJoCo never collides it (with the robot or the world)
        name = m.geom(g).name or f"{m.body(body).name or f'body{body}'}/{k}"
        kind = int(m.geom_type[g])
        if kind not in _KINDS:
            skipped.append(f"{name} (type {kind})")
            continue
        parts = _geom_data(m, g, kind, m.geom_pos[g].astype(np.float64), _rotation(m.geom_quat[g]),
                           mesh_capsules)
        for p, (shape, data) in enumerate(parts):
            out.append((name if len(parts) == 1 else f"{name}/{p}", body, _KINDS[kind], shape, data))
            ids.append(g)
    if skipped:
        warnings.warn(f"RobotCollision.from_mjcf: {len(skipped)} geom(s) of types without a distance here "
                      f"(ellipsoid, plane, height field, SDF) skipped: {', '.join(skipped)}", stacklevel=3)
    return out, ids


def mjcf_pairs(m, ids: list[int]) -> list[tuple[int, int]]:
    """Index pairs (into ``ids``) MuJoCo's collision filters let through, plus the explicit ``<pair>``s."""
    weld, parent = m.body_weldid, m.body_parentid
    excluded = {int(s) for s in m.exclude_signature[: m.nexclude]}
    filter_parent = not (m.opt.disableflags & _DSBL_FILTERPARENT)
    pos: dict[int, list[int]] = {}  # MuJoCo geom id -> our geoms (a mesh's capsules share its id)
    for i, g in enumerate(ids):
        pos.setdefault(g, []).append(i)
    out = set()
    for i, g1 in enumerate(ids):
        for j in range(i + 1, len(ids)):
            g2 = ids[j]
            b1, b2 = int(m.geom_bodyid[g1]), int(m.geom_bodyid[g2])
            w1, w2 = int(weld[b1]), int(weld[b2])
            if w1 == w2:
                continue
            if filter_parent and w1 and w2 and (w1 == weld[parent[w2]] or w2 == weld[parent[w1]]):
                continue
            ct, ca = m.geom_contype, m.geom_conaffinity
            if not (ct[g1] & ca[g2] or ct[g2] & ca[g1]):
                continue
            if ((min(b1, b2) << 16) + max(b1, b2)) in excluded:
                continue
            out.add((i, j))
    for g1, g2 in zip(m.pair_geom1[: m.npair], m.pair_geom2[: m.npair]):
        for i in pos.get(int(g1), []):
            out.update(tuple(sorted((i, j))) for j in pos.get(int(g2), []))
    return sorted(out)
