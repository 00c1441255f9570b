"""Motion through a sequence of points (§4.2.2 and the via points of §4.3.2).

``points``: (..., N, n) (N path points of n joints); ``times``: (N,) or (..., N), strictly increasing;
``t``: query times (T,) or (..., T); results are :class:`Trajectory` of shape (..., T, n). Outside
[t_1, t_N] positions hold the end values and velocity/acceleration are zero (except where noted).
Inputs follow :mod:`diffkin.validation` (one dtype, numbers and numpy arrays converted, NaN/inf refused).
"""

from __future__ import annotations

import torch
from torch import Tensor

from .._numerics import broadcast_shapes, stable_norm, stable_normalize
from ..errors import ConventionError, DiffkinError
from ..kernels.banded import tridiagonal_solve
from ..validation import broadcast_batch, check_trailing, tensors
from ._common import (
    InfeasibleTrajectoryError,
    Trajectory,
    cat_broadcast,
    check_knot_times,
    check_points,
    clamp_times,
    cubic_coeffs,
    mask_outside,
    per_item,
    poly_eval,
    query_times,
    segment_index,
    spline_slopes,
    take,
    take_scalar,
)
from .point_to_point import _law

__all__ = [
    "interpolating_polynomial",
    "cubic_through_points",
    "heuristic_velocities",
    "cubic_spline",
    "linear_parabolic_blends",
    "anticipated_segments",
]


def _setup(points, times, t, min_points: int = 2, **extra):
    """Validate the points (..., N, n), knot times (..., N), query times (..., T) (``t`` None: none) and the
    ``extra`` arguments (None entries stay None) together; returns them in this order."""
    names = list(extra)
    points, times, t, *rest = tensors(
        ("points", points, (None, None)), ("times", times, (None,)), ("t", t, None),
        *((k, extra[k], None) for k in names),
    )
    check_points(points, min_points=min_points)
    check_knot_times(times, points.shape[-2])
    t = None if t is None else query_times(t)
    broadcast_batch(("points", points, 2), ("times", times, 1), ("t", t, 1))
    return (points, times, t, *rest)


def interpolating_polynomial(points: Tensor, times, t) -> Trajectory:
    """The single polynomial of order N-1 through all N path points (§4.2.2, first option).

    Shown for comparison: end velocities cannot be imposed and it oscillates as N grows. Solved in the
    normalised time u = (t - t_1)/(t_N - t_1) for conditioning.
    """
    points, times, t = _setup(points, times, t)
    N = points.shape[-2]
    t0, span = times[..., :1], times[..., -1:] - times[..., :1]
    k = torch.arange(N, dtype=points.dtype, device=points.device)
    V = ((times - t0) / span)[..., :, None] ** k  # Vandermonde (..., N, N)
    c = torch.linalg.solve(V, points)  # (..., N, n)
    tq, inside = clamp_times(t, t0, times[..., -1:])
    u = ((tq - t0) / span)[..., :, None]
    U = u**k  # (..., T, N)
    zeros = torch.zeros_like(U[..., :1])
    dU = torch.cat([zeros, U[..., :-1] * k[1:]], -1) / span[..., None]
    ddU = torch.cat([zeros, zeros, U[..., :-2] * (k[2:] * (k[2:] - 1))], -1)[..., :N] / span[..., None] ** 2
    return mask_outside(Trajectory(U @ c, dU @ c, ddU @ c), inside[..., None])


def heuristic_velocities(points: Tensor, times) -> Tensor:
    """Path-point velocities by the rule (4.12): 0 at the ends and where the adjacent slopes change sign,
    else their mean. points (..., N, n), times (N,) or (..., N) -> (..., N, n)."""
    points, times, _ = _setup(points, times, None)
    return _heuristic_velocities(points, times)


def _heuristic_velocities(points: Tensor, times: Tensor) -> Tensor:
    slopes = torch.diff(points, dim=-2) / torch.diff(times, dim=-1)[..., None]
    same = torch.sign(slopes[..., :-1, :]) == torch.sign(slopes[..., 1:, :])
    inner = torch.where(
        same, 0.5 * (slopes[..., :-1, :] + slopes[..., 1:, :]), torch.zeros_like(slopes[..., 1:, :])
    )
    zero = torch.zeros_like(slopes[..., :1, :])
    return torch.cat([zero, inner, zero], dim=-2)


