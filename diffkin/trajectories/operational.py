"""Operational-space trajectories (§4.3): path primitives in arc length, timing along a path, orientation.

Paths are functions of the arc length ``s`` (..., T) returning a :class:`PathSample` of shape (..., T, 3):
build one with ``functools.partial(segment_path, p_i, p_f)`` or a lambda, and combine it with a timing
law s(t) (``timing_law``) in :func:`cartesian_trajectory`.

Orientation trajectories take ``timing`` in one of two forms:

* a :class:`Trajectory` of a normalised coordinate sigma(t) of shape (..., T) going from 0 to 1
  (e.g. ``timing_law(1.0, t_f, t)``); or
* a function ``length -> Trajectory``: it receives the length of the motion (..., ) (the Euler-angle
  distance |phi_f - phi_i| in (4.51), the angle theta_f in (4.52)) and returns s(t) from 0 to that
  length, e.g. ``lambda L: timing_law(L, t_f, t, "trapezoidal", qdd_max=2.0)`` to bound the angular
  acceleration.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from .._numerics import eps_for, safe_norm, safe_normalize
from ..errors import DiffkinError, ShapeError
from ..rotations import (
    euler_rate_matrix,
    euler_to_matrix,
    matrix_to_rotvec,
    quaternion_conjugate,
    quaternion_multiply,
    quaternion_slerp,
    quaternion_to_matrix,
    quaternion_to_rotvec,
    rotvec_to_matrix,
)
from ..validation import check_shape, check_tensor
from ._common import Trajectory, as_tensor, query_times
from .point_to_point import timing_law

__all__ = [
    "PathSample",
    "OrientationTrajectory",
    "QuaternionTrajectory",
    "segment_path",
    "circle_path",
    "circle_frame",
    "cartesian_trajectory",
    "cartesian_segment_trajectory",
    "euler_angle_trajectory",
    "euler_orientation_trajectory",
    "axis_angle_orientation_trajectory",
    "quaternion_orientation_trajectory",
]

Timing = Trajectory | Callable[[Tensor], Trajectory]


class PathSample(NamedTuple):
    """A path p(s) sampled at arc lengths s: position, tangent dp/ds and d2p/ds2, each (..., T, 3)."""

    position: Tensor
    dp_ds: Tensor
    d2p_ds2: Tensor


class OrientationTrajectory(NamedTuple):
    """R_e(t) (..., T, 3, 3); angular velocity and acceleration (..., T, 3) in the base frame."""

    rotation: Tensor
    angular_velocity: Tensor
    angular_acceleration: Tensor


class QuaternionTrajectory(NamedTuple):
    """Q_e(t) (..., T, 4) (scalar first), angular velocity and acceleration (..., T, 3) in the base frame."""

    quaternion: Tensor
    angular_velocity: Tensor
    angular_acceleration: Tensor


def segment_path(p_i: Tensor, p_f: Tensor, s) -> PathSample:
    """Rectilinear path (4.34) from p_i to p_f, with dp/ds (4.35) and d2p/ds2 = 0 (4.36).

    p_i, p_f: (..., m) (m = 3 for positions; any m works, e.g. Euler angles (4.51)); s: (T,) or (..., T)
    -> PathSample of (..., T, m). s runs from 0 to |p_f - p_i|.
    """
    check_tensor(p_i, "p_i")
    p_f = as_tensor(p_f, p_i, "p_f")
    if p_i.ndim < 1 or p_f.shape[-1:] != p_i.shape[-1:]:
        raise ShapeError(
            f"expected p_i and p_f of shape (..., m), got {tuple(p_i.shape)} and {tuple(p_f.shape)}"
        )
    s = query_times(s, p_i)[..., None]
    t_hat = safe_normalize(p_f - p_i)[..., None, :]
    pos = p_i[..., None, :] + s * t_hat
    return PathSample(pos, t_hat.expand_as(pos), torch.zeros_like(pos))


def circle_frame(axis_point: Tensor, axis: Tensor, p_i: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Centre c (4.37), radius rho and rotation R = [x' y' z'] (4.39) of the circle through p_i about r."""
    check_shape(p_i, (3,), "point_on_circle")
    d = as_tensor(axis_point, p_i, "center")
    r = as_tensor(axis, p_i, "axis")
    check_shape(d, (3,), "center")
    check_shape(r, (3,), "axis")
    if bool((safe_norm(r) <= eps_for(r)).any()):
        raise DiffkinError("axis must be a non-zero (..., 3) vector")
    r = safe_normalize(r)
    delta = p_i - d
    c = d + (delta * r).sum(-1, keepdim=True) * r  # (4.37)
    rho = safe_norm(p_i - c)
    if bool((rho <= eps_for(rho) ** 0.5 * safe_norm(delta).clamp_min(1.0)).any()):
        raise DiffkinError(
            "point_on_circle lies on the circle axis: need |delta^T r| < |delta| (degenerate circle)"
        )
    x = (p_i - c) / rho[..., None]
    y = torch.linalg.cross(r.expand_as(x), x)
    R = torch.stack(torch.broadcast_tensors(x, y, r), dim=-1)
    return c, rho, R


