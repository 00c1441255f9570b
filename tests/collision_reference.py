"""coal (hpp-fcl's successor) as the reference for the collision tests: shapes, placements, signed distance.

coal's ``distance`` returns the signed distance (negative: the penetration depth found by EPA) for every
pair of its convex primitives; capsules and cylinders lie along their local z axis, boxes take full side
lengths, a ``Halfspace(n, d)`` is {x : n·x ≤ d}.
"""

from __future__ import annotations

import numpy as np

coal = __import__("pytest").importorskip("coal")


def placement(R=None, p=None) -> coal.Transform3s:
    T = coal.Transform3s()
    if R is not None:
        T.setRotation(np.asarray(R, dtype=np.float64))
    if p is not None:
        T.setTranslation(np.asarray(p, dtype=np.float64))
    return T


def distance(g1, T1, g2, T2) -> float:
    req, res = coal.DistanceRequest(), coal.DistanceResult()
    req.gjk_tolerance = 1e-12  # the default 1e-6 leaves GJK up to ~1e-6 m above the distance on box pairs
    req.epa_tolerance = 1e-12
    return coal.distance(g1, T1, g2, T2, req, res)


def collide(g1, T1, g2, T2) -> bool:
    req, res = coal.CollisionRequest(), coal.CollisionResult()
    return coal.collide(g1, T1, g2, T2, req, res) > 0


def frame_along(a, b) -> tuple[np.ndarray, np.ndarray, float]:
    """(R whose z axis is b − a, the midpoint, the length) of a segment: a capsule's coal placement."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    d = b - a
    length = float(np.linalg.norm(d))
    z = d / length if length > 0 else np.array([0.0, 0.0, 1.0])
    x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    return np.stack((x, np.cross(z, x), z), axis=1), 0.5 * (a + b), length


def capsule(a, b, r):
    """(coal shape, placement) of the capsule with axis a–b and radius r (a sphere when a = b)."""
    R, m, length = frame_along(a, b)
    return coal.Capsule(float(r), length), placement(R, m)


def box(c, R, h):
    return coal.Box(*(2.0 * np.asarray(h, dtype=np.float64)).tolist()), placement(R, c)


def halfspace(n, d):
    return coal.Halfspace(np.asarray(n, dtype=np.float64), float(d)), placement()


def world_objects(world) -> list:
    """(coal shape, placement) of every object of a :class:`diffkin.collision.World`, in its order (spheres
    and points as capsules of zero length)."""
    objects = [capsule(s[:3], s[:3], s[3]) for s in world.spheres.numpy()]
    objects += [capsule(c[:3], c[3:6], c[6]) for c in world.capsules.numpy()]
    objects += [box(c, R, h) for c, R, h in zip(world.boxes.center.numpy(), world.boxes.rotation.numpy(),
                                               world.boxes.half_extents.numpy())]
    objects += [halfspace(h[:3], h[3]) for h in world.halfspaces.numpy()]
    objects += [capsule(p, p, 0.0) for p in world.points.numpy()]
    return objects
