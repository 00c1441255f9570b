"""The product along a tree of joints (2.50): frames, joint axes and origins, end links.

Joints are numbered in topological order; joint j hangs from the frame of joint ``parents[j]`` (−1: the
base) and its frame is F_j = F_parent · Pre_j · M(q_j + offset_j) · Post_j (:mod:`diffkin.kernels.joints`).
A serial chain is the tree with ``parents[j] = j − 1``; shared prefixes of a tree are computed once. End
link k is F_{ends[k]} · E_k. The motion axis of joint j is the z axis of F_parent · Pre_j · M_j through its
origin (what the Jacobian (3.30) needs: any point of the axis will do).

Mimic joints are not variables: q_full = M q + b with joint j driven by variable ``q_index[j]`` times
``multiplier[j]`` plus ``q_offset[j]`` (identity for ordinary joints).

Two evaluations of the same product:

* :func:`column_frames` — batch last, one joint at a time on the columns of the current frame (large
  batches; fixed transforms as constant plans when no gradient w.r.t. geometry is needed);
* :func:`matrix_frames` — batch first, every joint's link matrix at once from the same column arithmetic,
  then one matmul per joint (small batches: fewer, larger operations).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from .._numerics import stable_normalize
from .columns import (
    Columns,
    Fixed,
    apply_fixed,
    apply_motion,
    identity_columns,
    rotate_columns,
    stack_columns,
)
from .rigid import _quaternion_to_matrix

__all__ = ["Topology", "Segments", "column_frames", "matrix_frames", "couple", "spherical_rotations"]


@dataclass(frozen=True)
class Topology:
    """The structure of a kinematic tree (Python constants; see the module doc)."""

    parents: tuple[int, ...]
    revolute: tuple[bool, ...]
    ends: tuple[int, ...]
    q_index: tuple[int, ...]
    multiplier: tuple[float, ...]
    q_offset: tuple[float, ...]
    n_vars: int
    #: per frame: a ball motion "S" (the unit quaternion q[q_index[j] : q_index[j] + 4], three Jacobian
    #: columns); empty: none (every frame one R or P motion)
    spherical: tuple[bool, ...] = ()
    ancestors: tuple[tuple[bool, ...], ...] = field(init=False)
    last_use: tuple[int, ...] = field(init=False)
    n_dofs: int = field(init=False)
    motions: tuple[str, ...] = field(init=False)
    column_frame: tuple[int, ...] = field(init=False)
    column_v: tuple[int, ...] = field(init=False)
    column_revolute: tuple[bool, ...] = field(init=False)
    column_ancestors: tuple[tuple[bool, ...], ...] = field(init=False)
    _tensors: dict = field(init=False, default_factory=dict, compare=False, repr=False)

    def __post_init__(self):
        J = len(self.parents)
        if not all(-1 <= p < j for j, p in enumerate(self.parents)):
            raise ValueError(f"parents must precede their children, got {self.parents}")
        if self.spherical and len(self.spherical) != J:
            raise ValueError(f"spherical must have one entry per frame ({J}), got {len(self.spherical)}")
        anc = []
        for e in self.ends:
            row, j = [False] * J, e
            while j >= 0:
                row[j] = True
                j = self.parents[j]
            anc.append(tuple(row))
        object.__setattr__(self, "ancestors", tuple(anc))
        # the frame of joint j is needed until its last child (or end link) has used it
        last = list(range(J))
        for j, p in enumerate(self.parents):
            if p >= 0:
                last[p] = j
        for e in self.ends:
            if e >= 0:
                last[e] = J
        object.__setattr__(self, "last_use", tuple(last))
        self._set_columns(J)

    def _set_columns(self, J: int) -> None:
        """The velocity layout: the motion of each independent coordinate (R/P: one q and one v entry,
        S: four and three) in q order, each frame's first velocity column, and the Jacobian columns (one per
        R/P frame, three per S frame: its x, y, z axes)."""
        sph = self.spherical or (False,) * J
        motion_at: dict[int, str] = {}
        for j in range(J):
            m = "S" if sph[j] else ("R" if self.revolute[j] else "P")
            if motion_at.setdefault(self.q_index[j], m) != m:
                raise ValueError(f"frames of coordinate {self.q_index[j]} disagree on its motion")
            if m == "S" and (self.multiplier[j] != 1.0 or self.q_offset[j] != 0.0):
                raise ValueError(f"frame {j}: a ball motion cannot be coupled (mimic)")
        v_at, i, nv, motions = {}, 0, 0, []
        while i < self.n_vars:
            m = motion_at.get(i)
            if m is None:
                raise ValueError(f"coordinate {i} of q drives no frame (q_index {self.q_index})")
            v_at[i], motions = nv, motions + [m]
            i, nv = i + (4 if m == "S" else 1), nv + (3 if m == "S" else 1)
        if i != self.n_vars:
            raise ValueError(f"a quaternion runs past the end of q ({self.n_vars} coordinates)")
        cf, cv, cr = [], [], []
        for j in range(J):
            for k in range(3 if sph[j] else 1):
                cf.append(j)
                cv.append(v_at[self.q_index[j]] + k)
                cr.append(bool(self.revolute[j] or sph[j]))
        object.__setattr__(self, "n_dofs", nv)
        object.__setattr__(self, "motions", tuple(motions))
        object.__setattr__(self, "column_frame", tuple(cf))
        object.__setattr__(self, "column_v", tuple(cv))
        object.__setattr__(self, "column_revolute", tuple(cr))
        object.__setattr__(self, "column_ancestors",
                           tuple(tuple(row[f] for f in cf) for row in self.ancestors))

    @property
    def has_spherical(self) -> bool:
        return any(self.spherical)

    @property
    def nq(self) -> int:
        """Size of q: the independent coordinates (quaternions count four)."""
        return self.n_vars

    @property
    def nv(self) -> int:
        """Size of the velocities and of the Jacobian's columns (ball joints count three)."""
        return self.n_dofs

    @property
    def n_columns(self) -> int:
        """Jacobian columns before the coupling: one per R/P frame, three per S frame."""
        return len(self.column_frame)

    @classmethod
    def serial(cls, revolute: Sequence[bool]) -> Topology:
        J = len(revolute)
        return cls(tuple(range(-1, J - 1)), tuple(bool(r) for r in revolute), (J - 1,), tuple(range(J)),
                   (1.0,) * J, (0.0,) * J, J)

    @property
    def n_frames(self) -> int:
        return len(self.parents)

    @property
    def coupled(self) -> bool:
        """True when some joint is not simply variable j (mimic joints)."""
        J = len(self.parents)
        return (self.n_vars != J or self.q_index != tuple(range(J)) or any(m != 1.0 for m in self.multiplier)
                or any(b != 0.0 for b in self.q_offset) or self.column_v != tuple(range(self.n_columns)))

    def tensor(self, name: str, dtype, device) -> Tensor:
        """The structure as a tensor on ``device``, made once per (name, dtype, device): per-call
        ``torch.tensor(list, device=cuda)`` would be a blocking host-to-device copy in the hot paths.

        ``name``: ``q_index``, ``parent_index`` (parents + 1, long), ``revolute`` (bool), ``multiplier``,
        ``q_offset``, ``ancestors`` ``(K, J)``, ``coupling`` (M ``(J, n)`` with q_full = M q + b)."""
        key = (name, dtype, device)
        t = self._tensors.get(key)
        if t is None:
            if name == "coupling":  # (C, nv): Jacobian column c is velocity column_v[c] times its multiplier
                M = [[0.0] * self.n_dofs for _ in self.column_frame]
                for c, (j, i) in enumerate(zip(self.column_frame, self.column_v)):
                    M[c][i] = self.multiplier[j]
                t = torch.tensor(M, dtype=dtype, device=device)
            elif name == "quaternion_index":  # (J, 4): the q entries of each S frame's quaternion (0: others)
                t = torch.tensor([[self.q_index[j] + k if s else 0 for k in range(4)]
                                  for j, s in enumerate(self.spherical)], device=device)
            elif name == "spherical":
                t = torch.tensor(self.spherical, device=device)
            elif name == "axis_select":  # (C,): row 3 j + k of the (J, 3 axes) stack for each column
                sel, seen = [], {}
                for j in self.column_frame:  # an S frame's columns are its axes x, y, z; others use z
                    k = seen.get(j, 0)
                    seen[j] = k + 1
                    sel.append(3 * j + (k if self.spherical and self.spherical[j] else 2))
                t = torch.tensor(sel, device=device)
            elif name == "column_frame":
                t = torch.tensor(self.column_frame, device=device)
            elif name == "column_ancestors":
                t = torch.tensor(self.column_ancestors, dtype=dtype, device=device)
            elif name == "parent_index":
                t = torch.tensor([p + 1 for p in self.parents], device=device)
            elif name == "ancestors":
                t = torch.tensor(self.ancestors, dtype=dtype, device=device)
            elif name in ("q_index", "revolute"):
                t = torch.tensor(getattr(self, name), device=device)
            else:
                t = torch.tensor(getattr(self, name), dtype=dtype, device=device)
            self._tensors[key] = t
        return t

    def coupling_matrix(self, dtype, device) -> Tensor:
        """M ``(J, n)`` with q_full = M q + b."""
        return self.tensor("coupling", dtype, device)


