"""Centre of mass and its Jacobian (``chain.center_of_mass``, ``chain.com_jacobian``) against MuJoCo's
``subtree_com`` / ``mj_jacSubtreeCom`` on the vendored Menagerie models, Pinocchio's ``centerOfMass`` /
``jacobianCenterOfMass`` on the vendored URDFs, finite differences and gradcheck; float32 / float64, batch
shapes, and the typed error of a chain without masses."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from diffkin import models
from diffkin.errors import ModelError, ShapeError
from diffkin.models import from_urdf
from diffkin.models.urdf_xml import parse_inertials, parse_urdf

DATA = Path(__file__).parent / "data"
F64 = torch.float64
ENTRIES = json.loads((DATA / "mjcf" / "index.json").read_text())
MJCF = {Path(e["file"]).parent.name: DATA / "mjcf" / e["file"] for e in ENTRIES}
MJCF_MODELS = [*MJCF.values(), DATA / "mjcf_extra" / "joint_kinds.xml"]


def _mujoco():
    return pytest.importorskip("mujoco")


def _mjcf_chain(path, ends=None, dtype=F64, **kwargs):
    from diffkin.models import from_mjcf
    from diffkin.models.mjcf import compile_mjcf

    m = compile_mjcf(path)[0]
    if ends is None:  # every body: the chain's paths cover the whole model
        ends = [m.body(b).name for b in range(1, m.nbody)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # closed loops (connect equalities) are reported elsewhere
        return m, from_mjcf(path, ends, dtype=dtype, **kwargs)


def _mujoco_com(m, chain, q, root: str | None = None):
    """MuJoCo's ``subtree_com`` and ``mj_jacSubtreeCom`` of the chain's root body at the chain's ``q``
    (rows), in the root body's frame, on the chain's velocity columns."""
    mujoco = _mujoco()
    d = mujoco.MjData(m)
    body = 0 if root is None else mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, root)
    V = chain.velocity_map().detach().numpy()
    coms, jacs = [], []
    for row in chain.to_qpos(q.detach()).reshape(-1, m.nq).numpy():
        d.qpos[:] = row
        mujoco.mj_forward(m, d)
        J = np.zeros((3, m.nv))
        mujoco.mj_jacSubtreeCom(m, d, J, body)
        R = d.xmat[body].reshape(3, 3)
        coms.append(R.T @ (d.subtree_com[body] - d.xpos[body]))
        jacs.append(R.T @ J @ V)
    shape = q.shape[:-1]
    return (torch.tensor(np.array(coms)).reshape(*shape, 3),
            torch.tensor(np.array(jacs)).reshape(*shape, 3, chain.nv))


def _max_errors(chain, q, ref_com, ref_J):
    with torch.no_grad():
        com, J = chain.center_of_mass(q), chain.com_jacobian(q)
    return (com - ref_com).abs().max().item(), (J - ref_J).abs().max().item()


# ------------------------------------------------------------------------------------------ MuJoCo

@pytest.mark.filterwarnings("ignore:chain .* MuJoCo infers the masses")
@pytest.mark.parametrize("path", MJCF_MODELS, ids=lambda p: p.parent.name)
def test_every_menagerie_model_matches_mujoco(path):
    m, chain = _mjcf_chain(path)
    q = chain.random_configuration((6,), generator=torch.Generator().manual_seed(3))
    ref_com, ref_J = _mujoco_com(m, chain, q)
    e_com, e_J = _max_errors(chain, q, ref_com, ref_J)
    assert e_com < 1e-10 and e_J < 1e-10, (e_com, e_J)
    # the autograd path gives the same numbers
    qg = q[:2].clone().requires_grad_(True)
    torch.testing.assert_close(chain.center_of_mass(qg).detach(), ref_com[:2], atol=1e-10, rtol=0)
    torch.testing.assert_close(chain.com_jacobian(qg).detach(), ref_J[:2], atol=1e-10, rtol=0)
    # every body of the model with a mass is counted once
    assert sum(chain.link_masses.tolist()) == pytest.approx(float(m.body_subtreemass[0]), rel=1e-12)


@pytest.mark.parametrize("name, ends, root", [
    ("franka_emika_panda", "hand", None),  # the fingers are off the chain's path (at qpos0)
    ("franka_emika_panda", "hand", "link2"),  # a root body: its subtree, in its frame
    ("unitree_g1", ["left_ankle_roll_link", "right_ankle_roll_link"], None),  # arms and waist at qpos0
    ("unitree_g1", "left_elbow_roll_link", "torso_link"),
    ("unitree_h1", ["left_ankle_link", "right_ankle_link", "left_elbow_link", "right_elbow_link"], None),
    ("unitree_go2", ["FL_calf", "FR_calf", "RL_calf", "RR_calf"], None),
    ("universal_robots_ur5e", "wrist_3_link", None),
    ("agility_cassie", ["left-foot", "right-foot"], None),  # ball joints
])
def test_partial_chains_and_root_bodies_match_mujoco(name, ends, root):
    m, chain = _mjcf_chain(MJCF[name], ends, root_link=root)
    q = chain.random_configuration((5,), generator=torch.Generator().manual_seed(4))
    ref_com, ref_J = _mujoco_com(m, chain, q, root)
    e_com, e_J = _max_errors(chain, q, ref_com, ref_J)
    assert e_com < 1e-10 and e_J < 1e-10, (e_com, e_J)


def test_base_transform_moves_the_center_of_mass_with_the_frames():
    _, chain = _mjcf_chain(MJCF["universal_robots_ur5e"], "wrist_3_link")
    q = chain.random_configuration((4,), generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        com, J = chain.center_of_mass(q), chain.com_jacobian(q)
        T = chain.forward_kinematics(q)
        chain.base = models.load("ur5", dtype=F64).forward_kinematics(torch.tensor([0.3, -0.2, 0.5, 0.1,
                                                                                        0.2, 0.3], dtype=F64))
        B = chain.base
        com_b, J_b, T_b = chain.center_of_mass(q), chain.com_jacobian(q), chain.forward_kinematics(q)
    torch.testing.assert_close(T_b, B @ T)  # the same frame as FK's
    torch.testing.assert_close(com_b, com @ B[:3, :3].T + B[:3, 3])
    torch.testing.assert_close(J_b, B[:3, :3] @ J)


def test_masses_inferred_from_mesh_stand_ins_are_named_in_a_warning():
    """Allegro's bodies have no <inertial>: MuJoCo infers their masses from the mesh geoms, which the
    loader replaces by small spheres; the first centre-of-mass call says so, once. G1 gives every body an
    <inertial>: no warning."""
    _, hand = _mjcf_chain(MJCF["wonik_allegro"])
    with pytest.warns(UserWarning, match="infers the masses of palm, ff_base"):
        hand.center_of_mass(hand.neutral_configuration())
    _, g1 = _mjcf_chain(MJCF["unitree_g1"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        hand.center_of_mass(hand.neutral_configuration())  # said once per chain
        g1.center_of_mass(g1.neutral_configuration())


# --------------------------------------------------------------------------------------- Pinocchio

def _pinocchio_com(path, chain, q, floating: bool):
    """Pinocchio's centre of mass and its Jacobian at the chain's ``q`` rows, on the chain's columns.

    Pinocchio leaves the universe's inertia (the links welded to the root) out of ``data.com[0]``; the
    chain counts every link, so it is added back. A free flyer's linear velocity is in its own frame in
    Pinocchio, in the world in the chain (J_chain = J_pin Rᵀ on those columns); a continuous joint is
    (cos, sin) there; a mimic joint is a joint of its own, here a column folded into its leader's."""
    pin = pytest.importorskip("pinocchio")
    model = pin.buildModelFromUrdf(str(path), pin.JointModelFreeFlyer()) if floating \
        else pin.buildModelFromUrdf(str(path))
    data = model.createData()
    tree = parse_urdf(path)
    mimic = {j.name: j.mimic for j in tree.joints if j.mimic is not None}
    start, vstart = (7, 6) if floating else (0, 0)
    column = {name: vstart + k for k, name in enumerate(chain.joint_names[1 if floating else 0:])}
    coms, jacs = [], []
    for qi in q.detach().numpy():
        value = {name: qi[start + k] for k, name in enumerate(chain.joint_names[1 if floating else 0:])}
        qp = pin.neutral(model)
        if floating:
            qp[:3], qp[3:7] = qi[:3], [qi[4], qi[5], qi[6], qi[3]]
        for jid in range(1 + floating, model.njoints):
            name, joint = model.names[jid], model.joints[jid]
            x = value[name] if name in value else mimic[name][1] * value[mimic[name][0]] + mimic[name][2]
            qp[joint.idx_q:joint.idx_q + joint.nq] = [np.cos(x), np.sin(x)] if joint.nq == 2 else [x]
        pin.centerOfMass(model, data, qp)
        Jp = pin.jacobianCenterOfMass(model, data, qp)
        J = np.zeros((3, chain.nv))
        if floating:
            R = pin.Quaternion(qp[6], qp[3], qp[4], qp[5]).toRotationMatrix()
            J[:, :3], J[:, 3:6] = Jp[:, :3] @ R.T, Jp[:, 3:6]
        for jid in range(1 + floating, model.njoints):
            name, v = model.names[jid], model.joints[jid].idx_v
            if name in column:
                J[:, column[name]] += Jp[:, v]
            else:
                J[:, column[mimic[name][0]]] += mimic[name][1] * Jp[:, v]
        m0, M = model.inertias[0].mass, data.mass[0]
        coms.append((M * data.com[0] + m0 * model.inertias[0].lever) / (M + m0))
        jacs.append(J * M / (M + m0))
    return torch.tensor(np.array(coms)), torch.tensor(np.array(jacs))


