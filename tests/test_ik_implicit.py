"""IK as a differentiable layer (diffkin.ik.implicit): gradients of ik.solve / ik.optimize w.r.t. targets and
the robot's parameters, against finite differences of warm-started re-solves, the Jacobian identities
J·D = I and (I − J⁺J)·D = 0, −J⁻¹ ∂x/∂θ from FK finite differences, and gradcheck."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from diffkin import ik, models
from tests.helpers import TIGHT, moved

F64 = torch.float64


def _targets(chain, B, seed):
    q = chain.random_configuration((B,), generator=torch.Generator().manual_seed(seed))
    with torch.no_grad():
        return q, chain.forward_kinematics(q)


def _resolve(chain, T, q_start, **kw):
    with torch.no_grad():
        return ik.solve(chain, T, q0=q_start, seed=0, **TIGHT, **kw).q


def test_solve_returns_a_graph_and_gradients_match_warm_started_resolves():
    """UR5 (6-DOF): d(w·q*)/dξ by the implicit backward vs central differences of re-solves."""
    chain = models.load("ur5", dtype=F64)
    q_true, T = _targets(chain, 5, seed=1)
    xi = torch.zeros(5, 6, dtype=F64, requires_grad=True)
    res = ik.solve(chain, moved(T, xi), seed=0, **TIGHT)
    assert bool(res.success.all()) and res.q.grad_fn is not None and res.q.is_contiguous()
    w = torch.randn(5, 6, dtype=F64, generator=torch.Generator().manual_seed(2))
    (res.q * w).sum().backward()
    # h: the re-solves stop at 1e-11, so their noise in the quotient is ~1e-11 / h; the truncation error
    # is O(h²): 1e-4 keeps both below the tolerance (1e-6 let the solver's stopping point show, 2e-5)
    h = 1e-4
    fd = torch.zeros(5, 6, dtype=F64)
    for k in range(6):
        d = torch.zeros(5, 6, dtype=F64)
        d[:, k] = h
        up = _resolve(chain, moved(T, d), res.q.detach())
        down = _resolve(chain, moved(T, -d), res.q.detach())
        fd[:, k] = ((up - down) * w).sum(-1) / (2 * h)
    torch.testing.assert_close(xi.grad, fd, atol=1e-5, rtol=1e-5)


def test_panda_redundant_jacobian_identities():
    """Panda (7-DOF): D = dq*/dξ satisfies J D = I and has no null-space component, (I − J⁺J) D = 0."""
    chain = models.load("panda", dtype=F64)
    _, T = _targets(chain, 3, seed=3)
    res0 = ik.solve(chain, T, seed=0, **TIGHT)
    assert bool(res0.success.all())
    for b in range(3):
        def solved(x, b=b):  # warm-started: lands on the same point of the self-motion manifold
            return ik.solve(chain, moved(T[b], x), q0=res0.q[b].detach(), seed=0, **TIGHT).q

        D = torch.autograd.functional.jacobian(solved, torch.zeros(6, dtype=F64))  # (7, 6)
        J = chain.geometric_jacobian(solved(torch.zeros(6, dtype=F64)).detach()).detach()
        # exact (σ_min >= k: only the 10 ε floor damps; it was 2e-6 off with the former fixed damping)
        torch.testing.assert_close(J @ D, torch.eye(6, dtype=F64), atol=1e-9, rtol=0)
        P = torch.eye(7, dtype=F64) - torch.linalg.pinv(J) @ J
        torch.testing.assert_close(P @ D, torch.zeros(7, 6, dtype=F64), atol=1e-9, rtol=0)


def test_parameter_gradients_are_minus_jinv_dx_dtheta():
    """dq*/dθ = −J⁻¹ ∂x/∂θ, ∂x/∂θ the twist of the FK change from central differences of the parameters."""
    chain = models.load("ur5", dtype=F64, learnable=True)
    _, T = _targets(chain, 2, seed=4)
    res = ik.solve(chain, T, seed=0, **TIGHT)
    q = res.q
    for name in ("a", "d", "theta", "base_delta", "tool_delta"):
        p = getattr(chain, name)
        for i in range(min(p.numel(), 3)):
            (g,) = torch.autograd.grad(q[:, 0].sum() + 2 * q[:, 4].sum(), p, retain_graph=True)
            h = 1e-6
            with torch.no_grad():
                p.view(-1)[i] += h
                Tp = chain.forward_kinematics(q.detach())
                p.view(-1)[i] -= 2 * h
                Tm = chain.forward_kinematics(q.detach())
                p.view(-1)[i] += h
                T0 = chain.forward_kinematics(q.detach())
                dp = (Tp[..., :3, 3] - Tm[..., :3, 3]) / (2 * h)
                W = (Tp[..., :3, :3] - Tm[..., :3, :3]) / (2 * h) @ T0[..., :3, :3].mT
                dx = torch.cat((dp, torch.stack((W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]), -1)), -1)
                J = chain.geometric_jacobian(q.detach())
                dq = -torch.linalg.solve(J, dx)  # (2, 6)
            torch.testing.assert_close(g.view(-1)[i], (dq[:, 0] + 2 * dq[:, 4]).sum(), atol=1e-6, rtol=1e-6)


def test_gradcheck_position_only_and_full_pose_and_batch_equals_single():
    chain = models.load("ur5", dtype=F64)
    _, T = _targets(chain, 2, seed=5)
    q_sol = ik.solve(chain, T, seed=0, **TIGHT).q.detach()

    def full(x):
        return ik.solve(chain, moved(T, x), q0=q_sol, seed=0, **TIGHT).q

    # eps 1e-4: the central differences of re-solves carry ~tol / eps · 1/σ_min(J) of solver noise
    assert torch.autograd.gradcheck(full, (torch.zeros(2, 6, dtype=F64, requires_grad=True),), eps=1e-4,
                                    atol=1e-5)
    three = models.load("anthropomorphic_arm", dtype=F64)  # 3 joints, positions: square J
    _, T3 = _targets(three, 2, seed=6)
    q3 = ik.solve(three, T3[..., :3, 3], position_only=True, seed=0, **TIGHT).q.detach()

    def pos(p):
        return ik.solve(three, p, q0=q3, position_only=True, seed=0, **TIGHT).q

    assert torch.autograd.gradcheck(pos, (T3[..., :3, 3].clone().requires_grad_(True),), atol=1e-5)
    # batched ≡ per-sample
    xi = torch.zeros(2, 6, dtype=F64, requires_grad=True)
    (full(xi) ** 2).sum().backward()
    for b in range(2):
        xb = torch.zeros(6, dtype=F64, requires_grad=True)
        (ik.solve(chain, moved(T[b], xb), q0=q_sol[b], seed=0, **TIGHT).q ** 2).sum().backward()
        torch.testing.assert_close(xb.grad, xi.grad[b], atol=1e-9, rtol=1e-9)


def test_failed_and_singular_targets_give_finite_gradients():
    """An unreachable target: success False and a zero gradient; a wrist-singular solution: finite."""
    chain = models.load("ur5", dtype=F64)
    q_sing = torch.tensor([0.3, -1.2, 1.4, 0.5, 0.0, 0.7], dtype=F64)  # θ5 = 0: wrist singularity
    with torch.no_grad():
        T_sing = chain.forward_kinematics(q_sing)
    far = T_sing.clone()
    far[:3, 3] = torch.tensor([5.0, 0.0, 0.0], dtype=F64)
    T = torch.stack((T_sing, far)).requires_grad_(True)
    res = ik.solve(chain, T, q0=torch.stack((q_sing, q_sing)), seed=0, num_seeds=4)
    assert res.success.tolist() == [True, False]
    res.q.sum().backward()
    assert bool(torch.isfinite(T.grad).all())
    assert bool((T.grad[1] == 0).all())  # failed: zero gradient, documented
    assert float(T.grad[0].abs().max()) < 1e6  # bounded by the adaptive damping at the singularity


def test_gradients_reach_a_tree_and_a_float32_urdf_chain():
    path = Path(__file__).parent / "data" / "urdf" / "baxter.urdf"
    chain = models.from_urdf(path, ["left_gripper", "right_gripper"], dtype=torch.float32, learnable=True)
    _, T = _targets(chain, 6, seed=7)
    Tg = T.clone().requires_grad_(True)
    res = ik.solve(chain, Tg, seed=0)
    (res.q ** 2).sum().backward()
    assert bool(torch.isfinite(Tg.grad).all()) and float(Tg.grad.abs().sum()) > 0
    assert chain.origin_xyz.grad is not None and bool(torch.isfinite(chain.origin_xyz.grad).all())
    # joints of the left arm do not move the right gripper: its target's gradient w.r.t. a left-only loss is 0
    Tg.grad = None
    left = [i for i, name in enumerate(chain.joint_names) if name.startswith("left_")]
    res = ik.solve(chain, Tg, seed=0)
    res.q[..., left].sum().backward()
    assert float(Tg.grad[:, 1].abs().max()) == 0.0 and float(Tg.grad[:, 0].abs().max()) > 0


def test_no_graph_without_grad_and_contiguous_q_feeds_optimize():
    chain = models.load("panda", dtype=torch.float32)
    _, T = _targets(chain, 4, seed=8)
    with torch.no_grad():
        assert ik.solve(chain, T, seed=0).q.grad_fn is None
    frozen = models.load("panda", dtype=torch.float32).requires_grad_(False)
    assert ik.solve(frozen, T, seed=0).q.grad_fn is None  # nothing requires grad
    q = ik.solve(chain, T, seed=0).q
    assert q.is_contiguous()
    for name in ("lbfgs", "adam", "gauss_newton"):  # the README's workflow, every optimiser
        res = ik.optimize(chain, T, q0=q, optimizer=name, max_iterations=5,
                          costs=[ik.PoseCost(), ik.RestPostureCost(weight=1e-4)])
        assert res.q.shape == (4, 7) and bool(torch.isfinite(res.q).all())


def _polished(chain, costs, T, q):
    """The exact stationary point near ``q``: Newton steps on the summed cost (per sample, autograd
    Hessian), so that finite differences of it measure dq*/dz without optimiser tolerance."""
    def cost(x, Tb):
        return sum(term(ik.CostContext(chain, x, Tb)) for term in costs)

    q = q.detach().clone()
    for _ in range(8):
        for b in range(q.shape[0]):
            g = torch.autograd.functional.jacobian(lambda x, b=b: cost(x, T[b]), q[b])
            H = torch.autograd.functional.hessian(lambda x, b=b: cost(x, T[b]), q[b])
            q[b] = q[b] - torch.linalg.solve(H, g)
    return q


def test_optimize_implicit_gradient_matches_finite_differences_and_unroll():
    """Stationary point of pose + rest-posture cost on the Panda (a redundant arm, so the rest term picks
    the point): implicit gradient vs central differences of the exact stationary point, and unroll=True."""
    chain = models.load("panda", dtype=F64).requires_grad_(False)
    _, T = _targets(chain, 2, seed=9)
    q0 = ik.solve(chain, T, seed=0, **TIGHT).q.detach()
    costs = [ik.PoseCost(), ik.RestPostureCost(weight=1e-2)]
    # unconstrained: the stationary point is that of the costs alone (the Newton polish below ignores the
    # joint limits, and a solve's seed may land on a branch whose stationary point is past one)
    kw = {"costs": costs, "optimizer": "lbfgs", "max_iterations": 100, "respect_limits": False}
    xi = torch.zeros(2, 6, dtype=F64, requires_grad=True)
    res = ik.optimize(chain, moved(T, xi), q0=q0, **kw)
    q_star = _polished(chain, costs, T, res.q)
    assert float((q_star - res.q.detach()).abs().max()) < 1e-4  # the optimiser found this stationary point
    # zero iterations from the exact point: the backward is evaluated exactly there
    res = ik.optimize(chain, moved(T, xi), q0=q_star, **{**kw, "max_iterations": 0})
    w = torch.randn(2, 7, dtype=F64, generator=torch.Generator().manual_seed(10))
    (res.q * w).sum().backward()
    g_implicit = xi.grad.clone()
    h = 1e-6
    fd = torch.zeros(2, 6, dtype=F64)
    for k in range(6):
        d = torch.zeros(2, 6, dtype=F64)
        d[:, k] = h
        up = _polished(chain, costs, moved(T, d), q_star)
        down = _polished(chain, costs, moved(T, -d), q_star)
        fd[:, k] = ((up - down) * w).sum(-1) / (2 * h)
    torch.testing.assert_close(g_implicit, fd, atol=1e-5, rtol=1e-4)
    xi.grad = None
    res_u = ik.optimize(chain, moved(T, xi), q0=q_star, unroll=60, **{**kw, "max_iterations": 0})
    (res_u.q * w).sum().backward()
    torch.testing.assert_close(xi.grad, g_implicit, atol=1e-4, rtol=1e-3)


# compiles the whole solve (13 s); the kernels' fullgraph compiles stay in test_compile.py
@pytest.mark.extended
def test_usable_inside_torch_compile():
    """A caller's compiled function containing solve: the same values and gradients as eager."""
    chain = models.load("ur5", dtype=F64)
    q_true, T = _targets(chain, 4, seed=11)

    # one warm start near the generating configuration: the compiled call (the torch loop: dynamo does not
    # trace the C solve) and the eager one (the C solve) then land on the same one of the UR5's branches
    q0 = q_true + 0.05

    def loss(x):
        return (ik.solve(chain, moved(T, x), q0=q0, num_seeds=1, seed=0).q - q_true).square().sum()

    x1 = torch.zeros(4, 6, dtype=F64, requires_grad=True)
    x2 = torch.zeros(4, 6, dtype=F64, requires_grad=True)
    torch.compile(loss, backend="eager")(x1).backward()
    loss(x2).backward()
    torch.testing.assert_close(x1.grad, x2.grad, atol=1e-9, rtol=1e-9)