@dataclass(frozen=True)
class Segments:
    """Fixed parts of every joint and of the ends, per joint (lists, for :func:`column_frames`) or
    stacked (``(J, 4, 4)`` tensors, for :func:`matrix_frames`); offsets ``(J,)`` or per-joint scalars."""

    pre: Sequence[Fixed] | Tensor | None
    offset: Sequence | Tensor | None
    post: Sequence[Fixed] | Tensor | None
    base: Fixed
    ends: Sequence[Fixed]


def couple(q: Tensor, topo: Topology) -> Tensor:
    """q_full ``(..., J)`` of the independent joints ``q (..., n)`` (identity without mimic joints)."""
    if not topo.coupled:
        return q
    idx = topo.tensor("q_index", None, q.device)
    mult = topo.tensor("multiplier", q.dtype, q.device)
    off = topo.tensor("q_offset", q.dtype, q.device)
    return torch.index_select(q, -1, idx) * mult + off


def _base_columns(base: Fixed, like: Tensor, dim: int) -> Columns:
    return apply_fixed(identity_columns(like, dim), base, dim)


def _joint_value(qs: Sequence[Tensor], topo: Topology, j: int, offset):
    q = qs[topo.q_index[j]]
    m, b = topo.multiplier[j], topo.q_offset[j]
    if m != 1.0:
        q = q * m
    if isinstance(offset, Tensor):
        return q + (offset + b if b != 0.0 else offset)
    b = b + (offset or 0.0)
    return q + b if b != 0.0 else q


