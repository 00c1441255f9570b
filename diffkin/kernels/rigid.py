"""Rotations and rigid transforms (§2.2–2.7), the raw encodings: rotation matrices, skew / vee, Euler
angles (2.18)–(2.23), angle and axis (2.25)–(2.28), rotation vectors, unit quaternions (2.33)–(2.37) and
homogeneous transformations (2.41)–(2.45), on tensors already checked. :mod:`diffkin.rotations` and
:mod:`diffkin.transforms` are their checked public forms; the kernels use these directly, so the kernel layer
imports nothing above it."""

from __future__ import annotations

import torch
from torch import Tensor

from .._numerics import broadcast_shapes, eps_for, safe_atan2, safe_norm, safe_sqrt, sinc
from . import pose_error as _kpe
from .quaternion import _canonical, _matrix_to_quaternion

__all__: list[str] = []  # private encodings, re-exported by name from diffkin.rotations / diffkin.transforms


def _mat(rows) -> Tensor:
    """Stack a nested 3x3 list of broadcastable tensors into (..., 3, 3)."""
    rows = [torch.stack(torch.broadcast_tensors(*r), dim=-1) for r in rows]
    return torch.stack(rows, dim=-2)


def _rot(angle: Tensor, axis: int) -> Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    o, z = torch.ones_like(angle), torch.zeros_like(angle)
    if axis == 0:
        return _mat([[o, z, z], [z, c, -s], [z, s, c]])
    if axis == 1:
        return _mat([[c, z, s], [z, o, z], [-s, z, c]])
    return _mat([[c, -s, z], [s, c, z], [z, z, o]])


def _skew(v: Tensor) -> Tensor:
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return _mat([[o, -z, y], [z, o, -x], [-y, x, o]])


def _vee(S: Tensor) -> Tensor:
    return 0.5 * torch.stack(
        (S[..., 2, 1] - S[..., 1, 2], S[..., 0, 2] - S[..., 2, 0], S[..., 1, 0] - S[..., 0, 1]), dim=-1
    )


def _euler_to_matrix(angles: Tensor, convention: str) -> Tensor:
    cp, ct, cs = torch.cos(angles).unbind(-1)
    sp, st, ss = torch.sin(angles).unbind(-1)
    if convention == "ZYZ":  # (2.18)
        return _mat([
            [cp * ct * cs - sp * ss, -cp * ct * ss - sp * cs, cp * st],
            [sp * ct * cs + cp * ss, -sp * ct * ss + cp * cs, sp * st],
            [-st * cs, st * ss, ct],
        ])
    return _mat([  # RPY (2.21): Rz(phi) Ry(theta) Rx(psi)
        [cp * ct, cp * st * ss - sp * cs, cp * st * cs + sp * ss],
        [sp * ct, sp * st * ss + cp * cs, sp * st * cs - cp * ss],
        [-st, ct * ss, ct * cs],
    ])


def _singular_tol(R: Tensor) -> float:
    return 10.0 * eps_for(R)


