"""RobotCollision against coal with the geoms placed by Pinocchio's own URDF parser and FK (never by the
code under test): the Franka FR3's self-collision model (Franka's coarse spheres and cylinders, meshes not
shipped), a small robot with boxes; the link frames behind fixed joints; pair rules, SRDF, meshes."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import collision_reference as ref
import numpy as np
import pytest
import torch

import diffkin
from diffkin.collision import RobotCollision, World, box
from diffkin.collision._poses import LinkFrames
from diffkin.models.urdf_xml import parse_collisions

pin = pytest.importorskip("pinocchio")
coal = ref.coal

DATA = Path(__file__).parent / "data" / "urdf"
FR3 = DATA / "fr3.urdf"
F64 = torch.float64

# A small robot with every primitive URDF has: boxes on the base, a fixed sub-link, rotated origins.
BOXY = """<robot name="boxy">
  <link name="base"><collision><origin xyz="0 0 0.05" rpy="0.1 0 0.3"/><geometry><box size="0.3 0.2 0.1"/>
  </geometry></collision></link>
  <link name="l1"><collision><origin xyz="0 0 0.2" rpy="0 0.2 0"/><geometry>
  <cylinder radius="0.04" length="0.3"/></geometry></collision>
  <collision><origin xyz="0.05 0 0.4"/><geometry><sphere radius="0.05"/></geometry></collision></link>
  <link name="l2"><collision><origin xyz="0.15 0 0" rpy="0.3 0.1 -0.2"/><geometry><box size="0.3 0.06 0.05"/>
  </geometry></collision></link>
  <link name="l2_tip"><collision name="tip"><geometry><sphere radius="0.03"/></geometry></collision></link>
  <link name="l3"><collision><origin xyz="0.1 0 0" rpy="0 1.5707963 0"/><geometry>
  <cylinder radius="0.025" length="0.2"/></geometry></collision></link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><origin xyz="0 0 0.1"/>
    <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0 0 0.45" rpy="0 0 0.4"/>
    <axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="tip_joint" type="fixed"><parent link="l2"/><child link="l2_tip"/><origin xyz="0.32 0 0"/>
  </joint>
  <joint name="j3" type="revolute"><parent link="l2_tip"/><child link="l3"/>
    <origin xyz="0 0 0" rpy="1.2 0 0"/><axis xyz="1 0 1"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