def column_frames(qs: Sequence[Tensor], topo: Topology, seg: Segments, with_axes: bool = False,
                  keep_frames: bool = False):
    """Batch-last product. ``qs``: the n joint variables, each ``(B,)``; ``seg`` per joint (lists).

    Returns ``(ends, axes, frames)``: ``ends`` the K end frames as columns ``(3, B)`` (or ``(3, 1)`` where
    constant); ``axes`` (if ``with_axes``) a list of J pairs ``(z, p)`` of each joint's motion axis and a
    point on it (the origin of F_parent · Pre_j · M_j); ``frames`` (if ``keep_frames``) the J joint frames.
    Frames no longer needed are dropped, so a serial chain keeps one frame alive at a time.
    """
    J = topo.n_frames
    base = _base_columns(seg.base, qs[0], 0)
    frames: dict[int, Columns] = {}
    kept, axes = [], []
    offsets = seg.offset if seg.offset is not None else [None] * J
    sph = topo.spherical or (False,) * J
    for j in range(J):
        par = topo.parents[j]
        F = apply_fixed(base if par < 0 else frames[par], seg.pre[j] if seg.pre is not None else None, 0)
        if sph[j]:  # F · R(quaternion): three axes through one point
            F = rotate_columns(F, _quaternion_rows(qs, topo.q_index[j]))
            if with_axes:
                axes.extend(((F[0], F[3]), (F[1], F[3]), (F[2], F[3])))
        else:
            F = apply_motion(F, _joint_value(qs, topo, j, offsets[j]), topo.revolute[j])
            if with_axes:  # after the motion: the same point (revolute) or a point on the axis (prismatic)
                axes.append((F[2], F[3]))
        F = apply_fixed(F, seg.post[j] if seg.post is not None else None, 0)
        frames[j] = F
        if keep_frames:
            kept.append(F)
        if par >= 0 and topo.last_use[par] == j:
            del frames[par]
    ends = [apply_fixed(base if e < 0 else frames[e], E, 0) for e, E in zip(topo.ends, seg.ends)]
    return ends, (axes if with_axes else None), (kept if keep_frames else None)


