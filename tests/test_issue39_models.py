"""Issue 39, the model readers' and loaders' boundary: each item's regression test (test_itemNN_...).

MJCF kinematics are checked against MuJoCo itself (``mj_kinematics``, its equality-constraint residuals),
joint limits against the file's float64 ranges, J̇q̇ against a contiguous copy, errors by their type and
the element they name."""

from __future__ import annotations

import importlib.util
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from diffkin import ik, jacobian, models
from diffkin.collision import read_world
from diffkin.errors import DeviceError, DiffkinError, ModelError, ShapeError
from diffkin.models import from_mjcf
from diffkin.models.mjcf import compile_mjcf

mujoco = pytest.importorskip("mujoco")

DATA = Path(__file__).parent / "data"
KINDS = DATA / "mjcf_extra" / "joint_kinds.xml"
PANDA_XML = DATA / "mjcf" / "franka_emika_panda" / "panda.xml"
F64 = torch.float64

_ONE = ("<mujoco><worldbody><body name='a' pos='{pos}' quat='{bquat}'><joint name='j' type='hinge' "
        "axis='{axis}' ref='{ref}' range='{range}' limited='true'/><geom size='0.1'/>"
        "<site name='s' pos='0.1 0 0' quat='{quat}'/></body></worldbody></mujoco>")
_GOOD = dict(pos="0 0 0.1", bquat="1 0 0 0", axis="0 0 1", ref="0", range="-1 1", quat="1 0 0 0")


def _one(**change) -> str:
    return _ONE.format(**{**_GOOD, **change})


def _site_pose(m, qpos, site: int = 0) -> np.ndarray:
    """MuJoCo's world pose (4, 4) of a site at qpos."""
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_kinematics(m, d)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = d.site_xmat[site].reshape(3, 3), d.site_xpos[site]
    return T


# ------------------------------------------------------------------------------------------------ item 5
@pytest.mark.parametrize(("change", "element"), [
    (dict(pos="nan 0 0"), "body 'a': pos"),
    (dict(pos="0 inf 0"), "body 'a': pos"),
    (dict(bquat="nan 0 0 0"), "body 'a': quat"),
    (dict(axis="0 0 inf"), "joint 'j': axis"),
    (dict(axis="nan 0 1"), "joint 'j': axis"),
    (dict(quat="1 nan 0 0"), "site 's': quat"),
    (dict(ref="nan"), "joint 'j': ref"),
    (dict(range="-1 nan"), "joint 'j'"),
])
def test_item05_mjcf_nan_refused(change, element, tmp_path, monkeypatch):
    """MuJoCo compiles NaN / inf (a printed warning only) and the FK would be NaN: the loader refuses the
    model, naming the element and attribute."""
    monkeypatch.chdir(tmp_path)  # MuJoCo writes its warning to MUJOCO_LOG.TXT in the working directory
    xml = _one(**change)
    with pytest.raises(ModelError, match=f"{element}.*(NaN or inf|lower < upper)"):
        from_mjcf(xml, "s", dtype=F64)
    chain = from_mjcf(_one(), "s", dtype=F64)  # the same model with finite numbers loads, FK as MuJoCo's
    m = mujoco.MjModel.from_xml_string(_one())
    torch.testing.assert_close(chain.forward_kinematics(torch.tensor([0.3], dtype=F64)).detach(),
                               torch.tensor(_site_pose(m, [0.3])), atol=1e-12, rtol=0)


# ----------------------------------------------------------------------------------------------- item 14
_FREE_BALL = ("<mujoco><worldbody><body name='c' pos='0 0.2 0'><joint name='f' type='free'/>"
              "<geom size='0.1'/><body name='a' pos='0.1 0 0'><joint name='b' type='ball'/><geom size='0.1'/>"
              "<site name='s' pos='0.1 0.2 0.3'/></body></body></worldbody></mujoco>")


