"""CLIK (§3.7): the error behaves as the book says (exponential decay with rate K for the Jacobian inverse,
bounded for the transpose, drift without feedback), null-space objectives improve, second order tracks."""

from __future__ import annotations

import math

import pytest
import torch

from diffkin import models
from diffkin.chain import DHChain
from diffkin.errors import ConventionError, ModelError, ShapeError
from diffkin.ik.closed_loop import (
    CLIK_ALGORITHMS,
    CLIK_ORIENTATIONS,
    _jdot_qdot,
    _make_task,
    clik,
    joint_limit_objective,
)
from diffkin.jacobian import analytical_jacobian, geometric_jacobian
from diffkin.manipulability import manipulability
from diffkin.rotations import euler_rate_matrix, matrix_to_euler, rot_z

PI = math.pi
F64 = torch.float64
DT = 1e-3
Q0_BOOK = torch.tensor([PI, -PI / 2, -PI / 2], dtype=F64)  # §3.7.5: p = (0, 0.5), φ = 0
LIMITS = torch.tensor([[-2 * PI, 2 * PI], [-PI / 2, PI / 2], [-3 * PI / 2, -PI / 2]], dtype=F64)
PLANAR = dict(orientation="euler", convention="RPY", rows=(0, 1, 3))
POSITION = dict(orientation=None, rows=(0, 1))


@pytest.fixture(scope="module")
def planar():
    return models.load("three_link_planar", dtype=F64)  # a = 0.5 m (Table 2.1, §3.7.5)


def book_circle(duration: float):
    """x_d = [p; φ] (RPY) and ẋ_d of §3.7.5, sampled every 1 ms: (S, 6) each."""
    t = torch.arange(round(duration / DT) + 1, dtype=F64) * DT
    z = torch.zeros_like(t)
    p = torch.stack([0.25 * (1 - torch.cos(PI * t)), 0.25 * (2 + torch.sin(PI * t)), z], -1)
    v = torch.stack([0.25 * PI * torch.sin(PI * t), 0.25 * PI * torch.cos(PI * t), z], -1)
    phi = torch.stack([torch.sin(PI * t / 24), z, z], -1)
    dphi = torch.stack([PI / 24 * torch.cos(PI * t / 24), z, z], -1)
    return torch.cat([p, phi], -1), torch.cat([v, dphi], -1)


@pytest.fixture(scope="module")
def circle_runs(planar):
    """One second of the book's circle with the book's gains: open loop, inverse, pseudo-inverse (±q̇₀)."""
    x, xd = book_circle(1.0)
    w_book = lambda q: 0.5 * (torch.sin(q[..., 1]) ** 2 + torch.sin(q[..., 2]) ** 2)  # noqa: E731
    pos = (x[:, :3], xd[:, :3])
    return {
        "open": clik(planar, (x, xd), Q0_BOOK, DT, algorithm="inverse", K=0.0, **PLANAR),
        "inverse": clik(planar, (x, xd), Q0_BOOK, DT, algorithm="inverse", K=[500, 500, 100], **PLANAR),
        "pinv": clik(planar, pos, Q0_BOOK, DT, algorithm="pseudo_inverse", K=500, **POSITION),
        "manip": clik(planar, pos, Q0_BOOK, DT, K=500, nullspace=w_book, k0=50, **POSITION),
        "limits": clik(
            planar, pos, Q0_BOOK, DT, K=500, nullspace="joint_limits", k0=250, q_limits=LIMITS, **POSITION
        ),  # fmt: skip
        "w_book": w_book,
    }


def test_inverse_error_decays_with_rate_K(planar):
    """ė + K e = 0 (3.71); with Euler steps e_k = (1 − K Δt)^k e_0 per component (K diagonal)."""
    x0 = torch.tensor([0.0, 0.5, 0.0, 0.0, 0.0, 0.0], dtype=F64)
    e0 = torch.tensor([2e-5, -1e-5, 0, 3e-5, 0, 0], dtype=F64)
    K = torch.tensor([500.0, 200.0, 100.0], dtype=F64)
    res = clik(planar, ((x0 + e0)[None],), Q0_BOOK, DT, 30, algorithm="inverse", K=K, **PLANAR)
    assert res.error.shape == (31, 3) and res.q.shape == (31, 3) and res.t.shape == (31,)
    assert torch.allclose(res.error[0], e0[[0, 1, 3]], atol=1e-15)
    for k in (1, 5, 20):
        expected = (1 - K * DT) ** k * e0[[0, 1, 3]]
        assert torch.allclose(res.error[k], expected, rtol=1e-3, atol=1e-13)
    # the rate −ln(e(t)/e(0))/t is −ln(1 − KΔt)/Δt -> K as Δt -> 0 (within 6 % where KΔt <= 0.1)
    rate = -torch.log(res.error[20] / res.error[0]) / res.t[20]
    assert abs(rate[2] - K[2]) < 0.06 * K[2] and (rate > K).all()


