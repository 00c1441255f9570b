"""Issue 39, ``ik.optimize`` items: Gauss–Newton makes progress or reports failure, and its implicit gradient
is then right (4); a NaN cost is reported (8); options (11) and argument mistakes (21) are typed errors
naming the mistake. References: L-BFGS on the same cost (torch.optim), central finite differences of the
solver."""

from __future__ import annotations

import math

import pytest
import torch

from diffkin.errors import ConventionError, NonFiniteError, NonFiniteOptionError, OptionError, ShapeError
from diffkin.ik.optimization import JointLimitCost, PoseCost, RestPostureCost, _total, optimize
from diffkin.models import load

F64 = torch.float64
COSTS = [PoseCost(), RestPostureCost(1e-3)]


@pytest.fixture(scope="module")
def panda():
    return load("panda", dtype=F64)


def near(chain, B, noise, seed):
    g = torch.Generator().manual_seed(seed)
    q = chain.random_configuration(B, generator=g)
    with torch.no_grad():
        T = chain.forward_kinematics(q)
    return T, chain.clamp_to_limits(q + noise * torch.randn(q.shape, generator=g, dtype=F64))


def cost(chain, q, T):
    with torch.no_grad():
        return _total(chain, COSTS, q.detach(), T)


def test_item04_gauss_newton_makes_progress(panda):
    """The issue's case (PoseCost + RestPostureCost(1e-3), 0.01 rad off): Gauss–Newton used to stop after 5
    rejected steps with q0 unmoved. It now descends to a stationary point of the cost (zero gradient by
    autograd), where the implicit gradient applies."""
    T, q0 = near(panda, 3, 0.01, seed=0)
    gn = optimize(panda, T, q0, optimizer="gauss_newton", costs=COSTS, max_iterations=100)
    c0, c_gn = cost(panda, q0, T), cost(panda, gn.q, T)
    assert (c_gn < c0 - 1e-4).all()  # every sample moved downhill (used to stay at q0)
    q = gn.q.detach().clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(_total(panda, COSTS, q, T).sum(), q)
    assert float(grad.norm(dim=-1).max()) < 1e-6
    # success stays the pose tolerances of the result (the rest posture pulls the pose off by mm here)
    assert torch.equal(gn.success, (gn.position_error <= 1e-4) & (gn.orientation_error <= 1e-3))


def test_item04_gauss_newton_reports_no_progress_as_failure(panda):
    """A budget too small to find an acceptable step: success False (it used to return q0 as it was)."""
    T, q0 = near(panda, 4, 0.01, seed=0)
    plain = optimize(panda, T, q0, optimizer="gauss_newton", costs=COSTS, max_iterations=1)
    unmoved = (plain.q - q0).abs().amax(-1) == 0
    assert unmoved.any()  # the first damped step of a sample is rejected here
    assert not plain.success[unmoved].any()


def test_item04_implicit_gradient_matches_finite_differences(panda):
    """dq*/dT of the converged Gauss–Newton solution equals central differences of the solver (it was 10x
    off while q0 was returned unmoved)."""
    T, q0 = near(panda, 1, 0.01, seed=0)
    kw = dict(optimizer="gauss_newton", costs=COSTS, max_iterations=200, tolerance_change=0.0)
    Tv = T.clone().requires_grad_(True)
    res = optimize(panda, Tv, q0, **kw)
    w = torch.linspace(-1.0, 1.0, 7, dtype=F64)
    (g,) = torch.autograd.grad((res.q * w).sum(), Tv)
    h = 1e-5
    for i, j in ((0, 3), (2, 3)):  # the target position (a rigid perturbation)
        Tp, Tm = T.clone(), T.clone()
        Tp[0, i, j] += h
        Tm[0, i, j] -= h
        qp = optimize(panda, Tp, res.q.detach(), **kw).q
        qm = optimize(panda, Tm, res.q.detach(), **kw).q
        fd = float(((qp - qm).detach() * w).sum()) / (2 * h)
        assert math.isclose(float(g[0, i, j]), fd, rel_tol=2e-3, abs_tol=1e-4), (i, j, float(g[0, i, j]), fd)


