"""Differential kinematics (§3.1–3.7): geometric and analytical Jacobians, J̇q̇ and Jacobian inverses.

The geometric Jacobian (3.30) comes from one pass of the kernel layer (encoded in
:mod:`diffkin.kernels.jacobian`, run by ``chain.forward_kinematics_and_jacobian``); this module adds the
choice of frame and point, the analytical Jacobian (3.66) and J̇q̇. Rows are ``[linear; angular]``; a chain
with K end links gives ``(..., K, 6, n)``.

Singularity measures, manipulability and ellipsoids live in :mod:`diffkin.manipulability`, Jacobian inverses
in :mod:`diffkin.redundancy`, statics in :mod:`diffkin.statics`: each name has that one home.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import torch
from torch import Tensor

from ._numerics import cross, eps_for
from .errors import ConventionError, RepresentationSingularityError
from .rotations import _convention, _euler_rate_matrix, _matrix_to_euler
from .validation import broadcast_batch, check_trailing, tensors

__all__ = [
    "geometric_jacobian",
    "forward_kinematics_and_jacobian",
    "jacobian_dot_qdot",
    "analytical_jacobian",
    "AnalyticalJacobian",
    "analytical_transform",
    "analytical_to_geometric",
    "geometric_to_analytical",
    "shift_jacobian_point",
    "rotate_jacobian",
]

_SINGULAR_MODES = ("raise", "flag", "ignore")
_POINT_FRAMES = ("ee", "base")


def shift_jacobian_point(J: Tensor, r: Tensor) -> Tensor:
    """Jacobian of the point p = p_e + r on the same body (3.112): J_P' = J_P - S(r) J_O, J_O' = J_O.

    ``J`` (..., 6, n) in some frame, ``r`` (..., 3) the offset p - p_e expressed in that same frame.
    """
    J, r = tensors(("J", J, (6, None)), ("r", r, (3,)))
    broadcast_batch(("J", J, 2), ("r", r, 1))
    return _shift_jacobian_point(J, r)


def _shift_jacobian_point(J: Tensor, r: Tensor) -> Tensor:
    lin, ang = J[..., :3, :], J[..., 3:, :]
    wx, wy, wz = ang.unbind(-2)
    rx, ry, rz = (c.unsqueeze(-1) for c in r.unbind(-1))
    # v_p = v_e + omega x r
    shift = torch.stack((wy * rz - wz * ry, wz * rx - wx * rz, wx * ry - wy * rx), dim=-2)
    return torch.cat((lin + shift, ang.expand_as(shift)), dim=-2)


def rotate_jacobian(J: Tensor, R: Tensor) -> Tensor:
    """Express a Jacobian (..., 6, n) given in the base frame in frame u with orientation ``R`` = R^0_u
    (..., 3, 3): J^u = diag(R^T, R^T) J (3.34, where the book's R^u = (R^0_u)^T)."""
    J, R = tensors(("J", J, (6, None)), ("R", R, (3, 3)))
    broadcast_batch(("J", J, 2), ("R", R, 2))
    return _rotate_jacobian(J, R)


def _rotate_jacobian(J: Tensor, R: Tensor) -> Tensor:
    lin = torch.einsum("...ji,...jk->...ik", R, J[..., :3, :])
    ang = torch.einsum("...ji,...jk->...ik", R, J[..., 3:, :])
    return torch.cat((lin, ang), dim=-2)


def _check_options(chain, q, frame, point, point_frame: str, check: bool):
    """Validate ``q`` (when ``check``), a tensor ``frame`` and ``point`` together, in the chain's dtype."""
    if isinstance(frame, str) and frame not in ("base", "ee"):
        raise ConventionError(f"frame must be None, 'base', 'ee' or a rotation tensor, got {frame!r}")
    if point is not None and point_frame not in _POINT_FRAMES:
        raise ConventionError(f"point_frame must be one of {_POINT_FRAMES}, got {point_frame!r}")
    tensor_frame = None if frame is None or isinstance(frame, str) else frame
    if check or tensor_frame is not None or point is not None:
        q_spec = ("q", q if check else None, (chain.n_joints,))  # None: trusted, passed on as it is
        q_checked, tensor_frame, point = tensors(
            q_spec, ("frame", tensor_frame, None), ("point", point, (3,)), like=chain
        )
        q = q if q_checked is None else q_checked
    if tensor_frame is not None:
        if tensor_frame.ndim >= 2 and tuple(tensor_frame.shape[-2:]) == (4, 4):
            tensor_frame = tensor_frame[..., :3, :3]
        check_trailing(tensor_frame, (3, 3), "frame")
        frame = tensor_frame
    return q, frame, point


def _frame_rotation(frame, T_ee: Tensor) -> Tensor | None:
    if frame is None or (isinstance(frame, str) and frame == "base"):
        return None
    if isinstance(frame, str):
        return T_ee[..., :3, :3]
    broadcast_batch(("frame", frame, 2), ("q", T_ee, 2))
    return frame


def _point_offset(point, point_frame: str, T_ee: Tensor) -> Tensor | None:
    if point is None:
        return None
    broadcast_batch(("point", point, 1), ("q", T_ee, 2))
    R, p_e = T_ee[..., :3, :3], T_ee[..., :3, 3]
    if point_frame == "ee":
        return torch.einsum("...ij,...j->...i", R, point)
    return point - p_e


# ------------------------------------------------------------------------------ geometric Jacobian
def forward_kinematics_and_jacobian(
    chain, q: Tensor, frame=None, point: Tensor | None = None, point_frame: str = "ee", check: bool = True,
    base: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """End-effector pose ``T (..., 4, 4)`` and geometric Jacobian ``J (..., 6, n)`` from one FK pass.

    See :func:`geometric_jacobian` for the options. ``T`` is always the end-effector (tool) pose in the base
    frame, whatever ``point``/``frame`` say; with ``base`` (per-row world poses of the base, ``(..., 4, 4)``)
    the pose and the Jacobian are in the world (``point_frame="base"`` then means the world).
    """
    if base is not None:
        if frame is not None or point is not None:
            q, frame, point = _check_options(chain, q, frame, point, point_frame, check)
        T_ee, J = chain._fk_jacobian(q, check, base)
        return _jacobian_options(T_ee, J, frame, point, point_frame)
    if frame is None and point is None:  # the plain call: the chain checks q itself (the same rule)
        return chain._fk_jacobian(q, check)
    q, frame, point = _check_options(chain, q, frame, point, point_frame, check)
    T_ee, J = chain._fk_jacobian(q, False)
    return _jacobian_options(T_ee, J, frame, point, point_frame)


def _jacobian_options(T_ee: Tensor, J: Tensor, frame, point, point_frame: str) -> tuple[Tensor, Tensor]:
    r = _point_offset(point, point_frame, T_ee)
    if r is not None:
        J = _shift_jacobian_point(J, r)
    R = _frame_rotation(frame, T_ee)
    if R is not None:
        J = _rotate_jacobian(J, R)
    return T_ee, J


def geometric_jacobian(
    chain, q: Tensor, frame=None, point: Tensor | None = None, point_frame: str = "ee", check: bool = True,
    base: Tensor | None = None,
) -> Tensor:
    """Geometric Jacobian (3.29)–(3.30): ``q (..., n)`` -> ``J (..., 6, n)``, rows [linear; angular].

    Column i is [z_{i-1} × (p_e − p_{i-1}); z_{i-1}] for a revolute and [z_{i-1}; 0] for a prismatic joint,
    from the frames of one FK pass; p_e is the end-effector (tool) origin.

    Args:
        frame: frame the velocities are expressed in. ``None``/``"base"``: base frame (default). ``"ee"``:
            the end-effector frame. A tensor ``R`` (..., 3, 3) (or a transform (..., 4, 4), rotation used):
            the orientation of frame u in the base frame; J^u = diag(Rᵀ, Rᵀ) J (3.34).
        point: compute the linear velocity at this point of the end-effector body instead of p_e (e.g. a
            tool tip): v_p = v_e + ω × (p − p_e) (3.112). ``(..., 3)``.
        point_frame: ``"ee"`` (default): ``point`` is given in the end-effector frame (an offset from p_e,
            like a tool translation); ``"base"``: ``point`` is a position in the base frame.
        check: validate ``q`` (by the rule of :mod:`diffkin.validation`, in the chain's dtype and device;
            ``point`` and a tensor ``frame`` are always validated).
        base: per-row world poses of the chain's base ``(..., 4, 4)``: the Jacobian in the world,
            diag(R, R) J.
    """
    return forward_kinematics_and_jacobian(chain, q, frame, point, point_frame, check, base)[1]


# ------------------------------------------------------------------------------------------- J̇ q̇
def jacobian_dot_qdot(chain, q: Tensor, qdot: Tensor, check: bool = True) -> Tensor:
    """J̇(q, q̇) q̇ ``(..., [K,] 6)`` of the base-frame geometric Jacobian at each end link (for §3.7.4).

    ``q``, ``qdot`` ``(..., n)`` (broadcast together); ``K`` end links give ``(..., K, 6)``. J̇ is the
    directional derivative of the kernel Jacobian (3.30) along q̇, J̇ = Σ_k ∂J/∂q_k q̇_k, taken by
    forward-mode AD through the chain's FK + Jacobian pass (exact, no second encoding of (3.30); trees, mimic
    couplings, prismatic joints, base and tool as the kernels have them). Batches above
    ``chain.small_batch`` run vmapped in blocks of that size; a few times the cost of J.
    Differentiable with respect to ``q``, ``qdot`` and the chain's parameters.
    """
    if check:
        n = chain.n_joints
        q, qdot = tensors(("q", q, (n,)), ("qdot", qdot, (n,)), like=chain)
        broadcast_batch(("q", q, 1), ("qdot", qdot, 1))
    q, qdot = torch.broadcast_tensors(q, qdot)
    batch, n = q.shape[:-1], q.shape[-1]
    # contiguous rows: forward-mode AD writes the tangent into a tensor laid out like q, which an expanded
    # (stride-0) q, e.g. one q broadcast against a batch of qdot, cannot hold
    q, qdot = q.reshape(-1, n).contiguous(), qdot.reshape(-1, n).contiguous()
    B, m = q.shape[0], chain.small_batch
    if B <= m:
        return _jdot_qdot_rows(chain, q, qdot).reshape(*batch, *_jdot_tail(chain))
    # vmapped over blocks of m configurations (the last one padded with copies): within a block the kernels
    # take their autograd-safe small-batch path, whose ops all have forward-mode derivatives (the
    # large-batch path writes into preallocated rows)
    pad = -B % m
    q, qdot = (torch.cat((x, x[-1:].expand(pad, n))) if pad else x for x in (q, qdot))
    out = torch.func.vmap(partial(_jdot_qdot_rows, chain))(q.reshape(-1, m, n), qdot.reshape(-1, m, n))
    return out.flatten(0, 1)[:B].reshape(*batch, *_jdot_tail(chain))


def _jdot_tail(chain) -> tuple[int, ...]:
    return (6,) if chain.single_end else (chain.n_ends, 6)


def _jdot_qdot_rows(chain, q: Tensor, qdot: Tensor) -> Tensor:
    """J̇q̇ ``(m, [K,] 6)`` for at most ``chain.small_batch`` configurations ``q (m, n)``: (d/dt J(q + t q̇)) q̇
    by forward mode through the kernel Jacobian."""
    _, J_dot = torch.func.jvp(lambda x: chain._fk_jacobian(x, False)[1], (q,), (qdot,))
    v = qdot if chain.single_end else qdot.unsqueeze(-2)  # one q̇ for every end link
    return (J_dot @ v.unsqueeze(-1)).squeeze(-1)


# ----------------------------------------------------------------------------- analytical Jacobian
class AnalyticalJacobian(NamedTuple):
    """``analytical_jacobian(..., singular="flag")``: J_A (..., 6, n) and a boolean ``singular`` (...)."""

    J_A: Tensor
    singular: Tensor


def analytical_transform(phi: Tensor, representation: str = "ZYZ") -> Tensor:
    """T_A(φ) = diag(I, T(φ)) (3.65): Euler angles (..., 3) -> (..., 6, 6), with v_e = T_A(φ) ẋ_e."""
    conv = _convention(representation)
    (phi,) = tensors(("phi", phi, (3,)))
    T = _euler_rate_matrix(phi, conv)
    out = torch.zeros(*phi.shape[:-1], 6, 6, dtype=phi.dtype, device=phi.device)
    out[..., :3, :3] = torch.eye(3, dtype=phi.dtype, device=phi.device)
    out[..., 3:, 3:] = T
    return out


def analytical_to_geometric(J_A: Tensor, phi: Tensor, representation: str = "ZYZ") -> Tensor:
    """J = T_A(φ) J_A (3.66): (..., 6, n), Euler angles (..., 3) -> (..., 6, n)."""
    conv = _convention(representation)
    J_A, phi = tensors(("J_A", J_A, (6, None)), ("phi", phi, (3,)))
    broadcast_batch(("J_A", J_A, 2), ("phi", phi, 1))
    T = _euler_rate_matrix(phi, conv)
    return torch.cat((J_A[..., :3, :], T @ J_A[..., 3:, :]), dim=-2)


def _inverse3(T: Tensor, tol: float) -> tuple[Tensor, Tensor]:
    """Inverse of (..., 3, 3) by cofactors; where |det| <= tol returns finite garbage and flags it."""
    a, b, c = T.unbind(-1)  # columns
    bc, ca, ab = cross(b, c), cross(c, a), cross(a, b)
    det = (a * bc).sum(-1)
    singular = det.abs() <= tol
    det_safe = torch.where(singular, torch.ones_like(det), det)  # double where: no inf/NaN gradients
    inv = torch.stack((bc, ca, ab), dim=-2) / det_safe[..., None, None]
    return inv, singular


def geometric_to_analytical(J: Tensor, phi: Tensor, representation: str = "ZYZ", tol: float | None = None):
    """J_A = T_A(φ)⁻¹ J (3.66). Returns ``(J_A (..., 6, n), singular (...))``; where |det T(φ)| <= tol
    (default √eps) the representation is singular and the values there are finite but meaningless."""
    conv = _convention(representation)
    J, phi = tensors(("J", J, (6, None)), ("phi", phi, (3,)))
    broadcast_batch(("J", J, 2), ("phi", phi, 1))
    return _geometric_to_analytical(J, phi, conv, tol)


def _geometric_to_analytical(J: Tensor, phi: Tensor, conv: str, tol: float | None):
    T = _euler_rate_matrix(phi, conv)
    tol = eps_for(phi) ** 0.5 if tol is None else tol
    T_inv, singular = _inverse3(T, tol)
    return torch.cat((J[..., :3, :], T_inv @ J[..., 3:, :]), dim=-2), singular


def analytical_jacobian(
    chain,
    q: Tensor,
    representation: str = "ZYZ",
    singular: str = "raise",
    branch: str = "positive",
    tol: float | None = None,
    check: bool = True,
):
    """Analytical Jacobian J_A = T_A⁻¹(φ_e) J (3.62)–(3.66): ``q (..., n)`` -> ``(..., 6, n)``.

    Rows [ṗ_e; φ̇_e] for the Euler angles φ_e of the end-effector orientation (``"ZYZ"`` or ``"RPY"``,
    :func:`diffkin.rotations.matrix_to_euler` with ``branch``). At a representation singularity
    (|det T(φ)| = |sin ϑ| (ZYZ) or |cos ϑ| (RPY) <= ``tol``, default √eps of the dtype) T(φ) cannot be
    inverted; ``singular`` chooses what happens:

    - ``"raise"`` (default): raise :class:`~diffkin.errors.RepresentationSingularityError` if any
      configuration of the batch is singular (this synchronises with the device);
    - ``"flag"``: return :class:`AnalyticalJacobian` ``(J_A, singular)`` with a boolean mask (...);
    - ``"ignore"``: return J_A only.

    Values at flagged configurations are finite but meaningless; gradients stay finite everywhere.
    """
    if singular not in _SINGULAR_MODES:
        raise ConventionError(f"singular must be one of {_SINGULAR_MODES}, got {singular!r}")
    conv = _convention(representation)
    T_ee, J = forward_kinematics_and_jacobian(chain, q, check=check)
    phi = _matrix_to_euler(T_ee[..., :3, :3], conv, branch)
    J_A, mask = _geometric_to_analytical(J, phi, conv, tol)
    if singular == "flag":
        return AnalyticalJacobian(J_A, mask)
    if singular == "raise" and bool(mask.any()):
        n_bad = int(mask.sum())
        raise RepresentationSingularityError(
            f"{conv} Euler angles are singular at {n_bad} of {mask.numel()} configurations "
            f"({'sin' if conv == 'ZYZ' else 'cos'}(theta) ~ 0); use singular='flag' to get a mask, "
            "another representation, or the geometric Jacobian"
        )
    return J_A

