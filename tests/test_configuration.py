"""The configuration-space layer (diffkin.kernels.configuration) and chains with ball, free and planar joints:
the joint-kind table, q ⊕ v and its inverse, the Jacobian on the manifold against finite differences,
gradcheck in float64, URDF floating bases against Pinocchio's free-flyer, per-row base poses, IK on the
manifold."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from diffkin import ik
from diffkin.errors import ShapeError
from diffkin.jacobian import geometric_jacobian
from diffkin.kernels.configuration import JOINT_KINDS, ConfigurationSpace
from diffkin.kernels.joints import origin_transform
from diffkin.models import from_urdf, load
from diffkin.rotations import quaternion_to_matrix, rotvec_to_matrix

DATA = Path(__file__).parent / "data"
G1 = DATA / "urdf" / "g1_29dof_rev_1_0.urdf"
G1_ENDS = ["left_ankle_roll_link", "right_ankle_roll_link", "left_wrist_yaw_link", "right_wrist_yaw_link"]
F64 = torch.float64

PLANAR = """<robot name="planar_base">
  <link name="world"/><link name="base"/><link name="arm"/><link name="tip"/>
  <joint name="slide_base" type="planar"><parent link="world"/><child link="base"/>
    <origin xyz="0.1 0.2 0.3" rpy="0.1 -0.2 0.3"/><axis xyz="0.2 0.1 1"/></joint>
  <joint name="shoulder" type="revolute"><parent link="base"/><child link="arm"/>
    <origin xyz="0 0 0.2"/><axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="tool" type="fixed"><parent link="arm"/><child link="tip"/><origin xyz="0.5 0 0"/></joint>
