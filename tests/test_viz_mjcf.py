"""The viewer on MJCF models (issue 26 item 7) and collision geometry (issue 27 item 3).

References nobody here wrote: MuJoCo's own ``mj_kinematics`` (body and geom poses), ``mj_integratePos``
(ball and free joint slider moves), MuJoCo's compiled mesh vertices (meshes that resolve). Headless: viser
serves on loopback, nothing is rendered; no matplotlib or torch global setting is touched.
"""

from __future__ import annotations

import functools
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from diffkin import cli, models, viz

mujoco = pytest.importorskip("mujoco")
pytest.importorskip("viser")
pytest.importorskip("trimesh")

from diffkin.collision import RobotCollision, World  # noqa: E402
from diffkin.errors import DiffkinError, ShapeError  # noqa: E402
from diffkin.models.mjcf import compile_mjcf  # noqa: E402
from diffkin.models.mjcf_bodies import _companion, body_names, body_poses  # noqa: E402
from diffkin.viz.collision import CONTACT_RGB, FREE_RGB, WORLD_RGB  # noqa: E402
from diffkin.viz.mjcf import mjcf_visuals  # noqa: E402
from diffkin.viz.scene import _pose  # noqa: E402

DATA = Path(__file__).parent / "data" / "mjcf"
G1, CASSIE = DATA / "unitree_g1/g1.xml", DATA / "agility_cassie/cassie.xml"
PANDA = DATA / "franka_emika_panda/panda.xml"
F64 = torch.float64


def _quiet(fn, *a, **k):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*a, **k)


def _mj_at(model, qpos):
    d = mujoco.MjData(model)
    d.qpos[:] = np.asarray(qpos, dtype=np.float64)
    mujoco.mj_kinematics(model, d)
    return d


def _geom_id(model, name: str) -> int:
    """MuJoCo's id of a viewer geom name (the MJCF name, or "<body>/<k>": the body's k-th geom)."""
    g = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)
    if g >= 0:
        return g
    body, k = name.rsplit("/", 1)
    b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    return [i for i in range(model.ngeom) if model.geom_bodyid[i] == b][int(k)]


@pytest.fixture(scope="module")
def cassie():  # a floating base and a ball joint (the achilles rod) on the chain
    return _quiet(models.from_mjcf, CASSIE, ["left-achilles-rod", "right-foot"], dtype=F64)


# ------------------------------------------------------------------------------------ body poses
@pytest.mark.parametrize("path", sorted(DATA.glob("*/*.xml")), ids=lambda p: p.parent.name)
def test_body_poses_match_mujoco(path):
    if "joint_position_actuators" in path.name:
        pytest.skip("an include, not a model")
    model = compile_mjcf(path)[0]
    names = [model.body(b).name for b in range(1, model.nbody)]
    # a chain to one body only: the other bodies come from qpos0 / the companion chain
    chain = _quiet(models.from_mjcf, path, names[-1], dtype=F64)
    q = chain.random_configuration((3,), generator=torch.Generator().manual_seed(0))
    T = body_poses(chain, q).detach()
    assert T.shape == (3, model.nbody, 4, 4) and body_names(chain)[1:] == names
    for i in range(3):
        # joint equalities hold (ALOHA's qpos0 does not satisfy its finger couplings)
        full = _companion(chain)
        d = _mj_at(model, full.to_qpos(full.from_qpos(chain.to_qpos(q[i]))).detach().numpy())
        np.testing.assert_allclose(T[i, :, :3, 3].numpy(), d.xpos, atol=1e-10)
        np.testing.assert_allclose(T[i, :, :3, :3].numpy(), d.xmat.reshape(-1, 3, 3), atol=1e-10)


def test_body_poses_are_differentiable(cassie):
    q = cassie.random_configuration((), generator=torch.Generator().manual_seed(1)).requires_grad_()
    body_poses(cassie, q)[..., :3, 3].sum().backward()
    assert torch.isfinite(q.grad).all() and q.grad.abs().sum() > 0


