"""Robust calibration (outliers in the measurements: a mis-read target, a bumped reflector): the loss and its
scale, and the per-pose outlier report of :class:`~diffkin.calibration.CalibrationResult`.

A pose's residual is the weighted pose error Δx_i = [p_m − p; w rotvec(R_m Rᵀ)] (metres, w =
``orientation_weight``). With measurement noise σ_p (metres per coordinate) and σ_o (radians per coordinate)
its expected squared norm is s̄ = 3σ_p² + 3(w σ_o)² (3σ_p² for positions only). The robust loss
(:func:`~diffkin.calibration.robust_loss`, ``"huber"`` or ``"cauchy"``) is quadratic up to the scale
c = 2 √s̄ (a good pose exceeds it with probability below 1 % for Gaussian noise) and grows slower beyond, so
a pose off by millimetres pulls the fit by at most c (Huber) or by less the further it is off (Cauchy).
Without ``measurement_noise`` the scale is 1 mm (or ``scale=``).

Outliers are the poses whose final residual norm exceeds :data:`OUTLIER_FACTOR` √s̄ (3 √s̄: a good pose's
squared norm beyond 9 s̄, a χ² tail below 1e-5 for 3 or 6 degrees of freedom); without
``measurement_noise`` √s̄ is estimated robustly from the residuals themselves, as the median norm × 1.13
(for Gaussian noise the median of a χ_3 norm is 0.89 of its RMS).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..errors import ConventionError
from ..validation import check_number
from .solvers import LOSSES

__all__ = ["OUTLIER_FACTOR", "resolve_loss", "expected_norm", "pose_errors", "outlier_rows"]

#: a pose is reported as an outlier when its residual norm exceeds this many expected norms √s̄
OUTLIER_FACTOR = 3.0
_SCALE_FACTOR = 2.0  # the robust loss is quadratic up to 2 √s̄
_MEDIAN_TO_RMS = 1.13  # RMS / median of the norm of a 3-vector of i.i.d. Gaussians (√3 / 1.538)


def expected_norm(noise, orientation_weight: float, position_only: bool) -> float | None:
    """√s̄, the RMS residual norm of a good pose under ``noise = (σ_p [m], σ_o [rad])`` (None without)."""
    if noise is None:
        return None
    sp = float(noise[0])
    so = float(noise[1]) if len(noise) > 1 and not position_only else 0.0
    return math.sqrt(3.0 * sp * sp + 3.0 * (orientation_weight * so) ** 2)


def resolve_loss(method: str, loss: str | None, scale, noise, orientation_weight: float,
                 position_only: bool) -> tuple[str, float]:
    """``(loss, scale)``: ``loss=None`` is ``"l2"`` for least squares and ``"huber"`` for the gradient method
    (its former default); ``scale=None`` is 2 √s̄ from ``noise``, else 1 mm."""
    loss = ("l2" if method == "least_squares" else "huber") if loss is None else loss
    if loss not in LOSSES:
        raise ConventionError(f"unknown loss {loss!r}; valid: {', '.join(LOSSES)}")
    if scale is None:
        rms = expected_norm(noise, orientation_weight, position_only)
        scale = 1e-3 if not rms else _SCALE_FACTOR * rms
    return loss, check_number(scale, "scale", unit=" (metres)")


def pose_errors(model, zeta: Tensor, q: Tensor, T: Tensor, orientation_weight: float):
    """Per pose of one robot (``zeta (P,)``, ``q (N, n)``): ``(position error (N,) [m], orientation error
    (N,) [rad] or None, weighted residual norm (N,) [m])``."""
    with torch.no_grad():
        r = model.residual(zeta[None], q[None], T[None], orientation_weight)[0]
    pos = r[..., :3].norm(dim=-1)
    ori = None if r.shape[-1] == 3 else r[..., 3:].norm(dim=-1) / orientation_weight
    return pos, ori, r.norm(dim=-1)


def outlier_rows(norms: Tensor, noise, orientation_weight: float, position_only: bool) -> tuple[list[int],
                                                                                               float]:
    """``(rows, threshold [m])``: the poses whose residual norm exceeds :data:`OUTLIER_FACTOR` √s̄ (√s̄ from
    ``noise``, else robustly from the median norm)."""
    rms = expected_norm(noise, orientation_weight, position_only)
    if not rms:
        rms = float(norms.median()) * _MEDIAN_TO_RMS
    threshold = OUTLIER_FACTOR * rms
    return (norms > threshold).nonzero().flatten().tolist(), threshold
