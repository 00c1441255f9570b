"""Joint kinds as fixed transforms around one motion about z (§2.8): the only encodings of each.

Every one-DOF joint j is written as

    A_j(q_j) = Pre_j · M(q_j + offset_j) · Post_j,      M = Rz (revolute) or Tz (prismatic),

with Pre_j, Post_j fixed rigid transforms and offset_j a fixed joint offset, all computed here from the
geometric parameters, vectorised over the J joints (``(J,)`` parameters -> ``(J, 4, 4)`` transforms, ``(J,)``
offsets). A transform that is the identity for every joint of a kind is returned as None. The chain product
(:mod:`diffkin.kernels.tree`) then only ever multiplies fixed transforms and motions about z.

* standard DH (2.52): A = Rz(ϑ) Tz(d) Tx(a) Rx(α) = Rz(q + ϑ) · [Tz(d) Tx(a) Rx(α)] (revolute) or
  Tz(q + d) · [Rz(ϑ) Tx(a) Rx(α)] (prismatic), since Rz and Tz commute; with Hayati's β (Hayati & Mirmirani
  1985) the post transform ends with Ry(β): for near-parallel consecutive axes a small tilt in their plane is
  then a small change of β, where DH would need a huge d;
* modified DH (Craig): A = Rx(α) Tx(a) Rz(ϑ) Tz(d) = [Rx(α) Tx(a) Tz(d)] · Rz(q + ϑ) (revolute) or
  [Rx(α) Tx(a) Rz(ϑ)] · Tz(q + d) (prismatic);
* the general joint (URDF): A = Trans(xyz) Rot_rpy · Rot(k, q) = [Trans(xyz) Rot_rpy S] · Rz(q) · [Sᵀ] with S
  any rotation taking e_z to the unit axis k (prismatic: Tz instead of Rz).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from functools import reduce

import torch
from torch import Tensor

from .rigid import _euler_to_matrix, _make_transform, _rotvec_to_matrix, _skew

__all__ = [
    "dh_matrix",
    "modified_dh_matrix",
    "dh_joints",
    "origin_transform",
    "axis_alignment",
    "general_joints",
    "pose_correction",
    "compose_factors",
    "translation_axes",
]


def dh_matrix(a: Tensor, alpha: Tensor, d: Tensor, theta: Tensor) -> Tensor:
    """Standard DH link matrix (2.52) Rz(ϑ) Tz(d) Tx(a) Rx(α): ``(...)`` each -> ``(..., 4, 4)``."""
    ct, st, ca, sa = torch.cos(theta), torch.sin(theta), torch.cos(alpha), torch.sin(alpha)
    z, o = torch.zeros_like(ct), torch.ones_like(ct)
    rows = (ct, -st * ca, st * sa, a * ct, st, ct * ca, -ct * sa, a * st, z, sa, ca, d, z, z, z, o)
    return torch.stack(torch.broadcast_tensors(*rows), dim=-1).unflatten(-1, (4, 4))


def modified_dh_matrix(a: Tensor, alpha: Tensor, d: Tensor, theta: Tensor) -> Tensor:
    """Modified (Craig) DH link matrix Rx(α) Tx(a) Rz(ϑ) Tz(d): ``(...)`` each -> ``(..., 4, 4)``."""
    ct, st, ca, sa = torch.cos(theta), torch.sin(theta), torch.cos(alpha), torch.sin(alpha)
    z, o = torch.zeros_like(ct), torch.ones_like(ct)
    rows = (ct, -st, z, a, st * ca, ct * ca, -sa, -sa * d, st * sa, ct * sa, ca, ca * d, z, z, z, o)
    return torch.stack(torch.broadcast_tensors(*rows), dim=-1).unflatten(-1, (4, 4))


def _rot_y(beta: Tensor) -> Tensor:
    c, s = torch.cos(beta), torch.sin(beta)
    z, o = torch.zeros_like(c), torch.ones_like(c)
    rows = (c, z, s, z, z, o, z, z, -s, z, c, z, z, z, z, o)
    return torch.stack(rows, dim=-1).unflatten(-1, (4, 4))


def dh_joints(a: Tensor, alpha: Tensor, d: Tensor, theta: Tensor, revolute: Tensor, modified: bool,
              beta: Tensor | None = None) -> tuple[Tensor | None, Tensor, Tensor | None]:
    """``(Pre (J, 4, 4) or None, offset (J,), Post (J, 4, 4) or None)`` of a DH table (see the module doc).

    ``revolute`` is the float mask ``(J,)`` (1 revolute, 0 prismatic); ``beta`` (Hayati, standard
    convention only) adds Ry(β) at the end of each link.
    """
    prismatic = 1.0 - revolute
    offset = theta * revolute + d * prismatic
    if modified:
        return modified_dh_matrix(a, alpha, d * revolute, theta * prismatic), offset, None
    post = dh_matrix(a, alpha, d * revolute, theta * prismatic)
    if beta is not None:
        post = post @ _rot_y(beta)
    return None, offset, post


def origin_transform(xyz: Tensor, rpy: Tensor) -> Tensor:
    """URDF ``<origin>``: Trans(xyz) · Rz(yaw) Ry(pitch) Rx(roll) (the book's RPY (2.21) with φ = yaw):
    ``(..., 3)``, ``(..., 3)`` -> ``(..., 4, 4)``."""
    return _make_transform(_euler_to_matrix(rpy.flip(-1), "RPY"), xyz)


def axis_alignment(axis: Tensor, flip: Tensor) -> Tensor:
    """A rotation S ``(..., 3, 3)`` with S e_z = k = axis/|axis| for ``axis (..., 3)`` (non-zero).

    S = S₀(k') Rx(π)^f with k' = (−1)^f k and S₀(k') = I + [u]× + [u]×²/(1 + k'_z), u = e_z × k' (the
    shortest rotation from e_z to k'): smooth while k'_z > −1, so ``flip`` (bool ``(...)``, a constant chosen
    from the nominal axis: True where k_z < 0) keeps every axis away from the singular direction. Exact for
    the axis-aligned axes of real URDFs (e.g. k = e_x gives Ry(π/2)).
    """
    k = axis / torch.linalg.vector_norm(axis, dim=-1, keepdim=True)
    sign = 1.0 - 2.0 * flip.to(k.dtype).unsqueeze(-1)
    kp = k * sign
    zero = torch.zeros_like(kp[..., 0])
    u = torch.stack((-kp[..., 1], kp[..., 0], zero), dim=-1)
    U = _skew(u)
    eye = torch.eye(3, dtype=k.dtype, device=k.device)
    S0 = eye + U + (U @ U) / (1.0 + kp[..., 2])[..., None, None]
    # · Rx(π)^f = diag(1, s, s): negate the y and z columns where flipped
    return S0 * torch.cat((torch.ones_like(sign), sign, sign), dim=-1).unsqueeze(-2)


def general_joints(xyz: Tensor, rpy: Tensor, axis: Tensor, flip: Tensor) -> tuple[Tensor, Tensor]:
    """Moving URDF joints: ``(Pre, Post)``, each ``(J, 4, 4)``: Pre = origin · S, Post = Sᵀ (module doc)."""
    S = axis_alignment(axis, flip)
    zero = torch.zeros_like(xyz)
    return origin_transform(xyz, rpy) @ _make_transform(S, zero), _make_transform(S.transpose(-1, -2), zero)


def pose_correction(v: Tensor) -> Tensor:
    """Δ(v) = [[R(v[3:]), v[:3]], [0, 1]]: a pose correction ``(..., 6)`` (translation in m, rotation vector
    in rad) -> ``(..., 4, 4)``; smooth at v = 0, so a learnable base or tool stays rigid for any value."""
    return _make_transform(_rotvec_to_matrix(v[..., 3:]), v[..., :3])


def compose_factors(table: Mapping[str, Sequence[Tensor]], recipes: Sequence[Sequence[tuple]],
                    eye: Tensor) -> list[Tensor]:
    """Per recipe the product of its factors ``table[name][i]`` in order, each ``(4, 4)`` (the identity
    ``eye`` for an empty recipe): how the URDF and MJCF chains build each frame's Pre and Post from their
    parameters (origins, body poses, joint anchors, axis alignments) in one pass."""
    return [reduce(torch.matmul, [table[k][i] for k, i in r]) if r else eye for r in recipes]


_TRANSLATION_AXES: dict = {}


def translation_axes(like: Tensor) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
    """``(S, Sᵀ)`` by axis name ``"x"``, ``"y"``, ``"z"``: fixed rotations taking e_z to e_x (Ry(π/2)), e_y
    (Rx(−π/2)) and e_z, as ``(4, 4)``: the translations of free and planar joints are motions along z in
    these frames (exact: signed permutations)."""
    key = (like.dtype, like.device)
    if key not in _TRANSLATION_AXES:
        eye = torch.eye(4, dtype=like.dtype, device=like.device)
        Sx = torch.tensor([[0.0, 0, 1, 0], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]], dtype=like.dtype,
                          device=like.device)
        Sy = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], dtype=like.dtype,
                          device=like.device)
        _TRANSLATION_AXES[key] = ({"x": Sx, "y": Sy, "z": eye}, {"x": Sx.T, "y": Sy.T, "z": eye})
    return _TRANSLATION_AXES[key]