def _hermite_segments(points: Tensor, vel: Tensor, times: Tensor, t: Tensor) -> Trajectory:
    tq, inside = clamp_times(t, times[..., :1], times[..., -1:])
    k = segment_index(times, tq)
    tk, tk1 = take_scalar(times, k), take_scalar(times, k + 1)
    q0, q1, v0, v1 = take(points, k), take(points, k + 1), take(vel, k), take(vel, k + 1)
    coeffs = cubic_coeffs(q0, q1, v0, v1, (tk1 - tk)[..., None])
    return mask_outside(poly_eval(coeffs, (tq - tk)[..., None]), inside[..., None])


def cubic_through_points(points: Tensor, times, t, velocities: Tensor | None = None) -> Trajectory:
    """Sequence of N-1 cubics, each fixed by positions and velocities at its two path points (§4.2.2).

    ``velocities`` (..., N, n) are imposed; if None they are computed by the rule (4.12) (zero at the
    ends). Position and velocity are continuous, acceleration in general is not.
    """
    points, times, t, velocities = _setup(points, times, t, velocities=velocities)
    if velocities is None:
        velocities = _heuristic_velocities(points, times)
    else:
        check_trailing(velocities, tuple(points.shape[-2:]), "velocities")
        broadcast_batch(("points", points, 2), ("velocities", velocities, 2))
    return _hermite_segments(points, velocities, times, t)


def _virtual_spline(points, times, v_i, v_f, a_i, a_f, virtual_times):
    """Knots, knot positions and knot accelerations of the book's N+1 cubics with two virtual points.

    Unknowns: the accelerations at knots 2..N+1 (4.28). The virtual positions are affine in the
    accelerations next to them through the end velocity conditions (4.18), (4.21); substituting them
    keeps the matrix tridiagonal.
    """
    if virtual_times is None:
        tv = torch.stack([(times[..., 0] + times[..., 1]) / 2, (times[..., -2] + times[..., -1]) / 2], -1)
    else:
        tv = check_trailing(virtual_times, (2,), "virtual_times")
    knots = cat_broadcast([times[..., :1], tv[..., :1], times[..., 1:-1], tv[..., 1:], times[..., -1:]], -1)
    if bool((torch.diff(knots, dim=-1) <= 0).any()):
        raise DiffkinError("virtual_times must lie strictly inside the first and the last interval, in order")
    h = torch.diff(knots, dim=-1)  # (..., K-1), K = N + 2
    h0, h1, hl, hl1 = h[..., :1], h[..., 1:2], h[..., -1:], h[..., -2:-1]
    # Generic rows: h_{k-1} M_{k-1} + 2 (h_{k-1} + h_k) M_k + h_k M_{k+1} = 6 (slope_k - slope_{k-1});
    # the corrections move the virtual positions' dependence on M_2 and M_{N+1} to the left-hand side.
    diag = 2 * (h[..., :-1] + h[..., 1:])
    diag = torch.cat([diag[..., :1] + h0 + h0**2 / h1, diag[..., 1:]], -1)
    diag = torch.cat([diag[..., :-1], diag[..., -1:] + hl + hl**2 / hl1], -1)
    sub = torch.cat([h[..., 1:2] - h0**2 / h1, h[..., 2:-1]], -1)
    sup = torch.cat([h[..., 1:-2], h[..., -2:-1] - hl**2 / hl1], -1)
    qa = points[..., 0, :] + h0 * v_i + h0**2 * a_i / 3  # Q_2 = qa + h0^2/6 M_2
    qc = points[..., -1, :] - hl * v_f + hl**2 * a_f / 3  # Q_{N+1} = qc + hl^2/6 M_{N+1}
    Q = cat_broadcast(
        [points[..., :1, :], qa[..., None, :], points[..., 1:-1, :], qc[..., None, :], points[..., -1:, :]],
        -2,
    )
    slopes = torch.diff(Q, dim=-2) / h[..., None]
    b = 6 * torch.diff(slopes, dim=-2)
    b = cat_broadcast([b[..., :1, :] - h0[..., None] * a_i[..., None, :], b[..., 1:, :]], -2)
    b = cat_broadcast([b[..., :-1, :], b[..., -1:, :] - hl[..., None] * a_f[..., None, :]], -2)
    M_in = tridiagonal_solve(sub, diag, sup, b)
    M = cat_broadcast([a_i[..., None, :], M_in, a_f[..., None, :]], -2)
    Q = cat_broadcast(
        [
            Q[..., :1, :],
            Q[..., 1:2, :] + h0[..., None] ** 2 / 6 * M_in[..., :1, :],
            Q[..., 2:-2, :],
            Q[..., -2:-1, :] + hl[..., None] ** 2 / 6 * M_in[..., -1:, :],
            Q[..., -1:, :],
        ],
        -2,
    )
    return knots, Q, M


