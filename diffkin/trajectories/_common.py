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

from ..errors import DiffkinError, ShapeError
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
        torch.broadcast_shapes(*[x.shape[:dim] + (1,) + x.shape[len(x.shape) + dim + 1 :] for x in xs])
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
    batch = torch.broadcast_shapes(inner.shape[:-1], t.shape[:-1])
    inner = inner.expand(*batch, inner.shape[-1]).contiguous()
    return torch.searchsorted(inner, t.expand(*batch, t.shape[-1]).contiguous(), right=True)


def take(values: Tensor, idx: Tensor) -> Tensor:
    """values (..., K, n) gathered at idx (..., T) along K -> (..., T, n); batch dims broadcast."""
    batch = torch.broadcast_shapes(values.shape[:-2], idx.shape[:-1])
    K, n = values.shape[-2:]
    T = idx.shape[-1]
    v = values.expand(*batch, K, n)
    i = idx.expand(*batch, T)[..., None].expand(*batch, T, n)
    return torch.gather(v, -2, i)


def take_scalar(values: Tensor, idx: Tensor) -> Tensor:
    """values (..., K) gathered at idx (..., T) -> (..., T)."""
    return take(values[..., None], idx)[..., 0]


def poly_eval(coeffs: list[Tensor], tau: Tensor) -> Trajectory:
    """Horner evaluation of sum_k a_k tau^k and its first two derivatives in tau."""
    p = torch.zeros_like(tau * coeffs[-1])
    v = torch.zeros_like(p)
    a = torch.zeros_like(p)
    for c in reversed(coeffs):
        a = a * tau + 2 * v
        v = v * tau + p
        p = p * tau + c
    return Trajectory(p, v, a)


def cubic_coeffs(q0: Tensor, q1: Tensor, v0: Tensor, v1: Tensor, h: Tensor) -> list[Tensor]:
    """Coefficients a_0..a_3 of (4.1) from the four boundary conditions below it."""
    d = q1 - q0
    a2 = (3 * d - (2 * v0 + v1) * h) / h**2
    a3 = (-2 * d + (v0 + v1) * h) / h**3
    return [q0, v0, a2, a3]


def mask_outside(traj: Trajectory, inside: Tensor) -> Trajectory:
    """Zero velocity and acceleration where the query time lay outside the trajectory's interval."""
    zero = torch.zeros_like(traj.velocity)
    return Trajectory(
        traj.position, torch.where(inside, traj.velocity, zero), torch.where(inside, traj.acceleration, zero)
    )