# ------------------------------------------------------------------------------- drawn geoms = FK
def test_geoms_drawn_at_mujoco_poses(cassie):
    model = compile_mjcf(CASSIE)[0]
    v = _quiet(viz.show, cassie, port=0)
    try:
        assert v.visual_geoms and v.has_meshes
        for seed in (0, 1):
            q = cassie.random_configuration((), generator=torch.Generator().manual_seed(seed))
            v.set_q(q)
            d = _mj_at(model, cassie.to_qpos(v.q).numpy())
            G = v.geom_poses()
            ids = [_geom_id(model, g.name) for g in v.visual_geoms]
            np.testing.assert_allclose(G[:, :3, 3], d.geom_xpos[ids], atol=1e-6)  # float32 over the wire
            np.testing.assert_allclose(G[:, :3, :3], d.geom_xmat[ids].reshape(-1, 3, 3), atol=1e-6)
            # a geom's centre is its body's pose times its local offset
            B = body_poses(cassie, v.q).detach().numpy()
            for g, T in zip(v.visual_geoms, G):
                np.testing.assert_allclose(T, B[g.body] @ g.local, atol=1e-6)
    finally:
        v.close()


def test_primitive_triangles_have_the_compiled_size():
    model = compile_mjcf(G1)[0]
    geoms, missing = mjcf_visuals(G1)
    assert missing and geoms  # no meshes are vendored: the collision primitives stand in
    seen = set()
    for g in geoms:
        size = model.geom_size[_geom_id(model, g.name)]
        ext = np.ptp(g.vertices, axis=0)
        if g.kind == "box":
            np.testing.assert_allclose(ext, 2 * size, rtol=1e-6)
        elif g.kind == "sphere":
            np.testing.assert_allclose(np.linalg.norm(g.vertices, axis=1), size[0], rtol=1e-5)
        elif g.kind == "cylinder":
            np.testing.assert_allclose(ext[2], 2 * size[1], rtol=1e-6)
            assert np.linalg.norm(g.vertices[:, :2], axis=1).max() == pytest.approx(size[0], rel=1e-5)
        seen.add(g.kind)
    assert {"box", "sphere", "cylinder"} <= seen


def test_missing_meshes_still_draw():
    chain = _quiet(models.from_mjcf, PANDA, "hand", dtype=F64)
    for meshes in (True, False):
        v = viz.show(chain, port=0, meshes=meshes)
        try:
            names = set(v.server.scene._handle_from_node_name)
            assert "/robot/segments" in names and "/robot/frame_1" in names  # the skeleton
            assert len(v.missing_meshes) > 0 and all(".obj" in m or ".stl" in m for m in v.missing_meshes)
            v.set_q(chain.random_configuration(()))
            assert np.isfinite(v.geom_poses()).all()
        finally:
            v.close()


def _mesh_model(tmp_path: Path) -> Path:
    import trimesh

    (tmp_path / "parts").mkdir()
    m = trimesh.creation.icosphere(subdivisions=4, radius=0.05)  # 5 120 triangles
    m.vertices = m.vertices * [1.0, 0.6, 0.3] + [0.02, 0.0, 0.01]  # off-centre, not symmetric
    m.export(tmp_path / "parts" / "blob.obj")
    xml = """<mujoco><compiler meshdir="parts"/>
      <asset><mesh name="blob" file="blob.obj" scale="2 1 1.5"/><mesh name="gone" file="gone.stl"/></asset>
      <worldbody><body name="b1" pos="0.1 0 0.2" quat="0.9 0.1 0.3 0.2"><joint name="j1" axis="0 1 0"/>
        <geom type="mesh" mesh="blob" pos="0.05 0.02 0" euler="0.3 0.2 0.1"/>
        <geom type="mesh" mesh="gone" contype="0" conaffinity="0"/>
        <body name="b2" pos="0.3 0 0"><joint name="j2" type="ball"/><geom type="capsule" size="0.02 0.1"/>
        </body></body></worldbody></mujoco>"""
    (tmp_path / "robot.xml").write_text(xml)
    return tmp_path / "robot.xml"


