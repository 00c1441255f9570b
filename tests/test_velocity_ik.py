"""ik.velocity_step and the QP solvers of diffkin.ik.qp (issue 29).

References: scipy's bounded-variable least squares (``lsq_linear(method="bvls")``) on the stacked system
[W J; √λ I] q̇ = [W v; 0]; daqp through qpsolvers for general inequalities and for the null-space posture
stage (as the equality-constrained QP it is); KKT conditions; finite differences and gradcheck.
"""

from pathlib import Path

import numpy as np
import pytest
import qpsolvers
import torch
from scipy.optimize import lsq_linear

from diffkin import ik, models
from diffkin.errors import ConventionError, DiffkinError, ShapeError
from diffkin.ik.qp import box_qp, solve_qp

F64 = torch.float64
DATA = Path(__file__).parent / "data" / "urdf"
TIPS = ["link_3.0_tip", "link_7.0_tip", "link_11.0_tip", "link_15.0_tip"]


def _chain(name: str, dtype=F64):
    if name == "allegro":
        return models.from_urdf(DATA / "allegro_right_hand.urdf", TIPS, dtype=dtype).requires_grad_(False)
    return models.load(name, dtype=dtype).requires_grad_(False)


def _bounds(chain, q, dt, vmax):
    lim = chain.q_limits
    lo = torch.clamp((lim[:, 0] - q) / dt, -vmax, vmax)
    hi = torch.clamp((lim[:, 1] - q) / dt, -vmax, vmax)
    return lo, hi


def _bvls(A, b, lam, lo, hi):
    n = A.shape[-1]
    As = np.vstack([A, np.sqrt(lam) * np.eye(n)])
    bs = np.concatenate([b, np.zeros(n)])
    return lsq_linear(As, bs, bounds=(lo, hi), method="bvls", tol=1e-14).x


