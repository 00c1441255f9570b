"""Convex meshes (diffkin.collision.convex) against coal (its own GJK / EPA on coal.Convex hulls, capsules,
spheres, boxes, cylinders), gradcheck in float64, float32 and broadcasting, the pair table's entries, and
the Panda's convex model (RobotCollision.from_urdf(geometry="convex")) against coal on the true meshes.

Tolerances (float64): polytope pairs (meshes, boxes, segments) 1e-8 m against coal (GJK and EPA tolerances
1e-12) in both regimes (GJK and EPA both end on an exact face there); a cylinder's curved side in contact
2e-6 m (EPA on a curved surface converges to a few 1e-7 in 64 steps); the Panda's pairs, up to 2 m apart,
1e-7 m (coal's GJK stops at its relative tolerance there).
"""

from __future__ import annotations

import collision_reference as ref
import numpy as np
import pytest
import torch

from diffkin.collision import convex as CV
from diffkin.collision.pairs import distance

coal = ref.coal
F64 = torch.float64
KINDS = ("convex", "capsule", "sphere", "box", "cylinder")


_tf = ref.placement
_coal_sd = ref.distance  # signed (coal's default), GJK and EPA tolerances 1e-12


def _coal_hull(V):
    pts = coal.StdVec_Vec3s()
    pts.extend([np.asarray(v, dtype=float) for v in V])
    return coal.Convex.convexHull(pts, False, "")


def _axis_frame(a, b):
    d = b - a
    z = d / np.linalg.norm(d)
    x = np.cross(z, [1.0, 0, 0]) if abs(z[0]) < 0.9 else np.cross(z, [0, 1.0, 0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], 1), (a + b) / 2, np.linalg.norm(d)


def _random(kind, rng, m=None):
    """(diffkin args, coal geometry, coal placement) of a random solid of ``kind`` near the origin."""
    from scipy.spatial.transform import Rotation

    c = rng.uniform(-0.15, 0.15, 3)
    if kind == "convex":
        V = c + rng.normal(size=(m or int(rng.integers(8, 40)), 3)) * rng.uniform(0.02, 0.12, 3)
        V = V @ Rotation.random(random_state=rng).as_matrix().T
        return (V,), _coal_hull(V), _tf()
    if kind == "box":
        R, h = Rotation.random(random_state=rng).as_matrix(), rng.uniform(0.02, 0.15, 3)
        return (c, R, h), coal.Box(*(2 * h)), _tf(R, c)
    r = rng.uniform(0.01, 0.1)
    if kind == "sphere":
        return (c, c, r), coal.Sphere(r), _tf(np.eye(3), c)
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    L = rng.uniform(0.02, 0.3)
    a, b = c - u * L / 2, c + u * L / 2
    R, m, L = _axis_frame(a, b)
    return (a, b, r), (coal.Capsule if kind == "capsule" else coal.Cylinder)(r, L), _tf(R, m)


def _pairs(kind, n, seed, m=None):
    """n random (kind, convex) pairs: diffkin arguments stacked (the convex ones padded by repeating a
    vertex; ``m``: m vertices each, no padding) and coal's signed distances."""
    rng = np.random.default_rng(seed)
    xs, vs, ref = [], [], []
    for _ in range(n):
        x, g1, T1 = _random(kind, rng, m)
        (V,), g2, T2 = _random("convex", rng, m)
        xs.append(x)
        vs.append(V)
        ref.append(_coal_sd(g1, T1, g2, T2))
    M = max(len(V) for V in vs)
    V = torch.tensor(np.stack([np.concatenate((V, V[:1].repeat(M - len(V), 0))) for V in vs]), dtype=F64)
    if kind == "convex":
        M1 = max(len(x[0]) for x in xs)
        X = (torch.tensor(np.stack([np.concatenate((x[0], x[0][:1].repeat(M1 - len(x[0]), 0))) for x in xs]),
                          dtype=F64),)
    else:
        X = tuple(torch.tensor(np.stack([x[k] for x in xs]), dtype=F64) for k in range(len(xs[0])))
    return X, V, np.array(ref)


def _ours(kind, X, V):
    k = "capsule" if kind == "sphere" else kind
    return distance(k, X, "convex", (V,))


def _check_against_coal(kind, n, seed):
    X, V, ref = _pairs(kind, n, seed)
    d = _ours(kind, X, V).numpy()
    apart, contact = ref > 0, ref <= 0
    assert apart.sum() > n // 10 and contact.sum() > n // 10  # both regimes are exercised
    err = np.abs(d - ref)
    tol_contact = 2e-6 if kind == "cylinder" else 1e-8
    assert err[apart].max() < 1e-8, (kind, err[apart].max())
    assert err[contact].max() < tol_contact, (kind, err[contact].max())


