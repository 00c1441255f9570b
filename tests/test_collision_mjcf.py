"""RobotCollision.from_mjcf against MuJoCo: the pairs are exactly those MuJoCo's own collision filters let
through (every pair it reports with a large margin), distances against ``mj_geomDistance`` with the bodies
placed by MuJoCo's FK, and every contact ``mj_collision`` reports is a checked pair with a negative
distance. (The MJCF chain is not there yet: the body poses come in as a callable.)"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from mujoco_reference import MuJoCoPoses, random_qpos

from diffkin.collision import RobotCollision

mujoco = pytest.importorskip("mujoco")
F64 = torch.float64

ARM = """<mujoco model="arm">
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.1"/>
    <body name="base" pos="0 0 0.1">
      <geom name="base_box" type="box" size="0.15 0.15 0.05"/>
      <body name="l1" pos="0 0 0.05">
        <joint name="j1" type="hinge" axis="0 0 1"/>
        <geom name="l1_cap" type="capsule" fromto="0 0 0 0 0 0.4" size="0.05"/>
        <body name="l2" pos="0 0 0.4">
          <joint name="j2" type="hinge" axis="0 1 0" range="-2.5 2.5"/>
          <geom type="capsule" fromto="0 0 0 0.35 0 0" size="0.04"/>
          <geom type="sphere" pos="0.35 0 0" size="0.06" contype="2" conaffinity="2"/>
          <body name="l2_plate" pos="0.2 0 0.05" quat="0.9 0.1 0.3 0.2">
            <geom name="plate" type="box" size="0.08 0.03 0.01"/>
          </body>
          <body name="l3" pos="0.35 0 0">
            <joint name="j3" type="hinge" axis="0 1 0" range="-2.8 2.8"/>
            <geom name="l3_cap" type="capsule" fromto="0 0 0 -0.3 0 0.05" size="0.035"/>
            <geom name="l3_box" type="box" pos="-0.32 0 0.05" size="0.04 0.06 0.02" euler="0.3 0.2 0.1"/>
            <body name="l4" pos="-0.3 0 0.05">
              <joint name="j4" type="hinge" axis="1 0 0"/>
              <geom name="tip" type="sphere" pos="0 0 -0.12" size="0.04"/>
            </body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <contact>
    <exclude body1="l1" body2="l3"/>
    <pair geom1="l1_cap" geom2="tip"/>
  </contact>
