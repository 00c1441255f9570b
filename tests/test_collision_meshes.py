"""Meshes as fitted capsule sets, on the Panda's real collision meshes (tests/data/meshes, Franka's
``franka_description`` meshes as shipped by rtb-data): every triangle inside the set (conservative),
distances against coal's BVH distance to the true mesh (a bound, and tighter than one enclosing capsule),
through ``RobotCollision.from_urdf`` (placed by Pinocchio) and ``from_mjcf`` (against ``mj_geomDistance``,
which collides a mesh as its convex hull)."""

from __future__ import annotations

from pathlib import Path

import collision_reference as ref
import numpy as np
import pytest
import torch

import diffkin
from diffkin.collision import RobotCollision
from diffkin.collision.meshes import capsules_of_triangles, fit_capsules
from diffkin.errors import OptionError

trimesh = pytest.importorskip("trimesh")
coal = ref.coal
MESHES = Path(__file__).parent / "data" / "meshes" / "panda"
LINKS = ["link1", "link5", "link6"]
F64 = torch.float64


def _union_distance(p: np.ndarray, capsules) -> np.ndarray:
    """Distance ``(N,)`` of points ``(N, 3)`` to the union of capsules (negative inside), in numpy."""
    out = []
    for a, b, r in capsules:
        d = b - a
        t = np.clip((p - a) @ d / max(d @ d, 1e-300), 0.0, 1.0)
        out.append(np.linalg.norm(p - (a + t[:, None] * d), axis=1) - r)
    return np.min(out, axis=0)


def _bvh(mesh):
    model = coal.BVHModelOBBRSS()
    model.beginModel(len(mesh.faces), len(mesh.vertices))
    model.addVertices(np.asarray(mesh.vertices, dtype=np.float64))
    model.addTriangles(np.asarray(mesh.faces, dtype=np.int64))
    model.endModel()
    return model


@pytest.mark.parametrize("name", LINKS)
def test_every_triangle_lies_in_one_capsule_of_the_set(name):
    mesh = trimesh.load(MESHES / f"{name}.ply")
    caps = fit_capsules(MESHES / f"{name}.ply")
    assert 2 <= len(caps) <= 4  # the default: at most 4; these L-shaped links split
    assert _union_distance(mesh.vertices, caps).max() <= 1e-12
    surface, _ = trimesh.sample.sample_surface(mesh, 20_000, seed=0)  # points inside the triangles
    assert _union_distance(surface, caps).max() <= 1e-12
    again = fit_capsules(MESHES / f"{name}.ply")  # deterministic
    assert all(np.array_equal(x, y) for c, d in zip(caps, again) for x, y in zip(c[:2], d[:2]))
    assert [c[2] for c in caps] == [d[2] for d in again]
    assert len(fit_capsules(MESHES / f"{name}.ply", max_capsules=2)) <= 2
    scaled = fit_capsules(MESHES / f"{name}.ply", (2.0, 1.0, 0.5))
    assert _union_distance(mesh.vertices * [2.0, 1.0, 0.5], scaled).max() <= 1e-12


@pytest.mark.parametrize("name", LINKS)
def test_the_set_bounds_coals_mesh_distance_and_is_tighter_than_one_capsule(name):
    mesh = trimesh.load(MESHES / f"{name}.ply")
    bvh, point = _bvh(mesh), coal.Sphere(0.0)
    lo, hi = mesh.bounds
    p = np.random.default_rng(0).uniform(lo - 0.05, hi + 0.05, (600, 3))
    truth = np.array([ref.distance(bvh, ref.placement(), point, ref.placement(p=x)) for x in p])
    one = _union_distance(p, fit_capsules(MESHES / f"{name}.ply", max_capsules=1))
    fitted = _union_distance(p, fit_capsules(MESHES / f"{name}.ply"))
    # conservative everywhere: the mesh surface lies in the set, so no point is farther from the set
    assert (fitted <= truth + 1e-9).all() and (one <= truth + 1e-9).all()
    outside = ~mesh.convex_hull.contains(p)  # (inside the non-watertight mesh coal's distance is unsigned)
    err_one, err = (truth - one)[outside], (truth - fitted)[outside]
    assert np.median(err) <= 0.75 * np.median(err_one)
    assert err.max() <= 0.06 and np.median(err) <= 0.03  # measured: median 15-24 mm, max 36-48 mm


