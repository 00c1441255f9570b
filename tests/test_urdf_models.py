"""URDF models as learnable kinematic trees, against real robot descriptions (tests/data/urdf/, see README).

Every pose is checked against tests/urdf_reference.py, an independent numpy FK (xml.etree + products of
origin and joint-motion matrices), which is itself checked against pytorch-kinematics here. Jacobians are
checked against central finite differences of the FK: position rows dp/dq, angular rows vee(dR/dq R^T).

The API under test: ``diffkin.models.from_urdf(source, end_link, *, root_link=None, dtype=None, device=None)``
with ``end_link`` a link name (poses (..., 4, 4), Jacobians (..., 6, n)) or a list of K link names
((..., K, 4, 4), (..., K, 6, n)); ``chain.joint_names`` (the independent joints, mimic followers excluded),
``chain.n_joints``, ``chain.parameters()`` (the geometry) and ``chain.to_urdf(path)``.
"""

from __future__ import annotations

import functools
import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import torch
from urdf_reference import ReferenceTree  # tests/ is on sys.path (pytest rootdir conftest)

from diffkin.errors import ModelError
from diffkin.models import from_urdf

DATA = Path(__file__).parent / "data" / "urdf"
F64 = torch.float64

# (file stem, end link): the flange / tool frame of each single arm.
SINGLE_ARMS = [
    ("fr3", "fr3_link8"),  # Franka FR3 flange (7 DOF)
    ("ur10", "tool0"),  # UR10, parallel axes 2-3-4
    ("irb2400", "tool0"),  # ABB IRB 2400 (ROS-Industrial)
    ("kinova", "j2s6s200_end_effector"),  # encoding declaration; continuous joints 1, 4, 6
    ("meca500", "meca_axis_6_link"),  # encoding declaration; no tool frame, the last link
    ("so101", "gripper_frame_link"),  # encoding declaration; fixed joint with axis "0 0 0"
    ("ur3_robot", "tool0"),  # encoding declaration
]

# (file stem, end links in the order asked): trees with several end links.
TREES = [
    ("baxter", ["right_gripper", "left_gripper"]),
    ("yumi", ["gripper_l_base", "gripper_r_base"]),
    ("yumi", ["gripper_r_finger_r", "gripper_r_finger_l", "gripper_l_finger_l"]),  # mimic followers
    ("tiago_dual", ["arm_left_tool_link", "arm_right_tool_link"]),  # shared prismatic torso lift
]

ALLEGRO_TIPS = ["link_3.0_tip", "link_7.0_tip", "link_11.0_tip", "link_15.0_tip"]


@functools.cache
def reference(stem: str) -> ReferenceTree:
    return ReferenceTree(DATA / f"{stem}.urdf")


def load(stem: str, end_link, dtype=F64, **kw):
    return from_urdf(DATA / f"{stem}.urdf", end_link, dtype=dtype, **kw)


def sample(tree: ReferenceTree, names, n: int, seed: int) -> tuple[list[dict], torch.Tensor]:
    """n random configurations within limits, as dicts for the reference and as an (n, len(names)) tensor."""
    rng = np.random.default_rng(seed)
    qs = [tree.random_q(names, rng) for _ in range(n)]
    return qs, torch.tensor([[q[name] for name in names] for q in qs], dtype=F64)


def ref_poses(tree: ReferenceTree, q: dict, end_link, root_link=None) -> np.ndarray:
    if isinstance(end_link, str):
        return tree.fk(q, end_link, root_link)
    return np.stack([tree.fk(q, e, root_link) for e in end_link])


def vee_rate(dR: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """Angular velocity from dR/dq and R: vee of the (numerically skew) dR R^T."""
    W = dR @ R.transpose(-1, -2)
    wx, wy, wz = W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]
    return 0.5 * torch.stack([wx, wy, wz], -1)


