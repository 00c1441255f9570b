"""Approximate convex decomposition (diffkin.collision.decompose): containment of the mesh, the excess
against coal's distance to the mesh itself (BVH), the winding number against a closed form, typed errors,
and ``RobotCollision.from_urdf(..., geometry="convex", mesh_tolerance=...)``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

coal = pytest.importorskip("coal")
spatial = pytest.importorskip("scipy.spatial")
import collision_reference as ref  # noqa: E402

from diffkin.collision import convex as CV  # noqa: E402
from diffkin.collision.decompose import convex_parts, winding_number  # noqa: E402
from diffkin.errors import ModelError, NonFiniteError, OptionError, ShapeError  # noqa: E402

F64 = torch.float64
UNIT = 0.02  # the U's grid unit (m): arms 20 mm wide, a 20 mm slot, 20 mm thick


def _u_mesh():
    """A closed U-shaped prism (outward normals): the U polygon (3 x 3 units less the slot [1, 2] x [1, 3])
    extruded 1 unit along z; its closed form: inside iff in the polygon and 0 < z < 1 unit."""
    xy = np.array([(0, 0), (3, 0), (3, 3), (2, 3), (2, 1), (1, 1), (1, 3), (0, 3)], dtype=float) * UNIT
    cap = [(0, 1, 4), (1, 2, 4), (2, 3, 4), (0, 4, 5), (0, 5, 7), (5, 6, 7)]  # counter-clockwise
    v = np.concatenate((np.c_[xy, np.zeros(8)], np.c_[xy, np.full(8, UNIT)]))
    faces = [(a, c, b) for a, b, c in cap] + [(a + 8, b + 8, c + 8) for a, b, c in cap]
    for k in range(8):
        j = (k + 1) % 8
        faces += [(k, j, j + 8), (k, j + 8, k + 8)]
    return v, np.array(faces)


def _inside_u(p):
    x, y, z = (p / UNIT).T
    in_square = (x > 0) & (x < 3) & (y > 0) & (y < 3)
    in_slot = (x >= 1) & (x <= 2) & (y >= 1)
    return in_square & ~in_slot & (z > 0) & (z < 1)


def _bvh(v, faces):
    m = coal.BVHModelOBBRSS()
    m.beginModel(len(faces), len(v))
    m.addVertices(np.asarray(v, dtype=np.float64))
    m.addTriangles(np.asarray(faces, dtype=np.int64))
    m.endModel()
    return m


def _inside_some_hull(p, parts, tol=1e-12):
    """Which points lie in (or on) the hull of some part (Qhull's facet planes)."""
    ok = np.zeros(len(p), dtype=bool)
    for V in parts:
        eq = spatial.ConvexHull(V).equations
        ok |= (p @ eq[:, :3].T + eq[:, 3] <= tol * (1 + np.abs(p).max())).all(1)
    return ok


@pytest.fixture(scope="module")
def u_parts():
    v, faces = _u_mesh()
    return v, faces, convex_parts(v, faces, tolerance=0.002)


def test_u_parts_contain_the_mesh_and_are_fewer_than_its_faces(u_parts):
    v, faces, r = u_parts
    assert len(r.parts) == 3 and r.excess <= 0.002  # one arm, then the other, off the base
    assert _inside_some_hull(v, r.parts).all()  # every mesh vertex, and points spread over each triangle
    w = np.random.default_rng(0).dirichlet(np.ones(3), 200)
    assert _inside_some_hull(np.einsum("kj,fjd->fkd", w, v[faces]).reshape(-1, 3), r.parts).all()


def _distances(v, faces, parts, p):
    """At points ``p (N, 3)``: coal's distance to the mesh (its BVH), the distance to the nearest of the
    convex ``parts`` and to the mesh's hull (diffkin's capsule-convex distance with zero-length capsules)."""
    bvh = _bvh(v, faces)
    true = np.array([ref.distance(coal.Sphere(1e-12), ref.placement(p=x), bvh, ref.placement()) for x in p])
    M = max(len(V) for V in parts)
    V = torch.tensor(np.stack([np.concatenate((V, V[:1].repeat(M - len(V), 0))) for V in parts]))
    P = torch.tensor(p)
    ours = CV.capsule_convex(P[:, None], P[:, None], torch.zeros(len(p), 1, dtype=F64), V).amin(-1).numpy()
    hull = CV.capsule_convex(P, P, torch.zeros(len(p), dtype=F64), torch.tensor(v)).numpy()
    return true, ours, hull


def test_u_parts_distances_against_coal_on_the_mesh(u_parts):
    """Points outside the U: the distance to the parts is never above coal's distance to the mesh (BVH)
    and below it by at most the tolerance (the hull alone: up to the slot's half width, 10 mm)."""
    v, faces, r = u_parts
    rng = np.random.default_rng(1)
    p = rng.uniform(-0.02, 0.08, (600, 3))
    p = p[~_inside_u(p)]
    true, ours, hull = _distances(v, faces, r.parts, p)
    gap = true - ours
    assert gap.min() > -1e-9 and gap.max() <= 0.002 + 1e-9
    assert (true - hull).max() > 0.01  # (what the decomposition removes: the hull fills the slot)


def _box(lo, hi):
    """A closed box's vertices (8, 3) and outward triangles (12, 3)."""
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    h = spatial.ConvexHull(v)
    f = h.simplices.copy()
    flip = np.einsum("ij,ij->i", np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]),
                     v[f].mean(1) - v.mean(0)) < 0
    f[flip] = f[flip][:, ::-1]
    return v, f