</robot>"""


def test_the_table():
    expected = {"revolute": (1, 1), "continuous": (1, 1), "prismatic": (1, 1), "planar": (3, 3),
                "ball": (4, 3), "free": (7, 6)}
    assert {k: (v.nq, v.nv) for k, v in JOINT_KINDS.items()} == expected
    space = ConfigurationSpace(["P", "P", "P", "S", "R", "S"])
    assert (space.nq, space.nv) == (12, 10) and not space.euclidean
    assert ConfigurationSpace(["R", "P"]).euclidean


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_integrate_difference_interpolate(dtype):
    space = ConfigurationSpace(["P", "S", "R", "S"])
    g = torch.Generator().manual_seed(0)
    lo, hi = -torch.ones(2, dtype=dtype), torch.ones(2, dtype=dtype)
    q = space.sample(lo, hi, (5, 2), generator=g)
    assert q.shape == (5, 2, 10)
    for iq in space.quaternion_index():
        torch.testing.assert_close(q[..., list(iq)].norm(dim=-1), torch.ones(5, 2, dtype=dtype))
    v = 0.8 * torch.randn(5, 2, space.nv, generator=g, dtype=dtype)  # rotations below π
    q1 = space.integrate(q, v)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(space.difference(q, q1), v, atol=tol, rtol=0)
    torch.testing.assert_close(space.integrate(q, torch.zeros_like(v)), q, atol=tol, rtol=0)
    torch.testing.assert_close(space.interpolate(q, q1, torch.tensor(0.0, dtype=dtype)), q, atol=tol, rtol=0)
    torch.testing.assert_close(space.interpolate(q, q1, 1.0), q1, atol=tol, rtol=0)
    # the quaternion update is right multiplication by exp(ω/2): R(q ⊕ ω) = R(q) Exp(ω), ω in the child frame
    R0, R1 = quaternion_to_matrix(q[..., 1:5]), quaternion_to_matrix(q1[..., 1:5])
    torch.testing.assert_close(R1, R0 @ rotvec_to_matrix(v[..., 1:4]), atol=10 * tol, rtol=0)
    # slerp halfway: the rotation half-way along the geodesic
    Rh = quaternion_to_matrix(space.interpolate(q, q1, 0.5)[..., 1:5])
    torch.testing.assert_close(Rh, R0 @ rotvec_to_matrix(0.5 * v[..., 1:4]), atol=10 * tol, rtol=0)


def test_tangent_map_is_the_derivative_of_integrate():
    space = ConfigurationSpace(["S", "R", "P", "S"])
    one = torch.ones(2, dtype=F64)
    q = space.sample(-one, one, (3,), torch.Generator().manual_seed(1))
    for qr in q:
        ref = torch.autograd.functional.jacobian(lambda v, qr=qr: space.integrate(qr, v),
                                                 torch.zeros(space.nv, dtype=F64))
        torch.testing.assert_close(space.tangent_map(qr), ref, atol=1e-12, rtol=0)


def test_no_nan_at_zero_rotation_and_gradcheck():
    space = ConfigurationSpace(["S", "P"])
    q = torch.tensor([1.0, 0, 0, 0, 0.3], dtype=F64, requires_grad=True)
    v = torch.zeros(4, dtype=F64, requires_grad=True)
    out = space.integrate(q, v).sum() + space.difference(q, q.detach()).sum()
    out.backward()
    assert bool(torch.isfinite(q.grad).all() and torch.isfinite(v.grad).all())
    q2 = torch.tensor([0.6, 0.2, -0.5, 0.3, 0.1], dtype=F64, requires_grad=True)
    v2 = torch.tensor([0.3, -0.2, 0.4, 0.1], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(space.integrate, (q2, v2))
    q3 = space.integrate(q2.detach(), torch.tensor([0.2, 0.1, 0.0, 0.4], dtype=F64)).requires_grad_(True)
    assert torch.autograd.gradcheck(space.difference, (q2, q3))


def _floating_g1():
    return from_urdf(G1, G1_ENDS, floating_base=True, dtype=F64)


def test_jacobian_on_the_manifold_matches_finite_differences():
    """Column i of J is the twist of the end links when q moves along q ⊕ t e_i (central differences)."""
    for chain in (_floating_g1(), from_urdf(PLANAR, "tip", dtype=F64)):
        q = chain.random_configuration(2, generator=torch.Generator().manual_seed(3))
        with torch.no_grad():
            T, J = chain.forward_kinematics_and_jacobian(q)
            h = 1e-6
            for i in range(chain.nv):
                e = torch.zeros(chain.nv, dtype=F64)
                e[i] = h
                Tp = chain.forward_kinematics(chain.integrate(q, e))
                Tm = chain.forward_kinematics(chain.integrate(q, -e))
                dp = (Tp[..., :3, 3] - Tm[..., :3, 3]) / (2 * h)
                W = (Tp[..., :3, :3] - Tm[..., :3, :3]) / (2 * h) @ T[..., :3, :3].transpose(-1, -2)
                dw = torch.stack((W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]), dim=-1)
                torch.testing.assert_close(J[..., :3, i], dp, atol=1e-7, rtol=0)
                torch.testing.assert_close(J[..., 3:, i], dw, atol=1e-7, rtol=0)


def test_fk_gradcheck_on_ball_and_free_joints():
    chain = from_urdf(G1, ["left_wrist_yaw_link"], floating_base=True, dtype=F64)
    chain.requires_grad_(False)
    q = chain.random_configuration((), generator=torch.Generator().manual_seed(4)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: chain.forward_kinematics(x), (q,))
    chain.requires_grad_(True)
    T = chain.forward_kinematics(q)
    T.sum().backward()
    assert bool(torch.isfinite(chain.origin_xyz.grad).all())


def test_floating_base_matches_pinocchio_free_flyer():
    pin = pytest.importorskip("pinocchio")
    model = pin.buildModelFromUrdf(str(G1), pin.JointModelFreeFlyer())
    data = model.createData()
    chain = _floating_g1()
    assert (chain.nq, chain.nv) == (model.nq, model.nv) == (36, 35)
    q = chain.random_configuration(6, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        T, J = chain.forward_kinematics_and_jacobian(q)
    idx_v = [model.joints[model.getJointId(n)].idx_v for n in chain.joint_names[1:]]
    for r in range(q.shape[0]):
        qp = np.zeros(model.nq)
        qp[:3] = q[r, :3].numpy()
        qp[3:7] = q[r, [4, 5, 6, 3]].numpy()  # Pinocchio's quaternion is (x, y, z, w)
        for i, name in enumerate(chain.joint_names[1:]):
            qp[model.joints[model.getJointId(name)].idx_q] = q[r, 7 + i].item()
        pin.forwardKinematics(model, data, qp)
        pin.updateFramePlacements(model, data)
        pin.computeJointJacobians(model, data, qp)
        Rb = data.oMi[1].rotation
        for k, end in enumerate(G1_ENDS):
            fid = model.getFrameId(end)
            np.testing.assert_allclose(T[r, k, :3, 3].numpy(), data.oMf[fid].translation, atol=1e-12)
            np.testing.assert_allclose(T[r, k, :3, :3].numpy(), data.oMf[fid].rotation, atol=1e-12)
            Jp = pin.getFrameJacobian(model, data, fid, pin.LOCAL_WORLD_ALIGNED)
            Jp[:, :3] = Jp[:, :3] @ Rb.T  # Pinocchio's free-flyer velocity is local; ours is world (MuJoCo's)
            np.testing.assert_allclose(J[r, k].numpy(), Jp[:, [0, 1, 2, 3, 4, 5, *idx_v]], atol=1e-12)


def test_planar_joint():
    chain = from_urdf(PLANAR, "tip", dtype=F64)
    assert (chain.nq, chain.nv, chain.joint_types) == (4, 4, "PPRR")
    assert chain.joint_kinds == ["planar", "revolute"]
    q = torch.tensor([0.3, -0.2, 0.7, 0.0], dtype=F64)
    with torch.no_grad():
        T = chain.forward_kinematics(q)
        T0 = chain.forward_kinematics(torch.zeros(4, dtype=F64))
    # the base moved in the plane normal to the axis: the displacement has no component along the axis
    frame = chain.forward_kinematics(torch.zeros(4, dtype=F64), all_frames=True)[1].detach()
    n = frame[:3, 2]  # origin · S at q = 0: its z axis is the joint's axis, the plane's normal
    axis = torch.tensor([0.2, 0.1, 1.0], dtype=F64)
    O = origin_transform(torch.tensor([0.1, 0.2, 0.3], dtype=F64), torch.tensor([0.1, -0.2, 0.3], dtype=F64))
    torch.testing.assert_close(n, O[:3, :3] @ (axis / axis.norm()))
    assert abs(float((T[:3, 3] - T0[:3, 3]) @ n)) > 0  # the rotation moves the arm's tip out of line
    moved = chain.forward_kinematics(torch.tensor([0.3, -0.2, 0.0, 0.0], dtype=F64)).detach()
    assert abs(float((moved[:3, 3] - T0[:3, 3]) @ n)) < 1e-12
    torch.testing.assert_close((moved[:3, 3] - T0[:3, 3]).norm(), torch.tensor(0.13 ** 0.5, dtype=F64))


def test_per_row_base_poses():
    chain = load("panda", dtype=F64)
    g = torch.Generator().manual_seed(6)
    q = chain.random_configuration(16, generator=g)
    with torch.no_grad():
        B = chain.forward_kinematics(chain.random_configuration(16, generator=g))  # 16 rigid poses
        T = chain.forward_kinematics(q, base=B)
        J = geometric_jacobian(chain, q, base=B)
        T0, J0 = chain.forward_kinematics_and_jacobian(q)
    torch.testing.assert_close(T, B @ T0)
    R = B[:, :3, :3]
    torch.testing.assert_close(J, torch.cat((R @ J0[:, :3], R @ J0[:, 3:]), dim=1))
    with pytest.raises(ShapeError):
        chain.forward_kinematics(q, base=torch.eye(3, dtype=F64))
    res = ik.solve(chain, T, base=B, seed=0)  # world targets of robots at 16 places
    assert bool(res.success.all())
    with torch.no_grad():
        reached = chain.forward_kinematics(res.q, base=B)
    assert float((reached[:, :3, 3] - T[:, :3, 3]).norm(dim=-1).max()) <= 1e-4


def test_whole_body_ik_on_the_floating_g1():
    chain = _floating_g1()
    q_true = chain.random_configuration(12, generator=torch.Generator().manual_seed(7))
    with torch.no_grad():
        T = chain.forward_kinematics(q_true)
    res = ik.solve(chain, T, seed=0)
    assert res.q.shape == (12, 36)
    with torch.no_grad():
        reached = chain.forward_kinematics(res.q)
    pos = (reached[..., :3, 3] - T[..., :3, 3]).norm(dim=-1).amax(-1)
    # the flag is never wrong: success iff every end link is within the tolerance
    assert bool((res.success == (pos <= 1e-4) & (res.orientation_error <= 1e-3)).all())
    assert float(res.success.float().mean()) >= 0.9
    torch.testing.assert_close(res.q[:, 3:7].norm(dim=-1), torch.ones(12, dtype=F64), atol=1e-12, rtol=0)
    assert bool(chain.within_limits(res.q[res.success]).all())


def test_implicit_gradient_through_a_floating_base_solve():
    """dq*/dT_target of ik.solve pulled back through the quaternion's tangent map: the implied change of
    the end pose matches the target's change (J dv = dx at a square/redundant solution)."""
    chain = from_urdf(G1, ["left_wrist_yaw_link"], floating_base=True, dtype=F64)
    chain.requires_grad_(False)
    q_true = chain.random_configuration((), generator=torch.Generator().manual_seed(8))
    with torch.no_grad():
        T = chain.forward_kinematics(q_true)
    Tg = T.clone().requires_grad_(True)
    res = ik.solve(chain, Tg, q0=q_true, seed=0)
    assert bool(res.success)
    w = torch.randn(chain.nq, dtype=F64, generator=torch.Generator().manual_seed(9))
    (grad,) = torch.autograd.grad((res.q * w).sum(), Tg)
    assert bool(torch.isfinite(grad).all()) and float(grad.abs().sum()) > 0


