"""Rotations (textbook §2.2–2.6) and the orientation errors of CLIK (§3.7.3).

Every function takes arbitrary leading batch dims (shape ``()`` included), keeps dtype and device and is
differentiable, with finite gradients at the singular cases (angle 0 and π, Euler representation
singularities). Quaternions are scalar first ``(eta, eps_x, eps_y, eps_z)``; conversions *to* quaternions
return ``eta >= 0`` (2.34). Angles in radians.

Public functions check their input by the rule of :mod:`diffkin.validation` (float32/float64 tensors of
one dtype, numbers and numpy arrays converted, exact trailing shapes, finite values; the finiteness check
synchronises with the device). Hot loops elsewhere in diffkin call the unchecked private kernels
(``_name``) instead.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ._numerics import eps_for, stable_norm, wrap_angle
from .errors import ConventionError, DiffkinError
from .kernels import pose_error as _kpe
from .kernels.quaternion import _canonical, _matrix_to_quaternion
from .kernels.rigid import (  # the raw encodings (checked forms below)
    _axis_angle_to_matrix,
    _euler_rate_matrix,
    _euler_to_matrix,
    _matrix_to_euler,
    _matrix_to_rotvec,
    _quaternion_conjugate,
    _quaternion_multiply,
    _quaternion_slerp,
    _quaternion_to_axis_angle,
    _quaternion_to_matrix,
    _quaternion_to_rotvec,
    _rot,
    _rotvec_to_matrix,
    _rotvec_to_quaternion,
    _skew,
    _vee,
)
from .validation import broadcast_batch, check_trailing, tensors

__all__ = [
    "rot_x",
    "rot_y",
    "rot_z",
    "skew",
    "vee",
    "EULER_CONVENTIONS",
    "euler_to_matrix",
    "matrix_to_euler",
    "euler_rate_matrix",
    "axis_angle_to_matrix",
    "matrix_to_axis_angle",
    "rotvec_to_matrix",
    "matrix_to_rotvec",
    "quaternion_to_matrix",
    "matrix_to_quaternion",
    "axis_angle_to_quaternion",
    "quaternion_to_axis_angle",
    "rotvec_to_quaternion",
    "quaternion_to_rotvec",
    "quaternion_multiply",
    "quaternion_conjugate",
    "quaternion_slerp",
    "orientation_error_euler",
    "orientation_error_axis_angle",
    "orientation_error_quaternion",
]

EULER_CONVENTIONS = ("ZYZ", "RPY")
_ALIASES = {"ZYZ": "ZYZ", "RPY": "RPY", "ZYX": "RPY"}
_BRANCHES = ("positive", "negative")


# ----------------------------------------------------------------------------------------------- checks
def _one(x, trailing, name: str) -> Tensor:
    return tensors((name, x, trailing))[0]


def _convention(convention: str) -> str:
    key = convention.upper() if isinstance(convention, str) else None
    if key not in _ALIASES:
        raise ConventionError(
            f"unknown Euler convention {convention!r}; valid: {', '.join(EULER_CONVENTIONS)} ('ZYX' = 'RPY')"
        )
    return _ALIASES[key]


# ------------------------------------------------------------------------------- elementary rotations


def rot_x(angle) -> Tensor:
    """Elementary rotation about x (2.8): (...) -> (..., 3, 3)."""
    return _rot(_one(angle, None, "angle"), 0)


def rot_y(angle) -> Tensor:
    """Elementary rotation about y (2.7): (...) -> (..., 3, 3)."""
    return _rot(_one(angle, None, "angle"), 1)


def rot_z(angle) -> Tensor:
    """Elementary rotation about z (2.6): (...) -> (..., 3, 3)."""
    return _rot(_one(angle, None, "angle"), 2)


def skew(v: Tensor) -> Tensor:
    """Skew-symmetric matrix S(v) with S(v) w = v x w (3.7): (..., 3) -> (..., 3, 3)."""
    return _skew(_one(v, (3,), "v"))


def vee(S: Tensor) -> Tensor:
    """Inverse of :func:`skew`, taken from the skew-symmetric part (S - S^T)/2: (..., 3, 3) -> (..., 3)."""
    return _vee(_one(S, (3, 3), "S"))


# ----------------------------------------------------------------------------------------- Euler angles


def euler_to_matrix(angles: Tensor, convention: str = "ZYZ") -> Tensor:
    """Rotation matrix of Euler angles (phi, theta, psi): (..., 3) -> (..., 3, 3).

    ``"ZYZ"``: R = Rz(phi) Ry'(theta) Rz''(psi) (2.18). ``"RPY"`` (alias ``"ZYX"``):
    R = Rz(phi) Ry(theta) Rx(psi) (2.21), angles ordered (phi, theta, psi) as in the book.
    """
    convention = _convention(convention)
    return _euler_to_matrix(_one(angles, (3,), "angles"), convention)


def matrix_to_euler(R: Tensor, convention: str = "ZYZ", branch: str = "positive") -> Tensor:
    """Euler angles (phi, theta, psi) of a rotation matrix: (..., 3, 3) -> (..., 3).

    ``branch`` picks the sign of the square root in the inverse formulas:

    - ZYZ: ``"positive"`` (default) theta in (0, pi) (2.19); ``"negative"`` theta in (-pi, 0) (2.20).
    - RPY: ``"positive"`` (default) theta in (-pi/2, pi/2) (2.22); ``"negative"`` theta in
      (pi/2, 3pi/2), returned wrapped to (-pi, pi] (2.23).

    At the representation singularity (sin theta = 0 for ZYZ, cos theta = 0 for RPY) only phi +- psi is
    determined; by convention phi = 0 and psi takes the rest, so the result still reproduces R, with
    finite values and gradients. phi and psi lie in (-pi, pi].
    """
    convention = _convention(convention)
    if branch not in _BRANCHES:
        raise ConventionError(f"unknown branch {branch!r}; valid: {', '.join(_BRANCHES)}")
    return _matrix_to_euler(_one(R, (3, 3), "R"), convention, branch)


def euler_rate_matrix(angles: Tensor, convention: str = "ZYZ") -> Tensor:
    """T(phi) of omega = T(phi) phi_dot (3.64), omega in the base frame: (..., 3) -> (..., 3, 3).

    ZYZ as printed under (3.64) (det = -sin theta); RPY (Problem 3.12) has det = -cos theta.
    """
    convention = _convention(convention)
    return _euler_rate_matrix(_one(angles, (3,), "angles"), convention)


# ----------------------------------------------------------------------------------- angle and axis
def _unit(v: Tensor, name: str) -> Tensor:
    n = stable_norm(v, keepdim=True)  # an axis of 1e30 in float32 is still an axis
    if bool((n <= eps_for(v)).any()):
        raise DiffkinError(f"{name} must be non-zero; got a zero vector")
    return v / n


def axis_angle_to_matrix(axis: Tensor, angle: Tensor) -> Tensor:
    """Rotation by ``angle`` about ``axis`` (2.25): (..., 3), (...) -> (..., 3, 3) (batch dims broadcast).

    The axis is normalised first, so the gradient w.r.t. ``axis`` is tangent to the unit sphere.
    """
    axis, angle = tensors(("axis", axis, (3,)), ("angle", angle, None))
    broadcast_batch(("axis", axis, 1), ("angle", angle, 0))
    return _axis_angle_to_matrix(_unit(axis, "axis"), angle)


def quaternion_to_axis_angle(Q: Tensor) -> tuple[Tensor, Tensor]:
    """Axis and angle of a unit quaternion (inverse of (2.30)-(2.31)): (..., 4) -> ((..., 3), (...)).

    Q is first made eta >= 0, so the angle lies in [0, pi]; at angle 0 the axis is (1, 0, 0) by convention.
    """
    return _quaternion_to_axis_angle(_canonical(_one(Q, (4,), "Q")))


def matrix_to_axis_angle(R: Tensor) -> tuple[Tensor, Tensor]:
    """Axis r and angle theta of R, theta in [0, pi] ((2.27)-(2.28)): (..., 3, 3) -> ((..., 3), (...)).

    Computed through the singularity-free quaternion (2.34)-(2.35), so it is exact and finite at theta = 0
    (axis (1, 0, 0) by convention) and theta = pi, including gradients. At theta = pi exactly (R
    symmetric) the axis sign is fixed by making its largest-magnitude component positive; just below pi
    the sign follows (2.28).
    """
    return _quaternion_to_axis_angle(_matrix_to_quaternion(_one(R, (3, 3), "R")))


def quaternion_to_rotvec(Q: Tensor) -> Tensor:
    """Rotation vector theta r of a unit quaternion (made eta >= 0): (..., 4) -> (..., 3), theta <= pi."""
    return _quaternion_to_rotvec(_canonical(_one(Q, (4,), "Q")))


def rotvec_to_quaternion(v: Tensor) -> Tensor:
    """Unit quaternion (2.30)-(2.31) of the rotation vector v = theta r, eta >= 0: (..., 3) -> (..., 4)."""
    return _rotvec_to_quaternion(_one(v, (3,), "v"))


def axis_angle_to_quaternion(axis: Tensor, angle: Tensor) -> Tensor:
    """Unit quaternion (2.30)-(2.31) with eta >= 0: (..., 3), (...) -> (..., 4). The axis is normalised."""
    axis, angle = tensors(("axis", axis, (3,)), ("angle", angle, None))
    broadcast_batch(("axis", axis, 1), ("angle", angle, 0))
    axis, angle = torch.broadcast_tensors(_unit(axis, "axis"), angle[..., None])
    half = angle[..., :1] / 2
    return _canonical(torch.cat((torch.cos(half), torch.sin(half) * axis), dim=-1))


def rotvec_to_matrix(v: Tensor) -> Tensor:
    """Rotation matrix of the rotation vector v = theta r (2.25): (..., 3) -> (..., 3, 3); smooth at 0."""
    return _rotvec_to_matrix(_one(v, (3,), "v"))


def matrix_to_rotvec(R: Tensor) -> Tensor:
    """Rotation vector theta r of R, theta in [0, pi] ((2.27)-(2.28)): (..., 3, 3) -> (..., 3).

    Smooth with exact gradients at theta = 0; finite at theta = pi (where the sign is as in
    :func:`matrix_to_axis_angle`).
    """
    return _matrix_to_rotvec(_one(R, (3, 3), "R"))


# --------------------------------------------------------------------------------------- quaternions


def quaternion_to_matrix(Q: Tensor) -> Tensor:
    """Rotation matrix of a quaternion (eta, eps) (2.33): (..., 4) -> (..., 3, 3). Q is normalised first."""
    return _quaternion_to_matrix(_unit(_one(Q, (4,), "Q"), "Q"))


def matrix_to_quaternion(R: Tensor) -> Tensor:
    """Unit quaternion (eta, eps) of R with eta >= 0 ((2.34)-(2.35)): (..., 3, 3) -> (..., 4).

    Evaluated in Shepperd's numerically robust form (same result as (2.34)-(2.35) for rotation matrices,
    but dividing by the largest of the four square roots), then normalised and made eta >= 0.
    """
    return _matrix_to_quaternion(_one(R, (3, 3), "R"))


def quaternion_multiply(Q1: Tensor, Q2: Tensor) -> Tensor:
    """Quaternion product Q1 * Q2 (2.37), the quaternion of R1 R2: (..., 4), (..., 4) -> (..., 4).

    Batch dims broadcast; the result is not re-canonicalised (its eta may be negative).
    """
    Q1, Q2 = tensors(("Q1", Q1, (4,)), ("Q2", Q2, (4,)))
    broadcast_batch(("Q1", Q1, 1), ("Q2", Q2, 1))
    return _quaternion_multiply(Q1, Q2)


def quaternion_conjugate(Q: Tensor) -> Tensor:
    """Conjugate {eta, -eps}, the inverse of a unit quaternion (2.36): (..., 4) -> (..., 4)."""
    return _quaternion_conjugate(_one(Q, (4,), "Q"))


def quaternion_slerp(Q0: Tensor, Q1: Tensor, s: Tensor) -> Tensor:
    """Spherical linear interpolation Q0 * (Q0^-1 * Q1)^s along the shortest arc.

    Q0, Q1: (..., 4) unit quaternions, s: (...) (0 -> Q0, 1 -> Q1 up to sign); batch dims broadcast.
    Written as Q0 * exp(s log(dQ)) so it stays finite (values and gradients) for Q0 = +-Q1. The path
    starts at Q0 exactly and is continuous, so its eta is not forced to be >= 0.
    """
    Q0, Q1, s = tensors(("Q0", Q0, (4,)), ("Q1", Q1, (4,)), ("s", s, None))
    broadcast_batch(("Q0", Q0, 1), ("Q1", Q1, 1), ("s", s, 0))
    return _quaternion_slerp(Q0, Q1, s)


# -------------------------------------------------------------------------- orientation errors (§3.7.3)
def orientation_error_euler(phi_d: Tensor, phi_e: Tensor, wrap: bool = False) -> Tensor:
    """Euler-angle orientation error e_O = phi_d - phi_e (3.80): (..., 3), (..., 3) -> (..., 3).

    In Euler-angle space (pairs with the analytical Jacobian), not the base frame. ``wrap=True`` maps each
    component to (-pi, pi], which the book's plain difference does not do.
    """
    phi_d, phi_e = tensors(("phi_d", phi_d, (3,)), ("phi_e", phi_e, (3,)))
    broadcast_batch(("phi_d", phi_d, 1), ("phi_e", phi_e, 1))
    e = phi_d - phi_e
    return wrap_angle(e) if wrap else e


_AXIS_ANGLE_FORMS = ("sin", "rotvec")


def orientation_error_axis_angle(R_d: Tensor, R_e: Tensor, form: str = "sin") -> Tensor:
    """Angle-axis orientation error in the base frame: (..., 3, 3), (..., 3, 3) -> (..., 3).

    theta, r are the angle and axis of R_d R_e^T (3.84). ``form="sin"`` (default): e_O = r sin(theta)
    (3.83), computed as (3.85) = 1/2 (n_e x n_d + s_e x s_d + a_e x a_d); unique only for |theta| < pi/2.
    ``form="rotvec"``: e_O = theta r with theta in [0, pi] (valid for any error, finite grads at 0).
    """
    if form not in _AXIS_ANGLE_FORMS:
        raise ConventionError(f"unknown form {form!r}; valid: {', '.join(_AXIS_ANGLE_FORMS)}")
    R_d, R_e = tensors(("R_d", R_d, (3, 3)), ("R_e", R_e, (3, 3)))
    broadcast_batch(("R_d", R_d, 2), ("R_e", R_e, 2))
    return _kpe.orientation_error(R_d, R_e, "axis_angle" if form == "sin" else "rotvec")[0]


def orientation_error_quaternion(Q_d: Tensor, Q_e: Tensor, shortest: bool = False) -> Tensor:
    """Quaternion orientation error e_O = Delta eps of Q_d * Q_e^-1 (3.90)-(3.91), in the base frame.

    e_O = eta_e eps_d - eta_d eps_e - S(eps_d) eps_e = +-r sin(theta/2) for the angle/axis of R_d R_e^T
    (half the angle-axis error for small errors; the sign is + when Delta eta >= 0). Accepts quaternions
    (..., 4) or rotation matrices (..., 3, 3) (converted with (2.34)-(2.35)); both arguments must be of
    the same kind. Returns (..., 3).
    ``shortest=True`` flips the sign where Delta eta < 0, so the error points along the shortest rotation.
    """
    Q_d, Q_e = tensors(("Q_d", Q_d, None), ("Q_e", Q_e, None))
    if Q_d.ndim >= 1 and Q_d.shape[-1] == 3:  # rotation matrices
        check_trailing(Q_d, (3, 3), "R_d")
        check_trailing(Q_e, (3, 3), "R_e")
        broadcast_batch(("R_d", Q_d, 2), ("R_e", Q_e, 2))
        Q_d, Q_e = _matrix_to_quaternion(Q_d), _matrix_to_quaternion(Q_e)
    else:
        check_trailing(Q_d, (4,), "Q_d")
        check_trailing(Q_e, (4,), "Q_e")
        broadcast_batch(("Q_d", Q_d, 1), ("Q_e", Q_e, 1))
    return _kpe.quaternion_error(Q_d, Q_e, shortest)