def test_frame_of_overlapping_boxes_against_coal():
    """A square frame (outer 4 x 4 units, a 2 x 2 hole, 1 unit thick) as 4 closed boxes overlapping at the
    corners (like a CAD export's shells): the parts' union is never farther than coal's distance to the mesh
    and nearer by at most the reported excess (<= 2 mm) at points all around, the hole's included, where
    the hull alone is 20 mm off."""
    U = UNIT
    boxes = [_box((0, 0, 0), (4 * U, U, U)), _box((0, 3 * U, 0), (4 * U, 4 * U, U)),
             _box((0, 0, 0), (U, 4 * U, U)), _box((3 * U, 0, 0), (4 * U, 4 * U, U))]
    v = np.concatenate([b[0] for b in boxes])
    faces = np.concatenate([b[1] + 8 * k for k, b in enumerate(boxes)])
    r = convex_parts(v, faces, tolerance=0.002)
    assert len(r.parts) == 4 and r.excess <= 0.002  # one per side
    rng = np.random.default_rng(3)
    p = np.concatenate((rng.uniform(-0.02, 0.1, (400, 3)),
                        rng.uniform((U, U, -0.01), (3 * U, 3 * U, 0.03), (200, 3))))  # (the hole)
    x, y, z = (p / U).T
    hole = (x >= 1) & (x <= 3) & (y >= 1) & (y <= 3)
    inside = (x > 0) & (x < 4) & (y > 0) & (y < 4) & ~hole & (z > 0) & (z < 1)
    p = p[~inside]
    true, ours, hull = _distances(v, faces, r.parts, p)
    gap = true - ours
    assert gap.min() > -1e-9 and gap.max() <= r.excess + 1e-9
    assert (true - hull).max() > 0.015


def test_convex_mesh_is_one_part_its_hull():
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 2) for z in (0, 3)], dtype=float) * 0.01
    h = spatial.ConvexHull(v)
    r = convex_parts(v, h.simplices, tolerance=0.002)
    assert len(r.parts) == 1 and r.excess <= 0.002
    np.testing.assert_allclose(np.sort(r.parts[0], 0), np.sort(v, 0))


def test_winding_number_against_the_closed_form():
    v, faces = _u_mesh()
    p = np.random.default_rng(2).uniform(-0.01, 0.07, (400, 3))
    p = p[np.abs(p / UNIT - np.round(p / UNIT)).min(1) > 0.02]  # away from the faces' planes
    np.testing.assert_allclose(winding_number(p, v[faces]), _inside_u(p).astype(float), atol=1e-9)


def test_typed_errors():
    v, faces = _u_mesh()
    with pytest.raises(ShapeError, match="expected vertices"):
        convex_parts(v[:, :2], faces)
    with pytest.raises(ModelError, match="indices"):
        convex_parts(v, faces + 100)
    bad = v.copy()
    bad[0, 0] = np.nan
    with pytest.raises(NonFiniteError):
        convex_parts(bad, faces)
    with pytest.raises(OptionError, match="tolerance"):
        convex_parts(v, faces, tolerance=0.0)
    with pytest.raises(OptionError, match="max_parts"):
        convex_parts(v, faces, max_parts=0)


def test_max_parts_stops_early_with_the_excess_reported():
    v, faces = _u_mesh()
    r = convex_parts(v, faces, tolerance=0.004, max_parts=1)
    assert len(r.parts) == 1 and 0.0099 < r.excess < 0.0115  # the hull over the slot: its half width (10 mm)


