"""Gauss-Newton on SE(3) for the hand-eye loop G_i X C_i = Y (the refinement of :mod:`.handeye`).

Unknowns: X (the hand-eye transform) and Y (the other fixed transform of the loop: the target in the base
frame eye-in-hand, the target on the gripper eye-to-hand), each updated on the right by the pose correction
Δ(v) of the kernel layer (translation, rotation vector). The residual of pose i is the pose error (§3.7.3,
rotation-vector form) between the measured target pose C_i and the one the loop predicts,
X⁻¹ G_i⁻¹ Y, both in the camera frame; translation and rotation are each divided by their RMS at the
starting point, so that neither unit dominates (a maximum-likelihood fit for isotropic pose noise of the
target's pose estimate). A fixed number of iterations, no host synchronisation; differentiable (unrolled).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..kernels.dls import dls_solve
from ..kernels.joints import pose_correction
from ..transforms import _pose_error, _transform_inverse

__all__ = ["refine_loop", "start_y"]


def _project(R: Tensor) -> Tensor:
    """Nearest rotation (polar factor with det +1) of a (..., 3, 3) matrix."""
    U, _, Vh = torch.linalg.svd(R)
    s = torch.sign(torch.linalg.det(U @ Vh))
    D = torch.cat((torch.ones_like(U[..., 0, :2]), s[..., None]), -1)
    return U @ (D[..., :, None] * Vh)


def start_y(G: Tensor, C: Tensor, X: Tensor) -> Tensor:
    """Y from X: the chordal mean of G_i X C_i over the poses ``(..., N, 4, 4)`` -> ``(..., 4, 4)``."""
    Yi = G @ X[..., None, :, :] @ C
    Y = Yi.mean(-3)
    return torch.cat((torch.cat((_project(Y[..., :3, :3]), Y[..., :3, 3:]), -1), Yi[..., 0, 3:, :]), -2)


def _residual(G: Tensor, C: Tensor, X: Tensor, Y: Tensor) -> Tensor:
    """Pose error [p; rotvec] (..., N, 6) of the measured C_i against the predicted X⁻¹ G_i⁻¹ Y."""
    pred = _transform_inverse(X)[..., None, :, :] @ _transform_inverse(G) @ Y[..., None, :, :]
    return _pose_error(C, pred, "rotvec")


def refine_loop(G: Tensor, C: Tensor, X: Tensor, Y: Tensor, iterations: int = 10) -> tuple[Tensor, Tensor]:
    """Minimise Σ_i ‖W r_i‖² over X, Y from the given start: ``G, C (..., N, 4, 4)``, ``X, Y (..., 4, 4)``
    -> refined ``(X, Y)``. W = diag(1/σ_t I₃, 1/σ_r I₃) with σ the RMS residuals at the start."""
    batch, N = G.shape[:-3], G.shape[-3]
    G, C = G.reshape(-1, N, 4, 4), C.reshape(-1, N, 4, 4)
    X, Y = X.reshape(-1, 4, 4), Y.reshape(-1, 4, 4)
    r0 = _residual(G, C, X, Y)  # the weights are part of the estimator: not detached (exact gradients)
    tiny = torch.finfo(G.dtype).eps
    sig_t = r0[..., :3].square().sum(-1).mean(-1).clamp_min(tiny * tiny).sqrt()
    sig_r = r0[..., 3:].square().sum(-1).mean(-1).clamp_min(tiny * tiny).sqrt()
    w = torch.cat((sig_t[:, None].expand(-1, 3), sig_r[:, None].expand(-1, 3)), -1).reciprocal()

    def weighted(delta: Tensor) -> Tensor:
        xn = X @ pose_correction(delta[:, :6])
        yn = Y @ pose_correction(delta[:, 6:])
        return (_residual(G, C, xn, yn) * w[:, None, :]).flatten(-2)

    zero = G.new_zeros(G.shape[0], 12)
    tangents = torch.eye(12, dtype=G.dtype, device=G.device)[:, None, :].expand(12, *zero.shape)

    def column(t: Tensor) -> Tensor:
        return torch.func.jvp(weighted, (zero,), (t,))[1]

    for _ in range(iterations):
        # forward mode: the 12 columns (one per parameter, the whole batch) in one vectorised jvp (Φ as the
        # calibration matrix); twelve separate jvp calls cost 12× the framework overhead
        r = weighted(zero)
        J = torch.func.vmap(column)(tangents).movedim(0, -1)
        step = dls_solve(J, -r, 1e-12)
        X = X @ pose_correction(step[:, :6])
        Y = Y @ pose_correction(step[:, 6:])
    return X.reshape(*batch, 4, 4), Y.reshape(*batch, 4, 4)
