"""The centre of mass of a robot and its Jacobian, from the link frames and Jacobian columns of one pass.

The centre of mass of the model's bodies (masses m_i, centres c_i in the frame each body moves with) is
p_C = Σ_i m_i p_i / M with p_i = F_i c_i and M = Σ_i m_i, in the chain's base frame (the frame of its FK:
the world for an MJCF chain from the world, base transform included). Its Jacobian is the mass-weighted sum
of the linear rows of the point Jacobians (3.30) with p_e replaced by each p_i,
J_C = Σ_i (m_i / M) J_P(p_i), ``(..., 3, nv)`` (:func:`~diffkin.kernels.jacobian.weighted_point_jacobian`):
MuJoCo's ``subtree_com`` and ``mj_jacSubtreeCom`` of the chain's root body (``nv`` columns in the chain's
convention, as :meth:`~diffkin.chain.KinematicChain.geometric_jacobian`: a free joint's linear velocity
in its parent frame, angular velocity in its own frame).

Masses come from the model file (URDF ``<inertial>``, MJCF compiled by MuJoCo): the chain's buffers
``link_masses (B,)`` and ``link_inertial_frames (B, 4, 4)``. A chain without them (a DH table, a URDF
without ``<inertial>`` elements) raises :class:`~diffkin.errors.ModelError` naming what is missing.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .errors import ModelError
from .kernels.jacobian import weighted_point_jacobian
from .kernels.tree import matrix_frames

__all__ = ["center_of_mass", "com_jacobian", "com_and_jacobian"]


def _masses(chain) -> tuple[Tensor, Tensor]:
    """``(m (B,), c (B, 3))``: the chain's body masses and centres of mass in their frames, or the typed
    error naming what is missing."""
    m = getattr(chain, "link_masses", None)
    if m is None:
        note = getattr(chain, "_mass_note", "") or (
            "a DH table carries no masses; load the robot from a URDF with <inertial> elements "
            "(diffkin.models.from_urdf) or an MJCF model (diffkin.models.from_mjcf)")
        raise ModelError(f"the centre of mass needs link masses, and chain {chain.name!r} "
                         f"({type(chain).__name__}) has none: {note}")
    return m, chain.link_inertial_frames[:, :3, 3]


def _mass_columns(chain, like: Tensor) -> Tensor:
    """``(C, B)``: m_i / M where Jacobian column c moves body i (its frame is an ancestor of body i's),
    else 0. Structure cached per chain; the masses are read on every call (they may change)."""
    topo = chain.topology
    key = (topo, tuple(chain._mass_frames), like.dtype, like.device)
    cache = chain.__dict__.get("_mass_column_mask")
    if cache is None or cache[0] != key:
        rows = []
        for f in topo.column_frame:
            row = []
            for b in chain._mass_frames:
                j = b
                while j > f:
                    j = topo.parents[j]
                row.append(j == f)
            rows.append(row)
        mask = torch.tensor(rows, dtype=like.dtype, device=like.device).reshape(topo.n_columns, -1)
        cache = (key, mask)
        chain.__dict__["_mass_column_mask"] = cache
    m = chain.link_masses
    return cache[1] * (m / m.sum())


def _body_points(chain, q: Tensor, with_axes: bool):
    """The B centres of mass ``(..., B, 3)`` in the base frame, and the columns' axes and origins of the
    same pass (or None)."""
    _, c = _masses(chain)
    seg = chain._segments(per_joint=False)
    _, F, axes, origins = matrix_frames(q, chain.topology, seg, with_axes=with_axes)
    batch = q.shape[:-1]
    base = torch.eye(4, dtype=q.dtype, device=q.device) if seg.base is None else seg.base
    frames = torch.cat((base[:3].expand(*batch, 1, 3, 4), F[..., :3, :]), dim=-3)  # (..., J + 1, 3, 4)
    index = chain.__dict__.get("_mass_frame_index")
    if index is None or index.device != q.device:
        index = torch.tensor([f + 1 for f in chain._mass_frames], device=q.device)
        chain.__dict__["_mass_frame_index"] = index
    Fb = frames.index_select(-3, index)  # (..., B, 3, 4)
    points = (Fb[..., :3] @ c.unsqueeze(-1)).squeeze(-1) + Fb[..., 3]
    return points, axes, origins


def _checked(chain, q) -> Tensor:
    _masses(chain)  # the typed error first, before any input is looked at
    return chain.check_q(q)


def center_of_mass(chain, q: Tensor) -> Tensor:
    """The centre of mass ``(..., 3)`` of the model's bodies at ``q (..., nq)`` in the chain's base frame:
    p_C = Σ_i m_i p_i / Σ_i m_i (MuJoCo's ``subtree_com`` of the chain's root body)."""
    q = _checked(chain, q)
    with torch.autocast(q.device.type, enabled=False):
        points, _, _ = _body_points(chain, q, with_axes=False)
        m = chain.link_masses
        return (m / m.sum()) @ points


def com_jacobian(chain, q: Tensor) -> Tensor:
    """The Jacobian ``(..., 3, nv)`` of :func:`center_of_mass`: J_C = Σ_i (m_i / M) J_P(p_i), the linear
    rows of (3.30) at each body's centre of mass (MuJoCo's ``mj_jacSubtreeCom`` of the root body, on the
    chain's velocity columns)."""
    return com_and_jacobian(chain, q)[1]


def com_and_jacobian(chain, q: Tensor) -> tuple[Tensor, Tensor]:
    """``(center_of_mass (..., 3), com_jacobian (..., 3, nv))`` from one pass."""
    q = _checked(chain, q)
    with torch.autocast(q.device.type, enabled=False):
        points, axes, origins = _body_points(chain, q, with_axes=True)
        m = chain.link_masses
        com = (m / m.sum()) @ points
        J = weighted_point_jacobian(axes, origins, points, _mass_columns(chain, q), chain._joint_revolute,
                                    chain.topology)
    return com, J