@pytest.mark.parametrize(("dtype", "big"), [(torch.float64, 1e160), (torch.float32, 1e30)])
def test_item14_huge_quaternion_scaled_before_the_norm(dtype, big):
    """Quaternions of a free and a ball joint with entries near 1e160 (1e30 in float32) mean the rotation of
    their direction: the FK on every path (the batch-last and fused kernels without autograd, the autograd
    path) equals MuJoCo's FK of the same quaternions at unit scale (MuJoCo's own normalisation overflows
    there and gives the identity; before, diffkin's gave (0, 0, 0, 0) and R = -I)."""
    m = mujoco.MjModel.from_xml_string(_FREE_BALL)
    chain = from_mjcf(_FREE_BALL, "s", dtype=dtype)
    rng = np.random.default_rng(3)
    quats = rng.normal(size=(8, 2, 4))
    qpos = np.concatenate([rng.normal(size=(8, 3)), quats[:, 0], quats[:, 1]], axis=1)
    ref = torch.tensor(np.stack([_site_pose(m, row) for row in qpos]))
    q = torch.tensor(qpos)
    q[:, 3:] *= big
    q = q.to(dtype)
    tol = dict(atol=1e-12 if dtype == F64 else 2e-6, rtol=0)
    with torch.no_grad():
        torch.testing.assert_close(chain.forward_kinematics(q).double(), ref, **tol)
        many = q.repeat(64, 1)  # a batch for the fused / batch-last kernels
        torch.testing.assert_close(chain.forward_kinematics(many).double(), ref.repeat(64, 1, 1), **tol)
    qg = q.clone().requires_grad_(True)
    T = chain.forward_kinematics(qg)
    torch.testing.assert_close(T.detach().double(), ref, **tol)
    (g,) = torch.autograd.grad(T.sum(), qg)
    assert torch.isfinite(g).all()
    torch.testing.assert_close(chain.normalize_configuration(q)[:, 3:].double(),
                               torch.tensor(qpos[:, 3:] / np.repeat(np.linalg.norm(quats, axis=-1), 4, 1)),
                               **tol)


def test_item14_model_quaternion_that_overflows_in_mujoco_refused():
    """A body quaternion with entries of 1e160 compiles in MuJoCo to (0, 0, 0, 0) (its own normalisation
    overflows): refused, naming the body, instead of an FK without rotation."""
    with pytest.raises(ModelError, match="body 'a': quat is \\(0, 0, 0, 0\\)"):
        from_mjcf(_one(bquat="1e160 1e160 0 0"), "s", dtype=F64)
    chain = from_mjcf(_one(bquat="1e150 1e150 0 0"), "s", dtype=F64)  # MuJoCo normalises this one
    m = mujoco.MjModel.from_xml_string(_one(bquat="1e150 1e150 0 0"))
    torch.testing.assert_close(chain.forward_kinematics(torch.tensor([0.2], dtype=F64)).detach(),
                               torch.tensor(_site_pose(m, [0.2])), atol=1e-12, rtol=0)
    with torch.no_grad():  # a learnable body quaternion scaled up keeps its rotation (stable norm)
        chain.body_quat.mul_(1e160)
    torch.testing.assert_close(chain.forward_kinematics(torch.tensor([0.2], dtype=F64)).detach(),
                               torch.tensor(_site_pose(m, [0.2])), atol=1e-12, rtol=0)


# ------------------------------------------------------------------------------------- items 16 and 20
_COUPLED = """<mujoco><worldbody>
<body name='b1'><joint name='j1' axis='0 0 1' ref='0.1'/><geom size='0.05'/>
 <body name='b2' pos='0.3 0 0'><joint name='j2' axis='0 1 0'/><geom size='0.05'/>
  <body name='b3' pos='0.3 0 0'><joint name='j3' axis='1 0 0' ref='-0.2'/><geom size='0.05'/>
   <body name='b4' pos='0.2 0 0'><joint name='j4' type='slide' axis='1 0 0'/><geom size='0.05'/>
    <site name='tip' pos='0.1 0.05 0'/></body></body></body></body></worldbody>
<equality>{eq}</equality></mujoco>"""


def test_item16_two_joint_equalities_on_one_follower_refused():
    eq = ("<joint name='first' joint1='j3' joint2='j2' polycoef='0 1 0 0 0'/>"
          "<joint name='second' joint1='j3' joint2='j1' polycoef='0 2 0 0 0'/>")
    with pytest.raises(ModelError, match="'j3' follows two joint equalities \\('first' and 'second'\\)"):
        from_mjcf(_COUPLED.format(eq=eq), "tip")
    # one of them inactive: the active one holds, nothing is refused
    eq_off = eq.replace("name='second'", "name='second' active='false'")
    with pytest.warns(UserWarning, match="not enforced.*second \\(joint, inactive\\)"):
        chain = from_mjcf(_COUPLED.format(eq=eq_off), "tip", dtype=F64)
    assert chain.joint_names == ["j1", "j2", "j4"]
    # a cycle of couplings has no leader
    cycle = "<joint joint1='j2' joint2='j3'/><joint joint1='j3' joint2='j2'/>"
    with pytest.raises(ModelError, match="cycle \\(j2 -> j3 -> j2\\)"):
        from_mjcf(_COUPLED.format(eq=cycle), "tip")