def test_resolving_mesh_is_drawn_where_mujoco_puts_it(tmp_path):
    path = _mesh_model(tmp_path)
    geoms, missing = mjcf_visuals(path, max_faces=10**6)
    assert [g.kind for g in geoms] == ["mesh", "capsule"] and missing == ["b1/1 (gone.stl)"]
    # MuJoCo's own model of it, meshes loaded (the missing one removed): its vertices in the world
    spec = mujoco.MjSpec.from_file(str(path))
    spec.delete(spec.meshes[1])
    spec.delete([g for g in spec.geoms if g.meshname == "gone"][0])
    full = spec.compile()
    chain = _quiet(models.from_mjcf, path, "b2", dtype=F64)
    q = chain.random_configuration((), generator=torch.Generator().manual_seed(3))
    d = _mj_at(full, chain.to_qpos(q).numpy())
    vert = full.mesh_vert[: full.mesh_vertnum[0]]
    ref = vert @ d.geom_xmat[0].reshape(3, 3).T + d.geom_xpos[0]
    T = body_poses(chain, q).detach().numpy()[geoms[0].body] @ geoms[0].local
    ours = geoms[0].vertices @ T[:3, :3].T + T[:3, 3]
    assert len(geoms[0].faces) == 5120
    from scipy.spatial import cKDTree

    assert cKDTree(ref).query(ours)[0].max() < 1e-6 and cKDTree(ours).query(ref)[0].max() < 1e-6  # same set
    # decimated: at most the budget, the shape kept to about a cell
    small, _ = mjcf_visuals(path, max_faces=500)
    assert 50 < len(small[0].faces) <= 500
    np.testing.assert_allclose(np.ptp(small[0].vertices, axis=0), np.ptp(geoms[0].vertices, axis=0),
                               rtol=0.15)


# --------------------------------------------------------------------------- ball and free sliders
def test_ball_and_free_sliders_integrate_like_mujoco(cassie):
    model = compile_mjcf(CASSIE)[0]
    v = _quiet(viz.show, cassie, port=0)
    try:
        q0 = cassie.random_configuration((), generator=torch.Generator().manual_seed(2))
        v.set_q(q0)
        specs = v._slider_specs
        ball = [i for i, s in enumerate(specs) if s.label.startswith("left-achilles-rod.r")]
        free = [i for i, s in enumerate(specs) if s.label.startswith("joint0.")]
        assert len(ball) == 3
        assert [specs[i].label.split(".")[1] for i in free] == ["x", "y", "z", "rx", "ry", "rz"]
        assert all(v.sliders[i].value == 0.0 for i in ball + free[3:])
        moves = {ball[0]: 0.4, ball[2]: -1.1, free[4]: 0.7, free[2]: float(q0[2]) + 0.2, free[3]: 2.5}
        dofs = cassie.dof_index()
        qvel = np.zeros(model.nv)
        for i, x in moves.items():
            v.sliders[i].value = x
            s = specs[i]
            qvel[dofs[s.v]] = x - float(q0[s.q]) if s.q is not None else x
            ref = cassie.to_qpos(q0).numpy().copy()
            mujoco.mj_integratePos(model, ref, qvel, 1.0)
            got = cassie.to_qpos(v.q).numpy()
            np.testing.assert_allclose(got, ref, atol=1e-12)
            for quat in cassie.configuration_space.quaternion_index():
                assert float(v.q[list(quat)].norm()) == pytest.approx(1.0, abs=1e-12)
            np.testing.assert_allclose(v.q, cassie.integrate(q0, torch.as_tensor(
                [qvel[d] for d in dofs], dtype=F64)), atol=1e-12)
        # a new configuration from outside is the new reference: rotation sliders back to 0
        v.set_q(q0)
        assert all(v.sliders[i].value == 0.0 for i in ball + free[3:])
        np.testing.assert_allclose(v.q, q0, atol=1e-12)
    finally:
        v.close()


