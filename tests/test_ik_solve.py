"""diffkin.ik.numerical: batched LM IK (solve), dls_step, dls_delta.

References: success is re-checked with an independent FK (the chain's matrix kernel, one pose at a time) and
scipy's rotation magnitude; dls_delta against the SVD form of the damped inverse.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from diffkin.errors import DiffkinError, DTypeError, NonFiniteError, ShapeError
from diffkin.ik.numerical import dls_delta, dls_step, solve
from diffkin.ik.result import IKResult
from diffkin.models import DATA_DIR, from_urdf, load

F64 = torch.float64
TOL_P, TOL_O = 1e-4, 1e-3


def chain64(name):
    return load(name, dtype=F64)


def targets(chain, shape, seed=0):
    g = torch.Generator().manual_seed(seed)
    q = chain.random_configuration(shape, generator=g)
    with torch.no_grad():
        return q, chain.forward_kinematics(q)


def independent_errors(chain, q, T):
    """Per-sample errors via a float64 FK of one configuration at a time and scipy's rotation angle."""
    c = chain.copy().double() if hasattr(chain, "copy") else chain.double()
    qs = q.reshape(-1, chain.n_joints).double()
    Ts = T.reshape(-1, *T.shape[-2:]).double() if T.shape[-1] == 4 else T.reshape(-1, 3).double()
    pe, oe = [], []
    for qi, Ti in zip(qs, Ts.detach()):
        Te = c.forward_kinematics(qi).detach()
        if Ti.shape == (3,):
            pe.append(float(torch.linalg.norm(Ti - Te[:3, 3])))
            continue
        pe.append(float(torch.linalg.norm(Ti[:3, 3] - Te[:3, 3])))
        Rerr = Te[:3, :3].numpy().T @ Ti[:3, :3].numpy()
        oe.append(Rotation.from_matrix(Rerr).magnitude())
    return np.array(pe), np.array(oe) if oe else np.zeros(len(pe))


def assert_honest(chain, res: IKResult, T, position_only=False, limits=True):
    q = res.q.detach()
    assert torch.isfinite(q).all() and torch.isfinite(res.position_error).all()
    assert torch.isfinite(res.orientation_error).all()
    pe, oe = independent_errors(chain, q, T)
    ok = res.success.reshape(-1).numpy()
    # every success meets the tolerance per an independent FK; failures really fail (small slack for rounding)
    assert (pe[ok] <= TOL_P * (1 + 1e-6)).all()
    if not position_only:
        assert (oe[ok] <= TOL_O * (1 + 1e-6)).all()
    bad = ~ok
    if bad.any():
        fails_tol = (pe[bad] > TOL_P * 0.999) | ((oe[bad] > TOL_O * 0.999) if not position_only else False)
        if limits and chain.q_limits is not None:
            fails_tol |= ~chain.within_limits(q.reshape(-1, chain.n_joints)).numpy()[bad]
        assert fails_tol.all()
    np.testing.assert_allclose(res.position_error.reshape(-1).double().numpy(), pe, atol=1e-6)
    if limits and chain.q_limits is not None:
        lo, hi = chain.lower_upper()
        assert ((q >= lo) & (q <= hi)).all(), "joint limits violated"


@pytest.mark.parametrize("name", ["panda", "ur5", "kuka_iiwa14"])
def test_solve_reachable_targets(name):
    chain = chain64(name)
    _, T = targets(chain, (200,), seed=1)
    res = solve(chain, T, seed=0)
    assert res.q.shape == (200, chain.n_joints) and res.success.shape == (200,)
    assert res.success.double().mean() >= 0.99
    assert_honest(chain, res, T)
    assert (res.iterations > 0).all() and (res.seeds_tried >= 1).all()


def test_solve_urdf_chain_float32():
    """A URDF chain (not DH) in float32: float64 iteration inside, success judged in float32."""
    chain = from_urdf(DATA_DIR / "panda.urdf", "panda_link8", dtype=torch.float32)
    _, T = targets(chain, (100,), seed=2)
    res = solve(chain, T, seed=0)
    assert res.q.dtype == torch.float32 and res.position_error.dtype == torch.float32
    assert res.success.double().mean() >= 0.99
    assert_honest(chain, res, T)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(), (5,), (2, 3)])
def test_batch_shapes_and_dtypes(shape, dtype):
    chain = load("panda", dtype=dtype)
    _, T = targets(chain, shape, seed=3)
    res = solve(chain, T, seed=0)
    assert res.q.shape == (*shape, 7) and res.q.dtype == dtype
    for t in (res.success, res.position_error, res.orientation_error, res.iterations, res.seeds_tried):
        assert t.shape == shape
    assert res.success.all()
    assert_honest(chain, res, T)


