"""motion.plan's optimisation stage (diffkin.motion.optimize) on the FR3 among two spheres: the optimised
plan re-checked by Pinocchio + coal and against its limits, and the implicit gradient of the optimised knots
(and of the sampled trajectory, the timing held fixed) w.r.t. the start, the goal and a sphere's centre,
against central differences of warm-started re-optimisations (float64)."""

from __future__ import annotations

import pytest
import torch

from diffkin import motion
from diffkin.collision import World
from diffkin.errors import ConventionError, OptionError
from diffkin.motion.optimize import OptimizeConfig, optimize_knots, sample_with
from diffkin.sampling import random_configuration
from tests.helpers import SPHERES, CoalCheck, fr3_robot

pytest.importorskip("pinocchio")
V = [2.0, 1.0, 1.5, 1.25, 3.0, 1.5, 3.0]  # fr3.urdf's <limit velocity=>
A = 10.0
CFG = OptimizeConfig(knots=16)
MARGIN, ETA = 0.005, 0.01


@pytest.fixture(scope="module")
def planned():
    """One FR3 problem whose optimised path holds distance rows at the boundary, planned with gradients."""
    d = torch.float64
    chain, rc = fr3_robot(d)
    sph = torch.tensor(SPHERES, dtype=d)
    q = random_configuration(chain, (6,), torch.Generator().manual_seed(3), collision=rc,
                             world=World(spheres=sph), margin=0.02)
    qs, qg, s = q[:1].clone().requires_grad_(), q[3:4].clone().requires_grad_(), sph.clone().requires_grad_()
    res = motion.plan(chain, qs, qg, collision=rc, world=World(spheres=s), margin=MARGIN,
                      acceleration_limit=A, resolution=ETA, max_iterations=300, optimize=CFG)
    return chain, rc, qs, qg, s, res


@pytest.mark.extended
def test_optimized_plan_is_shorter(planned):
    chain, rc, qs, qg, s, res = planned
    base = motion.plan(chain, qs.detach(), qg.detach(), collision=rc, world=World(spheres=s.detach()),
                       margin=MARGIN, acceleration_limit=A, resolution=ETA, max_iterations=300)
    assert base.success.all() and not base.optimized.any()
    assert res.duration[0] < 0.8 * base.duration[0]  # 1.66 s against 2.39 s


def test_optimized_plan_rechecked_by_coal(planned):
    chain, rc, qs, qg, s, res = planned
    assert res.success.all() and res.optimized.all(), res.reason
    assert res.n_waypoints[0] == CFG.knots + 2 and torch.equal(res.waypoints[0, 0], qs[0].detach())
    assert torch.equal(res.q[0, 0], qs[0].detach()) and torch.equal(res.q[0, -1], qg[0].detach())
    t = torch.arange(0, float(res.duration[0]) + 0.02, 2e-3, dtype=torch.float64)
    st = res.state(t)
    assert (st.velocity.abs() <= torch.tensor(V) * (1 + 1e-9)).all()
    assert (st.acceleration.abs() <= A * (1 + 1e-9)).all()
    lim = chain.q_limits
    assert ((st.position >= lim[:, 0]) & (st.position <= lim[:, 1])).all()
    # the samples held by the result are the timed spline's (the differentiable resampling agrees)
    assert torch.allclose(res.q.detach(), res.sample(res.t[0]), atol=1e-12)
    ref = CoalCheck(rc, with_box=False, moving_only=True)
    idx = torch.linspace(0, t.numel() - 1, 25).long()
    assert min(ref.min_distance(st.position[0, i].numpy()) for i in idx) >= MARGIN - 1e-9


def _replan(rc, knots, qs, qg, s, lim, reach):
    """Knots re-optimised from ``knots`` (warm start) for the perturbed inputs (to steps of 1e-10 rad)."""
    cfg = OptimizeConfig(knots=CFG.knots, tolerance=1e-10)
    out = optimize_knots(rc, World(spheres=s), qs, qg, knots, lim[:, 0], lim[:, 1], MARGIN + ETA + CFG.buffer,
                         reach, cfg, warm=knots)
    assert out.converged.all()
    return out.path