@pytest.mark.parametrize("optimizer", ["gauss_newton",
                                       pytest.param("lbfgs", marks=pytest.mark.extended)])  # L-BFGS: 20 s
def test_optimize_moves_on_the_manifold(optimizer):
    chain = _floating_g1()
    chain.requires_grad_(False)
    g = torch.Generator().manual_seed(10)
    q_true = chain.random_configuration(4, generator=g)
    with torch.no_grad():
        T = chain.forward_kinematics(q_true)
    q_start = chain.integrate(q_true, 0.05 * torch.randn(4, chain.nv, generator=g, dtype=F64))
    res = ik.optimize(chain, T, q_start, optimizer=optimizer)
    assert bool(res.success.all())
    torch.testing.assert_close(res.q[:, 3:7].norm(dim=-1), torch.ones(4, dtype=F64), atol=1e-12, rtol=0)
    if optimizer == "lbfgs":  # a base-height cost (a callable, not least squares) pulls the pelvis to 0.8 m
        height = ik.optimize(chain, T, q_start, optimizer=optimizer,
                             costs=[ik.PoseCost(), lambda q, _: 10.0 * (q[..., 2] - 0.8) ** 2])
        moved = (height.q[:, 2] - 0.8).abs() - (res.q[:, 2] - 0.8).abs()
        assert bool((moved <= 1e-9).all()) and float(moved.min()) < 0
    Tg = T.clone().requires_grad_(True)
    out = ik.optimize(chain, Tg, q_start, optimizer=optimizer)
    (grad,) = torch.autograd.grad(out.q.sum(), Tg)
    assert bool(torch.isfinite(grad).all()) and float(grad.abs().sum()) > 0