def test_item20_chained_joint_couplings():
    """j3 follows j2 follows j1 (was ``KeyError: 1``): q holds j1 and j4; the qpos satisfies both of
    MuJoCo's equality constraints (zero residual) and the FK and Jacobian equal MuJoCo's at that qpos."""
    eq = ("<joint joint1='j3' joint2='j2' polycoef='0.05 -0.5 0 0 0'/>"
          "<joint joint1='j2' joint2='j1' polycoef='0.1 2 0 0 0'/>")
    xml = _COUPLED.format(eq=eq)
    chain = from_mjcf(xml, "tip", dtype=F64)
    assert chain.joint_names == ["j1", "j4"]
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    q = torch.tensor([[0.3, 0.1], [-0.7, 0.2], [1.1, -0.05]], dtype=F64)
    qpos = chain.to_qpos(q).numpy()
    T, J = chain.forward_kinematics_and_jacobian(q)
    for k, row in enumerate(qpos):
        d.qpos[:] = row
        mujoco.mj_forward(m, d)
        assert d.nefc >= 2 and np.abs(d.efc_pos[:2]).max() < 1e-12  # both equalities hold
        torch.testing.assert_close(T[k].detach(), torch.tensor(_site_pose(m, row)), atol=1e-12, rtol=0)
        Jm = np.zeros((6, m.nv))
        mujoco.mj_jacSite(m, d, Jm[:3], Jm[3:], 0)
        torch.testing.assert_close(J[k].detach(), torch.tensor(Jm @ chain.velocity_map().numpy()),
                                   atol=1e-12, rtol=0)


# ----------------------------------------------------------------------------------------------- item 18
def test_item18_float32_limits_judged_within_the_files_float64_ranges():
    """from_mjcf's dtype is torch's default (one rule for every loader, documented); in float32 the limits
    are rounded inwards, so every configuration the chain clamps to or judges within its limits is within
    MuJoCo's float64 ranges (rounded to the nearest float32, 4 of the Panda's 14 limits lay outside, by up
    to 6e-8 rad). Also after ``.float()`` of a float64 chain; float64 keeps the file's numbers exactly."""
    m = compile_mjcf(PANDA_XML)[0]  # the file's meshes are absent: MuJoCo compiles it without them
    default = from_mjcf(PANDA_XML, "hand")
    assert default.dtype == torch.get_default_dtype()
    c64 = from_mjcf(PANDA_XML, "hand", dtype=F64)
    ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n) for n in c64.joint_names]
    ranges = torch.tensor(m.jnt_range[ids])
    assert torch.equal(c64.q_limits, ranges)
    nearest_outside = (ranges.float().double()[:, 0] < ranges[:, 0]).sum() + \
        (ranges.float().double()[:, 1] > ranges[:, 1]).sum()
    assert nearest_outside > 0  # the case this item is about exists in this file
    for chain in (from_mjcf(PANDA_XML, "hand", dtype=torch.float32), c64.float()):
        lim = chain.q_limits.double()
        assert chain.q_limits.dtype == torch.float32
        assert (lim[:, 0] >= ranges[:, 0]).all() and (lim[:, 1] <= ranges[:, 1]).all()
        assert ((lim - ranges).abs() < 1e-6).all()  # one float32 step at most
        q = torch.tensor([[10.0] * 7, [-10.0] * 7], dtype=torch.float32)
        qc = chain.clamp_to_limits(q).double()
        assert ((qc >= ranges[:, 0]) & (qc <= ranges[:, 1])).all()
        g = torch.Generator().manual_seed(0)
        qr = chain.random_configuration(4000, generator=g)
        inside = chain.within_limits(qr)
        qd = qr.double()
        assert ((qd[inside] >= ranges[:, 0]) & (qd[inside] <= ranges[:, 1])).all()
    assert torch.equal(c64.float().double().q_limits, c64.float().q_limits.double())


