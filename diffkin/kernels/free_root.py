"""A free joint at the root (humanoids, quadrupeds, a floating object) as a per-row base of the 1-DOF tree
below it, so that the fused C kernel (:mod:`diffkin.kernels.native`) serves the tree.

A chain whose first four frames are a free joint (translations along x, y, z, then a ball motion, the layout
of :data:`~diffkin.kernels.configuration.JOINT_KINDS`' ``free``) and whose other frames are all 1-DOF joints
hanging below it is T_end(q) = M(q_free) · T_inner(q_rest): M is the pose of the free body (the chain's base
included), T_inner the product of the rest from the free body's frame. The Jacobian (3.30) is then
[J_free, diag(R_M, R_M) J_inner]: the free joint's six columns from its axes at the end points, the inner
columns rotated into the base frame. The same numbers as the torch kernels, to rounding.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .jacobian import jacobian_from_axes
from .tree import Segments, Topology, matrix_frames

__all__ = ["FreeRootSplit", "split_free_root", "split_segments", "compose"]

_HEAD = Topology((-1, 0, 1, 2), (False, False, False, True), (3,), (0, 1, 2, 3), (1.0,) * 4, (0.0,) * 4, 7,
                 (False, False, False, True))


@dataclass(frozen=True)
class FreeRootSplit:
    """The free joint's four frames (``head``) and the 1-DOF tree below it (``inner``, q entries 7..)."""

    head: Topology
    inner: Topology


def split_free_root(topo: Topology) -> FreeRootSplit | None:
    """The split of ``topo`` when it is a free joint at the root with 1-DOF joints below it, else None."""
    J = topo.n_frames
    if J <= 4 or not topo.spherical or topo.spherical[:4] != (False, False, False, True) \
            or any(topo.spherical[4:]) or topo.parents[:4] != (-1, 0, 1, 2) \
            or topo.revolute[:3] != (False, False, False) or topo.q_index[:4] != (0, 1, 2, 3) \
            or topo.multiplier[:4] != (1.0,) * 4 or topo.q_offset[:4] != (0.0,) * 4 \
            or any(p < 3 for p in topo.parents[4:]) or any(e < 3 for e in topo.ends) \
            or any(i < 7 for i in topo.q_index[4:]):
        return None
    inner = Topology(tuple(p - 4 for p in topo.parents[4:]), topo.revolute[4:],
                     tuple(e - 4 for e in topo.ends), tuple(i - 7 for i in topo.q_index[4:]),
                     topo.multiplier[4:], topo.q_offset[4:], topo.n_vars - 7)
    return FreeRootSplit(_HEAD, inner)


def split_segments(per_joint: Segments, stacked: Segments) -> tuple[Segments, Segments]:
    """``(head (stacked, with the chain's base), inner (per joint, base None))`` of a chain's constants."""
    cut = (lambda x: None if x is None else x[:4]), (lambda x: None if x is None else x[4:])
    head = Segments(cut[0](stacked.pre), cut[0](stacked.offset), cut[0](stacked.post), stacked.base, [None])
    inner = Segments(cut[1](per_joint.pre), cut[1](per_joint.offset), cut[1](per_joint.post), None,
                     per_joint.ends)
    return head, inner


def compose(q: Tensor, head_seg: Segments, T_inner: Tensor, J_inner: Tensor | None,
            split: FreeRootSplit) -> tuple[Tensor, Tensor | None]:
    """``(T (B, K, 4, 4), J (B, K, 6, nv) or None)`` from the inner tree's poses ``(B, K, 4, 4)`` and
    Jacobians ``(B, K, 6, nv − 6)`` and ``q (B, nq)``."""
    ends, _, axes, origins = matrix_frames(q[:, :7], split.head, head_seg, with_axes=True)
    F = ends[:, 0]  # (B, 4, 4): the free body in the base frame
    T = F.unsqueeze(1) @ T_inner
    if J_inner is None:
        return T, None
    R = F[:, None, :3, :3]
    inner = torch.cat((R @ J_inner[:, :, :3], R @ J_inner[:, :, 3:]), dim=-2)
    K = T.shape[1]
    z, o = (x.unsqueeze(1).expand(-1, K, -1, -1) for x in (axes, origins))  # the same axes for each end
    J_free = jacobian_from_axes(z, o, T[..., :3, 3], _revolute(q), False)
    return T, torch.cat((J_free, inner), dim=-1)


_REVOLUTE: dict = {}


def _revolute(like: Tensor) -> Tensor:
    """The free joint's column mask: three translations, three rotations."""
    key = (like.dtype, like.device)
    if key not in _REVOLUTE:
        _REVOLUTE[key] = torch.tensor([0.0, 0.0, 0.0, 1.0, 1.0, 1.0], dtype=like.dtype, device=like.device)
    return _REVOLUTE[key]