def test_velocity_drag_keeps_the_quaternion_unit():
    chain = _quiet(models.from_mjcf, DATA / "unitree_go2/go2.xml", "FL_calf", dtype=F64)
    v = viz.show(chain, port=0, drag="velocity")
    try:
        v.set_q(chain.neutral_configuration(), move_targets=True)
        T = v.end_poses()[0].copy()
        T[:3, 3] += [0.05, 0.03, -0.04]
        v.drag_to(T, steps=20)
        quat = list(chain.configuration_space.quaternion_index()[0])
        assert float(v.q[quat].norm()) == pytest.approx(1.0, abs=1e-12)
        assert v.ik_state["position_error"] < 0.05
    finally:
        v.close()


# ------------------------------------------------------------------------------------- collision
@pytest.fixture(scope="module")
def fr3():
    urdf = Path(__file__).parent / "data" / "urdf" / "fr3.urdf"
    chain = models.from_urdf(urdf, "fr3_link8", dtype=F64)
    srdf = '<robot name="fr3"><disable_collisions link1="fr3_link1_sc" link2="fr3_link3_sc"/></robot>'
    return chain, _quiet(RobotCollision.from_urdf, urdf, chain, srdf=srdf)  # (1-3 overlap in every pose)


def _colours(handles):
    return [tuple(int(c) for c in h.color) for h in handles]


def test_contact_colouring_follows_the_distances(fr3):
    chain, col = fr3
    qs = chain.random_configuration((400,), generator=torch.Generator().manual_seed(4))
    d = col.self_distances(qs).detach()
    hit = int(torch.nonzero((d < 0).any(-1))[0])
    world = World(spheres=[[0.0, 0.0, -5.0, 0.1]], dtype=F64)
    v = viz.show(chain, port=0, collision=col, world=world)
    try:
        names = [g.name for g in col.geoms]
        v.set_q(qs[hit])
        pairs = [(a, b) for (a, b), x in zip(col.pairs, d[hit]) if x < 0]
        assert [(a, b) for a, b, _ in v.contacts["pairs"]] == pairs
        red = {names.index(n) for p in pairs for n in p}
        cols = _colours(v._collision_view.handles)
        assert {i for i, c in enumerate(cols) if c == CONTACT_RGB} == red
        assert all(c == FREE_RGB for i, c in enumerate(cols) if i not in red)
        assert v.contacts["min_distance"] == pytest.approx(float(d[hit].min()))
        # a margin: every pair closer than it is a contact
        v2 = viz.show(chain, port=0, collision=col, margin=10.0)
        try:
            v2.set_q(qs[hit])
            assert len(v2.contacts["pairs"]) == len(col.pairs)
        finally:
            v2.close()
        # a configuration without contact: every geom back to its free colour
        free = int(torch.nonzero(~(d < 0).any(-1))[0])
        v.set_q(qs[free])
        assert v.contacts["pairs"] == [] and all(c == FREE_RGB for c in _colours(v._collision_view.handles))
        assert _colours(v._collision_view.world_handles) == [WORLD_RGB]
        # dragged there joint by joint with the sliders: the colours follow at every step
        for i, x in enumerate(qs[hit].tolist()):
            v.sliders[i].value = x
            step = col.self_distances(v.q).detach()
            red = {names.index(n) for p, dist in zip(col.pairs, step) if dist < 0 for n in p}
            cols = _colours(v._collision_view.handles)
            assert {k for k, c in enumerate(cols) if c == CONTACT_RGB} == red
        assert [(a, b) for a, b, _ in v.contacts["pairs"]] == pairs
    finally:
        v.close()


