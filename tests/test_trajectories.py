"""Tests of diffkin.trajectories against the textbook's closed forms (ch. 4), scipy splines, autograd and
finite differences."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.interpolate import CubicHermiteSpline, CubicSpline
from scipy.spatial.transform import Rotation

from diffkin import trajectories as tr
from diffkin.errors import DiffkinError, DTypeError, NonFiniteError, ShapeError
from diffkin.rotations import euler_to_matrix, matrix_to_quaternion, quaternion_to_matrix, vee

F64 = torch.float64
PI = math.pi


def tt(x):
    return torch.as_tensor(x, dtype=F64)


def d_dt(fn, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Autograd time derivatives of a trajectory's position and velocity, joint by joint: (..., T, n)."""
    t = t.clone().requires_grad_(True)
    out = fn(t)
    dpos, dvel = [], []
    for j in range(out.position.shape[-1]):
        dpos.append(torch.autograd.grad(out.position[..., j].sum(), t, retain_graph=True)[0])
        dvel.append(torch.autograd.grad(out.velocity[..., j].sum(), t, retain_graph=True)[0])
    return out, torch.stack(dpos, -1), torch.stack(dvel, -1)


# ------------------------------------------------------------------------------------ point to point
def test_problem_4_1_quintic_closed_form():
    """Problem 4.1: q(0)=1 -> q(2)=4, null end velocities and accelerations.

    Closed form: q = 1 + 3 (10 u^3 - 15 u^4 + 6 u^5), u = t/2.
    """
    t = torch.linspace(0, 2, 41, dtype=F64)
    out = tr.quintic(tt([1.0]), tt([4.0]), 2.0, t)
    u = t / 2
    q = 1 + 3 * (10 * u**3 - 15 * u**4 + 6 * u**5)
    qd = 3 * (30 * u**2 - 60 * u**3 + 30 * u**4) / 2
    qdd = 3 * (60 * u - 180 * u**2 + 120 * u**3) / 4
    torch.testing.assert_close(out.position[:, 0], q, atol=1e-12, rtol=0)
    torch.testing.assert_close(out.velocity[:, 0], qd, atol=1e-12, rtol=0)
    torch.testing.assert_close(out.acceleration[:, 0], qdd, atol=1e-12, rtol=0)
    # coefficients a3, a4, a5 = 3.75, -2.8125, 0.5625 of (4.2)
    tc = tt([0.5, 1.0, 1.5])
    ref = 1 + 3.75 * tc**3 - 2.8125 * tc**4 + 0.5625 * tc**5
    torch.testing.assert_close(
        tr.quintic(tt([1.0]), tt([4.0]), 2.0, tc).position[:, 0], ref, atol=1e-12, rtol=0
    )


def test_problem_4_1_one_joint_as_scalars():
    """Problem 4.1 as written, one joint of 0-d tensors (or numbers): the result is (T,), no joint axis."""
    t = torch.linspace(0, 2, 41, dtype=F64)
    u = t / 2
    q = 1 + 3 * (10 * u**3 - 15 * u**4 + 6 * u**5)  # (4.2) with the four null end conditions
    qd = 3 * (30 * u**2 - 60 * u**3 + 30 * u**4) / 2
    qdd = 3 * (60 * u - 180 * u**2 + 120 * u**3) / 4
    out = tr.quintic(tt(1.0), tt(4.0), 2.0, t)
    assert out.position.shape == out.velocity.shape == out.acceleration.shape == (41,)
    for got, ref in zip(out, (q, qd, qdd)):
        torch.testing.assert_close(got, ref, atol=1e-12, rtol=0)
    # the call: float32 0-d tensors and float64 query times would mix; float32 times follow them
    out32 = tr.quintic(torch.tensor(1.0), torch.tensor(4.0), 2.0, t.float())
    assert out32.position.dtype == torch.float32 and out32.position.shape == (41,)
    torch.testing.assert_close(out32.position.double(), q, atol=1e-5, rtol=0)
    assert float(out32.position[20]) == pytest.approx(2.5)  # midpoint, by symmetry
    with pytest.raises(DTypeError, match="float32"):
        tr.quintic(torch.tensor(1.0), torch.tensor(4.0), 2.0, t)
    # plain numbers are one joint too; the other laws follow the same rule
    torch.testing.assert_close(tr.quintic(1.0, 4.0, 2.0, t).position, q, atol=1e-12, rtol=0)  # t decides
    assert tr.cubic(tt(1.0), tt(4.0), 2.0, t).position.shape == (41,)
    assert tr.trapezoidal(tt(1.0), tt(4.0), 2.0, t).velocity.shape == (41,)
    # a 0-d datum next to an (n,) one broadcasts to n joints, as before
    assert tr.quintic(tt(1.0), tt([4.0, 5.0]), 2.0, t).position.shape == (41, 2)
    # a batch of query times (B, T) for one joint gives (B, T)
    assert tr.cubic(tt(1.0), tt(4.0), 2.0, t.expand(3, 41)).position.shape == (3, 41)


def test_trajectory_inputs_follow_the_validation_rule():
    """NaN/inf in data or query times, mixed dtypes, numpy input: the shared rule of diffkin.validation."""
    t = tt([0.0, 0.5, 1.0])
    for bad_t in (tt([0.0, float("nan")]), tt([float("inf")])):
        for law in (tr.cubic, tr.quintic, tr.trapezoidal):
            with pytest.raises(NonFiniteError, match="t "):
                law(tt([0.0]), tt([1.0]), 1.0, bad_t)
        with pytest.raises(NonFiniteError):
            tr.timing_law(1.0, 1.0, bad_t)
        with pytest.raises(NonFiniteError):
            tr.cubic_spline(PTS, TIMES, bad_t)
    with pytest.raises(NonFiniteError, match="q_i"):
        tr.cubic(tt([float("nan")]), tt([1.0]), 1.0, t)
    with pytest.raises(NonFiniteError, match="v_f"):
        tr.quintic(tt([0.0]), tt([1.0]), 1.0, t, v_f=float("inf"))
    with pytest.raises(NonFiniteError, match="t_f"):
        tr.cubic(tt([0.0]), tt([1.0]), float("nan"), t)
    with pytest.raises(DTypeError, match="float32"):
        tr.cubic(tt([0.0]), tt([1.0]), 1.0, t.float())
    with pytest.raises(DTypeError):
        tr.cubic(tt([0]).long(), tt([1.0]), 1.0, t)
    out = tr.cubic(np.array([0.0]), np.array([1.0]), 1.0, np.array([0.0, 0.5, 1.0]))
    assert out.position.dtype == torch.float64
    torch.testing.assert_close(out.position, tr.cubic(tt([0.0]), tt([1.0]), 1.0, t).position)
    empty = tr.cubic(torch.zeros(0, 2, dtype=F64), torch.ones(0, 2, dtype=F64), 1.0, t)
    assert empty.position.shape == (0, 3, 2)