@pytest.mark.parametrize("name, floating", [
    ("g1_29dof_rev_1_0", False), ("g1_29dof_rev_1_0", True), ("ur10", False), ("kinova", False),
    ("talos_reduced", False), ("yumi", False), ("baxter", False), ("allegro_right_hand", False),
])
def test_urdf_matches_pinocchio(name, floating):
    path = DATA / "urdf" / f"{name}.urdf"
    tree = parse_urdf(path)
    leaves = [link for link in tree.links if not tree.children(link)]
    chain = from_urdf(path, leaves, floating_base=floating, dtype=F64)
    q = chain.random_configuration((4,), generator=torch.Generator().manual_seed(6))
    ref_com, ref_J = _pinocchio_com(path, chain, q, floating)
    e_com, e_J = _max_errors(chain, q, ref_com, ref_J)
    assert e_com < 1e-10 and e_J < 1e-10, (e_com, e_J)


def test_urdf_links_fixed_to_a_moving_link_count_at_their_frame():
    """G1's pelvis_contour_link, head_link, imu and rubber-hand links hang from fixed joints; the chain to
    the two feet leaves the arms outside too (their joints at zero, as Pinocchio's neutral q)."""
    path = DATA / "urdf" / "g1_29dof_rev_1_0.urdf"
    chain = from_urdf(path, ["left_ankle_roll_link", "right_ankle_roll_link"], floating_base=True, dtype=F64)
    specs = parse_inertials(path)
    assert sorted(chain.mass_names) == sorted(k for k, s in specs.items() if s.mass > 0)
    full = from_urdf(path, [link for link in parse_urdf(path).links if not parse_urdf(path).children(link)],
                     floating_base=True, dtype=F64)
    q = chain.random_configuration((3,), generator=torch.Generator().manual_seed(7))
    q_full = torch.zeros(3, full.nq, dtype=F64)  # the joints outside the short chain at zero
    q_full[:, :7] = q[:, :7]  # the free joint
    for k, name in enumerate(chain.joint_names[1:]):
        q_full[:, 6 + full.joint_names.index(name)] = q[:, 7 + k]
    with torch.no_grad():
        torch.testing.assert_close(chain.center_of_mass(q), full.center_of_mass(q_full), atol=1e-12, rtol=0)


