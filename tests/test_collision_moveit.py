"""VAMP's Panda files and the MotionBenchMaker problems (tests/data/vamp_panda, read unchanged): the URDF with
a <mimic> on a fixed finger joint, the spherized URDF as a RobotCollision (against coal with Pinocchio's
placements), MoveIt PlanningScene YAML into a World (poses against scipy, distances against coal), the
allowed-collision matrix as pair rules, and the benchmark's problem loader."""

from __future__ import annotations

import tarfile

import collision_reference as ref
import numpy as np
import pytest
import torch
import yaml
from scipy.spatial.transform import Rotation

import diffkin
from benchmarks import motion_problems as mp
from diffkin.collision import RobotCollision, read_world
from diffkin.collision.moveit import read_scene
from diffkin.errors import ConventionError, ModelError

pin = pytest.importorskip("pinocchio")
coal = ref.coal
F64 = torch.float64
DATA = mp.DATA


@pytest.fixture(scope="module")
def problems():
    """Problems 1-7 and 41 of the cage, box and table_pick families (one pass over the archive)."""
    return mp.load_problems(families={"cage", "box", "table_pick"}, indices={*range(1, 8), 41})


@pytest.fixture(scope="module")
def cage(problems):
    return [p for p in problems if p.family == "cage" and p.index <= 7]


@pytest.fixture(scope="module")
def spherized():
    chain = diffkin.models.from_urdf(mp.PANDA_SPHERIZED_URDF, "panda_hand", dtype=F64)
    return chain, RobotCollision.from_urdf(mp.PANDA_SPHERIZED_URDF, chain, mp.PANDA_SRDF)


def _random_q(chain, n, seed):
    lo, hi = chain.q_limits.T
    g = torch.Generator().manual_seed(seed)
    return lo + (hi - lo) * torch.rand(n, chain.n_joints, dtype=F64, generator=g)


# ------------------------------------------------------------------------------ URDF: mimic on a fixed joint

def test_vamp_panda_urdf_with_mimic_on_fixed_finger_joint_against_pinocchio():
    """VAMP's panda.urdf: panda_finger_joint2 (fixed) mimics panda_finger_joint1 (fixed): accepted, the
    mimic inert (as ROS). The 7 arm joints are the variables; the hand and both fingers (fixed links
    included) are where Pinocchio puts them."""
    chain = diffkin.models.from_urdf(mp.PANDA_URDF, ["panda_hand", "panda_leftfinger", "panda_rightfinger"],
                                     dtype=F64)
    assert chain.joint_names == list(mp.PANDA_JOINTS)
    tree = diffkin.models.urdf_xml.parse_urdf(mp.PANDA_URDF)
    j2 = tree.joint("panda_finger_joint2")
    assert j2.type == "fixed" and j2.mimic is not None and j2.mimic[0] == "panda_finger_joint1"
    model = pin.buildModelFromUrdf(str(mp.PANDA_URDF))
    data = model.createData()
    q = _random_q(chain, 10, seed=3)
    T = chain.forward_kinematics(q).detach().numpy()  # (10, 3, 4, 4)
    for b in range(len(q)):
        pin.framesForwardKinematics(model, data, q[b].numpy())
        for k, name in enumerate(["panda_hand", "panda_leftfinger", "panda_rightfinger"]):
            M = data.oMf[model.getFrameId(name)]
            np.testing.assert_allclose(T[b, k, :3, :3], M.rotation, atol=1e-12)
            np.testing.assert_allclose(T[b, k, :3, 3], M.translation, atol=1e-12)


def test_mimic_on_a_fixed_joint_is_inert_but_a_moving_follower_of_a_fixed_joint_is_an_error():
    base = ('<robot name="t"><link name="a"/><link name="b"/><link name="c"/>'
            '<joint name="f1" type="fixed"><parent link="a"/><child link="b"/></joint>'
            '<joint name="f2" type="{t}"><parent link="b"/><child link="c"/><axis xyz="0 0 1"/>'
            '<limit lower="-1" upper="1"/><mimic joint="f1" multiplier="-1"/></joint></robot>')
    tree = diffkin.models.urdf_xml.parse_urdf(base.format(t="fixed"))
    assert tree.joint("f2").mimic == ("f1", -1.0, 0.0)
    with pytest.raises(ModelError, match="'f2' mimics 'f1', which is fixed"):
        diffkin.models.urdf_xml.parse_urdf(base.format(t="revolute"))