def test_open_loop_drifts_closed_loop_does_not(circle_runs):
    op, cl = circle_runs["open"], circle_runs["inverse"]
    assert op.position_error[-1] > 1e-4  # drift of the open-loop scheme (Fig. 3.15)
    assert op.position_error.max() > 30 * cl.position_error.max()
    assert cl.position_error.max() < 2e-5 and cl.orientation_error.max() < 1e-7  # Fig. 3.16: ~1e-5, ~1e-8
    assert op.orientation_error[-1] > 10 * cl.orientation_error[-1]


def test_transpose_bounded_and_converges(planar):
    x, xd = book_circle(0.4)
    # the target stops after 0.4 s (last sample at rest), the run goes on to 0.6 s
    xd = xd.clone()
    xd[-1] = 0
    res = clik(planar, (x[:, :3], xd[:, :3]), Q0_BOOK, DT, 600, algorithm="transpose", K=500, **POSITION)
    assert res.position_error.max() < 2e-2  # bounded along the trajectory (Fig. 3.18: a few mm)
    assert res.position_error[400] > 1e-3
    assert res.position_error[-1] < 1e-6  # and tends to zero at rest


def test_nullspace_manipulability_raises_w_without_hurting_tracking(circle_runs, planar):
    free, con, w = circle_runs["pinv"], circle_runs["manip"], circle_runs["w_book"]
    assert w(con.q).mean() > w(free.q).mean() + 0.02
    assert w(con.q).min() > w(free.q).min()
    assert con.position_error.max() < 1e-5 and free.position_error.max() < 1e-5  # Fig. 3.17 / 3.19
    assert torch.allclose(con.q[:, 1], con.q[:, 2], atol=0.05)  # "coincident trajectories for joints 2, 3"
    # the general objective (3.56) w = sqrt(det(J Jᵀ)) of the 2 × 3 task Jacobian, gradient by autograd
    x, xd = book_circle(0.3)
    pos = (x[:, :3], xd[:, :3])
    a = clik(planar, pos, Q0_BOOK, DT, K=500, **POSITION)
    b = clik(planar, pos, Q0_BOOK, DT, K=500, nullspace="manipulability", k0=50, **POSITION)
    mu = lambda r: manipulability(geometric_jacobian(planar, r.q)[..., :2, :])  # noqa: E731
    assert mu(b).mean() > mu(a).mean() and b.position_error.max() < 1e-5


def test_nullspace_joint_limits(circle_runs):
    lo, hi = LIMITS[:, 0], LIMITS[:, 1]
    free, con = circle_runs["pinv"], circle_runs["limits"]
    outside = lambda q: ((q < lo) | (q > hi)).any(-1)  # noqa: E731
    assert outside(free.q).any()  # the unconstrained joints 2 and 3 leave their ranges (§3.7.5)
    assert not outside(con.q[1:]).any()
    assert joint_limit_objective(con.q, lo, hi).min() > joint_limit_objective(free.q, lo, hi).min()
    assert con.position_error.max() < 1e-3  # "bounded anyhow within acceptable values"


def test_second_order_tracks(planar):
    """(3.102) with the analytical Jacobian: from an initial error, ë + K_D ė + K_P e = 0 (3.103)."""
    x, xd = book_circle(0.5)
    t = torch.arange(x.shape[0], dtype=F64) * DT
    xdd = torch.zeros_like(x)
    xdd[:, 0] = 0.25 * PI**2 * torch.cos(PI * t)
    xdd[:, 1] = -0.25 * PI**2 * torch.sin(PI * t)
    xdd[:, 3] = -((PI / 24) ** 2) * torch.sin(PI * t / 24)
    q0 = Q0_BOOK + torch.tensor([0.01, -0.01, 0.005], dtype=F64)
    res = clik(planar, (x, xd, xdd), q0, DT, algorithm="second_order", K_P=2500.0, K_D=100.0, **PLANAR)
    assert res.position_error[0] > 1e-3
    # Euler integration leaves a tracking error proportional to Δt (3e-5 m here, 8e-6 m at Δt/4)
    assert res.position_error[-100:].max() < 5e-5 and res.orientation_error[-100:].max() < 1e-6
    # without the acceleration feedforward ẍ_d the error is K_P e ≈ ẍ_d: 30 times larger
    no_ff = clik(planar, (x, xd), q0, DT, algorithm="second_order", K_P=2500.0, K_D=100.0, **PLANAR)
    assert no_ff.position_error[-1] > 30 * res.position_error[-1]