def test_far_targets_stay_finite_in_float32():
    """A straight line to 1e30 m in float32: the length and tangent without overflow of the squares."""
    p_i, p_f = torch.zeros(3), torch.tensor([1e30, 2e30, -2e30])
    out = tr.cartesian_segment_trajectory(p_i, p_f, 2.0, torch.tensor([0.0, 1.0, 2.0]))
    assert all(bool(torch.isfinite(x).all()) for x in out)
    torch.testing.assert_close(out.position[-1], p_f, rtol=1e-5, atol=0)
    path = tr.segment_path(p_i, p_f, torch.tensor([0.0, 3e30]))
    torch.testing.assert_close(path.dp_ds[0], p_f / 3e30, rtol=1e-5, atol=0)


def _random_bcs(gen, shape):
    return [torch.randn(shape, dtype=F64, generator=gen) for _ in range(6)]


@pytest.mark.parametrize("law", ["cubic", "quintic"])
def test_polynomial_boundary_conditions_exact(law):
    g = torch.Generator().manual_seed(0)
    q_i, q_f, v_i, v_f, a_i, a_f = _random_bcs(g, (4, 3))
    t_f = tt([[0.7], [1.0], [2.5], [4.0]])
    t = torch.cat([torch.zeros(4, 1, dtype=F64), t_f], -1)  # (4, 2): query 0 and t_f per batch element
    if law == "cubic":
        out = tr.cubic(q_i, q_f, t_f, t, v_i=v_i, v_f=v_f)
    else:
        out = tr.quintic(q_i, q_f, t_f, t, v_i=v_i, v_f=v_f, a_i=a_i, a_f=a_f)
        torch.testing.assert_close(out.acceleration[:, 0], a_i, atol=1e-10, rtol=0)
        torch.testing.assert_close(out.acceleration[:, 1], a_f, atol=1e-10, rtol=0)
    for got, ref in [(out.position[:, 0], q_i), (out.position[:, 1], q_f)]:
        torch.testing.assert_close(got, ref, atol=1e-10, rtol=0)
    for got, ref in [(out.velocity[:, 0], v_i), (out.velocity[:, 1], v_f)]:
        torch.testing.assert_close(got, ref, atol=1e-10, rtol=0)


def test_cubic_matches_scipy_hermite_and_clamps_outside():
    q_i, q_f, v_i, v_f = tt([0.3, -1.0]), tt([2.0, 1.0]), tt([0.5, 0.0]), tt([-1.0, 2.0])
    t = torch.linspace(-0.5, 2.0, 26, dtype=F64)
    out = tr.cubic(q_i, q_f, 1.5, t, v_i=v_i, v_f=v_f)
    ref = CubicHermiteSpline([0, 1.5], np.stack([q_i, q_f]), np.stack([v_i, v_f]))
    inside = (t >= 0) & (t <= 1.5)
    for k, got in enumerate(out):
        np.testing.assert_allclose(got[inside].numpy(), ref(t[inside].numpy(), k), atol=1e-12)
    np.testing.assert_allclose(out.position[t < 0].numpy(), np.broadcast_to(q_i, (5, 2)), atol=0)
    np.testing.assert_allclose(out.position[t > 1.5].numpy(), np.broadcast_to(q_f, (5, 2)), atol=0)
    assert (out.velocity[~inside] == 0).all() and (out.acceleration[~inside] == 0).all()


def test_fig_4_1_cubic():
    """Fig. 4.1 data (q_i=0, q_f=pi, t_f=1): peak velocity 3 pi/2 at t=1/2, accelerations +-6 pi at ends."""
    out = tr.cubic(tt([0.0]), tt([PI]), 1.0, tt([0.0, 0.5, 1.0]))
    torch.testing.assert_close(out.velocity[1, 0], tt(1.5 * PI))
    torch.testing.assert_close(out.acceleration[:, 0], tt([6 * PI, 0.0, -6 * PI]), atol=1e-12, rtol=0)


def _trapezoid_reference(q_i, q_f, t_f, qdd, t):
    """(4.6) and (4.8) written out in numpy for one joint."""
    t_c = t_f / 2 - 0.5 * math.sqrt((t_f**2 * qdd - 4 * (q_f - q_i)) / qdd)
    q = np.where(
        t <= t_c,
        q_i + 0.5 * qdd * t**2,
        np.where(t <= t_f - t_c, q_i + qdd * t_c * (t - t_c / 2), q_f - 0.5 * qdd * (t_f - t) ** 2),
    )
    return t_c, q


def test_trapezoidal_fig_4_3_matches_4_8_and_has_cruise_phase():
    t = torch.linspace(0, 1, 201, dtype=F64)
    qdd = 6 * PI
    out = tr.trapezoidal(tt([0.0]), tt([PI]), 1.0, t, qdd_c=qdd)
    t_c, q_ref = _trapezoid_reference(0.0, PI, 1.0, qdd, t.numpy())
    np.testing.assert_allclose(out.position[:, 0].numpy(), q_ref, atol=1e-12)
    assert out.acceleration.abs().max() <= qdd * (1 + 1e-12)
    cruise = (t > t_c + 1e-9) & (t < 1 - t_c - 1e-9)
    assert (1 - 2 * t_c) > 0.5  # cruise interval of positive length
    torch.testing.assert_close(out.velocity[cruise, 0], torch.full_like(t[cruise], qdd * t_c))
    assert (out.acceleration[cruise] == 0).all()