# --------------------------------------------------------------------------- finite differences, gradcheck

def _fd_jacobian(chain, q, h=1e-6):
    cols = []
    for k in range(chain.nv):
        e = torch.zeros(chain.nv, dtype=F64)
        e[k] = h
        plus = chain.center_of_mass(chain.integrate(q, e.expand(*q.shape[:-1], -1)))
        minus = chain.center_of_mass(chain.integrate(q, (-e).expand(*q.shape[:-1], -1)))
        cols.append((plus - minus) / (2 * h))
    return torch.stack(cols, dim=-1)


@pytest.mark.parametrize("kind", ["mjcf_free", "mjcf_ball", "urdf_mimic_prismatic"])
def test_jacobian_matches_finite_differences(kind):
    if kind == "mjcf_free":
        _, chain = _mjcf_chain(MJCF["unitree_g1"])
    elif kind == "mjcf_ball":
        _, chain = _mjcf_chain(MJCF["agility_cassie"], ["left-foot", "right-foot"])
    else:
        path = DATA / "urdf" / "yumi.urdf"
        tree = parse_urdf(path)
        chain = from_urdf(path, [k for k in tree.links if not tree.children(k)], dtype=F64)
    chain.requires_grad_(False)
    q = chain.random_configuration((3,), generator=torch.Generator().manual_seed(8))
    with torch.no_grad():
        torch.testing.assert_close(chain.com_jacobian(q), _fd_jacobian(chain, q), atol=1e-8, rtol=0)


