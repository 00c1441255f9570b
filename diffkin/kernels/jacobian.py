"""The geometric Jacobian (3.30) and the parameter Jacobian: the only encodings.

Column i of the geometric Jacobian of an end point p_e is [z_i × (p_e − p_i); z_i] for a revolute and
[z_i; 0] for a prismatic joint (a ball motion gives three revolute columns, about the x, y, z axes of its
rotated frame: its angular velocity in that frame, as MuJoCo's),
where z_i, p_i are the joint's motion axis and a point on it in the base frame
(from one pass of :mod:`diffkin.kernels.tree`). On a tree the columns of joints that are not ancestors of
end link k are zero for that end link; with mimic joints the column of a variable is the sum of its joints'
columns times their multipliers (J = J_full M).
"""

from __future__ import annotations

import torch
from torch import Tensor

from .rigid import _vee
from .tree import Topology

__all__ = [
    "jacobian_from_axes",
    "jacobian_rows",
    "tree_jacobian",
    "tree_jacobian_rows",
    "weighted_point_jacobian",
    "twist_of_derivative",
    "FEW_OPS_BATCH",
]

FEW_OPS_BATCH = 64  # up to this many configurations the Jacobian kernel minimises the number of ops


def jacobian_from_axes(
    axes: Tensor, origins: Tensor, p_e: Tensor, revolute: Tensor, all_revolute: bool
) -> Tensor:
    """(3.30) from joint axes/origins ``(..., n, 3)`` and the end point ``(..., 3)`` -> ``(..., 6, n)``,
    contiguous. Small batches: fewest ops, batch first; large ones: batch-last passes (:func:`jacobian_rows`).
    """
    if axes.shape[:-2].numel() <= FEW_OPS_BATCH:  # per-call overhead dominates: fewest ops
        lin = torch.linalg.cross(axes, p_e.unsqueeze(-2) - origins, dim=-1)
        if all_revolute:
            cols = torch.cat((lin, axes), dim=-1)
        else:
            rev = revolute.unsqueeze(-1)
            cols = torch.cat((lin * rev + axes * (1.0 - rev), axes * rev), dim=-1)
        return cols.transpose(-1, -2).contiguous()
    # large batches: elementwise passes over batch-last (3, n, *batch) memory, which is how the chains'
    # column kernel hands axes/origins out (stride(-1) != 1); other layouts are transposed to it once
    nb = axes.ndim - 2
    to_batch_last = (nb + 1, nb, *range(nb))
    z, o = axes.permute(*to_batch_last), origins.permute(*to_batch_last)
    if axes.stride(-1) == 1:
        z, o = z.contiguous(), o.contiguous()
    rows = jacobian_rows(z, o, p_e.permute(nb, *range(nb)).contiguous(), revolute, all_revolute)
    return rows.permute(*range(2, 2 + nb), 0, 1).contiguous()  # one transposing pass


def jacobian_rows(
    z: Tensor, o: Tensor, p_e: Tensor, revolute: Tensor, all_revolute: bool, rows: Tensor | None = None
) -> Tensor:
    """(3.30) on batch-last blocks: axes ``z`` and origins ``o`` (3, n, *batch), EE point ``p_e``
    (3, *batch) -> rows [linear; angular] of J as (6, n, *batch).

    Without autograd the rows are written in place into ``rows`` (new if None), whose ``rows[3:]`` may
    be ``z`` itself; with autograd they are stacked (the same arithmetic, so the same values).
    """
    nb = z.ndim - 2
    zx, zy, zz = z
    rx, ry, rz = p_e.unsqueeze(1) - o  # p_e - p_{i-1}
    terms = ((zy, rz, zz, ry), (zz, rx, zx, rz), (zx, ry, zy, rx))  # row k of z_{i-1} x (p_e - p_{i-1})
    rev = None if all_revolute else revolute.view(-1, *(1,) * nb)
    # prismatic joints: [z; 0]; an arithmetic blend keeps one code path for every joint
    if torch.compiler.is_compiling() or (torch.is_grad_enabled() and
                                         (z.requires_grad or o.requires_grad or p_e.requires_grad)):
        lin = [torch.addcmul(a * b, c, d, value=-1.0) for a, b, c, d in terms]
        if rev is not None:
            lin = [torch.addcmul(row * rev, zk, 1.0 - rev) for row, zk in zip(lin, z)]
        return torch.stack((*lin, *(z if rev is None else z * rev)))
    rows = z.new_empty(6, *z.shape[1:]) if rows is None else rows
    for k, (a, b, c, d) in enumerate(terms):
        torch.mul(a, b, out=rows[k]).addcmul_(c, d, value=-1.0)
        if rev is not None:
            rows[k].mul_(rev).addcmul_(z[k], 1.0 - rev)
    if rows[3:].data_ptr() != z.data_ptr():
        rows[3:].copy_(z)
    if rev is not None:
        rows[3:].mul_(rev)
    return rows