def test_trapezoidal_cruise_velocity_4_9_to_4_11():
    q_i, q_f, t_f, qd_c = 1.0, -2.0, 2.0, 2.0  # |dq|/t_f = 1.5 < 2 <= 3 (4.9); negative motion
    t = torch.linspace(0, t_f, 401, dtype=F64)
    out = tr.trapezoidal(tt([q_i]), tt([q_f]), t_f, t, qd_c=qd_c)
    qd = -qd_c  # sign follows q_f - q_i
    t_c = (q_i - q_f + qd * t_f) / qd  # (4.10)
    qdd = qd**2 / (q_i - q_f + qd * t_f)  # (4.11)
    assert out.velocity.min() == pytest.approx(qd, abs=1e-12)
    assert out.acceleration[0, 0] == pytest.approx(qdd, abs=1e-12)
    _, q_ref = _trapezoid_reference(q_i, q_f, t_f, qdd, t.numpy())
    np.testing.assert_allclose(out.position[:, 0].numpy(), q_ref, atol=1e-12)
    assert t_c == pytest.approx(2 - 3 / 2)


def test_trapezoidal_default_and_bound():
    q_i, q_f = tt([0.0, 1.0, 2.0]), tt([1.0, -3.0, 2.0])  # last joint does not move
    t = torch.linspace(0, 2, 801, dtype=F64)
    out = tr.trapezoidal(q_i, q_f, 2.0, t)
    dq = (q_f - q_i).abs()
    torch.testing.assert_close(out.velocity.abs().max(0).values, 1.5 * dq / 2)  # t_c = t_f / 3
    assert (out.position[:, 2] == 2.0).all()
    bound = tt([2.0, 4.2, 1.0])  # joint 0: default 1.125 fits; joint 1: 4.5 > 4.2 >= 4 -> lowered
    out = tr.trapezoidal(q_i, q_f, 2.0, t, qdd_max=bound)
    assert (out.acceleration.abs() <= bound * (1 + 1e-12)).all()
    flat = (out.acceleration[:, 1] == 0) & (t > 0) & (t < 2)
    assert flat.sum() > 10  # still a cruise phase
    torch.testing.assert_close(out.position[-1], q_f, atol=1e-10, rtol=0)


def test_trapezoidal_infeasible_bounds_raise():
    with pytest.raises(tr.InfeasibleTrajectoryError, match=r"\(4.7\)"):
        tr.trapezoidal(tt([0.0]), tt([PI]), 1.0, tt([0.5]), qdd_c=3.9 * PI)
    with pytest.raises(tr.InfeasibleTrajectoryError, match=r"\(4.7\)"):
        tr.trapezoidal(tt([0.0]), tt([PI]), 1.0, tt([0.5]), qdd_max=3.9 * PI)
    with pytest.raises(tr.InfeasibleTrajectoryError, match=r"\(4.9\)"):
        tr.trapezoidal(tt([0.0]), tt([1.0]), 1.0, tt([0.5]), qd_c=2.5)
    with pytest.raises(tr.InfeasibleTrajectoryError):
        tr.trapezoidal(tt([0.0]), tt([1.0]), 1.0, tt([0.5]), qd_c=1.0)
    assert issubclass(tr.InfeasibleTrajectoryError, DiffkinError)
    # the triangular limit case is allowed
    out = tr.trapezoidal(tt([0.0]), tt([PI]), 1.0, tt([0.5, 1.0]), qdd_c=4 * PI)
    torch.testing.assert_close(out.position[-1], tt([PI]))


def test_bad_inputs_raise():
    with pytest.raises(DiffkinError, match="t_f"):
        tr.cubic(tt([0.0]), tt([1.0]), 0.0, tt([0.5]))
    with pytest.raises(ShapeError):
        tr.cubic(tt([0.0, 1.0]), tt([1.0, 2.0, 3.0]), 1.0, tt([0.5]))
    with pytest.raises(ShapeError):  # the query times' batch dims must broadcast with the data's
        tr.cubic(tt([[0.0], [1.0]]), tt([[1.0], [2.0]]), 1.0, tt([[0.5], [0.6], [0.7]]))
    with pytest.raises(DTypeError):
        tr.cubic(tt([0.0]), torch.tensor([1.0], dtype=torch.float32), 1.0, tt([0.5]))
    pts = tt([[0.0], [1.0], [2.0]])
    with pytest.raises(DiffkinError, match="increasing"):
        tr.cubic_spline(pts, tt([0.0, 2.0, 1.0]), tt([0.5]))
    with pytest.raises(ShapeError):
        tr.cubic_spline(pts, tt([0.0, 2.0]), tt([0.5]))
    with pytest.raises(ShapeError):
        tr.cubic_through_points(pts, tt([0.0, 1.0, 2.0]), tt([0.5]), velocities=tt([[0.0], [1.0]]))
    with pytest.raises(tr.InfeasibleTrajectoryError, match="overlap"):
        tr.linear_parabolic_blends(pts, tt([0.0, 1.0, 2.0]), tt([0.5]), blend_time=1.5)
    with pytest.raises(DiffkinError):
        tr.cubic_spline(
            pts, tt([0.0, 1.0, 2.0]), tt([0.5]), end="natural_virtual", virtual_times=tt([1.5, 1.7])
        )
    with pytest.raises(DiffkinError, match="axis"):
        tr.circle_path(tt([0.0, 0.0, 0.0]), tt([0.0, 0.0, 1.0]), tt([0.0, 0.0, 2.0]), tt([0.1]))


# ------------------------------------------------------------------------- derivatives and batching
T_QUERY = tt([0.05, 0.31, 0.77, 1.13, 1.52, 1.94, 2.36, 2.88, 3.41, 3.97])  # away from knots and t_c
PTS = tt([[0.0, 1.0], [2 * PI, -1.0], [PI / 2, 0.5], [PI, 2.0]])  # the book's Fig. 4.5-4.9 data + a 2nd joint
TIMES = tt([0.0, 2.0, 3.0, 5.0])

LAWS = {
    "cubic": lambda t: tr.cubic(PTS[0], PTS[1], 4.2, t, v_i=tt([0.3, 0.0]), v_f=tt([-0.2, 1.0])),
    "quintic": lambda t: tr.quintic(PTS[0], PTS[1], 4.2, t, v_i=0.3, a_i=tt([1.0, -1.0]), a_f=0.5),
    "trapezoidal": lambda t: tr.trapezoidal(PTS[0], PTS[1], 4.2, t),
    "polynomial": lambda t: tr.interpolating_polynomial(PTS, TIMES, t),
    "through_points": lambda t: tr.cubic_through_points(PTS, TIMES, t),
    "spline": lambda t: tr.cubic_spline(PTS, TIMES, t, v_i=tt([0.1, 0.2])),
    "spline_virtual": lambda t: tr.cubic_spline(PTS, TIMES, t, end="natural_virtual", v_f=tt([0.1, 0.2])),
    "blends": lambda t: tr.linear_parabolic_blends(PTS, TIMES, t, blend_time=0.2),
    "anticipated": lambda t: tr.anticipated_segments(PTS, TIMES, t, advance=tt([0.0, 0.1, 0.05])),
}