def test_gradcheck_float64():
    _, chain = _mjcf_chain(MJCF["unitree_go2"], ["FL_calf", "RR_calf"])
    chain.requires_grad_(False)
    q = chain.random_configuration((2,), generator=torch.Generator().manual_seed(9)).requires_grad_(True)
    assert torch.autograd.gradcheck(chain.center_of_mass, (q,))
    assert torch.autograd.gradcheck(chain.com_jacobian, (q,))


def test_gradients_finite_at_the_neutral_configuration_and_to_the_geometry():
    _, chain = _mjcf_chain(MJCF["unitree_h1"], ["left_ankle_link", "right_elbow_link"])
    chain.requires_grad_()  # the geometry is frozen by default; this test differentiates w.r.t. it
    q = chain.neutral_configuration().requires_grad_(True)
    (chain.center_of_mass(q).sum() + chain.com_jacobian(q).square().sum()).backward()
    assert torch.isfinite(q.grad).all()
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in chain.parameters())
    assert chain.body_pos.grad is not None and chain.body_pos.grad.abs().sum() > 0


# ------------------------------------------------------------------------------ dtype, shapes, buffers

def test_float32_batch_shapes_and_buffers_follow_the_chain():
    _, c64 = _mjcf_chain(MJCF["unitree_go2"])
    _, c32 = _mjcf_chain(MJCF["unitree_go2"], dtype=torch.float32)
    assert c32.link_masses.dtype == torch.float32 and c64.link_masses.dtype == F64
    q = c64.random_configuration((2, 3), generator=torch.Generator().manual_seed(10))
    with torch.no_grad():
        com64, J64 = c64.center_of_mass(q), c64.com_jacobian(q)
        com32, J32 = c32.center_of_mass(q.float()), c32.com_jacobian(q.float())
        assert com64.shape == (2, 3, 3) and J64.shape == (2, 3, 3, c64.nv)
        assert com32.dtype == torch.float32 and J32.dtype == torch.float32
        torch.testing.assert_close(com32.double(), com64, atol=1e-5, rtol=0)
        torch.testing.assert_close(J32.double(), J64, atol=1e-5, rtol=0)
        assert c64.center_of_mass(q[0, 0]).shape == (3,) and c64.com_jacobian(q[0, 0]).shape == (3, c64.nv)
        torch.testing.assert_close(c64.center_of_mass(q[1, 2]), com64[1, 2])
        # > small_batch, and three 16 MiB slices of point Jacobians in the C pass (go2: 1493 rows each)
        big = c64.random_configuration((3100,), generator=torch.Generator().manual_seed(11))
        com_big, J_big = c64.center_of_mass(big), c64.com_jacobian(big)
    rows = torch.tensor([0, 1492, 1493, 2986, 3099])
    torch.testing.assert_close(J_big[rows], c64.com_jacobian(big[rows].requires_grad_(True)).detach())
    torch.testing.assert_close(com_big[rows], c64.center_of_mass(big[rows].requires_grad_(True)).detach())
    moved = c64.copy().to(torch.float32)
    assert moved.link_masses.dtype == torch.float32 and moved.link_inertial_frames.dtype == torch.float32
    assert "link_masses" not in c64.state_dict()  # not saved: the source file has the masses


