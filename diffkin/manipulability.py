"""Kinematic singularities (§3.3) and manipulability (§3.9): measures and ellipsoids of a Jacobian.

Functions take ``J (..., m, n)`` with free leading batch dims (a geometric or analytical Jacobian, or a part
of it). Measures built from singular values differentiate through ``svdvals`` (gradient U diag(ḡ) Vᵀ), which
stays finite at singular and repeated singular values, unlike a determinant's or an inverse's backward.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from ._numerics import broadcast_shapes, cross, eps_for, safe_norm, stable_norm
from .errors import ConventionError, ModelError, ShapeError
from .validation import broadcast_batch, check_trailing, shape_str, tensors

__all__ = [
    "smallest_singular_value",
    "jacobian_determinant",
    "condition_number",
    "inverse_condition_number",
    "DecoupledSingularities",
    "decoupled_singularities",
    "manipulability",
    "Ellipsoid",
    "velocity_ellipsoid",
    "force_ellipsoid",
    "force_transmission_ratio",
    "velocity_transmission_ratio",
]

_PARTS = {"full": slice(None), "position": slice(0, 3), "orientation": slice(3, 6)}


def _check_J(J) -> Tensor:
    J = tensors(("J", J, (None, None)))[0]
    if 0 in J.shape[-2:]:  # a matrix without rows or columns has no singular values
        raise ShapeError(f"expected J of shape (..., m, n) with m, n >= 1, got {shape_str(J.shape)}")
    return J


def _inv_or_inf(x: Tensor) -> Tensor:
    """1/x with +inf (and a zero, not NaN, gradient) where x == 0."""
    zero = x == 0
    return torch.where(zero, torch.full_like(x, float("inf")), 1.0 / torch.where(zero, torch.ones_like(x), x))


# ------------------------------------------------------------------------------- singularities (§3.3)
def smallest_singular_value(J: Tensor) -> Tensor:
    """σ_min of J ``(..., m, n)`` -> ``(...)``: 0 exactly at a kinematic singularity (rank loss, §3.3)."""
    return torch.linalg.svdvals(_check_J(J))[..., -1]


def jacobian_determinant(J: Tensor) -> Tensor:
    """det J of a square Jacobian ``(..., n, n)`` -> ``(...)`` (e.g. (3.41), det J_P of §3.3.3).

    Computed as det(U) det(Vᵀ) ∏σ_i from the SVD so its gradient, adj(J)ᵀ, is right at singular J too
    (``torch.linalg.det``'s backward returns 0 there).
    """
    J = _check_J(J)
    if J.shape[-1] != J.shape[-2]:
        raise ShapeError(f"jacobian_determinant needs a square J (..., n, n), got {shape_str(J.shape)}")
    U, S, Vh = torch.linalg.svd(J)
    sign = (torch.linalg.det(U.detach()) * torch.linalg.det(Vh.detach())).detach()
    return sign * S.prod(dim=-1)


def condition_number(J: Tensor) -> Tensor:
    """σ_max/σ_min of J ``(..., m, n)`` -> ``(...)``; +inf at an exact singularity (σ_min = 0)."""
    s = torch.linalg.svdvals(_check_J(J))
    # σ_min = 0 is singular whatever σ_max is (J = 0 included, where σ_max · inf would be NaN)
    return torch.where(s[..., -1] == 0, torch.full_like(s[..., 0], float("inf")),
                       s[..., 0] * _inv_or_inf(s[..., -1]))


def inverse_condition_number(J: Tensor) -> Tensor:
    """σ_min/σ_max in [0, 1] (§3.9): distance from singularity and isotropy of the ellipsoid; 0 for J = 0."""
    s = torch.linalg.svdvals(_check_J(J))
    top = s[..., 0]
    zero = top == 0
    return torch.where(zero, torch.zeros_like(top), s[..., -1] / torch.where(zero, torch.ones_like(top), top))


class DecoupledSingularities(NamedTuple):
    """Result of :func:`decoupled_singularities`; every field is ``(...)`` except ``wrist_point`` (..., 3)."""

    wrist: Tensor  # bool: z3, z4, z5 linearly dependent (z3 ∥ z5), §3.3.2
    shoulder: Tensor  # bool: wrist point on the axis of joint 1, §3.3.3
    elbow: Tensor  # bool: elbow outstretched or retracted, §3.3.3
    wrist_measure: Tensor  # |det J22| = |det[z3 z4 z5]| (= |sin ϑ5| for the book's wrist)
    shoulder_measure: Tensor  # distance of the wrist point from the joint-1 axis (|a2 c2 + a3 c23|)
    elbow_measure: Tensor  # |sine| of the elbow angle, between the links as seen along the joint-2 axis
    det_arm: Tensor  # det J11 with the Jacobian taken at the wrist point (3.42)–(3.44)
    det_wrist: Tensor  # det J22 (3.43)
    wrist_point: Tensor  # p_W, base frame


def _wrist_centre(axes: Tensor, origins: Tensor) -> Tensor:
    """Least-squares intersection of the lines (origins[k], axes[k]) (..., k, 3) -> (..., 3)."""
    eye = torch.eye(3, dtype=axes.dtype, device=axes.device)
    proj = eye - axes.unsqueeze(-1) * axes.unsqueeze(-2)  # (..., k, 3, 3)
    A = proj.sum(-3)
    b = (proj @ origins.unsqueeze(-1)).sum(-3)
    return torch.linalg.solve(A, b).squeeze(-1)


def decoupled_singularities(chain, q: Tensor, tol: float | None = None, check: bool = True):
    """Arm and wrist singularities of an anthropomorphic arm (+ spherical wrist) by decoupling (§3.3.1–3.3.3).

    For a 6-joint all-revolute chain whose last three axes intersect (spherical wrist, Table 2.6) the
    Jacobian at the wrist point p_W is block lower-triangular, so det J = det J11 · det J22 (3.44):

    - wrist: z3, z4, z5 linearly dependent, i.e. z3 ∥ z5 (ϑ5 = 0 or π for Table 2.6);
    - shoulder: p_W on the axis of joint 1 (p_x = p_y = 0 for the book's frames);
    - elbow: the wrist point, seen along the parallel axes of joints 2 and 3, aligned with the upper arm
      (ϑ3 = 0 or π in Table 2.4; ϑ3 = ±π/2 with Table 2.6's frames, as the book remarks under (2.70)).

    For the 3-joint anthropomorphic arm (Table 2.4) p_W is the end-effector point and the wrist fields are
    1/False. A flag is set where its measure is <= ``tol`` (default √eps; metres for the shoulder).
    Measures are geometric, so they do not depend on the DH frames chosen; with Table 2.4,
    det J11 = det J_P = −a2 a3 s3 (a2 c2 + a3 c23) (§3.3.3) and elbow/shoulder measures are |s3| and
    |a2 c2 + a3 c23|.
    """
    n = chain.n_joints
    if n not in (3, 6) or "P" in chain.joint_types:
        raise ModelError(
            "decoupled_singularities needs an all-revolute anthropomorphic arm with 3 joints or with a "
            f"spherical wrist (6 joints), got joint_types {chain.joint_types!r}"
        )
    if check:
        (q,) = tensors(("q", q, (n,)), like=chain)
    axes, origins, T_ee = chain.joint_axes_origins(q, check=False)
    if n == 6:
        p_w = _wrist_centre(axes[..., 3:, :], origins[..., 3:, :])
        z3, z4, z5 = axes[..., 3, :], axes[..., 4, :], axes[..., 5, :]
        det_wrist = (z3 * cross(z4, z5)).sum(-1)
    else:
        p_w = T_ee[..., :3, 3]
        det_wrist = torch.ones_like(p_w[..., 0])
    cols = cross(axes[..., :3, :], p_w.unsqueeze(-2) - origins[..., :3, :])  # J11 columns at p_W
    det_arm = (cols[..., 0, :] * cross(cols[..., 1, :], cols[..., 2, :])).sum(-1)
    shoulder = safe_norm(cross(axes[..., 0, :], p_w - origins[..., 0, :]))
    z1 = axes[..., 1, :]
    upper, fore = origins[..., 2, :] - origins[..., 1, :], p_w - origins[..., 2, :]
    perp = lambda v: v - (v * z1).sum(-1, keepdim=True) * z1  # noqa: E731
    denom = safe_norm(perp(upper)) * safe_norm(perp(fore))
    degenerate = denom <= eps_for(denom)
    sine = (z1 * cross(upper, fore)).sum(-1).abs()
    elbow = torch.where(degenerate, torch.zeros_like(sine), sine / torch.where(degenerate, 1.0, denom))
    wrist = det_wrist.abs()
    tol = eps_for(p_w) ** 0.5 if tol is None else tol
    return DecoupledSingularities(
        wrist <= tol, shoulder <= tol, elbow <= tol, wrist, shoulder, elbow, det_arm, det_wrist, p_w
    )


# ----------------------------------------------------------------------------- manipulability (§3.9)
def manipulability(J: Tensor) -> Tensor:
    """Manipulability w = sqrt(det(JJᵀ)) (3.56) = ∏ σ_i (Problem 3.8) = |det J| for square J (3.124).

    ``J (..., m, n)`` -> ``(...)``; for m > n the product of the n singular values. Zero exactly at
    singularities, where its gradient stays finite (and equals the one-sided derivative of ∏ σ_i).
    """
    return torch.linalg.svdvals(_check_J(J)).prod(dim=-1)


class Ellipsoid(NamedTuple):
    """Principal axes (columns of ``axes`` (..., m, m), unit vectors) and semi-axis ``lengths`` (..., m)."""

    axes: Tensor
    lengths: Tensor


def _select_part(J, part: str) -> Tensor:
    J = _check_J(J)
    if part not in _PARTS:
        raise ConventionError(f"part must be one of {tuple(_PARTS)}, got {part!r}")
    if part != "full" and J.shape[-2] != 6:
        raise ShapeError(f"part={part!r} needs a (..., 6, n) Jacobian, got {shape_str(J.shape)}")
    return J[..., _PARTS[part], :]


def _left_svd(J: Tensor) -> tuple[Tensor, Tensor]:
    """Left singular vectors (..., m, m) and singular values (..., m), descending, zero-padded if m > n.

    One thin SVD for every shape (no J Jᵀ: its squares underflow or overflow at |J| ~ 1e-20 / 1e20 in
    float32, and its eigendecomposition fails to converge on the m - n repeated zero eigenvalues of a tall
    J). For m > n the m - n directions of N(Jᵀ) (σ = 0) complete U to an orthonormal basis: a basis E of
    the complement from a complete QR of U (held constant), projected off range(U) (E itself at the
    evaluation point, differentiable in U) and orthonormalised.
    """
    m, n = J.shape[-2:]
    U, S, _ = torch.linalg.svd(J, full_matrices=False)  # (..., m, min(m, n)), (..., min(m, n))
    if m <= n:
        return U, S
    with torch.no_grad():
        E = torch.linalg.qr(U, mode="complete")[0][..., n:]  # (..., m, m - n), orthonormal, ⟂ range(U)
    Q = torch.linalg.qr(E - U @ (U.mT @ E))[0]
    return torch.cat((U, Q), -1), torch.cat((S, S.new_zeros(*S.shape[:-1], m - n)), -1)


def velocity_ellipsoid(J: Tensor, part: str = "full") -> Ellipsoid:
    """Velocity manipulability ellipsoid vᵀ(JJᵀ)⁻¹v = 1 (3.123): axes = eigenvectors u_i of JJᵀ (left
    singular vectors of J), semi-axes σ_i, in decreasing order.

    ``part``: ``"full"`` (J as given, any m), ``"position"`` (rows 0–2 of a 6-row J) or ``"orientation"``
    (rows 3–5). Gradients of the axes are undefined where singular values repeat (a sphere).
    """
    U, S = _left_svd(_select_part(J, part))
    return Ellipsoid(U, S)


def force_ellipsoid(J: Tensor, part: str = "full") -> Ellipsoid:
    """Force manipulability ellipsoid γᵀ(JJᵀ)γ = 1 (3.125)–(3.126): the same axes as the velocity
    ellipsoid with semi-axes 1/σ_i (+inf along directions where σ_i = 0)."""
    U, S = _left_svd(_select_part(J, part))
    return Ellipsoid(U, _inv_or_inf(S))


def _direction(J, u) -> tuple[Tensor, Tensor]:
    J, u = tensors(("J", J, (None, None)), ("u", u, (None,)))
    check_trailing(u, (J.shape[-2],), "u")
    broadcast_batch(("J", J, 2), ("u", u, 1))
    return J, u


def force_transmission_ratio(J: Tensor, u: Tensor) -> Tensor:
    """α = (uᵀJJᵀu)^(-1/2) (3.127) along the unit direction ``u (..., m)``: +inf where u ∈ N(Jᵀ)."""
    J, u = _direction(J, u)
    Jt_u = torch.einsum("...ij,...i->...j", J, u)
    return _inv_or_inf(stable_norm(Jt_u))


def velocity_transmission_ratio(J: Tensor, u: Tensor) -> Tensor:
    """β = (uᵀ(JJᵀ)⁻¹u)^(-1/2) (3.128) along the unit direction ``u (..., m)``; → 0 where u leaves R(J)."""
    J, u = _direction(J, u)
    m = J.shape[-2]
    G = J @ J.mT
    reg = eps_for(J) * G.diagonal(dim1=-2, dim2=-1).sum(-1) + torch.finfo(J.dtype).tiny
    G = G + reg[..., None, None] * torch.eye(m, dtype=J.dtype, device=J.device)
    batch = broadcast_shapes(G.shape[:-2], u.shape[:-1])
    u = u.expand(*batch, m)
    x = torch.linalg.solve(G.expand(*batch, m, m), u.unsqueeze(-1)).squeeze(-1)
    return torch.rsqrt((u * x).sum(-1))