@pytest.mark.parametrize("name", list(LAWS))
def test_velocity_and_acceleration_are_autograd_derivatives(name):
    out, dpos, dvel = d_dt(LAWS[name], T_QUERY)
    torch.testing.assert_close(out.velocity, dpos, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(out.acceleration, dvel, atol=1e-9, rtol=1e-9)


BATCHABLE = {
    "cubic": lambda p, t: tr.cubic(p[..., 0, :], p[..., 3, :], 5.0, t, v_i=p[..., 1, :]),
    "trapezoidal": lambda p, t: tr.trapezoidal(p[..., 0, :], p[..., 3, :], 5.0, t),
    "spline": lambda p, t: tr.cubic_spline(p, TIMES, t),
    "spline_virtual": lambda p, t: tr.cubic_spline(p, TIMES, t, end="natural_virtual"),
    "blends": lambda p, t: tr.linear_parabolic_blends(p, TIMES, t, blend_time=tt([0.2, 0.3, 0.4, 0.2])),
    "anticipated": lambda p, t: tr.anticipated_segments(p, TIMES, t, advance=0.1),
    "through_points": lambda p, t: tr.cubic_through_points(p, TIMES, t),
}


@pytest.mark.parametrize("name", list(BATCHABLE))
def test_batched_equals_per_trajectory(name):
    fn = BATCHABLE[name]
    g = torch.Generator().manual_seed(1)
    pts = PTS + 0.3 * torch.randn(3, 4, 2, dtype=F64, generator=g)  # batch of 3 path-point sets
    batched = fn(pts, T_QUERY)
    for b in range(3):
        single = fn(pts[b], T_QUERY)
        for x, y in zip(batched, single):
            torch.testing.assert_close(x[b], y, atol=1e-12, rtol=1e-12)
    # per-batch query times (B, T) give the same rows
    t_b = T_QUERY.expand(3, -1) + tt([[0.0], [0.01], [0.02]])
    rows = fn(pts, t_b)
    torch.testing.assert_close(rows.position[2], fn(pts[2], t_b[2]).position, atol=1e-12, rtol=1e-12)


def test_gradcheck_point_to_point():
    g = torch.Generator().manual_seed(2)
    args = [torch.randn(2, 3, dtype=F64, generator=g).requires_grad_() for _ in range(4)]
    t = tt([0.1, 0.5, 1.3])
    tf = tt([[1.4], [1.9]]).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b, c, d, e: tr.cubic(a, b, e, t, v_i=c, v_f=d), (*args, tf))
    assert torch.autograd.gradcheck(lambda a, b, c, d, e: tr.quintic(a, b, e, t, v_i=c, a_f=d), (*args, tf))
    q_i, q_f = tt([0.0, 1.0]).requires_grad_(), tt([1.0, -0.5]).requires_grad_()
    qdd = tt([6.0, 7.0]).requires_grad_()
    tf1 = tt(1.0).requires_grad_()
    t = tt([0.1, 0.5, 0.95])
    assert torch.autograd.gradcheck(
        lambda a, b, c, d: tr.trapezoidal(a, b, c, t, qdd_c=d), (q_i, q_f, tf1, qdd)
    )
    assert torch.autograd.gradcheck(lambda a, b, c: tr.trapezoidal(a, b, c, t), (q_i, q_f, tf1))
    qd = tt([1.5, 2.0]).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b, d: tr.trapezoidal(a, b, 1.0, t, qd_c=d), (q_i, q_f, qd))


def test_gradcheck_through_points():
    pts = PTS.clone().requires_grad_()
    v = tt([0.1, -0.2]).requires_grad_()
    vel = torch.randn(4, 2, dtype=F64, generator=torch.Generator().manual_seed(3)).requires_grad_()
    blend = tt([0.2, 0.3, 0.25, 0.4]).requires_grad_()
    t = T_QUERY
    checks = [
        (lambda p, a: tr.cubic_spline(p, TIMES, t, v_i=a), (pts, v)),
        (lambda p, a: tr.cubic_spline(p, TIMES, t, end="natural_virtual", v_f=a, a_i=a), (pts, v)),
        (lambda p, w: tr.cubic_through_points(p, TIMES, t, velocities=w), (pts, vel)),
        (lambda p: tr.cubic_through_points(p, TIMES, t), (pts,)),
        (lambda p: tr.interpolating_polynomial(p, TIMES, t), (pts,)),
        (lambda p, d: tr.linear_parabolic_blends(p, TIMES, t, blend_time=d), (pts, blend)),
        (lambda p: tr.anticipated_segments(p, TIMES, t, advance=0.1), (pts,)),
    ]
    for fn, args in checks:
        assert torch.autograd.gradcheck(fn, args)


# ------------------------------------------------------------------------------ sequences of points
def test_problem_4_5_spline_clamped_matches_scipy():
    pts, times = tt([[0.0], [2.0], [3.0]]), tt([0.0, 2.0, 4.0])
    t = torch.linspace(-0.5, 4.5, 101, dtype=F64)
    out = tr.cubic_spline(pts, times, t, v_i=0.0, v_f=0.0)
    ref = CubicSpline(times.numpy(), pts.numpy()[:, 0], bc_type=((1, 0.0), (1, 0.0)))
    tc = t.clamp(0, 4).numpy()
    np.testing.assert_allclose(out.position[:, 0].numpy(), ref(tc), atol=1e-12)
    inside = ((t >= 0) & (t <= 4)).numpy()
    np.testing.assert_allclose(out.velocity[inside, 0].numpy(), ref(tc[inside], 1), atol=1e-12)
    np.testing.assert_allclose(out.acceleration[inside, 0].numpy(), ref(tc[inside], 2), atol=1e-12)