# ----------------------------------------------------------------------------------------------- item 23
def test_item23_non_utf8_input_typed(tmp_path, capsys):
    latin = ("<mujoco model='caf\xe9'><worldbody><body name='a'><joint name='j'/><geom size='0.1'/></body>"
             "</worldbody></mujoco>").encode("latin-1")
    with pytest.raises(ModelError, match="<MJCF bytes>: not UTF-8 text \\(byte 0xe9 at offset 18\\)"):
        from_mjcf(latin, "a")
    path = tmp_path / "latin.xml"
    path.write_bytes(latin)
    with pytest.raises(ModelError, match="latin.xml: not UTF-8 text"):
        from_mjcf(path, "a")
    utf8 = from_mjcf(latin.decode("latin-1").encode("utf-8"), "a")  # the same model as UTF-8 loads
    assert utf8.joint_names == ["j"]
    world = tmp_path / "garbage.yaml"
    world.write_bytes(bytes(range(256)))
    with pytest.raises(DiffkinError, match=r"garbage.yaml: expected a YAML / JSON world file "
                                           r"\(UTF-8 text\), got byte 0x80 at offset 128"):
        read_world(world)
    from diffkin.cli import main

    urdf = DATA / "urdf" / "ur10.urdf"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the URDF's mesh files are absent
        rc = main(["fk", "--urdf", str(urdf), "--end-link", "tool0", "--random", "2", "--world", str(world)])
    err = capsys.readouterr().err
    assert rc == 2 and "(UTF-8 text), got byte 0x80" in err and "internal error" not in err, err


# ----------------------------------------------------------------------------------------------- item 25
@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_item25_from_mjcf_device_typed():
    for device in ("cuda", "cuda:0", "meta", "nonsense"):
        with pytest.raises(DeviceError):
            from_mjcf(KINDS, "palm", device=device)
        with pytest.raises(DeviceError):  # the same error as models.load gives
            models.load("panda", device=device)


def test_item25_from_mjcf_meta_typed():
    with pytest.raises(DeviceError, match="'meta' holds no values"):
        from_mjcf(KINDS, "palm", device="meta")
    assert from_mjcf(KINDS, "palm", device="cpu").device == torch.device("cpu")


# ----------------------------------------------------------------------------------------------- item 26
def test_item26_urdf_given_to_from_mjcf():
    urdf = DATA / "urdf" / "ur10.urdf"
    for source in (urdf, str(urdf), urdf.read_text(), urdf.read_bytes()):
        with pytest.raises(ModelError, match="is a URDF \\(root element <robot>\\).*from_urdf"):
            from_mjcf(source, "tool0")
    assert models.from_urdf(urdf, "tool0").n_joints == 6  # where the message points


# ----------------------------------------------------------------------------------------------- item 27
def test_item27_jacobian_dot_qdot_with_stride0_q():
    """One q broadcast against a batch of q̇ (an expanded, stride-0 q) was a raw error of forward-mode AD;
    the result equals that of the contiguous copy, on the small-batch and the vmapped path."""
    chain = models.load("panda", dtype=F64)
    g = torch.Generator().manual_seed(0)
    q1 = chain.random_configuration(generator=g)
    for batch in (5, chain.small_batch + 3):
        qdot = torch.randn(batch, 7, generator=g, dtype=F64)
        expanded = q1.expand(batch, 7)
        assert expanded.stride(0) == 0
        want = jacobian.jacobian_dot_qdot(chain, expanded.contiguous(), qdot)
        torch.testing.assert_close(jacobian.jacobian_dot_qdot(chain, expanded, qdot), want)
        torch.testing.assert_close(jacobian.jacobian_dot_qdot(chain, q1, qdot), want)
        torch.testing.assert_close(jacobian.jacobian_dot_qdot(chain, qdot, q1.expand(batch, 7)),
                                   jacobian.jacobian_dot_qdot(chain, qdot, q1.expand(batch, 7).clone()))


