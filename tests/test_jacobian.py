"""Geometric and analytical Jacobians and J̇q̇ (diffkin.jacobian, §3.1–3.7).

References: autograd / forward-mode AD through FK, central finite differences, the textbook's closed forms
(3.35), (3.37)–(3.38), Stanford §3.2.3, Robotics Toolbox's ``jacob0`` and pytorch-kinematics's ``jacobian``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.func import functional_call, jacrev, jvp

from diffkin.errors import ConventionError, RepresentationSingularityError, ShapeError
from diffkin.jacobian import (
    AnalyticalJacobian,
    analytical_jacobian,
    analytical_to_geometric,
    analytical_transform,
    forward_kinematics_and_jacobian,
    geometric_jacobian,
    geometric_to_analytical,
    jacobian_dot_qdot,
)
from diffkin.kernels import native
from diffkin.kernels.jacobian import jacobian_from_axes
from diffkin.rotations import euler_rate_matrix, matrix_to_euler, rotvec_to_matrix, vee
from tests.helpers import anthropomorphic, panda, planar3, random_chain, stanford

F64 = torch.float64
PI = math.pi
PANDA_URDF = Path(__file__).resolve().parents[1] / "diffkin" / "models" / "data" / "panda.urdf"


# ----------------------------------------------------------------------------------- references
def fd_jacobian(chain, q: torch.Tensor, h: float = 1e-6) -> torch.Tensor:
    """Central differences: linear part from p_e, angular part from vee(Ṙ Rᵀ)."""
    cols = []
    R = chain.forward_kinematics(q)[:3, :3]
    for i in range(q.shape[-1]):
        e = torch.zeros_like(q)
        e[i] = h
        Tp, Tm = chain.forward_kinematics(q + e), chain.forward_kinematics(q - e)
        dp = (Tp[:3, 3] - Tm[:3, 3]) / (2 * h)
        w = vee((Tp[:3, :3] - Tm[:3, :3]) / (2 * h) @ R.T)
        cols.append(torch.cat((dp, w)))
    return torch.stack(cols, dim=-1)


@pytest.mark.parametrize("convention", ["standard", "modified"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_geometric_jacobian_vs_autograd_and_finite_differences(convention, seed):
    chain = random_chain(seed, convention)
    q = chain.random_configuration((), generator=torch.Generator().manual_seed(seed + 10))
    with torch.no_grad():
        J = geometric_jacobian(chain, q)
        J_fd = fd_jacobian(chain, q)
    J_pos = jacrev(lambda x: chain.forward_kinematics(x)[:3, 3])(q)  # autograd through FK
    torch.testing.assert_close(J[:3], J_pos.detach(), atol=1e-12, rtol=0)
    torch.testing.assert_close(J, J_fd, atol=1e-8, rtol=0)
    # prismatic columns have no angular part
    prismatic = torch.tensor([c == "P" for c in chain.joint_types])
    assert torch.all(J[3:, prismatic] == 0)


@pytest.mark.parametrize("convention", ["standard", "modified"])
def test_geometric_jacobian_vs_robotics_toolbox(convention):
    rtb = pytest.importorskip("roboticstoolbox")
    SE3 = pytest.importorskip("spatialmath").SE3
    chain = random_chain(7, convention)
    a, alpha, d, theta = (p.detach().numpy() for p in (chain.a, chain.alpha, chain.d, chain.theta))
    rev_cls = rtb.RevoluteDH if convention == "standard" else rtb.RevoluteMDH
    pri_cls = rtb.PrismaticDH if convention == "standard" else rtb.PrismaticMDH
    links = [
        rev_cls(a=a[i], alpha=alpha[i], d=d[i], offset=theta[i])
        if c == "R"
        else pri_cls(a=a[i], alpha=alpha[i], theta=theta[i], offset=d[i])
        for i, c in enumerate(chain.joint_types)
    ]
    base, tool = SE3(chain.base.numpy(), check=False), SE3(chain.tool.numpy(), check=False)
    robot = rtb.DHRobot(links, base=base, tool=tool)
    qs = chain.random_configuration((5,), generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        J = geometric_jacobian(chain, qs)
    for k in range(5):
        np.testing.assert_allclose(J[k].numpy(), robot.jacob0(qs[k].numpy()), atol=1e-12)


def test_panda_vs_pytorch_kinematics():
    pk = pytest.importorskip("pytorch_kinematics")
    if not PANDA_URDF.exists():
        pytest.skip("panda.urdf not available")
    pk_chain = pk.build_serial_chain_from_urdf(PANDA_URDF.read_bytes(), "panda_link8").to(dtype=F64)
    chain = panda()
    q = chain.random_configuration((8,), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        T, J = forward_kinematics_and_jacobian(chain, q)
    J_pk = pk_chain.jacobian(q)
    T_pk = pk_chain.forward_kinematics(q).get_matrix()
    # the URDF stores its angles with 8 decimals
    torch.testing.assert_close(T, T_pk, atol=1e-7, rtol=0)
    torch.testing.assert_close(J, J_pk, atol=1e-7, rtol=0)


# ------------------------------------------------------------------------------------ closed forms
def test_three_link_planar_closed_form():  # (3.35)
    a1, a2, a3 = 0.5, 0.4, 0.3
    q = torch.tensor([0.3, -1.1, 0.7], dtype=F64)
    s = lambda *i: math.sin(sum(float(q[k]) for k in i))  # noqa: E731
    c = lambda *i: math.cos(sum(float(q[k]) for k in i))  # noqa: E731
    expected = torch.tensor([
        [-a1 * s(0) - a2 * s(0, 1) - a3 * s(0, 1, 2), -a2 * s(0, 1) - a3 * s(0, 1, 2), -a3 * s(0, 1, 2)],
        [a1 * c(0) + a2 * c(0, 1) + a3 * c(0, 1, 2), a2 * c(0, 1) + a3 * c(0, 1, 2), a3 * c(0, 1, 2)],
        [0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 1, 1],
    ], dtype=F64)  # fmt: skip
    torch.testing.assert_close(geometric_jacobian(planar3((a1, a2, a3)), q).detach(), expected)


def test_anthropomorphic_arm_closed_form():  # (3.37), whose upper block is (3.38)
    a2, a3 = 0.6, 0.45
    q = torch.tensor([0.4, 0.9, -0.5], dtype=F64)
    s1, c1 = math.sin(q[0]), math.cos(q[0])
    s2, c2 = math.sin(q[1]), math.cos(q[1])
    s23, c23 = math.sin(q[1] + q[2]), math.cos(q[1] + q[2])
    expected = torch.tensor([
        [-s1 * (a2 * c2 + a3 * c23), -c1 * (a2 * s2 + a3 * s23), -a3 * c1 * s23],
        [c1 * (a2 * c2 + a3 * c23), -s1 * (a2 * s2 + a3 * s23), -a3 * s1 * s23],
        [0, a2 * c2 + a3 * c23, a3 * c23],
        [0, s1, s1], [0, -c1, -c1], [1, 0, 0],
    ], dtype=F64)  # fmt: skip
    torch.testing.assert_close(geometric_jacobian(anthropomorphic(a2, a3), q).detach(), expected)


def test_stanford_closed_form():  # §3.2.3: z_i and p_i as printed, assembled by (3.30)
    d2, d6 = 0.2, 0.15
    q = torch.tensor([0.3, 0.8, 0.5, -0.6, 1.1, 0.4], dtype=F64)
    c1, s1, c2, s2 = math.cos(q[0]), math.sin(q[0]), math.cos(q[1]), math.sin(q[1])
    d3, c4, s4, c5, s5 = float(q[2]), math.cos(q[3]), math.sin(q[3]), math.cos(q[4]), math.sin(q[4])
    v = lambda *x: torch.tensor(x, dtype=F64)  # noqa: E731
    z0, z1, z2 = v(0, 0, 1), v(-s1, c1, 0), v(c1 * s2, s1 * s2, c2)
    z4 = v(-c1 * c2 * s4 - s1 * c4, -s1 * c2 * s4 + c1 * c4, s2 * s4)
    z5 = v(c1 * (c2 * c4 * s5 + s2 * c5) - s1 * s4 * s5, s1 * (c2 * c4 * s5 + s2 * c5) + c1 * s4 * s5,
           -s2 * c4 * s5 + c2 * c5)  # fmt: skip
    p0 = v(0, 0, 0)
    p3 = v(c1 * s2 * d3 - s1 * d2, s1 * s2 * d3 + c1 * d2, c2 * d3)
    p6 = p3 + d6 * z5  # (2.68)
    zero = torch.zeros(3, dtype=F64)
    cols = [
        torch.cat((torch.linalg.cross(z0, p6 - p0), z0)),
        torch.cat((torch.linalg.cross(z1, p6 - p0), z1)),
        torch.cat((z2, zero)),
        torch.cat((torch.linalg.cross(z2, p6 - p3), z2)),  # z3 = z2
        torch.cat((torch.linalg.cross(z4, p6 - p3), z4)),
        torch.cat((torch.linalg.cross(z5, p6 - p3), z5)),
    ]
    T, J = forward_kinematics_and_jacobian(stanford(d2, d6), q)
    torch.testing.assert_close(T[:3, 3].detach(), p6)
    torch.testing.assert_close(J.detach(), torch.stack(cols, dim=-1))


# ---------------------------------------------------------------------------------- frame and point
def test_point_option_matches_autograd_of_that_point():
    chain = random_chain(4, "standard")
    q = chain.random_configuration((), generator=torch.Generator().manual_seed(1))
    offset = torch.tensor([0.1, -0.2, 0.3], dtype=F64)  # in the EE frame

    def point(x):
        T = chain.forward_kinematics(x)
        return T[:3, :3] @ offset + T[:3, 3]

    J = geometric_jacobian(chain, q, point=offset).detach()
    torch.testing.assert_close(J[:3], jacrev(point)(q).detach())
    torch.testing.assert_close(J[3:], geometric_jacobian(chain, q)[3:].detach())
    p_base = point(q).detach()
    torch.testing.assert_close(geometric_jacobian(chain, q, point=p_base, point_frame="base").detach(), J)


def test_frame_option():
    chain = random_chain(5, "modified")
    q = chain.random_configuration((3,), generator=torch.Generator().manual_seed(2))
    T, J = forward_kinematics_and_jacobian(chain, q)
    R = T[..., :3, :3]
    J_ee = geometric_jacobian(chain, q, frame="ee")
    torch.testing.assert_close(J_ee[..., :3, :], R.mT @ J[..., :3, :])
    torch.testing.assert_close(J_ee[..., 3:, :], R.mT @ J[..., 3:, :])
    torch.testing.assert_close(geometric_jacobian(chain, q, frame=T), J_ee)  # (..., 4, 4) accepted
    Ru = rotvec_to_matrix(torch.tensor([0.3, -0.2, 0.9], dtype=F64))
    J_u = geometric_jacobian(chain, q, frame=Ru)
    torch.testing.assert_close(J_u[..., 3:, :], Ru.T @ J[..., 3:, :])
    with pytest.raises(ConventionError):
        geometric_jacobian(chain, q, frame="tool")


# ------------------------------------------------------------------------ batching, dtype, grads
@pytest.mark.parametrize("batch", [(), (4,), (2, 3)])
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_batch_shapes_and_dtypes(batch, dtype):
    chain = random_chain(8, "standard").to(dtype)
    q = chain.random_configuration(batch, generator=torch.Generator().manual_seed(0))
    T, J = chain.forward_kinematics_and_jacobian(q)
    assert J.shape == (*batch, 6, 6) and T.shape == (*batch, 4, 4)
    assert J.dtype == dtype and J.is_contiguous()
    jd = jacobian_dot_qdot(chain, q, q)
    assert jd.shape == (*batch, 6) and jd.dtype == dtype
    flat_q = q.reshape(-1, 6)
    for k in range(flat_q.shape[0]):
        torch.testing.assert_close(J.reshape(-1, 6, 6)[k], chain.geometric_jacobian(flat_q[k]))
    torch.testing.assert_close(T, chain.forward_kinematics(q))


@pytest.mark.parametrize("chain", [random_chain(14, "standard"), random_chain(15, "modified"), panda()])
def test_large_batch_kernel_matches_small_batch_kernel(chain):
    # batches above 64 configurations take the elementwise-row kernel, smaller ones the few-ops kernel
    q = chain.random_configuration((2, 60), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        J = geometric_jacobian(chain, q)
        for k in range(2):
            torch.testing.assert_close(J[k], geometric_jacobian(chain, q[k]), atol=1e-12, rtol=0)


@pytest.mark.parametrize("batch", [(100,), (10, 12)])
def test_batch_last_kernel_layout(batch):
    # a chain may hand out axes/origins as (..., n, 3) views of batch-last memory (3, n, ...): same J
    chain = random_chain(16, "standard")
    q = chain.random_configuration(batch, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        axes, origins, T = chain.joint_axes_origins(q)
        nb = len(batch)
        perm = (nb + 1, nb, *range(nb))
        inv = (*range(2, 2 + nb), 1, 0)
        axes_bl = axes.permute(*perm).contiguous().permute(*inv)
        origins_bl = origins.permute(*perm).contiguous().permute(*inv)
        assert axes_bl.stride(-1) != 1 and torch.equal(axes_bl, axes)
        args = (T[..., :3, 3], chain.revolute_mask, False)
        J = jacobian_from_axes(axes_bl, origins_bl, *args)
        torch.testing.assert_close(J, jacobian_from_axes(axes, origins, *args), atol=0, rtol=0)
        with native.disabled():  # the torch kernels: the same arithmetic, bit for bit
            torch.testing.assert_close(J, geometric_jacobian(chain, q), atol=0, rtol=0)
        torch.testing.assert_close(J, geometric_jacobian(chain, q), atol=1e-14, rtol=0)  # the fused C pass
        assert J.is_contiguous() and J.shape == (*batch, 6, 6)


def test_gradcheck_wrt_q_and_dh_parameters():
    chain = random_chain(9, "standard", types="RPRR")
    q = chain.random_configuration((2,), generator=torch.Generator().manual_seed(0)).requires_grad_()
    names = ("a", "alpha", "d", "theta")
    params = tuple(getattr(chain, k).detach().clone().requires_grad_() for k in names)

    class Wrap(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.chain = chain

        def forward(self, x):
            return geometric_jacobian(self.chain, x, point=torch.tensor([0.1, 0.0, 0.2], dtype=F64))

    wrap = Wrap()

    def f(x, *p):
        return functional_call(wrap, {f"chain.{k}": v for k, v in zip(names, p)}, (x,))

    assert torch.autograd.gradcheck(f, (q, *params))
    qd = torch.randn(2, 4, dtype=F64, generator=torch.Generator().manual_seed(1)).requires_grad_()
    assert torch.autograd.gradcheck(lambda x, v: jacobian_dot_qdot(chain, x, v), (q, qd))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    chain = random_chain(10, "modified").to(torch.float32)
    q = chain.random_configuration((64,))
    T, J = forward_kinematics_and_jacobian(chain, q)
    chain_gpu = chain.to("cuda")
    T_g, J_g = forward_kinematics_and_jacobian(chain_gpu, q.cuda())
    assert J_g.device.type == "cuda"
    torch.testing.assert_close(J_g.cpu(), J, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(jacobian_dot_qdot(chain_gpu, q.cuda(), q.cuda()).cpu(),
                               jacobian_dot_qdot(chain.cpu(), q, q), atol=1e-4, rtol=1e-4)  # fmt: skip


def test_bad_input():
    chain = random_chain(0, "standard")
    with pytest.raises(ShapeError):
        geometric_jacobian(chain, torch.zeros(5, dtype=F64))
    with pytest.raises(ShapeError):
        geometric_jacobian(chain, torch.zeros(6, dtype=F64), point=torch.zeros(2, dtype=F64))


# ------------------------------------------------------------------------------------------ J̇ q̇
@pytest.mark.parametrize("convention", ["standard", "modified"])
def test_jacobian_dot_qdot_vs_forward_mode_and_finite_differences(convention):
    chain = random_chain(11, convention)
    g = torch.Generator().manual_seed(4)
    q = chain.random_configuration((3,), generator=g)
    qd = torch.randn(3, 6, generator=g, dtype=F64)
    with torch.no_grad():
        jd = jacobian_dot_qdot(chain, q, qd)
        _, J_dot = jvp(lambda x: geometric_jacobian(chain, x), (q,), (qd,))
        h = 1e-6
        J_fd = (geometric_jacobian(chain, q + h * qd) - geometric_jacobian(chain, q - h * qd)) / (2 * h)
    torch.testing.assert_close(jd, (J_dot @ qd.unsqueeze(-1)).squeeze(-1), atol=1e-12, rtol=0)
    torch.testing.assert_close(jd, (J_fd @ qd.unsqueeze(-1)).squeeze(-1), atol=1e-7, rtol=0)


def test_jacobian_dot_qdot_is_ee_acceleration():
    # with q̈ = 0, the end-effector acceleration is J̇ q̇: second time-derivative of p_e along q(t) = q + t q̇
    chain = random_chain(12, "standard", types="RRPR")
    q = torch.tensor([0.3, -0.4, 0.2, 1.0], dtype=F64)
    qd = torch.tensor([0.5, 0.7, -0.3, 0.2], dtype=F64)
    h = 1e-4
    p = lambda t: chain.forward_kinematics(q + t * qd)[:3, 3]  # noqa: E731
    acc = (p(h) - 2 * p(0.0) + p(-h)) / h**2
    torch.testing.assert_close(jacobian_dot_qdot(chain, q, qd)[:3].detach(), acc.detach(), atol=1e-6, rtol=0)


# -------------------------------------------------------------------------------- analytical (3.66)
@pytest.mark.parametrize("representation", ["ZYZ", "RPY"])
def test_analytical_jacobian(representation):
    chain = random_chain(13, "standard")
    q = chain.random_configuration((4,), generator=torch.Generator().manual_seed(5))
    T, J = forward_kinematics_and_jacobian(chain, q)
    J_A = analytical_jacobian(chain, q, representation=representation)
    phi = matrix_to_euler(T[..., :3, :3], representation)
    torch.testing.assert_close(analytical_transform(phi, representation) @ J_A, J)  # J = T_A(φ) J_A
    torch.testing.assert_close(analytical_to_geometric(J_A, phi, representation), J)
    T_phi = euler_rate_matrix(phi, representation)
    torch.testing.assert_close(T_phi @ J_A[..., 3:, :], J[..., 3:, :])
    J_A2, singular = geometric_to_analytical(J, phi, representation)
    torch.testing.assert_close(J_A2, J_A)
    assert not singular.any()
    # (3.63): J_A = ∂[p_e; φ_e]/∂q, by autograd through FK and matrix_to_euler
    for k in range(4):
        def k_of_q(x):
            Tk = chain.forward_kinematics(x)
            return torch.cat((Tk[:3, 3], matrix_to_euler(Tk[:3, :3], representation)))

        torch.testing.assert_close(J_A[k].detach(), jacrev(k_of_q)(q[k]).detach())


def test_analytical_jacobian_representation_singularity():
    chain = planar3()
    q = torch.tensor([[0.3, 0.2, -0.1], [1.0, -0.5, 0.4]], dtype=F64, requires_grad=True)
    with pytest.raises(RepresentationSingularityError):  # ZYZ: ϑ = 0 for every planar pose
        analytical_jacobian(chain, q, "ZYZ")
    out = analytical_jacobian(chain, q, "ZYZ", singular="flag")
    assert isinstance(out, AnalyticalJacobian) and out.singular.all()
    assert torch.isfinite(out.J_A).all()
    out.J_A.sum().backward()
    assert torch.isfinite(q.grad).all()
    assert torch.isfinite(analytical_jacobian(chain, q, "ZYZ", singular="ignore")).all()
    # RPY is regular here and, as the book remarks after (3.66), J_A equals the non-null rows of J
    J_A = analytical_jacobian(chain, q, "RPY").detach()
    J = geometric_jacobian(chain, q).detach()
    torch.testing.assert_close(J_A[..., :3, :], J[..., :3, :])
    torch.testing.assert_close(J_A[..., 3, :], J[..., 5, :])  # φ̇ = ω_z
    assert torch.all(J_A[..., 4:, :].abs() < 1e-12)
    with pytest.raises(ConventionError):
        analytical_jacobian(chain, q, "RPY", singular="maybe")


@pytest.mark.parametrize("batch", [(100,), (7, 13)])
def test_sliced_large_batch_path_is_bit_identical(monkeypatch, batch):
    """Large CPU batches without autograd run in slices (_CHUNK); slicing must not change a single bit."""
    import diffkin.chain.evaluation as chain_module
    import diffkin.jacobian as jac
    from diffkin.models import from_urdf

    urdf = Path(__file__).resolve().parent.parent / "diffkin" / "models" / "data" / "ur5.urdf"
    chains = [random_chain(3, "standard", types="RPRRPR"), from_urdf(str(urdf), "tool0", dtype=F64)]
    for chain in chains:
        q = chain.random_configuration(batch, generator=torch.Generator().manual_seed(5))
        with torch.no_grad():
            monkeypatch.setattr(chain_module, "_CHUNK", 10**9)
            T_ref, J_ref = jac.forward_kinematics_and_jacobian(chain, q)
            monkeypatch.setattr(chain_module, "_CHUNK", 24)  # slices of 24 (and a remainder) per thread
            T, J = jac.forward_kinematics_and_jacobian(chain, q)
        assert torch.equal(T, T_ref) and torch.equal(J, J_ref)
        assert J.shape == (*batch, 6, chain.n_joints)


URDF_DATA = Path(__file__).resolve().parent / "data" / "urdf"


def _jdot_chain(kind: str, dtype):
    from diffkin.models import from_urdf

    if kind == "tiago_two_ends":  # a tree: two arms sharing the prismatic torso (K = 2)
        ends = ["arm_left_tool_link", "arm_right_tool_link"]
        return from_urdf(URDF_DATA / "tiago_dual.urdf", ends, dtype=dtype)
    if kind == "yumi_mimic":  # mimic followers (prismatic fingers), three end links
        ends = ["gripper_r_finger_r", "gripper_r_finger_l", "gripper_l_finger_l"]
        return from_urdf(URDF_DATA / "yumi.urdf", ends, dtype=dtype)
    return random_chain(21, "modified").to(dtype)  # a DH arm with prismatic joints, base and tool


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("kind", ["tiago_two_ends", "yumi_mimic", "dh"])
@pytest.mark.parametrize("batch", [(), (5,), (3, 13)])  # (3, 13): blocks of chain.small_batch, one padded
def test_jacobian_dot_qdot_on_trees_and_mimic_chains_vs_finite_differences(kind, dtype, batch):
    # J̇q̇ = (d/dt J(q + t q̇)) q̇ at t = 0, by central differences of the kernel Jacobian along q̇ (in float64)
    chain = _jdot_chain(kind, dtype)
    g = torch.Generator().manual_seed(5)
    q = chain.random_configuration(batch, generator=g)
    qd = torch.randn(*batch, chain.n_joints, generator=g, dtype=dtype)
    jd = jacobian_dot_qdot(chain, q, qd)
    K = () if chain.single_end else (chain.n_ends,)
    assert jd.shape == (*batch, *K, 6) and jd.dtype == dtype
    assert bool(torch.isfinite(jd).all())
    c64, q64, qd64 = chain.to(F64), q.to(F64), qd.to(F64)
    h = 1e-5
    with torch.no_grad():
        J_fd = (geometric_jacobian(c64, q64 + h * qd64) - geometric_jacobian(c64, q64 - h * qd64)) / (2 * h)
    qv = qd64 if chain.single_end else qd64.unsqueeze(-2)
    ref = (J_fd @ qv.unsqueeze(-1)).squeeze(-1)
    assert float(ref.abs().max()) > 1e-2  # the test can fail: J̇q̇ is not zero here
    atol = 1e-7 if dtype == F64 else 1e-4
    torch.testing.assert_close(jd.detach().to(F64), ref, atol=atol * max(1.0, float(ref.abs().max())), rtol=0)


def test_jacobian_dot_qdot_tree_gradcheck():
    chain = _jdot_chain("yumi_mimic", F64)
    g = torch.Generator().manual_seed(6)
    q = chain.random_configuration((2,), generator=g).requires_grad_()
    qd = torch.randn(2, chain.n_joints, generator=g, dtype=F64).requires_grad_()
    assert torch.autograd.gradcheck(lambda x, v: jacobian_dot_qdot(chain, x, v), (q, qd))
