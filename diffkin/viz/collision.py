"""The viewer's collision layer: a :class:`~diffkin.collision.RobotCollision`'s geoms and a
:class:`~diffkin.collision.World`'s objects as scene meshes, red where a pair is in contact.

Each robot geom is drawn as it is computed (``RobotCollision.placed(q)``: capsules — spheres and cylinders
included — as capsules, boxes as boxes), placed at every configuration the viewer shows. A checked pair
(``collision.pairs``) is *in contact* when its signed distance ``self_distances(q)`` is below ``margin``;
a geom and a world object when ``world_distances(q, world)`` is. Geoms and objects in contact are red,
the others translucent green (robot) and grey (world).
"""

from __future__ import annotations

import numpy as np
import torch

from ..errors import ModelError, ShapeError

__all__: list[str] = []  # used through diffkin.viz.Viewer(collision=, world=, margin=)

FREE_RGB = (60, 170, 90)
WORLD_RGB = (150, 150, 160)
CONTACT_RGB = (230, 30, 30)


def _capsule(length: float, radius: float):
    import trimesh

    if length < 1e-9:
        m = trimesh.creation.icosphere(subdivisions=2, radius=max(radius, 1e-4))
    else:
        m = trimesh.creation.capsule(height=length, radius=max(radius, 1e-4), count=[16, 16])
    return np.asarray(m.vertices, dtype=np.float32), np.asarray(m.faces, dtype=np.int32)


def _cylinder(length: float, radius: float):
    import trimesh

    m = trimesh.creation.cylinder(radius=max(radius, 1e-4), height=max(length, 1e-4), sections=32)
    return np.asarray(m.vertices, dtype=np.float32), np.asarray(m.faces, dtype=np.int32)


def _box(half):
    import trimesh

    m = trimesh.creation.box(extents=2.0 * np.asarray(half, dtype=np.float64))
    return np.asarray(m.vertices, dtype=np.float32), np.asarray(m.faces, dtype=np.int32)


def _wxyz(R: np.ndarray) -> np.ndarray:
    from ..rotations import matrix_to_quaternion

    return matrix_to_quaternion(torch.as_tensor(R, dtype=torch.float64)).numpy()


