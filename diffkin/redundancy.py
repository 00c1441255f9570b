"""Inverses of the Jacobian for redundancy resolution and near singularities (§3.4–3.5).

All functions take ``J (..., m, n)`` with free leading batch dims and return ``(..., n, m)`` (or the
``(..., n, n)`` projector); inputs follow the rule of :mod:`diffkin.validation`.

The pseudo-inverse is the Moore–Penrose one at every J, singular or not, and its values and gradients stay
finite. Each batch row is computed from the smaller Gram matrix (JJᵀ if m <= n, JᵀJ otherwise) by a
Cholesky solve where J is well conditioned (cond(J) <= eps^(-1/4): relative error below √eps), and by an
SVD with a relative cutoff otherwise: singular values below √eps·σ_max count as zero (as
``numpy.linalg.pinv(J, rcond)`` with ``rcond`` = :func:`rcond`) — so one singular row never fails (or
spoils) a batch. Gradients are exact where the rank is locally constant (autograd through the solve; the
closed form
dJ† = −J†dJ J† + J†J†ᵀdJᵀ(I − JJ†) + (I − J†J)dJᵀJ†ᵀJ† on the SVD rows), finite everywhere.

The damped inverse (3.59) with a damping λ = k² (``damping``: the value added to JJᵀ's diagonal) above
the rounding level of JJᵀ (λ > eps·‖J‖²_F) is the
regular solve; a smaller damping, zero included, is no damping at all in that arithmetic and gives the
pseudo-inverse.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ._numerics import eps_for
from .errors import DiffkinError, ShapeError
from .kernels import dls as _dls
from .validation import check_broadcasts_to, check_nonnegative, check_trailing, shape_str, tensors

__all__ = ["pinv", "damped_pinv", "weighted_pinv", "nullspace_projector"]


def _needs_grad(x: Tensor) -> bool:
    if torch.compiler.is_compiling():
        return True
    plain = type(x) in (Tensor, torch.nn.Parameter)
    wrapped = not plain or torch._C._functorch.is_functorch_wrapped_tensor(x)
    return wrapped or (torch.is_grad_enabled() and x.requires_grad)


def rcond(dtype: torch.dtype) -> float:
    """The relative cutoff of :func:`pinv`: singular values below √eps·σ_max count as zero (float64
    1.5e-8, float32 3.5e-4). Rounding noise of J at an exact singularity is far below it, and a singular
    value that small would be amplified by more than 1/√eps."""
    return eps_for(dtype) ** 0.5


def _svd_pinv(A: Tensor, rtol: float) -> Tensor:
    """Moore–Penrose inverse ``(k, c, r)`` of ``A (k, r, c)`` by SVD, singular values below rtol·σ_max
    counting as zero (no grad)."""
    U, S, Vh = torch.linalg.svd(A, full_matrices=False)
    cutoff = rtol * S[..., :1]
    inv = torch.where(S > cutoff, 1.0 / torch.where(S > cutoff, S, torch.ones_like(S)), torch.zeros_like(S))
    return (Vh.mT * inv[..., None, :]) @ U.mT


def _first_order(X0: Tensor, A: Tensor) -> Tensor:
    """X0 (constant) with the derivative of the pseudo-inverse at constant rank attached through ``A``."""
    A0 = A.detach()
    r, c = A.shape[-2:]
    I_r = torch.eye(r, dtype=A.dtype, device=A.device)
    I_c = torch.eye(c, dtype=A.dtype, device=A.device)
    F = (-X0 @ A @ X0 + X0 @ X0.mT @ A.mT @ (I_r - A0 @ X0) + (I_c - X0 @ A0) @ A.mT @ X0.mT @ X0)
    return X0 + (F - F.detach())


def _pinv_wide(A: Tensor) -> Tensor:
    """A† ``(..., c, r)`` of ``A (..., r, c)``, r <= c: Aᵀ(AAᵀ)⁻¹ where well conditioned, else the SVD.

    float32 input is worked in float64 (the Gram matrix squares the condition number) and the result
    returned in float32; the rank cutoff is that of the input's dtype (:func:`rcond`)."""
    r, c = A.shape[-2:]
    batch = A.shape[:-2]
    dtype, work = A.dtype, torch.float64 if A.dtype == torch.float32 else A.dtype
    A2 = A.reshape(-1, r, c)
    # Gram rows: cond(A) below both the working precision's eps^(-1/4) and the rank cutoff 1/rcond
    kappa2_max = min(eps_for(work) ** -0.5, rcond(dtype) ** -2)
    with torch.no_grad():
        Ad = A2.detach().to(work)
        L, info = torch.linalg.cholesky_ex(Ad @ Ad.mT)
        Li = torch.linalg.solve_triangular(L, torch.eye(r, dtype=work, device=A.device), upper=False)
        X = ((Li @ Ad).mT @ Li).to(dtype)  # Aᵀ(AAᵀ)⁻¹ = (L⁻¹A)ᵀL⁻¹
        # tr(AAᵀ)·tr((AAᵀ)⁻¹) is between cond(A)² and r²·cond(A)²: the Gram solve's error is eps·cond(A)²
        kappa2 = (Ad * Ad).sum((-2, -1)) * (Li * Li).sum((-2, -1))
        bad = (info != 0) | ~torch.isfinite(kappa2) | (kappa2 > kappa2_max)
        any_bad = bool(bad.any()) if A2.shape[0] else False

    def gram(M: Tensor) -> Tensor:  # differentiable Aᵀ(AAᵀ)⁻¹ in the working dtype
        Mw = M.to(work)
        return torch.linalg.solve(Mw @ Mw.mT, Mw).mT.to(dtype)

    if not any_bad:
        if not _needs_grad(A2):
            return X.reshape(*batch, c, r)
        return gram(A2).reshape(*batch, c, r)
    dummy = torch.eye(r, c, dtype=dtype, device=A.device)
    A_safe = torch.where(bad[:, None, None], dummy, A2)  # the Gram path's graph stays finite
    X_gram = gram(A_safe) if _needs_grad(A2) else torch.where(bad[:, None, None], torch.zeros_like(X), X)
    Ab = A2[bad]
    X_svd = _svd_pinv(Ab.detach().to(work), rcond(dtype)).to(dtype)
    if _needs_grad(Ab):
        X_svd = _first_order(X_svd, Ab)
    full = torch.zeros_like(X_gram)
    full = full.index_put((bad.nonzero().squeeze(-1),), X_svd)
    return torch.where(bad[:, None, None], full, X_gram).reshape(*batch, c, r)