def test_jdot_qdot_matches_finite_differences():
    chain = models.load("anthropomorphic_wrist", dtype=F64)
    g = torch.Generator().manual_seed(0)
    q, qd = torch.rand(2, 6, generator=g, dtype=F64), torch.randn(2, 6, generator=g, dtype=F64)
    h = 1e-6
    for orientation, JA in (
        ("euler", lambda q: analytical_jacobian(chain, q, "ZYZ")),
        ("axis_angle", lambda q: geometric_jacobian(chain, q)),
    ):
        fd = ((JA(q + h * qd) - JA(q - h * qd)) @ qd[..., None])[..., 0] / (2 * h)
        got = _jdot_qdot(chain, q, qd, _make_task(chain, orientation, "ZYZ", None))
        assert torch.allclose(got, fd, atol=1e-6)


def _moving_pose(chain, q0, steps):
    """T_d(t): p moves along x at 5 cm/s, R turns about z at 0.5 rad/s; twist [ṗ; ω]."""
    T0 = chain.forward_kinematics(q0)
    t = torch.arange(steps + 1, dtype=F64) * DT
    T = T0.repeat(steps + 1, 1, 1)
    T[:, :3, :3] = rot_z(0.5 * t) @ T0[:3, :3]
    T[:, :3, 3] = T0[:3, 3] + 0.05 * t[:, None] * torch.tensor([1.0, 0, 0], dtype=F64)
    v = torch.tensor([0.05, 0, 0, 0, 0, 0.5], dtype=F64).repeat(steps + 1, 1)
    return T, v


@pytest.mark.parametrize("orientation", ["euler", "axis_angle", "quaternion"])
def test_orientation_errors_track_a_moving_pose(orientation):
    """(3.82) Euler with J_A, (3.89) angle-axis and (3.92) quaternion with J: a 6-DOF arm follows."""
    chain = models.load("anthropomorphic_wrist", dtype=F64)
    q0 = torch.tensor([0.2, 0.4, 0.3, 0.5, 0.8, -0.3], dtype=F64)
    T, v = _moving_pose(chain, q0, 150)
    if orientation == "euler":  # [p; φ] and [ṗ; φ̇] with φ̇ = T(φ)⁻¹ ω (3.64)
        phi = matrix_to_euler(T[:, :3, :3], "ZYZ")
        phidot = torch.linalg.solve(euler_rate_matrix(phi, "ZYZ"), v[:, 3:])
        target = (torch.cat([T[:, :3, 3], phi], -1), torch.cat([v[:, :3], phidot], -1))
    else:
        target = (T, v)
    res = clik(
        chain, target, q0, DT, algorithm="inverse", K=500.0, orientation=orientation, return_poses=True
    )
    assert res.poses.shape == (151, 4, 4)
    assert res.position_error.max() < 1e-6 and res.orientation_error.max() < 1e-6
    assert (res.poses[-1, :3, 3] - T[-1, :3, 3]).norm() < 1e-6
    # a perturbed start converges at rate K (ė = −K e for position, (3.93)/(3.86) for orientation)
    res = clik(chain, target, q0 + 0.02, DT, algorithm="dls", damping=1e-8, K=200.0, orientation=orientation)
    assert res.position_error[0] > 1e-3 and res.position_error[-1] < 1e-6 and res.orientation_error[-1] < 1e-6


def test_dls_and_pinv_stay_finite_out_of_reach(planar):
    """Out of reach the arm stretches (a singularity): DLS (3.59) and the transpose approach the closest
    point; the plain pseudo-inverse spins the joints (as the book warns) but stays finite."""
    far = torch.tensor([[2.0, 1.0, 0.0]], dtype=F64)
    reach_gap = far[0, :2].norm() - 1.5
    for alg in ("dls", "pseudo_inverse", "transpose"):
        res = clik(planar, (far,), Q0_BOOK, DT, 300, algorithm=alg, K=100.0, damping=0.0025, **POSITION)
        assert torch.isfinite(res.q).all() and torch.isfinite(res.error).all()
        if alg != "pseudo_inverse":
            assert res.position_error[-1] < reach_gap + 0.06


