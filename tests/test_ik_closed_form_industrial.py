"""Closed-form IK of the industrial families (UR, ortho-parallel + spherical wrist) on real robot files:
every branch reproduces the target, the true configuration is among them, singular targets stay finite,
gradients match finite differences, and ik.solve agrees (and can be seeded by the closed form)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from diffkin import ik, models
from diffkin.chain import DHChain
from diffkin.errors import ModelError
from diffkin.ik.analytic import closed_form, identify_structure
from diffkin.ik.industrial import industrial_parameters
from diffkin.models import from_urdf

F64 = torch.float64
PI = math.pi
DATA = Path(__file__).parent / "data" / "urdf"
# name -> (loader, family)
ROBOTS = {
    "ur3_robot": (lambda dt: from_urdf(DATA / "ur3_robot.urdf", "tool0", dtype=dt), "ur"),
    "ur10": (lambda dt: from_urdf(DATA / "ur10.urdf", "tool0", dtype=dt), "ur"),
    "ur5_dh": (lambda dt: models.load("ur5", dtype=dt), "ur"),
    "irb2400": (lambda dt: from_urdf(DATA / "irb2400.urdf", "tool0", dtype=dt), "opw"),
    "rx160": (lambda dt: from_urdf(DATA / "rx160.urdf", "tool0", dtype=dt), "opw"),
    "meca500": (lambda dt: from_urdf(DATA / "meca500.urdf", "meca_axis_6_link", dtype=dt), "opw"),
    "kinova_j2s6s200": (lambda dt: from_urdf(DATA / "kinova.urdf", "j2s6s200_end_effector", dtype=dt), "opw"),
}


def _robot(name, dtype=F64):
    return ROBOTS[name][0](dtype)


def _residual(chain, q, T):
    return (chain.forward_kinematics(q) - T[..., None, :, :]).flatten(-2).norm(dim=-1)


def _contains(q_branches, q, tol=1e-7):
    dq = q_branches - q[..., None, :]
    return (torch.atan2(torch.sin(dq), torch.cos(dq)).abs().amax(-1) < tol).any(-1)


def _generic_q(chain, n, seed=0):
    """Configurations inside the limits, away from the wrist and elbow singularities."""
    q = chain.random_configuration((n,), generator=torch.Generator().manual_seed(seed))
    g = torch.Generator().manual_seed(seed + 1)
    q[:, 2] = torch.sign(q[:, 2] + 1e-3) * (0.4 + 0.8 * torch.rand(n, generator=g, dtype=q.dtype))
    q[:, 4] = torch.sign(q[:, 4] + 1e-3) * (0.3 + 1.0 * torch.rand(n, generator=g, dtype=q.dtype))
    return q


@pytest.mark.parametrize("name", list(ROBOTS))
def test_branches_reproduce_target_and_contain_true_q(name):
    chain = _robot(name)
    assert identify_structure(chain) == ROBOTS[name][1]
    q = chain.random_configuration((4, 50), generator=torch.Generator().manual_seed(1))
    T = chain.forward_kinematics(q)
    sol = closed_form(chain, T)
    assert sol.structure == ROBOTS[name][1]
    assert sol.q.shape == (4, 50, 8, 6) and sol.success.shape == sol.within_limits.shape == (4, 50, 8)
    assert torch.isfinite(sol.q).all()
    assert (_residual(chain, sol.q, T)[sol.success] < 1e-9).all()
    assert _contains(sol.q, q).all()
    assert (sol.success.sum(-1) % 2 == 0).all()  # branches come and go in pairs (one root of a subproblem)
    assert torch.equal(sol.within_limits, chain.within_limits(sol.q))
    q_, valid = sol  # still a 2-tuple
    assert q_ is sol.q and valid is sol.success


@pytest.mark.parametrize("name", list(ROBOTS))
def test_generic_targets_give_eight_distinct_branches(name):
    chain = _robot(name)
    q = _generic_q(chain, 40)
    sol = closed_form(chain, chain.forward_kinematics(q))
    full = sol.success.all(-1)
    # far targets lose branches whose planar 2R problem is out of reach (the UR's other shoulder moves the
    # 4–5 point by ~2 d5); LM from 384 random seeds finds no solution outside the valid branches there
    assert full.float().mean() >= 0.4
    d = (sol.q[full][:, :, None] - sol.q[full][:, None, :])
    d = torch.atan2(torch.sin(d), torch.cos(d)).abs().amax(-1) + 10 * torch.eye(8, dtype=F64)
    assert (d > 1e-3).all()


def test_geometry_parameters_from_urdf_and_dh():
    """The family's parameters come from the joint lines, the same for a URDF and a DH table."""
    ur5 = models.load("ur5", dtype=F64)
    p = industrial_parameters(ur5)
    a, d = ur5.a.detach().abs(), ur5.d.detach()
    expect = {"d1": d[0], "a2": a[1], "a3": a[2], "d4": d[3], "d5": d[4], "d6": d[5]}
    for k, v in expect.items():
        assert p[k] == pytest.approx(float(v), abs=1e-12), k
    ur10 = industrial_parameters(_robot("ur10"))  # UR10 DH: d1, a2, a3, d4, d5, d6
    for k, v in dict(d1=0.1273, a2=0.612, a3=0.5723, d4=0.163941, d5=0.1157, d6=0.0922).items():
        assert ur10[k] == pytest.approx(v, abs=1e-12), k
    irb = industrial_parameters(_robot("irb2400"))  # ROS-Industrial opw_kinematics' IRB 2400 (|a2|)
    for k, v in dict(c1=0.615, a1=0.1, c2=0.705, c3=0.755, a2=0.135, b=0.0, c4=0.085).items():
        assert irb[k] == pytest.approx(v, abs=1e-12), k
    rx = industrial_parameters(_robot("rx160"))
    for k, v in dict(c1=0.55, a1=0.15, c2=0.825, c3=0.625, a2=0.0, b=0.0, c4=0.11).items():
        assert rx[k] == pytest.approx(v, abs=1e-12), k