URDF = """<robot name="two_meshes">
  <link name="l1"><collision><geometry><mesh filename="{m}/link1.ply"/></geometry></collision></link>
  <link name="mid"/>
  <link name="l6"><collision name="hull6"><origin xyz="0.02 0 0.05" rpy="0.3 -0.2 0.1"/><geometry>
    <mesh filename="{m}/link6.ply"/></geometry></collision></link>
  <joint name="j1" type="revolute"><parent link="l1"/><child link="mid"/><origin xyz="0 0 0.2"/>
    <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="mid"/><child link="l6"/><origin xyz="0.12 0 0.05"/>
    <axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
</robot>"""


def test_from_urdf_fits_mesh_sets_and_bounds_coal_placed_by_pinocchio():
    pin = pytest.importorskip("pinocchio")
    text = URDF.format(m=MESHES)
    chain = diffkin.models.from_urdf(text, "l6", dtype=F64)
    rc = RobotCollision.from_urdf(text, chain)
    assert all(g.kind == "mesh" and g.shape == "capsule" for g in rc.geoms)
    assert {g.source for g in rc.geoms} == {f"{MESHES}/link1.ply", f"{MESHES}/link6.ply"}
    names = [g.name for g in rc.geoms]
    n1 = sum(n.startswith("l1/0/") for n in names)
    n6 = sum(n.startswith("hull6/") for n in names)
    assert n1 >= 2 and n6 >= 2 and n1 + n6 == len(names) and len(rc.pairs) == n1 * n6
    one = RobotCollision.from_urdf(text, chain, mesh_capsules=1)
    assert [g.name for g in one.geoms] == ["l1/0", "hull6"] and len(one.pairs) == 1
    with pytest.raises(OptionError, match="mesh_capsules"):
        RobotCollision.from_urdf(text, chain, mesh_capsules=0)

    model = pin.buildModelFromXML(text)
    data = model.createData()
    m1, m6 = (_bvh(trimesh.load(MESHES / f"{k}.ply")) for k in ("link1", "link6"))
    T6 = ref.placement(*_origin((0.3, -0.2, 0.1), (0.02, 0, 0.05)))
    lo, hi = chain.q_limits.T
    q = lo + (hi - lo) * torch.rand(150, 2, dtype=F64, generator=torch.Generator().manual_seed(0))
    ours, coarse = rc.self_distances(q).amin(-1), one.self_distances(q)[:, 0]
    truth = []
    for row in q.numpy():
        pin.framesForwardKinematics(model, data, row)
        M1, M6 = (data.oMf[model.getFrameId(k)] for k in ("l1", "l6"))
        P6 = ref.placement(M6.rotation, M6.translation) * T6
        truth.append(ref.distance(m1, ref.placement(M1.rotation, M1.translation), m6, P6))
    truth = torch.tensor(truth, dtype=F64)
    assert (ours <= truth + 1e-9).all() and (coarse <= truth + 1e-9).all()  # both conservative
    apart = truth > 0.01  # coal's mesh-mesh distance is 0 in contact: compare where the meshes are apart
    assert apart.sum() > 30
    assert (truth - ours)[apart].median() <= 0.75 * (truth - coarse)[apart].median()


def _origin(rpy, xyz):
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", rpy).as_matrix(), np.asarray(xyz, dtype=np.float64)


def test_bad_options_and_a_mesh_without_triangles():
    v = np.random.default_rng(0).normal(size=(50, 3))
    (a, b, r), = capsules_of_triangles(v, np.zeros((0, 3), dtype=np.int64))  # points: one capsule
    assert _union_distance(v, [(a, b, r)]).max() <= 1e-12
    for bad in ({"max_capsules": 0}, {"max_capsules": 2.5}, {"min_gain": 1.0}, {"min_gain": -0.1}):
        with pytest.raises(OptionError):
            capsules_of_triangles(v, np.zeros((0, 3), dtype=np.int64), **bad)


MJCF = """<mujoco model="mesh_probe"><compiler meshdir="{d}"/>
  <asset><mesh name="link5" file="link5.stl"/></asset>
  <worldbody>
    <body name="arm"><joint name="j" type="hinge" axis="0 0 1"/>
      <geom name="link" type="mesh" mesh="link5" pos="0.01 0 0.02" euler="0.2 0 0.1"/></body>
    <body name="probe"><joint name="x" type="slide" axis="1 0 0"/><joint name="y" type="slide" axis="0 1 0"/>
      <joint name="z" type="slide" axis="0 0 1"/>
      <geom name="ball" type="sphere" size="0.02"/>
      <geom name="stick" type="capsule" fromto="0 0 0 0 0.05 0.05" size="0.01"/></body>
  </worldbody>
</mujoco>"""


