"""The sole of a foot: the collision geometry of the foot body as points with radii in the foot frame.

A foot's height above the ground is the height of its lowest sole point: ``min_p (z_p - r_p)`` over the
points ``p`` (in the world) and their radii. The geometry is read from the model:

* MJCF (:class:`~diffkin.models.mjcf.MJCFChain`): the foot body's geoms that collide (``contype`` or
  ``conaffinity`` non-zero) and are primitives: a sphere is its centre with its radius, a capsule its two
  end centres with its radius, a box its eight corners, a cylinder 16 points on each cap's rim (the lowest
  rim point of a tilted cylinder is missed by at most r (1 - cos(π/16)) = 0.019 r). Mesh geoms are not
  read (the mesh files are not loaded); an ellipsoid or plane is refused.
* URDF (:class:`~diffkin.models.urdf.URDFChain`): the link's ``<collision>`` spheres, boxes and cylinders,
  the same way.

Anything else, or to override: ``Sole(points, radii)`` given to :func:`~diffkin.retarget.metrics`
(``sole={foot: Sole(...)}``) or to :class:`~diffkin.retarget.Mapping` (``sole=``). The sole centre (the
point whose horizontal path measures foot skating) is the mean of the points.
"""

from __future__ import annotations

import math
import weakref
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..errors import ModelError, ShapeError
from ..rotations import euler_to_matrix, quaternion_to_matrix
from ..transforms import _transform_points
from ..validation import as_tensor

__all__ = ["Sole", "sole_of"]


@dataclass(frozen=True)
class Sole:
    """Sole points ``(P, 3)`` in the foot frame (metres) and their radii ``(P,)`` (0 for corners)."""

    points: Tensor
    radii: Tensor

    def __post_init__(self):
        p = as_tensor(self.points, "sole points", dtype=torch.float64)
        r = as_tensor(self.radii, "sole radii", dtype=torch.float64).reshape(-1)
        if p.ndim != 2 or p.shape[-1] != 3 or p.shape[0] < 1 or r.shape[0] != p.shape[0]:
            raise ShapeError(f"expected sole points (P, 3) with P >= 1 and radii (P,), got points "
                             f"{tuple(p.shape)} and radii {tuple(r.shape)}")
        object.__setattr__(self, "points", p)
        object.__setattr__(self, "radii", r)

    def lowest(self, T: Tensor, ground: float = 0.0) -> tuple[Tensor, Tensor]:
        """Height of the lowest sole point above ``ground`` ``(...)`` and the sole centre ``(..., 3)`` for
        foot poses ``T (..., 4, 4)``."""
        world = _transform_points(T[..., None, :, :], self.points.to(T))  # (..., P, 3), (2.38)
        height = (world[..., 2] - self.radii.to(T)).amin(-1) - ground
        return height, world.mean(-2)


def _box_corners(h) -> np.ndarray:
    s = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=np.float64)
    return s * np.asarray(h, dtype=np.float64)


def _rim(radius: float, half: float) -> np.ndarray:
    a = np.arange(16) * (2 * math.pi / 16)
    ring = np.stack((radius * np.cos(a), radius * np.sin(a), np.zeros(16)), -1)
    return np.concatenate((ring + [0, 0, -half], ring + [0, 0, half]))


def _quat_matrix(q) -> np.ndarray:
    return quaternion_to_matrix(torch.as_tensor(np.asarray(q, dtype=np.float64), device="cpu")).numpy()