def _rigid(seed):
    g = torch.Generator().manual_seed(seed)
    Q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=F64))
    T = torch.eye(4, dtype=F64)
    T[:3, :3], T[:3, 3] = Q * torch.sign(torch.linalg.det(Q)), 0.2 * torch.randn(3, generator=g, dtype=F64)
    return T


def test_base_tool_joint_offsets_and_modified_dh():
    """Base and tool folded in; a DH table with other joint offsets and flipped joint directions."""
    ur5 = models.load("ur5", dtype=F64)
    a, alpha, d, theta = (x.detach().clone() for x in (ur5.a, ur5.alpha, ur5.d, ur5.theta))
    theta += torch.tensor([0.3, -0.5, 1.0, 0.2, -0.7, 2.0], dtype=F64)
    alpha[3] = -alpha[3]  # axis 5 flipped
    chain = DHChain(a, alpha, d, theta, base=_rigid(0), tool=_rigid(1))
    assert identify_structure(chain) == "ur"
    q = chain.random_configuration((60,), generator=torch.Generator().manual_seed(2))
    T = chain.forward_kinematics(q)
    sol = closed_form(chain, T)
    assert (_residual(chain, sol.q, T)[sol.success] < 1e-9).all() and _contains(sol.q, q).all()


def test_joint_limits_wrapping():
    ur5 = models.load("ur5", dtype=F64)
    lim = torch.tensor([[0.0, 2 * PI]] + [[-PI, PI]] * 4 + [[-2 * PI, 0.0]], dtype=F64)
    chain = DHChain(ur5.a.detach(), ur5.alpha.detach(), ur5.d.detach(), ur5.theta.detach(), q_limits=lim)
    q = chain.random_configuration((50,), generator=torch.Generator().manual_seed(3))
    T = chain.forward_kinematics(q)
    sol = closed_form(chain, T)
    assert sol.within_limits.all()  # every branch brought in by ±2π
    assert (sol.q[..., 0] >= 0).all() and (sol.q[..., 5] <= 0).all()
    assert (_residual(chain, sol.q, T)[sol.success] < 1e-9).all() and _contains(sol.q, q).all()
    irb = _robot("irb2400")  # narrow limits: some valid branches are outside, and flagged so
    q = irb.random_configuration((200,), generator=torch.Generator().manual_seed(4))
    sol = closed_form(irb, irb.forward_kinematics(q))
    assert torch.equal(sol.within_limits, irb.within_limits(sol.q))
    assert (sol.success & ~sol.within_limits).any() and (sol.success & sol.within_limits).any(-1).all()