def test_unreachable_and_singular_targets():
    chain = chain64("panda")
    _, T = targets(chain, (4,), seed=4)
    far = T.clone()
    far[:2, :3, 3] += torch.tensor([5.0, 0.0, 0.0], dtype=F64)  # 5 m away
    q_str = torch.tensor([0.0, 0.0, 0.0, -0.0698, 0.0, 0.0, 0.0], dtype=F64)
    stretched = chain.forward_kinematics(q_str).detach()
    over = stretched.clone()
    over[2, 3] += 0.02  # 2 cm beyond the (nearly) stretched arm
    T_all = torch.cat((far[:2], stretched[None], over[None]))
    res = solve(chain, T_all, num_seeds=8, seed=0)
    assert not res.success[:2].any() and not res.success[3]
    assert (res.position_error[:2] > 4.0).all()
    assert_honest(chain, res, T_all)


def test_ur5_singular_stretched_target_is_finite():
    chain = chain64("ur5")
    T = chain.forward_kinematics(torch.zeros(6, dtype=F64)).detach()  # elbow singular, arm stretched
    res = solve(chain, T, seed=0)
    assert torch.isfinite(res.q).all()
    assert_honest(chain, res, T)


@pytest.mark.parametrize("as_pose", [False, True])
def test_position_only(as_pose):
    chain = chain64("kuka_iiwa14")
    _, T = targets(chain, (50,), seed=5)
    goal = T if as_pose else T[..., :3, 3]
    res = solve(chain, goal, position_only=True, seed=0)
    assert res.success.all()
    assert_honest(chain, res, goal, position_only=True)
    if not as_pose:
        assert (res.orientation_error == 0).all()


def test_user_seeds_are_used():
    chain = chain64("panda")
    q_true, T = targets(chain, (20,), seed=6)
    res = solve(chain, T, q_true, seed=0)
    assert res.success.all() and (res.seeds_tried == 1).all()
    assert torch.allclose(res.q, q_true, atol=1e-6)  # converged at the given seed
    # several seeds per target (..., S, n), tried in order: the true one first converges at once
    S = torch.stack((q_true, chain.random_configuration(20)), dim=-2)
    res2 = solve(chain, T, S, seed=0)
    assert res2.success.all() and (res2.seeds_tried == 1).all() and (res2.iterations == 1).all()
    assert torch.allclose(res2.q, q_true, atol=1e-6)
    # one seed for every target, broadcast
    res3 = solve(chain, T, q_true[0], seed=0)
    assert res3.success.all()
    assert_honest(chain, res3, T)


def test_seeded_runs_are_reproducible():
    chain = chain64("ur5")
    _, T = targets(chain, (30,), seed=7)
    a, b = solve(chain, T, seed=3), solve(chain, T, seed=3)
    assert torch.equal(a.q, b.q) and torch.equal(a.iterations, b.iterations)


def test_respect_limits_false_allows_any_branch():
    chain = chain64("panda")
    _, T = targets(chain, (50,), seed=8)
    res = solve(chain, T, respect_limits=False, seed=0)
    assert res.success.double().mean() >= 0.98
    assert_honest(chain, res, T, limits=False)
    # limits narrowed to ±0.1 rad about their midpoints: the targets' configurations lie outside them, so
    # respect_limits=False must solve them there, and the default must not return any q outside
    lo, hi = chain.lower_upper()
    mid = (lo + hi) / 2
    chain.q_limits = torch.stack((mid - 0.1, mid + 0.1), dim=-1)
    free = solve(chain, T, respect_limits=False, seed=0)
    assert free.success.double().mean() >= 0.9
    assert bool((~chain.within_limits(free.q.detach()))[free.success].all())
    strict = solve(chain, T, seed=0)
    assert bool(chain.within_limits(strict.q.detach()).all()) and strict.success.double().mean() <= 0.1
    assert_honest(chain, strict, T)