@pytest.mark.parametrize("kind", KINDS)
def test_signed_distance_matches_coal(kind):
    _check_against_coal(kind, 60, seed=KINDS.index(kind))


@pytest.mark.extended
@pytest.mark.parametrize("kind", KINDS)
def test_signed_distance_matches_coal_thousands(kind):
    _check_against_coal(kind, 2000, seed=100 + KINDS.index(kind))


def test_halfspace_closed_form():
    rng = np.random.default_rng(5)
    V = torch.tensor(rng.normal(size=(50, 20, 3)) * 0.1, dtype=F64)
    n = torch.nn.functional.normalize(torch.tensor(rng.normal(size=(50, 3)), dtype=F64), dim=-1)
    off = torch.tensor(rng.uniform(-0.1, 0.1, 50), dtype=F64)
    d = distance("convex", (V,), "halfspace", (n, off))
    for k in range(0, 50, 7):
        g = coal.Halfspace(n[k].numpy(), float(off[k]))
        assert abs(float(d[k]) - _coal_sd(_coal_hull(V[k].numpy()), _tf(), g, _tf())) < 1e-9


@pytest.mark.parametrize("kind", KINDS)
def test_gradcheck_apart_and_in_contact(kind):
    # meshes of 8 vertices, unpadded (a repeated vertex ties the support: no derivative per copy)
    X, V, ref = _pairs(kind, 10, seed=20 + KINDS.index(kind), m=8)
    assert (ref > 0).any() and (ref < 0).any()
    if kind == "sphere":  # one centre (a = b as two inputs is a segment's kink)
        X = X[1:]
    X = tuple(x.clone().requires_grad_() for x in X)
    V = V.clone().requires_grad_()
    fn = lambda *a: _ours(kind, ((a[0],) if kind == "sphere" else ()) + a[:-1], a[-1])  # noqa: E731
    tol = dict(atol=1e-5, rtol=1e-4) if kind == "cylinder" else dict(atol=1e-6, rtol=1e-5)
    assert torch.autograd.gradcheck(fn, (*X, V), fast_mode=True, **tol)


