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

from .._numerics import eps_for, stable_norm, stable_normalize
from ..errors import DiffkinError, ShapeError
from ..rotations import (
    _canonical,
    _convention,
    _euler_rate_matrix,
    _euler_to_matrix,
    _matrix_to_rotvec,
    _quaternion_conjugate,
    _quaternion_multiply,
    _quaternion_slerp,
    _quaternion_to_matrix,
    _quaternion_to_rotvec,
    _rotvec_to_matrix,
    _unit,
)
from ..validation import broadcast_batch, shape_str, tensors
from ._common import Trajectory, query_times
from .point_to_point import _law_options, _timing_law

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


def _timing_specs(timing) -> list:
    """The three tensors of a Trajectory ``timing`` as validation specs (none for a callable)."""
    if isinstance(timing, Trajectory):
        return [(f"timing.{k}", getattr(timing, k), None) for k in Trajectory._fields]
    if callable(timing):
        return []
    raise TypeError(f"timing must be a Trajectory or a callable, got {type(timing).__name__}")


def _law_of(fields: list[Tensor], batch: Tensor | None = None, k: int = 1) -> Trajectory:
    """A validated timing law: its fields' shapes broadcast (and with ``batch``'s first dims, all but k)."""
    named = [(f"timing.{name}", x, 0) for name, x in zip(Trajectory._fields, fields)]
    broadcast_batch(*named)
    if batch is not None:
        broadcast_batch(("timing", fields[0], 1), ("the boundary data", batch, k))
    return Trajectory(*fields)


def _ends(a: tuple[str, object], b: tuple[str, object], trailing: tuple[int | None, ...], timing):
    """Validate the two ends of a motion and a Trajectory ``timing`` together."""
    x_a, x_b, *law = tensors((a[0], a[1], trailing), (b[0], b[1], trailing), *_timing_specs(timing))
    if x_a.shape[-1] != x_b.shape[-1]:
        raise ShapeError(f"expected {a[0]} and {b[0]} of one shape (..., m), "
                         f"got {shape_str(x_a.shape)} and {shape_str(x_b.shape)}")
    broadcast_batch((a[0], x_a, len(trailing)), (b[0], x_b, len(trailing)))
    return x_a, x_b, (_law_of(law, x_a, len(trailing)) if law else timing)


def segment_path(p_i: Tensor, p_f: Tensor, s) -> PathSample:
    """Rectilinear path (4.34) from p_i to p_f, with dp/ds (4.35) and d2p/ds2 = 0 (4.36).

    p_i, p_f: (..., m) (m = 3 for positions; any m works, e.g. Euler angles (4.51)); s: (T,) or (..., T)
    -> PathSample of (..., T, m). s runs from 0 to |p_f - p_i|.
    """
    p_i, p_f, s = tensors(("p_i", p_i, (None,)), ("p_f", p_f, (None,)), ("s", s, None))
    if p_f.shape[-1] != p_i.shape[-1]:
        raise ShapeError(
            f"expected p_i and p_f of shape (..., m), got {shape_str(p_i.shape)} and {shape_str(p_f.shape)}"
        )
    s = query_times(s)
    broadcast_batch(("p_i", p_i, 1), ("p_f", p_f, 1), ("s", s, 1))
    return _segment_path(p_i, p_f, s)


def _segment_path(p_i: Tensor, p_f: Tensor, s: Tensor) -> PathSample:
    s = s[..., None]
    t_hat = stable_normalize(p_f - p_i)[..., None, :]
    pos = p_i[..., None, :] + s * t_hat
    return PathSample(pos, t_hat.expand_as(pos), torch.zeros_like(pos))