def test_bad_inputs():
    chain = chain64("panda")
    _, T = targets(chain, (4,), seed=9)
    with pytest.raises(ShapeError, match=r"q0"):
        solve(chain, T, torch.zeros(4, 6, dtype=F64))  # wrong n
    with pytest.raises(ShapeError, match=r"broadcast"):
        solve(chain, T, torch.zeros(3, 7, dtype=F64))  # 3 seeds for 4 targets
    with pytest.raises(ShapeError, match=r"q0"):
        solve(chain, T, torch.zeros(1, 1, 4, 7, dtype=F64))  # too many dims
    with pytest.raises(ShapeError, match=r"\(\.\.\., 4, 4\)"):
        solve(chain, T[..., :3, :])
    skew = T.clone()
    skew[1, 0, 1] += 0.3  # not a rotation
    with pytest.raises(DiffkinError, match="rigid"):
        solve(chain, skew)
    nan = T.clone()
    nan[0, 0, 3] = math.nan
    with pytest.raises(NonFiniteError):
        solve(chain, nan)
    with pytest.raises(DTypeError):
        solve(chain, T.float())


def test_frame_task_zero_costs_are_honoured_or_refused():
    """A FrameTask's zero cost removes that row of log(T_f⁻¹T_t) in every solver alike: ik.optimize and
    ik.solve_velocity drop it (here: scipy's least_squares on the same weighted residual W e reaches 0, and
    so does optimize, with the x row 0 and the free rows not); the LM pose solve has every row, so it
    refuses zeros on some axes only (it used to reach the whole position silently) and keeps the position
    only solve for orientation costs 0 everywhere; positive costs leave its exact solution unchanged."""
    from scipy.optimize import least_squares

    from diffkin import ik
    from diffkin.errors import ConventionError
    from diffkin.ik.tasks import Problem

    chain = chain64("ur5")
    q, T = targets(chain, (3,), seed=4)
    q0 = q + 0.2
    task = ik.FrameTask(0, target=T, position_cost=[1.0, 0.0, 0.0], orientation_cost=0.0)
    with pytest.raises(ConventionError, match="position_cost"):
        solve(chain, tasks=[task])
    with pytest.raises(ConventionError, match="orientation_cost"):
        solve(chain, tasks=[ik.FrameTask(0, target=T, orientation_cost=[0.0, 0.0, 1.0])])
    with pytest.raises(ConventionError, match="orientation_cost"):  # zero for some samples only
        some = torch.tensor([[1.0], [0.0], [1.0]], dtype=F64).expand(3, 3)
        solve(chain, tasks=[ik.FrameTask(0, target=T, orientation_cost=some)])
    # positive costs: the same exact solve as the plain target; orientation costs 0: position only
    plain = solve(chain, T, seed=2)
    weighted = solve(chain, tasks=[ik.FrameTask(0, target=T, position_cost=[1.0, 2.0, 0.5],
                                                orientation_cost=0.3)], seed=2)
    torch.testing.assert_close(weighted.q, plain.q, atol=0, rtol=0)
    pos = solve(chain, tasks=[ik.FrameTask(0, target=T, orientation_cost=0.0)], seed=2)
    ref = solve(chain, T[..., :3, 3], position_only=True, seed=2)
    torch.testing.assert_close(pos.q, ref.q, atol=0, rtol=0)
    # the solvers that take the task drop the zero rows: a zero of W e, away from the target
    w = torch.tensor([1.0, 0, 0, 0, 0, 0], dtype=F64)

    def residual(qn, k):
        p = Problem(chain, torch.as_tensor(qn), 1.0)
        return (w * ik.FrameTask(0, target=T[k]).error(p)).numpy()

    for k in range(3):
        ref = least_squares(residual, q0[k].numpy(), args=(k,), xtol=1e-15, ftol=1e-15, gtol=1e-15)
        assert np.abs(ref.fun).max() < 1e-12
    res = ik.optimize(chain, q0=q0, tasks=[task], optimizer="gauss_newton")
    e = task.error(Problem(chain, res.q, 1.0))
    assert float(e[:, 0].abs().max()) < 1e-10 and float(e[:, 1:3].norm(dim=-1).min()) > 1e-3
    v = ik.solve_velocity(chain, q0, [task], 0.1, damping=1e-3)
    p = Problem(chain, q0, 0.1)
    A, b = w[:, None] * task.jacobian(p), -w * task.error(p)  # W J, −α W e: (T.1), damped least squares
    want = torch.linalg.solve(A.mT @ A + 1e-3 * torch.eye(6, dtype=F64), (A.mT @ b[..., None]))[..., 0] / 0.1
    torch.testing.assert_close(v, want, atol=1e-9, rtol=0)


def test_empty_batch():
    chain = chain64("ur5")
    res = solve(chain, torch.zeros(0, 4, 4, dtype=F64))
    assert res.q.shape == (0, 6) and res.success.shape == (0,)