def test_spline_clamped_random_matches_scipy_batched():
    g = torch.Generator().manual_seed(4)
    times = torch.cumsum(0.3 + torch.rand(7, dtype=F64, generator=g), 0)
    pts = torch.randn(2, 7, 3, dtype=F64, generator=g)
    v_i, v_f = torch.randn(2, 3, dtype=F64, generator=g), torch.randn(2, 3, dtype=F64, generator=g)
    t = torch.linspace(float(times[0]), float(times[-1]), 57, dtype=F64)
    out = tr.cubic_spline(pts, times, t, v_i=v_i, v_f=v_f)
    for b in range(2):
        for j in range(3):
            ref = CubicSpline(
                times.numpy(), pts[b, :, j].numpy(), bc_type=((1, v_i[b, j].item()), (1, v_f[b, j].item()))
            )
            for k in range(3):
                np.testing.assert_allclose(out[k][b, :, j].numpy(), ref(t.numpy(), k), atol=1e-9)


def _virtual_spline_dense(q, times, tv, v_i, v_f, a_i=0.0, a_f=0.0):
    """The book's system (4.13)-(4.25) for N+1 cubics in monomial form, solved densely (one joint)."""
    knots = np.concatenate([[times[0], tv[0]], times[1:-1], [tv[1], times[-1]]])
    S = len(knots) - 1
    rows, rhs = [], []

    def row(seg, tau, der):
        r = np.zeros(4 * S)
        for j in range(der, 4):
            r[4 * seg + j] = math.factorial(j) / math.factorial(j - der) * tau ** (j - der)
        return r

    for der, val in enumerate([q[0], v_i, a_i]):
        rows.append(row(0, 0.0, der)), rhs.append(val)
    h_last = knots[-1] - knots[-2]
    for der, val in enumerate([q[-1], v_f, a_f]):
        rows.append(row(S - 1, h_last, der)), rhs.append(val)
    for k in range(1, S):
        h = knots[k] - knots[k - 1]
        for der in range(3):
            rows.append(row(k - 1, h, der) - row(k, 0.0, der)), rhs.append(0.0)
        if 2 <= k <= S - 2:  # real intermediate point q_{k}
            rows.append(row(k - 1, h, 0)), rhs.append(q[k - 1])
    coef = np.linalg.solve(np.array(rows), np.array(rhs)).reshape(S, 4)

    def evaluate(t):
        k = np.clip(np.searchsorted(knots[1:-1], t, side="right"), 0, S - 1)
        tau = t - knots[k]
        c = coef[k]
        return c[:, 0] + c[:, 1] * tau + c[:, 2] * tau**2 + c[:, 3] * tau**3, knots

    return evaluate


def test_problem_4_5_spline_null_end_accelerations_virtual_points():
    """Problem 4.5 with the book's virtual points: compare with the dense system (4.13)-(4.25) and scipy."""
    pts, times = tt([[0.0], [2.0], [3.0]]), tt([0.0, 2.0, 4.0])
    t = torch.linspace(0, 4, 81, dtype=F64)
    out = tr.cubic_spline(pts, times, t, end="natural_virtual")
    ref = _virtual_spline_dense(pts[:, 0].numpy(), times.numpy(), [1.0, 3.0], 0.0, 0.0)
    q_ref, knots = ref(t.numpy())
    np.testing.assert_allclose(out.position[:, 0].numpy(), q_ref, atol=1e-12)
    assert out.acceleration[0, 0].abs() < 1e-12 and out.acceleration[-1, 0].abs() < 1e-12
    assert out.velocity[0, 0].abs() < 1e-12 and out.velocity[-1, 0].abs() < 1e-12
    # through all N+2 knots it is scipy's clamped spline, whose end accelerations then vanish
    qk = tr.cubic_spline(pts, times, tt(knots), end="natural_virtual").position[:, 0].numpy()
    cs = CubicSpline(knots, qk, bc_type=((1, 0.0), (1, 0.0)))
    np.testing.assert_allclose(cs(t.numpy()), q_ref, atol=1e-12)
    np.testing.assert_allclose(cs(knots[[0, -1]], 2), [0.0, 0.0], atol=1e-12)


def test_fig_4_7_virtual_points_random_against_dense():
    g = torch.Generator().manual_seed(5)
    times = tt([0.0, 2.0, 3.0, 5.0, 5.5])
    q = torch.randn(5, dtype=F64, generator=g)
    for tv, v_i, v_f, a_i, a_f in [([0.5, 5.25], 0.0, 0.0, 0.0, 0.0), ([1.5, 5.1], 0.4, -1.0, 2.0, -0.5)]:
        t = torch.linspace(0, 5.5, 111, dtype=F64)
        out = tr.cubic_spline(q[:, None], times, t, v_i=v_i, v_f=v_f, a_i=a_i, a_f=a_f,
                              end="natural_virtual", virtual_times=tt(tv))  # fmt: skip
        q_ref, _ = _virtual_spline_dense(q.numpy(), times.numpy(), tv, v_i, v_f, a_i, a_f)(t.numpy())
        np.testing.assert_allclose(out.position[:, 0].numpy(), q_ref, atol=1e-11)
        assert out.acceleration[0, 0].item() == pytest.approx(a_i, abs=1e-10)
        assert out.acceleration[-1, 0].item() == pytest.approx(a_f, abs=1e-10)


def _one_sided(fn, knots, eps=1e-7):
    left = fn(knots - eps)
    right = fn(knots + eps)
    return left, right


@pytest.mark.parametrize("end", ["clamped", "natural_virtual"])
def test_spline_continuity_at_path_points(end):
    fn = functools.partial(tr.cubic_spline, PTS, TIMES, end=end)
    left, right = _one_sided(lambda t: fn(t), TIMES[1:-1])
    for k in range(3):  # position, velocity, acceleration continuous
        torch.testing.assert_close(left[k], right[k], atol=1e-5, rtol=0)
    torch.testing.assert_close(fn(TIMES).position, PTS, atol=1e-10, rtol=0)