def _z_to(u: np.ndarray) -> np.ndarray:
    """Rotations ``(N, 3, 3)`` whose z axis is the unit vector along ``u (N, 3)`` (z where u is 0)."""
    n = np.linalg.norm(u, axis=-1, keepdims=True)
    z = np.where(n > 1e-12, u / np.where(n > 1e-12, n, 1.0), np.array([0.0, 0.0, 1.0]))
    helper = np.where(np.abs(z[:, :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    x = np.cross(helper, z)
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    return np.stack((x, np.cross(z, x), z), axis=-1)


def _capsule_poses(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(centres (N, 3), rotations (N, 3, 3))`` of capsules from their end points: the drawn capsule's
    axis z runs from ``a`` to ``b``."""
    return 0.5 * (a + b), _z_to(b - a)


class CollisionView:
    """Scene meshes of a robot's collision geoms and the world's objects, kept at the shown q."""

    def __init__(self, scene, collision, world=None, margin: float = 0.0, scale: float = 1.0, q=None):
        self.collision, self.world, self.margin = collision, world, float(margin)
        self._scene = scene
        self._shape = [g.shape for g in collision.geoms]
        other = sorted({s for s in self._shape if s not in ("capsule", "box")})
        if other:  # convex meshes are not drawn yet: say so instead of a KeyError below
            raise ModelError(f"the viewer draws capsule and box geoms, this model has {', '.join(other)} "
                             'geoms: build it with RobotCollision.from_urdf(..., geometry="capsules") to '
                             "view it")
        self._slot = []  # per geom: its row among the capsules or among the boxes of placed(q)
        counts = {"capsule": 0, "box": 0}
        for s in self._shape:
            self._slot.append(counts[s])
            counts[s] += 1
        with torch.no_grad():
            a, b, r, c, R, h = (t.detach().cpu().double().numpy() for t in collision.placed(q))
        self.handles, self.meshes = [], []  # per geom: its scene node and its triangles (V, 3), (F, 3)
        for g, geom in enumerate(collision.geoms):
            k = self._slot[g]
            v, f = (_capsule(float(np.linalg.norm(b[k] - a[k])), float(r[k])) if geom.shape == "capsule"
                    else _box(h[k]))
            self.meshes.append((v, f))
            self.handles.append(scene.add_mesh_simple(f"/collision/{g}", v, f, color=FREE_RGB, opacity=0.45))
        self.world_handles = self._add_world(world, scale) if world is not None else []
        self.contact = np.zeros(len(self.handles), dtype=bool)
        self.world_contact = np.zeros(len(self.world_handles), dtype=bool)
        self.state: dict = {}

    def _add_world(self, world, scale: float) -> list:
        if len(world.batch_shape):
            raise ShapeError(f"the viewer draws one world: expected objects without batch dims, got batch "
                             f"shape {tuple(world.batch_shape)}")
        np_ = lambda t: t.detach().cpu().double().numpy()  # noqa: E731
        out, self.world_meshes = [], []

        def add(name, v, f, **kw):
            self.world_meshes.append((v, f))
            return self._scene.add_mesh_simple(name, v, f, **kw)

        for i, (x, y, z, rad) in enumerate(np_(world.spheres)):
            out.append(add(f"/world/sphere_{i}", *_capsule(0.0, rad), color=WORLD_RGB, position=(x, y, z)))
        caps = np_(world.capsules)
        if len(caps):
            centres, rots = _capsule_poses(caps[:, :3], caps[:, 3:6])
            for i, (cap, p, R) in enumerate(zip(caps, centres, rots)):
                out.append(add(f"/world/capsule_{i}", *_capsule(float(np.linalg.norm(cap[3:6] - cap[:3])),
                                                               cap[6]), color=WORLD_RGB, position=p,
                               wxyz=_wxyz(R)))
        for i, (p, R, h) in enumerate(zip(np_(world.boxes.center), np_(world.boxes.rotation),
                                          np_(world.boxes.half_extents))):
            out.append(add(f"/world/box_{i}", *_box(h), color=WORLD_RGB, position=p, wxyz=_wxyz(R)))
        for i, hs in enumerate(np_(world.halfspaces)):  # a thin plate, top face on the plane
            R = _z_to(hs[None, :3])[0]
            half = (1.25 * scale, 1.25 * scale, 0.005 * scale)
            out.append(add(f"/world/halfspace_{i}", *_box(half), color=WORLD_RGB, opacity=0.35,
                           position=hs[:3] * hs[3] - R[:, 2] * half[2], wxyz=_wxyz(R)))
        for i, p in enumerate(np_(world.points)):
            out.append(add(f"/world/point_{i}", *_capsule(0.0, 0.01 * scale), color=WORLD_RGB, position=p))
        cyls = np_(world.cylinders)
        if len(cyls):  # exact cylinders (flat ends), last as in the world's columns
            centres, rots = _capsule_poses(cyls[:, :3], cyls[:, 3:6])
            for i, (cyl, p, R) in enumerate(zip(cyls, centres, rots)):
                out.append(add(f"/world/cylinder_{i}", *_cylinder(float(np.linalg.norm(cyl[3:6] - cyl[:3])),
                                                                 cyl[6]), color=WORLD_RGB, position=p,
                               wxyz=_wxyz(R)))
        return out

    def update(self, q) -> dict:
        """Place the geoms at ``q (nq,)``, colour the contacts; returns :attr:`state`: ``pairs`` (the checked
        pairs below the margin, ``(geom_a, geom_b, distance)``), ``world`` (``(geom, object index,
        distance)``), ``min_distance`` (over both; inf when nothing is checked)."""
        col = self.collision
        with torch.no_grad():
            a, b, _, c, R, _ = (t.detach().cpu().double().numpy() for t in col.placed(q))
            d = col.self_distances(q).detach().cpu().double().numpy()
            w = (col.world_distances(q, self.world).detach().cpu().double().numpy() if self.world is not None
                 else np.zeros((len(self.handles), 0)))
        centres, rots = _capsule_poses(a, b)
        pos = [centres[k] if s == "capsule" else c[k] for s, k in zip(self._shape, self._slot)]
        rot = [rots[k] if s == "capsule" else R[k] for s, k in zip(self._shape, self._slot)]
        for hdl, p, wxyz in zip(self.handles, pos, _wxyz(np.asarray(rot).reshape(-1, 3, 3))):
            hdl.position, hdl.wxyz = p, wxyz
        index = {g.name: i for i, g in enumerate(col.geoms)}
        hit = d < self.margin
        contact = np.zeros(len(self.handles), dtype=bool)
        for (ga, gb), on in zip(col.pairs, hit):
            if on:
                contact[index[ga]] = contact[index[gb]] = True
        whit = w < self.margin
        contact |= whit.any(axis=1)
        self._recolour(self.handles, self.contact, contact, FREE_RGB)
        self._recolour(self.world_handles, self.world_contact, whit.any(axis=0), WORLD_RGB)
        self.contact, self.world_contact = contact, whit.any(axis=0)
        self.state = {
            "pairs": [(ga, gb, float(x)) for (ga, gb), x, on in zip(col.pairs, d, hit) if on],
            "world": [(col.geoms[g].name, int(j), float(w[g, j])) for g, j in zip(*np.nonzero(whit))],
            "min_distance": float(min(d.min(initial=np.inf), w.min(initial=np.inf))),
        }
        return self.state

    @staticmethod
    def _recolour(handles, old: np.ndarray, new: np.ndarray, free) -> None:
        """Send a colour only where the contact flag changed (every mesh starts in its free colour)."""
        for h, was, now in zip(handles, old, new):
            if was != now:
                h.color = CONTACT_RGB if now else free