</robot>"""


def _no_meshes(text: str) -> str:
    return re.sub(r"<collision>\s*<geometry>\s*<mesh[^>]*/>\s*</geometry>\s*</collision>", "", text)


def _robot(source, end):
    chain = diffkin.models.from_urdf(source, end, dtype=F64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return chain, RobotCollision.from_urdf(source, chain)


class _Pinocchio:
    """The URDF's collision geoms as Pinocchio builds them (its parser, its FK), cylinders as coal capsules
    (the representation RobotCollision documents), distances by coal."""

    def __init__(self, text: str, chain, geoms, capsules: bool = True):
        text = _no_meshes(text)
        per_link: dict[str, int] = {}
        self.names = {}  # Pinocchio names a link's collisions '<link>_<i>' (i: index in the link)
        for g in geoms:
            self.names[g.name] = f"{g.link}_{per_link.setdefault(g.link, 0)}"
            per_link[g.link] += 1
        self.model = pin.buildModelFromXML(text)
        self.geom = pin.buildGeomFromUrdfString(self.model, text, pin.COLLISION)
        for o in self.geom.geometryObjects:
            if capsules and isinstance(o.geometry, coal.Cylinder):
                o.geometry = coal.Capsule(o.geometry.radius, 2 * o.geometry.halfLength)
        self.data, self.gdata = self.model.createData(), pin.GeometryData(self.geom)
        self.index = {o.name: i for i, o in enumerate(self.geom.geometryObjects)}
        self.q_of = [self.model.joints[self.model.getJointId(n)].idx_q for n in chain.joint_names]

    def place(self, q: np.ndarray) -> None:
        qp = pin.neutral(self.model)
        qp[self.q_of] = q
        pin.updateGeometryPlacements(self.model, self.data, self.geom, self.gdata, qp)

    def shape(self, name: str):
        i = self.index[self.names[name]]
        M = self.gdata.oMg[i]
        return self.geom.geometryObjects[i].geometry, ref.placement(M.rotation, M.translation)


def _random_q(chain, n: int, seed: int) -> torch.Tensor:
    lo, hi = chain.q_limits.T
    g = torch.Generator().manual_seed(seed)
    return lo + (hi - lo) * torch.rand(n, chain.n_joints, dtype=F64, generator=g)


@pytest.mark.parametrize("robot", ["fr3", "boxy"])
def test_self_distances_against_coal_placed_by_pinocchio(robot):
    text = FR3.read_text() if robot == "fr3" else BOXY
    source = FR3 if robot == "fr3" else BOXY
    chain, rc = _robot(source, "fr3_link8" if robot == "fr3" else "l3")
    pref = _Pinocchio(text, chain, rc.geoms)
    q = _random_q(chain, 600 if robot == "fr3" else 2000, seed=1)
    with torch.no_grad():
        d = rc.self_distances(q).numpy()
    assert d.shape == (len(q), len(rc.pairs))
    want = np.empty_like(d)
    hits = np.zeros(d.shape, dtype=bool)
    for b in range(len(q)):
        pref.place(q[b].numpy())
        for p, (ga, gb) in enumerate(rc.pairs):
            sa, sb = pref.shape(ga), pref.shape(gb)
            want[b, p] = ref.distance(*sa, *sb)
            hits[b, p] = ref.collide(*sa, *sb)
    assert (want < 0).mean() > 0.01 and (want > 0).mean() > 0.5  # contacts and gaps both occur
    np.testing.assert_allclose(d, want, atol=1e-8, rtol=0)
    clear = np.abs(want) > 1e-8  # every contact coal reports is a checked pair with a negative distance
    np.testing.assert_array_equal(hits[clear], (d < 0)[clear])


def test_fr3_capsules_are_exact_for_franka_cylinders_with_end_spheres():
    """Franka caps each cylinder with a sphere of its radius at both ends: the union is the capsule, so the
    distance between two links apart (min over their geoms) equals coal's with true cylinders, and links in
    contact are in contact for both (coal's EPA returns -DBL_MAX on some deep cylinder pairs: sign only)."""
    chain, rc = _robot(FR3, "fr3_link8")
    pref = _Pinocchio(FR3.read_text(), chain, rc.geoms, capsules=False)
    assert any(isinstance(o.geometry, coal.Cylinder) for o in pref.geom.geometryObjects)
    link = {g.name: g.link for g in rc.geoms}
    groups: dict[tuple[str, str], list[int]] = {}
    for p, (a, b) in enumerate(rc.pairs):
        groups.setdefault((link[a], link[b]), []).append(p)
    q = _random_q(chain, 200, seed=7)
    with torch.no_grad():
        d = rc.self_distances(q).numpy()
    for b in range(len(q)):
        pref.place(q[b].numpy())
        for ps in groups.values():
            want = min(ref.distance(*pref.shape(rc.pairs[p][0]), *pref.shape(rc.pairs[p][1])) for p in ps)
            ours = d[b, ps].min()
            assert abs(ours - want) < 1e-8 if want > 0 else ours < 1e-8


def test_world_distances_against_coal():
    chain, rc = _robot(FR3, "fr3_link8")
    pref = _Pinocchio(FR3.read_text(), chain, rc.geoms)
    world = World(spheres=[[0.5, 0.0, 0.5, 0.1], [0.0, 0.4, 0.3, 0.05]],
                  capsules=[[0.3, -0.3, 0.2, 0.3, 0.3, 0.6, 0.04]],
                  boxes=box([[0.4, 0.0, 0.1], [0.0, -0.5, 0.6]], [[0.1, 0.2, 0.1], [0.2, 0.05, 0.3]],
                            rpy=[[0.0, 0.0, 0.5], [0.3, 0.2, 0.1]], dtype=F64),
                  halfspaces=[[0.0, 0.0, 1.0, 0.0]], points=[[0.3, 0.1, 0.7]], dtype=F64)
    objects = ref.world_objects(world)
    q = _random_q(chain, 300, seed=2)
    with torch.no_grad():
        d = rc.world_distances(q, world).numpy()
    assert d.shape == (300, len(rc.geoms), len(world)) == (300, 30, 7)
    want = np.empty_like(d)
    for b in range(len(q)):
        pref.place(q[b].numpy())
        for g, geom in enumerate(rc.geoms):
            s = pref.shape(geom.name)
            want[b, g] = [ref.distance(*s, *o) for o in objects]
    assert (want < 0).mean() > 0.01
    np.testing.assert_allclose(d, want, atol=1e-8, rtol=0)
    m = rc.min_distance(q, world).detach().numpy()
    np.testing.assert_allclose(m, np.minimum(d.reshape(300, -1).min(-1), rc.self_distances(q).detach().numpy()
                                             .min(-1)), atol=0)


@pytest.mark.parametrize("case", ["fr3", "fr3_tool", "allegro"])
def test_link_frames_against_pinocchio(case):
    path = DATA / ("allegro_right_hand.urdf" if case == "allegro" else "fr3.urdf")
    if case == "allegro":
        tree = diffkin.models.urdf_xml.parse_urdf(path)
        ends = [k for k in tree.links if not tree.children(k)]
        chain = diffkin.models.from_urdf(path, ends, dtype=F64)
    else:
        chain = diffkin.models.from_urdf(path, "fr3_link8", dtype=F64)
    if case == "fr3_tool":
        chain.tool = torch.tensor([[0.0, -1, 0, 0.1], [1, 0, 0, 0], [0, 0, 1, 0.2], [0, 0, 0, 1]], dtype=F64)
    frames = LinkFrames(chain)
    model = pin.buildModelFromUrdf(str(path))
    data = model.createData()
    q_of = [model.joints[model.getJointId(n)].idx_q for n in chain.joint_names]
    q = _random_q(chain, 20, seed=3)
    T = frames.poses(chain, q).detach().numpy()
    assert len(frames.links) == len(set(frames.links)) >= chain.n_joints + 1
    for b in range(len(q)):
        qp = pin.neutral(model)
        qp[q_of] = q[b].numpy()
        pin.framesForwardKinematics(model, data, qp)
        for i, link in enumerate(frames.links):
            np.testing.assert_allclose(T[b, i], data.oMf[model.getFrameId(link)].homogeneous, atol=1e-12)


def test_gradients_in_q_and_in_the_geometry():
    chain, rc = _robot(BOXY, "l3")
    chain.requires_grad_()  # the chain's origins learnable too (frozen by default)
    q = _random_q(chain, 3, seed=4).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda q: rc.self_distances(q), (q,), eps=1e-6, atol=1e-6)
    world = World(spheres=[[0.2, 0.1, 0.5, 0.05]], boxes=box([0.3, 0, 0.3], [0.05, 0.1, 0.2], dtype=F64),
                  halfspaces=[[0, 0, 1.0, -0.01]], dtype=F64)
    assert torch.autograd.gradcheck(lambda q: rc.world_distances(q, world), (q,), eps=1e-6, atol=1e-6)
    # the geometry: d/d radius is −1 on every capsule pair side; the chain's origins by finite differences
    d = rc.self_distances(q.detach())
    g = torch.autograd.grad(d.sum(), rc.capsule_radius)[0]
    count = [sum(n in pair for pair in rc.pairs) for n in [x.name for x in rc.geoms if x.shape == "capsule"]]
    torch.testing.assert_close(g, -3.0 * torch.tensor(count, dtype=F64))
    f = lambda: rc.self_distances(q.detach()).sum()  # noqa: E731
    g = torch.autograd.grad(f(), chain.origin_xyz)[0]
    fd = torch.zeros_like(g)
    with torch.no_grad():
        for idx in np.ndindex(*g.shape):
            chain.origin_xyz[idx] += 1e-6
            up = f()
            chain.origin_xyz[idx] -= 2e-6
            fd[idx] = (up - f()) / 2e-6
            chain.origin_xyz[idx] += 1e-6
    torch.testing.assert_close(g, fd, atol=1e-6, rtol=1e-5)