def test_item27_joint_trajectory_from_poses_shapes():
    """A path (N, 4) is a ShapeError naming the accepted shapes; a batch of starts q0 (B, n) along one path
    (S, 4, 4) broadcasts (was a raw IndexError / size mismatch): row b equals the call with q0[b]; batch
    dims that do not broadcast are a ShapeError naming both."""
    chain = models.load("panda", dtype=F64)
    q0 = torch.tensor([[0.1, -0.3, 0.2, -2.0, 0.1, 1.6, 0.7], [0.0, 0.2, 0.0, -1.5, 0.0, 1.5, 0.3]],
                      dtype=F64)
    path = chain.forward_kinematics(q0[0] + torch.linspace(0, 0.05, 4, dtype=F64)[:, None]).detach()
    for bad in (torch.zeros(3, 4, dtype=F64), torch.zeros(5, 4, dtype=F64), torch.zeros(2, 5, 4, dtype=F64)):
        with pytest.raises(ShapeError, match="\\(\\.\\.\\., S, 4, 4\\) \\(poses\\) or \\(\\.\\.\\., S, 3\\)"):
            ik.joint_trajectory_from_poses(chain, bad, q0[0])
    for method in ("clik", "solve"):
        for target in (path, path[:, :3, 3]):
            res = ik.joint_trajectory_from_poses(chain, target, q0, method=method)
            assert res.q.shape == (2, 4, 7)
            for b in range(2):
                one = ik.joint_trajectory_from_poses(chain, target, q0[b], method=method)
                torch.testing.assert_close(res.q[b], one.q, atol=1e-9, rtol=0)
                assert torch.equal(res.success[b], one.success)
    assert ik.joint_trajectory_from_poses(chain, path, q0, method="solve").success.all()
    with pytest.raises(ShapeError, match="T_target \\(3, 4, 4, 4\\), q0 \\(2, 7\\)"):
        ik.joint_trajectory_from_poses(chain, path.expand(3, 4, 4, 4), q0)


def test_item27_models_load_of_a_list_typed():
    for bad in (["panda"], ("panda",), None, 3, {"name": "panda"}):
        with pytest.raises(ModelError, match="expected a model name"):
            models.load(bad)
    with pytest.raises(ModelError, match="unknown model"):
        models.model_path(["panda"])
    assert models.load("panda").n_joints == 7


# ----------------------------------------------------------------------------------------------- item 12
_TWO_LINKS = """<robot name="r">
  <link name="a"><collision name="base_box"><geometry><box size="0.2 0.2 0.1"/></geometry></collision>
    {extra_a}</link>
  <link name="b"><collision name="ball"><origin xyz="0.3 0 0"/><geometry>{shape_b}</geometry></collision>
  </link>
  <link name="c"><collision name="tip"><geometry><sphere radius="0.05"/></geometry></collision></link>
  <joint name="j1" type="revolute"><parent link="a"/><child link="b"/><origin xyz="0 0 0.2"/>
    <axis xyz="0 0 1"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="b"/><child link="c"/><origin xyz="0.5 0 0"/>
    <axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
</robot>"""


def _two_links(extra_a: str = "", shape_b: str = '<sphere radius="0.08"/>') -> str:
    return _TWO_LINKS.format(extra_a=extra_a, shape_b=shape_b)


def test_item12_urdf_collision_unknown_shapes_two_shapes_and_srdf_links():
    from diffkin.collision import RobotCollision
    from diffkin.models.urdf_xml import parse_collisions

    cone = '<collision name="horn"><geometry><cone radius="0.1" length="0.2"/></geometry></collision>'
    text = _two_links(extra_a=cone)
    chain = models.from_urdf(text, "c", dtype=F64)
    with pytest.warns(UserWarning, match="1 <collision> shape\\(s\\) URDF does not define.*horn \\(<cone>\\) "
                                         "on link 'a'"):
        rc = RobotCollision.from_urdf(text, chain)
    assert [g.name for g in rc.geoms] == ["base_box", "ball", "tip"]  # the known shapes all kept
    unknown: list[str] = []
    assert [s.name for s in parse_collisions(text, unknown=unknown)["a"]] == ["base_box"]
    assert unknown == ["horn (<cone>) on link 'a'"]
    with pytest.warns(UserWarning, match="horn"):
        parse_collisions(text)
    # a <geometry> holding two shapes: refused, naming both (before: one of them silently)
    two = _two_links(shape_b='<sphere radius="0.08"/><box size="0.1 0.1 0.1"/>')
    with pytest.raises(ModelError, match="link 'b' <collision> 'ball': <geometry> holds 2 shapes "
                                         "\\(<sphere>, <box>\\)"):
        RobotCollision.from_urdf(two, models.from_urdf(two, "c", dtype=F64))
    # an SRDF naming links this URDF does not have: refused (it would disable nothing)
    plain = _two_links()
    chain = models.from_urdf(plain, "c", dtype=F64)
    ok = '<robot><disable_collisions link1="a" link2="c" reason="Never"/></robot>'
    assert RobotCollision.from_urdf(plain, chain).pairs == [("base_box", "tip")]  # a, c: not adjacent
    assert RobotCollision.from_urdf(plain, chain, srdf=ok).pairs == []
    other = '<robot><disable_collisions link1="a" link2="fr3_link3_sc" reason="Never"/></robot>'
    with pytest.raises(ModelError, match="SRDF: <disable_collisions> names 1 link\\(s\\) the URDF does not "
                                         "have: fr3_link3_sc"):
        RobotCollision.from_urdf(plain, chain, srdf=other)