def _grad_finite(fn, x):
    x = x.detach().clone().requires_grad_(True)
    q = fn(x)
    (g,) = torch.autograd.grad((q * torch.linspace(0.5, 1.5, q.shape[-1], dtype=q.dtype)).sum(), x)
    return q, g


def test_singular_targets_finite_values_and_gradients():
    # UR wrist singularity (q5 = 0: axis 6 parallel to axes 2-4) and elbow stretched (q3 = 0)
    ur10 = _robot("ur10")
    for q in ([0.3, -1.0, 1.2, 0.4, 0.0, 0.5], [0.3, -1.0, 0.0, 0.4, 0.9, 0.5],
              [0.3, -1.0, 0.0, 0.4, 0.0, 0.5]):
        q = torch.tensor(q, dtype=F64)
        T = ur10.forward_kinematics(q)
        sol, g = _grad_finite(lambda T: closed_form(ur10, T).q, T)
        valid = closed_form(ur10, T).success
        assert torch.isfinite(sol).all() and torch.isfinite(g).all() and valid.any()
        assert (_residual(ur10, sol.detach(), T)[valid] < 1e-9).all()
    # OPW wrist singularity (axes 4 and 6 aligned) and elbow singularity
    irb = _robot("irb2400")
    for q in ([0.3, 0.4, -0.2, 0.7, 0.0, -0.5], [0.3, 0.4, 0.0, 0.7, 0.6, -0.5]):
        q = torch.tensor(q, dtype=F64)
        T = irb.forward_kinematics(q)
        sol, g = _grad_finite(lambda T: closed_form(irb, T).q, T)
        valid = closed_form(irb, T).success
        assert torch.isfinite(sol).all() and torch.isfinite(g).all() and valid.any()
        assert (_residual(irb, sol.detach(), T)[valid] < 1e-9).all()
    # OPW shoulder singularity: wrist centre on axis 1 (a shoulder offset a1 keeps it reachable)
    a = torch.tensor([0.1, 0.5, 0, 0, 0, 0], dtype=F64)
    alpha = torch.tensor([PI / 2, 0, PI / 2, -PI / 2, PI / 2, 0], dtype=F64)
    d = torch.tensor([0.3, 0, 0, 0.5, 0, 0.1], dtype=F64)
    arm = DHChain(a, alpha, d, torch.zeros(6, dtype=F64))
    assert identify_structure(arm) == "opw"
    T = torch.eye(4, dtype=F64)
    T[:3, :3] = _rigid(5)[:3, :3]
    T[:3, 3] = torch.tensor([0.0, 0.0, 0.9], dtype=F64) + 0.1 * T[:3, 2]  # wrist centre (0, 0, 0.9)
    sol = closed_form(arm, T)
    assert sol.success.all() and (_residual(arm, sol.q, T) < 1e-9).all()
    q, g = _grad_finite(lambda T: closed_form(arm, T).q, T)
    assert torch.isfinite(g).all()


def _perturbed(T0):
    def f(x):  # x = (rotation vector, translation) applied on the left
        w, t = x[:3], x[3:]
        S = torch.zeros(3, 3, dtype=F64)
        S = S + torch.stack([torch.stack([0 * w[0], -w[2], w[1]]), torch.stack([w[2], 0 * w[0], -w[0]]),
                             torch.stack([-w[1], w[0], 0 * w[0]])])  # fmt: skip
        R = torch.matrix_exp(S) @ T0[:3, :3]
        return torch.cat((torch.cat((R, (T0[:3, 3] + t)[:, None]), -1), T0[3:]), -2)

    return f


@pytest.mark.parametrize("name", ["ur10", "irb2400", "ur5_dh"])
def test_gradients_wrt_target_against_finite_differences(name):
    chain = _robot(name)
    q = _generic_q(chain, 1, seed=7)[0]
    f = _perturbed(chain.forward_kinematics(q).detach())
    x = torch.zeros(6, dtype=F64, requires_grad=True)
    assert closed_form(chain, f(x)).success.all()
    assert torch.autograd.gradcheck(lambda x: closed_form(chain, f(x)).q, (x,))