def circle_path(center: Tensor, axis: Tensor, point_on_circle: Tensor, s) -> PathSample:
    """Circular path (4.38)-(4.39) through ``point_on_circle`` (p_i, origin of s) about ``axis`` r.

    ``center``: any point d of the axis (the centre itself is fine; (4.37) projects p_i onto the axis).
    Motion is counter-clockwise about r (right-hand rule). Derivatives (4.40)-(4.41). center, axis,
    point_on_circle: (..., 3); s: (T,) or (..., T) -> PathSample of (..., T, 3). Radius: |p_i - c|.
    """
    c, rho, R = circle_frame(center, axis, point_on_circle)
    s = query_times(s, point_on_circle)
    rho_t = rho[..., None]
    ang = s / rho_t
    cos, sin, zero = torch.cos(ang), torch.sin(ang), torch.zeros_like(ang)
    local = [
        torch.stack([rho_t * cos, rho_t * sin, zero], -1),  # (4.38)
        torch.stack([-sin, cos, zero], -1),
        torch.stack([-cos / rho_t, -sin / rho_t, zero], -1),
    ]
    rot = [torch.einsum("...ij,...tj->...ti", R, v) for v in local]
    return PathSample(c[..., None, :] + rot[0], rot[1], rot[2])


def cartesian_trajectory(path: Callable[[Tensor], PathSample], timing: Trajectory) -> Trajectory:
    """Position, velocity and acceleration along ``path`` with the timing law s(t) (§4.3.2).

    p = f(s), p_dot = s_dot dp/ds (4.42), (4.44), p_ddot = s_ddot dp/ds + s_dot^2 d2p/ds2 (4.43), (4.45).
    path: s (..., T) -> PathSample; timing: Trajectory of s with shape (..., T) -> Trajectory (..., T, m).
    """
    ps = path(timing.position)
    sd, sdd = timing.velocity[..., None], timing.acceleration[..., None]
    return Trajectory(ps.position, sd * ps.dp_ds, sdd * ps.dp_ds + sd**2 * ps.d2p_ds2)


def cartesian_segment_trajectory(
    p_i: Tensor, p_f: Tensor, t_f, t, profile: str = "cubic", **kwargs
) -> Trajectory:
    """Straight-line motion p_i -> p_f in t_f: segment (4.34) timed by ``timing_law`` (4.42)-(4.43).

    p_i, p_f: (..., m); t_f: number or (...); ``profile``/``kwargs`` as in ``timing_law`` (bounds act on
    the arc length s) -> Trajectory of (..., T, m).
    """
    check_tensor(p_i, "p_i")
    p_f = as_tensor(p_f, p_i, "p_f")
    law = timing_law(safe_norm(p_f - p_i), t_f, query_times(t, p_i), profile, **kwargs)
    return cartesian_trajectory(lambda s: segment_path(p_i, p_f, s), law)


def _along(delta: Tensor, timing: Timing) -> tuple[Trajectory, Tensor]:
    """Scalar law and direction d with x(t) = x_i + s(t) d for a straight motion by ``delta`` (..., m)."""
    if isinstance(timing, Trajectory):
        return timing, delta
    if callable(timing):
        return timing(safe_norm(delta)), safe_normalize(delta)
    raise TypeError(f"timing must be a Trajectory or a callable, got {type(timing).__name__}")