def test_clik_integrates_on_the_manifold():
    chain = from_urdf(G1, "left_wrist_yaw_link", floating_base=True, dtype=F64)
    chain.requires_grad_(False)
    g = torch.Generator().manual_seed(11)
    q = chain.random_configuration(3, generator=g)
    with torch.no_grad():
        T = chain.forward_kinematics(q)
    q0 = chain.integrate(q, 0.1 * torch.randn(3, chain.nv, generator=g, dtype=F64))
    res = ik.clik(chain, (T.unsqueeze(-3), None), q0, dt=0.01, steps=100, algorithm="dls")
    assert res.q.shape == (3, 101, chain.nq) and res.qdot.shape == (3, 101, chain.nv)
    assert float(res.position_error[:, -1].max()) < 1e-6 < float(res.position_error[:, 0].min())
    torch.testing.assert_close(res.q[..., 3:7].norm(dim=-1), torch.ones(3, 101, dtype=F64), atol=1e-12,
                               rtol=0)


def test_velocity_step_on_a_floating_base_matches_bvls():
    """Joint position bounds on the scalar coordinates, none on the base's rotation: scipy's BVLS on the
    stacked system [J; √λ I] v = [twist; 0] within the per-column bounds."""
    from scipy.optimize import lsq_linear

    chain = from_urdf(G1, ["left_wrist_yaw_link", "right_ankle_roll_link"], floating_base=True, dtype=F64)
    chain.requires_grad_(False)
    g = torch.Generator().manual_seed(14)
    q = chain.random_configuration(40, generator=g)
    twist = torch.randn(40, 2, 6, generator=g, dtype=F64)
    dt, vmax, lam = 0.05, 1.5, 1e-3
    v = ik.velocity_step(chain, q, twist, dt, damping=lam, velocity_limit=vmax)
    assert v.shape == (40, chain.nv)
    J = chain.forward_kinematics_and_jacobian(q)[1].reshape(40, 12, chain.nv)
    space = chain.configuration_space
    sq, sv = list(space.scalar_index("q")), list(space.scalar_index("v"))
    lim = chain.q_limits
    active = 0
    for i in range(40):
        lo, hi = np.full(chain.nv, -vmax), np.full(chain.nv, vmax)
        lo[sv] = np.maximum(-vmax, ((lim[sq, 0] - q[i, sq]) / dt).numpy())
        hi[sv] = np.minimum(vmax, ((lim[sq, 1] - q[i, sq]) / dt).numpy())
        A = np.vstack((J[i].numpy(), lam ** 0.5 * np.eye(chain.nv)))
        b = np.concatenate((twist[i].reshape(-1).numpy(), np.zeros(chain.nv)))
        ref = lsq_linear(A, b, bounds=(lo, hi), method="bvls", tol=1e-14).x
        np.testing.assert_allclose(v[i].numpy(), ref, atol=1e-8)
        active += int(((np.abs(ref - lo) < 1e-12) | (np.abs(ref - hi) < 1e-12)).sum())
    assert active > 40  # bounds shape the answer
    q1 = chain.integrate(q, v * dt)  # the step stays within the joint limits, the quaternion unit
    assert bool(chain.within_limits(q1, tol=1e-12).all())
    torch.testing.assert_close(q1[:, 3:7].norm(dim=-1), torch.ones(40, dtype=F64), atol=1e-12, rtol=0)