def test_masses_are_read_on_every_call():
    _, chain = _mjcf_chain(MJCF["universal_robots_ur5e"], "wrist_3_link")
    q = chain.random_configuration((2,), generator=torch.Generator().manual_seed(12))
    with torch.no_grad():
        before = chain.center_of_mass(q)
        chain.link_masses[-1] += 10.0  # a payload on the last link
        after = chain.center_of_mass(q)
        m = chain.link_masses
        p_last = (chain.forward_kinematics(q)[..., :3, :3] @ chain.link_inertial_frames[-1, :3, 3]
                  + chain.forward_kinematics(q)[..., :3, 3])
        expected = (before * (m.sum() - 10.0) + 10.0 * p_last) / m.sum()
    assert chain.mass_names[-1] == "wrist_3_link"
    torch.testing.assert_close(after, expected)


# ------------------------------------------------------------------------------------------- errors

def test_chains_without_masses_raise_a_typed_error():
    dh = models.load("stanford", dtype=F64)
    with pytest.raises(ModelError, match="link masses.*stanford.*DH table"):
        dh.center_of_mass(torch.zeros(6, dtype=F64))
    with pytest.raises(ModelError, match="link masses"):
        dh.com_jacobian(torch.zeros(6, dtype=F64))
    fr3 = from_urdf(DATA / "urdf" / "fr3.urdf", "fr3_link8", dtype=F64)
    with pytest.raises(ModelError, match="no <inertial> element"):
        fr3.center_of_mass(torch.zeros(7, dtype=F64))
    _, chain = _mjcf_chain(MJCF["universal_robots_ur5e"], "wrist_3_link")
    with pytest.raises(ShapeError):
        chain.center_of_mass(torch.zeros(5, dtype=F64))