def _check_gradients(planned, which):
    chain, rc, qs, qg, s, res = planned
    knots = res.waypoints.detach()
    lim, reach = chain.q_limits, motion.joint_reach(rc)
    g = torch.Generator().manual_seed(1)
    wk = torch.randn(knots.shape, generator=g, dtype=torch.float64)
    wq = torch.randn(res.q.shape, generator=g, dtype=torch.float64)
    timed, tt = res._timing[0][1], res.t[:, :].to(torch.float64)
    gk = torch.autograd.grad((res.waypoints * wk).sum(), (qs, qg, s), retain_graph=True)
    gq = torch.autograd.grad((res.q * wq).sum(), (qs, qg, s), retain_graph=True)  # the fixture is shared
    # the solution holds distance rows (the KKT part of the gradient is exercised): a sphere moves the path
    assert gk[2][:, :3].abs().max() > 1.0
    eps = 1e-4
    inputs = [qs.detach(), qg.detach(), s.detach()]
    for i in which:
        v = torch.randn(inputs[i].shape, generator=g, dtype=torch.float64)
        if i == 2:
            v[:, 3] = 0.0  # the centres (the radii too are differentiable; the centres are the parameter)
        f = []
        for sign in (1.0, -1.0):
            x = list(inputs)
            x[i] = x[i] + sign * eps * v
            f.append(_replan(rc, knots, *x, lim, reach))
        fd_k = ((f[0] - f[1]) / (2 * eps) * wk).sum()
        q_pm = [sample_with(timed, k, tt)[0] for k in f]
        fd_q = ((q_pm[0] - q_pm[1]) / (2 * eps) * wq).sum()
        for fd, grad in ((fd_k, gk[i]), (fd_q, gq[i])):
            got = (grad * v).sum()
            assert torch.isclose(got, fd, rtol=1e-5, atol=1e-7), (i, float(fd), float(got))


def test_gradients_match_warm_started_replans(planned):
    """d(knots)/d(start, sphere centres) and d(q samples)/d(…) at fixed timing, against central differences
    (ε = 1e-4) of re-optimisations started from the solution, along random directions."""
    _check_gradients(planned, (0, 2))


@pytest.mark.extended
def test_gradients_wrt_the_goal_match_warm_started_replans(planned):
    _check_gradients(planned, (1,))


def test_unconverged_rows_carry_no_gradient(planned):
    """One step from the straight line through the spheres is no KKT point: its interior knots get a zero
    gradient (the ends are the inputs themselves)."""
    chain, rc, qs, qg, s, res = planned
    lim = chain.q_limits
    line = torch.stack((qs.detach(), qg.detach()), 1)
    s1 = s.detach().clone().requires_grad_(True)
    q1 = qs.detach().clone().requires_grad_(True)
    one = OptimizeConfig(knots=8, iterations=1)
    out = optimize_knots(rc, World(spheres=s1), q1, qg.detach(), line, lim[:, 0], lim[:, 1],
                         MARGIN + ETA + CFG.buffer, motion.joint_reach(rc), one)
    assert not out.converged.any()
    gs, gq = torch.autograd.grad(out.path[:, 1:-1].sum(), (s1, q1), allow_unused=True, retain_graph=True)
    assert (gs is None or not gs.any()) and not gq.any()
    assert torch.equal(torch.autograd.grad(out.path[:, 0].sum(), q1)[0], torch.ones_like(q1))


def test_options_are_checked():
    chain, rc = fr3_robot(torch.float64)
    q = torch.zeros(1, 7, dtype=torch.float64)
    with pytest.raises(ConventionError, match="optimize"):
        motion.plan(chain, q, q, collision=rc, acceleration_limit=A, optimize="yes")
    for bad in ({"knots": 0}, {"trust": 0.0}, {"buffer": float("nan")}, {"iterations": 1.5}):
        with pytest.raises(OptionError):
            OptimizeConfig(**bad)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_resample_of_a_zero_length_path_is_its_start(dtype):
    """A path whose start is its goal (length 0 in the bound's metric) resamples to its start, finite in
    float32 too (the segment-length floor was 1e-300, which is 0 in float32: 0/0 knots)."""
    from diffkin.motion.optimize import resample

    start = torch.tensor([[0.1, -0.2, 0.3]], dtype=dtype)
    path = start[:, None].expand(1, 3, 3).contiguous()
    out = resample(path, torch.tensor([0.5, 0.4, 0.3], dtype=dtype), 6)
    assert out.shape == (1, 6, 3) and torch.equal(out, start[:, None].expand(1, 6, 3))