def test_dls_delta_matches_svd_damped_inverse():
    g = torch.Generator().manual_seed(0)
    J = torch.randn(5, 6, 7, generator=g, dtype=F64)
    e = torch.randn(5, 6, generator=g, dtype=F64)
    lam = 0.01  # λ, added to JJᵀ's diagonal (3.59)
    U, S, Vh = torch.linalg.svd(J, full_matrices=False)
    ref = (Vh.mT * (S / (S**2 + lam)).unsqueeze(-2)) @ (U.mT @ e.unsqueeze(-1))
    torch.testing.assert_close(dls_delta(J, e, lam), ref.squeeze(-1))
    Jg = J.clone().requires_grad_()
    torch.autograd.gradcheck(lambda A: dls_delta(A, e[:2], lam), (Jg[:2],))


def test_dls_step_reduces_error_and_respects_limits():
    chain = chain64("panda")
    q_true, T = targets(chain, (64,), seed=10)
    q = chain.clamp_to_limits(q_true + 0.05 * torch.randn(q_true.shape, dtype=F64))
    before = torch.linalg.norm(chain.forward_kinematics(q)[..., :3, 3] - T[..., :3, 3], dim=-1)
    q1 = dls_step(chain, q, T, damping=1e-4)
    after = torch.linalg.norm(chain.forward_kinematics(q1)[..., :3, 3] - T[..., :3, 3], dim=-1)
    assert (after < before).double().mean() > 0.95 and after.median() < 0.2 * before.median()
    assert chain.within_limits(q1).all()
    qp = dls_step(chain, q, T[..., :3, 3], damping=1e-4, position_only=True)
    assert qp.shape == q.shape and torch.isfinite(qp).all()
    # differentiable w.r.t. q
    qg = q[:3].clone().requires_grad_()
    dls_step(chain, qg, T[:3]).sum().backward()
    assert torch.isfinite(qg.grad).all()


def test_summary_and_str():
    chain = chain64("ur5")
    _, T = targets(chain, (10,), seed=11)
    res = solve(chain, T, seed=0)
    s = res.summary()
    ok = res.success
    assert s["targets"] == 10
    assert s["success_rate"] == pytest.approx(ok.double().mean().item())  # the fraction of the flags
    assert s["median_position_error"] == pytest.approx(res.position_error.median().item())
    assert s["max_position_error_success"] == pytest.approx(res.position_error[ok].max().item())
    assert s["max_position_error_success"] <= 1e-4 and s["max_orientation_error_success"] <= 1e-3
    assert s["mean_seeds_tried"] == pytest.approx(res.seeds_tried.double().mean().item())
    assert f"{100 * s['success_rate']:.2f} %" in str(res)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_solve_cuda():
    chain = load("panda", dtype=torch.float32, device="cuda")
    cpu = chain.copy().cpu()  # Module.cpu() moves in place: the CUDA chain must stay on the GPU
    _, T = targets(cpu, (500,), seed=12)
    res = solve(chain, T.cuda(), generator=torch.Generator(device="cuda").manual_seed(0))
    assert res.q.is_cuda and res.success.double().mean() >= 0.99
    assert_honest(cpu, res.to(device="cpu"), T)


