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

import warnings
from dataclasses import replace

import torch
from torch import Tensor

from .errors import ModelError
from .kernels import cache, native
from .kernels.jacobian import weighted_point_jacobian
from .kernels.tree import Segments, matrix_frames

__all__ = ["center_of_mass", "com_jacobian", "com_and_jacobian"]

_NATIVE_BYTES = 16 << 20  # the largest batch of body-point Jacobians the native pass writes (16 MiB)


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
    approximate = getattr(chain, "_mass_note", "")
    if approximate and not chain.__dict__.get("_mass_warned"):
        chain.__dict__["_mass_warned"] = True
        warnings.warn(f"chain {chain.name!r}: MuJoCo infers the masses of {approximate} from mesh geoms, "
                      "which the loader replaces by small spheres (the mesh files are not read): their "
                      "masses and the centre of mass are approximate; give those bodies an <inertial>",
                      stacklevel=4)
    return m, chain.link_inertial_frames[:, :3, 3]


def _mass_columns(chain, like: Tensor) -> Tensor:
    """``(C, B)``: m_i / M where Jacobian column c moves body i (its frame is an ancestor of body i's),
    else 0. Structure cached per chain and topology; the masses are read on every call (they may change)."""
    topo = chain.topology
    memo = chain.__dict__.get("_mass_column_mask")  # topology only (a key of the structure, no values)
    if memo is None or memo[0][0] is not topo or memo[0][1:] != (like.dtype, like.device):
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
        memo = ((topo, like.dtype, like.device), mask)
        chain.__dict__["_mass_column_mask"] = memo
    return memo[1] * _mass_weights(chain)


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
    points = (Fb[..., :3] * c.unsqueeze(-2)).sum(-1) + Fb[..., 3]  # R_i c_i + t_i
    return points, axes, origins


def _native_pass(chain, q: Tensor, with_jacobian: bool) -> tuple[Tensor, Tensor | None] | None:
    """The fused C pass of the chain's FK and Jacobian (:mod:`diffkin.kernels.native`) with the bodies'
    centres of mass as its end points (the same frames, ends translated by c_i), reduced to
    ``(center_of_mass (..., 3), com_jacobian (..., 3, nv) or None)``; None where the native pass does not
    serve the call (autograd, tracing, another device: :meth:`~diffkin.chain.KinematicChain._native_model`).
    The pack is kept on the chain's :class:`~diffkin.kernels.cache.Data` (remade with it).
    Large batches run in slices whose B point Jacobians fit in 16 MiB, each reduced at once."""
    if chain._native_model(q) is None:
        return None
    data = cache.current(chain)  # the Data _native_model has just checked (or remade)

    def make():
        per_joint = data.segments(chain)[0]
        c = chain.link_inertial_frames[:, :3, 3].detach().double().cpu().tolist()
        identity = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
        ends = [None if not any(ci) else (identity, tuple(ci)) for ci in c]
        seg = Segments(per_joint.pre, per_joint.offset, per_joint.post, per_joint.base, ends)
        return native.NativeModel(replace(chain.topology, ends=tuple(chain._mass_frames)), seg)

    packed = data.derived("mass", make)
    batch, nv, B = q.shape[:-1], chain.nv, len(chain._mass_frames)
    flat = q.reshape(-1, chain.nq).contiguous()
    rows = flat.shape[0]
    w = _mass_weights(chain)
    step = max(1, _NATIVE_BYTES // (B * (6 * nv if with_jacobian else 16) * q.element_size()))
    parts = []
    for start in range(0, rows, step):  # slices of the batch (one for a control loop's few rows)
        T, Jp, _ = native.fk_jacobian(packed, flat[start:start + step], with_jacobian)
        n = T.shape[0]
        # Σ_i (m_i / M) over the bodies: one product each for the poses and the point Jacobians
        com = (w @ T.view(n, B, 16))[:, 3:12:4]
        parts.append((com, None if Jp is None else (w @ Jp.view(n, B, 6 * nv)).view(n, 6, nv)[:, :3]))
    if len(parts) == 1:
        com, J = parts[0]
    else:
        com = torch.cat([c for c, _ in parts])
        J = torch.cat([j for _, j in parts]) if with_jacobian else None
    return com.reshape(*batch, 3), None if J is None else J.reshape(*batch, 3, nv)


def _mass_weights(chain) -> Tensor:
    """m_i / M ``(B,)``, kept on the chain's :class:`~diffkin.kernels.cache.Data` (remade with it when the
    masses, a buffer, change in any way)."""
    m = chain.link_masses
    data = None if m.requires_grad and torch.is_grad_enabled() else cache.current(chain, grad=False)
    if data is None:  # learnable masses (a fresh graph every call), or values not readable as constants
        return m / m.sum()
    return data.derived("mass_weights", lambda: m / m.sum())


def _weighted_mean(chain, points: Tensor) -> Tensor:
    """Σ_i m_i p_i / Σ_i m_i ``(..., 3)`` of ``points (..., B, 3)``."""
    return (_mass_weights(chain).unsqueeze(-1) * points).sum(-2)


def _checked(chain, q) -> Tensor:
    _masses(chain)  # the typed error first, before any input is looked at
    return chain.check_q(q)


def center_of_mass(chain, q: Tensor) -> Tensor:
    """The centre of mass ``(..., 3)`` of the model's bodies at ``q (..., nq)`` in the chain's base frame:
    p_C = Σ_i m_i p_i / Σ_i m_i (MuJoCo's ``subtree_com`` of the chain's root body)."""
    q = _checked(chain, q)
    fast = _native_pass(chain, q, with_jacobian=False)
    if fast is not None:
        return fast[0]
    with torch.autocast(q.device.type, enabled=False):
        points, _, _ = _body_points(chain, q, with_axes=False)
        return _weighted_mean(chain, points)


def com_jacobian(chain, q: Tensor) -> Tensor:
    """The Jacobian ``(..., 3, nv)`` of :func:`center_of_mass`: J_C = Σ_i (m_i / M) J_P(p_i), the linear
    rows of (3.30) at each body's centre of mass (MuJoCo's ``mj_jacSubtreeCom`` of the root body, on the
    chain's velocity columns)."""
    return com_and_jacobian(chain, q)[1]


def com_and_jacobian(chain, q: Tensor) -> tuple[Tensor, Tensor]:
    """``(center_of_mass (..., 3), com_jacobian (..., 3, nv))`` from one pass."""
    q = _checked(chain, q)
    fast = _native_pass(chain, q, with_jacobian=True)
    if fast is not None:
        return fast
    with torch.autocast(q.device.type, enabled=False):
        points, axes, origins = _body_points(chain, q, with_axes=True)
        com = _weighted_mean(chain, points)
        J = weighted_point_jacobian(axes, origins, points, _mass_columns(chain, q), chain._joint_revolute,
                                    chain.topology)
    return com, J