</mujoco>"""


def _robot():
    m = mujoco.MjModel.from_xml_string(ARM)
    return m, RobotCollision.from_mjcf(m, body_poses=MuJoCoPoses(m), dtype=F64)


def _random_q(m, n, seed):
    rng = np.random.default_rng(seed)
    lo, hi = np.where(m.jnt_limited[:, None], m.jnt_range, [[-np.pi, np.pi]]).T
    return torch.tensor(rng.uniform(lo, hi, (n, m.nq)), dtype=F64)


def test_names_and_the_pairs_mujoco_checks():
    m, rc = _robot()
    assert [g.name for g in rc.geoms] == ["base_box", "l1_cap", "l2/0", "l2/1", "plate", "l3_cap", "l3_box",
                                          "tip"]
    assert "floor" not in [g.name for g in rc.geoms]  # the world body's geoms are the surroundings
    # MuJoCo itself: with a 10 m margin every pair its filters let through reports a contact (the margin
    # is set in the XML: the compiler sizes the broad phase's bounding volumes with it)
    wide = '<mujoco model="arm"><default><geom margin="10"/></default>'
    big = mujoco.MjModel.from_xml_string(ARM.replace('<mujoco model="arm">', wide))
    d = mujoco.MjData(big)
    mujoco.mj_forward(big, d)
    name = lambda g: rc.geoms[[x for x in range(big.ngeom) if big.geom_bodyid[x]].index(g)].name  # noqa: E731
    theirs = {tuple(sorted((name(c.geom1), name(c.geom2)))) for c in d.contact[: d.ncon]
              if big.geom_bodyid[c.geom1] and big.geom_bodyid[c.geom2]}
    assert {tuple(sorted(p)) for p in rc.pairs} == theirs
    assert ("l1_cap", "tip") in rc.pairs and ("l1_cap", "l3_cap") not in rc.pairs  # <pair>, <exclude>


def test_distances_against_mj_geom_distance_and_contacts():
    m, rc = _robot()
    d = mujoco.MjData(m)
    gid = {g.name: i for i, g in zip([x for x in range(m.ngeom) if m.geom_bodyid[x]], rc.geoms)}
    q = _random_q(m, 300, seed=0)
    ours = rc.self_distances(q).detach().numpy()
    fromto = np.zeros(6)
    negative = 0
    for b in range(len(q)):
        d.qpos[:] = q[b].numpy()
        mujoco.mj_forward(m, d)
        want = [mujoco.mj_geomDistance(m, d, gid[a], gid[c], 10.0, fromto) for a, c in rc.pairs]
        np.testing.assert_allclose(ours[b], want, atol=1e-6, rtol=0)
        index = {tuple(sorted((gid[a], gid[c]))): p for p, (a, c) in enumerate(rc.pairs)}
        for c in d.contact[: d.ncon]:
            if m.geom_bodyid[c.geom1] and m.geom_bodyid[c.geom2]:
                p = index[tuple(sorted((c.geom1, c.geom2)))]  # a checked pair...
                assert ours[b, p] < 1e-9  # ... in contact
                negative += 1
    assert negative > 10


def test_gradients_through_the_poses_and_missing_poses():
    m = mujoco.MjModel.from_xml_string(ARM)
    poses = MuJoCoPoses(m)
    T0 = poses(_random_q(m, 4, seed=1)).requires_grad_(True)
    rc = RobotCollision.from_mjcf(ARM, body_poses=lambda q: T0, dtype=F64)
    (g,) = torch.autograd.grad(rc.min_distance(torch.zeros(4, m.nq, dtype=F64)).sum(), T0)
    assert torch.isfinite(g).all() and g.abs().sum() > 0
    from diffkin.errors import ModelError

    with pytest.raises(ModelError, match="body_poses"):
        RobotCollision.from_mjcf(ARM)


def test_fr3_through_mujocos_urdf_compiler_matches_from_urdf():
    """MuJoCo compiles the FR3 URDF (meshes dropped, static bodies kept): from_mjcf on it, posed by the URDF
    chain's link frames, finds from_urdf's 297 pairs (MuJoCo's weld and parent filters are the URDF adjacency
    rule) plus link 0 × link 1, which MuJoCo does not filter (link 0 is welded to the world, and the parent
    filter skips world-welded bodies), and the same distances."""
    import re
    import warnings
    from pathlib import Path

    import diffkin
    from diffkin.collision._poses import LinkFrames

    path = Path(__file__).parent / "data" / "urdf" / "fr3.urdf"
    mesh = r"<collision>\s*<geometry>\s*<mesh[^>]*/>\s*</geometry>\s*</collision>"
    text = re.sub(mesh, "", path.read_text())
    text = re.sub(r"<visual>.*?</visual>", "", text, flags=re.S).replace(
        '<robot name="fr3">', '<robot name="fr3"><mujoco><compiler fusestatic="false"/></mujoco>')
    m = mujoco.MjModel.from_xml_string(text)
    chain = diffkin.models.from_urdf(path, "fr3_link8", dtype=F64)
    frames = LinkFrames(chain)
    rows = torch.tensor([frames.index[m.body(b).name] for b in range(1, m.nbody)])

    def body_poses(q):
        T = frames.poses(chain, q).index_select(-3, rows)
        return torch.cat((torch.eye(4, dtype=F64).expand(*T.shape[:-3], 1, 4, 4), T), -3)

    mj = RobotCollision.from_mjcf(m, chain, body_poses=body_poses)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        urdf = RobotCollision.from_urdf(path, chain)
    rename = {g.name: u.name for g, u in zip(mj.geoms, urdf.geoms)}
    assert [g.link for g in mj.geoms] == [g.link for g in urdf.geoms]
    theirs = [(rename[a], rename[b]) for a, b in mj.pairs]
    base = {p for p in theirs if p[0].startswith("fr3_link0_sc") and p[1].startswith("fr3_link1_sc")}
    assert len(base) == 9 and sorted(set(theirs) - base) == sorted(urdf.pairs)
    q = chain.random_configuration((64,), generator=torch.Generator().manual_seed(0))
    order = [theirs.index(p) for p in urdf.pairs]
    torch.testing.assert_close(mj.self_distances(q)[:, order], urdf.self_distances(q), atol=1e-12, rtol=0)


# Real MuJoCo Menagerie robots (tests/data/mjcf, XML only: their mesh geoms are skipped, the primitives are
# what is tested) and the random configurations drawn for each: 3 300 in all.
MENAGERIE = Path(__file__).parent / "data" / "mjcf"
REAL = [("universal_robots_ur5e/ur5e.xml", 1000), ("unitree_h1/h1.xml", 400), ("unitree_go2/go2.xml", 500),
        ("kuka_iiwa_14/iiwa14.xml", 300), ("shadow_hand/right_hand.xml", 400), ("unitree_g1/g1.xml", 400),
        ("agility_cassie/cassie.xml", 300)]  # (cassie: ball joints; its pelvis ellipsoid is skipped)
_CYLINDER, _BOX = int(mujoco.mjtGeom.mjGEOM_CYLINDER), int(mujoco.mjtGeom.mjGEOM_BOX)
_SUPPORTED = {int(mujoco.mjtGeom.mjGEOM_SPHERE), int(mujoco.mjtGeom.mjGEOM_CAPSULE), _CYLINDER, _BOX}


@pytest.mark.parametrize(("path", "n"), REAL, ids=[p.split("/")[0] for p, _ in REAL])
def test_real_menagerie_robots_against_mj_geom_distance_and_mj_collision(path, n):
    """Every primitive pair (sphere, capsule, box) equals ``mj_geomDistance`` to 1e-9, except where a box
    pair penetrates: MuJoCo's box depths are not the signed distance there (they can be several cm short),
    so those are checked against coal's EPA. A pair with a cylinder (its enclosing capsule) is never
    farther than MuJoCo's true cylinder, and at most the cylinders' radii nearer (the capsule's caps reach
    r beyond the flat ends). Every contact ``mj_collision`` reports between two robot geoms is a checked
    pair, negative where MuJoCo's is."""
    from diffkin.collision.mjcf import load_model

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the mesh files are not vendored: those geoms are skipped
        m = load_model(MENAGERIE / path)
        rc = RobotCollision.from_mjcf(m, body_poses=MuJoCoPoses(m), dtype=F64)
    ids = [g for g in range(m.ngeom) if m.geom_bodyid[g] and int(m.geom_type[g]) in _SUPPORTED
           and (m.geom_contype[g] or m.geom_conaffinity[g])]  # (no <pair> names a visual geom here)
    assert len(ids) == len(rc.geoms) and len(rc.pairs) > 10
    gid = {g.name: i for g, i in zip(rc.geoms, ids)}
    pairs = np.array([(gid[a], gid[b]) for a, b in rc.pairs])
    index = {tuple(sorted(p)): k for k, p in enumerate(pairs.tolist())}
    kind = lambda t: np.isin(m.geom_type[pairs], t).any(-1)  # noqa: E731  pairs with a geom of type t
    cyl, boxes = kind(_CYLINDER), kind(_BOX) & ~kind(_CYLINDER)
    q = random_qpos(m, n, seed=len(path))
    with torch.no_grad():
        ours = rc.self_distances(torch.tensor(q, dtype=F64)).numpy()
    d = mujoco.MjData(m)
    want, contacts, deep = np.empty_like(ours), [], []
    for row in range(n):
        d.qpos[:] = q[row]
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        want[row] = [mujoco.mj_geomDistance(m, d, a, b, 10.0, None) for a, b in pairs]
        contacts += [(row, index[tuple(sorted((c.geom1, c.geom2)))], c.dist) for c in d.contact[: d.ncon]
                     if m.geom_bodyid[c.geom1] and m.geom_bodyid[c.geom2]]
        deep += [(row, k, _coal_distance(m, d, *pairs[k])) for k in np.flatnonzero(boxes & (want[row] < 0))]
    exact = ~cyl & ~(boxes & (want < 0))
    np.testing.assert_allclose(ours[exact], want[exact], atol=1e-9, rtol=0)
    if deep:
        rows, k, theirs = (np.array(x) for x in zip(*deep))
        np.testing.assert_allclose(ours[rows, k], theirs, atol=1e-8, rtol=0)
    radii = np.where(m.geom_type[pairs] == _CYLINDER, m.geom_size[pairs][..., 0], 0.0).sum(-1)
    assert (ours[:, cyl] <= want[:, cyl] + 1e-6).all() and (want - ours <= radii + 1e-6)[:, cyl].all()
    rows, k, dist = (np.array(x) for x in zip(*contacts))
    assert (ours[rows, k][dist < 0] < 0).all() and (dist < 0).sum() >= 1
    # MuJoCo's contact depths: exact for sphere/capsule pairs; box and cylinder contacts come from its
    # convex solvers, a few 1e-5 m off (measured up to 2.3e-5 m on Go2)
    tol = np.where(cyl[k] | boxes[k], 1e-4, 1e-9)
    assert (ours[rows, k] <= dist + tol).all()


def _coal_distance(m, d, a: int, b: int) -> float:
    """coal's signed distance of MuJoCo geoms a and b (spheres, capsules, boxes) where MuJoCo placed them."""
    import collision_reference as ref

    def shape(g):
        s, R, p = m.geom_size[g], d.geom_xmat[g].reshape(3, 3), d.geom_xpos[g]
        if m.geom_type[g] == _BOX:
            return ref.box(p, R, s[:3])
        half = R[:, 2] * (s[1] if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE else 0.0)
        return ref.capsule(p - half, p + half, s[0])

    return ref.distance(*shape(a), *shape(b))
