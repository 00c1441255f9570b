"""Collision-free IK: ``ik.solve(..., collision=, world=, margin=)`` re-checked by coal with the geoms placed
by Pinocchio's own URDF parser and FK (never by the code under test), on the Franka FR3 (Panda's successor;
Franka's coarse self-collision model) among a few obstacles."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import diffkin
from diffkin import ik
from diffkin.collision import World, box
from diffkin.errors import DiffkinError, OptionError

pytest.importorskip("pinocchio")
pytest.importorskip("coal")  # the reference distances (tests/collision_reference.py)

from tests.helpers import BOX, FR3, SPHERES, TIGHT, CoalCheck, fr3_robot, moved  # noqa: E402


def _world(dtype, with_box=True):
    b = box(center=torch.tensor(BOX[0], dtype=dtype), half_extents=torch.tensor(BOX[1], dtype=dtype),
            dtype=dtype) if with_box else None
    return World(spheres=torch.tensor(SPHERES, dtype=dtype), boxes=b, dtype=dtype)


def _targets(chain, check: CoalCheck, n: int, seed: int, clear: float = 0.01):
    """Reachable, collision-free targets: FK of random configurations that coal finds clear by ``clear``."""
    lo, hi = chain.q_limits.T.double()
    g = torch.Generator().manual_seed(seed)
    q = lo + (hi - lo) * torch.rand(12 * n, chain.n_joints, dtype=torch.float64, generator=g)
    keep = [qq for qq in q if check.min_distance(qq.numpy()) > clear][:n]
    assert len(keep) == n
    return chain.forward_kinematics(torch.stack(keep).to(chain.dtype))


@pytest.mark.parametrize("dtype,refine", [(torch.float64, 0), (torch.float64, 1), (torch.float32, 0)])
def test_solve_successes_are_collision_free_by_coal(dtype, refine):
    """Every success is within the pose tolerances and clear of every checked pair and obstacle by the margin
    (coal); the success rate stays high; the same solve without collision has successes in collision."""
    chain, rc = fr3_robot(dtype)
    check = CoalCheck(rc)
    T = _targets(chain, check, 40, seed=3)
    margin = 0.005
    cfg = ik.LMConfig(collision_refine_calls=refine)  # re-seeding only, or the constrained refinement too
    res = ik.solve(chain, T, collision=rc, world=_world(dtype), margin=margin, seed=0, config=cfg)
    plain = ik.solve(chain, T, seed=0)
    assert plain.success.all()
    d_plain = np.array([check.min_distance(q) for q in plain.q.double().numpy()])
    assert (d_plain < margin).any()  # the problem is not trivial: plain IK ends in collision
    assert res.success.float().mean() >= 0.95
    d = np.array([check.min_distance(q) for q in res.q.double().numpy()])
    ok = res.success.numpy()
    tol = 1e-9 if dtype == torch.float64 else 2e-6
    assert (d[ok] >= margin - tol).all(), d[ok].min()
    T_e = chain.double().forward_kinematics(res.q.double()) if dtype == torch.float64 else \
        diffkin.models.from_urdf(FR3, "fr3_link8", dtype=torch.float64).forward_kinematics(res.q.double())
    pos = (T_e[..., :3, 3] - T.double()[..., :3, 3]).norm(dim=-1)
    assert (pos[res.success] <= 1e-4 + 1e-7).all()


def test_success_is_never_claimed_in_collision():
    """Targets reachable only in collision (the flange inside an obstacle grown to cover it) come back
    unsuccessful, and every success is clear by coal, with self-collision only (no world)."""
    chain, rc = fr3_robot(torch.float64)
    check = CoalCheck(rc, with_box=False)
    T = _targets(chain, check, 12, seed=5)
    p = T[:6, :3, 3]
    inside = World(spheres=torch.cat((p, torch.full((6, 1), 0.05, dtype=torch.float64)), -1))
    res = ik.solve(chain, T[:6], collision=rc, world=inside, seed=1, num_seeds=8)
    assert not res.success.any()
    res = ik.solve(chain, T[6:], collision=rc, margin=0.01, seed=1)
    assert res.success.all()
    assert min(check.min_distance(q) for q in res.q.reshape(-1, 7).numpy()) >= 0.0
    assert min(check.min_self_distance(q) for q in res.q.numpy()) >= 0.01 - 1e-9




def test_collision_arguments_are_checked():
    chain, rc = fr3_robot(torch.float64)
    T = chain.forward_kinematics(torch.zeros(7, dtype=torch.float64))
    with pytest.raises(DiffkinError, match="collision model"):
        ik.solve(chain, T, world=_world(torch.float64))
    with pytest.raises(DiffkinError, match="RobotCollision"):
        ik.solve(chain, T, collision="fr3")
    with pytest.raises(OptionError, match="margin"):
        ik.solve(chain, T, collision=rc, margin=-1.0)
    with pytest.raises(DiffkinError, match="one world"):
        ik.solve(chain, T, collision=rc, world=World(spheres=torch.zeros(2, 1, 4, dtype=torch.float64)))


def test_batched_targets_and_gradients_with_collision():
    """A (2, 3) batch keeps its shape and every target is solved clear of collisions (coal); d(w·q*)/dξ
    (ξ a base-frame twist of every target) by the implicit backward equals central differences of
    warm-started collision-aware re-solves (the targets' distances are clear: no constraint is active).
    The FR3 is redundant, so a re-solve may move along the self-motion manifold: w = Jᵀv lies in J's row
    space, where that motion does not count (w·N = 0), and both then equal v (J D = I)."""

    chain, rc = fr3_robot(torch.float64)
    check, world = CoalCheck(rc), _world(torch.float64)
    T = _targets(chain, check, 6, seed=7).reshape(2, 3, 4, 4)
    xi = torch.zeros(2, 3, 6, dtype=torch.float64, requires_grad=True)
    res = ik.solve(chain, moved(T, xi), collision=rc, world=world, seed=0, **TIGHT)
    assert res.q.shape == (2, 3, 7) and res.success.shape == (2, 3)
    assert res.success.all() and res.q.grad_fn is not None
    assert min(check.min_distance(q) for q in res.q.detach().reshape(-1, 7).numpy()) >= 0.0
    v = torch.randn(2, 3, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    J = chain.geometric_jacobian(res.q.detach()).detach()  # (2, 3, 6, 7)
    w = (J.mT @ v.unsqueeze(-1)).squeeze(-1)
    (res.q * w).sum().backward()
    h, q_star, fd = 1e-4, res.q.detach(), torch.zeros(2, 3, 6, dtype=torch.float64)
    for k in range(6):
        d = torch.zeros(2, 3, 6, dtype=torch.float64)
        d[..., k] = h
        with torch.no_grad():
            up, down = (ik.solve(chain, moved(T, s * d), q0=q_star, collision=rc, world=world, seed=0,
                                 **TIGHT) for s in (1.0, -1.0))
        assert up.success.all() and down.success.all()
        fd[..., k] = ((up.q - down.q) * w).sum(-1) / (2 * h)
    torch.testing.assert_close(xi.grad, v, atol=1e-8, rtol=0)  # J D = I
    # the re-solves stop at 1e-11 at slightly different points: measured 1.3e-5 worst of the 36 entries,
    # the same at h = 1e-4 and 2e-5 (not truncation); a wrong gradient is off by O(1)
    torch.testing.assert_close(fd, xi.grad, atol=5e-5, rtol=0)


def _clear_target(chain, rc, w, clear: float, seed: int):
    """A configuration whose distances all exceed ``clear`` (m), and its pose."""
    g = torch.Generator().manual_seed(seed)
    q = chain.random_configuration((2000,), generator=g)
    with torch.no_grad():
        q = q[rc.min_distance(q, w) > clear][:1]
    assert q.shape[0] == 1
    return q, chain.forward_kinematics(q)


@pytest.mark.extended  # 21 s of finite differences; the KKT gradient against finite differences stays in the
# default run (test_ik_optimize_constraints.py)
def test_optimize_gradients_at_inactive_constraints_match_finite_differences():
    """optimize(collision=, world=) with every distance beyond margin + buffer: dq*/dT by the implicit
    gradient equals central differences of the solver (float64), and equals the gradient without the
    collision term (the penalty vanishes near q*)."""
    chain, rc = fr3_robot(torch.float64)
    w = _world(torch.float64)
    q_t, T = _clear_target(chain, rc, w, 0.03, seed=11)
    q0 = q_t + 0.05
    costs = [ik.PoseCost(), ik.RestPostureCost(weight=1e-2)]  # a unique stationary point
    kw = dict(costs=costs, optimizer="gauss_newton", max_iterations=200, tolerance_change=0.0)
    v = torch.linspace(-1.0, 1.0, 7, dtype=torch.float64)

    def solve(TT, **extra):
        return ik.optimize(chain, TT, q0, **kw, **extra).q

    Tg = T.clone().requires_grad_(True)
    q = solve(Tg, collision=rc, world=w)
    (g,) = torch.autograd.grad((q * v).sum(), Tg)
    Tg2 = T.clone().requires_grad_(True)
    (g_plain,) = torch.autograd.grad((solve(Tg2) * v).sum(), Tg2)
    torch.testing.assert_close(g, g_plain, rtol=1e-6, atol=1e-7)
    eps = 1e-3  # (smaller steps meet the solvers' convergence noise, about 1e-9 in q: 1e-5 at 1e-4)
    for i in range(3):  # the translation entries
        E = torch.zeros_like(T)
        E[..., i, 3] = eps
        with torch.no_grad():
            dq = solve(T + E, collision=rc, world=w) - solve(T - E, collision=rc, world=w)
        fd = (dq * v).sum() / (2 * eps)
        assert abs(float(fd) - float(g[..., i, 3].sum())) <= 1e-5 * max(1.0, abs(float(fd))), (i, fd, g)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_optimize_collision_success_is_the_hard_check(dtype):
    """A target whose flange sits inside an obstacle is never a success; a clear one is, and coal agrees."""
    chain, rc = fr3_robot(dtype)
    check = CoalCheck(rc, with_box=False)
    q_t, T = _clear_target(chain, rc, _world(dtype, with_box=False), 0.03, seed=13)
    p = T[:, :3, 3]
    inside = World(spheres=torch.cat((p, torch.full((1, 1), 0.04, dtype=dtype)), -1))
    res = ik.optimize(chain, T, q_t, optimizer="gauss_newton", collision=rc, world=inside)
    assert not res.success.any()
    res = ik.optimize(chain, T, q_t + 0.02, optimizer="gauss_newton", collision=rc, margin=0.005)
    assert res.success.all()
    assert check.min_self_distance(res.q[0].double().numpy()) >= 0.005 - 2e-6


def test_collision_solve_in_c_rounds_is_the_same_for_every_thread_count(monkeypatch):
    """The CPU solve through rounds of the whole C solve (ik/_collision_native.py), 600 targets (more than
    one C thread's share): the same answers on 1 and 2 threads; some targets were solved again (their first
    solution collides); every success among those and among 60 others is clear by coal."""
    from diffkin.ik import _collision_native

    if not diffkin.kernels.native.available():
        pytest.skip("the native library is not built here")
    chain, rc = fr3_robot(torch.float32)
    w = _world(torch.float32)
    g = torch.Generator().manual_seed(17)
    q = chain.random_configuration((4000,), generator=g)
    with torch.no_grad():  # targets only: the successes below are checked by coal
        T = chain.forward_kinematics(q[rc.min_distance(q, w) > 0.01][:600])
    calls = []
    run = _collision_native.run
    monkeypatch.setattr(_collision_native, "run", lambda *a, **k: calls.append(a[2]) or run(*a, **k))
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = ik.solve(chain, T, collision=rc, world=w, seed=0)
        torch.set_num_threads(2)
        two = ik.solve(chain, T, collision=rc, world=w, seed=0)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one.q, two.q) and torch.equal(one.success, two.success)
    assert torch.equal(one.seeds_tried, two.seeds_tried)
    assert calls[0] == 600 and len(calls) >= 4  # round 0 and re-solve rounds, twice
    assert one.success.float().mean() >= 0.99
    plain = ik.solve(chain, T, seed=0)
    with torch.no_grad():
        redone = (rc.min_distance(plain.q, w) < 0).nonzero().squeeze(-1)
    assert redone.numel() > 0
    check = CoalCheck(rc)
    rows = torch.cat((redone, torch.arange(0, 600, 10))).unique()
    rows = rows[one.success[rows]]
    assert min(check.min_distance(q) for q in one.q[rows].double().numpy()) >= -2e-6


def test_benchmark_runs_small():
    """benchmarks/bench_collision_ik.py at a tiny size: its rows, and the collision rows all clear."""
    import argparse

    from benchmarks import bench_collision_ik

    rows = bench_collision_ik.run(argparse.Namespace(quick=True, targets=16, world="spheres", repeats=1))
    assert [r["impl"] for r in rows] == ["ik.solve", "ik.solve collision", "ik.solve collision + refinement"]
    for r in rows[1:]:
        assert r["success"] >= 0.9 and r["collision_free"] == r["success"] and r["speed_ratio"] > 0


def test_the_collision_free_library_has_the_solvers_layout():
    """The collision-free library of the C rounds holds its poses as dk_solve's nearest-pose search reads
    them, feature-major (12 K, L'): rows p, x, y, z of FK(u) (a row-major copy once sent every target to
    far library poses; only the speed showed it)."""
    from diffkin.ik._collision_native import _library
    from diffkin.ik._native_solve import prepared
    from diffkin.ik.residuals import DistanceConstraint

    chain, rc = fr3_robot(torch.float64)
    prep = prepared(chain, torch.zeros(3, 1, dtype=torch.float64), torch.float64, True, 0)
    if prep is None:
        pytest.skip("the C solve does not serve here")
    u, pose = _library(prep, DistanceConstraint(rc, _world(torch.float64)), 64, 1)
    assert pose.shape == (12, u.shape[0]) and u.shape[0] > 0
    with torch.no_grad():
        T = chain.forward_kinematics(prep.jmap.q_of_u(u.T).T)
    expect = torch.cat((T[:, :3, 3], T[:, :3, 0], T[:, :3, 1], T[:, :3, 2]), 1).T
    torch.testing.assert_close(pose, expect, rtol=0, atol=1e-12)