def test_gradients_wrt_dh_geometry_against_finite_differences():
    """d q_branches / d (a, d) of the DH UR5 by autograd vs central differences of the closed form."""
    chain = models.load("ur5", dtype=F64, learnable=True)
    q = _generic_q(chain, 3, seed=9)
    with torch.no_grad():
        T = chain.forward_kinematics(q)
    w = torch.linspace(0.5, 1.5, 8 * 6, dtype=F64).reshape(8, 6)

    def loss():
        return (closed_form(chain, T).q * w).sum()

    ga, gd = torch.autograd.grad(loss(), (chain.a, chain.d))
    eps = 1e-6
    for param, grad in ((chain.a, ga), (chain.d, gd)):
        for i in range(6):
            with torch.no_grad():
                param[i] += eps
                up = float(loss())
                param[i] -= 2 * eps
                down = float(loss())
                param[i] += eps
            fd = (up - down) / (2 * eps)
            assert grad[i].item() == pytest.approx(fd, abs=1e-5, rel=1e-5), (param.shape, i)
    assert ga.abs().sum() > 0 and gd.abs().sum() > 0


def test_float32_and_batch_shapes():
    chain = _robot("ur10", torch.float32)
    q = _generic_q(chain, 30, seed=11).reshape(3, 10, 6)
    T = chain.forward_kinematics(q)
    sol = closed_form(chain, T)
    assert sol.q.dtype == torch.float32 and sol.q.shape == (3, 10, 8, 6)
    ref = closed_form(_robot("ur10"), T.double())
    assert (sol.success == ref.success).float().mean() > 0.98 and _contains(sol.q, q, tol=2e-3).all()
    dq = sol.q[ref.success].double() - ref.q[ref.success]
    assert torch.atan2(torch.sin(dq), torch.cos(dq)).abs().max() < 2e-3
    irb = _robot("irb2400", torch.float32)
    q = _generic_q(irb, 30, seed=12)
    sol = closed_form(irb, irb.forward_kinematics(q))
    assert _contains(sol.q, q, tol=2e-3).all()
    one = closed_form(irb, irb.forward_kinematics(q[0]))
    assert one.q.shape == (8, 6) and one.success.shape == (8,)


def test_agreement_with_numerical_solve_and_closed_form_seeds():
    chain = _robot("ur10")
    q = chain.random_configuration((40,), generator=torch.Generator().manual_seed(13))
    T = chain.forward_kinematics(q)
    sol = closed_form(chain, T)
    res = ik.solve(chain, T, seed=0, position_tolerance=1e-6, orientation_tolerance=1e-6)
    ok = res.success
    assert ok.float().mean() > 0.8
    # every numerical solution is one of the closed-form branches
    assert _contains(sol.q[ok], res.q[ok], tol=1e-4).all()
    seeded = ik.solve(chain, T, seeds_from_closed_form=True, seed=0, position_tolerance=1e-9,
                      orientation_tolerance=1e-9)  # fmt: skip
    assert seeded.success.all()
    assert _contains(sol.q, seeded.q, tol=1e-8).all()
    with pytest.raises(ModelError):
        ik.solve(models.load("panda", dtype=F64), torch.eye(4, dtype=F64), seeds_from_closed_form=True)


def test_other_structures_get_a_model_error_naming_the_checks():
    ur5 = models.load("ur5", dtype=F64)
    alpha = ur5.alpha.detach().clone()
    alpha[1] = 0.2  # axis 3 no longer parallel to axis 2
    bent = DHChain(ur5.a.detach(), alpha, ur5.d.detach(), ur5.theta.detach(), name="bent")
    with pytest.raises(ModelError, match=r"ur: .*axes 2 ∥ 3 FAILS.*opw: "):
        closed_form(bent, torch.eye(4, dtype=F64))
    with pytest.raises(ModelError, match="closed-form"):
        identify_structure(models.load("kuka_iiwa14", dtype=F64))
    tree = from_urdf(DATA / "baxter.urdf", ["right_gripper", "left_gripper"], dtype=F64)
    with pytest.raises(ModelError):
        identify_structure(tree)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_follows_inputs():
    chain = _robot("ur10").to("cuda")
    q = chain.random_configuration((100,))
    sol = closed_form(chain, chain.forward_kinematics(q))
    assert sol.q.device.type == "cuda" and _contains(sol.q, q).all()
