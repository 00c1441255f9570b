"""ik.clik reads the task and limit objects (issue 35): the shorthand arguments and the object form give
the same trajectory; ConfigurationLimit / VelocityLimit hold along it; the costs weight the laws as the
weighted damped least squares (3.59) computed by numpy."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from diffkin import ik, models
from diffkin.errors import ConventionError

F64 = torch.float64
DT = 0.01
Q0 = torch.tensor([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8], dtype=F64)


@pytest.fixture(scope="module")
def panda():
    return models.load("panda", dtype=F64).requires_grad_(False)


def _track(chain, S: int):
    """A pose trajectory (S, 4, 4) moving on a circle and turning about z, and its twist (S, 6)."""
    T0 = chain.forward_kinematics(Q0)
    t = torch.arange(S, dtype=F64) * DT
    x = T0.expand(S, 4, 4).clone()
    x[:, :3, 3] += torch.stack([0.2 * torch.sin(t), 0.0 * t, 0.2 * (1 - torch.cos(t))], -1)
    c, s = torch.cos(0.5 * t), torch.sin(0.5 * t)
    Rz = torch.zeros(S, 3, 3, dtype=F64)
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
    x[:, :3, :3] = Rz @ T0[:3, :3]
    v = torch.cat((torch.stack([0.2 * torch.cos(t), 0 * t, 0.2 * torch.sin(t)], -1),
                   torch.tensor([0.0, 0.0, 0.5], dtype=F64).expand(S, 3)), -1)
    return x, v


@pytest.mark.parametrize("algorithm", ["dls", "transpose", "second_order"])
def test_shorthand_and_objects_give_the_same_trajectory(panda, algorithm):
    x, v = _track(panda, 15)
    kw = dict(algorithm=algorithm, damping=1e-4)
    a = ik.clik(panda, (x, v), Q0, DT, **kw)
    b = ik.clik(panda, q0=Q0, dt=DT, tasks=[ik.FrameTask(0, target=x, gain=0.5), ik.FrameTask(0, twist=v)],
                **kw)
    torch.testing.assert_close(b.q, a.q, atol=1e-12, rtol=0)


def test_rows_are_the_nonzero_costs(panda):
    x, v = _track(panda, 30)
    kw = dict(algorithm="pseudo_inverse")
    # rows: a zero cost drops the row; position only: orientation_cost 0
    a = ik.clik(panda, (x, v), Q0, DT, rows=(0, 1, 2, 5), K=30.0, **kw)
    b = ik.clik(panda, None, Q0, DT, K=30.0, tasks=[
        ik.FrameTask(0, target=x, orientation_cost=[0.0, 0.0, 1.0]), ik.FrameTask(0, twist=v)], **kw)
    torch.testing.assert_close(b.q, a.q, atol=1e-12, rtol=0)
    a = ik.clik(panda, (x[:, :3, 3], v), Q0, DT, orientation=None, **kw)
    b = ik.clik(panda, q0=Q0, dt=DT, tasks=[ik.FrameTask(0, target=x, orientation_cost=0.0, gain=0.5),
                                            ik.FrameTask(0, twist=v)], **kw)
    torch.testing.assert_close(b.q, a.q, atol=1e-12, rtol=0)


def test_posture_task_is_the_joint_limit_objective(panda):
    """nullspace="joint_limits" (3.57) with gain k₀ = PostureTask(middle, cost 1/(√n range), gain k₀Δt)."""
    x, v = _track(panda, 40)
    lo, hi = panda.q_limits[:, 0], panda.q_limits[:, 1]
    k0 = 200.0
    a = ik.clik(panda, (x, v), Q0, DT, nullspace="joint_limits", k0=k0)
    posture = ik.PostureTask(0.5 * (lo + hi), cost=1.0 / ((hi - lo) * 7**0.5), gain=k0 * DT)
    b = ik.clik(panda, q0=Q0, dt=DT, tasks=[ik.FrameTask(0, target=x, gain=0.5), ik.FrameTask(0, twist=v),
                                            posture])
    torch.testing.assert_close(b.q, a.q, atol=1e-10, rtol=0)
    c = ik.clik(panda, (x, v), Q0, DT)  # the posture acts: a different null-space motion
    assert float((c.q - a.q).abs().max()) > 1e-3


def test_limits_hold_and_limits_true_is_the_objects(panda):
    """A target running away along x stretches the elbow (joint 4) into its upper limit: the plain DLS law
    passes it; with ConfigurationLimit(γ, d) and VelocityLimit the run stays within [q_m + d, q_M − d] and
    |q̇| ≤ q̇_max, reaching both; limits=True, qdot_max=v is [ConfigurationLimit(gain=1), VelocityLimit(v)]."""
    q1 = torch.tensor([0.0, 0.3, 0.0, -0.5, 0.0, 1.0, 0.8], dtype=F64)
    S = 80
    x = panda.forward_kinematics(q1).expand(S, 4, 4).clone()
    x[:, 0, 3] += 0.5 * torch.arange(S, dtype=F64) * DT
    v = torch.zeros(S, 6, dtype=F64)
    v[:, 0] = 0.5
    kw = dict(algorithm="dls", orientation=None, damping=1e-4)
    a = ik.clik(panda, (x[:, :3, 3], v), q1, DT, limits=True, qdot_max=2.0, **kw)
    b = ik.clik(panda, (x[:, :3, 3], v), q1, DT,
                limits=[ik.ConfigurationLimit(gain=1.0), ik.VelocityLimit(2.0)], **kw)
    torch.testing.assert_close(b.q, a.q, atol=1e-12, rtol=0)
    vmax = torch.tensor([2.0, 2.0, 2.0, 2.0, 1.0, 1.0, 1.0], dtype=F64)
    d, lim = 0.05, panda.q_limits
    tasks = [ik.FrameTask(0, target=x, orientation_cost=0.0), ik.FrameTask(0, twist=v)]
    c = ik.clik(panda, q0=q1, dt=DT, tasks=tasks, **kw,
                limits=[ik.ConfigurationLimit(gain=0.5, min_distance_from_limits=d), ik.VelocityLimit(vmax)])
    margin = torch.minimum(c.q - lim[:, 0] - d, lim[:, 1] - d - c.q)
    assert float(margin.min()) >= -1e-12 and float(margin[:, 3].min()) < 0.02  # held, and reached
    assert bool((c.qdot.abs() <= vmax + 1e-12).all())
    assert bool((c.qdot.abs().amax(0) >= vmax - 1e-9).any())  # a velocity limit binds
    free = ik.clik(panda, q0=q1, dt=DT, tasks=tasks, **kw)
    assert float(torch.minimum(free.q - lim[:, 0] - d, lim[:, 1] - d - free.q).min()) < -0.1


def test_costs_weight_the_dls_law(panda):
    """q̇ = (WJ)ᵀ((WJ)(WJ)ᵀ + λI)⁻¹ W(ẋ_d + K e) (3.59) with W the FrameTask's costs (numpy)."""
    x, v = _track(panda, 2)
    x = x.clone()
    x[:, :3, 3] += 0.05
    wp, wo, lam, K = torch.tensor([1.0, 2.0, 0.5], dtype=F64), 0.3, 1e-2, 20.0
    res = ik.clik(panda, q0=Q0, dt=DT, steps=0, algorithm="dls", orientation="quaternion", damping=lam, K=K,
                  tasks=[
        ik.FrameTask(0, target=x, position_cost=wp, orientation_cost=wo), ik.FrameTask(0, twist=v)])
    T, J = panda.forward_kinematics_and_jacobian(Q0)
    e = res.error[0]  # [p_d − p_e; Δε] (3.91), as fed back: the reference ẋ_d + K e (3.92)
    W = np.diag(np.r_[wp.numpy(), [wo] * 3])
    WJ = W @ J.numpy()
    want = WJ.T @ np.linalg.solve(WJ @ WJ.T + lam * np.eye(6), W @ (v[0].numpy() + K * e.numpy()))
    np.testing.assert_allclose(res.qdot[0].numpy(), want, atol=1e-10)