def _quaternion_rows(qs: Sequence[Tensor], start: int) -> Tensor:
    """The rotation matrix ``(3, 3, B)`` of the quaternion in rows ``start .. start + 3`` of batch-last q
    (normalised: the kernel accepts any non-zero quaternion, as MuJoCo does)."""
    Q = torch.stack(tuple(qs[start : start + 4]), dim=-1)
    return _quaternion_to_matrix(stable_normalize(Q)).permute(1, 2, 0)


def spherical_rotations(q: Tensor, topo: Topology) -> Tensor:
    """Per frame the rotation of its S motion ``(..., J, 3, 3)`` from ``q (..., nq)`` (identity on the
    other frames)."""
    Q = q.index_select(-1, topo.tensor("quaternion_index", None, q.device).reshape(-1)).unflatten(-1, (-1, 4))
    mask = topo.tensor("spherical", None, q.device).unsqueeze(-1)
    identity = torch.zeros_like(Q[..., :1, :])
    identity[..., 0] = 1.0
    return _quaternion_to_matrix(stable_normalize(torch.where(mask, Q, identity)))


def matrix_frames(q: Tensor, topo: Topology, seg: Segments, with_axes: bool = False,
                  with_frames: bool = True):
    """Batch-first product of ``q (..., n)`` with stacked segments (tensors ``(J, 4, 4)`` or None).

    Returns ``(ends (..., K, 4, 4), frames (..., J, 4, 4) or None, axes (..., J, 3) or None, origins or
    None)``; ``with_frames=False`` skips stacking the joint frames (FK of the end links only).
    """
    q_full = couple(q, topo)
    if seg.offset is not None:
        q_full = q_full + seg.offset
    if seg.pre is None:
        cols = identity_columns(q, -1)
    else:
        cols = tuple(seg.pre[..., :3, k] for k in range(4))
    # every joint's Pre · M(q) at once (batch first: the joints are one more batch axis; the columns
    # (J, 3) broadcast against q's batch)
    kind = True if all(topo.revolute) else topo.tensor("revolute", None, q.device).unsqueeze(-1)
    if topo.has_spherical:  # S frames: Rz(0) here, then their rotation
        q_full = torch.where(topo.tensor("spherical", None, q.device), torch.zeros_like(q_full), q_full)
    x, y, z, p = apply_motion(cols, q_full.unsqueeze(-1), kind)
    if topo.has_spherical:
        x, y, z, p = rotate_columns((x, y, z, p), spherical_rotations(q, topo), dim=-1)
    PM = stack_columns((x, y, z, p), -1)  # (..., J, 4, 4)
    A = (PM if seg.post is None else PM @ seg.post).unbind(-3)
    batch = q.shape[:-1]
    base = torch.eye(4, dtype=q.dtype, device=q.device) if seg.base is None else seg.base
    base = base.expand(*batch, 4, 4)
    frames = []
    for j in range(topo.n_frames):
        par = topo.parents[j]
        if par < 0:
            frames.append(A[j] if seg.base is None else base @ A[j])  # no product with an identity base
        else:
            frames.append(frames[par] @ A[j])
    ends = []
    for e, E in zip(topo.ends, seg.ends):
        F = base if e < 0 else frames[e]
        ends.append(F if E is None else F @ E)
    F = torch.stack(frames, dim=-3) if with_frames or with_axes else None
    out_axes = out_origins = None
    if with_axes:  # the axis of joint j is the z axis of G_j = F_parent · Pre_j · M_j, through its origin
        if seg.post is None:
            G = F
        else:
            par = topo.tensor("parent_index", None, q.device)
            F_par = torch.cat((base.unsqueeze(-3), F), dim=-3).index_select(-3, par)
            G = F_par @ PM
        out_axes, out_origins = G[..., :3, 2], G[..., :3, 3]
        if topo.has_spherical:  # one axis per Jacobian column: x, y, z of an S frame
            sel = topo.tensor("axis_select", None, q.device)
            out_axes = G[..., :3, :3].transpose(-1, -2).flatten(-3, -2).index_select(-2, sel)
            out_origins = out_origins.index_select(-2, topo.tensor("column_frame", None, q.device))
    return torch.stack(ends, dim=-3), F, out_axes, out_origins