def test_batch_broadcast_matches_single_runs(planar):
    x, xd = book_circle(0.05)
    shift = torch.tensor([0.0, 0.01, -0.01, 0.02], dtype=F64)[:, None, None]
    xb = x + shift * torch.tensor([1.0, 1.0, 0, 0, 0, 0], dtype=F64)  # (4, S, 6)
    q0 = Q0_BOOK + torch.tensor([[0.0], [0.01]], dtype=F64)[:, None, :]  # (2, 1, 3)
    res = clik(planar, (xb, xd), q0, DT, algorithm="pseudo_inverse", K=300.0, **PLANAR)
    assert res.q.shape == (2, 4, 51, 3) and res.error.shape == (2, 4, 51, 3)
    assert res.position_error.shape == (2, 4, 51)
    one = clik(planar, (xb[2], xd), q0[1, 0], DT, algorithm="pseudo_inverse", K=300.0, **PLANAR)
    assert torch.allclose(res.q[1, 2], one.q, atol=1e-12)


def test_differentiable_through_the_integration(planar):
    x, xd = book_circle(0.005)

    def final_error(q0):
        return clik(planar, (x, xd), q0, DT, algorithm="inverse", K=[500, 500, 100], **PLANAR).error[-1]

    q0 = (Q0_BOOK + 0.01).requires_grad_(True)
    assert torch.autograd.gradcheck(final_error, (q0,))
    chain = planar.copy().requires_grad_()
    res = clik(chain, (x, xd), Q0_BOOK, DT, algorithm="inverse", differentiable=True, **PLANAR)
    res.position_error[-1].backward()
    # w.r.t. the DH table: central differences of the whole integration with a_i moved by ±h
    h = 1e-6
    fd = torch.zeros(3, dtype=F64)
    for i in range(3):
        ends = []
        for sign in (1.0, -1.0):
            moved = planar.copy()
            with torch.no_grad():
                moved.a[i] += sign * h
                res_h = clik(moved, (x, xd), Q0_BOOK, DT, algorithm="inverse", **PLANAR)
                ends.append(res_h.position_error[-1])
        fd[i] = (ends[0] - ends[1]) / (2 * h)
    assert fd.abs().max() > 1e-3  # a real dependence, not a vanishing one
    torch.testing.assert_close(chain.a.grad, fd, rtol=1e-3, atol=1e-6)
    assert not clik(planar, (x, xd), Q0_BOOK, DT, **PLANAR).q.requires_grad  # no graph by default


def test_callable_target_and_clamp(planar):
    def target(t):
        return torch.stack([0.5 + 0.1 * t, 0.5 + 0 * t, 0 * t]), torch.stack([0.1 + 0 * t, 0 * t, 0 * t])

    lim_chain = DHChain(planar.a.detach(), planar.alpha.detach(), planar.d.detach(), planar.theta.detach(),
                        q_limits=LIMITS)  # fmt: skip
    res = clik(lim_chain, target, Q0_BOOK, DT, 100, algorithm="dls", clamp=True, **POSITION)
    assert res.q.shape == (101, 3) and lim_chain.within_limits(res.q).all()
    with pytest.raises(ConventionError, match="steps"):
        clik(planar, target, Q0_BOOK, DT, **POSITION)


def test_bad_input():
    planar = models.load("three_link_planar", dtype=F64)
    x = torch.zeros(3, 6, dtype=F64)
    with pytest.raises(ConventionError):
        clik(planar, (x,), Q0_BOOK, DT, algorithm="newton")
    with pytest.raises(ConventionError):
        clik(planar, (x,), Q0_BOOK, DT, orientation="rodrigues")
    assert None in CLIK_ORIENTATIONS
    with pytest.raises(ShapeError, match="square"):
        clik(planar, (x[:, :3],), Q0_BOOK, DT, algorithm="inverse", **POSITION)
    with pytest.raises(ShapeError):
        clik(planar, (x,), Q0_BOOK, DT, K=torch.ones(4, dtype=F64), **PLANAR)
    with pytest.raises(ShapeError, match="poses"):
        clik(planar, (x,), Q0_BOOK, DT, orientation="quaternion")
    with pytest.raises(ShapeError):
        clik(planar, (x,), Q0_BOOK, DT, rows=(0, 7), orientation=None)
    no_limits = DHChain([0.5] * 3, [0.0] * 3, [0.0] * 3, [0.0] * 3)
    with pytest.raises(ModelError, match="q_limits"):
        clik(no_limits.double(), (x[:, :3],), Q0_BOOK, DT, nullspace="joint_limits", **POSITION)
    with pytest.raises(ConventionError):
        clik(planar, (x[:, :3],), Q0_BOOK, DT, nullspace="distance", **POSITION)
    with pytest.raises(ShapeError):
        clik(planar, (x,), Q0_BOOK[:2], DT, **PLANAR)