def _scaled(law: Trajectory, d: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    d = d[..., None, :]
    return law.position[..., None] * d, law.velocity[..., None] * d, law.acceleration[..., None] * d


def euler_angle_trajectory(phi_i: Tensor, phi_f: Tensor, timing: Timing) -> Trajectory:
    """Euler angles moving on the segment from phi_i to phi_f (4.51): (..., 3) -> Trajectory (..., T, 3)."""
    check_shape(phi_i, (3,), "phi_i")
    phi_f = check_shape(as_tensor(phi_f, phi_i, "phi_f"), (3,), "phi_f")
    law, d = _along(phi_f - phi_i, timing)
    pos, vel, acc = _scaled(law, d)
    return Trajectory(phi_i[..., None, :] + pos, vel, acc)


def euler_orientation_trajectory(phi_i: Tensor, phi_f: Tensor, timing: Timing, convention: str = "ZYZ"):
    """Orientation from the Euler-angle law (4.51): R from the angles (2.18), omega = T(phi) phi_dot (3.64).

    omega_dot = T(phi) phi_ddot + T_dot phi_dot, with T's columns a_k the successive rotation axes, so
    T_dot phi_dot = (phi1_dot a_1) x (phi2_dot a_2) + (phi1_dot a_1 + phi2_dot a_2) x (phi3_dot a_3).
    Returns OrientationTrajectory of (..., T, 3, 3), (..., T, 3), (..., T, 3).
    """
    phi = euler_angle_trajectory(phi_i, phi_f, timing)
    R = euler_to_matrix(phi.position, convention)
    Tm = euler_rate_matrix(phi.position, convention)
    w = [Tm[..., :, k] * phi.velocity[..., k : k + 1] for k in range(3)]
    omega = w[0] + w[1] + w[2]
    coupling = torch.linalg.cross(w[0], w[1]) + torch.linalg.cross(w[0] + w[1], w[2])
    omega_dot = torch.einsum("...ij,...j->...i", Tm, phi.acceleration) + coupling
    return OrientationTrajectory(R, omega, omega_dot)


def _relative_rotvec(R_i: Tensor, R_f: Tensor) -> Tensor:
    """theta_f r^i of R_i^T R_f ((4.52)-(4.53), computed without the 1/sin singularity)."""
    return matrix_to_rotvec(R_i.transpose(-1, -2) @ R_f)


def axis_angle_orientation_trajectory(R_i: Tensor, R_f: Tensor, timing: Timing) -> OrientationTrajectory:
    """Rotation about the fixed axis r^i of R_i^T R_f (4.52)-(4.55).

    R^i(t) = R(theta(t), r^i) (2.25); omega^i = theta_dot r^i (4.54), omega_dot^i = theta_ddot r^i (4.55);
    R_e = R_i R^i, omega_e = R_i omega^i, omega_dot_e = R_i omega_dot^i. Smooth at theta_f = 0.
    R_i, R_f: (..., 3, 3) -> OrientationTrajectory of (..., T, 3, 3), (..., T, 3), (..., T, 3).
    """
    check_shape(R_i, (3, 3), "R_i")
    R_f = check_shape(as_tensor(R_f, R_i, "R_f"), (3, 3), "R_f")
    law, d = _along(_relative_rotvec(R_i, R_f), timing)
    rv, w, wd = _scaled(law, d)
    Ri = R_i[..., None, :, :]
    rotate = lambda v: torch.einsum("...ij,...j->...i", Ri, v)  # noqa: E731
    return OrientationTrajectory(Ri @ rotvec_to_matrix(rv), rotate(w), rotate(wd))


def quaternion_orientation_trajectory(Q_i: Tensor, Q_f: Tensor, timing: Timing) -> QuaternionTrajectory:
    """Unit-quaternion orientation by slerp on the shortest arc (``quaternion_slerp``).

    Equivalent to the angle-axis law (4.52)-(4.55) with quaternion output; omega_e = R_i theta_dot r^i.
    Q_i, Q_f: (..., 4) -> QuaternionTrajectory of (..., T, 4), (..., T, 3), (..., T, 3).
    """
    check_shape(Q_i, (4,), "Q_i")
    Q_f = check_shape(as_tensor(Q_f, Q_i, "Q_f"), (4,), "Q_f")
    dQ = quaternion_multiply(quaternion_conjugate(Q_i), Q_f)
    dQ = torch.where(dQ[..., :1] < 0, -dQ, dQ)  # shortest arc, as in slerp
    v = quaternion_to_rotvec(dQ)
    law, d = _along(v, timing)
    if isinstance(timing, Trajectory):
        sigma = law.position
    else:  # arc angle -> fraction of the total angle
        theta_f = safe_norm(v)[..., None]
        sigma = law.position / torch.where(theta_f > 0, theta_f, torch.ones_like(theta_f))
    Q = quaternion_slerp(Q_i[..., None, :], Q_f[..., None, :], sigma)
    _, w, wd = _scaled(law, d)
    Ri = quaternion_to_matrix(Q_i)[..., None, :, :]
    rotate = lambda x: torch.einsum("...ij,...j->...i", Ri, x)  # noqa: E731
    return QuaternionTrajectory(Q, rotate(w), rotate(wd))