def test_cubic_through_points_fig_4_5_imposed_velocities():
    vel = tt([[0.0], [PI], [-PI], [0.0]])
    pts = PTS[:, :1]
    t = torch.linspace(0, 5, 101, dtype=F64)
    out = tr.cubic_through_points(pts, TIMES, t, velocities=vel)
    ref = CubicHermiteSpline(TIMES.numpy(), pts[:, 0].numpy(), vel[:, 0].numpy())
    for k in range(3):
        np.testing.assert_allclose(out[k][:, 0].numpy(), ref(t.numpy(), k), atol=1e-11)
    at = tr.cubic_through_points(pts, TIMES, TIMES, velocities=vel)
    torch.testing.assert_close(at.position, pts, atol=1e-10, rtol=0)
    torch.testing.assert_close(at.velocity, vel, atol=1e-10, rtol=0)
    left, right = _one_sided(lambda s: tr.cubic_through_points(pts, TIMES, s, velocities=vel), TIMES[1:-1])
    torch.testing.assert_close(left.position, right.position, atol=1e-5, rtol=0)
    torch.testing.assert_close(left.velocity, right.velocity, atol=1e-5, rtol=0)
    assert (left.acceleration - right.acceleration).abs().max() > 1.0  # accelerations jump (Fig. 4.5)


def test_heuristic_velocities_rule_4_12():
    """Fig. 4.6: slopes pi, -3pi/2, pi/4 change sign at both intermediate points -> zero velocities."""
    v = tr.heuristic_velocities(PTS[:, :1], TIMES)
    torch.testing.assert_close(v[:, 0], torch.zeros(4, dtype=F64))
    v = tr.heuristic_velocities(tt([[0.0], [1.0], [3.0], [3.5]]), tt([0.0, 1.0, 2.0, 4.0]))
    torch.testing.assert_close(v[:, 0], tt([0.0, 1.5, 1.125, 0.0]))  # slopes 1, 2, 0.25


def test_interpolating_polynomial_passes_through_points():
    out = tr.interpolating_polynomial(PTS, TIMES, TIMES)
    torch.testing.assert_close(out.position, PTS, atol=1e-10, rtol=0)
    ref = np.polynomial.polynomial.Polynomial.fit(TIMES.numpy(), PTS[:, 0].numpy(), 3)
    t = torch.linspace(0, 5, 21, dtype=F64)
    np.testing.assert_allclose(
        tr.interpolating_polynomial(PTS, TIMES, t).position[:, 0].numpy(), ref(t.numpy()), atol=1e-11
    )


def test_linear_parabolic_blends_4_29_4_30():
    pts = PTS[:, :1]
    dtb = 0.2
    t = torch.linspace(-0.2, 5.2, 1081, dtype=F64)
    out = tr.linear_parabolic_blends(pts, TIMES, t, blend_time=dtb)
    slopes = (torch.diff(pts[:, 0]) / torch.diff(TIMES)).tolist()  # (4.29)
    for k, v in enumerate(slopes):  # linear part of each segment
        mid = (TIMES[k] + TIMES[k + 1]) / 2
        line = tr.linear_parabolic_blends(pts, TIMES, mid[None], blend_time=dtb)
        assert line.velocity.item() == pytest.approx(v, abs=1e-12)
        assert line.position.item() == pytest.approx(
            pts[k, 0].item() + v * (mid - TIMES[k]).item(), abs=1e-12
        )
    vs = [0.0, *slopes, 0.0]
    for k in range(4):  # blend acceleration (4.30), at the centre of each blend
        a = tr.linear_parabolic_blends(pts, TIMES, TIMES[k : k + 1], blend_time=dtb).acceleration.item()
        assert a == pytest.approx((vs[k + 1] - vs[k]) / dtb, rel=1e-12)
    # duration t_N - t_1 + (dt'_1 + dt'_N)/2, at rest outside; velocity continuous
    assert out.position[0, 0] == 0 and out.position[-1, 0] == pytest.approx(PI)
    moving = out.velocity[:, 0] != 0
    assert t[moving].min() >= -dtb / 2 and t[moving].max() <= 5 + dtb / 2
    assert torch.diff(out.velocity[:, 0]).abs().max() <= out.acceleration.abs().max() * (t[1] - t[0]) * (
        1 + 1e-9
    )
    q = tr.linear_parabolic_blends(pts, TIMES, t, qdd=40.0)
    assert q.acceleration.abs().max() == pytest.approx(40.0)