def test_item08_nan_cost_is_reported(panda):
    T, q0 = near(panda, 3, 0.1, seed=1)

    def nan_cost(q, T):
        return q.sum(-1) * float("nan")

    with pytest.raises(NonFiniteError, match=r"costs\[1\] \(nan_cost\).*3 of 3"):
        optimize(panda, T, q0, costs=[PoseCost(), nan_cost])
    c = q0[:, 0].clone()

    def trap(q, T):  # finite at q0, NaN 0.02 rad away: the optimiser steps into it
        far = (q[..., 0] - c).abs() > 0.02
        return torch.where(far, torch.full_like(q[..., 0], float("nan")), 0 * q[..., 0])

    for opt in ("lbfgs", "adam"):
        with pytest.raises(NonFiniteError, match=r"during the iterations: costs\[1\] \(trap\)"):
            optimize(panda, T, q0, optimizer=opt, costs=[PoseCost(), trap])


@pytest.mark.parametrize("kwargs, error, needle", [
    (dict(max_iterations=-1), OptionError, "max_iterations"),
    (dict(lr=0), OptionError, "lr"),
    (dict(damping=-1.0, optimizer="gauss_newton"), OptionError, "damping"),
    (dict(damping=float("nan")), NonFiniteOptionError, "damping"),
    (dict(tolerance_change=float("nan")), NonFiniteOptionError, "tolerance_change"),
    (dict(unroll=-1), OptionError, "unroll"),
    (dict(costs=[PoseCost(weight=-1)]), OptionError, "PoseCost.weight"),
    (dict(costs=[JointLimitCost(margin=float("nan"))]), NonFiniteOptionError, "JointLimitCost.margin"),
    (dict(margin=0.1), OptionError, "margin.*collision"),
])
def test_item11_options_are_checked(panda, kwargs, error, needle):
    T, q0 = near(panda, 2, 0.1, seed=2)
    with pytest.raises(error, match=needle):
        optimize(panda, T, q0, **kwargs)
    assert issubclass(error, OptionError)  # one error type for every numeric option


@pytest.mark.parametrize("kwargs, error, needle", [
    (dict(costs=[]), ConventionError, "non-empty"),
    (dict(costs=PoseCost()), ConventionError, r"costs=\[PoseCost"),
    (dict(costs=[lambda q, T: q]), ShapeError, r"costs\[0\].*shape \(2, 7\)"),
    (dict(costs=[PoseCost(), RestPostureCost(q_rest=torch.zeros(3, dtype=F64))]), ShapeError, "q_rest"),
    (dict(costs=[PoseCost(orientation_weight=-1)]), OptionError, "orientation_weight"),
    (dict(max_iterations=1.5), OptionError, "max_iterations"),
    (dict(lr=-1), OptionError, "lr"),
])
def test_item21_argument_mistakes_are_typed_errors(panda, kwargs, error, needle):
    T, q0 = near(panda, 2, 0.1, seed=3)
    with pytest.raises(error, match=needle):
        optimize(panda, T, q0, **kwargs)


def test_item11_valid_options_still_run(panda):
    """The checks refuse only mistakes: 0 damping, unroll=0, weight 0 and lr given all run."""
    T, q0 = near(panda, 2, 0.05, seed=4)
    costs = [PoseCost(), RestPostureCost(weight=0.0)]
    res = optimize(panda, T, q0, optimizer="gauss_newton", damping=0.0, unroll=0, costs=costs)
    with torch.no_grad():
        assert (_total(panda, costs, res.q, T) < _total(panda, costs, q0, T)).all()
    res = optimize(panda, T, q0, optimizer="lbfgs", lr=0.5, max_iterations=30)
    assert torch.isfinite(res.q).all()