@pytest.mark.extended
def test_vamp_panda_capsule_model_covers_every_collision_mesh_fingers_included():
    """Today's default model of VAMP's panda.urdf (meshes fitted by capsules; ~10 s): a geom on every link
    with a <collision> (both fixed fingers included), and every vertex of each OBJ (read by trimesh), placed
    by Pinocchio's frames, inside the union of that mesh's capsules."""
    trimesh = pytest.importorskip("trimesh")
    import xml.etree.ElementTree as ET

    chain = diffkin.models.from_urdf(mp.PANDA_URDF, "panda_hand", dtype=F64)
    rc = RobotCollision.from_urdf(mp.PANDA_URDF, chain, mp.PANDA_SRDF)
    root = ET.parse(mp.PANDA_URDF).getroot()
    meshes = {}  # link -> (mesh file, collision origin (4, 4))
    for link in root.iter("link"):
        for c in link.findall("collision"):
            o = c.find("origin")
            T = np.eye(4)
            if o is not None:  # URDF rpy: R = Rz(y) Ry(p) Rx(r), scipy's extrinsic "xyz"
                rpy = [float(x) for x in o.get("rpy", "0 0 0").split()]
                T[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()
                T[:3, 3] = [float(x) for x in o.get("xyz", "0 0 0").split()]
            meshes[link.get("name")] = (c.find("geometry/mesh").get("filename").replace("package://", ""), T)
    assert {g.link for g in rc.geoms} == set(meshes)
    assert {"panda_leftfinger", "panda_rightfinger"} <= set(meshes)
    model = pin.buildModelFromUrdf(str(mp.PANDA_URDF))
    data = model.createData()
    q = _random_q(chain, 3, seed=11)
    with torch.no_grad():
        a, b, r, *_ = rc.placed(q)
    for s in range(len(q)):
        pin.framesForwardKinematics(model, data, q[s].numpy())
        for link, (file, T) in meshes.items():
            M = data.oMf[model.getFrameId(link)].homogeneous @ T
            v = trimesh.load(DATA / file, force="mesh").vertices @ M[:3, :3].T + M[:3, 3]
            ks = [k for k, g in enumerate(g for g in rc.geoms if g.shape == "capsule") if g.link == link]
            inside = np.zeros(len(v), dtype=bool)
            for k in ks:
                A, B = a[s, k].numpy(), b[s, k].numpy()
                t = np.clip((v - A) @ (B - A) / max((B - A) @ (B - A), 1e-18), 0.0, 1.0)
                radius = float(r[k].detach())
                inside |= np.linalg.norm(v - (A + t[:, None] * (B - A)), axis=1) <= radius + 1e-9
            assert inside.all(), (link, (~inside).sum())


# ------------------------------------------------------------------------------ the spherized URDF

def test_spherized_panda_self_distances_against_coal_placed_by_pinocchio(spherized):
    """Every <sphere> collision of VAMP's spherized URDF is a geom (counted from the XML), and the checked
    pairs' distances are coal's for the spheres Pinocchio's own parser and FK place."""
    chain, rc = spherized
    import xml.etree.ElementTree as ET

    root = ET.parse(mp.PANDA_SPHERIZED_URDF).getroot()
    spheres = [(link.get("name"), float(c.find("geometry/sphere").get("radius")))
               for link in root.iter("link") for c in link.findall("collision")]
    assert len(spheres) == 59 and {g.kind for g in rc.geoms} == {"sphere"}
    assert sorted((g.link, float(r)) for g, r in zip(rc.geoms, rc.capsule_radius.detach())) == sorted(spheres)
    model = pin.buildModelFromUrdf(str(mp.PANDA_SPHERIZED_URDF))
    gmodel = pin.buildGeomFromUrdf(model, str(mp.PANDA_SPHERIZED_URDF), pin.COLLISION)
    data, gdata = model.createData(), pin.GeometryData(gmodel)
    per_link: dict[str, int] = {}
    index = {}  # Pinocchio names a link's collisions '<link>_<i>'
    for g in rc.geoms:
        index[g.name] = gmodel.getGeometryId(f"{g.link}_{per_link.setdefault(g.link, 0)}")
        per_link[g.link] += 1
    q = _random_q(chain, 40, seed=5)
    with torch.no_grad():
        d = rc.self_distances(q).numpy()
    want = np.empty_like(d)
    for b in range(len(q)):
        pin.updateGeometryPlacements(model, data, gmodel, gdata, q[b].numpy())
        for p, (ga, gb) in enumerate(rc.pairs):
            i, j = index[ga], index[gb]
            want[b, p] = ref.distance(gmodel.geometryObjects[i].geometry, gdata.oMg[i],
                                      gmodel.geometryObjects[j].geometry, gdata.oMg[j])
    assert (want < 0).any() and (want > 0).mean() > 0.5
    np.testing.assert_allclose(d, want, atol=1e-9, rtol=0)


# ------------------------------------------------------------------------------ MoveIt scenes

HAND_WRITTEN = """
name: hand written
robot_state:
  joint_state: {name: [j1, j2], position: [0.5, -1]}
allowed_collision_matrix:
  entry_names: [panda_link1, panda_link5, panda_hand, table]
  entry_values:
    - [false, true, false, false]
    - [true, false, true, false]
    - [false, true, false, true]
    - [false, false, true, false]
world:
  collision_objects:
    - id: ball
      primitives: [{type: sphere, dimensions: [0.05]}]
      primitive_poses: [{position: [0.5, 0.1, 0.4], orientation: [0, 0, 0, 1]}]
    - id: table
      pose: {position: [0.6, 0, 0.2], orientation: [0, 0, 0.3826834323650898, 0.9238795325112867]}
      primitives:
        - {type: 1, dimensions: [0.8, 0.4, 0.04]}
        - {type: cylinder, dimensions: [0.3, 0.02]}
      primitive_poses:
        - {position: [0, 0, 0], orientation: [0, 0, 0, 1]}
        - {position: [0.3, 0.1, -0.15], orientation: [0.7071067811865476, 0, 0, 0.7071067811865476]}
"""


def _pose(position, quat_xyzw):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(quat_xyzw).as_matrix()  # scipy's quaternions are (x, y, z, w)
    T[:3, 3] = position
    return T


def test_hand_written_scene_poses_against_scipy_and_acm_pairs(tmp_path):
    sc = read_scene(HAND_WRITTEN)
    assert [(p.name, p.kind, p.dimensions) for p in sc.objects] == [
        ("ball", "sphere", (0.05,)), ("table/0", "box", (0.8, 0.4, 0.04)),
        ("table/1", "cylinder", (0.3, 0.02))]
    base = _pose([0.6, 0, 0.2], [0, 0, 0.3826834323650898, 0.9238795325112867])
    want = base @ _pose([0.3, 0.1, -0.15], [0.7071067811865476, 0, 0, 0.7071067811865476])
    np.testing.assert_allclose(sc.objects[2].pose.numpy(), want, atol=1e-12)
    np.testing.assert_allclose(sc.objects[1].pose.numpy(), base, atol=1e-12)
    pairs = [("panda_link1", "panda_link5"), ("panda_link5", "panda_hand"), ("panda_hand", "table")]
    assert sc.allowed == {frozenset(p) for p in pairs}
    assert dict(sc.joint_state) == {"j1": 0.5, "j2": -1.0} and sc.name == "hand written"
    path = tmp_path / "scene.yaml"
    path.write_text(HAND_WRITTEN)
    w = read_world(path, dtype=F64)
    assert len(w) == 3 and sc.world_names[0] == "ball"
    np.testing.assert_allclose(w.spheres.numpy(), [[0.5, 0.1, 0.4, 0.05]])
    np.testing.assert_allclose(w.boxes.rotation[0].numpy(), base[:3, :3], atol=1e-12)
    np.testing.assert_allclose(w.boxes.half_extents[0].numpy(), [0.4, 0.2, 0.02])
    # the cylinder: its axis is the local z axis of its pose, ends at ± height / 2
    axis, c = want[:3, 2], want[:3, 3]
    cyl = w.capsules if w.capsules.shape[0] else w.cylinders
    np.testing.assert_allclose(cyl[0, :6].numpy(), np.r_[c - 0.15 * axis, c + 0.15 * axis], atol=1e-12)
    assert float(cyl[0, 6]) == 0.02
    held = sc.to_world(dtype=F64, cylinders="capsules")  # the enclosing capsule on request, in any World
    torch.testing.assert_close(held.capsules, cyl, rtol=0, atol=0)
    assert sc.column_names("capsules") == ["ball", "table/1", "table/0"]
    with pytest.raises(ConventionError,
                       match="expected cylinders as 'exact', 'capsules' or None, got 'cones'"):
        sc.to_world(cylinders="cones")


_OBJ = r"world.collision_objects\[1\] \('table'\)"


def _sub(old: str, new: str):
    return lambda text: text.replace(old, new)


_EDITS = {  # id: (edit of HAND_WRITTEN, what the ModelError says: the entry, what was expected, what came)
    "cone": (_sub("type: sphere", "type: cone"),
             r"primitives\[0\]: primitive type 'cone' is not supported \(expected box, sphere or cylinder\)"),
    "asymmetric-acm": (_sub("- [false, true, false, false]", "- [false, false, false, false]"),
                       r"allowed_collision_matrix: expected a symmetric matrix, not symmetric: "
                       r"\(panda_link1, panda_link5\) is False but \(panda_link5, panda_link1\) is True"),
    "dimensions": (_sub("dimensions: [0.05]", "dimensions: [0.05, 1]"),
                   r"primitives\[0\].dimensions: expected 1 numbers, got 2"),
    "zero-quaternion": (_sub("orientation: [0, 0, 0, 1]}]\n    - id: table",
                             "orientation: [0, 0, 0, 0]}]\n    - id: table"),
                        r"primitive_poses\[0\].orientation: expected a non-zero quaternion, "
                        r"got \[0.0, 0.0, 0.0, 0.0\]"),
    "mesh": (_sub("primitives: [{type: sphere", "meshes: [{}]\n      primitives: [{type: sphere"),
             r"meshes are not supported \(expected primitives: boxes, spheres and cylinders only, "
             r"got meshes\)"),
    "flat-cylinder": (_sub("dimensions: [0.3, 0.02]", "dimensions: [0.0, 0.02]"),
                      _OBJ + r".primitives\[1\].dimensions: expected a cylinder height > 0, got 0.0"),
    "poses": (_sub("        - {position: [0, 0, 0], orientation: [0, 0, 0, 1]}\n", ""),
              _OBJ + ": expected one primitive_pose per primitive, got 2 primitives and 1 primitive_poses"),
    "operation": (_sub("    - id: table\n", "    - id: table\n      operation: remove\n"),
                  _OBJ + r": expected operation add \(0\) or append .*, got 'remove'"),
    "yaml": (lambda t: t + "  bad: [\n", "expected PlanningScene YAML, cannot read it"),
}


@pytest.mark.parametrize("edit, match", list(_EDITS.values()), ids=list(_EDITS))
def test_scene_errors_name_the_entry(edit, match):
    with pytest.raises(ModelError, match=match):
        read_scene(edit(HAND_WRITTEN))


def test_scene_source_errors(tmp_path):
    with pytest.raises(ModelError, match=r"scene file '.*nowhere.yaml' not found \(expected an existing"):
        read_scene(tmp_path / "nowhere.yaml")
    with pytest.raises(ModelError, match="expected a scene as a path, YAML text or a mapping, got int"):
        read_scene(3)
    with pytest.raises(ModelError, match="not a MoveIt PlanningScene .*got keys spheres"):
        read_scene({"spheres": [[0, 0, 0, 1]]})


def test_real_scene_world_distances_against_coal(cage):
    """Cage scenes from the archive: a probe sphere's World distance to every box is coal's to the box the
    file describes (placed with scipy's quaternion); to a cylinder it is never above coal's distance to the
    true cylinder and equal where the probe faces its side (the World holds its enclosing capsule until exact
    cylinders land)."""
    rng = np.random.default_rng(0)
    for problem in cage[:3]:
        tar_scene = problem.scene
        w = tar_scene.to_world(dtype=F64)
        probes = np.c_[rng.uniform([-0.2, -0.8, 0.0], [1.0, 0.8, 1.2], (50, 3)), rng.uniform(0.0, 0.1, 50)]
        a = torch.tensor(probes[:, None, :3])  # (50, 1, 3): one zero-length capsule per row
        d = w.distances(a, a, torch.tensor(probes[:, 3:4]), a.new_zeros(50, 0, 3), a.new_zeros(50, 0, 3, 3),
                        a.new_zeros(50, 0, 3))[:, 0, :].numpy()  # (50, W)
        names = tar_scene.world_names
        for prim in tar_scene.objects:
            col = names.index(prim.name)
            T = prim.pose.numpy()
            if prim.kind == "box":
                shape = coal.Box(*prim.dimensions)
            else:
                shape = coal.Cylinder(prim.dimensions[1], prim.dimensions[0])
            Tc = ref.placement(T[:3, :3], T[:3, 3])
            want = np.array([ref.distance(coal.Sphere(max(r, 1e-9)), ref.placement(None, p), shape, Tc)
                             for *p, r in probes])
            if prim.kind == "box":
                np.testing.assert_allclose(d[:, col], want, atol=1e-8)
            else:
                side = np.abs((probes[:, :3] - T[:3, 3]) @ T[:3, 2]) < prim.dimensions[0] / 2
                assert (d[:, col] <= want + 1e-8).all()
                np.testing.assert_allclose(d[side, col], want[side], atol=1e-8)


def test_real_scene_file_matches_the_raw_yaml(cage):
    """The loader's problem 7 of the cage family against the archive member read by PyYAML directly."""
    p = next(x for x in cage if x.index == 7)
    with tarfile.open(mp.ARCHIVE, "r:bz2") as tar:
        raw = {m.name: yaml.safe_load(tar.extractfile(m).read()) for m in tar
               if m.name in ("problems/cage_panda/scene0007.yaml", "problems/cage_panda/request0007.yaml")}
    scene, request = raw["problems/cage_panda/scene0007.yaml"], raw["problems/cage_panda/request0007.yaml"]
    objs = scene["world"]["collision_objects"]
    assert [o.name for o in p.scene.objects] == [o["id"] for o in objs]
    for o, prim in zip(objs, p.scene.objects):
        pp = o["primitive_poses"][0]
        np.testing.assert_allclose(prim.pose.numpy(), _pose(pp["position"], pp["orientation"]), atol=1e-12)
    js = request["start_state"]["joint_state"]
    assert p.start == tuple(js["position"][js["name"].index(j)] for j in mp.PANDA_JOINTS)
    goal = {c["joint_name"]: c["position"] for c in request["goal_constraints"][0]["joint_constraints"]}
    assert p.goal == tuple(goal[j] for j in mp.PANDA_JOINTS)
    acm = scene["allowed_collision_matrix"]
    n = acm["entry_names"]
    assert p.scene.allowed == {frozenset((n[i], n[j])) for i in range(len(n)) for j in range(len(n))
                               if i != j and acm["entry_values"][i][j]}
    assert [(x.family, x.index) for x in cage] == [("cage", i) for i in range(1, 8)]


# ------------------------------------------------------------------------------ allowed pairs as pair rules

def test_allow_collisions_drops_exactly_the_allowed_link_pairs(spherized, cage):
    chain, rc = spherized
    # the MBM matrix allows what the SRDF disables: nothing more to drop
    assert rc.allow_collisions(cage[0].scene.allowed).pairs == rc.pairs
    link = {g.name: g.link for g in rc.geoms}
    rule = {frozenset(("panda_link1", "panda_link5")), frozenset(("panda_link5", "panda_hand"))}
    out = rc.allow_collisions(read_scene(HAND_WRITTEN).allowed - {frozenset(("panda_hand", "table"))})
    kept = [p for p in rc.pairs if frozenset((link[p[0]], link[p[1]])) not in rule]
    assert out.pairs == kept and len(kept) < len(rc.pairs)
    q = _random_q(chain, 8, seed=2)
    with torch.no_grad():
        full, mine = rc.self_distances(q), out.self_distances(q)
    cols = [rc.pairs.index(p) for p in kept]
    torch.testing.assert_close(mine, full[:, cols], rtol=0, atol=0)
    with pytest.raises(ModelError, match="robot-object"):
        rc.allow_collisions(read_scene(HAND_WRITTEN).allowed)
    # object-object entries are ignored
    assert rc.allow_collisions([("table", "shelf")]).pairs == rc.pairs


# ------------------------------------------------------------------------------ the benchmark's counts

def test_benchmark_counts_against_coal_and_pinocchio(problems, spherized):
    """The benchmark's verdicts for the spherized Panda on 24 problems (VAMP's one invalid problem,
    table_pick 41, among them) are those of coal with the spheres placed by Pinocchio against the scene's
    true boxes and cylinders; with cylinders as capsules the box family's goals are flagged too (their
    caps)."""
    from benchmarks import bench_motion_problems as bench

    chain, rc = spherized
    model = pin.buildModelFromUrdf(str(mp.PANDA_SPHERIZED_URDF))
    gmodel = pin.buildGeomFromUrdf(model, str(mp.PANDA_SPHERIZED_URDF), pin.COLLISION)
    data, gdata = model.createData(), pin.GeometryData(gmodel)
    want = {}
    for p in problems:
        shapes = [(coal.Box(*o.dimensions) if o.kind == "box" else coal.Cylinder(*o.dimensions[::-1]),
                   ref.placement(o.pose[:3, :3].numpy(), o.pose[:3, 3].numpy())) for o in p.scene.objects]
        states = []
        for q in (p.start, p.goal):
            pin.updateGeometryPlacements(model, data, gmodel, gdata, np.array(q))
            states.append(any(ref.collide(go.geometry, gdata.oMg[i], *s)
                              for i, go in enumerate(gmodel.geometryObjects) for s in shapes))
        want.setdefault(p.family, []).append(states)
    rows = {r["family"]: r for r in bench.run(models=("spherized",), problems=problems)}
    for family, states in want.items():
        st = np.array(states)
        assert rows[family]["start"] == st[:, 0].sum() and rows[family]["goal"] == st[:, 1].sum()
        assert rows[family]["start_or_goal"] == st.any(1).sum() and rows[family]["self"] == 0
    assert rows["all"]["start_or_goal"] == 1 and rows["table_pick"]["goal"] == 1  # table_pick 41's goal
    capsules = {r["family"]: r for r in bench.run(models=("spherized",), problems=problems,
                                                  cylinders="capsules")}
    assert capsules["box"]["goal"] > 0 and capsules["all"]["start_or_goal"] > 1


@pytest.mark.extended
def test_spherized_panda_finds_vamps_one_invalid_problem():
    """VAMP's resources README: 699 of the 700 problems are valid for its spherized Panda (the one left a
    start or goal in collision); the benchmark's count with the same spheres and exact cylinders agrees."""
    from benchmarks import bench_motion_problems

    rows = bench_motion_problems.run(models=("spherized",))
    total = next(r for r in rows if r["family"] == "all")
    assert total["problems"] == 700 and sum(r["problems"] for r in rows if r["family"] != "all") == 700
    assert total["start_or_goal"] == 1
