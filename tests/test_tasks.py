"""ik.solve_velocity with the task and limit objects (issue 35, part 1) against mink's solve_ik (daqp).

References: mink (its own MuJoCo model of the same MJCF file, solver "daqp"); MuJoCo's geom distances
through mink's CollisionAvoidanceLimit; autograd of the SE(3) logarithm for its Jacobian; scipy's
bounded least squares and numpy's lstsq for the extreme-weight regression; finite differences and gradcheck.
"""

from pathlib import Path

import numpy as np
import pytest
import torch

from diffkin import ik
from diffkin.errors import ConventionError, DiffkinError, ShapeError
from diffkin.kernels.se3 import se3_jlog, se3_log
from diffkin.models import from_mjcf
from diffkin.models.mjcf import compile_mjcf
from tests.helpers import g1_com_case, g1_com_robot, g1_mink_tasks, se3_exp

mink = pytest.importorskip("mink")
mujoco = pytest.importorskip("mujoco")

F64 = torch.float64
MJCF = Path(__file__).parent / "data" / "mjcf"
PANDA = MJCF / "franka_emika_panda" / "panda.xml"
G1 = MJCF / "unitree_g1" / "g1.xml"
ARM = ["joint1", "joint2", "joint3", "joint4", "joint5", "joint6", "joint7"]


def _panda(ends="hand", dtype=F64):
    return compile_mjcf(PANDA)[0], from_mjcf(PANDA, ends, dtype=dtype).requires_grad_(False)


def _panda_rows(model, chain, n, seed):
    rng = np.random.default_rng(seed)
    lo, hi = chain.q_limits[:, 0].numpy(), chain.q_limits[:, 1].numpy()
    qs = []
    for _ in range(n):
        qpos = model.qpos0.copy()
        qpos[chain.qpos_index()] = lo + (hi - lo) * rng.uniform(0.05, 0.95, size=lo.shape)
        qs.append(qpos)
    return qs


def _mink_v(model, qpos, tasks, limits, dt, damping=1e-12):
    conf = mink.Configuration(model, qpos)
    return mink.solve_ik(conf, tasks, dt, "daqp", damping=damping, limits=limits)


# ------------------------------------------------------------------------------------------- SE(3)
def test_se3_log_and_its_jacobian_against_the_matrix_exponential_and_autograd():
    g = torch.Generator().manual_seed(0)
    for scale in (1e-8, 1e-4, 0.05, 0.3, 1.0, 1.7):  # rotation angles up to about 3 rad (log's range: < π)
        xi = torch.randn(8, 6, generator=g, dtype=F64) * scale
        w = xi[:, 3:]
        xi[:, 3:] = w * (3.0 / w.norm(dim=-1, keepdim=True)).clamp(max=1.0)
        T = se3_exp(xi)
        torch.testing.assert_close(se3_log(T), xi, atol=1e-12, rtol=1e-9)
        for Ti in T[:3]:
            J = torch.autograd.functional.jacobian(lambda d, Ti=Ti: se3_log(Ti @ se3_exp(d)),
                                                   torch.zeros(6, dtype=F64))
            torch.testing.assert_close(se3_jlog(Ti), J, atol=1e-9, rtol=1e-9)


