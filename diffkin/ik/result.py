"""The result object shared by the numerical and optimisation-based IK solvers."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor

from .._unchecked import fk
from ..kernels.pose_error import rotation_angle

__all__ = ["IKResult", "final_errors", "rotation_angle_between"]


@dataclass
class IKResult:
    """Per-target IK solutions for a batch of targets of shape ``(...)``.

    Attributes:
        q: joint variables ``(..., n)``, within the joint limits when the solver respected them.
        success: ``(...)`` bool, True iff the errors below meet the requested tolerances (and the limits).
        position_error: ``(...)`` [m], ‖p_d − p_e‖ from an exact FK of ``q`` in the chain's dtype.
        orientation_error: ``(...)`` [rad], rotation angle of R_eᵀR_d (0 when only positions were given;
            reported but not part of ``success`` in position-only solves).
        iterations: ``(...)`` int, solver iterations spent on the target (all of its seeds together).
        seeds_tried: ``(...)`` int, number of initial configurations tried (None if not applicable).
    """

    q: Tensor
    success: Tensor
    position_error: Tensor
    orientation_error: Tensor
    iterations: Tensor
    seeds_tried: Tensor | None = None

    @property
    def batch_shape(self) -> torch.Size:
        return self.success.shape

    def summary(self) -> dict:
        """Success rate and median / max errors over the successful and over all targets (Python floats)."""
        ok = self.success.reshape(-1)
        pe, oe = self.position_error.reshape(-1).double(), self.orientation_error.reshape(-1).double()
        it = self.iterations.reshape(-1).double()
        n = ok.numel()

        def med(x):
            return float(x.median()) if x.numel() else float("nan")

        out = {
            "targets": n,
            "success_rate": float(ok.double().mean()) if n else float("nan"),
            "median_position_error": med(pe),
            "median_orientation_error": med(oe),
            "max_position_error_success": float(pe[ok].max()) if bool(ok.any()) else float("nan"),
            "max_orientation_error_success": float(oe[ok].max()) if bool(ok.any()) else float("nan"),
            "median_iterations": med(it),
        }
        if self.seeds_tried is not None:
            out["mean_seeds_tried"] = float(self.seeds_tried.double().mean()) if n else float("nan")
        return out

    def __str__(self) -> str:
        s = self.summary()
        return (
            f"IKResult({s['targets']} targets: success {100 * s['success_rate']:.2f} %, median errors "
            f"{s['median_position_error']:.2e} m / {s['median_orientation_error']:.2e} rad, "
            f"median iterations {s['median_iterations']:.0f})"
        )

    def to(self, device=None, dtype: torch.dtype | None = None) -> IKResult:
        """Move every tensor to ``device``; ``dtype`` applies to the floating-point fields only."""
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, Tensor):
                v = v.to(device=device, dtype=dtype if v.is_floating_point() else None)
            out[f.name] = v
        return IKResult(**out)


def rotation_angle_between(R_a: Tensor, R_b: Tensor) -> Tensor:
    """Angle of R_aᵀR_b ``(..., 3, 3)`` -> ``(...)`` in [0, π], by atan2(‖vee‖, cos) (accurate near 0)."""
    return rotation_angle(R_b, R_a)  # R_b R_aᵀ = R_a (R_aᵀR_b) R_aᵀ: the same angle


def _norm(v: Tensor) -> Tensor:
    """Euclidean norm over the last axis without overflow (scaled by the largest entry): a 1e30 m error is
    1e30 in float32, not inf."""
    s = v.abs().amax(-1, keepdim=True)
    scale = torch.where(s > 0, s, torch.ones_like(s))
    return s.squeeze(-1) * torch.linalg.vector_norm(v / scale, dim=-1)


def final_errors(chain, q: Tensor, T_target: Tensor, position_only: bool) -> tuple[Tensor, Tensor]:
    """Exact position / orientation errors of ``q (..., n)`` against ``T_target`` in the chain's dtype
    (for K end links: the worst of the K)."""
    T = fk(chain, q)
    tree = T.ndim > q.ndim + 1  # (..., K, 4, 4)
    if T_target.ndim == T.ndim - 1:  # positions (..., [K,] 3)
        pos = _norm(T_target - T[..., :3, 3])
        ori = torch.zeros_like(pos)
    else:
        pos = _norm(T_target[..., :3, 3] - T[..., :3, 3])
        ori = rotation_angle_between(T[..., :3, :3], T_target[..., :3, :3])
    return (pos.amax(-1), ori.amax(-1)) if tree else (pos, ori)