def _matrix_to_euler(R: Tensor, convention: str, branch: str = "positive") -> Tensor:
    sg = 1.0 if branch == "positive" else -1.0
    r = lambda i, j: R[..., i - 1, j - 1]  # noqa: E731  (1-based, as in the book)
    zero = torch.zeros_like(r(1, 1))
    if convention == "ZYZ":  # (2.19) / (2.20)
        s = safe_sqrt(r(1, 3) ** 2 + r(2, 3) ** 2)
        theta = torch.atan2(sg * s, r(3, 3))
        sing = s <= _singular_tol(R)
        one = torch.ones_like(s)
        # double where: the regular atan2s get harmless arguments on the singular branch
        phi = torch.atan2(torch.where(sing, zero, sg * r(2, 3)), torch.where(sing, one, sg * r(1, 3)))
        psi_reg = torch.atan2(torch.where(sing, zero, sg * r(3, 2)), torch.where(sing, one, -sg * r(3, 1)))
        # sin(theta) ~ 0: only phi +- psi is defined; take phi = 0, then Rz(psi) = Ry(theta)^T R
        ct, st = torch.cos(theta), torch.sin(theta)
        psi_sing = safe_atan2(r(2, 1), ct * r(1, 1) - st * r(3, 1))
    else:  # RPY (2.22) / (2.23)
        c = safe_sqrt(r(3, 2) ** 2 + r(3, 3) ** 2)
        theta = torch.atan2(-r(3, 1), sg * c)
        sing = c <= _singular_tol(R)
        one = torch.ones_like(c)
        phi = torch.atan2(torch.where(sing, zero, sg * r(2, 1)), torch.where(sing, one, sg * r(1, 1)))
        psi_reg = torch.atan2(torch.where(sing, zero, sg * r(3, 2)), torch.where(sing, one, sg * r(3, 3)))
        # cos(theta) ~ 0: take phi = 0, then Rx(psi) = Ry(theta)^T R
        ct, st = torch.cos(theta), torch.sin(theta)
        psi_sing = safe_atan2(st * r(1, 2) + ct * r(3, 2), r(2, 2))
    phi = torch.where(sing, zero, phi)
    psi = torch.where(sing, psi_sing, psi_reg)
    return torch.stack((phi, theta, psi), dim=-1)


def _euler_rate_matrix(angles: Tensor, convention: str) -> Tensor:
    phi, theta, _ = angles.unbind(-1)
    cp, sp, ct, st = torch.cos(phi), torch.sin(phi), torch.cos(theta), torch.sin(theta)
    o, z = torch.ones_like(phi), torch.zeros_like(phi)
    if convention == "ZYZ":  # columns: z, Rz(phi) y, Rz(phi) Ry(theta) z
        return _mat([[z, -sp, cp * st], [z, cp, sp * st], [o, z, ct]])
    # RPY columns: z, Rz(phi) y, Rz(phi) Ry(theta) x
    return _mat([[z, -sp, cp * ct], [z, cp, sp * ct], [o, z, -st]])


def _axis_angle_to_matrix(axis: Tensor, angle: Tensor) -> Tensor:
    """(2.25) as R = c I + (1 - c) r r^T + s S(r); ``axis`` must be unit."""
    axis, angle = torch.broadcast_tensors(axis, angle[..., None])
    angle = angle[..., 0]
    c, s = torch.cos(angle)[..., None, None], torch.sin(angle)[..., None, None]
    eye = torch.eye(3, dtype=axis.dtype, device=axis.device)
    return c * eye + (1 - c) * axis[..., :, None] * axis[..., None, :] + s * _skew(axis)


def _quaternion_to_axis_angle(Q: Tensor) -> tuple[Tensor, Tensor]:
    eta, eps = Q[..., 0], Q[..., 1:]
    n = safe_norm(eps)
    angle = 2.0 * torch.atan2(n, eta)
    small = n <= eps_for(Q)
    fallback = torch.zeros_like(eps)
    fallback[..., 0] = 1.0  # null rotation: any axis; x by convention
    axis = torch.where(small[..., None], fallback, eps / torch.where(small, torch.ones_like(n), n)[..., None])
    return axis, angle


def _atan_ratio(n2: Tensor, eta: Tensor) -> Tensor:
    """2 atan2(n, eta) / n with n = sqrt(n2): the rotation angle over |eps|; smooth at n = 0 (eta > 0)."""
    tiny = eps_for(eta) ** 0.5
    small = n2 <= tiny * eta * eta
    n2_safe = torch.where(small, torch.ones_like(n2), n2)
    n = torch.sqrt(n2_safe)
    eta_safe = torch.where(small, eta, torch.ones_like(eta))
    x2 = n2 / (eta_safe * eta_safe)  # Taylor of atan(x)/x on the small branch
    taylor = 2.0 / eta_safe * (1.0 - x2 / 3.0 + x2 * x2 / 5.0)
    return torch.where(small, taylor, 2.0 * torch.atan2(n, eta) / n)