# ----------------------------------------------------------------------------------------- vs mink
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_panda_frame_posture_configuration_velocity_matches_mink(dtype):
    model, chain = _panda(dtype=dtype)
    dt, vel = 0.01, {n: 0.6 + 0.1 * i for i, n in enumerate(ARM[:5])}
    rows = _panda_rows(model, chain, 12, 1)
    rng = np.random.default_rng(2)
    q_ref = model.qpos0.copy()
    q, targets, want = [], [], []
    for qpos in rows:
        conf = mink.Configuration(model, qpos)
        tgt = conf.get_transform_frame_to_world("hand", "body") @ mink.SE3.exp(rng.normal(size=6) * 0.02)
        ft = mink.FrameTask("hand", "body", position_cost=[1.0, 2.0, 1.0], orientation_cost=0.5,
                            lm_damping=1e-2, gain=0.8)
        ft.set_target(tgt)
        pt = mink.PostureTask(model, cost=1e-2)
        pt.set_target(q_ref)
        limits = [mink.ConfigurationLimit(model, gain=0.9, min_distance_from_limits=0.01),
                  mink.VelocityLimit(model, vel)]
        want.append(_mink_v(model, qpos, [ft, pt], limits, dt, 1e-6)[chain.dof_index()])
        q.append(qpos[chain.qpos_index()])
        targets.append(tgt.as_matrix())
    q = torch.tensor(np.array(q), dtype=dtype)
    T = torch.tensor(np.array(targets), dtype=dtype)
    tasks = [ik.FrameTask("hand", target=T, position_cost=torch.tensor([1.0, 2.0, 1.0], dtype=dtype),
                          orientation_cost=0.5, lm_damping=1e-2, gain=0.8),
             ik.PostureTask(torch.tensor(q_ref[chain.qpos_index()], dtype=dtype), cost=1e-2)]
    limits = [ik.ConfigurationLimit(gain=0.9, min_distance_from_limits=0.01), ik.VelocityLimit(vel)]
    v = ik.solve_velocity(chain, q, tasks, dt, limits=limits, damping=1e-6)
    want = np.array(want)
    assert v.dtype == dtype and v.shape == (12, 7)
    assert np.isclose(np.abs(want[:, :5]), [0.6, 0.7, 0.8, 0.9, 1.0], atol=1e-9).sum() >= 3  # limits active
    np.testing.assert_allclose(v.double().numpy(), want, atol=1e-6 if dtype == F64 else 2e-3)
    # every limit holds after the step
    q1 = chain.integrate(q, v * dt)
    lim = chain.q_limits
    assert bool((q1 >= lim[:, 0] - 1e-6).all() and (q1 <= lim[:, 1] + 1e-6).all())
    vmax = torch.tensor([0.6, 0.7, 0.8, 0.9, 1.0], dtype=dtype)
    assert bool((v[:, :5].abs() <= vmax * (1 + 1e-6)).all())


def test_relative_frame_task_and_damping_task_match_mink():
    model, chain = _panda(["hand", "link3"])
    dt = 0.02
    rows = _panda_rows(model, chain, 6, 3)
    rng = np.random.default_rng(4)
    q, targets, want = [], [], []
    for qpos in rows:
        conf = mink.Configuration(model, qpos)
        T_rf = conf.get_transform("hand", "body", "link3", "body")
        tgt = T_rf @ mink.SE3.exp(rng.normal(size=6) * 0.05)
        rt = mink.RelativeFrameTask("hand", "body", "link3", "body", position_cost=1.0, orientation_cost=0.3)
        rt.set_target(tgt)
        dk = mink.DampingTask(model, cost=0.1)
        want.append(_mink_v(model, qpos, [rt, dk], [mink.ConfigurationLimit(model)], dt)[chain.dof_index()])
        q.append(qpos[chain.qpos_index()])
        targets.append(tgt.as_matrix())
    tasks = [ik.RelativeFrameTask("hand", "link3", target=torch.tensor(np.array(targets)), position_cost=1.0,
                                  orientation_cost=0.3), ik.DampingTask(0.1)]
    v = ik.solve_velocity(chain, torch.tensor(np.array(q)), tasks, dt, limits=[ik.ConfigurationLimit()])
    np.testing.assert_allclose(v.numpy(), np.array(want), atol=1e-6)
    assert np.abs(np.array(want)).max() > 0.1


def _g1():
    ends = ["left_ankle_roll_link", "right_ankle_roll_link", "left_zero_link", "right_zero_link"]
    model = compile_mjcf(G1)[0]
    chain = from_mjcf(G1, ends, dtype=F64).requires_grad_(False)
    return model, chain, ends