def circle_frame(axis_point: Tensor, axis: Tensor, p_i: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Centre c (4.37), radius rho and rotation R = [x' y' z'] (4.39) of the circle through p_i about r."""
    d, r, p_i = tensors(("center", axis_point, (3,)), ("axis", axis, (3,)), ("point_on_circle", p_i, (3,)))
    broadcast_batch(("center", d, 1), ("axis", r, 1), ("point_on_circle", p_i, 1))
    return _circle_frame(d, r, p_i)


def _circle_frame(d: Tensor, r: Tensor, p_i: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    if bool((stable_norm(r) <= eps_for(r)).any()):
        raise DiffkinError("axis must be a non-zero (..., 3) vector")
    r = stable_normalize(r)
    delta = p_i - d
    c = d + (delta * r).sum(-1, keepdim=True) * r  # (4.37)
    rho = stable_norm(p_i - c)
    if bool((rho <= eps_for(rho) ** 0.5 * stable_norm(delta).clamp_min(1.0)).any()):
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
    d, r, p_i, s = tensors(
        ("center", center, (3,)), ("axis", axis, (3,)), ("point_on_circle", point_on_circle, (3,)),
        ("s", s, None),
    )
    s = query_times(s)
    broadcast_batch(("center", d, 1), ("axis", r, 1), ("point_on_circle", p_i, 1), ("s", s, 1))
    c, rho, R = _circle_frame(d, r, p_i)
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
    if not isinstance(timing, Trajectory):
        raise TypeError(f"timing must be a Trajectory, got {type(timing).__name__}")
    return _cartesian(path, _law_of(list(tensors(*_timing_specs(timing)))))


def _cartesian(path: Callable[[Tensor], PathSample], timing: Trajectory) -> Trajectory:
    ps = path(timing.position)
    sd, sdd = timing.velocity[..., None], timing.acceleration[..., None]
    # sd (sd d2p/ds2), not sd^2 d2p/ds2: no overflow of sd^2 (float32, far targets) times a null curvature
    return Trajectory(ps.position, sd * ps.dp_ds, sdd * ps.dp_ds + sd * (sd * ps.d2p_ds2))


def cartesian_segment_trajectory(
    p_i: Tensor, p_f: Tensor, t_f, t, profile: str = "cubic", **kwargs
) -> Trajectory:
    """Straight-line motion p_i -> p_f in t_f: segment (4.34) timed by ``timing_law`` (4.42)-(4.43).

    p_i, p_f: (..., m); t_f: number or (...); ``profile``/``kwargs`` as in ``timing_law`` (bounds act on
    the arc length s) -> Trajectory of (..., T, m).
    """
    options = _law_options(profile, kwargs)
    names = list(options)
    p_i, p_f, t_f, t, *rest = tensors(
        ("p_i", p_i, (None,)), ("p_f", p_f, (None,)), ("t_f", t_f, None), ("t", t, None),
        *((k, options[k], None) for k in names),
    )
    if p_f.shape[-1] != p_i.shape[-1]:
        raise ShapeError(
            f"expected p_i and p_f of shape (..., m), got {shape_str(p_i.shape)} and {shape_str(p_f.shape)}"
        )
    broadcast_batch(("p_i", p_i, 1), ("p_f", p_f, 1))
    law = _timing_law(profile, {"s_f": stable_norm(p_f - p_i), "t_f": t_f, **dict(zip(names, rest))},
                      query_times(t))
    return _cartesian(lambda s: _segment_path(p_i, p_f, s), law)


def _along(delta: Tensor, timing: Timing) -> tuple[Trajectory, Tensor]:
    """Scalar law and direction d with x(t) = x_i + s(t) d for a straight motion by ``delta`` (..., m)."""
    if isinstance(timing, Trajectory):
        return timing, delta
    if callable(timing):
        law = timing(stable_norm(delta))
        if not isinstance(law, Trajectory):
            raise TypeError(f"the timing function must return a Trajectory, got {type(law).__name__}")
        fields = tensors(*_timing_specs(law), like=delta)
        return _law_of(list(fields), delta, 1), stable_normalize(delta)
    raise TypeError(f"timing must be a Trajectory or a callable, got {type(timing).__name__}")


def _scaled(law: Trajectory, d: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    d = d[..., None, :]
    return law.position[..., None] * d, law.velocity[..., None] * d, law.acceleration[..., None] * d


def euler_angle_trajectory(phi_i: Tensor, phi_f: Tensor, timing: Timing) -> Trajectory:
    """Euler angles moving on the segment from phi_i to phi_f (4.51): (..., 3) -> Trajectory (..., T, 3)."""
    phi_i, phi_f, timing = _ends(("phi_i", phi_i), ("phi_f", phi_f), (3,), timing)
    return _euler_angle_trajectory(phi_i, phi_f, timing)


def _euler_angle_trajectory(phi_i: Tensor, phi_f: Tensor, timing: Timing) -> Trajectory:
    law, d = _along(phi_f - phi_i, timing)
    pos, vel, acc = _scaled(law, d)
    return Trajectory(phi_i[..., None, :] + pos, vel, acc)


def euler_orientation_trajectory(phi_i: Tensor, phi_f: Tensor, timing: Timing, convention: str = "ZYZ"):
    """Orientation from the Euler-angle law (4.51): R from the angles (2.18), omega = T(phi) phi_dot (3.64).

    omega_dot = T(phi) phi_ddot + T_dot phi_dot, with T's columns a_k the successive rotation axes, so
    T_dot phi_dot = (phi1_dot a_1) x (phi2_dot a_2) + (phi1_dot a_1 + phi2_dot a_2) x (phi3_dot a_3).
    Returns OrientationTrajectory of (..., T, 3, 3), (..., T, 3), (..., T, 3).
    """
    convention = _convention(convention)
    phi_i, phi_f, timing = _ends(("phi_i", phi_i), ("phi_f", phi_f), (3,), timing)
    phi = _euler_angle_trajectory(phi_i, phi_f, timing)
    R = _euler_to_matrix(phi.position, convention)
    Tm = _euler_rate_matrix(phi.position, convention)
    w = [Tm[..., :, k] * phi.velocity[..., k : k + 1] for k in range(3)]
    omega = w[0] + w[1] + w[2]
    coupling = torch.linalg.cross(w[0], w[1]) + torch.linalg.cross(w[0] + w[1], w[2])
    omega_dot = torch.einsum("...ij,...j->...i", Tm, phi.acceleration) + coupling
    return OrientationTrajectory(R, omega, omega_dot)


def _relative_rotvec(R_i: Tensor, R_f: Tensor) -> Tensor:
    """theta_f r^i of R_i^T R_f ((4.52)-(4.53), computed without the 1/sin singularity)."""
    return _matrix_to_rotvec(R_i.transpose(-1, -2) @ R_f)


def axis_angle_orientation_trajectory(R_i: Tensor, R_f: Tensor, timing: Timing) -> OrientationTrajectory:
    """Rotation about the fixed axis r^i of R_i^T R_f (4.52)-(4.55).

    R^i(t) = R(theta(t), r^i) (2.25); omega^i = theta_dot r^i (4.54), omega_dot^i = theta_ddot r^i (4.55);
    R_e = R_i R^i, omega_e = R_i omega^i, omega_dot_e = R_i omega_dot^i. Smooth at theta_f = 0.
    R_i, R_f: (..., 3, 3) -> OrientationTrajectory of (..., T, 3, 3), (..., T, 3), (..., T, 3).
    """
    R_i, R_f, timing = _ends(("R_i", R_i), ("R_f", R_f), (3, 3), timing)
    law, d = _along(_relative_rotvec(R_i, R_f), timing)
    rv, w, wd = _scaled(law, d)
    Ri = R_i[..., None, :, :]
    rotate = lambda v: torch.einsum("...ij,...j->...i", Ri, v)  # noqa: E731
    return OrientationTrajectory(Ri @ _rotvec_to_matrix(rv), rotate(w), rotate(wd))


def quaternion_orientation_trajectory(Q_i: Tensor, Q_f: Tensor, timing: Timing) -> QuaternionTrajectory:
    """Unit-quaternion orientation by slerp on the shortest arc (``quaternion_slerp``).

    Equivalent to the angle-axis law (4.52)-(4.55) with quaternion output; omega_e = R_i theta_dot r^i.
    Q_i, Q_f: (..., 4) -> QuaternionTrajectory of (..., T, 4), (..., T, 3), (..., T, 3).
    """
    Q_i, Q_f, timing = _ends(("Q_i", Q_i), ("Q_f", Q_f), (4,), timing)
    dQ = _canonical(_quaternion_multiply(_quaternion_conjugate(Q_i), Q_f))  # shortest arc, as in slerp
    v = _quaternion_to_rotvec(dQ)
    law, d = _along(v, timing)
    if isinstance(timing, Trajectory):
        sigma = law.position
    else:  # arc angle -> fraction of the total angle
        theta_f = stable_norm(v)[..., None]
        sigma = law.position / torch.where(theta_f > 0, theta_f, torch.ones_like(theta_f))
    Q = _quaternion_slerp(Q_i[..., None, :], Q_f[..., None, :], sigma)
    _, w, wd = _scaled(law, d)
    Ri = _quaternion_to_matrix(_unit(Q_i, "Q_i"))[..., None, :, :]
    rotate = lambda x: torch.einsum("...ij,...j->...i", Ri, x)  # noqa: E731
    return QuaternionTrajectory(Q, rotate(w), rotate(wd))
