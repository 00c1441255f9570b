"""One meaning of ``damping`` in every solver: λ, added to JJᵀ's (or JᵀJ's) diagonal, eq. (3.59)
J* = Jᵀ(JJᵀ + λI)⁻¹ (the textbook's k²). Each public function's step is checked against numpy's solve of
that system with the same λ: ``dls_delta``, ``dls_step``, ``solve`` (one LM step, both backends; λ̄ of
λ̄ + μ‖e‖² with μ = 0), ``optimize`` (Gauss–Newton's first step), ``clik`` and ``solve_velocity``."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from diffkin import ik, models
from diffkin.kernels import native

F64 = torch.float64
LAM = 0.04  # 0.2²: a λ whose square root or square would give a visibly different step


def _dls(J: np.ndarray, e: np.ndarray, lam: float) -> np.ndarray:
    """Jᵀ(JJᵀ + λI)⁻¹ e (3.59) by numpy, one row at a time."""
    return np.stack([j.T @ np.linalg.solve(j @ j.T + lam * np.eye(j.shape[0]), v) for j, v in zip(J, e)])


def _ur5_rows(n: int, seed: int, spread: float = 0.3):
    chain = models.load("ur5", dtype=F64)
    g = torch.Generator().manual_seed(seed)
    lo, hi = chain.lower_upper()
    q0 = (0.5 * (lo + hi) + 0.6 * (torch.rand(n, chain.nq, generator=g, dtype=F64) - 0.5)).detach()
    with torch.no_grad():
        T = chain.forward_kinematics(q0 + spread * (torch.rand(n, chain.nq, generator=g, dtype=F64) - 0.5))
        T0, J = chain.forward_kinematics_and_jacobian(q0)
    return chain, q0, T, T0, J


def _pose_error(T: torch.Tensor, T0: torch.Tensor, w_o: float = 1.0) -> np.ndarray:
    """[p_d − p_e; √w θr] with θr the rotation vector of R_d R_eᵀ (scipy)."""
    dp = (T[..., :3, 3] - T0[..., :3, 3]).numpy()
    R = (T[..., :3, :3] @ T0[..., :3, :3].mT).numpy()
    return np.concatenate((dp, w_o**0.5 * Rotation.from_matrix(R).as_rotvec()), -1)


def test_dls_delta_adds_lambda_to_the_diagonal():
    g = torch.Generator().manual_seed(0)
    J, e = torch.randn(4, 6, 7, generator=g, dtype=F64), torch.randn(4, 6, generator=g, dtype=F64)
    np.testing.assert_allclose(ik.dls_delta(J, e, LAM).numpy(), _dls(J.numpy(), e.numpy(), LAM), atol=1e-12)
    tall = J.mT[..., :4]  # 7 x 4: the same λ in the tall form (JᵀJ + λI)⁻¹Jᵀe
    e4 = e.new_ones(4, 7)
    want = np.stack([np.linalg.solve(j.T @ j + LAM * np.eye(4), j.T @ v)
                     for j, v in zip(tall.numpy(), e4.numpy())])
    np.testing.assert_allclose(ik.dls_delta(tall, e4, LAM).numpy(), want, atol=1e-12)


def test_dls_step_adds_lambda_to_the_diagonal():
    chain, q0, T, T0, J = _ur5_rows(6, 1)
    q1 = ik.dls_step(chain, q0, T, damping=LAM, respect_limits=False)
    want = q0.numpy() + _dls(J.numpy(), _pose_error(T, T0), LAM)
    np.testing.assert_allclose(q1.numpy(), want, atol=1e-12)


@pytest.mark.parametrize("backend", ["c", "torch"])
def test_solve_takes_lambda_bar(backend):
    """One LM step of ``ik.solve`` (max_iterations 2, a stall check every 2: one step, then the seed ends):
    q0 + J_wᵀ(J_w J_wᵀ + λ̄ I)⁻¹ e_w with J_w, e_w the orientation rows scaled by √w (μ = 0)."""
    if backend == "c" and not native.available():
        pytest.skip("no C compiler")
    chain, q0, T, T0, J = _ur5_rows(6, 2)
    w = 0.3
    cfg = ik.LMConfig(damping=LAM, error_damping=0.0, orientation_weight=w, library_size=0, check_every=2)
    kw = dict(q0=q0, num_seeds=1, max_iterations=2, respect_limits=False, config=cfg, seed=0)
    with torch.no_grad(), (native.disabled() if backend == "torch" else torch.no_grad()):
        res = ik.solve(chain, T, **kw)
    assert not bool(res.success.any()) and bool((res.iterations == 2).all())  # one step taken, not done
    Jw = J.numpy().copy()
    Jw[:, 3:] *= w**0.5
    want = q0.numpy() + _dls(Jw, _pose_error(T, T0, w), LAM)
    np.testing.assert_allclose(res.q.numpy(), want, atol=1e-10)
    with torch.no_grad():  # the damping argument is the same λ̄ as the config's
        np.testing.assert_allclose(ik.solve(chain, T, damping=LAM, **{**kw, "config": ik.LMConfig(
            damping=1.0, error_damping=0.0, orientation_weight=w, library_size=0, check_every=2)}).q.numpy(),
            want, atol=1e-10)


def test_optimize_gauss_newton_starts_from_lambda():
    """The first Gauss–Newton step of a rest-posture cost r = q − q_rest (J = I) is
    −(JᵀJ + λI)⁻¹Jᵀr = −r/(1 + λ)."""
    chain, q0, T, _, _ = _ur5_rows(3, 3)
    q_rest = q0 + 0.2
    res = ik.optimize(chain, T, q0, costs=[ik.RestPostureCost(q_rest=q_rest[0])], optimizer="gauss_newton",
                      max_iterations=1, damping=LAM, respect_limits=False)
    r = (q0 - q_rest[0]).numpy()
    np.testing.assert_allclose(res.q.detach().numpy(), q0.numpy() - r / (1.0 + LAM), atol=1e-12)


def test_clik_and_solve_velocity_take_the_same_lambda():
    chain, q0, T, T0, J = _ur5_rows(4, 4)
    K = 5.0
    res = ik.clik(chain, T[:, None, :3, 3], q0, 0.01, 0, algorithm="dls", orientation=None, K=K, damping=LAM)
    want = _dls(J[:, :3].numpy(), K * (T[:, :3, 3] - T0[:, :3, 3]).numpy(), LAM)
    np.testing.assert_allclose(res.qdot[:, 0].numpy(), want, atol=1e-12)
    twist = torch.randn(4, 6, generator=torch.Generator().manual_seed(5), dtype=F64)
    v = ik.solve_velocity(chain, q0, [ik.FrameTask(0, twist=twist)], 0.1, damping=LAM)
    # (D.1) with e = −ξΔt, Δq = q̇Δt: q̇ = Jᵀ(JJᵀ + λI)⁻¹ξ, the same λ
    np.testing.assert_allclose(v.numpy(), _dls(J.numpy(), twist.numpy(), LAM), atol=1e-10)


def test_calibration_least_squares_takes_lambda():
    """One step of the calibration least squares (2.88)–(2.89): on the unit-norm columns Ā = Φ̄ S⁻¹,
    Δζ = S⁻¹(ĀᵀĀ + λI)⁻¹Āᵀ Δx̄ with λ = ``damping`` (numpy)."""
    from diffkin.calibration.model import CalibrationModel, pose_residual
    from diffkin.calibration.solvers import least_squares

    chain = models.load("ur5", dtype=F64)
    model = CalibrationModel.from_chains(chain)
    g = torch.Generator().manual_seed(0)
    q = chain.random_configuration((12,), generator=g)[None]
    with torch.no_grad():
        T = model.forward_kinematics((model.nominal + 1e-3 * torch.randn(model.n_params, generator=g,
                                                                         dtype=F64))[None], q)
    cand, zeta0 = model.candidate, model.nominal[None].clone()
    P = int(cand.sum())
    out = least_squares(model, zeta0, torch.ones(1, P, dtype=F64), q, T, orientation_weight=1.0,
                        max_iterations=1, damping=LAM)
    Phi, Tm = model.calibration_matrix(zeta0, q, False, 1.0, cand)
    A, r = Phi.reshape(-1, P).numpy(), pose_residual(Tm, T, 1.0).reshape(-1).numpy()
    s = np.linalg.norm(A, axis=0)
    s[s == 0] = 1.0
    want = np.linalg.solve((A / s).T @ (A / s) + LAM * np.eye(P), (A / s).T @ r) / s
    np.testing.assert_allclose((out.zeta - zeta0)[0, cand].numpy(), want, atol=1e-14)


@pytest.mark.parametrize("fn", ["dls_delta", "damped_pinv", "weighted_pinv"])
def test_negative_damping_is_a_typed_error(fn):
    """λ < 0 is refused (it used to fall into the λ ≈ 0 branch and return the plain pseudo-inverse)."""
    from diffkin import redundancy
    from diffkin.errors import OptionError

    J, e = torch.eye(6, 7, dtype=torch.float64), torch.ones(6, dtype=torch.float64)
    call = {"dls_delta": lambda lam: ik.dls_delta(J, e, lam),
            "damped_pinv": lambda lam: redundancy.damped_pinv(J, lam),
            "weighted_pinv": lambda lam: redundancy.weighted_pinv(J, torch.ones(7, dtype=torch.float64),
                                                                  lam)}[fn]
    with pytest.raises(OptionError, match="damping >= 0"):
        call(-1.0)
    with pytest.raises(OptionError, match="damping >= 0"):
        call(torch.tensor(-1e-3, dtype=torch.float64))
    assert torch.isfinite(call(0.0)).all()