def test_anticipated_segments_4_50():
    pts = tt([[0.0], [PI], [1.5 * PI]])
    times = tt([0.0, 1.0, 2.0])
    qdd = tt([6 * PI, 3 * PI])
    stop = tr.anticipated_segments(pts, times, times, qdd_c=qdd)  # (4.47): each point reached, at rest
    torch.testing.assert_close(stop.position, pts, atol=1e-12, rtol=0)
    torch.testing.assert_close(stop.velocity, torch.zeros_like(pts))
    t = torch.linspace(0, 2, 201, dtype=F64)
    out = tr.anticipated_segments(pts, times, t, advance=tt([0.0, 0.18]), qdd_c=qdd)  # Fig. 4.10
    first = tr.trapezoidal(tt([0.0]), tt([PI]), 1.0, t, qdd_c=qdd[0])
    second = tr.trapezoidal(tt([0.0]), tt([PI / 2]), 1.0, t - 0.82, qdd_c=qdd[1])
    for k in range(3):  # sum of the two segment laws
        torch.testing.assert_close(out[k], first[k] + second[k], atol=1e-12, rtol=0)
    assert out.position[t >= 1.82].sub(1.5 * PI).abs().max() < 1e-12
    assert out.velocity[(t > 0.8) & (t < 1.2)].abs().min() > 0.5  # no stop at the via point
    # Cartesian segments (4.46)-(4.49): velocity along each segment's tangent
    P = tt([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    c = tr.anticipated_segments(P, times, tt([0.5, 1.5]), qdd_c=4.5)
    torch.testing.assert_close(c.velocity[0, 1:], torch.zeros(2, dtype=F64))
    torch.testing.assert_close(c.velocity[1, ::2], torch.zeros(2, dtype=F64))


def test_time_scale_equals_recomputed_law():
    t = torch.linspace(0, 1, 11, dtype=F64)
    k = 2.5
    base = tr.quintic(PTS[0], PTS[1], 1.0, t, v_i=0.2)
    scaled = tr.time_scale(base, k)
    ref = tr.quintic(PTS[0], PTS[1], k, k * t, v_i=0.2 / k)
    for x, y in zip(scaled, ref):
        torch.testing.assert_close(x, y)
    fn = tr.time_scale(lambda s: tr.cubic(PTS[0], PTS[1], 1.0, s), k)
    torch.testing.assert_close(fn(k * t).acceleration, tr.cubic(PTS[0], PTS[1], k, k * t).acceleration)
    with pytest.raises(DiffkinError):
        tr.time_scale(base, 0.0)


@settings(max_examples=20, deadline=None)
@given(
    batch=st.sampled_from([(), (1,), (3,), (2, 2)]),
    kind=st.sampled_from(["cubic", "quintic", "trapezoidal"]),
    seed=st.integers(0, 2**16),
)
def test_timing_law_shapes_and_ends(batch, kind, seed):
    g = torch.Generator().manual_seed(seed)
    s_f = 0.1 + torch.rand(batch, dtype=F64, generator=g)
    t_f = 0.5 + torch.rand(batch, dtype=F64, generator=g)
    t = torch.stack([torch.zeros_like(t_f), t_f / 2, t_f], -1)
    law = tr.timing_law(s_f, t_f, t, kind)
    assert law.position.shape == (*batch, 3)
    torch.testing.assert_close(law.position[..., 0], torch.zeros_like(s_f), atol=1e-10, rtol=0)
    torch.testing.assert_close(law.position[..., 1], s_f / 2, atol=1e-10, rtol=0)  # symmetric laws
    torch.testing.assert_close(law.position[..., 2], s_f, atol=1e-10, rtol=0)
    torch.testing.assert_close(law.velocity[..., 2], torch.zeros_like(s_f), atol=1e-10, rtol=0)


def test_float32_and_dtype_follow_inputs():
    out = tr.cubic_spline(PTS.float(), TIMES.float(), T_QUERY.float())
    assert out.position.dtype == torch.float32
    torch.testing.assert_close(
        out.position.double(), tr.cubic_spline(PTS, TIMES, T_QUERY).position, atol=1e-5, rtol=0
    )


# ------------------------------------------------------------------------------- operational space
def _fd(fn, s, eps=1e-6):
    return (fn(s + eps) - fn(s - eps)) / (2 * eps)


def test_segment_path_unit_tangent_and_problem_4_7():
    p_i, p_f = tt([0.0, 0.5, 0.0]), tt([1.0, -0.5, 0.0])
    L = torch.linalg.norm(p_f - p_i)
    s = torch.linspace(0, float(L), 11, dtype=F64)
    ps = tr.segment_path(p_i, p_f, s)
    torch.testing.assert_close(torch.linalg.norm(ps.dp_ds, dim=-1), torch.ones(11, dtype=F64))
    torch.testing.assert_close(ps.position[-1], p_f)
    law = tr.timing_law(L, 2.0, torch.linspace(0, 2, 201, dtype=F64), "trapezoidal")
    traj = tr.cartesian_trajectory(functools.partial(tr.segment_path, p_i, p_f), law)
    torch.testing.assert_close(traj.position[0], p_i, atol=1e-12, rtol=0)
    torch.testing.assert_close(traj.position[-1], p_f, atol=1e-12, rtol=0)
    torch.testing.assert_close(traj.velocity, law.velocity[:, None] * (p_f - p_i) / L)  # (4.42)
    speed = torch.linalg.norm(traj.velocity, dim=-1)
    assert speed.max().item() == pytest.approx(1.5 * math.sqrt(2) / 2)
    same = tr.cartesian_segment_trajectory(p_i, p_f, 2.0, torch.linspace(0, 2, 201, dtype=F64), "trapezoidal")
    for x, y in zip(same, traj):
        torch.testing.assert_close(x, y)


def test_circle_path_radius_arc_length_and_problem_4_8():
    c, x_axis, p_i = tt([0.0, 0.0, 1.0]), tt([1.0, 0.0, 0.0]), tt([0.0, 0.5, 1.0])
    rho = 0.5
    s = torch.linspace(0, PI * rho, 31, dtype=F64)
    path = functools.partial(tr.circle_path, c, x_axis, p_i)
    ps = path(s)
    torch.testing.assert_close(torch.linalg.norm(ps.position - c, dim=-1), torch.full_like(s, rho))
    torch.testing.assert_close(torch.linalg.norm(ps.dp_ds, dim=-1), torch.ones_like(s))  # arc length
    torch.testing.assert_close(ps.dp_ds, _fd(lambda x: path(x).position, s), atol=1e-8, rtol=0)
    torch.testing.assert_close(ps.d2p_ds2, _fd(lambda x: path(x).dp_ds, s), atol=1e-8, rtol=0)
    torch.testing.assert_close(ps.position[-1], tt([0.0, -0.5, 1.0]), atol=1e-12, rtol=0)
    assert ps.position[15, 2] == pytest.approx(1.5)  # positive rotation about x passes through z = 1.5
    # any axis point works as "center" (4.37); the plane is x = 0
    ps2 = tr.circle_path(tt([3.0, 0.0, 1.0]), 2 * x_axis, p_i, s)
    torch.testing.assert_close(ps2.position, ps.position)
    law = tr.timing_law(PI * rho, 2.0, torch.linspace(0, 2, 101, dtype=F64), "trapezoidal")
    traj = tr.cartesian_trajectory(path, law)
    acc_ref = (
        law.acceleration[:, None] * path(law.position).dp_ds
        + law.velocity[:, None] ** 2 * path(law.position).d2p_ds2
    )
    torch.testing.assert_close(traj.acceleration, acc_ref)  # (4.45)
    n = traj.acceleration[50]  # mid-cruise: pure centripetal acceleration s_dot^2 / rho
    assert torch.linalg.norm(n).item() == pytest.approx(law.velocity[50].item() ** 2 / rho)


def test_cartesian_trajectory_derivatives_autograd():
    c, r, p_i = tt([0.1, -0.2, 0.3]), tt([0.3, 0.4, 0.5]), tt([0.6, 0.1, 0.2])
    path = functools.partial(tr.circle_path, c, r, p_i)
    _, dpos, dvel = d_dt(
        lambda t: tr.cartesian_trajectory(path, tr.timing_law(1.3, 2.0, t, "quintic")), T_QUERY / 2
    )
    traj = tr.cartesian_trajectory(path, tr.timing_law(1.3, 2.0, T_QUERY / 2, "quintic"))
    torch.testing.assert_close(traj.velocity, dpos)
    torch.testing.assert_close(traj.acceleration, dvel)
    assert torch.autograd.gradcheck(
        lambda a, b: tr.circle_path(a, r, b, tt([0.1, 0.7])).position,
        (c.clone().requires_grad_(), p_i.clone().requires_grad_()),
    )


def _rand_rot(n, seed):
    return torch.from_numpy(Rotation.random(n, random_state=seed).as_matrix())


def _check_orientation(fn, R_i, R_f, t_f):
    t = torch.linspace(0, t_f, 9, dtype=F64)
    out = fn(t)
    torch.testing.assert_close(out.rotation[..., 0, :, :], R_i, atol=1e-10, rtol=0)
    torch.testing.assert_close(out.rotation[..., -1, :, :], R_f, atol=1e-10, rtol=0)
    tm = t[1:-1]
    eps = 1e-6
    Rdot = (fn(tm + eps).rotation - fn(tm - eps).rotation) / (2 * eps)
    omega_fd = vee(Rdot @ fn(tm).rotation.transpose(-1, -2))
    torch.testing.assert_close(fn(tm).angular_velocity, omega_fd, atol=1e-7, rtol=0)
    wdot_fd = (fn(tm + eps).angular_velocity - fn(tm - eps).angular_velocity) / (2 * eps)
    torch.testing.assert_close(fn(tm).angular_acceleration, wdot_fd, atol=1e-6, rtol=0)


@pytest.mark.parametrize("normalised", [True, False])
def test_axis_angle_orientation_trajectory(normalised):
    R_i, R_f = _rand_rot(3, 0), _rand_rot(3, 1)

    def fn(t):
        timing = (
            tr.timing_law(1.0, 2.0, t) if normalised else (lambda L: tr.timing_law(L, 2.0, t, "trapezoidal"))
        )
        return tr.axis_angle_orientation_trajectory(R_i, R_f, timing)

    _check_orientation(fn, R_i, R_f, 2.0)


def test_axis_angle_orientation_null_rotation_finite_gradient():
    R0 = _rand_rot(1, 0)[0].requires_grad_()
    out = tr.axis_angle_orientation_trajectory(R0, R0.detach(), tr.timing_law(1.0, 1.0, tt([0.3])))
    torch.testing.assert_close(out.angular_velocity, torch.zeros(1, 3, dtype=F64))
    torch.testing.assert_close(out.rotation[0], R0.detach())
    (g,) = torch.autograd.grad(out.rotation.sum() + out.angular_velocity.sum(), R0)
    assert torch.isfinite(g).all()


@pytest.mark.parametrize("convention", ["ZYZ", "RPY"])
def test_euler_orientation_trajectory(convention):
    phi_i, phi_f = tt([0.1, 0.8, -0.4]), tt([1.2, 0.3, 0.9])
    R_i, R_f = euler_to_matrix(phi_i, convention), euler_to_matrix(phi_f, convention)

    def fn(t):
        return tr.euler_orientation_trajectory(
            phi_i, phi_f, tr.timing_law(1.0, 1.5, t, "quintic"), convention
        )

    _check_orientation(fn, R_i, R_f, 1.5)
    angles = tr.euler_angle_trajectory(phi_i, phi_f, lambda L: tr.timing_law(L, 1.5, tt([0.0, 1.5]), "cubic"))
    torch.testing.assert_close(angles.position, torch.stack([phi_i, phi_f]), atol=1e-12, rtol=0)


def test_quaternion_slerp_trajectory_matches_axis_angle():
    R_i, R_f = _rand_rot(4, 2), _rand_rot(4, 3)
    Q_i, Q_f = matrix_to_quaternion(R_i), -matrix_to_quaternion(R_f)  # sign of Q_f must not matter
    t = torch.linspace(0, 1, 8, dtype=F64)  # not at the blend times 1/3, 2/3
    for timing in (tr.timing_law(1.0, 1.0, t), lambda L: tr.timing_law(L, 1.0, t, "trapezoidal")):
        q = tr.quaternion_orientation_trajectory(Q_i, Q_f, timing)
        a = tr.axis_angle_orientation_trajectory(R_i, R_f, timing)
        torch.testing.assert_close(quaternion_to_matrix(q.quaternion), a.rotation, atol=1e-10, rtol=0)
        torch.testing.assert_close(q.angular_velocity, a.angular_velocity, atol=1e-10, rtol=0)
        torch.testing.assert_close(q.angular_acceleration, a.angular_acceleration, atol=1e-10, rtol=0)


def test_operational_batched_equals_per_item():
    g = torch.Generator().manual_seed(6)
    c, r, p = (torch.randn(3, 3, dtype=F64, generator=g) for _ in range(3))
    law = tr.timing_law(tt([1.0, 2.0, 0.5]), 2.0, T_QUERY / 2, "quintic")  # (3, T)
    R_i, R_f = _rand_rot(3, 7), _rand_rot(3, 8)
    batched = tr.cartesian_trajectory(functools.partial(tr.circle_path, c, r, p), law)
    rot = tr.axis_angle_orientation_trajectory(R_i, R_f, lambda L: tr.timing_law(L, 2.0, T_QUERY / 2))
    for b in range(3):
        law_b = tr.Trajectory(*(x[b] for x in law))
        single = tr.cartesian_trajectory(functools.partial(tr.circle_path, c[b], r[b], p[b]), law_b)
        rot_b = tr.axis_angle_orientation_trajectory(
            R_i[b], R_f[b], lambda L: tr.timing_law(L, 2.0, T_QUERY / 2)
        )
        for x, y in zip((*batched, *rot), (*single, *rot_b)):
            torch.testing.assert_close(x[b], y, atol=1e-12, rtol=1e-12)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_outputs_stay_on_device():
    def run(dev):
        pts, times, t = PTS.to(dev), TIMES.to(dev), T_QUERY.to(dev)
        return [
            tr.cubic_spline(pts, times, t, end="natural_virtual"),
            tr.trapezoidal(pts[0], pts[1], 4.2, t),
            tr.linear_parabolic_blends(pts, times, t, blend_time=0.2),
            tr.anticipated_segments(pts, times, t, advance=0.1),
        ]

    for out, ref in zip(run(torch.device("cuda")), run(torch.device("cpu"))):
        assert out.position.device.type == "cuda"
        torch.testing.assert_close(out.position.cpu(), ref.position)
