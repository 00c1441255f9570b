"""SE(3) logarithm and its Jacobian: the frame-task error of the velocity IK (mink's conventions).

A twist ξ = [v; ω] ``(..., 6)`` (linear part first) is the tangent coordinate of T = exp(ξ^). For a pose
T = (R, p) ``(..., 4, 4)``:

    log T = [V(ω)⁻¹ p; ω],  ω = θ r the rotation vector of R (2.27)-(2.28),
    V⁻¹ = I − ½ S(ω) + c(θ) S(ω)²,  c(θ) = (1 − θ cot(θ/2)/2)/θ²                                     (S.1)

(:func:`se3_log`), and the right Jacobian of the logarithm, the matrix with d log(T exp(δ^)) = J_log δ at
δ = 0 (:func:`se3_jlog`):

    J_log = J_r(ξ)⁻¹ = J_l(−ξ)⁻¹,  J_l(ξ)⁻¹ = [[J⁻¹, −J⁻¹ Q J⁻¹], [0, J⁻¹]],  J⁻¹ = V(ω)⁻¹ of (S.1)      (S.2)

with Q(ξ) the coupling block of Barfoot and Furgale (2014), eq. 102 (Solà et al. 2018, eq. 180):

    Q = ½ S_v + B (S_ω S_v + S_v S_ω + S_ω S_v S_ω) − C (S_v S_ω² + S_ω² S_v − 3 S_ω S_v S_ω)
        + D (S_ω S_v S_ω² + S_ω² S_v S_ω),
    B = (θ − sinθ)/θ³, C = (1 − θ²/2 − cosθ)/θ⁴, D = (2θ − 3 sinθ + θ cosθ)/(2θ⁵).                   (S.3)

The coefficients c, B, C, D are evaluated by their Taylor series below θ² < 10⁻² (float64) or 0.25 (lower
precision), where the closed forms cancel digits; both branches are smooth, so the Jacobian is exact
everywhere (mink switches to the identity below θ = 10⁻⁵ rad, which differs by O(θ‖v‖)).
"""

from __future__ import annotations

import torch
from torch import Tensor

from .rigid import _matrix_to_rotvec, _skew

__all__ = ["se3_jlog", "se3_log"]

# Taylor coefficients in θ² (0, 2, 4, 6) of c, B, C, D of (S.1), (S.3)
_SERIES = {
    "c": (1 / 12, 1 / 720, 1 / 30240, 1 / 1209600),
    "B": (1 / 6, -1 / 120, 1 / 5040, -1 / 362880),
    "C": (-1 / 24, 1 / 720, -1 / 40320, 1 / 3628800),
    "D": (1 / 120, -1 / 2520, 1 / 120960, -1 / 9979200),
}


def _series(name: str, t2: Tensor) -> Tensor:
    a0, a1, a2, a3 = _SERIES[name]
    return a0 + t2 * (a1 + t2 * (a2 + t2 * a3))


def _coefficients(w: Tensor, names: str) -> dict[str, Tensor]:
    """The coefficients of (S.1)/(S.3) at the rotation vector ``w (..., 3)``: each ``(..., 1, 1)``."""
    t2 = (w * w).sum(-1)[..., None, None]
    small = t2 < (1e-2 if w.dtype == torch.float64 else 0.25)
    t2s = torch.where(small, torch.ones_like(t2), t2)  # the closed forms see θ away from 0 only
    t = torch.sqrt(t2s)
    s, co = torch.sin(t), torch.cos(t)
    closed = {
        "c": (1.0 - 0.5 * t * torch.cos(0.5 * t) / torch.sin(0.5 * t)) / t2s,
        "B": (t - s) / (t2s * t),
        "C": (1.0 - 0.5 * t2s - co) / (t2s * t2s),
        "D": (2.0 * t - 3.0 * s + t * co) / (2.0 * t2s * t2s * t),
    }
    return {k: torch.where(small, _series(k, t2), closed[k]) for k in names}


def _v_inverse(w: Tensor, c: Tensor) -> Tensor:
    S = _skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye - 0.5 * S + c * (S @ S)


def se3_log(T: Tensor) -> Tensor:
    """log T = [V⁻¹ p; ω] ``(..., 6)`` of poses ``(..., 4, 4)`` (S.1)."""
    w = _matrix_to_rotvec(T[..., :3, :3])
    (c,) = _coefficients(w, "c").values()
    v = (_v_inverse(w, c) @ T[..., :3, 3:4]).squeeze(-1)
    return torch.cat((v, w), dim=-1)


def se3_jlog(T: Tensor) -> Tensor:
    """J_log ``(..., 6, 6)`` of (S.2): the right Jacobian inverse at ξ = log T, d log(T exp(δ^))/dδ."""
    xi = -se3_log(T)  # J_r(ξ)⁻¹ = J_l(−ξ)⁻¹
    v, w = xi[..., :3], xi[..., 3:]
    k = _coefficients(w, "cBCD")
    Jinv = _v_inverse(w, k["c"])
    Sv, Sw = _skew(v), _skew(w)
    SwSv, SvSw = Sw @ Sv, Sv @ Sw
    SwSvSw = SwSv @ Sw
    Sw2 = Sw @ Sw
    Q = (0.5 * Sv + k["B"] * (SwSv + SvSw + SwSvSw) - k["C"] * (Sv @ Sw2 + Sw2 @ Sv - 3.0 * SwSvSw)
         + k["D"] * (SwSvSw @ Sw + Sw @ SwSvSw))
    top = torch.cat((Jinv, -Jinv @ Q @ Jinv), dim=-1)
    bottom = torch.cat((torch.zeros_like(Jinv), Jinv), dim=-1)
    return torch.cat((top, bottom), dim=-2)