def tree_jacobian(axes: Tensor, origins: Tensor, p_ends: Tensor, revolute: Tensor, topo: Topology) -> Tensor:
    """Jacobians of the K end links ``(..., K, 6, nv)`` from the C column axes/origins ``(..., C, 3)`` (one
    per R/P frame, three per ball motion), the end points ``p_ends (..., K, 3)`` and the float mask
    ``revolute (C,)``: (3.30), masked by ancestry, coupled through the mimic matrix."""
    all_rev = all(topo.column_revolute)
    blocks = []
    for k, row in enumerate(topo.column_ancestors):
        Jk = jacobian_from_axes(axes, origins, p_ends[..., k, :], revolute, all_rev)
        if not all(row):
            Jk = Jk * topo.tensor("column_ancestors", Jk.dtype, Jk.device)[k]
        blocks.append(Jk)
    J = torch.stack(blocks, dim=-3)
    if topo.coupled:
        J = J @ topo.coupling_matrix(J.dtype, J.device)
    return J


def tree_jacobian_rows(axes: list, p_ends: list, revolute: Tensor, topo: Topology, m: int) -> Tensor:
    """Batch-last twin of :func:`tree_jacobian`: from the J ``(axis, point)`` column pairs of
    :func:`~diffkin.kernels.tree.column_frames` and the K end points ``(3, m)`` (or ``(3, 1)``) -> rows
    ``(n, 6K, m)`` (row block k for end link k), masked by ancestry and coupled through the mimic matrix.

    A single end link without autograd writes the axes straight into the angular rows (no extra copy)."""
    J = topo.n_columns
    all_rev = all(topo.column_revolute)
    grad = torch.is_grad_enabled() and any(c.requires_grad for a in axes for c in a)
    in_place = len(p_ends) == 1 and not grad and not torch.compiler.is_compiling()  # graphs: no aliasing
    rows = axes[0][0].new_empty(6, J, m) if in_place else None
    z = torch.stack([a[0].expand(3, m) for a in axes], dim=1, out=rows[3:] if in_place else None)
    o = torch.stack([a[1].expand(3, m) for a in axes], dim=1)  # (3, J, m)
    blocks = []
    for k, p in enumerate(p_ends):
        R = jacobian_rows(z, o, p.expand(3, m), revolute, all_rev, rows)  # (6, J, m)
        if not all(topo.column_ancestors[k]):
            R = R * topo.tensor("column_ancestors", R.dtype, R.device)[k].view(1, -1, 1)
        blocks.append(R)
    out = blocks[0] if len(blocks) == 1 else torch.cat(blocks, dim=0)  # (6K, J, m)
    if topo.coupled:
        return torch.einsum("rjm,jn->nrm", out, topo.coupling_matrix(out.dtype, out.device))
    return out.permute(1, 0, 2)


def weighted_point_jacobian(axes: Tensor, origins: Tensor, points: Tensor, weights: Tensor, revolute: Tensor,
                            topo: Topology) -> Tensor:
    """Σ_i w_i J_P(p_i) ``(..., 3, nv)``: the linear rows of (3.30) for B points ``p_i`` ``(..., B, 3)``
    attached to the tree, summed with weights (the centre-of-mass Jacobian for w_i = m_i / M).

    ``axes`` / ``origins`` ``(..., C, 3)`` are the C columns' z_c and p_c of one pass of
    :mod:`diffkin.kernels.tree`; ``weights (C, B)`` holds w_i where column c moves point i (its frame is an
    ancestor of point i's) and 0 elsewhere. By linearity of (3.30) in p_e, column c is
    z_c × (S_c − W_c p_c) for a revolute and W_c z_c for a prismatic joint, with S_c = Σ_i w_ci p_i and
    W_c = Σ_i w_ci: one cross product per column, whatever B. Coupled through the mimic matrix.
    """
    C, B = weights.shape
    batch = points.shape[:-2]
    # one (C, B) x (B, 3 · batch) product: a broadcast batched matmul is many times slower for small C, B
    S = (weights @ points.movedim(-2, 0).reshape(B, -1)).reshape(C, *batch, 3).movedim(0, -2)  # (..., C, 3)
    W = weights.sum(-1, keepdim=True)  # (C, 1)
    lin = torch.linalg.cross(axes, S - W * origins, dim=-1)
    if not all(topo.column_revolute):
        rev = revolute.unsqueeze(-1)
        lin = lin * rev + axes * (W * (1.0 - rev))
    J = lin.transpose(-1, -2)  # (..., 3, C)
    if topo.coupled:
        J = J @ topo.coupling_matrix(J.dtype, J.device)
    return J


def twist_of_derivative(dT: Tensor, T: Tensor) -> Tensor:
    """Base-frame twists ``(..., 6, P)`` [δp; δω] of pose derivatives ``dT (..., 4, 4, P)`` at poses
    ``T (..., 4, 4)``: δp = dp, [δω]× = dR Rᵀ (the parameter Jacobian's columns, comparable with the
    geometric Jacobian's)."""
    lin = dT[..., :3, 3, :]
    W = torch.einsum("...ijp,...kj->...pik", dT[..., :3, :3, :], T[..., :3, :3])
    return torch.cat((lin, _vee(W).transpose(-1, -2)), dim=-2)