def test_clik_refuses_what_it_cannot_use(panda):
    x, v = _track(panda, 3)
    pose = ik.FrameTask(0, target=x)
    with pytest.raises(ConventionError, match="once"):
        ik.clik(panda, x, Q0, DT, tasks=[pose])
    with pytest.raises(ConventionError, match="one FrameTask with a target"):
        ik.clik(panda, q0=Q0, dt=DT, tasks=[pose, ik.FrameTask(0, target=x)])
    with pytest.raises(ConventionError, match="FrameTask and PostureTask"):
        ik.clik(panda, q0=Q0, dt=DT, tasks=[pose, ik.DampingTask(1.0)])
    with pytest.raises(ConventionError, match="frame"):
        ik.clik(panda, q0=Q0, dt=DT, tasks=[ik.FrameTask(1, target=x)])
    with pytest.raises(ConventionError, match="Limit objects"):
        ik.clik(panda, q0=Q0, dt=DT, tasks=[pose], algorithm="dls", limits=[object()])
    with pytest.raises(ConventionError, match="VelocityLimit, not"):
        ik.clik(panda, q0=Q0, dt=DT, tasks=[pose], algorithm="dls", limits=[ik.ConfigurationLimit()],
                qdot_max=1.0)
    with pytest.raises(ConventionError, match="limit objects"):
        ik.clik(panda, q0=Q0, dt=DT, tasks=[pose], limits=[ik.ConfigurationLimit()])  # pseudo_inverse