def fd_jacobian(fk, q: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Central-difference geometric Jacobian (..., 6, n) of fk: (..., n) -> (..., [K,] 4, 4).

    The batch dimensions of q lead; a K axis of the poses (if any) stays in front of the 6 rows.
    """
    T = fk(q)
    cols = []
    for i in range(q.shape[-1]):
        dq = torch.zeros_like(q)
        dq[..., i] = eps
        Tp, Tm = fk(q + dq), fk(q - dq)
        dp = (Tp[..., :3, 3] - Tm[..., :3, 3]) / (2 * eps)
        w = vee_rate((Tp[..., :3, :3] - Tm[..., :3, :3]) / (2 * eps), T[..., :3, :3])
        cols.append(torch.cat([dp, w], -1))
    return torch.stack(cols, -1)


def ref_fk_torch(tree: ReferenceTree, names, end_link, root_link=None):
    """The reference FK as a function of a (n,) float64 tensor, for finite differences of the reference."""

    def fk(q: torch.Tensor) -> torch.Tensor:
        qd = dict(zip(names, q.tolist(), strict=True))
        return torch.from_numpy(ref_poses(tree, qd, end_link, root_link))

    return fk


def c14n(elem: ET.Element) -> str:
    return ET.canonicalize(ET.tostring(elem), strip_text=True)


# ---------------------------------------------------------------------------------------------------------
# The reference itself, against a third party


@pytest.fixture
def pk_float64(monkeypatch):
    """pytorch-kinematics 0.10 with its joint/link offsets built in float64.

    Stock pk converts each URDF origin through a float32 rpy tensor and a float32 Transform3d
    (urdf._convert_transform) and builds the Chain in float32, which limits agreement to ~1e-7; the two
    patches below change only those dtypes, not its arithmetic (quaternion_from_euler "sxyz", its own FK).
    """
    pk = pytest.importorskip("pytorch_kinematics")
    import pytorch_kinematics.chain as pk_chain
    import pytorch_kinematics.transforms as pk_tf
    import pytorch_kinematics.urdf as pk_urdf

    def convert_transform_f64(origin):
        if origin is None:
            return pk_tf.Transform3d(dtype=F64)
        rpy = torch.tensor(origin.rpy, dtype=F64)
        return pk_tf.Transform3d(rot=pk_tf.quaternion_from_euler(rpy, "sxyz"), pos=origin.xyz, dtype=F64)

    monkeypatch.setattr(pk_urdf, "_convert_transform", convert_transform_f64)
    monkeypatch.setattr(pk_chain.Chain.__init__, "__defaults__", (F64, "cpu"))
    return pk


@pytest.mark.parametrize("stem,end_link", [("fr3", "fr3_link8"), ("ur10", "tool0"), ("irb2400", "tool0"),
                                           ("kinova", "j2s6s200_end_effector")])
def test_reference_matches_pytorch_kinematics(pk_float64, stem, end_link):
    tree = reference(stem)
    # bytes, so that kinova's encoding declaration is accepted by pk's parser
    pk_chain = pk_float64.build_serial_chain_from_urdf((DATA / f"{stem}.urdf").read_bytes(), end_link)
    pk_chain = pk_chain.to(dtype=F64)
    names = pk_chain.get_joint_parameter_names()
    assert names == tree.moving_path_joints(end_link)
    qs, Q = sample(tree, names, 10, seed=1)
    T_pk = pk_chain.forward_kinematics(Q).get_matrix().numpy()
    for q, T in zip(qs, T_pk, strict=True):
        np.testing.assert_allclose(T, tree.fk(q, end_link), rtol=0, atol=1e-10)


@pytest.mark.parametrize("stem,ends", [("baxter", ["left_gripper", "right_gripper"]),
                                       ("tiago_dual", ["arm_left_tool_link", "arm_right_tool_link"]),
                                       ("allegro_right_hand", ALLEGRO_TIPS)])
def test_reference_matches_pytorch_kinematics_on_trees(pk_float64, stem, ends):
    tree = reference(stem)
    pk_chain = pk_float64.build_chain_from_urdf((DATA / f"{stem}.urdf").read_bytes()).to(dtype=F64)
    names = pk_chain.get_joint_parameter_names()
    qs, Q = sample(tree, names, 2, seed=1)
    frames = pk_chain.forward_kinematics(Q)
    for b, q in enumerate(qs):
        for end in ends:
            T = frames[end].get_matrix()[b].numpy()
            np.testing.assert_allclose(T, tree.fk(q, end), rtol=0, atol=1e-10)


def test_reference_handles_mimic_and_root_link():
    yumi = reference("yumi")
    assert yumi.variables("gripper_r_finger_l") >= {"gripper_r_joint"}
    assert "gripper_r_joint_m" not in yumi.variables("gripper_r_finger_l")
    q = {name: 0.0 for name in yumi.variables(["gripper_r_finger_l", "gripper_r_finger_r"])}
    q["gripper_r_joint"] = 0.02
    # the two fingers of the same gripper open symmetrically (origins rotated by pi about z, axes -x)
    base = yumi.fk(q, "gripper_r_base")
    d_r = np.linalg.solve(base, yumi.fk(q, "gripper_r_finger_r"))[:3, 3]
    d_l = np.linalg.solve(base, yumi.fk(q, "gripper_r_finger_l"))[:3, 3]
    assert abs(abs(d_r[0] - d_l[0]) - 2 * 0.02) < 1e-12
    fr3 = reference("fr3")
    q = {name: 0.3 for name in fr3.variables("fr3_link8")}
    T = fr3.fk(q, "fr3_link8")
    np.testing.assert_allclose(fr3.fk(q, "fr3_link3") @ fr3.fk(q, "fr3_link8", root_link="fr3_link3"), T,
                               atol=1e-14)


# ---------------------------------------------------------------------------------------------------------
# Single arms


@pytest.mark.parametrize("stem,end_link", SINGLE_ARMS)
def test_single_arm_fk_matches_reference(stem, end_link):
    tree = reference(stem)
    chain = load(stem, end_link)
    assert set(chain.joint_names) == set(tree.moving_path_joints(end_link))
    assert chain.n_joints == len(chain.joint_names)
    qs, Q = sample(tree, chain.joint_names, 20, seed=2)
    T = chain.forward_kinematics(Q)
    assert T.shape == (20, 4, 4) and T.dtype == F64
    want = np.stack([tree.fk(q, end_link) for q in qs])
    np.testing.assert_allclose(T.detach().numpy(), want, rtol=0, atol=1e-10)


@pytest.mark.parametrize("stem,end_link", SINGLE_ARMS)
def test_single_arm_jacobian_matches_finite_differences(stem, end_link):
    tree = reference(stem)
    chain = load(stem, end_link)
    _, Q = sample(tree, chain.joint_names, 3, seed=3)
    J = chain.geometric_jacobian(Q)
    assert J.shape == (3, 6, chain.n_joints)
    with torch.no_grad():
        J_fd = fd_jacobian(chain.forward_kinematics, Q)
    torch.testing.assert_close(J.detach(), J_fd, rtol=0, atol=1e-6)


@pytest.mark.parametrize("stem,end_link", SINGLE_ARMS)
def test_single_arm_float32(stem, end_link):
    tree = reference(stem)
    chain = load(stem, end_link, dtype=torch.float32)
    qs, Q = sample(tree, chain.joint_names, 5, seed=4)
    T = chain.forward_kinematics(Q.float())
    assert T.dtype == torch.float32
    want = np.stack([tree.fk(q, end_link) for q in qs])
    np.testing.assert_allclose(T.detach().double().numpy(), want, rtol=0, atol=1e-4)
    assert chain.geometric_jacobian(Q.float()).dtype == torch.float32


def test_continuous_joints_are_unlimited():
    """kinova's continuous joints carry <limit lower=-2pi upper=2pi>, which do not apply: no clamping."""
    tree = reference("kinova")
    end = "j2s6s200_end_effector"
    chain = load("kinova", end)
    q = {name: 0.5 for name in chain.joint_names}
    for name in ("j2s6s200_joint_1", "j2s6s200_joint_4", "j2s6s200_joint_6"):
        q[name] = 7.0 if name != "j2s6s200_joint_4" else -9.5
    Q = torch.tensor([q[name] for name in chain.joint_names], dtype=F64)
    np.testing.assert_allclose(chain.forward_kinematics(Q).detach().numpy(), tree.fk(q, end), atol=1e-10)


def test_sources_path_str_bytes_and_encoding_declaration():
    """A file with an XML encoding declaration loads from a Path, a path string, an XML str and bytes."""
    path = DATA / "meca500.urdf"
    text = path.read_text(encoding="utf-8")
    assert text.startswith('<?xml version="1.0" encoding="utf-8"?>')
    end = "meca_axis_6_link"
    chains = [from_urdf(src, end, dtype=F64) for src in (path, str(path), text, path.read_bytes())]
    names = list(chains[0].joint_names)
    qs, Q = sample(reference("meca500"), names, 4, seed=5)
    want = np.stack([reference("meca500").fk(q, end) for q in qs])
    for chain in chains:
        assert list(chain.joint_names) == names
        np.testing.assert_allclose(chain.forward_kinematics(Q).detach().numpy(), want, rtol=0, atol=1e-10)


def test_root_link():
    tree = reference("fr3")
    chain = load("fr3", "fr3_link8", root_link="fr3_link2")
    assert set(chain.joint_names) == {f"fr3_joint{i}" for i in range(3, 8)}
    qs, Q = sample(tree, chain.joint_names, 5, seed=6)
    want = np.stack([tree.fk(q, "fr3_link8", root_link="fr3_link2") for q in qs])
    np.testing.assert_allclose(chain.forward_kinematics(Q).detach().numpy(), want, atol=1e-10)


# ---------------------------------------------------------------------------------------------------------
# Trees with several end links


@pytest.mark.parametrize("stem,ends", TREES, ids=[f"{s}-{len(e)}" for s, e in TREES])
def test_tree_fk_matches_reference(stem, ends):
    tree = reference(stem)
    chain = load(stem, ends)
    assert set(chain.joint_names) == tree.variables(ends)
    assert len(chain.joint_names) == len(set(chain.joint_names)) == chain.n_joints
    qs, Q = sample(tree, chain.joint_names, 6, seed=7)
    T = chain.forward_kinematics(Q)
    assert T.shape == (6, len(ends), 4, 4)
    want = np.stack([ref_poses(tree, q, ends) for q in qs])
    np.testing.assert_allclose(T.detach().numpy(), want, rtol=0, atol=1e-10)


@pytest.mark.parametrize("stem,ends", TREES, ids=[f"{s}-{len(e)}" for s, e in TREES])
def test_tree_jacobian_matches_finite_differences_and_is_block_sparse(stem, ends):
    tree = reference(stem)
    chain = load(stem, ends)
    _, Q = sample(tree, chain.joint_names, 2, seed=8)
    J = chain.geometric_jacobian(Q).detach()
    assert J.shape == (2, len(ends), 6, chain.n_joints)
    with torch.no_grad():
        J_fd = fd_jacobian(chain.forward_kinematics, Q)
    torch.testing.assert_close(J, J_fd, rtol=0, atol=1e-6)
    for k, end in enumerate(ends):
        moving = tree.ancestors(end)
        for j, name in enumerate(chain.joint_names):
            col = J[:, k, :, j]
            if name in moving:
                assert col.abs().amax() > 1e-6, (end, name)
            else:
                assert torch.equal(col, torch.zeros_like(col)), (end, name)


def test_tiago_root_link_drops_the_shared_torso():
    tree = reference("tiago_dual")
    ends = ["arm_right_tool_link", "arm_left_tool_link"]
    chain = load("tiago_dual", ends, root_link="torso_lift_link")
    assert "torso_lift_joint" not in chain.joint_names
    assert set(chain.joint_names) == tree.variables(ends, "torso_lift_link")
    qs, Q = sample(tree, chain.joint_names, 3, seed=9)
    want = np.stack([ref_poses(tree, q, ends, "torso_lift_link") for q in qs])
    np.testing.assert_allclose(chain.forward_kinematics(Q).detach().numpy(), want, atol=1e-10)


def test_allegro_four_fingertips_in_one_chain():
    tree = reference("allegro_right_hand")
    hand = load("allegro_right_hand", ALLEGRO_TIPS)
    singles = [load("allegro_right_hand", tip) for tip in ALLEGRO_TIPS]
    union = set().union(*(s.joint_names for s in singles))
    assert hand.n_joints == len(union) == 16 and set(hand.joint_names) == union
    qs, Q = sample(tree, hand.joint_names, 5, seed=10)
    T = hand.forward_kinematics(Q)
    J = hand.geometric_jacobian(Q)
    assert T.shape == (5, 4, 4, 4) and J.shape == (5, 4, 6, 16)
    want = np.stack([ref_poses(tree, q, ALLEGRO_TIPS) for q in qs])
    np.testing.assert_allclose(T.detach().numpy(), want, rtol=0, atol=1e-10)
    for k, single in enumerate(singles):
        idx = [hand.joint_names.index(name) for name in single.joint_names]
        torch.testing.assert_close(single.forward_kinematics(Q[:, idx]), T[:, k], rtol=0, atol=1e-12)
        J_single = single.geometric_jacobian(Q[:, idx])
        torch.testing.assert_close(J_single, J[:, k][..., idx], rtol=0, atol=1e-12)
        others = [j for j in range(16) if j not in idx]
        assert torch.equal(J[:, k][..., others], torch.zeros_like(J[:, k][..., others]))


# ---------------------------------------------------------------------------------------------------------
# Mimic joints


def _check_mimic(tree, chain, ends, leader, followers, seed):
    """Followers are not variables; FK equals the reference (follower = m * leader + offset); the leader's
    Jacobian column equals finite differences of the reference w.r.t. the leader (the follower moves too)."""
    names = list(chain.joint_names)
    assert leader in names
    assert not set(followers) & set(names)
    qs, Q = sample(tree, names, 3, seed=seed)
    T = chain.forward_kinematics(Q).detach()
    want = np.stack([ref_poses(tree, q, ends) for q in qs])
    np.testing.assert_allclose(T.numpy(), want, rtol=0, atol=1e-10)
    J = chain.geometric_jacobian(Q).detach()
    i = names.index(leader)
    for b in range(Q.shape[0]):
        J_ref = fd_jacobian(ref_fk_torch(tree, names, ends), Q[b])
        torch.testing.assert_close(J[b][..., i], J_ref[..., i], rtol=0, atol=1e-6)
        assert J[b][..., i].abs().amax() > 1e-3


def test_yumi_mimic_fingers():
    tree = reference("yumi")
    # gripper_r_finger_l is moved only by gripper_r_joint_m, <mimic joint="gripper_r_joint"/> (m=1, offset=0),
    # a sibling branch of the leader's own finger.
    chain = load("yumi", "gripper_r_finger_l")
    _check_mimic(tree, chain, "gripper_r_finger_l", "gripper_r_joint", ["gripper_r_joint_m"], seed=11)
    ends = ["gripper_l_finger_r", "gripper_l_finger_l"]
    chain = load("yumi", ends)
    _check_mimic(tree, chain, ends, "gripper_l_joint", ["gripper_l_joint_m"], seed=12)


TALOS_LEFT_MIMICS = {  # follower -> (multiplier, offset) in the file; all are type="fixed" there
    "gripper_left_inner_double_joint": 1.0,
    "gripper_left_fingertip_1_joint": -1.0,
    "gripper_left_fingertip_2_joint": -1.0,
    "gripper_left_motor_single_joint": -1.0,
    "gripper_left_inner_single_joint": -1.0,
    "gripper_left_fingertip_3_joint": -1.0,
}


def test_talos_fixed_joints_with_mimic_stay_fixed():
    """talos_reduced keeps the <mimic> elements of its gripper joints but declares them type="fixed": they do
    not move, so the fingertips do not depend on the gripper joint."""
    tree = reference("talos_reduced")
    ends = ["gripper_left_motor_double_link", "gripper_left_fingertip_1_link",
            "gripper_left_fingertip_3_link"]
    chain = load("talos_reduced", ends)
    assert "gripper_left_joint" in chain.joint_names
    assert not set(TALOS_LEFT_MIMICS) & set(chain.joint_names)
    qs, Q = sample(tree, chain.joint_names, 3, seed=13)
    want = np.stack([ref_poses(tree, q, ends) for q in qs])
    np.testing.assert_allclose(chain.forward_kinematics(Q).detach().numpy(), want, rtol=0, atol=1e-10)
    J = chain.geometric_jacobian(Q).detach()
    i = chain.joint_names.index("gripper_left_joint")
    assert J[:, 0, :, i].abs().amax() > 1e-3
    assert torch.equal(J[:, 1:, :, i], torch.zeros_like(J[:, 1:, :, i]))


def _talos_with_moving_mimics() -> str:
    """talos_reduced with its left gripper's mimic joints made revolute, and an offset on one of them."""
    text = (DATA / "talos_reduced.urdf").read_text()
    for name in TALOS_LEFT_MIMICS:
        head = f'<joint name="{name}" type='
        text, n = re.subn(re.escape(head + '"fixed">'), head + '"revolute">', text)
        assert n == 1, name
    text, n = re.subn(r'(<joint name="gripper_left_fingertip_1_joint" type="revolute">(?:(?!</joint>).)*?'
                      r'offset=")0.0(")', r"\g<1>0.25\2", text, flags=re.S)
    assert n == 1
    return text


def test_talos_mimic_on_another_branch():
    """Made revolute, the followers (m = +1 / -1, one with offset 0.25) move the fingertips, which are on
    other branches than the leader gripper_left_joint: the leader is a variable of a chain to a fingertip."""
    text = _talos_with_moving_mimics()
    tree = ReferenceTree(text)
    assert tree.joints["gripper_left_fingertip_1_joint"].mimic == ("gripper_left_joint", -1.0, 0.25)
    assert "gripper_left_joint" not in tree.path_joints("gripper_left_fingertip_1_link")
    chain = from_urdf(text, "gripper_left_fingertip_1_link", dtype=F64)
    _check_mimic(tree, chain, "gripper_left_fingertip_1_link", "gripper_left_joint", list(TALOS_LEFT_MIMICS),
                 seed=14)
    ends = ["gripper_left_fingertip_3_link", "gripper_left_motor_double_link",
            "gripper_left_fingertip_2_link"]
    chain = from_urdf(text.encode(), ends, dtype=F64)
    _check_mimic(tree, chain, ends, "gripper_left_joint", list(TALOS_LEFT_MIMICS), seed=15)


# ---------------------------------------------------------------------------------------------------------
# Batch shapes


@pytest.mark.parametrize("stem,ends", [("fr3", "fr3_link8"), ("baxter", ["left_gripper", "right_gripper"])])
def test_batch_shapes(stem, ends):
    tree = reference(stem)
    chain = load(stem, ends)
    n = chain.n_joints
    _, Q = sample(tree, chain.joint_names, 6, seed=16)
    tail = (4, 4) if isinstance(ends, str) else (len(ends), 4, 4)
    jtail = (6, n) if isinstance(ends, str) else (len(ends), 6, n)
    T_all = chain.forward_kinematics(Q)
    J_all = chain.geometric_jacobian(Q)
    for shape in [(), (5,), (2, 3)]:
        m = math.prod(shape)
        Qs = Q[:m].reshape(*shape, n)
        T = chain.forward_kinematics(Qs)
        J = chain.geometric_jacobian(Qs)
        assert T.shape == (*shape, *tail) and J.shape == (*shape, *jtail)
        torch.testing.assert_close(T.reshape(m, *tail), T_all[:m], rtol=0, atol=1e-13)
        torch.testing.assert_close(J.reshape(m, *jtail), J_all[:m], rtol=0, atol=1e-13)


# ---------------------------------------------------------------------------------------------------------
# Gradients with respect to the geometry


class _FK(torch.nn.Module):
    def __init__(self, chain):
        super().__init__()
        self.chain = chain

    def forward(self, q):
        return self.chain.forward_kinematics(q)


def test_fk_gradcheck_wrt_geometry():
    chain = load("fr3", "fr3_link8")
    named = [(name, p) for name, p in chain.named_parameters()]
    assert named and all(p.dtype == F64 for _, p in named)
    _, Q = sample(reference("fr3"), chain.joint_names, 3, seed=17)
    module = _FK(chain)
    keys = [f"chain.{name}" for name, _ in named]

    def fk_of(*values):
        return torch.func.functional_call(module, dict(zip(keys, values, strict=True)), (Q,))

    values = tuple(p.detach().clone().requires_grad_(True) for _, p in named)
    assert torch.autograd.gradcheck(fk_of, values, eps=1e-6, atol=1e-7)


def test_every_parameter_gets_a_gradient():
    """meca500 is purely serial (no side links), so every geometry parameter moves the last link."""
    chain = load("meca500", "meca_axis_6_link", learnable=True)
    params = list(chain.named_parameters())
    assert params
    _, Q = sample(reference("meca500"), chain.joint_names, 3, seed=18)
    W = torch.randn(3, 4, 4, dtype=F64, generator=torch.Generator().manual_seed(0))
    (chain.forward_kinematics(Q) * W).sum().backward()
    for name, p in params:
        assert p.grad is not None, name
        assert torch.isfinite(p.grad).all(), name
        assert p.grad.abs().amax() > 0, name


# ---------------------------------------------------------------------------------------------------------
# Structural errors


def _urdf(body: str) -> str:
    # no encoding declaration here: that feature is tested on its own (meca500 as a str)
    return f'<?xml version="1.0"?>\n<robot name="t">\n{body}\n</robot>\n'


def _rev(name, parent, child, jtype="revolute"):
    lim = ""
    if jtype in ("revolute", "prismatic"):
        lim = '<limit lower="-1" upper="1" effort="1" velocity="1"/>'
    return (f'<joint name="{name}" type="{jtype}"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="0 0 1"/>{lim}</joint>')


def _links(*names):
    return "".join(f'<link name="{n}"/>' for n in names)


GOOD = _links("base", "l1", "tip") + _rev("j1", "base", "l1") + _rev("j2", "l1", "tip")

BAD = {
    "missing_parent": (_links("base", "l1", "tip") + _rev("j1", "ghost_parent", "l1")
                       + _rev("j2", "l1", "tip"), "tip", "ghost_parent"),
    "missing_child": (_links("base", "l1", "tip") + _rev("j1", "base", "l1") + _rev("j2", "l1", "tip")
                      + _rev("j3", "l1", "ghost_child"), "tip", "ghost_child"),
    "two_parents": (_links("base", "l1", "l2", "shared_child") + _rev("j1", "base", "l1")
                    + _rev("j2", "base", "l2") + _rev("j3", "l1", "shared_child")
                    + _rev("j4", "l2", "shared_child"), "shared_child", "shared_child"),
    "duplicate_joint": (_links("base", "l1", "tip") + _rev("dup_joint", "base", "l1")
                        + _rev("dup_joint", "l1", "tip"), "tip", "dup_joint"),
    "duplicate_link": (_links("base", "dup_link", "dup_link", "tip") + _rev("j1", "base", "dup_link")
                       + _rev("j2", "dup_link", "tip"), "tip", "dup_link"),
    # floating and planar joints on a path load (free and planar joints, tests/test_configuration.py); a
    # mimic of one is refused, naming the follower
    "mimic_of_floating": (_links("base", "l1", "tip") + _rev("float_joint", "base", "l1", "floating")
                          + _rev("follower", "l1", "tip").replace(
                              "</joint>", '<mimic joint="float_joint"/></joint>'), "tip", "follower"),
    "unknown_end_link": (GOOD, "no_such_link", "no_such_link"),
    "unknown_end_link_in_list": (GOOD, ["tip", "no_such_link"], "no_such_link"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_structural_errors(case):
    text, end, offending = BAD[case]
    with pytest.raises(ModelError, match=re.escape(offending)):
        from_urdf(_urdf(text), end, dtype=F64)


@pytest.mark.parametrize("with_root", [True, False], ids=["loop_beside_root", "loop_without_root"])
def test_loop_raises_and_does_not_hang(with_root):
    loop = (_links("loop_a", "loop_b", "loop_c") + _rev("ja", "loop_a", "loop_b")
            + _rev("jb", "loop_b", "loop_c") + _rev("jc", "loop_c", "loop_a"))
    if with_root:
        loop = _links("base", "l1") + _rev("j0", "base", "l1") + loop
    with pytest.raises(ModelError, match="loop_a|loop_b|loop_c"):
        from_urdf(_urdf(loop), "loop_c", dtype=F64)


def test_valid_small_urdf_and_floating_joint_off_the_path():
    """The hand-written fixture itself is valid; a floating joint on a side branch does not matter."""
    chain = from_urdf(_urdf(GOOD), "tip", dtype=F64)
    assert set(chain.joint_names) == {"j1", "j2"}
    side = GOOD + _links("side") + _rev("side_float", "l1", "side", "floating")
    chain = from_urdf(_urdf(side), "tip", dtype=F64)
    assert set(chain.joint_names) == {"j1", "j2"}
    q = {"j1": 0.3, "j2": -0.2}
    T = chain.forward_kinematics(torch.tensor([q[name] for name in chain.joint_names], dtype=F64))
    want = ReferenceTree(_urdf(GOOD)).fk(q, "tip")
    np.testing.assert_allclose(T.detach().numpy(), want, atol=1e-14)


# ---------------------------------------------------------------------------------------------------------
# Writing back


def _geometry_blocks(path: Path) -> dict[str, list[str]]:
    """Canonical XML of each link's <visual> and <collision> blocks, in file order."""
    root = ET.fromstring(path.read_bytes())
    return {link.get("name"): [c14n(e) for e in link if e.tag in ("visual", "collision")]
            for link in root.findall("link")}


@pytest.mark.parametrize("stem,ends", [("fr3", "fr3_link8"), ("baxter", ["left_gripper", "right_gripper"])])
def test_to_urdf_round_trip(tmp_path, stem, ends):
    tree = reference(stem)
    chain = load(stem, ends)
    qs, Q = sample(tree, chain.joint_names, 4, seed=19)
    T_orig = chain.forward_kinematics(Q).detach()
    with torch.no_grad():
        for p in chain.parameters():
            p.add_(1e-3)
    T_mod = chain.forward_kinematics(Q).detach()
    assert (T_mod - T_orig).abs().amax() > 1e-4  # the edit moved the end links
    out = tmp_path / f"{stem}_calibrated.urdf"
    chain.to_urdf(out)
    again = from_urdf(out, ends, dtype=F64)
    assert set(again.joint_names) == set(chain.joint_names)
    idx = [chain.joint_names.index(name) for name in again.joint_names]
    torch.testing.assert_close(again.forward_kinematics(Q[:, idx]).detach(), T_mod, rtol=0, atol=1e-12)
    assert _geometry_blocks(out) == _geometry_blocks(DATA / f"{stem}.urdf")



def test_valid_urdfs_parse_without_console_noise(capfd):
    """Loading real manufacturer URDFs prints nothing (no "Unknown attribute" lines, as pytorch-kinematics'
    parser printed for a valid Franka URDF)."""
    files = sorted(DATA.glob("*.urdf"))
    assert files
    for path in files:
        from_urdf(path, _first_leaf(path))
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def _first_leaf(path: Path) -> str:
    """The leaf link with the most moving joints on its path from the root."""
    root = ET.parse(path).getroot()
    up = {j.find("child").get("link"): (j.find("parent").get("link"), j.get("type") != "fixed")
          for j in root.findall("joint")}
    parents = {p for p, _ in up.values()}

    def moving(link: str) -> int:
        n = 0
        while link in up:
            link, m = up[link]
            n += m
        return n

    return max((c for c in up if c not in parents), key=moving)