# ----------------------------------------------------------------------------------------------- item 13
def test_item13_cli_reader_by_flag_not_suffix(tmp_path, capsys):
    """``--urdf robot.urdf.xml`` is read as a URDF (was: as MJCF, by its .xml suffix): its FK equals the
    independent numpy URDF reference; ``--mjcf X --robot panda`` is an error naming both options (was:
    --robot silently ignored)."""
    from urdf_reference import ReferenceTree

    from diffkin.cli import main

    src = DATA / "urdf" / "ur10.urdf"
    urdf_xml = tmp_path / "ur10.urdf.xml"
    urdf_xml.write_bytes(src.read_bytes())
    q = np.random.default_rng(0).uniform(-2, 2, (3, 6))
    np.save(tmp_path / "q.npy", q)
    rc = main(["fk", "--urdf", str(urdf_xml), "--end-link", "tool0", "--input", str(tmp_path / "q.npy"),
               "--output", str(tmp_path / "T.npy")])
    assert rc == 0, capsys.readouterr().err
    T = np.load(tmp_path / "T.npy")
    ref = ReferenceTree(src)
    names = models.from_urdf(src, "tool0").joint_names
    want = np.stack([ref.fk(dict(zip(names, row)), "tool0") for row in q])
    np.testing.assert_allclose(T, want, atol=1e-12, rtol=0)
    for args in (["--mjcf", str(PANDA_XML), "--end-link", "hand", "--robot", "panda"],
                 ["--urdf", str(src), "--end-link", "tool0", "--mjcf", str(PANDA_XML)]):
        rc = main(["fk", *args, "--random", "2"])
        err = capsys.readouterr().err
        assert rc == 2 and "give the robot once" in err, err
    if importlib.util.find_spec("viser") is not None:  # the viewer's options follow the same rule
        rc = main(["view", "--robot", "panda", "--urdf", str(src), "--end-link", "tool0"])
        err = capsys.readouterr().err
        assert rc == 2 and "--robot and --urdf were both given" in err, err
    with pytest.raises(ModelError, match="file_format"):
        models.load_chain(src, "tool0", file_format="sdf")
    assert models.load_chain(urdf_xml, "tool0", file_format="urdf").joint_names == names


# ----------------------------------------------------------------------------------------------- item 30
def test_item30_mesh_warning_names_only_geoms_that_would_be_checked():
    """Without mesh files, RobotCollision.from_mjcf warns about the meshes it would have checked only: the
    UR5e's 20 meshes are all visual (no warning), the Panda's 71 hold 13 collision meshes (the warning
    names those 13, none of the visual ones)."""
    from diffkin.collision import RobotCollision

    root = DATA / "mjcf"
    for path, count in ((root / "universal_robots_ur5e" / "ur5e.xml", 0),
                        (root / "franka_emika_panda" / "panda.xml", 13)):
        spec = mujoco.MjSpec.from_file(str(path))
        meshes = [g for g in spec.geoms if g.type == mujoco.mjtGeom.mjGEOM_MESH]
        collidable = [g for g in meshes if g.contype or g.conaffinity]
        assert len(collidable) == count and len(meshes) > count  # visual meshes exist in both
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            chain = from_mjcf(path, "wrist_3_link" if count == 0 else "hand", dtype=F64)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            RobotCollision.from_mjcf(path, chain)
        skipped = [str(w.message) for w in caught if "mesh geoms skipped" in str(w.message)]
        if count == 0:
            assert skipped == []
        else:
            assert len(skipped) == 1 and f"{count} mesh geoms skipped" in skipped[0]
            assert "link0/link0_c" in skipped[0] and "link0_0" not in skipped[0]