def _knot_velocities(knots: Tensor, Q: Tensor, M: Tensor) -> Tensor:
    """Knot velocities (..., K, n) of the spline (4.27) with knot positions Q and accelerations M (..., K, n):
    its derivative at the start of each interval and, last, at the end of the last one."""
    h = torch.diff(knots, dim=-1)[..., None]
    slope = torch.diff(Q, dim=-2) / h
    start = slope - h * (2 * M[..., :-1, :] + M[..., 1:, :]) / 6
    end = slope[..., -1:, :] + h[..., -1:, :] * (M[..., -2:-1, :] + 2 * M[..., -1:, :]) / 6
    return cat_broadcast([start, end], -2)


def cubic_spline(
    points: Tensor, times, t, v_i=0.0, v_f=0.0, end: str = "clamped", a_i=0.0, a_f=0.0, virtual_times=None
) -> Trajectory:
    """Cubic spline through the path points with continuous velocity and acceleration (4.26)-(4.28).

    end="clamped": N-1 cubics with the end velocities v_i, v_f imposed (end accelerations free), knot
    slopes from a tridiagonal system. end="natural_virtual": the book's construction with two
    virtual points (4.13)-(4.25), so that end accelerations a_i, a_f (default 0) are imposed too; the
    virtual points sit at ``virtual_times`` (..., 2) (default: middles of the first and last interval)
    and the unknown knot accelerations solve (4.28). v_i, v_f, a_i, a_f: (..., n).
    Both are evaluated as the Hermite cubics (4.1) of their knot positions and velocities; the tridiagonal
    systems are solved by :func:`~diffkin.kernels.banded.tridiagonal_solve` (batched, differentiable).
    """
    if end not in ("clamped", "natural_virtual"):
        raise ConventionError(f'unknown spline end condition {end!r}; valid: "clamped", "natural_virtual"')
    if end == "clamped" and virtual_times is not None:
        raise ConventionError('virtual_times is only used with end="natural_virtual"')
    points, times, t, v_i, v_f, a_i, a_f, virtual_times = _setup(
        points, times, t, v_i=v_i, v_f=v_f, a_i=a_i, a_f=a_f, virtual_times=virtual_times
    )
    n = points.shape[-1]
    ends = {"v_i": v_i, "v_f": v_f, "a_i": a_i, "a_f": a_f}
    for name, x in ends.items():
        per_item(x, n, name, "one per joint")
    named = ((k, x, 1) for k, x in ends.items())
    broadcast_batch(("points", points, 2), *named, ("virtual_times", virtual_times, 1))
    v_i, v_f, a_i, a_f = (x.expand(broadcast_shapes(x.shape, points.shape[-1:])) for x in ends.values())
    if end == "clamped":
        return _hermite_segments(points, spline_slopes(times, points, "clamped", v_i, v_f), times, t)
    knots, Q, M = _virtual_spline(points, times, v_i, v_f, a_i, a_f, virtual_times)
    return _hermite_segments(Q, _knot_velocities(knots, Q, M), knots, t)


def _ramp(x: Tensor, D: Tensor) -> Trajectory:
    """Integral of a velocity ramp from 0 to 1 over [0, D]: the unit parabolic blend, safe at D = 0."""
    pos_D = D > 0
    D_safe = torch.where(pos_D, D, torch.ones_like(D))
    xc = torch.minimum(torch.maximum(x, torch.zeros_like(x)), D)
    inside = pos_D & (x > 0) & (x < D)
    pos = torch.where(x >= D, x - D / 2, torch.where(inside, xc**2 / (2 * D_safe), torch.zeros_like(x)))
    vel = torch.where(x >= D, torch.ones_like(x), torch.where(inside, xc / D_safe, torch.zeros_like(x)))
    acc = torch.where(inside, 1 / D_safe, torch.zeros_like(x))
    return Trajectory(pos, vel, acc)