def test_floating_base_g1_matches_mink_and_its_base_velocity_limit_holds():
    model, chain, ends = _g1()
    assert chain.joint_kinds[0] == "free"
    dt, rng = 0.01, np.random.default_rng(5)
    qpos = model.qpos0.copy()
    hinge = [n for n, k in zip(chain.joint_names, chain.joint_kinds) if k != "free"]
    conf = mink.Configuration(model, qpos)
    mtasks, ttasks = [], []
    for e in ends:
        tgt = conf.get_transform_frame_to_world(e, "body") @ mink.SE3.exp(rng.normal(size=6) * 0.03)
        t = mink.FrameTask(e, "body", position_cost=1.0, orientation_cost=0.5, lm_damping=1e-3)
        t.set_target(tgt)
        mtasks.append(t)
        ttasks.append(ik.FrameTask(e, target=torch.tensor(tgt.as_matrix()), position_cost=1.0,
                                   orientation_cost=0.5, lm_damping=1e-3))
    pt = mink.PostureTask(model, cost=0.05)
    pt.set_target(model.qpos0)
    mtasks += [pt, mink.DampingTask(model, cost=1e-3)]
    q = torch.tensor(qpos[chain.qpos_index()])
    ttasks += [ik.PostureTask(q.clone(), cost=0.05), ik.DampingTask(1e-3)]
    vel = {n: 1.5 for n in hinge[:12]}
    base = {"linear": 0.2, "angular": 0.3}
    mlimits = [mink.ConfigurationLimit(model), mink.VelocityLimit(model, vel),
               mink.FreeJointVelocityLimit(model, max_linear_velocity=base["linear"],
                                           max_angular_velocity=base["angular"])]
    want = _mink_v(model, qpos, mtasks, mlimits, dt)[chain.dof_index()]
    base_limit = [base["linear"]] * 3 + [base["angular"]] * 3  # the base at rest orientation: the same rows
    limits = [ik.ConfigurationLimit(), ik.VelocityLimit({**vel, chain.joint_names[0]: base_limit})]
    v = ik.solve_velocity(chain, q, ttasks, dt, limits=limits)
    np.testing.assert_allclose(v.numpy(), want, atol=1e-6)
    assert np.isclose(np.abs(want[:6]), [0.2, 0.2, 0.2, 0.3, 0.3, 0.3]).any()  # the base limit is active
    # batched and rotated: the box on the chain's base velocity coordinates holds, and so do the others
    g = torch.Generator().manual_seed(6)
    qb = q.expand(5, -1).clone()
    qb[:, 3:7] = torch.nn.functional.normalize(torch.randn(5, 4, generator=g, dtype=F64), dim=-1)
    tb = [ik.FrameTask(e, target=chain.forward_kinematics(qb)[:, k] @ se3_exp(
        0.1 * torch.randn(5, 6, generator=g, dtype=F64))) for k, e in enumerate(ends)]
    vb = ik.solve_velocity(chain, qb, tb + [ik.DampingTask(1e-3)], dt, limits=limits)
    assert bool((vb[:, :3].abs() <= 0.2 + 1e-9).all() and (vb[:, 3:6].abs() <= 0.3 + 1e-9).all())
    q1 = chain.integrate(qb, vb * dt)
    lim = chain.q_limits
    scalar = list(chain.configuration_space.scalar_index("q"))[3:]
    assert bool((q1[:, scalar] >= lim[scalar, 0] - 1e-9).all())
    assert bool((q1[:, scalar] <= lim[scalar, 1] + 1e-9).all())


ARM_XML = """<mujoco model="arm">
  <worldbody>
    <body name="obstacle" pos="0.25 0.05 0.55"><geom name="ball" type="sphere" size="0.06"/></body>
    <body name="base" pos="0 0 0.1">
      <geom name="base_box" type="box" size="0.1 0.1 0.05"/>
      <body name="l1" pos="0 0 0.05">
        <joint name="j1" type="hinge" axis="0 0 1" range="-3 3"/>
        <geom name="l1_cap" type="capsule" fromto="0 0 0 0 0 0.35" size="0.04"/>
        <body name="l2" pos="0 0 0.35">
          <joint name="j2" type="hinge" axis="0 1 0" range="-2.5 2.5"/>
          <geom name="l2_cap" type="capsule" fromto="0 0 0 0.3 0 0" size="0.035"/>
          <body name="l3" pos="0.3 0 0">
            <joint name="j3" type="hinge" axis="0 1 0" range="-2.8 2.8"/>
            <geom name="l3_cap" type="capsule" fromto="0 0 0 0.25 0 0" size="0.03"/>
            <body name="tip" pos="0.25 0 0"><geom name="tip_ball" type="sphere" size="0.03"/></body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>"""