@pytest.mark.parametrize("name", ["panda", "ur5", "stanford", "urdf_ur5"])
def test_batch_last_kernel_matches_geometric_jacobian(name):
    """The solver's batch-last kernel agrees with diffkin.jacobian on DH (incl. prismatic) and URDF."""
    from diffkin.ik._kernel import BatchLastKernel
    from diffkin.jacobian import forward_kinematics_and_jacobian

    chain = from_urdf(DATA_DIR / "ur5.urdf", "tool0", dtype=F64) if name == "urdf_ur5" else chain64(name)
    q = chain.random_configuration((50,), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        T_ref, J_ref = forward_kinematics_and_jacobian(chain, q)
        J, x, y, z, p = BatchLastKernel(chain)(q.T.contiguous())
    torch.testing.assert_close(J.permute(2, 1, 0), J_ref)
    torch.testing.assert_close(torch.stack((x, y, z, p), 1).permute(2, 0, 1), T_ref[:, :3, :])


def test_solve_prismatic_chain():
    chain = chain64("stanford")
    _, T = targets(chain, (100,), seed=13)
    res = solve(chain, T, seed=0)
    assert res.success.double().mean() >= 0.99
    assert_honest(chain, res, T)


# ------------------------------------------------------------------------------------------------ trees
def _tree_reference_errors(path, chain, q, T_target):
    """Worst error over the end links by the tests' own numpy URDF FK (not diffkin's kernels)."""
    from urdf_reference import ReferenceTree

    ref = ReferenceTree(path)
    pos, ori = [], []
    for qi, Ti in zip(q.detach().double().numpy(), T_target.double().numpy()):
        values = dict(zip(chain.joint_names, qi))
        Tr = np.stack([ref.fk(values, end) for end in chain.end_links])
        if Ti.shape[-1] == 3:
            pos.append(np.linalg.norm(Tr[:, :3, 3] - Ti, axis=-1).max())
            continue
        pos.append(np.linalg.norm(Tr[:, :3, 3] - Ti[:, :3, 3], axis=-1).max())
        rel = np.einsum("kji,kjl->kil", Tr[:, :3, :3], Ti[:, :3, :3])
        ori.append(Rotation.from_matrix(rel).magnitude().max())
    return np.array(pos), np.array(ori) if ori else None


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_solve_two_arm_tree_full_pose(dtype):
    """Both Baxter arms at once: T_target (..., K, 4, 4); success only when both meet the tolerances, and the
    flags agree with an independent FK."""
    from pathlib import Path

    path = Path(__file__).parent / "data" / "urdf" / "baxter.urdf"
    chain = from_urdf(path, ["left_gripper", "right_gripper"], dtype=dtype)
    _, T = targets(chain, (40,), seed=4)
    res = solve(chain, T.reshape(4, 10, 2, 4, 4), seed=0, num_seeds=128)
    assert res.q.shape == (4, 10, 14) and res.success.shape == (4, 10)
    assert res.success.float().mean() >= 0.95
    pos, ori = _tree_reference_errors(path, chain, res.q.reshape(40, 14), T)
    ok = (pos <= TOL_P * 1.001) & (ori <= TOL_O * 1.001)
    assert bool((ok | ~res.success.reshape(40).numpy()).all())  # a success flag is never wrong
    assert bool(chain.within_limits(res.q)[res.success].all())


def test_solve_hand_fingertip_positions_and_shape_errors():
    from pathlib import Path

    path = Path(__file__).parent / "data" / "urdf" / "allegro_right_hand.urdf"
    tips = [f"link_{i}.0_tip" for i in (3, 7, 11, 15)]
    chain = from_urdf(path, tips, dtype=F64)
    _, T = targets(chain, (60,), seed=5)
    p = T[..., :3, 3]  # (60, 4, 3)
    res = solve(chain, p, position_only=True, seed=0)
    assert res.success.float().mean() >= 0.98 and res.q.shape == (60, 16)
    pos, _ = _tree_reference_errors(path, chain, res.q, p)
    assert bool(((pos <= TOL_P * 1.001) | ~res.success.numpy()).all())
    with pytest.raises(ShapeError, match=r"\(\.\.\., 4, 3\)"):
        solve(chain, p[:, :3], position_only=True)
    with pytest.raises(ShapeError, match=r"\(\.\.\., 4, 4, 4\)"):
        solve(chain, T[:, 0])


# ------------------------------------------------------------------ the input rule and boundary cases (#15)
@pytest.mark.parametrize("bad", [torch.float16, torch.bfloat16, torch.int64])
def test_half_and_integer_targets_are_refused(bad):
    """float16/bfloat16 used to pass and report success 1.4 mm from a 0.1 mm target: now DTypeError."""
    chain = chain64("panda")
    _, T = targets(chain, (4,), seed=3)
    with pytest.raises(DTypeError):
        solve(chain, T[..., :3, 3].to(bad), position_only=True, seed=0)
    with pytest.raises(DTypeError):
        solve(chain.float(), T.to(bad), seed=0)


def test_far_target_errors_are_finite_in_float32():
    """A 1e30 m target: finite errors (an overflow-safe norm), never success."""
    chain = load("panda", dtype=torch.float32)
    p = torch.tensor([[1e30, 0.0, 0.0], [0.3, 0.2, 0.5]])
    res = solve(chain, p, position_only=True, seed=0, num_seeds=4)
    assert torch.isfinite(res.q).all() and torch.isfinite(res.position_error).all()
    assert res.position_error[0] == pytest.approx(1e30, rel=1e-3)
    assert not bool(res.success[0])
    T = torch.eye(4).expand(2, 4, 4).clone()
    T[0, 0, 3] = -3e30
    res = solve(chain, T, seed=0, num_seeds=4)
    assert torch.isfinite(res.position_error).all() and not bool(res.success[0])


def test_empty_batches_give_empty_results():
    from diffkin.ik import clik, closed_form, optimize, refine_path

    chain = chain64("ur5")
    T = torch.zeros(0, 4, 4, dtype=F64)
    for res in (solve(chain, T, seed=0), optimize(chain, T)):
        assert res.q.shape == (0, 6) and res.success.shape == (0,) and res.position_error.shape == (0,)
    q0 = torch.zeros(0, 6, dtype=F64)
    out = clik(chain, (torch.eye(4, dtype=F64).expand(0, 3, 4, 4),), q0, 0.01)
    assert out.q.shape == (0, 3, 6) and out.position_error.shape == (0, 3)
    sol = closed_form(chain, T)
    assert sol.q.shape[0] == 0 and sol.success.shape[0] == 0
    assert refine_path(torch.eye(4, dtype=F64).expand(0, 3, 4, 4), 2).shape == (0, 5, 4, 4)
    assert dls_step(chain, q0, T).shape == (0, 6)


def test_numpy_and_numbers_follow_the_chain():
    chain = chain64("ur5").float()
    q, T = targets(chain, (3,), seed=5)
    a = solve(chain, T.numpy().astype(np.float64), seed=0)  # a float64 array to a float32 chain: converted
    b = solve(chain, T, seed=0)
    assert a.q.dtype == torch.float32
    torch.testing.assert_close(a.q, b.q)
    torch.testing.assert_close(dls_step(chain, q.tolist(), T.numpy()), dls_step(chain, q, T))


def test_dls_step_refuses_nan_and_bad_shapes():
    chain = chain64("ur5")
    q, T = targets(chain, (3,), seed=6)
    p = T[..., :3, 3].clone()
    p[1, 2] = float("nan")
    with pytest.raises(NonFiniteError):
        dls_step(chain, q, p, position_only=True)  # used to pass NaN through
    with pytest.raises(ShapeError):
        dls_step(chain, q, T[..., :3, :])  # (..., 3, 4) is neither a pose nor a position
    with pytest.raises(ShapeError):
        dls_step(chain, q, torch.zeros(3, 4, dtype=F64), position_only=True)
    with pytest.raises(NonFiniteError):
        dls_step(chain, q, T, damping=float("nan"))
    with pytest.raises(NonFiniteError):
        solve(chain, T, position_tolerance=float("nan"))


def test_dls_with_zero_damping_is_finite_at_a_singularity():
    chain = chain64("ur5")
    q = torch.zeros(2, 6, dtype=F64)  # UR5 at q = 0: singular
    q[1] = torch.tensor([0.1, -1.0, 1.2, 0.3, 0.9, 0.2])
    _, T = targets(chain, (2,), seed=7)
    out = dls_step(chain, q, T, damping=0.0)
    assert torch.isfinite(out).all()
    J = torch.randn(6, 3, dtype=F64) @ torch.randn(3, 7, dtype=F64)  # rank 3
    e = torch.randn(6, dtype=F64)
    np.testing.assert_allclose(dls_delta(J, e, 0.0).numpy(), np.linalg.pinv(J.numpy()) @ e.numpy(), atol=1e-9)


def test_lockstep_seeds_equal_the_sequential_schedule(monkeypatch):
    """The torch backend's lockstep rounds (ik/_lm.py: seeds 0 | 1-2 | 3-6 | 7 in fixed slots)
    give the sequential schedule's flags, iterations, seeds tried and q, unreachable targets (every seed
    tried, the least-merit one kept) included; without the C solve, so it runs where there is no compiler."""
    from diffkin.ik import _lm
    from diffkin.kernels import native

    chain = chain64("panda")
    _, T = targets(chain, (16,), seed=31)
    T[:3, 0, 3] += 5.0
    kw = dict(seed=2, num_seeds=8, max_iterations=10, config=_lm.LMConfig(library_size=0))
    with native.disabled(), torch.no_grad():
        a = solve(chain, T, **kw)
        monkeypatch.setattr(_lm, "_run_lockstep", _lm._run_sequential)
        b = solve(chain, T, **kw)
    assert torch.equal(a.success, b.success) and torch.equal(a.iterations, b.iterations)
    assert torch.equal(a.seeds_tried, b.seeds_tried) and bool((a.seeds_tried[:3] == 8).all())
    torch.testing.assert_close(a.q, b.q, atol=1e-12, rtol=0)
    assert int(a.success[3:].sum()) >= 10 and not bool(a.success[:3].any())