def test_self_distances_of_a_floating_base_do_not_depend_on_where_it_is():
    """The collision layer places links through the chain's frames, multi-frame joints included: a floating
    G1's self-distances equal the fixed-base G1's at the same joint angles."""
    import warnings

    from diffkin.collision import RobotCollision

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # meshes absent: skipped with a warning
        floating, fixed = _floating_g1(), from_urdf(G1, G1_ENDS, dtype=F64)
        col_floating, col_fixed = RobotCollision.from_urdf(G1, floating), RobotCollision.from_urdf(G1, fixed)
    assert col_floating.pairs == col_fixed.pairs and len(col_floating.pairs) > 0
    q = floating.random_configuration(5, generator=torch.Generator().manual_seed(15))
    with torch.no_grad():
        torch.testing.assert_close(col_floating.self_distances(q), col_fixed.self_distances(q[:, 7:]),
                                   atol=1e-12, rtol=0)


def test_a_chain_ending_in_a_ball_joint_matches_mujoco():
    """q has more entries than frames (hinge, hinge, ball: 6 coordinates, 3 frames): the coupling of q to the
    frames is not the identity even where every frame's first entry is in order."""
    mujoco = pytest.importorskip("mujoco")
    from diffkin.models import from_mjcf

    xml = """<mujoco><worldbody><body name="a"><joint name="j1" axis="0 0 1"/><geom size="0.1"/>
      <body name="b" pos="0.3 0 0"><joint name="j2" axis="0 1 0"/><geom size="0.1"/>
      <body name="c" pos="0.3 0 0.1"><joint name="ball" type="ball"/><geom size="0.1"/>
      <site name="tip" pos="0.2 0.1 0"/></body></body></body></worldbody></mujoco>"""
    chain = from_mjcf(xml, "tip", dtype=F64)
    assert (chain.nq, chain.nv) == (6, 5)
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    q = chain.random_configuration(4, generator=torch.Generator().manual_seed(18))
    with torch.no_grad():
        T, J = chain.forward_kinematics_and_jacobian(q)
    for r in range(4):
        d.qpos[:] = chain.to_qpos(q[r]).numpy()
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        mujoco.mj_jacSite(m, d, jp, jr, 0)
        np.testing.assert_allclose(T[r, :3, 3].numpy(), d.site_xpos[0], atol=1e-12)
        np.testing.assert_allclose(J[r].numpy(), np.vstack((jp, jr)), atol=1e-12)