def _pinv(J: Tensor) -> Tensor:
    """Moore–Penrose inverse of a validated ``J (..., m, n)`` (no checks)."""
    m, n = J.shape[-2:]
    if m == 0 or n == 0:
        return J.new_zeros(*J.shape[:-2], n, m)
    return _pinv_wide(J) if m <= n else _pinv_wide(J.mT).mT


def _damped(J: Tensor, k2: Tensor) -> Tensor:
    """Jᵀ(JJᵀ + λI)⁻¹ of validated inputs, λ = ``k2`` broadcastable to the batch dims: the pseudo-inverse
    where λ is at or below the rounding level eps·‖J‖²_F (zero included), else the regular damped solve."""
    frob2 = (J * J).sum(dim=(-2, -1))
    k2, frob2 = torch.broadcast_tensors(k2, frob2)
    small = k2 <= eps_for(J) * frob2
    if small.numel() == 0 or not bool(small.any()):
        return _dls.damped_pinv(J, k2)
    J = J.expand(*small.shape, *J.shape[-2:])
    damped = _dls.damped_pinv(J, torch.where(small, frob2 + 1.0, k2))  # the pinv rows: any regular value
    if bool(small.all()):
        return _pinv(J)
    return torch.where(small[..., None, None], _pinv(J), damped)


def _check_J(J, *more, finite=True):
    out = tensors(("J", J, (None, None)), *more, finite=finite)
    J = out[0]
    return out if more else J


def pinv(J) -> Tensor:
    """Moore–Penrose pseudo-inverse J† ``(..., n, m)``: the right pseudo-inverse Jᵀ(JJᵀ)⁻¹ (3.52) for full
    row rank, the left one (JᵀJ)⁻¹Jᵀ for full column rank, and at rank-deficient J the inverse of the nonzero
    singular values only (numpy's cutoff; see the module docstring). Finite values and gradients."""
    return _pinv(_check_J(J))