def test_collision_limit_rows_match_minks_collision_avoidance_limit():
    """mink bounds J Δq by γ(d − d_min)/Δt (a velocity against a displacement), CollisionLimit by
    γ(d − d_min), the distance's own decrease over the step: at Δt = 1 they are the same rows, compared
    there, on rows whose detected pairs are all clear of the minimum distance (mink flips the row of a
    penetrating pair by MuJoCo's witness points; CollisionLimit uses the signed distance's gradient)."""
    from diffkin.collision import RobotCollision

    model = mujoco.MjModel.from_xml_string(ARM_XML)
    chain = from_mjcf(ARM_XML, "tip", dtype=F64).requires_grad_(False)
    rc = RobotCollision.from_mjcf(model, chain, dtype=F64)
    geoms = [model.geom(i).name for i in range(model.ngeom)]
    tgt = mink.SE3.from_translation(np.array([0.25, 0.05, 0.55]))  # pull the tip into the obstacle
    limit = ik.CollisionLimit(rc, gain=0.85, minimum_distance=0.01, detection_distance=0.08)
    task = ik.FrameTask("tip", target=torch.tensor(tgt.as_matrix()), orientation_cost=0.0)
    rng = np.random.default_rng(7)
    compared = active = 0
    for _ in range(300):
        qpos = rng.uniform(-2.0, 2.0, size=3)
        conf = mink.Configuration(model, qpos)
        ft = mink.FrameTask("tip", "body", position_cost=1.0, orientation_cost=0.0)
        ft.set_target(tgt)
        lim = mink.CollisionAvoidanceLimit(model, [(geoms, geoms)], gain=0.85,
                                           minimum_distance_from_collisions=0.01,
                                           collision_detection_distance=0.08)
        G, h = lim.compute_qp_inequalities(conf, 1.0)
        on = np.isfinite(h)
        if not on.any() or (h[on] <= 0.0).any():
            continue
        compared += 1
        want = _mink_v(model, qpos, [ft], [lim], 1.0, damping=1e-4)
        active += int(np.any(G[on] @ want >= h[on] - 1e-9))
        v = ik.solve_velocity(chain, torch.tensor(qpos), [task], 1.0, limits=[limit], damping=1e-4)
        np.testing.assert_allclose(v.numpy(), want, atol=1e-6)
    assert compared >= 5 and active >= 2


# ------------------------------------------------------------------------------------- gradients
def test_gradients_with_respect_to_the_target_finite_differences_and_gradcheck():
    model, chain = _panda()
    q = torch.tensor(np.array(_panda_rows(model, chain, 3, 8)))[:, chain.qpos_index()]
    T0 = chain.forward_kinematics(q)
    xi = torch.tensor([[0.02, -0.01, 0.03, 0.1, -0.2, 0.05]], dtype=F64).expand(3, 6).clone()
    limits = [ik.ConfigurationLimit(), ik.VelocityLimit(0.8)]

    def f(xi, w):
        T = T0 @ se3_exp(xi)
        return ik.solve_velocity(chain, q, [ik.FrameTask(0, target=T, orientation_cost=w, lm_damping=1e-3),
                                            ik.PostureTask(torch.zeros(7, dtype=F64), cost=0.1)], 0.05,
                                 limits=limits)

    v = f(xi, torch.tensor(0.5, dtype=F64))
    assert int((v.abs() > 0.8 - 1e-12).sum()) >= 1  # a bound is active
    assert torch.autograd.gradcheck(f, (xi.clone().requires_grad_(True),
                                        torch.tensor(0.5, dtype=F64, requires_grad=True)), atol=1e-6)
    xg = xi.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(f(xg, 0.5).square().sum(), xg)
    h = 1e-6
    for j in range(6):
        e = torch.zeros_like(xi)
        e[:, j] = h
        fd = (f(xi + e, 0.5).square().sum(-1) - f(xi - e, 0.5).square().sum(-1)) / (2 * h)
        torch.testing.assert_close(grad[:, j], fd, atol=1e-5, rtol=1e-5)


def test_batch_dims_broadcast_and_one_row_equals_the_batch():
    model, chain = _panda()
    q = torch.tensor(np.array(_panda_rows(model, chain, 6, 9)))[:, chain.qpos_index()].reshape(2, 3, 7)
    T = chain.forward_kinematics(q) @ se3_exp(torch.full((6,), 0.02, dtype=F64))
    tasks = [ik.FrameTask("hand", target=T), ik.PostureTask(torch.zeros(7, dtype=F64), cost=0.1)]
    v = ik.solve_velocity(chain, q, tasks, 0.02, limits=[ik.ConfigurationLimit(), ik.VelocityLimit(1.0)])
    assert v.shape == (2, 3, 7)
    one = ik.solve_velocity(chain, q[1, 2], [ik.FrameTask("hand", target=T[1, 2]), tasks[1]], 0.02,
                            limits=[ik.ConfigurationLimit(), ik.VelocityLimit(1.0)])
    torch.testing.assert_close(one, v[1, 2], atol=1e-12, rtol=0)
    # one target for the whole batch, per-row costs (..., 3)
    cost = torch.tensor([[1.0, 1.0, 1.0], [2.0, 2.0, 2.0]], dtype=F64)[:, None, :]
    w = ik.solve_velocity(chain, q, [ik.FrameTask(0, target=T[0, 0], position_cost=cost)], 0.02)
    assert w.shape == (2, 3, 7)


