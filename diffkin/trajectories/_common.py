"""Shared pieces of the trajectory kernels: result types, input conversion, time handling, gathering.

Shape vocabulary: ``...`` leading batch dims, ``n`` joints (or coordinates), ``T`` query times,
``N`` path points, ``K`` knots.

Inputs follow :mod:`diffkin.validation`: each public function validates all of its arguments in one
:func:`~diffkin.validation.tensors` call (one dtype and device, numbers and numpy arrays converted, finite
values, query times included); the helpers below work on the validated tensors.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .._numerics import broadcast_shapes
from ..errors import DiffkinError, ShapeError
from ..kernels.banded import tridiagonal_solve
from ..validation import check_trailing, shape_str

__all__ = ["Trajectory", "InfeasibleTrajectoryError"]


class Trajectory(NamedTuple):
    """Position, velocity and acceleration sampled at the query times, each of shape (..., T, n).

    Scalar timing laws (``timing_law``) use (..., T).
    """

    position: Tensor
    velocity: Tensor
    acceleration: Tensor


class InfeasibleTrajectoryError(DiffkinError):
    """The requested bound (acceleration, cruise velocity, blend time) admits no trajectory."""


def per_item(x: Tensor | None, size: int, name: str, what: str) -> Tensor | None:
    """A validated argument that is either one number (shape ()) or one value per ``what``: (..., size)."""
    if x is not None and x.ndim:
        if x.shape[-1] != size:
            raise ShapeError(f"expected {name} as a number or of shape (..., {size}) ({what}), "
                             f"got {shape_str(x.shape)}")
    return x


def cat_broadcast(tensors: list[Tensor], dim: int) -> Tensor:
    """torch.cat along the negative ``dim`` after broadcasting all the other dims."""
    nd = max(x.ndim for x in tensors)
    xs = [x.reshape((1,) * (nd - x.ndim) + tuple(x.shape)) for x in tensors]
    shape = list(
        broadcast_shapes(*[x.shape[:dim] + (1,) + x.shape[len(x.shape) + dim + 1 :] for x in xs])
    )
    out = []
    for x in xs:
        shape[dim] = x.shape[dim]
        out.append(x.expand(*shape))
    return torch.cat(out, dim)


def query_times(t: Tensor) -> Tensor:
    """Validated query times of shape (T,) or (..., T); a number (shape ()) becomes (1,)."""
    return t.reshape(1) if t.ndim == 0 else t


def check_durations(t_f: Tensor, name: str = "t_f") -> Tensor:
    if bool((t_f <= 0).any()):
        raise DiffkinError(f"{name} must be > 0 everywhere, got min {float(t_f.min())}")
    return t_f


def check_knot_times(times: Tensor, N: int, name: str = "times") -> Tensor:
    """Validated knot times: (N,) or (..., N), strictly increasing."""
    check_trailing(times, (N,), name)
    if N > 1 and bool((times[..., 1:] <= times[..., :-1]).any()):
        raise DiffkinError(f"{name} must be strictly increasing along the last dim")
    return times


def check_points(points: Tensor, name: str = "points", min_points: int = 2) -> Tensor:
    """Validated path points: (..., N, n) with N >= ``min_points``."""
    if points.ndim < 2 or points.shape[-2] < min_points:
        raise ShapeError(
            f"expected {name} of shape (..., N, n) with N >= {min_points}, "
            f"got {shape_str(points.shape)}"
        )
    return points


def clamp_times(t: Tensor, t0: Tensor, t1: Tensor) -> tuple[Tensor, Tensor]:
    """Clamp ``t`` into [t0, t1] (broadcasting) and return the mask of times that were inside."""
    tc = torch.minimum(torch.maximum(t, t0), t1)
    return tc, (t >= t0) & (t <= t1)


def segment_index(knots: Tensor, t: Tensor) -> Tensor:
    """Index k of the segment [knots_k, knots_{k+1}] holding each (already clamped) time.

    knots: (..., K), t: (..., T) with broadcastable batch dims -> (..., T) in [0, K-2].
    """
    inner = knots[..., 1:-1]
    if inner.ndim == 1:
        return torch.searchsorted(inner, t.contiguous(), right=True)
    batch = broadcast_shapes(inner.shape[:-1], t.shape[:-1])
    inner = inner.expand(*batch, inner.shape[-1]).contiguous()
    return torch.searchsorted(inner, t.expand(*batch, t.shape[-1]).contiguous(), right=True)


def take(values: Tensor, idx: Tensor) -> Tensor:
    """values (..., K, n) gathered at idx (..., T) along K -> (..., T, n); batch dims broadcast."""
    batch = broadcast_shapes(values.shape[:-2], idx.shape[:-1])
    K, n = values.shape[-2:]
    T = idx.shape[-1]
    v = values.expand(*batch, K, n)
    i = idx.expand(*batch, T)[..., None].expand(*batch, T, n)
    return torch.gather(v, -2, i)


def take_scalar(values: Tensor, idx: Tensor) -> Tensor:
    """values (..., K) gathered at idx (..., T) -> (..., T)."""
    return take(values[..., None], idx)[..., 0]


def poly_eval(coeffs: list[Tensor], tau: Tensor, position_only: bool = False) -> Trajectory:
    """Horner evaluation of sum_k a_k tau^k and its first two derivatives in tau (``position_only``: the
    derivatives are None)."""
    if position_only:
        p = coeffs[-1]
        for c in reversed(coeffs[:-1]):
            p = p * tau + c
        return Trajectory(p, None, None)
    # Horner from the top coefficient: the steps that would multiply zeros are skipped (the same floats as
    # starting from p = v = a = 0; fewer full-size temporaries on large sample sets)
    p, v, a = coeffs[-1], None, None
    for c in reversed(coeffs[:-1]):
        if v is not None:
            a = 2 * v if a is None else a * tau + 2 * v
        v = p if v is None else v * tau + p
        p = p * tau + c
    shape = broadcast_shapes(p.shape, tau.shape)
    p = p.expand(shape) if p.shape != shape else p
    v = torch.zeros(shape, dtype=p.dtype, device=p.device) if v is None else v.expand(shape)
    a = torch.zeros(shape, dtype=p.dtype, device=p.device) if a is None else a.expand(shape)
    return Trajectory(p, v, a)


def cubic_coeffs(q0: Tensor, q1: Tensor, v0: Tensor, v1: Tensor, h: Tensor) -> list[Tensor]:
    """Coefficients a_0..a_3 of (4.1) from the four boundary conditions below it."""
    d = q1 - q0
    a2 = (3 * d - (2 * v0 + v1) * h) / h**2
    a3 = (-2 * d + (v0 + v1) * h) / h**3
    return [q0, v0, a2, a3]


def spline_slopes(knots: Tensor, y: Tensor, bc: str = "clamped", v_i: Tensor | None = None,
                  v_f: Tensor | None = None) -> Tensor:
    """Knot slopes m (..., N, n) of the C² cubic spline through y (..., N, n) at knots (N,) or (..., N).

    With the slopes, each segment is the Hermite cubic (4.1) of its end positions and velocities
    (:func:`cubic_coeffs`); continuity of the acceleration at the interior knots gives the rows
    h_k m_{k-1} + 2 (h_{k-1} + h_k) m_k + h_{k-1} m_{k+1} = 3 (h_k d_{k-1} + h_{k-1} d_k) (h: intervals, d:
    chord slopes). bc="clamped": m_1 = v_i, m_N = v_f ((..., n), default 0: §4.2.2's imposed end
    velocities, scipy's ``bc_type="clamped"``); bc="not-a-knot": scipy ``CubicSpline``'s default (third
    derivative continuous at the second and the last but one knot; N = 2: the chord, N = 3: the parabola).
    """
    h = torch.diff(knots, dim=-1)  # (..., N-1)
    d = torch.diff(y, dim=-2) / h[..., None]  # chord slopes (..., N-1, n)
    N = y.shape[-2]
    if bc == "not-a-knot" and N == 2:
        return cat_broadcast([d, d], -2)
    if bc == "not-a-knot" and N == 3:  # scipy: the parabola through the three points
        c = (d[..., 1, :] - d[..., 0, :]) / (knots[..., 2] - knots[..., 0])[..., None]
        h0, h1 = h[..., :1], h[..., 1:]
        return torch.stack(torch.broadcast_tensors(d[..., 0, :] - c * h0, d[..., 0, :] + c * h0,
                                                   d[..., 1, :] + c * h1), -2)
    hl, hr = h[..., :-1], h[..., 1:]  # the intervals left and right of each interior knot (..., N-2)
    rhs = 3 * (hr[..., None] * d[..., :-1, :] + hl[..., None] * d[..., 1:, :])
    if bc == "clamped":
        one, zero = torch.ones_like(h[..., :1]), torch.zeros_like(h[..., :1])
        diag = torch.cat([one, 2 * (hl + hr), one], -1)
        sub, sup = torch.cat([hr, zero], -1), torch.cat([zero, hl], -1)
        v0 = torch.zeros_like(y[..., 0, :]) if v_i is None else v_i
        v1 = torch.zeros_like(y[..., -1, :]) if v_f is None else v_f
        rhs = cat_broadcast([v0[..., None, :], rhs, v1[..., None, :]], -2)
    else:  # not-a-knot: scipy's first and last rows
        w0, w1 = knots[..., 2:3] - knots[..., :1], knots[..., -1:] - knots[..., -3:-2]
        h0, h1, hm, hn = h[..., :1], h[..., 1:2], h[..., -2:-1], h[..., -1:]
        diag = torch.cat([h1, 2 * (hl + hr), hm], -1)
        sub, sup = torch.cat([hr, w1], -1), torch.cat([w0, hl], -1)
        first = ((h0 + 2 * w0) * h1)[..., None] * d[..., :1, :] + (h0**2)[..., None] * d[..., 1:2, :]
        last = (hn**2)[..., None] * d[..., -2:-1, :] + ((2 * w1 + hn) * hm)[..., None] * d[..., -1:, :]
        rhs = cat_broadcast([first / w0[..., None], rhs, last / w1[..., None]], -2)
    # clamped: every row diagonally dominant (2 (h_l + h_r) against h_l + h_r; the end rows the identity)
    return tridiagonal_solve(sub, diag, sup, rhs, dominant=bc == "clamped")


def mask_outside(traj: Trajectory, inside: Tensor) -> Trajectory:
    """Zero velocity and acceleration where the query time lay outside the trajectory's interval."""
    zero = torch.zeros_like(traj.velocity)
    return Trajectory(
        traj.position, torch.where(inside, traj.velocity, zero), torch.where(inside, traj.acceleration, zero)
    )