def test_float32_broadcasting_and_finite_gradients_at_touching():
    rng = np.random.default_rng(3)
    V = torch.tensor(rng.normal(size=(4, 1, 12, 3)) * 0.05, dtype=F64)  # (4, 1) meshes x (1, 5) spheres
    c = torch.tensor(rng.normal(size=(1, 5, 3)) * 0.1, dtype=F64)
    r = torch.full((1, 5), 0.02, dtype=F64)
    d64 = CV.capsule_convex(c, c, r, V)
    assert d64.shape == (4, 5)
    d32 = CV.capsule_convex(c.float(), c.float(), r.float(), V.float())
    assert d32.dtype == torch.float32 and torch.allclose(d32.double(), d64, atol=1e-6)
    # a vertex exactly on a face (touching, d = 0) and coincident meshes: finite values and gradients
    cube = torch.tensor([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=F64) * 0.05
    other = (cube + torch.tensor([0.1, 0.0, 0.0], dtype=F64)).requires_grad_()
    same = cube.clone().requires_grad_()
    d = CV.convex_convex(torch.stack((cube, cube)), torch.stack((other, same)))
    assert abs(float(d[0])) < 1e-12 and abs(float(d[1]) + 0.1) < 1e-12
    d.sum().backward()
    assert torch.isfinite(other.grad).all() and torch.isfinite(same.grad).all()


# ------------------------------------------------------------------ the Panda's convex model against coal
@pytest.fixture(scope="module")
def panda():
    """VAMP's Panda (tests/data/vamp_panda) as ``geometry="convex"`` and Pinocchio's model of the same URDF
    with coal's own hulls of the collision meshes (BVHModel.buildConvexHull, Qhull)."""
    import warnings

    pin = pytest.importorskip("pinocchio")
    from benchmarks import motion_problems as mp
    from diffkin import models
    from diffkin.collision import RobotCollision

    chain = models.from_urdf(mp.PANDA_URDF, "panda_hand", dtype=F64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # visual meshes are not vendored
        rc = RobotCollision.from_urdf(mp.PANDA_URDF, chain, mp.PANDA_SRDF, geometry="convex")
    model = pin.buildModelFromUrdf(str(mp.PANDA_URDF))
    gmodel = pin.buildGeomFromUrdf(model, str(mp.PANDA_URDF), pin.COLLISION, package_dirs=[str(mp.DATA)])
    hulls = {}
    for go in gmodel.geometryObjects:
        go.geometry.buildConvexHull(True, "Qt")  # (buildConvexRepresentation keeps a non-convex link6)
        hulls[model.frames[go.parentFrame].name] = (go.geometry, len(hulls))
    return pin, chain, rc, model, gmodel, hulls


def test_panda_convex_model_geoms_and_flags(panda):
    _, chain, rc, *_ = panda
    assert [g.shape for g in rc.geoms] == ["convex"] * 11
    assert [g.link for g in rc.geoms if g.hull] == ["panda_link6"]  # the one non-convex collision mesh
    assert rc._nconvex == 11 and rc._counts == (0, 0)
    q = torch.tensor([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785], dtype=F64)
    # the ready pose: 22 mm between the closest checked links (the capsule model: 2.8 mm)
    assert 0.020 < float(rc.self_distances(q).min()) < 0.024


def test_panda_convex_distances_match_coal_with_pinocchio_placements(panda):
    """Self pairs and distances to a scene's boxes and cylinders at random configurations: those of coal
    between its own hulls of the meshes placed by Pinocchio (and the scene's true shapes)."""
    from benchmarks import motion_problems as mp

    pin, chain, rc, model, gmodel, hulls = panda
    data, gdata = model.createData(), pin.GeometryData(gmodel)
    problem = mp.load_problems(families={"table_pick"}, indices={41})[0]  # VAMP's one invalid problem
    world = problem.scene.to_world(dtype=F64)
    lo, hi = chain.q_limits.T
    q = lo + (hi - lo) * torch.rand(3, 7, dtype=F64, generator=torch.Generator().manual_seed(0))
    q = torch.cat((q, torch.tensor([problem.start, problem.goal], dtype=F64)))
    with torch.no_grad():
        d_self, d_world = rc.self_distances(q), rc.world_distances(q, world)
    link = {g.name: g.link for g in rc.geoms}
    by_name = {o.name: o for o in problem.scene.objects}
    objects = [by_name[n] for n in problem.scene.column_names()]  # the world's column order
    assert len(objects) == len(problem.scene.objects) == len(world)
    shapes = [(coal.Box(*o.dimensions) if o.kind == "box" else coal.Cylinder(*o.dimensions[::-1]),
               _tf(o.pose[:3, :3].numpy(), o.pose[:3, 3].numpy()), o.kind) for o in objects]
    for k in range(len(q)):
        pin.updateGeometryPlacements(model, data, gmodel, gdata, q[k].numpy())
        place = lambda name: (hulls[link[name]][0].convex, gdata.oMg[hulls[link[name]][1]])  # noqa: E731
        want = [_coal_sd(*place(a), *place(b)) for a, b in rc.pairs]
        np.testing.assert_allclose(d_self[k].numpy(), want, atol=1e-7, rtol=0)
        for g, geom in enumerate(rc.geoms):
            for w, (shape, T, kind) in enumerate(shapes):
                tol = 2e-6 if kind == "cylinder" else 1e-7
                assert abs(float(d_world[k, g, w]) - _coal_sd(*place(geom.name), shape, T)) < tol
    assert float(d_world[-1].min()) > 0 and float(d_self[-1].min()) > 0  # problem 41's goal is clear


def test_panda_convex_gradients_in_q_are_finite_and_match_finite_differences(panda):
    _, chain, rc, *_ = panda
    q = torch.tensor([[0.3, -0.5, 0.2, -2.0, 0.4, 1.2, 0.5]], dtype=F64)
    q.requires_grad_()
    d = rc.self_distances(q)
    (g,) = torch.autograd.grad(d.min(-1).values.sum(), q)
    assert torch.isfinite(g).all()
    eps = 1e-6
    with torch.no_grad():
        j = d.detach().min(-1).indices
        for i in range(7):
            e = torch.zeros(7, dtype=F64)
            e[i] = eps
            at = lambda x: rc.self_distances(x).gather(-1, j[:, None])[:, 0]  # noqa: E731
            torch.testing.assert_close(g[:, i], (at(q + e) - at(q - e)) / (2 * eps), atol=1e-6, rtol=1e-5)


def test_link6_hull_is_conservative_by_a_few_millimetres(panda):
    """link6's mesh is not convex: its hull's distance to points around the link is never above coal's
    distance to the mesh itself (BVH), and below it by at most the measured 13 mm (median ~0)."""
    _, chain, rc, *_ = panda
    import trimesh

    from benchmarks import motion_problems as mp

    mesh = trimesh.load(mp.DATA / "meshes" / "collision" / "link6.obj", force="mesh")
    bvh = coal.BVHModelOBBRSS()
    bvh.beginModel(len(mesh.faces), len(mesh.vertices))
    bvh.addVertices(np.asarray(mesh.vertices, dtype=np.float64))
    bvh.addTriangles(np.asarray(mesh.faces, dtype=np.int64))
    bvh.endModel()
    # (link6's collision origin is the identity: the link frame is the mesh frame)
    V = rc.convex_vertices[[g.link for g in rc.geoms].index("panda_link6")].detach()
    rng = np.random.default_rng(0)
    lo, hi = mesh.bounds
    p = rng.uniform(lo - 0.05, hi + 0.05, (400, 3))
    ours = CV.capsule_convex(torch.tensor(p), torch.tensor(p), torch.zeros(len(p), dtype=F64), V).numpy()
    out = ours > 1e-4
    true = np.array([_coal_sd(coal.Sphere(1e-9), _tf(p=x), bvh, _tf()) for x in p[out]])
    gap = true - ours[out]
    assert gap.min() > -1e-6 and gap.max() < 0.02


@pytest.mark.extended
def test_convex_panda_has_no_more_start_or_goal_collisions_than_vamps_spheres():
    """The 700 MotionBenchMaker problems: with the exact hulls, at most VAMP's count (1: table_pick 41's
    goal touches with its spheres) have a start or a goal in collision (measured: 0; capsules: 237)."""
    from benchmarks import bench_motion_problems

    rows = bench_motion_problems.run(models=("convex",))
    total = next(r for r in rows if r["family"] == "all")
    assert total["problems"] == 700 and total["start_or_goal"] <= 1


def test_panda_convex_with_one_scene_per_row(panda):
    """World.stack of two scenes (padded), one per row: each row's columns are that scene's own distances,
    and the decisions with a margin follow them."""
    from benchmarks import motion_problems as mp
    from diffkin.collision import World
    from diffkin.collision.world_stack import stacked_columns

    _, chain, rc, *_ = panda
    ps = mp.load_problems(families={"cage", "box"}, indices={1})
    ws = [p.scene.to_world(dtype=F64) for p in ps]
    q = torch.tensor([p.start for p in ps], dtype=F64)
    with torch.no_grad():
        d = rc.world_distances(q, World.stack(ws))
        own = []
        for k in range(2):
            own.append(rc.world_distances(q[k], ws[k]))
            torch.testing.assert_close(d[k][:, stacked_columns(ws, k)], own[k], atol=1e-12, rtol=0)
        lowest = torch.stack([torch.cat((o.flatten(), rc.self_distances(q[k]))).min()
                              for k, o in enumerate(own)])
        for margin in (0.0, float(lowest.mean())):
            assert torch.equal(rc._clear(q, World.stack(ws), margin=margin), lowest >= margin)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("kind", KINDS)
def test_cuda_matches_cpu(kind):
    X, V, _ = _pairs(kind, 40, seed=40 + KINDS.index(kind))
    d = _ours(kind, X, V)
    dc = _ours(kind, tuple(x.cuda() for x in X), V.cuda())
    assert dc.device.type == "cuda"
    torch.testing.assert_close(dc.cpu(), d, atol=1e-9, rtol=0)


def test_exported_functions_check_their_input():
    from diffkin import collision as C
    from diffkin.errors import DiffkinError

    V = torch.rand(5, 8, 3, dtype=F64)
    torch.testing.assert_close(C.convex_convex(V, V + 1.0), CV.convex_convex(V, V + 1.0))
    d = C.capsule_convex([0.0, 0, 2], [0.0, 0, 3], 0.1, V.tolist())  # lists become tensors
    assert d.shape == (5,) and d.dtype == torch.float32 and bool((d > 0.8).all())
    with pytest.raises(DiffkinError, match="V"):
        C.convex_halfspace(V[..., :2], [0.0, 0, 1], 0.0)  # points of 2 coordinates
    with pytest.raises(DiffkinError, match="broadcast"):
        C.box_convex(torch.zeros(4, 3, dtype=F64), torch.eye(3, dtype=F64), torch.ones(3, dtype=F64), V)


def test_planner_and_viewer_refuse_convex_geoms_by_name(panda):
    """motion.plan's continuous check bounds the motion of capsule ends and box centres only, and the viewer
    draws capsules and boxes: both refuse a convex model with a typed error naming the way out, never a
    silent under-bound or a KeyError."""
    from diffkin import motion
    from diffkin.errors import ModelError
    from diffkin.viz.collision import CollisionView

    _, chain, rc, *_ = panda
    q = torch.tensor([[0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]], dtype=F64)
    with pytest.raises(ModelError, match=r'11 convex geoms: build it with .*geometry="capsules"'):
        motion.plan(chain, q, q + 0.1, collision=rc, acceleration_limit=5.0)
    with pytest.raises(ModelError, match=r"the viewer draws capsule and box geoms, this model has convex"):
        CollisionView(None, rc, q=q[0])