# ------------------------------------------------------------------------- shorthands and errors
def test_velocity_step_is_solve_velocity_with_twist_tasks():
    model, chain = _panda()
    q = torch.tensor(np.array(_panda_rows(model, chain, 8, 10)))[:, chain.qpos_index()]
    twist = torch.randn(8, 6, generator=torch.Generator().manual_seed(11), dtype=F64) * 0.3
    w = torch.tensor([1.0, 1.0, 1.0, 0.3, 0.3, 0.3], dtype=F64)
    a = ik.velocity_step(chain, q, twist, 0.05, damping=1e-3, velocity_limit=0.7, weight=w)
    b = ik.solve_velocity(chain, q, [ik.FrameTask(0, twist=twist, position_cost=1.0, orientation_cost=0.3)],
                          0.05, limits=[ik.ConfigurationLimit(gain=1.0), ik.VelocityLimit(0.7)], damping=1e-3)
    torch.testing.assert_close(a, b, atol=1e-12, rtol=0)


def test_velocity_step_weight_zero_is_not_ignored():
    """Issue 39 item 3: a plain weight 0.0 on a single-end chain was turned into None (weight 1)."""
    _, chain = _panda()
    q = torch.zeros(7, dtype=F64)
    twist = torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0, 0.2], dtype=F64)
    kw = dict(respect_limits=False)
    assert float(ik.velocity_step(chain, q, twist, 0.1, weight=0.0, **kw).abs().max()) == 0.0
    full = torch.full((6,), 2.0, dtype=F64)
    torch.testing.assert_close(ik.velocity_step(chain, q, twist, 0.1, weight=2.0, **kw),
                               ik.velocity_step(chain, q, twist, 0.1, weight=full, **kw))


def test_velocity_step_extreme_weights_reach_the_optimum():
    """Issue 39 item 15: weight (1e8, 1, 1, 1, 1, 1) landed 15x (up to ~500x) above the optimal cost, forming
    AᵀA squared the condition number; the free variables are now re-solved by QR."""
    from scipy.optimize import lsq_linear

    _, chain = _panda()
    g = torch.Generator().manual_seed(12)
    q = chain.random_configuration(20, generator=g)
    tw = torch.randn(20, 6, generator=g, dtype=F64) * 0.2
    w = torch.tensor([1e8, 1, 1, 1, 1, 1], dtype=F64)
    lam, dt, vmax = 1e-3, 0.1, 2.0
    qd = ik.velocity_step(chain, q, tw, dt, weight=w, damping=lam, velocity_limit=vmax)
    J = chain.forward_kinematics_and_jacobian(q)[1]
    lim = chain.q_limits
    for i in range(20):
        A = np.vstack([(w[:, None] * J[i]).numpy(), np.sqrt(lam) * np.eye(7)])
        b = np.concatenate([(w * tw[i]).numpy(), np.zeros(7)])
        lo = np.clip(((lim[:, 0] - q[i]) / dt).numpy(), -vmax, vmax)
        hi = np.clip(((lim[:, 1] - q[i]) / dt).numpy(), -vmax, vmax)
        ref = lsq_linear(A, b, bounds=(lo, hi), method="bvls", tol=1e-15).x
        cost, best = np.sum((A @ qd[i].numpy() - b) ** 2), np.sum((A @ ref - b) ** 2)
        assert cost <= best * (1 + 1e-6) + 1e-9


