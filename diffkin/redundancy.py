"""Inverses of the Jacobian for redundancy resolution and near singularities (§3.4–3.5).

All functions take ``J (..., m, n)`` with free leading batch dims and return ``(..., n, m)`` (or the
``(..., n, n)`` projector). None forms an explicit inverse: each solves the symmetric system with the smaller
Gram matrix (JJᵀ if m <= n, JᵀJ otherwise) by LU, regularised by λ² = 0.01·eps·‖J‖²_F (+ the smallest
normal number) so that it stays solvable at exact singularities. That regularisation is below the rounding
error of forming JJᵀ, and turns the inverse of a zero singular value into 0 instead of inf: values and
gradients stay finite at singular configurations. Forming JJᵀ squares the condition number, so in float32
expect errors of order cond(J)²·eps (use float64 or a damped inverse near singularities).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ._numerics import eps_for
from .errors import DTypeError, ShapeError
from .kernels import dls as _dls
from .validation import check_tensor, shape_str

__all__ = ["pinv", "damped_pinv", "weighted_pinv", "nullspace_projector"]


def _check_J(J: Tensor) -> Tensor:
    check_tensor(J, "J")
    if J.ndim < 2:
        raise ShapeError(f"expected J of shape (..., m, n), got {shape_str(J.shape)}")
    return J


def _as_sq(x, like: Tensor) -> Tensor:
    """damping k -> k² as a tensor broadcastable against the batch dims ``(...)`` of ``like``."""
    k = torch.as_tensor(x, dtype=like.dtype, device=like.device)
    return k * k


def _regulariser(J: Tensor) -> Tensor:
    frob2 = (J * J).sum(dim=(-2, -1))
    return 0.01 * eps_for(J) * frob2 + torch.finfo(J.dtype).tiny


def _damped_inverse(J: Tensor, k2: Tensor) -> Tensor:
    """Jᵀ(JJᵀ + k²I)⁻¹ = (JᵀJ + k²I)⁻¹Jᵀ (the kernel solves the smaller of the two systems)."""
    return _dls.damped_pinv(J, k2 + _regulariser(J))


def pinv(J: Tensor) -> Tensor:
    """Moore–Penrose pseudo-inverse J† ``(..., n, m)``: the right pseudo-inverse Jᵀ(JJᵀ)⁻¹ (3.52) for
    m <= n, the left one (JᵀJ)⁻¹Jᵀ for m > n. Finite at singularities (see the module docstring: zero
    singular values are inverted to 0, and near-zero ones σ to at most ~5/(√eps ‖J‖_F))."""
    _check_J(J)
    return _damped_inverse(J, torch.zeros((), dtype=J.dtype, device=J.device))


def damped_pinv(J: Tensor, damping, threshold: float | None = None) -> Tensor:
    """Damped least-squares inverse J* = Jᵀ(JJᵀ + k²I)⁻¹ (3.59): ``(..., m, n)`` -> ``(..., n, m)``.

    It minimises ‖v − Jq̇‖² + k²‖q̇‖²: each singular value σ of J is inverted as σ/(σ² + k²), bounded by
    1/(2k) so joint velocities stay bounded through singularities.

    Args:
        damping: k, a float or a tensor broadcastable to the batch dims ``(...)``.
        threshold: if given, adaptive damping (Nakamura & Hanafusa 1986; Chiaverini 1997): k² =
            damping² (1 − (σ_min/threshold)²) where the smallest singular value σ_min < threshold, and no
            damping otherwise, so the inverse is exact away from singular regions.
    """
    _check_J(J)
    k2 = _as_sq(damping, J)
    if threshold is not None:
        k2 = _dls.adaptive_damping(J, k2, threshold)
    return _damped_inverse(J, k2)


def weighted_pinv(J: Tensor, W: Tensor, damping=0.0) -> Tensor:
    """Weighted pseudo-inverse W⁻¹Jᵀ(JW⁻¹Jᵀ + k²I)⁻¹ (3.50): the q̇ = J†_W v minimising ½ q̇ᵀWq̇ subject
    to Jq̇ = v (m <= n; for m > n the equal form (JᵀJ + k²W)⁻¹Jᵀ is used).

    Args:
        J: ``(..., m, n)``.
        W: symmetric positive-definite weights, ``(..., n, n)``, or their diagonal ``(..., n)`` (not checked
            for positivity, which would synchronise with the device).
        damping: optional k (float or tensor (...)) as in :func:`damped_pinv`.
    """
    _check_J(J)
    m, n = J.shape[-2:]
    if not isinstance(W, Tensor) or W.dtype != J.dtype:
        raise DTypeError(f"W must be a tensor of dtype {J.dtype}, got {getattr(W, 'dtype', type(W))}")
    diagonal = W.ndim >= 1 and W.shape[-1] == n and (W.ndim == 1 or W.shape[-2:] != (n, n))
    if not diagonal and (W.ndim < 2 or W.shape[-2:] != (n, n)):
        raise ShapeError(f"expected W of shape (..., {n}, {n}) or (..., {n}), got {tuple(W.shape)}")
    k2 = (_as_sq(damping, J) + _regulariser(J))[..., None, None]
    if m > n:
        Wm = torch.diag_embed(W) if diagonal else W
        return torch.linalg.solve(J.mT @ J + k2 * Wm, J.mT)
    Wi_Jt = J.mT / W[..., :, None] if diagonal else torch.linalg.solve(W, J.mT)  # W⁻¹Jᵀ (..., n, m)
    G = J @ Wi_Jt + k2 * torch.eye(m, dtype=J.dtype, device=J.device)
    return torch.linalg.solve(G, Wi_Jt.mT).mT  # W⁻¹Jᵀ G⁻¹ with G symmetric


def nullspace_projector(J: Tensor, J_pinv: Tensor | None = None, damping=None) -> Tensor:
    """Projector onto the null space of J, P = I − J†J ``(..., n, n)`` (3.54).

    P is symmetric, idempotent and JP = 0 when J has full row rank. ``J_pinv`` lets you pass a weighted
    inverse J†_W (then P = I − J†_W J, the projector of (3.54) for that metric); ``damping`` uses the
    damped inverse (3.59) instead (then P is only approximately a projector, but smooth everywhere).
    At singular J the lost directions join the null space; values and gradients stay finite.
    """
    _check_J(J)
    if J_pinv is None:
        J_pinv = pinv(J) if damping is None else damped_pinv(J, damping)
    n = J.shape[-1]
    return torch.eye(n, dtype=J.dtype, device=J.device) - J_pinv @ J