# ------------------------------------------------------------------------- finite everywhere (#15)
def _ur5_starts_and_targets():
    chain = models.load("ur5", dtype=F64)
    g = torch.Generator().manual_seed(1)
    starts = torch.cat([torch.zeros(1, 6, dtype=F64),  # q = 0: shoulder/elbow and wrist singular
                        torch.tensor([[0.3, -1.0, 1.1, 0.2, 0.0, 0.5]], dtype=F64),  # wrist singular (ϑ5 = 0)
                        chain.random_configuration((50,), generator=g)])  # fmt: skip
    with torch.no_grad():
        T = chain.forward_kinematics(chain.random_configuration((52,), generator=g))
    return chain, starts, T


@pytest.mark.parametrize("algorithm", CLIK_ALGORITHMS)
def test_every_algorithm_stays_finite_from_singular_and_random_starts(algorithm):
    """Second-order CLIK used to return NaN from step 11 at UR5 q = 0 and from some random starts."""
    chain, starts, T = _ur5_starts_and_targets()
    euler = torch.cat((T[:, :3, 3], matrix_to_euler(T[:, :3, :3], "ZYZ")), dim=-1)
    for orientation in CLIK_ORIENTATIONS:
        x = {None: T[:, None, :3, 3], "euler": euler[:, None]}.get(orientation, T[:, None])
        if algorithm == "inverse" and orientation is None:
            continue  # 3 rows for 6 joints: not square
        res = clik(chain, (x,), starts, DT, 40, algorithm=algorithm, orientation=orientation)
        for name in ("q", "qdot", "error", "position_error", "orientation_error"):
            assert torch.isfinite(getattr(res, name)).all(), (algorithm, orientation, name)


def test_default_clik_from_a_stretched_planar_arm():
    """pinv raised torch's _LinAlgError on the stretched arm, so clik's default did too."""
    planar = models.load("three_link_planar", dtype=F64)
    q0 = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]], dtype=F64)
    x = torch.tensor([0.6, 0.9, 0.2], dtype=F64).expand(2, 1, 3)
    for algorithm in ("pseudo_inverse", "second_order", "dls"):
        res = clik(planar, (x,), q0, DT, 50, algorithm=algorithm, orientation=None, rows=(0, 1))
        assert torch.isfinite(res.q).all() and torch.isfinite(res.qdot).all()
    res = clik(planar, (x,), q0, DT, 2000, orientation=None, rows=(0, 1))
    assert (res.position_error[:, -1] < 1e-6).all()  # leaves the singularity and converges


def test_clik_refuses_non_finite_targets():
    from diffkin.errors import NonFiniteError

    planar = models.load("three_link_planar", dtype=F64)
    x = torch.tensor([[0.6, 0.9, 0.2]], dtype=F64)
    bad = x.clone()
    bad[0, 1] = float("nan")
    with pytest.raises(NonFiniteError):
        clik(planar, (bad,), Q0_BOOK, DT, **POSITION)
    with pytest.raises(NonFiniteError):
        clik(planar, (x, torch.full((1, 3), float("inf"), dtype=F64)), Q0_BOOK, DT, **POSITION)
    with pytest.raises(NonFiniteError):
        clik(planar, lambda t: (bad[0],), Q0_BOOK, DT, 3, **POSITION)
    with pytest.raises(ShapeError):  # a derivative of the wrong size is refused, not cut
        clik(planar, (x, torch.zeros(1, 5, dtype=F64)), Q0_BOOK, DT, **POSITION)
    with pytest.raises(ShapeError):
        clik(planar, (torch.zeros(1, 4, dtype=F64),), Q0_BOOK, DT, **POSITION)