def test_old_keywords_and_typed_errors():
    _, chain = _panda()
    assert ik.FrameTask(end=0, weight=[1, 1, 1, 0, 0, 0]).end == 0
    assert ik.PostureTask(torch.zeros(7), weight=2.0).cost == 2.0
    task = ik.FrameTask("hand", target=torch.eye(4, dtype=F64))
    with pytest.raises(AttributeError, match="frozen"):
        task.gain = 0.5
    q = torch.zeros(7, dtype=F64)
    with pytest.raises(ConventionError, match="end link"):
        ik.solve_velocity(chain, q, [ik.FrameTask("nope", target=torch.eye(4, dtype=F64))], 0.1)
    with pytest.raises(ConventionError, match="Task"):
        ik.solve_velocity(chain, q, ["posture"], 0.1)
    with pytest.raises(ConventionError, match="at least one"):
        ik.solve_velocity(chain, q, [], 0.1)
    with pytest.raises(ConventionError, match="Limit"):
        ik.solve_velocity(chain, q, [task], 0.1, limits=["joint"])
    with pytest.raises(ShapeError, match="4, 4"):
        ik.solve_velocity(chain, q, [ik.FrameTask(0, target=torch.eye(3, dtype=F64))], 0.1)
    with pytest.raises(ConventionError, match="not a joint"):
        ik.solve_velocity(chain, q, [task], 0.1, limits=[ik.VelocityLimit({"elbow": 1.0})])
    with pytest.raises(DiffkinError, match="gain"):
        ik.ConfigurationLimit(gain=1.5)
    with pytest.raises(DiffkinError, match="damping"):
        ik.solve_velocity(chain, q, [task], 0.1, damping=-1.0)
    with pytest.raises(DiffkinError, match="target pose or a twist"):
        ik.FrameTask(0, target=torch.eye(4), twist=torch.zeros(6))


def test_joint_limit_cost_does_not_penalise_the_identity_quaternion():
    """Issue 35: JointLimitCost gave residual 0.05 at the neutral pose of a floating-base chain (lower_upper
    gives ±1 on quaternion entries, and the identity's w = 1 sat on the 'upper limit')."""
    from diffkin.ik import CostContext, JointLimitCost

    _, chain, _ = _g1()
    q = chain.neutral_configuration()
    lo, hi = chain.lower_upper()
    mid = 0.5 * (lo + hi)
    scalar = list(chain.configuration_space.scalar_index("q"))
    q[scalar[3:]] = mid[scalar[3:]]  # the hinges mid-range, the base at the origin, identity orientation
    ctx = CostContext(chain, q, None)
    assert float(JointLimitCost(weight=1.0).residual(ctx).abs().max()) == 0.0
    q[scalar[3]] = hi[scalar[3]]  # a hinge on its limit is still penalised
    residual = JointLimitCost(weight=1.0).residual(CostContext(chain, q, None))
    assert float(residual.abs().max()) == pytest.approx(0.05)


def test_com_task_on_the_g1_matches_mink():
    """Feet fixed, hands moving, the centre of mass pulled over the support: ComTask + FrameTasks +
    PostureTask with limits, against mink's ComTask (subtree_com / mj_jacSubtreeCom of the pelvis)."""
    model, chain = g1_com_robot()
    assert chain.nv == model.nv
    dt = 0.01
    qpos, q, ttasks = g1_com_case(model, chain, 13, feet=0.0)  # feet fixed, hands moved
    mlimits = [mink.ConfigurationLimit(model)]
    want = _mink_v(model, qpos, g1_mink_tasks(model, ttasks), mlimits, dt, 1e-6)[chain.dof_index()]
    v = ik.solve_velocity(chain, q, ttasks, dt, limits=[ik.ConfigurationLimit()], damping=1e-6)
    np.testing.assert_allclose(v.numpy(), want, atol=1e-6)
    # the step moves the centre of mass towards its target
    c0, c1 = chain.center_of_mass(q), chain.center_of_mass(chain.integrate(q, v * dt))
    t = ttasks[0].target
    assert float((c1 - t).norm()) < float((c0 - t).norm())


def test_solve_takes_pose_frame_tasks_and_limits():
    """ik.solve(chain, tasks=..., limits=...) is ik.solve(chain, T, ...): the same q and flags."""
    _, chain = _panda()
    q = chain.random_configuration(16, generator=torch.Generator().manual_seed(14))
    T = chain.forward_kinematics(q)
    a = ik.solve(chain, T, seed=3)
    b = ik.solve(chain, tasks=[ik.FrameTask("hand", target=T)], limits=[ik.ConfigurationLimit()], seed=3)
    torch.testing.assert_close(a.q, b.q, atol=0, rtol=0)
    assert bool((a.success == b.success).all()) and bool(b.success.all())
    c = ik.solve(chain, tasks=[ik.FrameTask(0, target=T, orientation_cost=0.0)], seed=3)  # position only
    assert bool(c.success.all())
    torch.testing.assert_close(chain.forward_kinematics(c.q)[..., :3, 3], T[..., :3, 3], atol=2e-4, rtol=0)
    with pytest.raises(ConventionError, match="pose FrameTasks"):
        ik.solve(chain, tasks=[ik.PostureTask(torch.zeros(7, dtype=F64))])
    with pytest.raises(ConventionError, match="VelocityLimit"):
        ik.solve(chain, T, limits=[ik.VelocityLimit(1.0)])
    with pytest.raises(ConventionError, match="once"):
        ik.solve(chain, T, tasks=[ik.FrameTask(0, target=T)])


