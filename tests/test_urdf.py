"""URDF import: URDFChain against pytorch-kinematics's own FK / Jacobian and against the DH models.

pytorch-kinematics 0.10 builds its joint offsets in float32 (``_convert_transform``), so comparisons with it
use a ~1e-6 tolerance even in float64; the DH models are compared at 1e-12.
"""

from __future__ import annotations

import math

import pytest
import torch

from diffkin import models
from diffkin.errors import ModelError
from diffkin.models import URDFChain, from_urdf, load

pk = pytest.importorskip("pytorch_kinematics")

F64 = torch.float64
PANDA = models.DATA_DIR / "panda.urdf"
UR5 = models.DATA_DIR / "ur5.urdf"
RZ_PI = torch.tensor([[-1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=F64)

# A synthetic tree: prismatic and continuous joints, tilted and negative axes, fixed joints between moving
# ones, a side branch, and a fixed tip.
TOY = """<?xml version="1.0"?>
<robot name="toy">
  <link name="world"/><link name="l1"/><link name="l1b"/><link name="l2"/><link name="l3"/><link name="l4"/>
  <link name="tip"/><link name="side"/>
  <joint name="j1" type="revolute"><parent link="world"/><child link="l1"/>
    <origin xyz="0.1 0 0.2" rpy="0.1 0.2 0.3"/><axis xyz="0 0 1"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="f1" type="fixed"><parent link="l1"/><child link="l1b"/>
    <origin xyz="0 0.3 0" rpy="1.5707963267948966 0 0"/></joint>
  <joint name="side" type="revolute"><parent link="l1"/><child link="side"/><axis xyz="1 0 0"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="j2" type="prismatic"><parent link="l1b"/><child link="l2"/>
    <origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="0.6 0 0.8"/>
    <limit lower="-0.1" upper="0.4" effort="1" velocity="1"/></joint>
  <joint name="j3" type="continuous"><parent link="l2"/><child link="l3"/>
    <origin xyz="0.2 0 0" rpy="0 -0.5 0"/><axis xyz="0 -1 0"/></joint>
  <joint name="j4" type="revolute"><parent link="l3"/><child link="l4"/>
    <origin xyz="0 0.1 0.3" rpy="0.4 0 -1.2"/><axis xyz="1 2 2"/>
    <limit lower="-3" upper="1" effort="1" velocity="1"/></joint>
  <joint name="tipj" type="fixed"><parent link="l4"/><child link="tip"/>
    <origin xyz="0.05 0 0.15" rpy="0 0.3 0"/></joint>
</robot>
"""


def _pk_chain(source, end, dtype):
    data = source.read_bytes() if hasattr(source, "read_bytes") else source.encode()
    return pk.build_serial_chain_from_urdf(data, end).to(dtype=dtype)


def _force(chain, kernel):
    chain.small_batch = 10**9 if kernel == "matrix" else -1
    return chain


@pytest.mark.parametrize("source, end", [(PANDA, "panda_link8"), (UR5, "tool0"), (TOY, "tip")])
@pytest.mark.parametrize("kernel", ["matrix", "column"])
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_fk_matches_pytorch_kinematics(source, end, kernel, dtype):
    chain = _force(from_urdf(source, end, dtype=dtype), kernel)
    ref = _pk_chain(source, end, dtype)
    q = chain.random_configuration((20,), generator=torch.Generator().manual_seed(0))
    T = chain.forward_kinematics(q)
    assert T.dtype == dtype and T.shape == (20, 4, 4)
    torch.testing.assert_close(T, ref.forward_kinematics(q).get_matrix(), atol=2e-6, rtol=0)
    # every link frame (all_frames) against pk's per-link poses
    frames = chain.forward_kinematics(q, all_frames=True)
    pk_frames = ref.forward_kinematics(q, end_only=False)
    for i in range(1, chain.n_joints):
        link = chain.link_names[i - 1]
        torch.testing.assert_close(frames[:, i], pk_frames[link].get_matrix(), atol=2e-6, rtol=0)


@pytest.mark.parametrize("source, end", [(PANDA, "panda_link8"), (UR5, "tool0"), (TOY, "tip")])
@pytest.mark.parametrize("kernel", ["matrix", "column"])
def test_joint_axes_give_pk_jacobian(source, end, kernel):
    """Columns [k × (p_e − o); k] (revolute) / [k; 0] (prismatic) from joint_axes_origins vs pk.jacobian."""
    chain = _force(from_urdf(source, end, dtype=F64), kernel)
    q = chain.random_configuration((6,), generator=torch.Generator().manual_seed(1))
    axes, origins, T = chain.joint_axes_origins(q)
    rev = chain.revolute_mask.bool()[:, None]
    lin = torch.where(rev, torch.linalg.cross(axes, T[:, None, :3, 3] - origins, dim=-1), axes)
    ang = torch.where(rev, axes, torch.zeros_like(axes))
    J = torch.cat((lin, ang), dim=-1).transpose(-1, -2)
    torch.testing.assert_close(J, _pk_chain(source, end, F64).jacobian(q), atol=2e-6, rtol=0)
    torch.testing.assert_close(torch.linalg.norm(axes, dim=-1), torch.ones(6, chain.n_joints, dtype=F64))


def test_panda_urdf_equals_dh_model():
    chain, dh = from_urdf(PANDA, "panda_link8", dtype=F64), load("panda", dtype=F64)
    q = dh.random_configuration((50,), generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(chain.forward_kinematics(q), dh.forward_kinematics(q), atol=1e-12, rtol=0)
    # modified DH: link frames coincide too
    torch.testing.assert_close(chain.forward_kinematics(q, all_frames=True),
                               dh.forward_kinematics(q, all_frames=True), atol=1e-12, rtol=0)
    assert torch.equal(chain.q_limits, dh.q_limits)
    assert chain.joint_names[0] == "panda_joint1" and chain.name == "panda"


def test_ur5_urdf_equals_dh_model_up_to_base_rotation():
    """ROS "base_link" is the DH base frame rotated by π about z: T_urdf = Rz(π) T_dh (documented)."""
    chain, dh = from_urdf(UR5, "tool0", dtype=F64), load("ur5", dtype=F64)
    q = dh.random_configuration((50,), generator=torch.Generator().manual_seed(3))
    T, T_dh = chain.forward_kinematics(q), dh.forward_kinematics(q)
    torch.testing.assert_close(T, RZ_PI @ T_dh, atol=1e-12, rtol=0)
    axes, origins, _ = chain.joint_axes_origins(q)
    axes_dh, origins_dh, _ = dh.joint_axes_origins(q)
    torch.testing.assert_close(axes, axes_dh @ RZ_PI[:3, :3].T, atol=1e-12, rtol=0)
    # origins differ along the axes (URDF joint frames are not the DH ones); the lines coincide
    d = (origins - origins_dh @ RZ_PI[:3, :3].T)
    torch.testing.assert_close(torch.linalg.cross(d, axes, dim=-1), torch.zeros_like(d), atol=1e-12, rtol=0)


@pytest.mark.parametrize("shape", [(), (1,), (3, 7), (40,)])
def test_batch_shapes_kernels_and_gradients(shape):
    chain = from_urdf(TOY, "tip", dtype=F64)
    q = torch.rand(*shape, 4, dtype=F64)
    outs = []
    for kernel in ("matrix", "column"):
        _force(chain, kernel)
        outs.append((chain.forward_kinematics(q), chain.forward_kinematics(q, all_frames=True),
                     *chain.joint_axes_origins(q)))
        assert outs[-1][0].shape == (*shape, 4, 4) and outs[-1][1].shape == (*shape, 5, 4, 4)
    for a, b in zip(*outs):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0)
    qg = torch.rand(3, 4, dtype=F64, requires_grad=True)
    for kernel in ("matrix", "column"):
        _force(chain, kernel)
        assert torch.autograd.gradcheck(lambda x: chain.forward_kinematics(x, all_frames=True), (qg,))


def test_limits_types_and_module_behaviour():
    chain = from_urdf(TOY, "tip")
    assert isinstance(chain, URDFChain) and chain.joint_types == "RPRR"
    assert chain.joint_names == ["j1", "j2", "j3", "j4"]
    inf = math.inf  # the continuous joint j3 has no limit; it is sampled and seeded over ±π
    torch.testing.assert_close(chain.q_limits, torch.tensor([[-2, 2], [-0.1, 0.4], [-inf, inf],
                                                             [-3, 1]], dtype=torch.float32))
    torch.testing.assert_close(torch.stack(chain.lower_upper(), -1)[2], torch.tensor([-math.pi, math.pi]))
    assert bool(chain.within_limits(torch.tensor([0.0, 0.0, 9.0, 0.0])))
    c64 = chain.copy().double()
    assert c64.dtype == F64 and c64.forward_kinematics(torch.zeros(4, dtype=F64)).dtype == F64
    # learnable geometry: every origin on the path (fixed joints too), every moving axis, base and tool
    names = {k: tuple(p.shape) for k, p in chain.named_parameters()}
    assert names == {"origin_xyz": (6, 3), "origin_rpy": (6, 3), "axis": (4, 3), "base_delta": (6,),
                     "tool_delta": (6,)}
    q = torch.zeros(4)
    torch.testing.assert_close(chain.to(torch.float32).forward_kinematics(q), chain.forward_kinematics(q))
    sub = from_urdf(TOY, "l3", root_link="l1")  # a sub-chain
    assert sub.joint_types == "PR"
    text_chain = from_urdf(PANDA.read_text(), "panda_link8")
    assert text_chain.n_joints == 7


def test_urdf_errors():
    with pytest.raises(ModelError, match="end link 'nope'.*panda_link8"):
        from_urdf(PANDA, "nope")
    with pytest.raises(ModelError, match="no such URDF file"):
        from_urdf("/no/such/file.urdf", "x")
    with pytest.raises(ModelError, match="no moving joint"):
        from_urdf(TOY, "world")
    with pytest.raises(ModelError, match="not an ancestor"):
        from_urdf(TOY, "tip", root_link="side")
    floating = TOY.replace('name="j3" type="continuous"', 'name="j3" type="floating"')
    chain = from_urdf(floating, "tip")  # a floating joint on the path is a free joint (nq 7, nv 6)
    assert (chain.nq, chain.nv) == (chain.n_joints, chain.n_joints - 1) == (10, 9)
    with pytest.raises(ModelError, match="j4"):
        from_urdf(TOY.replace('<axis xyz="1 2 2"/>', '<axis xyz="0 0 0"/>'), "tip")
