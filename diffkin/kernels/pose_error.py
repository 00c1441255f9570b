"""The pose error of §3.7.3: the only encoding of [p_d − p_e; e_O] and its orientation errors in diffkin.

Position error e_P = p_d − p_e (3.78). Orientation error from the columns n, s, a of R_d and R_e (all in the
base frame), ``form``:

- ``"axis_angle"``: e_O = r sinθ (3.83), evaluated as (3.85) ½(n_e × n_d + s_e × s_d + a_e × a_d), where θ, r
  are the angle and axis of R_d R_eᵀ (3.84); unique only for |θ| < π/2.
- ``"rotvec"``: e_O = θ r with θ = atan2(‖r sinθ‖, cosθ) (cosθ from the trace of (3.84)), accurate at small
  angles and with a useful gradient up to θ = π (where r sinθ vanishes). With ``exact_near_pi`` (default)
  the axis for θ > π/2 is taken from the symmetric part ½(R + Rᵀ) − cosθ I = (1 − cosθ) r rᵀ instead of
  r sinθ / sinθ, which loses digits as sinθ → 0; at θ = π exactly its largest component is made positive.
- ``"quaternion"``: e_O = Δε = η_e ε_d − η_d ε_e − S(ε_d) ε_e (3.91) of the unit quaternions of R_d and R_e
  (each with η >= 0), = ±r sin(θ/2); ``shortest`` flips it where Δη < 0.

The Euler-angle error (3.80) e_O = φ_d − φ_e is a difference in Euler-angle space, not a function of the two
rotations, and stays with the Euler angles (:func:`diffkin.rotations.orientation_error_euler`).

Layouts, one arithmetic (every function works on three rotation columns with their components along
``dim``): ``"batch_first"`` takes rotation matrices ``(..., 3, 3)`` (batch dims broadcast) and returns
``(..., 3)``; ``"columns"`` takes the IK loop's batch-last columns ``(x, y, z)`` each ``(3, m)`` and returns
``(3, m)``. Every function also returns the angle θ ∈ [0, π] of R_d R_eᵀ (``(...)`` or ``(m,)``).
No input checks here (the public wrappers check).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from .._numerics import cross
from .quaternion import _matrix_to_quaternion

__all__ = ["ORIENTATION_FORMS", "orientation_error", "pose_error", "quaternion_error", "rotation_angle"]

ORIENTATION_FORMS = ("axis_angle", "rotvec", "quaternion")


def _columns(R, layout: str) -> tuple[tuple[Tensor, Tensor, Tensor], int]:
    """Rotation columns and their component dim for a layout."""
    if layout == "batch_first":
        return (R[..., :, 0], R[..., :, 1], R[..., :, 2]), -1
    if layout == "columns":
        return tuple(R), 0
    raise ValueError(f"unknown layout {layout!r}; valid: batch_first, columns")


def _dot(a: Tensor, b: Tensor, dim: int) -> Tensor:
    a0, a1, a2 = a.unbind(dim)
    b0, b1, b2 = b.unbind(dim)
    return a0 * b0 + a1 * b1 + a2 * b2


def _sin_cos(d: Sequence[Tensor], e: Sequence[Tensor], dim: int) -> tuple[Tensor, Tensor]:
    """r sinθ (3.85) along ``dim`` and cosθ = ½(tr(R_d R_eᵀ) − 1) of (3.84)."""
    v = 0.5 * (cross(e[0], d[0], dim) + cross(e[1], d[1], dim) + cross(e[2], d[2], dim))
    c = 0.5 * ((e[0] * d[0] + e[1] * d[1] + e[2] * d[2]).sum(dim) - 1.0)
    return v, c


def _angle(v: Tensor, c: Tensor, dim: int) -> tuple[Tensor, Tensor]:
    """(θ, s): θ = atan2(s, cosθ) with s = ‖r sinθ‖ clamped to >= √tiny, so that θ/s -> 1/cosθ and every
    gradient stays finite at v = 0 (θ is then √tiny, ~1e-154 in float64, instead of 0)."""
    tiny = torch.finfo(v.dtype).tiny
    s = torch.sqrt(_dot(v, v, dim).clamp_min(tiny))
    return torch.atan2(s, c), s


def _axis_near_pi(d, e, v: Tensor, c: Tensor, dim: int) -> tuple[Tensor, Tensor]:
    """Unit axis r of R_d R_eᵀ from (1 − c) r rᵀ = ½(R + Rᵀ) − cI (accurate for θ > π/2), and sinθ = r·v.

    r is column k of ½(R + Rᵀ) − cI over sqrt((1 − c)(R_kk − c)) for the largest diagonal entry k (then
    R_kk − c >= (1 − c)/3); its sign follows v, or at θ = π (v = 0) makes component k positive."""
    dim = dim % d[0].ndim
    R = sum(dk.unsqueeze(dim + 1) * ek.unsqueeze(dim) for dk, ek in zip(d, e))  # R_ij = Σ_k d_k[i] e_k[j]
    S = 0.5 * (R + R.transpose(dim, dim + 1))
    diag = torch.stack([S.select(dim + 1, j).select(dim, j) for j in range(3)], -1)  # (..., 3)
    k = diag.argmax(-1)
    onehot = torch.nn.functional.one_hot(k, 3).to(c.dtype).movedim(-1, dim)  # components along dim
    u = (S * onehot.unsqueeze(dim)).sum(dim + 1) - c.unsqueeze(dim) * onehot
    den = (1.0 - c) * (diag.gather(-1, k.unsqueeze(-1)).squeeze(-1) - c)
    r = u * torch.rsqrt(den.clamp_min(torch.finfo(c.dtype).tiny)).unsqueeze(dim)
    rv = _dot(r, v, dim)
    sgn = torch.where(rv < 0, -torch.ones_like(rv), torch.ones_like(rv))
    return r * sgn.unsqueeze(dim), rv * sgn


def _orientation(d, e, form: str, dim: int, exact_near_pi: bool, shortest: bool) -> tuple[Tensor, Tensor]:
    v, c = _sin_cos(d, e, dim)
    theta, s = _angle(v, c, dim)
    if form == "axis_angle":
        return v, theta
    if form == "rotvec":
        e_o = v * (theta / s).unsqueeze(dim)
        if exact_near_pi:
            far = c < 0.0
            r, sin_t = _axis_near_pi(d, e, v, torch.where(far, c, -torch.ones_like(c)), dim)
            theta_far = torch.atan2(sin_t, c)
            e_o = torch.where(far.unsqueeze(dim), r * theta_far.unsqueeze(dim), e_o)
            theta = torch.where(far, theta_far, theta)
        return e_o, theta
    if form == "quaternion":
        Rd, Re = (torch.stack(tuple(x), -1) for x in (d, e))  # (..., 3, 3) for dim -1
        if dim % d[0].ndim != d[0].ndim - 1:
            Rd, Re = Rd.movedim(dim, -2), Re.movedim(dim, -2)
        e_o = quaternion_error(_matrix_to_quaternion(Rd), _matrix_to_quaternion(Re), shortest)
        if dim % d[0].ndim != d[0].ndim - 1:
            e_o = e_o.movedim(-1, dim)
        return e_o, theta
    raise ValueError(f"unknown orientation error {form!r}; valid: {', '.join(ORIENTATION_FORMS)}")


def quaternion_error(Q_d: Tensor, Q_e: Tensor, shortest: bool = False) -> Tensor:
    """Δε = η_e ε_d − η_d ε_e − S(ε_d) ε_e (3.91) of unit quaternions ``(..., 4)`` -> ``(..., 3)``."""
    eta_d, eps_d, eta_e, eps_e = Q_d[..., :1], Q_d[..., 1:], Q_e[..., :1], Q_e[..., 1:]
    eps_d, eps_e = torch.broadcast_tensors(eps_d, eps_e)
    e = eta_e * eps_d - eta_d * eps_e - cross(eps_d, eps_e, -1)
    if shortest:
        d_eta = eta_d * eta_e + (eps_d * eps_e).sum(-1, keepdim=True)
        e = torch.where(d_eta < 0, -e, e)
    return e


def orientation_error(
    R_d,
    R_e,
    form: str = "axis_angle",
    *,
    layout: str = "batch_first",
    exact_near_pi: bool = True,
    shortest: bool = False,
) -> tuple[Tensor, Tensor]:
    """(e_O, θ) of R_d against R_e: matrices ``(..., 3, 3)`` (``"batch_first"``) or column triples ``(3, m)``
    (``"columns"``). See the module docstring for ``form``, ``exact_near_pi`` and ``shortest``."""
    d, dim = _columns(R_d, layout)
    e, _ = _columns(R_e, layout)
    return _orientation(d, e, form, dim, exact_near_pi, shortest)


def pose_error(
    p_d: Tensor,
    R_d,
    p_e: Tensor,
    R_e,
    form: str = "axis_angle",
    *,
    layout: str = "batch_first",
    exact_near_pi: bool = True,
) -> tuple[Tensor, Tensor, Tensor]:
    """(e_P, e_O, θ): e_P = p_d − p_e (3.78) and :func:`orientation_error`. Batch first: p ``(..., 3)`` and R
    ``(..., 3, 3)`` (all broadcast); columns: p ``(3, m)`` and R a triple of ``(3, m)``."""
    e_o, theta = orientation_error(R_d, R_e, form, layout=layout, exact_near_pi=exact_near_pi)
    return p_d - p_e, e_o, theta


def rotation_angle(R_d, R_e, *, layout: str = "batch_first") -> Tensor:
    """The angle θ ∈ [0, π] of R_d R_eᵀ (= that of R_eᵀ R_d) by atan2(‖r sinθ‖, cosθ)."""
    d, dim = _columns(R_d, layout)
    e, _ = _columns(R_e, layout)
    v, c = _sin_cos(d, e, dim)
    return _angle(v, c, dim)[0]
