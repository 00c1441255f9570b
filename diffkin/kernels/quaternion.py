"""Unit quaternions from rotation matrices (2.34)–(2.35): the one encoding, shared by
:mod:`diffkin.rotations` and the pose-error kernel (:mod:`diffkin.kernels.pose_error`)."""

from __future__ import annotations

import torch
from torch import Tensor

from .._numerics import safe_norm

__all__ = ["_canonical", "_matrix_to_quaternion"]


def _canonical(Q: Tensor) -> Tensor:
    """Flip the sign where eta < 0 (Q and -Q are the same rotation)."""
    return torch.where(Q[..., :1] < 0, -Q, Q)



def _matrix_to_quaternion(R: Tensor) -> Tensor:
    r11, r12, r13 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    r21, r22, r23 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    r31, r32, r33 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    # 4 * (eta^2, ex^2, ey^2, ez^2): the square roots of (2.34)-(2.35)
    t = torch.stack(
        (1 + r11 + r22 + r33, 1 + r11 - r22 - r33, 1 - r11 + r22 - r33, 1 - r11 - r22 + r33), dim=-1
    )
    a, b, c = r32 - r23, r13 - r31, r21 - r12  # 4 eta * eps
    d, e, f = r12 + r21, r13 + r31, r23 + r32  # 4 ex ey, 4 ex ez, 4 ey ez
    # Shepperd: each row k is 4 * q_k * q, divided by 2 sqrt(t_k); take the row with the largest t_k.
    # The clamp keeps the unused rows (and their gradients) finite: the double-where pattern.
    cand = torch.stack(
        (
            torch.stack((t[..., 0], a, b, c), -1),
            torch.stack((a, t[..., 1], d, e), -1),
            torch.stack((b, d, t[..., 2], f), -1),
            torch.stack((c, e, f, t[..., 3]), -1),
        ),
        dim=-2,
    ) / (2 * torch.sqrt(t.clamp_min(0.1)))[..., None]
    k = t.argmax(dim=-1)[..., None, None].expand(*t.shape[:-1], 1, 4)
    q = torch.gather(cand, -2, k)[..., 0, :]
    q = q / safe_norm(q, keepdim=True)
    return _canonical(q)