def test_from_mjcf_fits_the_hull_mujoco_collides_against_mj_geom_distance(tmp_path):
    """MuJoCo collides a mesh as its convex hull: the set contains it (never farther than
    ``mj_geomDistance``), is tighter than one capsule (less so than for the mesh itself), and every
    ``mj_collision`` contact is a checked pair with a negative distance."""
    mujoco = pytest.importorskip("mujoco")
    from mujoco_reference import MuJoCoPoses

    trimesh.load(MESHES / "link5.ply").export(tmp_path / "link5.stl")
    m = mujoco.MjModel.from_xml_string(MJCF.format(d=tmp_path))
    rc = RobotCollision.from_mjcf(m, body_poses=MuJoCoPoses(m), dtype=F64)
    one = RobotCollision.from_mjcf(m, body_poses=MuJoCoPoses(m), dtype=F64, mesh_capsules=1)
    parts = [g.name for g in rc.geoms if g.kind == "mesh"]
    assert len(parts) >= 2 and parts == [f"link/{k}" for k in range(len(parts))]
    assert [g.name for g in one.geoms] == ["link", "ball", "stick"] and len(one.pairs) == 2
    rng = np.random.default_rng(0)
    q = np.concatenate((rng.uniform(-np.pi, np.pi, (300, 1)), rng.uniform(-0.2, 0.2, (300, 3))), 1)
    with torch.no_grad():
        ours = rc.self_distances(torch.tensor(q)).reshape(300, len(parts), 2).amin(1)  # (ball, stick)
        coarse = one.self_distances(torch.tensor(q))
    d, ids = mujoco.MjData(m), [m.geom(k).id for k in ("link", "ball", "stick")]
    want, negative = np.empty((300, 2)), 0
    for row in range(300):
        d.qpos[:] = q[row]
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        want[row] = [mujoco.mj_geomDistance(m, d, ids[0], g, 10.0, None) for g in ids[1:]]
        for c in d.contact[: d.ncon]:
            k = ids.index(c.geom1 if c.geom1 != ids[0] else c.geom2) - 1
            assert ours[row, k] < 0 and c.dist < 1e-9
            negative += 1
    ours, coarse = ours.numpy(), coarse.numpy()
    assert negative > 10
    assert (ours <= want + 1e-6).all() and (coarse <= want + 1e-6).all()
    apart = want > 0.005  # a convex hull is fitted well by one capsule already: the set gains less
    assert np.median((want - ours)[apart]) <= 0.95 * np.median((want - coarse)[apart])  # measured: 0.88


def test_degenerate_meshes_give_finite_enclosing_sets():
    square = np.array([[0, 0, 0], [0.3, 0, 0], [0.3, 0.1, 0], [0, 0.1, 0]], dtype=np.float64)  # flat
    sliver = np.array([[0, 0, 0], [0.2, 0, 0], [0.4, 0, 0]], dtype=np.float64)  # a zero-area triangle
    point = np.zeros((3, 3))  # every vertex the same
    for v, faces in ((square, [[0, 1, 2], [0, 2, 3]]), (sliver, [[0, 1, 2]]), (point, [[0, 1, 2]])):
        caps = capsules_of_triangles(v, np.array(faces))
        assert 1 <= len(caps) <= 4
        assert all(np.isfinite(a).all() and np.isfinite(b).all() and np.isfinite(r) for a, b, r in caps)
        assert _union_distance(v, caps).max() <= 1e-12
    (a, b, r), = capsules_of_triangles(point, np.array([[0, 1, 2]]))
    assert r == 0.0 and np.array_equal(a, b)