def test_finite_at_contact_and_batched_float32():
    chain, rc = _robot(FR3, "fr3_link8")
    q = _random_q(chain, 64, seed=5).reshape(4, 16, 7).requires_grad_(True)
    d = rc.self_distances(q)
    assert d.shape == (4, 16, len(rc.pairs)) and (d < 0).any()
    (g,) = torch.autograd.grad(d.clamp(max=0.0).sum() + rc.min_distance(q).sum(), q)
    assert torch.isfinite(g).all() and g.abs().sum() > 0
    chain32, rc32 = _robot(FR3, "fr3_link8")
    chain32.float()  # the chain is held by reference: convert it and the geometry together
    rc32 = rc32.float()
    with torch.no_grad():
        d32 = rc32.self_distances(q.detach().float())
    torch.testing.assert_close(d32.double(), d.detach(), atol=2e-5, rtol=0)
    per_row = World(spheres=torch.rand(4, 16, 3, 4, dtype=F64))  # one world per row
    assert rc.world_distances(q, per_row).shape == (4, 16, 30, 3)


def test_pair_rules_and_srdf():
    chain, rc = _robot(FR3, "fr3_link8")
    body = lambda g: int(re.match(r"fr3_link(\d)", g).group(1))  # noqa: E731  the sc links ride on link k
    names = [g.name for g in rc.geoms]
    want = {(a, b) for i, a in enumerate(names) for b in names[i + 1:] if abs(body(a) - body(b)) >= 2}
    assert set(rc.pairs) == want and len(rc.pairs) == len(want)
    srdf = """<robot name="fr3"><disable_collisions link1="fr3_link3_sc" link2="fr3_link1_sc" reason="Never"/>
      <disable_collisions link1="fr3_link7_sc" link2="fr3_link5_sc" reason="Default"/></robot>"""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rs = RobotCollision.from_urdf(FR3, chain, srdf=srdf)
    dropped = {p for p in want if {body(p[0]), body(p[1])} in ({1, 3}, {5, 7})}
    assert len(dropped) == 3 * 3 + 6 * 6 and set(rs.pairs) == want - dropped


