"""``ik.optimize(optimizer="gauss_newton", collision=, world=)``: the distances are constraints of every
step (not a penalty): an obstacle placed on the unconstrained solution's elbow is cleared by moving in the
null space, the result is checked by coal (Pinocchio's placements), and the implicit gradient at the active
constraint (a KKT point) equals central differences of the solver."""

from __future__ import annotations

import pytest
import torch

from diffkin import ik
from diffkin.collision import World
from tests.helpers import CoalCheck, fr3_robot

pytest.importorskip("pinocchio")

F64 = torch.float64
COSTS = [ik.PoseCost(), ik.RestPostureCost(weight=1e-2)]  # a unique local minimiser
KW = dict(costs=COSTS, optimizer="gauss_newton", max_iterations=300, tolerance_change=0.0)


def _blocked_elbow():
    """(chain, rc, q_u, T, world): q_u minimises pose + rest posture for T without obstacles; the world's
    one sphere, centred out from the elbow (frame 4) where its centre is 3 cm or more clear of the arm,
    reaches 1 cm into q_u's geometry."""
    chain, rc = fr3_robot(F64)
    q_t = torch.tensor([0.3, 0.4, -0.2, -1.9, 0.1, 2.0, 0.6], dtype=F64)
    T = chain.forward_kinematics(q_t)
    q_u = ik.optimize(chain, T, q_t, **KW).q.detach()
    with torch.no_grad():
        elbow = chain.forward_kinematics(q_u, all_frames=True)[4, :3, 3]
        out = torch.tensor([elbow[0], elbow[1], 0.0], dtype=F64)
        for reach in torch.arange(0.1, 0.4, 0.01, dtype=F64):
            centre = elbow + reach * out / out.norm()
            point = World(points=centre[None])  # the centre's clearance
            clear = rc.world_distances(q_u, point).min()
            if clear >= 0.03:
                break
        assert clear >= 0.03
        world = World(spheres=torch.cat((centre, (clear + 0.01).reshape(1)))[None])
        assert float(rc.world_distances(q_u, world).min()) == pytest.approx(-0.01, abs=1e-9)
    return chain, rc, q_u, T, world


def test_constraints_clear_an_obstacle_on_the_unconstrained_solution():
    chain, rc, q_u, T, world = _blocked_elbow()
    margin = 0.005
    kw = {**KW, "costs": [ik.PoseCost()]}  # the pose alone: its solutions are a manifold, clear ones too
    assert not bool(ik.optimize(chain, T, q_u, **kw).success & (rc.world_distances(q_u, world).min() >= 0))
    res = ik.optimize(chain, T, q_u, collision=rc, world=world, margin=margin, **kw)
    assert bool(res.success)
    check = CoalCheck(rc, with_box=False)
    check.obstacles = [(check.obstacles[0][0].__class__(float(world.spheres[0, 3])),
                        _placement(world.spheres[0, :3]))]
    assert check.min_distance(res.q.detach().numpy()) >= margin - 1e-9
    assert check.min_self_distance(res.q.detach().numpy()) >= margin - 1e-9
    assert float(res.position_error) <= 1e-4 and float(res.orientation_error) <= 1e-3


def _placement(c):
    import collision_reference as ref

    return ref.placement(None, c.numpy())


def test_kkt_gradient_at_the_active_constraint_matches_finite_differences():
    chain, rc, q_u, T, world = _blocked_elbow()
    kw = dict(collision=rc, world=world, margin=0.005, **KW)
    q_c = ik.optimize(chain, T, q_u, **kw).q.detach()
    # held at the boundary (margin + the QP's slack): the constraint is what stops the rest-posture pull
    assert float(rc.world_distances(q_c, world).min()) == pytest.approx(0.005 + 1e-4, abs=2e-5)
    v = torch.linspace(-1.0, 1.0, 7, dtype=F64)
    Tg = T.clone().requires_grad_(True)
    (g,) = torch.autograd.grad((ik.optimize(chain, Tg, q_c, **kw).q * v).sum(), Tg)
    Tg2 = T.clone().requires_grad_(True)
    (g_free,) = torch.autograd.grad((ik.optimize(chain, Tg2, q_c, **KW).q * v).sum(), Tg2)
    eps = 1e-4  # (smaller steps meet the solver's stopping noise: 1e-6 is 2 % off)
    fds = []
    for i in range(3):  # the translation entries; the constraint stays active at T ± eps
        E = torch.zeros_like(T)
        E[i, 3] = eps
        with torch.no_grad():
            dq = ik.optimize(chain, T + E, q_c, **kw).q - ik.optimize(chain, T - E, q_c, **kw).q
        fd = float((dq * v).sum()) / (2 * eps)
        assert abs(fd - float(g[i, 3])) <= 1e-3 * max(1.0, abs(fd)), (i, fd, float(g[i, 3]))
        fds.append(fd)
    # the gradient of the unconstrained stationary point is far off here (the constraint matters)
    fds = torch.tensor(fds, dtype=F64)
    off = (fds - g_free[:3, 3]).norm() / fds.norm()
    assert off > 0.2