def test_world_objects_drawn_and_coloured(fr3):
    chain, col = fr3
    q = chain.neutral_configuration()
    flange = chain.forward_kinematics(q)[:3, 3].detach()

    def world_at(p):
        return World(spheres=[[*p.tolist(), 0.05]], capsules=[[0.5, 0.5, 0.0, 0.5, 0.5, 0.4, 0.03]],
                     halfspaces=[[0.0, 0.0, 1.0, -0.3]], points=[[0.6, -0.6, 0.2]],
                     cylinders=[[-0.5, 0.5, 0.0, -0.5, 0.5, 0.4, 0.05]], dtype=F64)
    for p, touching in ((flange, True), (flange + torch.tensor([2.0, 0, 0], dtype=F64), False)):
        world = world_at(p)
        w = col.world_distances(q, world).detach()
        assert bool((w[:, 0] < 0).any()) is touching and not bool((w[:, 1:] < 0).any())
        v = viz.show(chain, q, port=0, collision=col, world=world)
        try:
            cols = _colours(v._collision_view.world_handles)
            assert len(cols) == 5 and cols[0] == (CONTACT_RGB if touching else WORLD_RGB)
            assert cols[1:] == [WORLD_RGB] * 4
            cyl = v._collision_view.world_handles[4]  # the cylinder, drawn where it is (last column)
            np.testing.assert_allclose(cyl.position, [-0.5, 0.5, 0.2], atol=1e-6)
            vv = np.asarray(v._collision_view.world_meshes[4][0])
            np.testing.assert_allclose(np.ptp(vv, axis=0), [0.1, 0.1, 0.4], atol=2e-3)  # flat ends
            np.testing.assert_allclose(v._collision_view.world_handles[0].position, p.numpy(), atol=1e-6)
            red = {g for g, _, _ in v.contacts["world"]}
            assert red == {col.geoms[g].name for g in torch.nonzero(w[:, 0] < 0)[:, 0].tolist()}
        finally:
            v.close()


def test_collision_geoms_drawn_where_placed(fr3):
    chain, col = fr3
    q = chain.random_configuration((), generator=torch.Generator().manual_seed(5))
    v = viz.show(chain, q, port=0, collision=col)
    try:
        a, b, *_ = col.placed(q)
        caps = [i for i, g in enumerate(col.geoms) if g.shape == "capsule"]
        for k, g in enumerate(caps):
            h = v._collision_view.handles[g]
            np.testing.assert_allclose(h.position, (0.5 * (a[k] + b[k])).detach().numpy(), atol=1e-6)
            z = _pose(h.wxyz, h.position)[:3, 2]
            u = (b[k] - a[k]).detach().numpy()
            if np.linalg.norm(u) > 1e-9:
                assert abs(float(z @ u) / np.linalg.norm(u)) == pytest.approx(1.0, abs=1e-6)
    finally:
        v.close()


def test_mjcf_collision_and_cli(tmp_path, capsys):
    chain = _quiet(models.from_mjcf, G1, ["left_ankle_roll_link", "right_ankle_roll_link"], dtype=F64)
    model = compile_mjcf(G1)[0]
    col = RobotCollision.from_mjcf(model, chain, body_poses=functools.partial(body_poses, chain))
    q = chain.random_configuration((), generator=torch.Generator().manual_seed(6))
    v = _quiet(viz.show, chain, q, port=0, collision=col)
    try:
        d = col.self_distances(v.q).detach()
        assert [(a, b) for a, b, _ in v.contacts["pairs"]] == [p for p, x in zip(col.pairs, d) if x < 0]
    finally:
        v.close()
    argv = ["view", "--mjcf", str(G1), "--end-link", "left_foot", "--collision", "--port", "0",
            "--duration", "0.3"]
    assert _quiet(cli.main, argv) == 0
    assert "MJCF geoms" in capsys.readouterr().out


def test_bad_collision_arguments_are_refused(fr3, cassie):
    chain, col = fr3
    with pytest.raises(DiffkinError, match="collision must be a RobotCollision of the chain"):
        viz.show(cassie, port=0, collision=col)
    with pytest.raises(DiffkinError, match="world needs collision="):
        viz.show(chain, port=0, world=World(points=[[0.0, 0.0, 0.0]], dtype=F64))
    with pytest.raises(DiffkinError, match="margin"):
        viz.show(chain, port=0, collision=col, margin=float("nan"))
    batched = World(spheres=torch.zeros(2, 1, 4, dtype=F64) + torch.tensor([0, 0, 0, 0.1], dtype=F64))
    with pytest.raises(ShapeError, match="the viewer draws one world"):
        viz.show(chain, port=0, collision=col, world=batched)
