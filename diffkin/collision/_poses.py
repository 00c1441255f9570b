"""Poses of every link of a chain, links behind fixed joints included (private; the model will own this).

The chain's ``forward_kinematics(q, all_frames=True)`` gives the base and the child link of every moving
joint; a link attached by fixed joints is that frame times the fixed origins down to it. The fixed origins
on the chain's paths are the chain's ``origin_xyz`` / ``origin_rpy`` rows (differentiable); those off the
paths (e.g. a link hanging off the arm by a fixed joint) are constants from the tree.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import reduce

import torch
from torch import Tensor

from ..kernels import cache, native
from ..kernels.joints import origin_transform
from ..kernels.tree import Segments
from ..models.urdf_xml import moves
from ..validation import check_finite

__all__ = ["LinkFrames"]


@dataclass(frozen=True)
class _Plan:
    anchor: tuple[int, ...]  # per link: index into all_frames (0 = base / root link)
    rows: tuple[tuple[tuple[str, int], ...], ...]  # per link: fixed origins, ("chain"|"const", index)
    const: Tensor  # (C, 4, 4) float64 origins of fixed joints off the chain's paths


class LinkFrames:
    """Which links of a :class:`~diffkin.models.urdf.URDFChain` have a pose, and how to compute them.

    ``links`` lists them: the root link, the child link of every moving joint of the chain, and every link
    hanging below those by fixed joints only (links behind moving joints the chain does not model are
    left out). ``bodies[i]`` is the rigid body of link i (the moving-joint frame it is welded to).
    """

    def __init__(self, chain):
        tree = chain.tree
        frame_of = chain.link_frame  # the all_frames index of each moving link (multi-frame joints too)
        chain_row = {name: i for i, name in enumerate(chain.joint_origin_names)}
        links, anchor, rows, const = [], [], [], []
        stack = [(chain.root_link, frame_of[chain.root_link], ())]
        while stack:  # depth first from the root through the chain's moving joints and all fixed joints
            link, a, fixed = stack.pop()
            links.append(link)
            anchor.append(a)
            rows.append(fixed)
            for j in reversed(tree.children(link)):
                if moves(j.type):
                    if j.child in frame_of:
                        stack.append((j.child, frame_of[j.child], ()))
                elif j.type == "fixed":
                    if j.name in chain_row:
                        row = ("chain", chain_row[j.name])
                    else:
                        row = ("const", len(const))
                        const.append(origin_transform(torch.tensor(j.xyz, dtype=torch.float64),
                                                      torch.tensor(j.rpy, dtype=torch.float64)))
                    stack.append((j.child, a, (*fixed, row)))
        self.links = links
        self.index = {k: i for i, k in enumerate(links)}
        self.bodies = anchor
        c = torch.stack(const) if const else torch.zeros(0, 4, 4, dtype=torch.float64)
        self._plan = _Plan(tuple(anchor), tuple(rows), c)
        self._last = self._last_frame_fix(chain)

    @staticmethod
    def _last_frame_fix(chain):
        """For a single-end chain whose last frame is the end-link pose (tail and tool applied), the origin
        rows of that tail: the last moving link is recovered as T_end · (E · tool)⁻¹."""
        topo = chain._topo
        if chain._single_end and topo.ends[0] == topo.n_frames - 1:
            return tuple(i for _, i in chain._end_factors[0])
        return None

    def offsets(self, chain, dtype: torch.dtype, device) -> Tensor:
        """``(L, 4, 4)``: each link's pose in its anchor frame (differentiable in the chain's origins)."""
        O = chain._origins()
        const = self._plan.const.to(dtype=dtype, device=device)
        eye = torch.eye(4, dtype=dtype, device=device)
        mats = [reduce(torch.matmul, [O[i] if kind == "chain" else const[i] for kind, i in rows], eye)
                for rows in self._plan.rows]
        return torch.stack(mats)

    def frames(self, chain, q: Tensor) -> Tensor:
        """``(..., J + 1, 4, 4)``: the base and the child link of every moving joint (never the tool)."""
        F = self._native_frames(chain, q)
        if F is not None:
            return F
        F = chain.forward_kinematics(q, all_frames=True)
        if self._last is None:
            return F
        O = chain._origins()
        E = reduce(torch.matmul, [O[i] for i in self._last], torch.eye(4, dtype=F.dtype, device=F.device))
        tool = chain.tool
        M = E if tool is None else E @ tool
        Minv = torch.cat((torch.cat((M[:3, :3].T, -M[:3, :3].T @ M[:3, 3:]), 1), M[3:]), 0)
        return torch.cat((F[..., :-1, :, :], F[..., -1:, :, :] @ Minv), -3)

    def _native_frames(self, chain, q: Tensor) -> Tensor | None:
        """:meth:`frames` from one call of the fused C FK (:mod:`diffkin.kernels.native`) where it serves
        ``q`` (CPU, no gradient, a chain of 1-DOF joints without mimic couplings): the chain's constants
        with every joint frame as an end link (no end transform, so the last frame is the joint's own).
        None elsewhere (the torch kernels)."""
        made = self.native_frames_model(chain, q)
        if made is None:
            return None
        packed, B = made
        batch, n = q.shape[:-1], q.shape[-1]
        T, _, bad = native.fk_jacobian(packed, q.reshape(-1, n).contiguous())
        if bad:
            check_finite(q, "q")
        F = torch.cat((B.expand(T.shape[0], 1, 4, 4), T), 1)
        return F.reshape(*batch, *F.shape[1:])

    def native_frames_model(self, chain, q: Tensor):
        """``(NativeModel, base (4, 4))`` of :meth:`_native_frames` where the fused C FK serves ``q``: the
        chain's constants with every joint frame as an end link (frames 1.. of :meth:`frames`; frame 0 is
        ``base``); None elsewhere. The planner's C search places its geoms with it."""
        if chain._topo.coupled or any(chain._topo.spherical) or chain._native_model(q) is None:
            return None
        data = cache.current(chain)  # the Data _native_model has just checked; the pack is kept on it
        seg, stacked = data.segments(chain)

        def make():
            topo = dataclasses.replace(chain._topo, ends=tuple(range(chain._topo.n_frames)))
            return native.NativeModel(topo, Segments(seg.pre, seg.offset, seg.post, seg.base,
                                                     [None] * topo.n_frames))

        packed = data.derived("all_frames", make)
        B = torch.eye(4, dtype=q.dtype) if stacked.base is None else stacked.base.to(q.dtype)
        return packed, B

    def poses(self, chain, q: Tensor) -> Tensor:
        """``(..., L, 4, 4)``: the pose of every link of ``links`` in the base frame of the chain's world."""
        F = self.frames(chain, q)
        anchor = torch.tensor(self._plan.anchor, device=F.device)
        return F.index_select(-3, anchor) @ self.offsets(chain, F.dtype, F.device)