def test_optimize_takes_tasks_and_limits():
    """ik.optimize(chain, tasks=[pose FrameTask, PostureTask], limits=[ConfigurationLimit()]): the pose
    reached (success against the FrameTask's target) and, among the poses that reach it, the one the
    posture cost pulls towards (the redundant Panda's null space), against the same problem as cost
    objects."""
    _, chain = _panda()
    q = chain.random_configuration(8, generator=torch.Generator().manual_seed(15))
    T = chain.forward_kinematics(q)
    q0 = chain.clamp_to_limits(q + 0.05)
    q_ref = torch.zeros(7, dtype=F64)
    tasks = [ik.FrameTask("hand", target=T), ik.PostureTask(q_ref, cost=1e-3)]
    res = ik.optimize(chain, q0=q0, tasks=tasks, limits=[ik.ConfigurationLimit()], optimizer="gauss_newton")
    assert bool(res.success.all())
    # the same problem as cost objects: ‖log(T_f⁻¹T_t)‖² + 1e-6 ‖q − q_ref‖²
    from diffkin.ik._from_tasks import TaskCost

    costs = [TaskCost(task=tasks[0]), ik.RestPostureCost(q_rest=q_ref, weight=1e-6)]
    ref = ik.optimize(chain, T, q0, costs=costs, optimizer="gauss_newton")
    torch.testing.assert_close(res.q, ref.q, atol=1e-6, rtol=0)
    with pytest.raises(ConventionError, match="twist"):
        ik.optimize(chain, T, q0, tasks=[ik.FrameTask(0, twist=torch.zeros(6, dtype=F64))])


@pytest.mark.cuda
def test_solve_velocity_cuda_matches_cpu():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA")
    _, chain = _panda()
    q = chain.random_configuration(64, generator=torch.Generator().manual_seed(16))
    T = chain.forward_kinematics(q) @ se3_exp(torch.full((6,), 0.03, dtype=F64))
    tasks = [ik.FrameTask("hand", target=T, lm_damping=1e-3),
             ik.PostureTask(torch.zeros(7, dtype=F64), cost=0.1)]
    limits = [ik.ConfigurationLimit(), ik.VelocityLimit(1.0)]
    cpu = ik.solve_velocity(chain, q, tasks, 0.02, limits=limits)
    dev = torch.device("cuda")
    gchain = chain.to(dev)
    gtasks = [ik.FrameTask("hand", target=T.to(dev), lm_damping=1e-3),
              ik.PostureTask(torch.zeros(7, dtype=F64, device=dev), cost=0.1)]
    gpu = ik.solve_velocity(gchain, q.to(dev), gtasks, 0.02, limits=limits)
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, atol=1e-9, rtol=0)


def test_tasks_and_limits_arguments_name_what_they_take():
    _, chain = _panda()
    q = torch.zeros(7, dtype=F64)
    posture = ik.PostureTask(q, cost=0.1)
    kinds = r"\(FrameTask, RelativeFrameTask, PostureTask, ComTask, DampingTask\)"
    with pytest.raises(ConventionError, match=r"expected tasks as Task objects " + kinds + ", got 'hand'"):
        ik.solve_velocity(chain, q, [posture, "hand"], 0.01)
    with pytest.raises(ConventionError, match=r"expected limits as Limit objects \(ConfigurationLimit, "
                                              r"VelocityLimit, CollisionLimit\), got 1.0"):
        ik.solve_velocity(chain, q, posture, 0.01, limits=[ik.ConfigurationLimit(), 1.0])
    with pytest.raises(ConventionError, match="at least one task"):
        ik.solve_velocity(chain, q, None, 0.01)
    v = ik.solve_velocity(chain, q, posture, 0.01, limits=ik.ConfigurationLimit())  # one of each, unwrapped
    assert v.shape == (7,)
