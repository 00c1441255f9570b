"""Statics (§3.8): joint torques balancing an end-effector wrench and velocity/force transformations.

Twists are ``[ṗ; ω]`` and wrenches ``[f; μ]`` ``(..., 6)``, like the rows of the geometric Jacobian.
A pair of frames on one rigid body is given either as ``(R, r)`` with ``R = R^1_2 (..., 3, 3)`` the
orientation of frame 2 in frame 1 and ``r = r^1_12 (..., 3)`` the origin of frame 2 seen from frame 1
(in frame 1), or as the transform ``T^1_2 (..., 4, 4)`` alone. Inputs follow :mod:`diffkin.validation`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .errors import ShapeError
from .rotations import _skew
from .validation import broadcast_batch, shape_str, tensors

__all__ = [
    "joint_torques_from_wrench",
    "velocity_transform",
    "wrench_transform",
    "transform_velocity",
    "transform_wrench",
    "closed_chain_torques",
]


def joint_torques_from_wrench(J: Tensor, wrench: Tensor) -> Tensor:
    """τ = Jᵀ(q) γ_e (3.111): ``J (..., 6, n)``, ``wrench (..., 6)`` -> ``(..., n)``.

    γ_e = [f_e; μ_e] is the force and moment the end effector exerts on the environment, expressed in the
    frame (and at the point) J refers to; τ are the joint torques/forces that balance it at equilibrium.
    """
    J, wrench = tensors(("J", J, (6, None)), ("wrench", wrench, (6,)))
    broadcast_batch(("J", J, 2), ("wrench", wrench, 1))
    return torch.einsum("...ij,...i->...j", J, wrench)


def _pair(R, r, *extra: tuple[str, object, tuple[int, ...]]) -> tuple[Tensor, ...]:
    """The frame pair ``(R, r)`` (from ``T`` when ``r`` is None) and the further arguments, validated."""
    if r is None:
        T, *rest = tensors(("T", R, (4, 4)), *extra)
        R, r = T[..., :3, :3], T[..., :3, 3]
    else:
        R, r, *rest = tensors(("R", R, (3, 3)), ("r", r, (3,)), *extra)
    named = ((name, x, len(trail)) for (name, _, trail), x in zip(extra, rest))
    broadcast_batch(("R", R, 2), ("r", r, 1), *named)
    return (R, r, *rest)


def _blocks(a: Tensor, b: Tensor, c: Tensor, d: Tensor) -> Tensor:
    """[[a, b], [c, d]] of (..., 3, 3) blocks -> (..., 6, 6)."""
    a, b, c, d = torch.broadcast_tensors(a, b, c, d)
    return torch.cat((torch.cat((a, b), dim=-1), torch.cat((c, d), dim=-1)), dim=-2)


def velocity_transform(R: Tensor, r: Tensor | None = None) -> Tensor:
    """J^2_1 of v^2_2 = J^2_1 v^1_1 (3.113): [[R^2_1, −R^2_1 S(r^1_12)], [O, R^2_1]] ``(..., 6, 6)``.

    ``v^1_1`` is the twist of frame 1 in its own coordinates, ``v^2_2`` that of frame 2 (same body).
    """
    R, r = _pair(R, r)
    Rt = R.mT  # R^2_1
    return _blocks(Rt, -Rt @ _skew(r), torch.zeros_like(Rt), Rt)


def wrench_transform(R: Tensor, r: Tensor | None = None) -> Tensor:
    """(J^2_1)ᵀ of γ^1_1 = (J^2_1)ᵀ γ^2_2 (3.115)–(3.116): ``(..., 6, 6)``
    [[R^1_2, O], [S(r^1_12) R^1_2, R^1_2]]."""
    R, r = _pair(R, r)
    return _blocks(R, torch.zeros_like(R), _skew(r) @ R, R)


def transform_velocity(R: Tensor, r: Tensor | None, v: Tensor) -> Tensor:
    """Apply (3.113) without forming the 6×6 matrix: twist ``v^1_1 (..., 6)`` -> ``v^2_2 (..., 6)``."""
    R, r, v = _pair(R, r, ("v", v, (6,)))
    lin, ang = v[..., :3], v[..., 3:]
    ang_b, r_b = torch.broadcast_tensors(ang, r)
    lin2 = lin + torch.linalg.cross(ang_b, r_b, dim=-1)  # ṗ_2 = ṗ_1 + ω × r_12
    rot = lambda x: torch.einsum("...ji,...j->...i", R, x)  # noqa: E731  (R^2_1 x)
    return torch.cat(torch.broadcast_tensors(rot(lin2), rot(ang)), dim=-1)


def transform_wrench(R: Tensor, r: Tensor | None, wrench: Tensor) -> Tensor:
    """Apply (3.116): wrench ``γ^2_2 (..., 6)`` -> ``γ^1_1 (..., 6)``: f1 = R f2, μ1 = r × (R f2) + R μ2."""
    R, r, wrench = _pair(R, r, ("wrench", wrench, (6,)))
    f1 = torch.einsum("...ij,...j->...i", R, wrench[..., :3])
    mu1 = torch.einsum("...ij,...j->...i", R, wrench[..., 3:])
    r, f1b = torch.broadcast_tensors(r, f1)
    return torch.cat(torch.broadcast_tensors(f1, torch.linalg.cross(r, f1b, dim=-1) + mu1), dim=-1)


def closed_chain_torques(upsilon: Tensor, tau: Tensor) -> Tensor:
    """Torques of the actuated joints of a closed chain, τ_a = Υᵀ τ_o (3.118)–(3.120).

    ``upsilon (..., n_o, n_a)`` maps actuated joint velocities to those of the open tree, q̇_o = Υ q̇_a;
    ``tau (..., n_o)`` are the torques of the open-tree joints. Returns ``(..., n_a)``.
    """
    upsilon, tau = tensors(("upsilon", upsilon, (None, None)), ("tau", tau, (None,)))
    if tau.shape[-1] != upsilon.shape[-2]:
        raise ShapeError(
            "expected upsilon (..., n_o, n_a) and tau (..., n_o), "
            f"got {shape_str(upsilon.shape)} and {shape_str(tau.shape)}"
        )
    broadcast_batch(("upsilon", upsilon, 2), ("tau", tau, 1))
    return torch.einsum("...ij,...i->...j", upsilon, tau)