@pytest.mark.extended
def test_panda_link6_parts_bound_against_coal():
    """Panda link6 (a CAD export of overlapping open shells), 32 parts at 2 mm asked: on 3 000 random
    points around the link outside the mesh (winding number), the distance to the parts' union (0 inside a
    hull) is never above coal's distance to the mesh and below it by at most the reported excess
    (measured 4 December: excess 5.5 mm, max 4.5 mm; the old cut rule 7.3 mm excess at 32 parts)."""
    trimesh = pytest.importorskip("trimesh")
    from benchmarks import motion_problems as mp

    mesh = trimesh.load(mp.DATA / "meshes" / "collision" / "link6.obj", force="mesh")
    mesh.merge_vertices()
    v, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
    r = convex_parts(v, faces, tolerance=0.002, max_parts=32)
    assert len(r.parts) == 32 and r.excess < 0.006
    rng = np.random.default_rng(0)
    p = rng.uniform(v.min(0) - 0.05, v.max(0) + 0.05, (3000, 3))
    p = p[np.abs(winding_number(p, v[faces])) < 0.5]
    bvh = _bvh(v, faces)
    true = np.array([ref.distance(coal.Sphere(1e-12), ref.placement(p=x), bvh, ref.placement()) for x in p])
    M = max(len(V) for V in r.parts)
    V = torch.tensor(np.stack([np.concatenate((V, V[:1].repeat(M - len(V), 0))) for V in r.parts]))
    P = torch.tensor(p)
    ours = torch.cat([CV.capsule_convex(P[s:s + 500, None], P[s:s + 500, None],
                                        torch.zeros(len(P[s:s + 500]), 1, dtype=F64), V).amin(-1)
                      for s in range(0, len(P), 500)]).clamp_min(0.0).numpy()
    gap = true - ours
    assert len(p) > 2500 and gap.min() > -1e-7 and gap.max() <= r.excess + 1e-9
    hull = CV.capsule_convex(P, P, torch.zeros(len(p), dtype=F64), torch.tensor(v)).clamp_min(0.0).numpy()
    assert (true - hull).max() > 0.012  # (the hull alone)


_URDF = """<robot name="u"><link name="base"/><link name="arm"><collision><geometry>
<mesh filename="u.obj"/></geometry></collision></link><link name="mid"/><link name="tip"><collision>
<origin xyz="0.03 0.03 0.2"/><geometry><sphere radius="0.008"/></geometry></collision></link>
<joint name="j1" type="revolute"><parent link="base"/><child link="arm"/><axis xyz="0 0 1"/>
<limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
<joint name="j2" type="prismatic"><parent link="arm"/><child link="mid"/><axis xyz="0 0 1"/>
<limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
<joint name="j3" type="revolute"><parent link="mid"/><child link="tip"/><axis xyz="0 0 1"/>
<limit lower="-3" upper="3" effort="1" velocity="1"/></joint></robot>"""


def test_from_urdf_convex_parts(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    from diffkin import models
    from diffkin.collision import RobotCollision

    v, faces = _u_mesh()
    trimesh.Trimesh(v, faces).export(tmp_path / "u.obj")
    (tmp_path / "u.urdf").write_text(_URDF)
    chain = models.from_urdf(tmp_path / "u.urdf", "tip", dtype=F64)
    rc = RobotCollision.from_urdf(tmp_path / "u.urdf", chain, geometry="convex", mesh_tolerance=0.002)
    parts = [g for g in rc.geoms if g.link == "arm"]
    assert len(parts) >= 2 and all(g.shape == "convex" and g.name.startswith("arm") for g in parts)
    hull = RobotCollision.from_urdf(tmp_path / "u.urdf", chain, geometry="convex")
    assert [g.hull for g in hull.geoms if g.link == "arm"] == [True]
    # the tip's sphere (radius 8 mm) lowered into the slot, its centre 10 mm from both inner walls and the
    # slot's floor: 2 mm from the U; inside its hull
    q = torch.tensor([[0.0, -0.2 + 0.5 * UNIT, 0.0]], dtype=F64)
    with torch.no_grad():
        d_parts, d_hull = float(rc.self_distances(q).min()), float(hull.self_distances(q).min())
    assert d_hull < 0 and -1e-9 <= d_parts <= 0.002 + 1e-9
    with pytest.raises(OptionError, match="mesh_tolerance"):
        RobotCollision.from_urdf(tmp_path / "u.urdf", chain, geometry="convex", mesh_tolerance=-1.0)
    with pytest.raises(OptionError, match="needs geometry='convex'"):  # not silently ignored
        RobotCollision.from_urdf(tmp_path / "u.urdf", chain, mesh_tolerance=0.002)