def damped_pinv(J, damping, threshold: float | None = None) -> Tensor:
    """Damped least-squares inverse J* = Jᵀ(JJᵀ + λI)⁻¹ (3.59), λ = k²: ``(..., m, n)`` -> ``(..., n, m)``.

    It minimises ‖v − Jq̇‖² + λ‖q̇‖²: each singular value σ of J is inverted as σ/(σ² + λ), bounded by
    1/(2√λ) so joint velocities stay bounded through singularities. ``damping = 0`` gives :func:`pinv`.

    Args:
        damping: λ, added to JJᵀ's diagonal, eq. (3.59) (the textbook's k²; the unreleased 0.1.0 took k),
            >= 0, a number or a tensor broadcastable to the batch dims ``(...)``.
        threshold: if given, adaptive damping (Nakamura & Hanafusa 1986; Chiaverini 1997): the damping
            λ (1 − (σ_min/threshold)²) where the smallest singular value σ_min < threshold, and none
            otherwise, so the inverse is exact away from singular regions.
    """
    J, k2 = _check_J(J, ("damping", damping, None))
    check_broadcasts_to(check_nonnegative(k2, "damping"), J.shape[:-2], "damping")
    if threshold is not None:
        (thr,) = tensors(("threshold", threshold, ()), like=J)
        k2 = _dls.adaptive_damping(J, k2, thr)
    return _damped(J, k2)


def weighted_pinv(J, W, damping=0.0) -> Tensor:
    """Weighted pseudo-inverse W⁻¹Jᵀ(JW⁻¹Jᵀ + λI)⁻¹ (3.50): the q̇ = J†_W v minimising ½ q̇ᵀWq̇ subject
    to Jq̇ = v (m <= n; for m > n the equal form (JᵀJ + λW)⁻¹Jᵀ).

    Computed as L⁻ᵀ (J L⁻ᵀ)* with W = LLᵀ and * the damped inverse of :func:`damped_pinv` (so the pseudo-
    inverse of J L⁻ᵀ for λ = 0: finite at singular J).

    Args:
        J: ``(..., m, n)``.
        W: symmetric positive-definite weights, ``(..., n, n)``, or their diagonal ``(..., n)``
            (:class:`~diffkin.errors.DiffkinError` if not positive definite).
        damping: optional λ (number or tensor (...)), added to JW⁻¹Jᵀ's diagonal, eq. (3.59), as in
            :func:`damped_pinv`.
    """
    J, W, lam = _check_J(J, ("W", W, None), ("damping", damping, None))
    check_broadcasts_to(check_nonnegative(lam, "damping"), J.shape[:-2], "damping")
    n = J.shape[-1]
    diagonal = W.ndim >= 1 and W.shape[-1] == n and (W.ndim == 1 or W.shape[-2:] != (n, n))
    if not diagonal:
        if W.ndim < 2:
            raise ShapeError(f"expected W of shape (..., {n}, {n}) or (..., {n}), got {shape_str(W.shape)}")
        check_trailing(W, (n, n), "W")
    if diagonal:
        if W.numel() and not bool((W > 0).all()):
            raise DiffkinError("W must be positive definite: its diagonal has entries <= 0")
        s = torch.rsqrt(W)  # L⁻ᵀ = diag(W^-½)
        return s[..., :, None] * _damped(J * s[..., None, :], lam)
    L, info = torch.linalg.cholesky_ex(W)
    if info.numel() and bool((info != 0).any()):
        raise DiffkinError("W must be symmetric positive definite (its Cholesky factorisation failed)")
    Jt = torch.linalg.solve_triangular(L, J.mT, upper=False).mT  # J L⁻ᵀ
    return torch.linalg.solve_triangular(L.mT, _damped(Jt, lam), upper=True)


def nullspace_projector(J, J_pinv=None, damping=None) -> Tensor:
    """Projector onto the null space of J, P = I − J†J ``(..., n, n)`` (3.54).

    P is symmetric, idempotent and JP = 0 (at singular J the lost directions join the null space).
    ``J_pinv`` ``(..., n, m)`` lets you pass a weighted inverse J†_W (then P = I − J†_W J, the projector of
    (3.54) for that metric); ``damping`` λ (added to JJᵀ's diagonal) uses the damped inverse (3.59)
    Jᵀ(JJᵀ + λI)⁻¹ instead (then P is only approximately a projector, but smooth everywhere). Values and
    gradients stay finite.
    """
    J, J_pinv, lam = _check_J(J, ("J_pinv", J_pinv, None), ("damping", damping, None))
    check_broadcasts_to(lam, J.shape[:-2], "damping")
    m, n = J.shape[-2:]
    if J_pinv is None:
        J_pinv = _pinv(J) if lam is None else _damped(J, lam)
    else:
        check_trailing(J_pinv, (n, m), "J_pinv")
    return torch.eye(n, dtype=J.dtype, device=J.device) - J_pinv @ J
