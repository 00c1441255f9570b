"""Operational-space trajectory -> joint trajectory for a batch (§3.7 with ch. 4's trajectories).

Two ways along a sampled pose trajectory T_d(t_k), k = 0 … S−1:

- ``method="clik"``: closed-loop inverse kinematics (:func:`diffkin.ik.closed_loop.clik`) integrated with
  the trajectory's sample period, fed forward with its velocities (given, or finite differences of the
  samples) — smooth, differentiable, one Jacobian solve per sample, tracks through redundancy;
- ``method="solve"``: :func:`diffkin.ik.numerical.solve` on each sample, warm-started from the previous
  solution so the joint path stays on one branch — converges to the tolerance at every sample even when
  the samples are coarse.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from ..errors import ConventionError, ShapeError
from ..rotations import _matrix_to_rotvec, _rotvec_to_matrix
from ..transforms import RIGIDITY_TOLERANCE, _transform_deviations
from ..validation import (
    _traced,
    broadcast_batch,
    check_count,
    check_number,
    check_trailing,
    shape_str,
    tensors,
)
from .closed_loop import clik
from .result import final_errors

__all__ = ["JointTrajectory", "joint_trajectory_from_poses", "finite_difference_twists", "refine_path"]

_METHODS = ("clik", "solve")


class JointTrajectory(NamedTuple):
    """q ``(..., S, n)``; position_error [m] / orientation_error [rad] ``(..., S)`` from an exact FK of q
    (orientation: angle of R_eᵀR_d, 0 for position targets); success ``(..., S)`` both within tolerance."""

    q: Tensor
    position_error: Tensor
    orientation_error: Tensor
    success: Tensor


def finite_difference_twists(T_traj: Tensor, dt: float) -> Tensor:
    """Velocities of a sampled trajectory by forward differences: ``(..., S, 4, 4)`` -> ``(..., S, 6)``.

    ṗ_k = (p_{k+1} − p_k)/Δt and ω_k = rotvec(R_{k+1} R_kᵀ)/Δt (base frame; exact for a constant angular
    velocity over the step), the increment one Euler step (3.48) needs; the last sample is at rest.
    Positions ``(..., S, 3)`` -> ``(..., S, 3)``.
    """
    (T_traj,) = tensors(("T_traj", T_traj, None))
    _path_kind(T_traj, "T_traj", vectors=(3,))
    check_number(dt, "dt", unit=" (s)")
    return _finite_difference_twists(T_traj, dt)


def _path_kind(x: Tensor, name: str, vectors: tuple[int, ...]) -> bool:
    """True for poses ``(..., S, 4, 4)``, False for vectors ``(..., S, k)`` with k in ``vectors``; else
    :class:`ShapeError`. Poses must be rigid by the one rule of
    :data:`~diffkin.transforms.RIGIDITY_TOLERANCE` (:class:`~diffkin.errors.DiffkinError` naming the first
    offending sample): a scaled or sheared rotation block has no rotation vector, its twists and geodesics
    would be silently wrong."""
    if x.ndim >= 3 and tuple(x.shape[-2:]) == (4, 4):
        if not _traced(x):  # values cannot be read while torch.compile / torch.func trace
            _transform_deviations(x.detach(), name, RIGIDITY_TOLERANCE)
        return True
    if x.ndim >= 2 and x.shape[-1] in vectors:
        return False
    sizes = " or ".join(f"(..., S, {k})" for k in vectors)
    raise ShapeError(f"expected {name} of shape (..., S, 4, 4) (poses) or {sizes}, got {shape_str(x.shape)}")


def _finite_difference_twists(T_traj: Tensor, dt: float) -> Tensor:
    pose = T_traj.shape[-2:] == (4, 4)
    lead = T_traj.shape[:-3] if pose else T_traj.shape[:-2]
    if T_traj.shape[len(lead)] == 0:  # no samples: no velocities
        return T_traj.new_zeros(*lead, 0, 6 if pose else T_traj.shape[-1])
    if pose:
        p = T_traj[..., :3, 3]
        R = T_traj[..., :3, :3]
        w = _matrix_to_rotvec(R[..., 1:, :, :] @ R[..., :-1, :, :].mT)
        v = torch.cat((p[..., 1:, :] - p[..., :-1, :], w), dim=-1) / dt
    else:
        v = (T_traj[..., 1:, :] - T_traj[..., :-1, :]) / dt
    rest = v.new_zeros(*v.shape[:-2], 1, v.shape[-1])  # the last sample at rest (the only one when S = 1)
    return torch.cat((v, rest), dim=-2)


def refine_path(T_traj: Tensor, substeps: int) -> Tensor:
    """Insert m − 1 samples (m = ``substeps``) between neighbours: (..., S, 4, 4) -> (..., (S−1)m+1, 4, 4).

    Positions move linearly and rotations along the geodesic R(τ) = exp(τ log(R_{k+1}R_kᵀ)) R_k, i.e. with
    the constant twist of :func:`finite_difference_twists`. Vectors ``(..., S, k)`` are interpolated
    linearly (k = 3 or 6: positions, twists).
    """
    (T_traj,) = tensors(("T_traj", T_traj, None))
    _path_kind(T_traj, "T_traj", vectors=(3, 6))
    return _refine_path(T_traj, check_count(substeps, "substeps"))


def _refine_path(T_traj: Tensor, substeps: int) -> Tensor:
    if substeps == 1 or T_traj.shape[-3 if T_traj.shape[-2:] == (4, 4) else -2] == 0:
        return T_traj
    pose = T_traj.shape[-2:] == (4, 4)
    x = T_traj if pose else T_traj[..., None]  # (..., S, r, c)
    tau = torch.arange(substeps, dtype=x.dtype, device=x.device) / substeps  # (m,)
    a, b = x[..., :-1, :, :], x[..., 1:, :, :]
    tau_x = tau[:, None, None]
    lin = a[..., None, :, :] + tau_x * (b - a)[..., None, :, :]  # (..., S-1, m, r, c)
    if pose:
        w = _matrix_to_rotvec(b[..., :3, :3] @ a[..., :3, :3].mT)  # (..., S-1, 3)
        R = _rotvec_to_matrix(tau[:, None] * w[..., None, :]) @ a[..., None, :3, :3]
        lin = torch.cat((torch.cat((R, lin[..., :3, 3:]), dim=-1), lin[..., 3:, :]), dim=-2)
    fine = torch.cat((lin.flatten(-4, -3), x[..., -1:, :, :]), dim=-3)
    return fine if pose else fine[..., 0]


def _check_path(chain, T_traj, velocities) -> tuple[Tensor, Tensor | None, bool]:
    """-> (T_traj, velocities, True for pose targets (..., S, 4, 4) / False for positions (..., S, 3)), by
    the rule of :mod:`diffkin.validation` (the chain's dtype and device, finite)."""
    T_traj, velocities = tensors(("T_traj", T_traj, None), ("velocities", velocities, None), like=chain)
    poses = _path_kind(T_traj, "T_traj", vectors=(3,))
    n_s = T_traj.shape[-3 if poses else -2]
    if n_s == 0:
        raise ShapeError(f"expected T_traj with at least one sample, got {shape_str(T_traj.shape)}")
    if velocities is not None:
        check_trailing(velocities, (n_s, 6 if poses else 3), "velocities")
    return T_traj, velocities, poses


def joint_trajectory_from_poses(
    chain,
    T_target: Tensor,
    q0: Tensor,
    *,
    method: str = "clik",
    dt: float = 1.0,
    velocities: Tensor | None = None,
    substeps: int = 1,
    algorithm: str = "dls",
    orientation: str = "axis_angle",
    K=None,
    damping: float = 1e-4,
    position_tolerance: float = 1e-4,
    orientation_tolerance: float = 1e-3,
    warm_seeds: int = 1,
    **solve_kwargs,
) -> JointTrajectory:
    """Joint trajectory q(t_k) ``(..., S, n)`` whose FK follows the sampled poses ``T_target``.

    Args:
        chain: a :class:`~diffkin.chain.KinematicChain`.
        T_target: poses ``(..., S, 4, 4)`` or positions ``(..., S, 3)`` (position only), sampled every
            ``dt``.
        q0: starting joints ``(..., n)`` (batch broadcastable); CLIK starts there (converging onto the path
            with rate K), ``solve`` uses it as the first sample's seed.
        method: ``"clik"`` or ``"solve"`` (see the module docstring).
        dt: sample period [s] (with finite-difference velocities and the default gain its value does not
            change the result).
        velocities: ``(..., S, 6)`` twists [ṗ; ω] (or ``(..., S, 3)`` for positions) at the samples; default
            :func:`finite_difference_twists`.
        substeps: CLIK Euler steps per sample interval (Δt = dt/substeps), along :func:`refine_path`; the
            tracking error falls roughly with substeps² (linearisation error of each step).
        algorithm, orientation, K, damping: passed to :func:`~diffkin.ik.closed_loop.clik` (damping λ = k²
            of (3.59)); defaults
            damped least squares (robust near singularities) and K = 1/Δt (each step removes the whole
            error on top of the feedforward: a Newton step toward the next sample).
        position_tolerance, orientation_tolerance: thresholds of ``success`` (and of ``solve``).
        warm_seeds: ``num_seeds`` of ``solve`` after the first sample (1: only the previous solution, so the
            branch is kept). Other keyword arguments go to ``solve`` (``num_seeds`` there applies to the
            first sample only).
    """
    if method not in _METHODS:
        raise ConventionError(f"unknown method {method!r}; valid: {_METHODS}")
    T_traj, velocities, poses = _check_path(chain, T_target, velocities)
    q0 = chain.check_q(q0, name="q0")
    # one batch for the path and q0 (a batch of starts along one path, or one start for a batch of paths)
    k = 3 if poses else 2
    batch = broadcast_batch(("T_target", T_traj, k), ("q0", q0, 1), ("velocities", velocities, 2))
    T_traj = T_traj.expand(*batch, *T_traj.shape[-k:])
    velocities = None if velocities is None else velocities.expand(*batch, *velocities.shape[-2:])
    q0 = q0.expand(*batch, q0.shape[-1])
    if method == "clik":
        substeps = check_count(substeps, "substeps")
        kw = dict(algorithm=algorithm, orientation=orientation, K=K, damping=damping)
        q = _along_clik(chain, T_traj, q0, poses, dt, velocities, substeps, kw)
    else:
        tol = (position_tolerance, orientation_tolerance)
        q = _along_solve(chain, T_traj, q0, poses, tol, warm_seeds, solve_kwargs)
    pos_err, ori_err = final_errors(chain, q, T_traj, not poses)
    success = (pos_err <= position_tolerance) & (ori_err <= orientation_tolerance)
    return JointTrajectory(q, pos_err, ori_err, success)


def _along_clik(chain, T_traj, q0, poses, dt, velocities, substeps, clik_kwargs) -> Tensor:
    if velocities is not None:
        velocities = _refine_path(velocities, substeps)
    fine = _refine_path(T_traj, substeps)
    h = dt / substeps
    if velocities is None:
        velocities = _finite_difference_twists(fine, h)
    kw = dict(algorithm="dls", orientation="axis_angle", K=1.0 / h)
    kw.update({k: v for k, v in clik_kwargs.items() if v is not None})
    if not poses:
        kw["orientation"] = None
    return clik(chain, (fine, velocities), q0, h, **kw).q[..., ::substeps, :]


def _along_solve(chain, T_traj, q0, poses, tol, warm_seeds, solve_kwargs) -> Tensor:
    from .numerical import solve

    axis = -3 if poses else -2
    kw = dict(position_tolerance=tol[0], orientation_tolerance=tol[1], position_only=not poses)
    kw.update(solve_kwargs)
    first_seeds = kw.pop("num_seeds", None)
    qs, q_prev = [], q0
    for k in range(T_traj.shape[axis]):
        seeds = first_seeds if k == 0 else warm_seeds
        extra = {} if seeds is None else {"num_seeds": seeds}
        q_prev = solve(chain, T_traj.select(axis, k), q0=q_prev, **kw, **extra).q
        qs.append(q_prev)
    return torch.stack(torch.broadcast_tensors(*qs), dim=-2)