def test_menagerie_panda_with_its_collision_meshes_against_mujoco():
    """Menagerie's Panda compiled with two of its real collision meshes (link1.stl, link6.stl: Franka's, as
    vendored) and every other mesh file served as a small tetrahedron: only the geoms MuJoCo can collide
    are read (its visual meshes, contype = conaffinity = 0, are not), each collision mesh becomes a set of
    capsules named after it, and per MuJoCo pair the set's distance never exceeds ``mj_geomDistance`` where
    the geoms are apart and is negative where they penetrate; every ``mj_collision`` contact is a checked
    pair, negative where MuJoCo's is."""
    mujoco = pytest.importorskip("mujoco")
    import io

    from mjcf_util import _TETRA_OBJ, _tetra_stl
    from mujoco_reference import MuJoCoPoses, random_qpos

    path = Path(__file__).parent / "data" / "mjcf" / "franka_emika_panda" / "panda.xml"
    spec = mujoco.MjSpec.from_file(str(path))
    assets = {mesh.file: _tetra_stl() if mesh.file.endswith(".stl") else _TETRA_OBJ for mesh in spec.meshes}
    for name in ("link1", "link6"):
        data = io.BytesIO()
        trimesh.load(MESHES / f"{name}.ply").export(data, file_type="stl")
        assets[f"{name}.stl"] = data.getvalue()
    m = mujoco.MjModel.from_xml_path(str(path), assets)
    rc = RobotCollision.from_mjcf(m, body_poses=MuJoCoPoses(m), dtype=F64)
    collidable = [g for g in range(m.ngeom)
                  if m.geom_bodyid[g] and (m.geom_contype[g] or m.geom_conaffinity[g])]
    base = {(m.geom(g).name or f"{m.body(m.geom_bodyid[g]).name}/{g - m.body_geomadr[m.geom_bodyid[g]]}"): g
            for g in collidable}
    of = [base.get(geom.name, base.get(geom.name.rpartition("/")[0])) for geom in rc.geoms]  # MuJoCo ids
    assert None not in of and sorted(set(of)) == collidable
    meshes = [g for g in collidable if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH]
    assert len(meshes) == 13 and len(rc.geoms) > len(collidable)  # link5 has 3 meshes; the sets split
    groups: dict[tuple[int, int], list[int]] = {}
    index = {g.name: i for i, g in enumerate(rc.geoms)}
    for p, (a, b) in enumerate(rc.pairs):
        groups.setdefault(tuple(sorted((of[index[a]], of[index[b]]))), []).append(p)
    q = random_qpos(m, 100, seed=0)
    with torch.no_grad():
        ours = rc.self_distances(torch.tensor(q, dtype=F64)).numpy()
    keys = list(groups)
    best = np.stack([ours[:, groups[k]].min(-1) for k in keys], -1)  # (100, MuJoCo pairs)
    d, negative = mujoco.MjData(m), 0
    for row in range(len(q)):
        d.qpos[:] = q[row]
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        want = np.array([mujoco.mj_geomDistance(m, d, a, b, 10.0, None) for a, b in keys])
        # apart: never farther than MuJoCo; in penetration the sign (a union's depth is not its parts' min)
        assert (np.where(want >= 0, best[row] <= want + 1e-6, best[row] < 0)).all()
        for c in d.contact[: d.ncon]:
            if m.geom_bodyid[c.geom1] and m.geom_bodyid[c.geom2]:
                k = keys.index(tuple(sorted((c.geom1, c.geom2))))  # a checked pair ...
                assert c.dist >= 0 or best[row, k] < 0
                negative += c.dist < 0
    assert negative > 0


def _two_meshes(dtype=F64, device="cpu"):
    text = URDF.format(m=MESHES)
    chain = diffkin.models.from_urdf(text, "l6", dtype=dtype, device=device)
    return chain, RobotCollision.from_urdf(text, chain)


def test_mesh_sets_are_differentiable_in_q_and_in_the_fitted_geometry():
    chain, rc = _two_meshes()
    q = torch.tensor([[0.3, 1.2], [-2.0, 2.4], [1.0, -2.9]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(rc.self_distances, (q,))
    (g,) = torch.autograd.grad(rc.min_distance(q.detach()).sum(), rc.capsule_radius)
    assert torch.isfinite(g).all() and (g <= 0).all() and (g < 0).any()  # a larger radius: nearer
    rc32 = _two_meshes(torch.float32)[1]
    d32 = rc32.self_distances(q.detach().float())
    torch.testing.assert_close(d32.double(), rc.self_distances(q.detach()), atol=1e-5, rtol=0)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_mesh_sets_on_cuda_match_cpu():
    rc_cpu, rc_gpu = _two_meshes()[1], _two_meshes(device="cuda")[1]
    q = torch.rand(64, 2, dtype=F64, generator=torch.Generator().manual_seed(0)) * 6 - 3
    torch.testing.assert_close(rc_gpu.self_distances(q.cuda()).cpu(), rc_cpu.self_distances(q), atol=1e-10,
                               rtol=0)


def test_a_file_named_again_is_fitted_once_and_bad_options_are_named():
    first = fit_capsules(MESHES / "link6.ply", max_capsules=3)
    again = fit_capsules(MESHES / "link6.ply", max_capsules=3)
    assert all(np.array_equal(x, y) for c, d in zip(first, again) for x, y in zip(c[:2], d[:2]))
    first[0][0][:] = 0.0  # the caller's copy: the remembered fit is not changed
    assert not np.array_equal(fit_capsules(MESHES / "link6.ply", max_capsules=3)[0][0], first[0][0])
    for bad in ({"max_capsules": [2]}, {"max_capsules": 0}, {"min_gain": "a"}):
        with pytest.raises(OptionError):
            fit_capsules(MESHES / "link6.ply", **bad)