def test_unresolved_meshes_warn_once_naming_them():
    chain = diffkin.models.from_urdf(FR3, "fr3_link8", dtype=F64)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = RobotCollision.from_urdf(FR3, chain)
    assert len(caught) == 1
    message = str(caught[0].message)
    assert all(f"fr3_link{k}/0" in message and f"link{k}.stl" in message for k in range(8))
    specs = parse_collisions(FR3)
    assert len(rc.geoms) == sum(len(v) for v in specs.values()) - 8 == 30
    assert {g.kind for g in rc.geoms} == {"sphere", "cylinder"}


def test_meshes_become_enclosing_capsules(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    (tmp_path / "mypkg" / "meshes").mkdir(parents=True)
    (tmp_path / "mypkg" / "urdf").mkdir()
    trimesh.creation.cylinder(radius=0.05, height=0.4, sections=64).export(tmp_path / "mypkg/meshes/rod.stl")
    blob = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    blob.apply_scale([1.0, 0.6, 0.3])
    blob.export(tmp_path / "mypkg/meshes/blob.stl")
    urdf = tmp_path / "mypkg" / "urdf" / "r.urdf"
    urdf.write_text("""<robot name="r">
      <link name="a"><collision><origin xyz="0 0 0.2" rpy="0.3 0 0"/><geometry>
        <mesh filename="package://mypkg/meshes/rod.stl"/></geometry></collision>
        <collision><geometry><mesh filename="package://nowhere/missing.stl"/></geometry></collision></link>
      <link name="b"><collision><origin xyz="0.1 0 0"/><geometry><mesh filename="../meshes/blob.stl"
        scale="2 2 2"/></geometry></collision></link>
      <joint name="j" type="revolute"><parent link="a"/><child link="b"/><origin xyz="0 0 0.5"/>
        <axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>""")
    chain = diffkin.models.from_urdf(urdf, "b", dtype=F64)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = RobotCollision.from_urdf(urdf, chain, mesh_capsules=1)  # one capsule per mesh (the sets:
    message = str(caught[0].message)  # tests/test_collision_meshes.py)
    assert len(caught) == 1 and "missing.stl" in message and "rod.stl" not in message
    assert [g.kind for g in rc.geoms] == ["mesh", "mesh"]
    a, b, r = rc.capsule_a.detach(), rc.capsule_b.detach(), rc.capsule_radius.detach()
    # the cylinder's enclosing capsule: its own axis and radius
    R = torch.tensor([[1, 0, 0], [0, np.cos(0.3), -np.sin(0.3)], [0, np.sin(0.3), np.cos(0.3)]], dtype=F64)
    ends = sorted([a[0], b[0]], key=lambda p: float(p @ R[:, 2]))
    mid = torch.tensor([0, 0, 0.2], dtype=F64)
    torch.testing.assert_close(ends[0], mid - 0.2 * R[:, 2], atol=1e-6, rtol=0)
    torch.testing.assert_close(ends[1], mid + 0.2 * R[:, 2], atol=1e-6, rtol=0)
    assert r[0].item() == pytest.approx(0.05, abs=1e-6)
    # the ellipsoid (scaled ×2): every vertex inside, and tighter than its bounding sphere (radius 0.2)
    v = torch.tensor(blob.vertices * 2.0, dtype=F64) + torch.tensor([0.1, 0, 0], dtype=F64)
    from diffkin.collision import sphere_capsule

    inside = sphere_capsule(v, torch.zeros((), dtype=F64), a[1], b[1], r[1])  # STL: float32 vertices
    assert (inside <= 1e-7).all() and r[1] < 0.2


def test_the_model_does_not_import_the_collision_layer():
    """Dependencies point one way: the collision layer sits above the model (chain, kernels, models,
    transforms, calibration, ...) and below what builds on it (IK's distance constraints, motion planning,
    retargeting, the viewer, the demo and the command line); nothing of the model names diffkin.collision,
    and diffkin.collision names nothing of those above it."""
    root = Path(diffkin.__file__).parent
    above = {root / "__init__.py", *(root / "demo").rglob("*.py")}
    above |= {p for d in ("cli", "viz", "ik", "motion", "retarget") for p in (root / d).rglob("*.py")}
    files = [p for p in root.rglob("*.py") if "collision" not in p.relative_to(root).parts and p not in above]
    pattern = re.compile(r"^\s*(from\s+(\.+|diffkin\.)collision"
                         r"|from\s+(\.+|diffkin)\s+import\s.*\bcollision\b"
                         r"|import\s+diffkin\.collision)", re.M)
    assert len(files) > 20 and [str(p) for p in files if pattern.search(p.read_text())] == []
    upward = re.compile(r"^\s*(from\s+(\.\.|diffkin\.)(ik|viz|demo|cli)\b|import\s+diffkin\.(ik|viz))", re.M)
    layer = list((root / "collision").rglob("*.py"))
    assert layer and [str(p) for p in layer if upward.search(p.read_text())] == []


def test_parse_collisions_rejects_malformed_elements():
    from diffkin.errors import ModelError

    def urdf(geometry: str) -> str:
        return (f'<robot name="r"><link name="a"><collision><geometry>{geometry}</geometry></collision>'
                "</link></robot>")

    assert parse_collisions(urdf('<sphere radius="0.1"/>'))["a"][0].size == (0.1,)
    assert parse_collisions(urdf('<box size="1 2 3"/>'))["a"][0].size == (1.0, 2.0, 3.0)
    for bad, match in (('<sphere radius="-1"/>', "radius"), ("<cylinder radius='1'/>", "length"),
                       ('<box size="1 2"/>', "3 numbers"), ("<mesh/>", "filename"), ("", "no <geometry>")):
        with pytest.raises(ModelError, match=match):
            parse_collisions(urdf(bad))


def test_world_validation():
    from diffkin.errors import DiffkinError, DTypeError, ShapeError

    with pytest.raises(ShapeError, match="spheres"):
        World(spheres=[[0.0, 0.0, 0.0]])
    with pytest.raises(DiffkinError, match="unit half-space normals"):
        World(halfspaces=[[0.0, 0.0, 2.0, 0.0]])
    with pytest.raises(DiffkinError, match="diffkin.collision.box"):
        World(boxes=[[0.0, 0.0, 0.0]])
    with pytest.raises(DTypeError):
        World(spheres=torch.zeros(1, 4, dtype=torch.float32), boxes=box([0, 0, 0], [1, 1, 1], dtype=F64))
    chain, rc = _robot(BOXY, "l3")
    with pytest.raises(DiffkinError, match="dtype"):
        rc.world_distances(torch.zeros(3, dtype=F64), World(spheres=torch.zeros(1, 4, dtype=torch.float32)))
    w = World()
    assert len(w) == 0 and rc.world_distances(torch.zeros(3, dtype=F64), World(dtype=F64)).shape == (6, 0)
    assert rc.min_distance(torch.zeros(3, dtype=F64), World(dtype=F64)) == rc.self_distances(
        torch.zeros(3, dtype=F64)).min()


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    chain, rc = _robot(BOXY, "l3")
    q = _random_q(chain, 64, seed=8)
    world = World(spheres=[[0.2, 0.1, 0.5, 0.05]], boxes=box([0.3, 0, 0.3], [0.05, 0.1, 0.2], dtype=F64),
                  halfspaces=[[0, 0, 1.0, -0.01]], dtype=F64)
    cpu = (rc.self_distances(q), rc.world_distances(q, world))
    rc.cuda()
    world_gpu = World(spheres=world.spheres.cuda(), boxes=box(world.boxes.center.cuda(),
                      world.boxes.half_extents.cuda()), halfspaces=world.halfspaces.cuda())
    gpu = (rc.self_distances(q.cuda()), rc.world_distances(q.cuda(), world_gpu))
    for a, b in zip(cpu, gpu):
        torch.testing.assert_close(b.cpu(), a, atol=1e-10, rtol=0)