# --------------------------------------------------- exactness of the solve backward (issue 30 item 11)
EXACT = {"position_tolerance": 1e-13, "orientation_tolerance": 1e-13, "max_iterations": 500}


def _solution_map_gradient(chain, q_sol, w, h):
    """The implicit gradient of w·q*(ξ) at ξ = 0, and the same by a 4-point stencil of warm-started solves."""
    with torch.no_grad():
        T = chain.forward_kinematics(q_sol)
    xi = torch.zeros(6, dtype=F64, requires_grad=True)
    res = ik.solve(chain, moved(T, xi), q0=q_sol, num_seeds=1, seed=0, **EXACT)
    assert bool(res.success)
    (res.q @ w).backward()

    def f(d):
        with torch.no_grad():
            r = ik.solve(chain, moved(T, d), q0=q_sol, num_seeds=1, seed=0, **EXACT)
            assert bool(r.success)
            return r.q @ w

    fd = torch.zeros(6, dtype=F64)
    for k in range(6):
        e = torch.zeros(6, dtype=F64)
        e[k] = h
        fd[k] = (-f(2 * e) + 8 * f(e) - 8 * f(-e) + f(-2 * e)) / (12 * h)
    return xi.grad, fd


@pytest.mark.parametrize(("q5", "sigma_min", "h"), [(1.2, 0.2, 1e-3), (0.0154, 0.007, 1e-4)])
def test_solve_gradient_is_exact_where_the_jacobian_is_well_conditioned(q5, sigma_min, h):
    """UR5 at σ_min(J) ≈ 0.2 and ≈ 0.007 (above the solver's damping k = 3e-3): the implicit gradient is the
    exact J⁻¹ (relative error <= 1e-8 against finite differences of the solution map; it was 2e-5 at 0.007
    with the former fixed damping)."""
    chain = models.load("ur5", dtype=F64)
    q = torch.tensor([0.3, -1.1, 1.4, -0.9, q5, 0.5], dtype=F64)
    s = float(torch.linalg.svdvals(chain.geometric_jacobian(q).detach())[-1])
    assert abs(s - sigma_min) < 0.25 * sigma_min
    w = torch.randn(6, dtype=F64, generator=torch.Generator().manual_seed(7))
    g, fd = _solution_map_gradient(chain, q, w, h)
    rel = float((g - fd).norm() / fd.norm())
    assert rel <= 1e-8, rel