def _random_problem(B, m, n, seed, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(B, m, n, generator=g, dtype=dtype)
    b = torch.randn(B, m, generator=g, dtype=dtype)
    lo = -torch.rand(B, n, generator=g, dtype=dtype) * 0.3
    hi = torch.rand(B, n, generator=g, dtype=dtype) * 0.3
    return A, b, lo, hi


# ------------------------------------------------------------------------------------------ solvers
def test_box_qp_matches_bvls_with_unbounded_and_zero_width_variables():
    A, b, lo, hi = _random_problem(300, 6, 7, 0)
    lo[:, 0] = -float("inf")  # one-sided and zero-width boxes
    hi[:50, 1] = lo[:50, 1]
    lam = 1e-3
    H = A.mT @ A + lam * torch.eye(7, dtype=F64)
    g = (A.mT @ b[..., None])[..., 0]
    res = box_qp(H, g, lo, hi)
    assert bool(res.converged.all())
    assert float((res.at_lower | res.at_upper).sum(-1).float().mean()) > 2.0  # bounds are active
    for i in range(300):
        a, bb, lo_i, hi_i = A[i].numpy(), b[i].numpy(), lo[i].numpy(), hi[i].numpy()
        ref = np.array(lo_i)  # bvls wants lower < upper: the zero-width variable is substituted
        keep = lo_i < hi_i
        ref[keep] = _bvls(a[:, keep], bb - a[:, ~keep] @ lo_i[~keep], lam, lo_i[keep], hi_i[keep])
        np.testing.assert_allclose(res.x[i].numpy(), ref, atol=1e-10)


def test_solve_qp_matches_daqp_with_general_inequalities():
    A, b, lo, hi = _random_problem(200, 6, 7, 1)
    g0 = torch.Generator().manual_seed(2)
    G = torch.randn(200, 5, 7, generator=g0, dtype=F64)
    h = torch.rand(200, 5, generator=g0, dtype=F64) * 0.1  # x = 0 is feasible
    h[:, 4] = float("inf")  # a switched-off row
    H = A.mT @ A + 1e-3 * torch.eye(7, dtype=F64)
    g = (A.mT @ b[..., None])[..., 0]
    res = solve_qp(H, g, G, h, lo, hi)
    assert bool(res.converged.all())
    assert float(res.active[:, :4].sum(-1).float().mean()) > 0.5
    for i in range(200):
        fin = torch.isfinite(h[i])
        ref = qpsolvers.solve_qp(H[i].numpy(), -g[i].numpy(), G[i][fin].numpy(), h[i][fin].numpy(),
                                 lb=lo[i].numpy(), ub=hi[i].numpy(), solver="daqp")
        np.testing.assert_allclose(res.x[i].numpy(), ref, atol=1e-8)
    # and the box-only case agrees with the active-set solver
    np.testing.assert_allclose(solve_qp(H, g, lower=lo, upper=hi).x, box_qp(H, g, lo, hi).x, atol=1e-8)


def test_qp_float32_matches_float64():
    A, b, lo, hi = _random_problem(100, 6, 7, 3)
    H = A.mT @ A + 1e-2 * torch.eye(7, dtype=F64)
    g = (A.mT @ b[..., None])[..., 0]
    G, h = A[:, :3] * 0.1, torch.full((100, 3), 0.05, dtype=F64)
    for fn, args in ((box_qp, (H, g, lo, hi)), (solve_qp, (H, g, G, h, lo, hi))):
        x64 = fn(*args).x
        x32 = fn(*(t.float() for t in args)).x
        assert x32.dtype == torch.float32
        assert float((x32.double() - x64).abs().max()) < 1e-4


def _gradcheck_problem():
    A, b, lo, hi = _random_problem(6, 4, 5, 4)
    H = (A.mT @ A + 0.1 * torch.eye(5, dtype=F64))
    g = (A.mT @ b[..., None])[..., 0] * 3.0  # strong pull: several bounds active, strictly
    return H, g, lo, hi


def test_box_qp_gradcheck_with_active_bounds():
    H, g, lo, hi = _gradcheck_problem()
    res = box_qp(H, g, lo, hi)
    assert int((res.at_lower | res.at_upper).sum()) >= 6
    args = tuple(t.clone().requires_grad_(True) for t in (H, g, lo, hi))
    assert torch.autograd.gradcheck(lambda H, g, lo, hi: box_qp(0.5 * (H + H.mT), g, lo, hi).x, args)


def test_solve_qp_gradcheck_with_active_inequalities():
    H, g, lo, hi = (t[:3] for t in _gradcheck_problem())
    gen = torch.Generator().manual_seed(5)
    G = torch.randn(3, 3, 5, generator=gen, dtype=F64)
    h = torch.rand(3, 3, generator=gen, dtype=F64) * 0.1
    res = solve_qp(H, g, G, h, lo, hi)
    assert int(res.active[:, :3].sum()) >= 2 and int(res.active[:, 3:].sum()) >= 2
    args = tuple(t.clone().requires_grad_(True) for t in (H, g, G, h, lo, hi))
    assert torch.autograd.gradcheck(
        lambda H, g, G, h, lo, hi: solve_qp(0.5 * (H + H.mT), g, G, h, lo, hi).x, args, atol=1e-6,
        fast_mode=True)


# ---------------------------------------------------------------------------------- velocity_step
def _rows(chain, B, seed, K=None):
    gen = torch.Generator().manual_seed(seed)
    q = chain.random_configuration((B,), generator=gen)
    shape = (B, 6) if K is None else (B, K, 6)
    return q, torch.randn(shape, generator=gen, dtype=F64)


@pytest.mark.parametrize("name", ["panda", "ur5", "allegro"])
def test_velocity_step_matches_bvls(name):
    chain = _chain(name)
    K = None if chain.single_end else chain.n_ends
    B, dt, vmax, lam = 150, 0.1, 1.0, 1e-3
    q, twist = _rows(chain, B, 6, K)
    w = torch.tensor([1.0, 1.0, 1.0, 0.3, 0.3, 0.3], dtype=F64)
    weight = w if K is None else w.expand(K, 6)
    qd = ik.velocity_step(chain, q, twist, dt, damping=lam, velocity_limit=vmax, weight=weight)
    J = chain.forward_kinematics_and_jacobian(q)[1]
    J = J.reshape(B, -1, J.shape[-1])
    W = weight.reshape(-1)
    lo, hi = _bounds(chain, q, dt, vmax)
    active = 0
    for i in range(B):
        ref = _bvls((W[:, None] * J[i]).numpy(), (W * twist[i].reshape(-1)).numpy(), lam, lo[i].numpy(),
                    hi[i].numpy())
        np.testing.assert_allclose(qd[i].numpy(), ref, atol=1e-9)
        active += int(((np.abs(ref - lo[i].numpy()) < 1e-12) | (np.abs(ref - hi[i].numpy()) < 1e-12)).sum())
    assert active / B > 1.0  # the limits shape the answer: it is not a plain DLS step


def test_velocity_step_kkt_residuals():
    chain = _chain("panda")
    q, twist = _rows(chain, 400, 7)
    lam, dt = 1e-3, 0.05
    qd = ik.velocity_step(chain, q, twist, dt, damping=lam, velocity_limit=2.0)
    J = chain.forward_kinematics_and_jacobian(q)[1]
    lo, hi = _bounds(chain, q, dt, 2.0)
    r = (J.mT @ (J @ qd[..., None] - twist[..., None]))[..., 0] + lam * qd  # ½∇ of (V.1)
    at_lo, at_hi = qd <= lo, qd >= hi
    free = ~(at_lo | at_hi)
    assert bool(((qd >= lo) & (qd <= hi)).all())
    assert float(r[free].abs().max()) < 1e-10  # stationarity on the free joints
    assert bool((r[at_lo] >= -1e-10).all()) and bool((r[at_hi] <= 1e-10).all())  # multipliers' signs
    assert int((at_lo | at_hi).sum()) > 400


def test_trajectory_never_leaves_the_limits():
    chain = _chain("panda")
    lo_lim, hi_lim = chain.q_limits[:, 0], chain.q_limits[:, 1]
    q = chain.random_configuration((64,), generator=torch.Generator().manual_seed(8))
    twist = torch.tensor([0.4, 0.3, -0.5, 0.0, 0.0, 1.0], dtype=F64).expand(64, 6)  # drives into limits
    dt, vmax = 0.05, torch.tensor([2.0, 2.0, 2.0, 2.0, 2.5, 2.5, 2.5], dtype=F64)
    at_limit = torch.zeros(64, 7, dtype=torch.bool)
    for _ in range(150):
        qd = ik.velocity_step(chain, q, twist, dt, velocity_limit=vmax)
        assert bool((qd.abs() <= vmax).all())
        q = q + qd * dt
        assert bool(((q >= lo_lim - 1e-12) & (q <= hi_lim + 1e-12)).all())
        at_limit |= (q - lo_lim < 1e-9) | (hi_lim - q < 1e-9)
    assert int(at_limit.any(-1).sum()) > 32  # most rows ran into a limit and stayed within it


def test_velocity_step_without_limits_is_the_damped_least_squares_step():
    chain = _chain("ur5")
    q, twist = _rows(chain, 50, 9)
    qd = ik.velocity_step(chain, q, twist, 0.1, damping=1e-2, respect_limits=False)
    J = chain.forward_kinematics_and_jacobian(q)[1]
    ref = ik.dls_delta(J, twist, 1e-2)  # Jᵀ(JJᵀ + λI)⁻¹v, the same λ
    torch.testing.assert_close(qd, ref, atol=1e-10, rtol=0)


def test_posture_task_matches_daqp_and_keeps_the_primary_task():
    chain = _chain("panda")
    B, dt = 60, 0.1
    q, twist = _rows(chain, B, 10)
    twist = 0.3 * twist
    wpos = torch.tensor([1.0, 1.0, 1.0, 0.0, 0.0, 0.0], dtype=F64)  # position only: a 4-D null space
    q_ref = torch.zeros(7, dtype=F64)
    d = torch.tensor([1.0, 2.0, 1.0, 0.5, 1.0, 1.0, 1.0], dtype=F64)
    post = ik.PostureTask(q_ref=q_ref, weight=d, gain=0.5)
    qd1 = ik.velocity_step(chain, q, twist, dt, velocity_limit=1.0, weight=wpos)
    qd = ik.velocity_step(chain, q, twist, dt, velocity_limit=1.0, weight=wpos, tasks=[post])
    J = chain.forward_kinematics_and_jacobian(q)[1][:, :3]
    torch.testing.assert_close(J @ qd[..., None], J @ qd1[..., None], atol=1e-7, rtol=0)
    lo, hi = _bounds(chain, q, dt, 1.0)
    target = 0.5 * (q_ref - q) / dt
    for i in range(B):
        D2 = np.diag(d.numpy() ** 2)
        ref = qpsolvers.solve_qp(D2, -D2 @ target[i].numpy(), A=J[i].numpy(), b=(J[i] @ qd1[i]).numpy(),
                                 lb=lo[i].numpy(), ub=hi[i].numpy(), solver="daqp")
        np.testing.assert_allclose(qd[i].numpy(), ref, atol=1e-5)
    assert float((qd - qd1).abs().max()) > 0.1  # the posture moved the null space


def test_frame_tasks_select_and_weight_end_links():
    chain = _chain("allegro")
    q, twist = _rows(chain, 20, 11, chain.n_ends)
    tasks = [ik.FrameTask(end=1, weight=[1, 1, 1, 0, 0, 0]), ik.FrameTask(end=3, weight=2.0)]
    qd = ik.velocity_step(chain, q, twist, 0.1, velocity_limit=3.0, tasks=tasks)
    W = torch.ones(chain.n_ends, 6, dtype=F64) * 0
    W[1, :3], W[3] = 1.0, 2.0
    ref = ik.velocity_step(chain, q, twist, 0.1, velocity_limit=3.0, weight=W)
    torch.testing.assert_close(qd, ref, atol=1e-12, rtol=0)


def test_velocity_step_gradients_finite_differences_and_gradcheck():
    chain = _chain("panda")
    q, twist = _rows(chain, 4, 12)
    q[0, 3] = chain.q_limits[3, 1] - 0.01  # near a limit: its bound active
    vmax = torch.full((7,), 0.8, dtype=F64)
    w = torch.tensor([1.0, 1.0, 1.0, 0.5, 0.5, 0.5], dtype=F64)

    def f(q, twist, vmax, w, lam=None):
        lam = torch.tensor(1e-2, dtype=F64) if lam is None else lam
        return ik.velocity_step(chain, q, twist, 0.1, damping=lam, velocity_limit=vmax, weight=w)

    qd = f(q, twist, vmax, w)
    lo, hi = _bounds(chain, q, 0.1, vmax)
    n_active = int(((qd - lo).abs() < 1e-12).sum() + ((qd - hi).abs() < 1e-12).sum())
    assert n_active >= 3
    args = (q.clone().requires_grad_(True), twist.clone().requires_grad_(True),
            vmax.clone().requires_grad_(True), w.clone().requires_grad_(True),
            torch.tensor(1e-2, dtype=F64, requires_grad=True))
    assert torch.autograd.gradcheck(f, args, atol=1e-6)
    # the derivative w.r.t. q by central differences, direction by direction
    qg = q.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad((f(qg, twist, vmax, w) ** 2).sum(), qg)
    h = 1e-6
    for j in range(7):
        e = torch.zeros_like(q)
        e[:, j] = h
        fd = ((f(q + e, twist, vmax, w) ** 2).sum(-1) - (f(q - e, twist, vmax, w) ** 2).sum(-1)) / (2 * h)
        torch.testing.assert_close(grad[:, j], fd, atol=1e-5, rtol=1e-5)


def test_posture_gradcheck():
    chain = _chain("panda")
    q, twist = _rows(chain, 2, 13)
    wpos = torch.tensor([1.0, 1.0, 1.0, 0.0, 0.0, 0.0], dtype=F64)

    def f(q, twist, q_ref):
        return ik.velocity_step(chain, q, twist, 0.1, velocity_limit=1.0, weight=wpos,
                                tasks=[ik.PostureTask(q_ref=q_ref, weight=1.0)])

    args = (q.requires_grad_(True), (0.2 * twist).requires_grad_(True),
            torch.zeros(7, dtype=F64).requires_grad_(True))
    assert torch.autograd.gradcheck(f, args, atol=1e-5)


def test_float32_and_batch_shapes():
    c64, c32 = _chain("panda"), _chain("panda", torch.float32)
    q, twist = _rows(c64, 6, 14)
    q, twist = q.reshape(2, 3, 7), twist.reshape(2, 3, 6)
    qd = ik.velocity_step(c64, q, twist, 0.1, velocity_limit=1.0)
    assert qd.shape == (2, 3, 7)
    qd32 = ik.velocity_step(c32, q.float(), twist.float(), 0.1, velocity_limit=1.0)
    assert qd32.dtype == torch.float32
    assert float((qd32.double() - qd).abs().max()) < 1e-4
    post64 = [ik.PostureTask(q_ref=torch.zeros(7, dtype=F64))]  # the interior point runs in float64 inside
    post32 = [ik.PostureTask(q_ref=torch.zeros(7))]
    p64 = ik.velocity_step(c64, q, twist, 0.1, velocity_limit=1.0, weight=[1, 1, 1, 0, 0, 0], tasks=post64)
    p32 = ik.velocity_step(c32, q.float(), twist.float(), 0.1, velocity_limit=1.0, weight=[1, 1, 1, 0, 0, 0],
                           tasks=post32)
    assert p32.dtype == torch.float32 and p32.shape == (2, 3, 7)
    assert float((p32.double() - p64).abs().max()) < 1e-3
    one = ik.velocity_step(c64, q[1, 2], twist[1, 2], 0.1, velocity_limit=1.0)
    assert one.shape == (7,)
    torch.testing.assert_close(one, qd[1, 2], atol=1e-12, rtol=0)
    # a twist broadcast over a batch of q
    qb = ik.velocity_step(c64, q, twist[0, 0], 0.1, velocity_limit=1.0)
    torch.testing.assert_close(qb[1, 2], ik.velocity_step(c64, q[1, 2], twist[0, 0], 0.1, velocity_limit=1.0))


def test_rows_outside_the_limits_move_back_at_the_velocity_limit():
    chain = _chain("panda")
    q = torch.tensor([0.0, -0.5, 0.0, 0.1, 0.0, 1.5, 0.5], dtype=F64)  # joint 4 above its limit -0.0698
    qd = ik.velocity_step(chain, q, torch.zeros(6, dtype=F64), 0.01, velocity_limit=0.5)
    assert float(qd[3]) == pytest.approx(-0.5)


def test_typed_errors():
    chain = _chain("panda")
    q, tw = torch.zeros(7, dtype=F64), torch.zeros(6, dtype=F64)
    with pytest.raises(ShapeError, match=r"\(\.\.\., 6\)"):
        ik.velocity_step(chain, q, torch.zeros(3, dtype=F64), 0.1)
    with pytest.raises(ShapeError, match="7"):
        ik.velocity_step(chain, torch.zeros(6, dtype=F64), tw, 0.1)
    with pytest.raises(DiffkinError, match="dt"):
        ik.velocity_step(chain, q, tw, -0.1)
    with pytest.raises(DiffkinError, match="velocity_limit"):
        ik.velocity_step(chain, q, tw, 0.1, velocity_limit=-1.0)
    with pytest.raises(DiffkinError, match="damping"):
        ik.velocity_step(chain, q, tw, 0.1, damping=0.0)
    with pytest.raises(ShapeError, match="velocity_limit"):
        ik.velocity_step(chain, q, tw, 0.1, velocity_limit=torch.ones(3, dtype=F64))
    with pytest.raises(ShapeError, match="weight"):
        ik.velocity_step(chain, q, tw, 0.1, weight=torch.ones(4, dtype=F64))
    with pytest.raises(ShapeError, match="broadcast"):
        ik.velocity_step(chain, torch.zeros(3, 7, dtype=F64), tw, 0.1, damping=torch.ones(4, dtype=F64))
    with pytest.raises(ShapeError, match="end"):
        ik.velocity_step(chain, q, tw, 0.1, tasks=[ik.FrameTask(end=1)])
    with pytest.raises(ConventionError, match="FrameTask or PostureTask"):
        ik.velocity_step(chain, q, tw, 0.1, tasks=["posture"])
    with pytest.raises(DiffkinError, match="lower <= upper"):
        box_qp(torch.eye(2), torch.zeros(2), torch.ones(2), torch.zeros(2))
    with pytest.raises(ShapeError, match="H"):
        solve_qp(torch.eye(3), torch.zeros(2))


@pytest.mark.cuda
def test_velocity_step_cuda_matches_cpu():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA")
    chain = _chain("panda")
    q, twist = _rows(chain, 256, 15)
    cpu = ik.velocity_step(chain, q, twist, 0.1, velocity_limit=1.0,
                           tasks=[ik.PostureTask(q_ref=torch.zeros(7, dtype=F64))])
    gpu = ik.velocity_step(chain.to("cuda"), q.cuda(), twist.cuda(), 0.1, velocity_limit=1.0,
                           tasks=[ik.PostureTask(q_ref=torch.zeros(7, dtype=F64, device="cuda"))])
    torch.testing.assert_close(gpu.cpu(), cpu, atol=1e-8, rtol=0)


# ------------------------------------------------------------------------------------------- users
def _circle(chain, q0, S, dt):
    T0 = chain.forward_kinematics(q0)
    t = torch.arange(S + 1, dtype=F64) * dt
    x = T0[:3, 3] + torch.stack([0.3 * torch.sin(t), 0.0 * t, 0.3 * (1 - torch.cos(t))], -1)
    v = torch.stack([0.3 * torch.cos(t), 0 * t, 0.3 * torch.sin(t)], -1)
    return x, v


def test_clik_limits_stays_within_the_limits_and_steps_by_velocity_step():
    chain = _chain("panda")
    q0 = torch.tensor([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8], dtype=F64)
    dt = 0.01
    x, v = _circle(chain, q0, 300, dt)
    free = ik.clik(chain, (x, v), q0, dt, algorithm="dls", orientation=None)
    assert not bool(chain.within_limits(free.q).all())  # the plain DLS law runs through a limit
    res = ik.clik(chain, (x, v), q0, dt, algorithm="dls", orientation=None, limits=True, qdot_max=2.0)
    assert bool(chain.within_limits(res.q).all()) and float(res.qdot.abs().max()) <= 2.0
    for k in (0, 100, 250):  # each step is velocity_step's for the CLIK reference ẋ_d + K e (3.70)
        ref = v[k] + 0.5 / dt * res.error[k]
        step = ik.velocity_step(chain, res.q[k], torch.cat((ref, torch.zeros(3, dtype=F64))), dt,
                                damping=1e-4, velocity_limit=2.0, weight=[1, 1, 1, 0, 0, 0])
        torch.testing.assert_close(res.qdot[k], step, atol=1e-10, rtol=0)
    with pytest.raises(ConventionError, match="limits=True"):
        ik.clik(chain, (x, v), q0, dt, algorithm="pseudo_inverse", orientation=None, limits=True)


def test_env_cartesian_action_is_limit_safe():
    from diffkin.envs.robot import Robot

    robot = Robot("panda", action_mode="cartesian", dtype=F64)
    q = robot.home.expand(32, 7).clone()
    q[:, 3] = robot.chain.q_limits[3, 1] - 0.02  # the elbow next to its upper limit
    action = torch.tensor([0.0, 0.0, -1.0], dtype=F64).expand(32, 3)  # down: folds the elbow further
    for _ in range(40):
        dq = robot.cartesian_delta(q, action * robot.config.max_ee_step)
        assert bool(robot.chain.within_limits(q + dq, tol=1e-12).all())  # no clamp needed
        assert float(dq.abs().max()) <= robot.step_limit + 1e-12
        q = robot.apply_action(q, action)
    lim = robot.chain.q_limits
    assert int((torch.minimum(q - lim[:, 0], lim[:, 1] - q).amin(0) < 1e-9).sum()) >= 2  # limits reached
    twist = torch.cat((action * robot.config.max_ee_step / robot.config.control_dt,
                       torch.zeros(32, 3, dtype=F64)), -1)
    ref = ik.velocity_step(robot.chain, q, twist, robot.config.control_dt, damping=robot.config.damping,
                           velocity_limit=robot.config.max_joint_speed, weight=[1, 1, 1, 0, 0, 0])
    torch.testing.assert_close(robot.cartesian_delta(q, action * robot.config.max_ee_step),
                               ref * robot.config.control_dt)


def test_box_qp_masked_iterations_match_the_compacted_ones():
    """The CUDA schedule (all rows masked, a sync every 4 iterations) run on CPU gives the same answer."""
    from diffkin.ik.qp import _box_solve

    A, b, lo, hi = _random_problem(200, 6, 7, 16)
    H = A.mT @ A + 1e-3 * torch.eye(7, dtype=F64)
    g = (A.mT @ b[..., None])[..., 0]
    x1, l1, u1, ok1 = _box_solve(H, g, lo, hi, 36, compact=True)
    x2, l2, u2, ok2 = _box_solve(H, g, lo, hi, 36, compact=False)
    assert bool(ok1.all()) and bool(ok2.all())
    torch.testing.assert_close(x1, x2, atol=1e-12, rtol=0)
    assert bool((l1 == l2).all()) and bool((u1 == u2).all())


def test_velocity_dampers_as_extra_inequalities_match_daqp():
    """(V.1)-(V.2) plus distance-rate rows as the collision issue will add them: the flange may approach
    a plane below it (normal +z, distance d) at most at ξ d/Δt, n_zᵀ J_p q̇ ≥ −ξ d/Δt (a velocity damper)."""
    chain = _chain("panda")
    q, twist = _rows(chain, 80, 17)
    dt, lam, vmax = 0.1, 1e-3, 1.0
    _, J = chain.forward_kinematics_and_jacobian(q)
    d = 0.01 + 0.04 * torch.rand(80, generator=torch.Generator().manual_seed(18), dtype=F64)
    G = -J[:, 2:3, :]  # −n_zᵀ J_p q̇ ≤ ξ d/Δt
    h = (0.5 * d / dt)[:, None]
    H = J.mT @ J + lam * torch.eye(7, dtype=F64)
    g = (J.mT @ twist[..., None])[..., 0]
    lo, hi = _bounds(chain, q, dt, vmax)
    res = solve_qp(H, g, G, h, lo, hi)
    assert bool(res.converged.all()) and int(res.active[:, 0].sum()) > 5  # the damper shapes some rows
    for i in range(80):
        ref = qpsolvers.solve_qp(H[i].numpy(), -g[i].numpy(), G[i].numpy(), h[i].numpy(), lb=lo[i].numpy(),
                                 ub=hi[i].numpy(), solver="daqp")
        np.testing.assert_allclose(res.x[i].numpy(), ref, atol=1e-8)


def test_box_qp_rows_stopped_early_are_still_feasible():
    A, b, lo, hi = _random_problem(300, 6, 7, 19)
    H = A.mT @ A + 1e-3 * torch.eye(7, dtype=F64)
    g = 5.0 * (A.mT @ b[..., None])[..., 0]
    res = box_qp(H, g, lo, hi, max_iter=1)
    assert not bool(res.converged.all())  # some rows needed more iterations
    assert bool(((res.x >= lo) & (res.x <= hi)).all())


def _fr3_collision():
    import warnings

    from diffkin.collision import RobotCollision

    srdf = ('<robot name="fr3"><disable_collisions link1="fr3_link1_sc" link2="fr3_link3_sc" '
            'reason="Default"/></robot>')
    path = Path(__file__).parent / "data" / "urdf" / "fr3.urdf"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the FR3's mesh geoms are not shipped: skipped with a warning
        chain = models.from_urdf(path, "fr3_link8", dtype=F64).requires_grad_(False)
        return chain, RobotCollision.from_urdf(path, chain, srdf=srdf).requires_grad_(False)


def test_collision_dampers_match_daqp_and_keep_the_margin():
    """velocity_step(collision=, world=) against daqp on the same QP, its damper rows built here by central
    differences of the distances; a flange pushed down onto a sphere stops at the margin."""
    from diffkin.collision import World

    chain, col = _fr3_collision()
    q = chain.random_configuration(60, generator=torch.Generator().manual_seed(21))
    with torch.no_grad():
        q = q[col.self_distances(q).amin(-1) > 0.02][:6]  # start clear of self-contact
        T = chain.forward_kinematics(q)
    assert q.shape[0] == 6
    centre = T[:, :3, 3] + torch.tensor([0.0, 0.0, -0.25], dtype=F64)
    world = World(spheres=torch.cat((centre, torch.full((6, 1), 0.04, dtype=F64)), -1).unsqueeze(-2))
    twist = torch.zeros(6, 6, dtype=F64)
    twist[:, 2] = -0.5
    dt, vmax, lam, margin, detection, gain = 0.02, 2.0, 1e-3, 0.005, 0.3, 0.85
    kw = dict(damping=lam, velocity_limit=vmax, collision=col, world=world, collision_margin=margin,
              collision_detection=detection, collision_gain=gain)
    qd = ik.velocity_step(chain, q, twist, dt, **kw)

    def dist(qq, i):
        w = World(spheres=world.spheres[i])
        return torch.cat((col.self_distances(qq), col.world_distances(qq, w).flatten(-2)), -1)

    J = chain.forward_kinematics_and_jacobian(q)[1]
    lo, hi = _bounds(chain, q, dt, vmax)
    active = 0
    for i in range(6):
        with torch.no_grad():
            d = dist(q[i], i)
            eps = 1e-6
            Jd = torch.stack([(dist(q[i] + eps * e, i) - dist(q[i] - eps * e, i)) / (2 * eps)
                              for e in torch.eye(7, dtype=F64)], -1)
        rows = d < detection
        active += int(rows.sum())
        G = np.vstack((-Jd[rows].numpy(), np.eye(7), -np.eye(7)))
        h = np.concatenate((gain * (d[rows] - margin).numpy() / dt, hi[i].numpy(), -lo[i].numpy()))
        P = (J[i].T @ J[i]).numpy() + lam * np.eye(7)
        ref = qpsolvers.solve_qp(P, -(J[i].T @ twist[i]).numpy(), G, h, solver="daqp")
        assert ref is not None, f"row {i}: daqp found the QP infeasible"
        np.testing.assert_allclose(qd[i].numpy(), ref, atol=1e-6)
    assert active > 0  # the dampers are in play
    qq = q[:1].clone()
    one = World(spheres=world.spheres[:1])
    for _ in range(50):
        qq = qq + dt * ik.velocity_step(chain, qq, twist[:1], dt, **{**kw, "world": one})
        with torch.no_grad():
            assert float(col.world_distances(qq, one).min()) >= margin - 1e-6
            assert float(col.self_distances(qq).min()) >= min(margin, float(col.self_distances(q[:1]).min()))
    with pytest.raises(DiffkinError, match="collision model"):
        ik.velocity_step(chain, q, twist, dt, world=world)