def test_malformed_inertials_are_named():
    text = ('<robot name="r"><link name="a"><inertial><mass value="-1"/></inertial></link>'
            '<link name="b"/><joint name="j" type="revolute"><parent link="a"/><child link="b"/>'
            '<axis xyz="0 0 1"/></joint></robot>')
    with pytest.raises(ModelError, match="link 'a' <inertial>"):
        from_urdf(text, "b", dtype=F64)
    massless = text.replace('<inertial><mass value="-1"/></inertial>', "")
    with pytest.raises(ModelError, match="no <inertial>"):
        from_urdf(massless, "b", dtype=F64).center_of_mass(torch.zeros(1, dtype=F64))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    _, chain = _mjcf_chain(MJCF["unitree_g1"])
    q = chain.random_configuration((64,), generator=torch.Generator().manual_seed(13))
    with torch.no_grad():
        com, J = chain.center_of_mass(q), chain.com_jacobian(q)
    gpu = chain.copy().to("cuda")
    assert gpu.link_masses.device.type == "cuda"
    qg = q.cuda().requires_grad_(True)
    com_g, J_g = gpu.center_of_mass(qg), gpu.com_jacobian(qg)
    torch.testing.assert_close(com_g.detach().cpu(), com, atol=1e-10, rtol=0)
    torch.testing.assert_close(J_g.detach().cpu(), J, atol=1e-10, rtol=0)
    (com_g.sum() + J_g.sum()).backward()
    assert torch.isfinite(qg.grad).all()


def test_urdf_root_link_is_its_subtree_in_its_frame():
    """From ``root_link="torso_link"`` the chain's bodies are the torso's subtree, in the torso's frame:
    Pinocchio's subtree centre of mass of the joint that carries the torso (``data.com[j]``,
    ``jacobianSubtreeCenterOfMass``), rotated into the torso frame."""
    pin = pytest.importorskip("pinocchio")
    path = DATA / "urdf" / "g1_29dof_rev_1_0.urdf"
    tree = parse_urdf(path)
    below = {"torso_link"}
    for j in tree.joints:  # file order is topological here; checked by the assertion below
        if j.parent in below:
            below.add(j.child)
    leaves = [k for k in below if not tree.children(k)]
    chain = from_urdf(path, leaves, root_link="torso_link", dtype=F64)
    assert set(chain.mass_names) <= below
    model = pin.buildModelFromUrdf(str(path))
    data = model.createData()
    jid = model.getJointId(tree.parent_joint("torso_link").name)
    q = chain.random_configuration((3,), generator=torch.Generator().manual_seed(14))
    for qi in q:
        qp = pin.neutral(model)
        qp[[model.joints[model.getJointId(n)].idx_q for n in chain.joint_names]] = qi.numpy()
        pin.forwardKinematics(model, data, qp)
        pin.centerOfMass(model, data, qp)
        Jp = pin.jacobianSubtreeCenterOfMass(model, data, qp, jid)
        R, p = data.oMi[jid].rotation, data.oMi[jid].translation
        cols = [model.joints[model.getJointId(n)].idx_v for n in chain.joint_names]
        with torch.no_grad():
            com = chain.center_of_mass(qi).numpy()
            np.testing.assert_allclose(com, R.T @ (data.com[jid] - p), atol=1e-12)
            np.testing.assert_allclose(chain.com_jacobian(qi).numpy(), R.T @ Jp[:, cols], atol=1e-12)


def test_gradients_reach_learnable_masses():
    """A payload estimate: the masses as a learnable tensor, the gradient of the centre of mass w.r.t. them
    against finite differences; two backward passes in a row (no graph kept between calls)."""
    _, chain = _mjcf_chain(MJCF["universal_robots_ur5e"], "wrist_3_link")
    chain.requires_grad_(False)
    q = chain.random_configuration((3,), generator=torch.Generator().manual_seed(15))
    chain.link_masses.requires_grad_(True)
    for _ in range(2):
        chain.link_masses.grad = None
        chain.center_of_mass(q).sum().backward()
    g = chain.link_masses.grad.clone()
    chain.link_masses.requires_grad_(False)
    fd = []
    for i in range(len(chain.mass_names)):
        with torch.no_grad():
            chain.link_masses[i] += 1e-6
            plus = chain.center_of_mass(q).sum()
            chain.link_masses[i] -= 2e-6
            minus = chain.center_of_mass(q).sum()
            chain.link_masses[i] += 1e-6
        fd.append((plus - minus) / 2e-6)
    torch.testing.assert_close(g, torch.stack(fd), atol=1e-8, rtol=0)
