"""Point-to-point timing laws (§4.2.1): cubic (4.1), quintic (4.2), trapezoidal velocity (4.3)-(4.11).

All functions take boundary data of shape (..., n) (numbers broadcast), query times ``t`` of shape (T,)
or (..., T), and return a :class:`Trajectory` of shape (..., T, n). Boundary data that are all numbers or
0-d tensors describe one joint: the result then has shape (..., T) (the T axis of ``t``), as in the
textbook's scalar laws. ``t_f`` may be a number or a tensor broadcastable to (..., n) (use (..., 1) for one
duration per batch element). Times outside [0, t_f] clamp to the end values, with zero velocity and
acceleration there. Everything is differentiable w.r.t. the boundary conditions and ``t_f``.
Inputs follow :mod:`diffkin.validation` (NaN/inf in the data or in ``t`` raise ``NonFiniteError``).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from .._numerics import eps_for, safe_sqrt
from ..errors import ConventionError, DiffkinError, ShapeError
from ..validation import broadcast_batch, shape_str, tensors
from ._common import (
    InfeasibleTrajectoryError,
    Trajectory,
    check_durations,
    clamp_times,
    cubic_coeffs,
    mask_outside,
    poly_eval,
    query_times,
)

__all__ = ["cubic", "quintic", "trapezoidal", "timing_law", "time_scale"]


def _validated(t, **data) -> tuple[dict[str, Tensor], Tensor]:
    """The boundary data (None entries dropped) and the query times, validated together."""
    given = {k: v for k, v in data.items() if v is not None}
    *vals, t = tensors(*((k, v, None) for k, v in given.items()), ("t", t, None))
    return dict(zip(given, vals)), query_times(t)


def _law(kind: str, data: dict[str, Tensor], t: Tensor) -> Trajectory:
    """Evaluate a law on validated data (q_i, q_f, t_f first): broadcast to (..., 1, n), times (..., T, 1).

    All data of shape () (one joint): computed as n = 1 and returned as (..., T).
    """
    shape = broadcast_batch(*((k, v, 0) for k, v in data.items()))
    scalar = len(shape) == 0
    vals = torch.broadcast_tensors(*(v.reshape(1) if scalar else v for v in data.values()))
    broadcast_batch(("boundary data", vals[0], 1), ("t", t, 1))
    check_durations(vals[2])
    b = {k: v[..., None, :] for k, v in zip(data, vals)}
    zero = torch.zeros((), dtype=t.dtype, device=t.device)
    tau, inside = clamp_times(t[..., :, None], zero, b["t_f"])
    out = _KERNELS[kind](b, tau, inside)
    return Trajectory(*(x[..., 0] for x in out)) if scalar else out


def _cubic(b: dict[str, Tensor], tau: Tensor, inside: Tensor) -> Trajectory:
    coeffs = cubic_coeffs(b["q_i"], b["q_f"], b["v_i"], b["v_f"], b["t_f"])
    return mask_outside(poly_eval(coeffs, tau), inside)


def cubic(q_i, q_f, t_f, t, v_i=0.0, v_f=0.0) -> Trajectory:
    """Cubic timing law (4.1) with q(0)=q_i, q(t_f)=q_f, qdot(0)=v_i, qdot(t_f)=v_f.

    q_i, q_f, v_i, v_f: (..., n); t: (T,) or (..., T) -> Trajectory of (..., T, n); for one joint given as
    numbers or 0-d tensors, of (..., T).
    """
    return _law("cubic", *_validated(t, q_i=q_i, q_f=q_f, t_f=t_f, v_i=v_i, v_f=v_f))


def _quintic(b: dict[str, Tensor], tau: Tensor, inside: Tensor) -> Trajectory:
    q0, q1, h, v0, v1, a0, a1 = (b[k] for k in ("q_i", "q_f", "t_f", "v_i", "v_f", "a_i", "a_f"))
    d = q1 - q0
    # Solution of the six conditions q, qdot, qddot at 0 and h on (4.2).
    a3 = (20 * d - (8 * v1 + 12 * v0) * h - (3 * a0 - a1) * h**2) / (2 * h**3)
    a4 = (-30 * d + (14 * v1 + 16 * v0) * h + (3 * a0 - 2 * a1) * h**2) / (2 * h**4)
    a5 = (12 * d - 6 * (v1 + v0) * h - (a0 - a1) * h**2) / (2 * h**5)
    return mask_outside(poly_eval([q0, v0, a0 / 2, a3, a4, a5], tau), inside)


def quintic(q_i, q_f, t_f, t, v_i=0.0, v_f=0.0, a_i=0.0, a_f=0.0) -> Trajectory:
    """Quintic timing law (4.2) with position, velocity and acceleration imposed at t=0 and t=t_f.

    q_i, q_f, v_i, v_f, a_i, a_f: (..., n); t: (T,) or (..., T) -> Trajectory of (..., T, n); for one joint
    given as numbers or 0-d tensors (e.g. ``quintic(torch.tensor(1.0), torch.tensor(4.0), 2.0, t)``,
    Problem 4.1), of (..., T).
    """
    data = _validated(t, q_i=q_i, q_f=q_f, t_f=t_f, v_i=v_i, v_f=v_f, a_i=a_i, a_f=a_f)
    return _law("quintic", *data)


def _tol(x: Tensor) -> float:
    return 1e-9 + 64 * eps_for(x)


def _from_cruise_velocity(d: Tensor, tf: Tensor, qd_c: Tensor) -> tuple[Tensor, Tensor]:
    """t_c (4.10) and signed acceleration (4.11) from the cruise velocity magnitude, checked by (4.9)."""
    ad, moving, qd = d.abs(), d != 0, qd_c.abs()
    bad = moving & ((qd * tf <= ad * (1 + _tol(d))) | (qd * tf > 2 * ad * (1 + _tol(d))))
    if bool(bad.any()):
        raise InfeasibleTrajectoryError(
            "cruise velocity violates (4.9): need |q_f - q_i|/t_f < |qd_c| <= 2|q_f - q_i|/t_f"
        )
    qd_safe = torch.where(moving, qd, torch.ones_like(qd))
    t_c = torch.where(moving, tf - ad / qd_safe, tf / 3)  # (4.10)
    qdd = (
        torch.sign(d) * qd / torch.where(moving, t_c, torch.ones_like(t_c))
    )  # (4.11): qd_c^2/(qd_c t_f - |d|)
    return t_c, qdd


def _from_acceleration(d: Tensor, tf: Tensor, acc: Tensor) -> tuple[Tensor, Tensor]:
    """t_c (4.6) and signed acceleration from the acceleration magnitude, checked by (4.7)."""
    ad, moving = d.abs(), d != 0
    if bool((moving & (acc * tf**2 < 4 * ad * (1 - _tol(d)))).any()):
        raise InfeasibleTrajectoryError(
            "acceleration violates (4.7): need |qdd_c| >= 4|q_f - q_i|/t_f^2 "
            f"(largest required {float((4 * ad / tf**2).max()):.6g})"
        )
    acc_safe = torch.where(moving, acc, torch.ones_like(acc))
    disc = torch.where(moving, (tf**2 - 4 * ad / acc_safe).clamp_min(0), tf**2)
    t_c = torch.where(moving, tf / 2 - 0.5 * safe_sqrt(disc), tf / 3)  # (4.6)
    return t_c, torch.sign(d) * acc


def _trapezoid_params(d: Tensor, tf: Tensor, qdd_c, qd_c, qdd_max) -> tuple[Tensor, Tensor]:
    """Blend time t_c and signed blend acceleration, from whichever of the data was given."""
    if qdd_c is not None and qd_c is not None:
        raise DiffkinError("give at most one of qdd_c and qd_c")
    if qd_c is not None:
        t_c, qdd = _from_cruise_velocity(d, tf, qd_c)
    elif qdd_c is not None:
        t_c, qdd = _from_acceleration(d, tf, qdd_c.abs())
    elif qdd_max is not None:  # the default profile, or the bound where the default exceeds it
        t_c, qdd = _from_acceleration(d, tf, torch.minimum(4.5 * d.abs() / tf**2, qdd_max.abs()))
    else:  # t_c = t_f/3: cruise at 1.5 times the mean velocity (what (4.6) gives, without its rounding)
        t_c, qdd = tf / 3 + torch.zeros_like(d), 4.5 * d / tf**2
    if qdd_max is not None and bool((qdd.abs() > qdd_max.abs() * (1 + _tol(d))).any()):
        raise InfeasibleTrajectoryError("the requested profile exceeds qdd_max")
    return t_c, qdd


def trapezoidal(q_i, q_f, t_f, t, qdd_c=None, qd_c=None, qdd_max=None) -> Trajectory:
    """Trapezoidal velocity profile: linear segment with parabolic blends (4.8).

    Give at most one of ``qdd_c`` (blend acceleration magnitude, checked against (4.7); t_c from (4.6))
    and ``qd_c`` (cruise velocity magnitude, checked against (4.9); t_c, qdd_c from (4.10)-(4.11)). With
    neither, t_c = t_f/3 (cruise at 1.5x the mean velocity), lowered to ``qdd_max`` if that bound is
    smaller; ``qdd_max`` also checks the other two cases. Magnitudes: signs follow q_f - q_i. Joints with
    q_f = q_i stay put. Raises :class:`InfeasibleTrajectoryError` where a bound admits no profile.

    q_i, q_f, qdd_c, qd_c, qdd_max: (..., n); t: (T,) or (..., T) -> Trajectory of (..., T, n); for one
    joint given as numbers or 0-d tensors, of (..., T).
    """
    data, t = _validated(t, q_i=q_i, q_f=q_f, t_f=t_f, qdd_c=qdd_c, qd_c=qd_c, qdd_max=qdd_max)
    return _law("trapezoidal", data, t)


def _trapezoidal(b: dict[str, Tensor], tau: Tensor, inside: Tensor) -> Trajectory:
    q0, q1, tf = b["q_i"], b["q_f"], b["t_f"]
    t_c, qdd = _trapezoid_params(q1 - q0, tf, b.get("qdd_c"), b.get("qd_c"), b.get("qdd_max"))
    first, last = tau <= t_c, tau > tf - t_c
    rest = tf - tau
    pos = torch.where(
        first,
        q0 + 0.5 * qdd * tau**2,
        torch.where(last, q1 - 0.5 * qdd * rest**2, q0 + qdd * t_c * (tau - t_c / 2)),
    )
    vel = torch.where(first, qdd * tau, torch.where(last, qdd * rest, qdd * t_c))
    acc = torch.where(first, qdd, torch.where(last, -qdd, torch.zeros_like(qdd))).expand_as(vel)
    return mask_outside(Trajectory(pos, vel, acc), inside)


_LAWS = ("cubic", "quintic", "trapezoidal")
_KERNELS = {"cubic": _cubic, "quintic": _quintic, "trapezoidal": _trapezoidal}
_DEFAULTS = {"cubic": {"v_i": 0.0, "v_f": 0.0}, "quintic": {"v_i": 0.0, "v_f": 0.0, "a_i": 0.0, "a_f": 0.0},
             "trapezoidal": {}}
_OPTIONS = {"cubic": ("v_i", "v_f"), "quintic": ("v_i", "v_f", "a_i", "a_f"),
            "trapezoidal": ("qdd_c", "qd_c", "qdd_max")}


def timing_law(s_f, t_f, t, kind: str = "cubic", **kwargs) -> Trajectory:
    """Scalar timing law s(t) from 0 to s_f in t_f (§4.3.2): "cubic", "quintic" or "trapezoidal".

    s_f, t_f and ``kwargs`` (the law's options, e.g. ``qdd_c``, ``v_f``): numbers or tensors of shape (...);
    t: (T,) or (..., T) -> Trajectory of shape (..., T).
    """
    data, t = _validated(t, s_f=s_f, t_f=t_f, **_law_options(kind, kwargs))
    return _timing_law(kind, data, t)


def _law_options(kind: str, kwargs: dict) -> dict:
    """The options of the law ``kind`` with their defaults; unknown laws and options refused."""
    if kind not in _LAWS:
        raise ConventionError(f"unknown timing law {kind!r}; valid: {', '.join(_LAWS)}")
    unknown = set(kwargs) - set(_OPTIONS[kind])
    if unknown:
        raise TypeError(f"unknown option(s) {sorted(unknown)} of the {kind} law; valid: {_OPTIONS[kind]}")
    return {**_DEFAULTS[kind], **kwargs}


def _timing_law(kind: str, data: dict[str, Tensor], t: Tensor) -> Trajectory:
    """:func:`timing_law` on validated data (``s_f``, ``t_f`` and the law's options, each (...))."""
    s_f = data.pop("s_f")
    b = {"q_i": torch.zeros_like(s_f)[..., None], "q_f": s_f[..., None], "t_f": data.pop("t_f")[..., None]}
    b.update({k: v[..., None] for k, v in data.items()})
    return Trajectory(*(x[..., 0] for x in _law(kind, b, t)))


def time_scale(traj: Trajectory | Callable[[Tensor], Trajectory], factor):
    """Slow a trajectory down by ``factor`` k (duration k t_f): q'(t) = q(t/k), so q' dot = qdot/k and
    q' ddot = qddot/k^2.

    Given a :class:`Trajectory` sampled at times t, returns the scaled one, valid at times k t. Given a
    function t -> Trajectory, returns the function of the new time. ``factor``: positive number or a
    tensor broadcastable to the arrays (e.g. (..., 1, 1)) or, for functions, to ``t``.
    """
    if isinstance(traj, Trajectory):
        pos, vel, acc, k = tensors(
            ("traj.position", traj.position, None), ("traj.velocity", traj.velocity, None),
            ("traj.acceleration", traj.acceleration, None), ("factor", factor, None),
        )
        if not pos.shape == vel.shape == acc.shape:
            raise ShapeError(
                "expected a Trajectory whose position, velocity and acceleration have one shape, got "
                f"{shape_str(pos.shape)}, {shape_str(vel.shape)} and {shape_str(acc.shape)}"
            )
        broadcast_batch(("traj", pos, 0), ("factor", k, 0))
        return _scale(Trajectory(pos, vel, acc), _check_factor(k))
    if callable(traj):
        _check_factor(tensors(("factor", factor, None))[0])

        def scaled(t) -> Trajectory:
            t, k = tensors(("t", t, None), ("factor", factor, None))
            return _scale(traj(t / k), k)

        return scaled
    raise TypeError(f"time_scale expects a Trajectory or a callable, got {type(traj).__name__}")


def _check_factor(k: Tensor) -> Tensor:
    if bool((k <= 0).any()):
        raise DiffkinError(f"time-scaling factor must be > 0, got min {float(k.min())}")
    return k


def _scale(tr: Trajectory, k: Tensor) -> Trajectory:
    return Trajectory(tr.position, tr.velocity / k, tr.acceleration / k**2)