def _shape_points(kind: str, size, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Points (n, 3) and radii (n,) of a primitive in its own frame (z its axis)."""
    if kind == "sphere":
        return np.zeros((1, 3)), np.array([size[0]])
    if kind == "capsule":
        return np.array([[0, 0, -size[1]], [0, 0, size[1]]], dtype=np.float64), np.array([size[0]] * 2)
    if kind == "box":
        return _box_corners(size[:3]), np.zeros(8)
    if kind == "cylinder":
        return _rim(size[0], size[1]), np.zeros(32)
    raise ModelError(f"{where}: a {kind} geom cannot give a sole; give sole=Sole(points, radii)")


def _mjcf_sole(chain, body: str) -> Sole:
    from ..models.mjcf import _mujoco, _strip_assets

    mujoco = _mujoco()
    spec = (mujoco.MjSpec.from_file(chain.source_path) if chain.source_path
            else mujoco.MjSpec.from_string(chain.source_text))
    files = (mujoco.mjtGeom.mjGEOM_MESH, mujoco.mjtGeom.mjGEOM_HFIELD, mujoco.mjtGeom.mjGEOM_SDF)
    for g in spec.geoms:  # mesh geoms are not read: out of the collision set before they become stand-ins
        if g.type in files:
            g.contype, g.conaffinity = 0, 0
    _strip_assets(spec)
    model = spec.compile()
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    if bid < 0:
        sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, body)
        if sid < 0:
            raise ModelError(f"foot {body!r} is neither a body nor a site of the model")
        bid = int(model.site_bodyid[sid])
    names = {int(mujoco.mjtGeom.mjGEOM_SPHERE): "sphere", int(mujoco.mjtGeom.mjGEOM_CAPSULE): "capsule",
             int(mujoco.mjtGeom.mjGEOM_BOX): "box", int(mujoco.mjtGeom.mjGEOM_CYLINDER): "cylinder"}
    pts, rad = [], []
    for g in range(model.ngeom):
        if int(model.geom_bodyid[g]) != bid or not (model.geom_contype[g] or model.geom_conaffinity[g]):
            continue
        kind = names.get(int(model.geom_type[g]), mujoco.mjtGeom(int(model.geom_type[g])).name)
        p, r = _shape_points(kind, model.geom_size[g], f"foot {body!r}")
        pts.append(p @ _quat_matrix(model.geom_quat[g]).T + model.geom_pos[g])
        rad.append(r)
    if not pts:
        raise ModelError(f"foot {body!r} has no primitive collision geom (sphere, capsule, box, cylinder); "
                         "give sole=Sole(points, radii)")
    return Sole(*(torch.as_tensor(np.concatenate(x), device="cpu") for x in (pts, rad)))


def _rpy_matrix(rpy) -> np.ndarray:
    """URDF's rpy: R = Rz(yaw) Ry(pitch) Rx(roll), the book's RPY angles (2.21) as (yaw, pitch, roll)."""
    r, p, y = rpy
    return euler_to_matrix(torch.tensor([y, p, r], dtype=torch.float64, device="cpu"), "RPY").numpy()


def _urdf_sole(chain, link: str) -> Sole:
    root = ET.fromstring(chain.tree.text)
    el = next((e for e in root.iter("link") if e.get("name") == link), None)
    if el is None:
        raise ModelError(f"foot {link!r} is not a link of the URDF")
    pts, rad = [], []
    for col in el.findall("collision"):
        o = col.find("origin")
        xyz = np.array([float(v) for v in (o.get("xyz", "0 0 0") if o is not None else "0 0 0").split()])
        rpy = [float(v) for v in (o.get("rpy", "0 0 0") if o is not None else "0 0 0").split()]
        geo = col.find("geometry")
        shape = geo[0] if geo is not None and len(geo) else None
        if shape is None or shape.tag == "mesh":
            continue
        if shape.tag == "sphere":
            p, r = _shape_points("sphere", [float(shape.get("radius"))], link)
        elif shape.tag == "box":
            p, r = _shape_points("box", [float(v) / 2 for v in shape.get("size").split()], link)
        elif shape.tag == "cylinder":
            size = [float(shape.get("radius")), float(shape.get("length")) / 2]
            p, r = _shape_points("cylinder", size, link)
        else:
            p, r = _shape_points(shape.tag, [], f"foot {link!r}")
        pts.append(p @ _rpy_matrix(rpy).T + xyz)
        rad.append(r)
    if not pts:
        raise ModelError(f"foot {link!r} has no sphere, box or cylinder <collision>; give sole=Sole(points, "
                         "radii)")
    return Sole(*(torch.as_tensor(np.concatenate(x), device="cpu") for x in (pts, rad)))


_read: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # chain -> {foot: Sole}


def sole_of(chain, foot: str) -> Sole:
    """The :class:`Sole` of ``foot`` (a body, link or site name) read from the chain's model (module doc);
    read once per chain and foot (a chain's model text does not change; MJCF soles compile the model)."""
    try:
        known = _read.setdefault(chain, {})
    except TypeError:  # a chain that takes no weak reference: read every time
        known = {}
    if foot not in known:
        if getattr(chain, "source_text", None) is not None:
            known[foot] = _mjcf_sole(chain, foot)
        elif getattr(getattr(chain, "tree", None), "text", None) is not None:
            known[foot] = _urdf_sole(chain, foot)
        else:
            raise ModelError(f"the sole of {foot!r} cannot be read from a {type(chain).__name__} (MJCF and "
                             "URDF chains only); give sole=Sole(points, radii)")
    return known[foot]