def linear_parabolic_blends(points: Tensor, times, t, blend_time=None, qdd=None) -> Trajectory:
    """Linear segments through the points joined by parabolic blends at each point (4.29)-(4.30).

    Segment velocities (4.29) with null velocity before t_1 and after t_N; the blend at t_k lasts
    Delta t'_k, centred on t_k, with acceleration (4.30). Give either ``blend_time`` (number or (..., N),
    one per point) or ``qdd`` (blend acceleration magnitude, number or (..., n); then Delta t'_k =
    |Delta velocity|/qdd). The points become via points; the motion spans
    [t_1 - Delta t'_1/2, t_N + Delta t'_N/2] (so it starts before t_1). Blends must not overlap.
    """
    if (blend_time is None) == (qdd is None):
        raise DiffkinError("give exactly one of blend_time and qdd")
    points, times, t, blend_time, qdd = _setup(points, times, t, blend_time=blend_time, qdd=qdd)
    per_item(blend_time, points.shape[-2], "blend_time", "one per point")
    per_item(qdd, points.shape[-1], "qdd", "one per joint")
    broadcast_batch(("points", points, 2), ("blend_time", blend_time, 1), ("qdd", qdd, 1))
    h = torch.diff(times, dim=-1)
    v = torch.diff(points, dim=-2) / h[..., None]
    zero = torch.zeros_like(v[..., :1, :])
    dv = torch.diff(torch.cat([zero, v, zero], -2), dim=-2)  # (..., N, n)
    if blend_time is not None:
        D = blend_time
        D = D[..., None] if D.ndim else D.expand(dv.shape[-2:])  # (..., N, 1) or (N, n)
        if bool((D < 0).any()):
            raise DiffkinError("blend_time must be >= 0")
    else:
        acc = qdd.abs()
        if bool((acc <= 0).any()):
            raise DiffkinError("qdd must be > 0")
        D = dv.abs() / (acc[..., None, :] if acc.ndim else acc)
    if bool(((D[..., :-1, :] + D[..., 1:, :]) / 2 > h[..., None] * (1 + 1e-12)).any()):
        raise InfeasibleTrajectoryError(
            "parabolic blends overlap: need (dt'_k + dt'_{k+1})/2 <= t_{k+1} - t_k"
        )
    x = t[..., None, :, None] - (times[..., :, None, None] - D[..., :, None, :] / 2)  # (..., N, T, n)
    r = _ramp(x, D[..., :, None, :])
    dv = dv[..., :, None, :]
    return Trajectory(
        points[..., :1, :] + (dv * r.position).sum(-3),
        (dv * r.velocity).sum(-3),
        (dv * r.acceleration).sum(-3),
    )


def anticipated_segments(points: Tensor, times, t, advance=None, qdd_c=None) -> Trajectory:
    """Segments p_{j-1} -> p_j with trapezoidal timing laws, each started ``advance`` earlier (4.46)-(4.50).

    points (..., N+1, n); times (..., N+1) are the nominal t_0 .. t_N; ``advance`` (number or (..., N)) is
    delta t_j of (4.50): segment j starts at t_{j-1} - Delta t_j with Delta t_j = sum_{i<=j} delta t_i
    (default 0: the path points are reached and the motion stops at each, (4.47)). ``qdd_c``: arc-length
    acceleration of each segment's trapezoidal law (number or (..., N); default as in ``trapezoidal``).
    Position (4.46), velocity (4.48), acceleration (4.49). Works for joint space (Fig. 4.10) too.
    """
    points, times, t, advance, qdd_c = _setup(points, times, t, advance=advance, qdd_c=qdd_c)
    N = points.shape[-2] - 1
    per_item(advance, N, "advance", "one per segment")
    per_item(qdd_c, N, "qdd_c", "one per segment")
    broadcast_batch(("points", points, 2), ("advance", advance, 1), ("qdd_c", qdd_c, 1))
    dp = torch.diff(points, dim=-2)
    L, u = stable_norm(dp), stable_normalize(dp)  # (..., N), (..., N, n)
    h = torch.diff(times, dim=-1)
    shift = torch.zeros_like(h) if advance is None else advance
    cum = torch.cumsum(torch.broadcast_to(shift, broadcast_shapes(shift.shape, h.shape)), dim=-1)
    local = t[..., None, :] + (cum - times[..., :-1])[..., None]  # (..., N, T)
    data = {"q_i": torch.zeros_like(L)[..., None], "q_f": L[..., None], "t_f": h[..., None]}
    if qdd_c is not None:
        data["qdd_c"] = qdd_c[..., None] if qdd_c.ndim else qdd_c
    s = [x[..., 0] for x in _law("trapezoidal", data, local)]  # (..., N, T)
    return Trajectory(
        points[..., :1, :] + torch.einsum("...jt,...jn->...tn", s[0], u),
        torch.einsum("...jt,...jn->...tn", s[1], u),
        torch.einsum("...jt,...jn->...tn", s[2], u),
    )