def _quaternion_to_rotvec(Q: Tensor) -> Tensor:
    eps = Q[..., 1:]
    return eps * _atan_ratio((eps * eps).sum(-1), Q[..., 0])[..., None]


def _rotvec_to_quaternion(v: Tensor) -> Tensor:
    theta = safe_norm(v)
    q = torch.cat(((torch.cos(theta / 2))[..., None], 0.5 * sinc(theta / 2)[..., None] * v), dim=-1)
    return _canonical(q)


def _rotvec_to_matrix(v: Tensor) -> Tensor:
    theta = safe_norm(v)[..., None, None]
    S = _skew(v)
    eye = torch.eye(3, dtype=v.dtype, device=v.device)
    # (2.25) in Rodrigues form, with sin(t)/t and (1 - cos t)/t^2 = sinc(t/2)^2 / 2 smooth at t = 0
    return eye + sinc(theta) * S + 0.5 * sinc(theta / 2) ** 2 * (S @ S)


def _matrix_to_rotvec(R: Tensor) -> Tensor:
    return _quaternion_to_rotvec(_matrix_to_quaternion(R))


def _quaternion_to_matrix(Q: Tensor) -> Tensor:
    e, x, y, z = Q.unbind(-1)
    return _mat([  # (2.33)
        [2 * (e * e + x * x) - 1, 2 * (x * y - e * z), 2 * (x * z + e * y)],
        [2 * (x * y + e * z), 2 * (e * e + y * y) - 1, 2 * (y * z - e * x)],
        [2 * (x * z - e * y), 2 * (y * z + e * x), 2 * (e * e + z * z) - 1],
    ])


def _quaternion_multiply(Q1: Tensor, Q2: Tensor) -> Tensor:
    Q1, Q2 = torch.broadcast_tensors(Q1, Q2)
    e1, v1, e2, v2 = Q1[..., :1], Q1[..., 1:], Q2[..., :1], Q2[..., 1:]
    eta = e1 * e2 - (v1 * v2).sum(-1, keepdim=True)
    return torch.cat((eta, e1 * v2 + e2 * v1 + torch.linalg.cross(v1, v2, dim=-1)), dim=-1)


def _quaternion_conjugate(Q: Tensor) -> Tensor:
    return torch.cat((Q[..., :1], -Q[..., 1:]), dim=-1)


def _quaternion_slerp(Q0: Tensor, Q1: Tensor, s: Tensor) -> Tensor:
    dQ = _canonical(_quaternion_multiply(_quaternion_conjugate(Q0), Q1))  # shortest arc: eta >= 0
    v = _quaternion_to_rotvec(dQ) * s[..., None]
    return _quaternion_multiply(Q0, _rotvec_to_quaternion(v))


def _make_transform(R: Tensor, p: Tensor) -> Tensor:
    batch = broadcast_shapes(R.shape[:-2], p.shape[:-1])
    top = torch.cat((R.expand(*batch, 3, 3), p.expand(*batch, 3)[..., None]), dim=-1)
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=R.dtype, device=R.device).expand(*batch, 1, 4)
    return torch.cat((top, bottom), dim=-2)


def _transform_inverse(T: Tensor) -> Tensor:
    Rt = T[..., :3, :3].transpose(-1, -2)
    p = -torch.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    return _make_transform(Rt, p)


def _transform_points(T: Tensor, points: Tensor) -> Tensor:
    return torch.einsum("...ij,...j->...i", T[..., :3, :3], points) + T[..., :3, 3]


def _pose_error(T_desired: Tensor, T_current: Tensor, orientation: str = "axis_angle") -> Tensor:
    p_d, R_d = T_desired[..., :3, 3], T_desired[..., :3, :3]
    p_e, R_e = T_current[..., :3, 3], T_current[..., :3, :3]
    e_p, e_o, _ = _kpe.pose_error(p_d, R_d, p_e, R_e, orientation)  # (3.78), §3.7.3
    e_p, e_o = torch.broadcast_tensors(e_p, e_o)
    return torch.cat((e_p, e_o), dim=-1)
