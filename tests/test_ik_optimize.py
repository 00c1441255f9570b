"""diffkin.ik.optimization: optimisation-based IK with composable cost terms (L-BFGS, Adam, Gauss–Newton).

Honesty is checked with an independent FK (one configuration at a time) and scipy's rotation angle.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from diffkin.errors import ConventionError, ShapeError
from diffkin.ik.optimization import (
    JointLimitCost,
    ManipulabilityCost,
    PoseCost,
    RestPostureCost,
    optimize,
)
from diffkin.manipulability import manipulability
from diffkin.models import load

F64 = torch.float64


@pytest.fixture(scope="module")
def panda():
    return load("panda", dtype=F64)


def near_targets(chain, B, noise, seed=0):
    g = torch.Generator().manual_seed(seed)
    q = chain.random_configuration(B, generator=g)
    with torch.no_grad():
        T = chain.forward_kinematics(q)
    q0 = chain.clamp_to_limits(q + noise * torch.randn(q.shape, generator=g, dtype=q.dtype))
    return q, T, q0


def check_honest(chain, res, T, tol_p, tol_o):
    q = res.q.detach()
    assert torch.isfinite(q).all()
    assert chain.within_limits(q).all()
    for qi, Ti, ok, pe_r in zip(q, T, res.success, res.position_error):
        with torch.no_grad():
            Te = chain.forward_kinematics(qi)
        pe = float(torch.linalg.norm(Te[:3, 3] - Ti[:3, 3]))
        oe = Rotation.from_matrix(Te[:3, :3].numpy().T @ Ti[:3, :3].numpy()).magnitude()
        assert bool(ok) == (pe <= tol_p and oe <= tol_o)
        assert abs(pe - float(pe_r)) < 1e-9


@pytest.mark.parametrize(
    "optimizer, kwargs, tol, rate",
    [
        ("gauss_newton", {}, (1e-4, 1e-3), 1.0),
        ("lbfgs", {"max_iterations": 20}, (1e-4, 1e-3), 0.9),
        ("adam", {"max_iterations": 400}, (1e-3, 1e-2), 0.9),
    ],
)
def test_optimizers_converge_on_easy_targets(panda, optimizer, kwargs, tol, rate):
    _, T, q0 = near_targets(panda, 20, 0.1, seed=1)
    res = optimize(panda, T, q0, optimizer=optimizer, position_tolerance=tol[0], orientation_tolerance=tol[1],
                   **kwargs)  # fmt: skip
    assert res.q.shape == (20, 7) and res.success.shape == (20,)
    assert res.success.double().mean() >= rate
    check_honest(panda, res, T, *tol)


def test_rest_posture_pulls_the_redundant_dof(panda):
    _, T, q0 = near_targets(panda, 20, 0.1, seed=2)
    rest = torch.zeros(7, dtype=F64).clamp(*panda.lower_upper())
    plain = optimize(panda, T, q0, optimizer="gauss_newton")
    pulled = optimize(panda, T, q0, optimizer="gauss_newton", max_iterations=100,
                      costs=[PoseCost(), RestPostureCost(weight=1e-8, q_rest=rest)])  # fmt: skip
    d_plain = torch.linalg.norm(plain.q - rest, dim=-1)
    d_pulled = torch.linalg.norm(pulled.q - rest, dim=-1)
    assert (d_pulled < d_plain - 1e-3).double().mean() >= 0.8  # moved along the self-motion manifold
    assert (pulled.position_error < 1e-3).all() and (pulled.orientation_error < 1e-2).all()


def test_manipulability_and_custom_terms(panda):
    _, T, q0 = near_targets(panda, 10, 0.05, seed=3)
    start = optimize(panda, T, q0, optimizer="gauss_newton")
    w0 = manipulability(panda.geometric_jacobian(start.q)).detach()
    res = optimize(panda, T, start.q, optimizer="lbfgs", max_iterations=10,
                   costs=[PoseCost(), ManipulabilityCost(weight=3e-5)])  # fmt: skip
    w1 = manipulability(panda.geometric_jacobian(res.q)).detach()
    assert w1.mean() > w0.mean()
    assert (res.position_error < 2e-3).all()
    # a user callable: pull joint 1 toward 0.3 rad, and nothing else (no pose term)
    res2 = optimize(panda, T, q0, optimizer="lbfgs", max_iterations=5,
                    costs=[lambda q, T: (q[..., 0] - 0.3) ** 2])  # fmt: skip
    torch.testing.assert_close(res2.q[:, 0], torch.full((10,), 0.3, dtype=F64), atol=1e-6, rtol=0)
    torch.testing.assert_close(res2.q[:, 1:], q0[:, 1:])


def test_joint_limit_cost_keeps_away_from_limits(panda):
    """The cost (not the projection onto the limits) moves joints out of the margin: the same solve without
    it (respect_limits=False, so nothing else acts) leaves them where they start, inside the margin."""
    lo, hi = panda.lower_upper()
    margin = 0.2
    g = torch.Generator().manual_seed(4)
    q0 = panda.random_configuration(10, generator=g)
    q0[:, 3] = hi[3] - 0.05  # joint 4 within the margin of its upper limit, joint 1 of its lower one
    q0[:, 0] = lo[0] + 0.02
    with torch.no_grad():
        T = panda.forward_kinematics(q0)
    costs = [PoseCost(weight=1.0), JointLimitCost(weight=100.0, margin=margin)]
    kw = dict(optimizer="gauss_newton", max_iterations=40, respect_limits=False)
    res = optimize(panda, T, q0, costs=costs, **kw)
    plain = optimize(panda, T, q0, costs=[PoseCost(weight=1.0)], **kw)
    q, qp = res.q.detach(), plain.q.detach()

    def depth(x):  # how far into the margins: 0 when every joint is at least `margin` from its limits
        return (torch.relu(lo + margin - x) + torch.relu(x - (hi - margin))).amax(-1)

    assert (depth(qp) > 0.1).all()  # the target is met at q0 already: no reason to move
    assert (depth(q) < 0.5 * depth(q0)).all()  # the cost pushed the joints out of the margin
    assert (depth(q) < depth(qp) - 0.05).all()


def test_position_only_and_batch_shapes(panda):
    _, T, q0 = near_targets(panda, 6, 0.1, seed=5)
    T2, q02 = T.reshape(2, 3, 4, 4), q0.reshape(2, 3, 7)
    res = optimize(panda, T2[..., :3, 3], q02, optimizer="gauss_newton", position_only=True)
    assert res.q.shape == (2, 3, 7) and res.success.shape == (2, 3)
    assert res.success.all() and (res.orientation_error == 0).all()
    res0 = optimize(panda, T[0], q0[0], optimizer="gauss_newton")
    assert res0.q.shape == (7,) and res0.success.shape == () and bool(res0.success)


def test_float32_chain():
    chain = load("ur5", dtype=torch.float32)
    _, T, q0 = near_targets(chain, 10, 0.1, seed=6)
    res = optimize(chain, T, q0, optimizer="gauss_newton", position_tolerance=1e-3,
                   orientation_tolerance=1e-2)  # fmt: skip
    assert res.q.dtype == torch.float32 and res.success.all()
    assert np.isfinite(res.q.detach().numpy()).all()  # q is differentiable (implicit gradients)


def test_bad_inputs(panda):
    _, T, q0 = near_targets(panda, 4, 0.1, seed=7)
    with pytest.raises(ConventionError, match="optimizer"):
        optimize(panda, T, q0, optimizer="sgd")
    with pytest.raises(ConventionError, match="residual"):
        optimize(panda, T, q0, optimizer="gauss_newton", costs=[ManipulabilityCost()])
    with pytest.raises(ConventionError, match="cost terms"):
        optimize(panda, T, q0, costs=[3.0])
    with pytest.raises(ShapeError):
        optimize(panda, T, q0[:, :6])