def test_solve_gradient_is_bounded_at_a_singular_solution():
    """σ_min(J) ≈ 5e-4 < k: the backward is damped, λ = k² − σ_min², so every direction is amplified by at
    most σ/(σ² + λ) <= 1/k; the gradient stays finite and within that bound (the exact one: ~1/σ_min)."""
    chain = models.load("ur5", dtype=F64)
    q = torch.tensor([0.3, -1.1, 1.4, -0.9, 1.1e-3, 0.5], dtype=F64)
    assert float(torch.linalg.svdvals(chain.geometric_jacobian(q).detach())[-1]) < 1e-3
    with torch.no_grad():
        T = chain.forward_kinematics(q)
    xi = torch.zeros(6, dtype=F64, requires_grad=True)
    res = ik.solve(chain, moved(T, xi), q0=q, seed=0, **EXACT)
    w = torch.randn(6, dtype=F64, generator=torch.Generator().manual_seed(8))
    (res.q @ w).backward()
    k = ik.LMConfig().damping ** 0.5  # λ̄ = k² = 9e-6
    assert bool(torch.isfinite(xi.grad).all())
    # ξ enters F with ∂F/∂ξ of norm <= ~1 near the solution (p: identity; ω: the rotvec's Jacobian at 0)
    assert float(xi.grad.norm()) <= 1.01 * float(w.norm()) / k
