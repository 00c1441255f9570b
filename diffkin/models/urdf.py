"""URDF chains and trees: the one kinematic model with URDF joint origins and axes as parameters.

:func:`from_urdf` reads a URDF (:mod:`diffkin.models.urdf_xml` validates it) and builds a
:class:`URDFChain` from the root (or ``root_link``) to one end link or to a list of K end links (a tree whose
shared joints are computed once). Every joint on the way keeps its ``<origin>`` as learnable ``xyz`` / ``rpy``
rows (fixed joints too), every moving joint its axis; :meth:`URDFChain.to_urdf` writes them back into the
source text. ``<mimic>`` joints follow their leader and are not variables.

Joint j of the model is the general joint of :mod:`diffkin.kernels.joints`: Pre_j = O_f1 ··· O_fm · O_j · S_j
(the origins of the fixed joints since the previous moving joint, its own origin, and the rotation S_j taking
e_z to its axis), a motion about z, Post_j = S_jᵀ; end link k adds the origins of the fixed joints after
its last moving joint. Without gradients w.r.t. the geometry all of these are evaluated once in float64 and
applied as constants (zero terms skipped): real URDFs' fixed rotations are mostly signed permutations.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..errors import ModelError
from ..kernels.configuration import JointKind, joint_kind, urdf_kind
from ..kernels.joints import axis_alignment, origin_transform, pose_correction
from ..rotations import _matrix_to_euler
from ..transforms import _make_transform
from ..validation import check_end_links
from .description import BodyInertia, FrameSpec, TreeChain, TreeDescription, kind_frames
from .urdf_xml import JointSpec, URDFTree, parse_inertials, parse_urdf, write_urdf

__all__ = ["URDFChain", "from_urdf"]


def _kind(j: JointSpec) -> JointKind:
    """The joint kind of a moving joint's URDF type (the ``urdf`` column of the kinds table)."""
    kind = urdf_kind(j.type)
    if kind is None:
        raise ModelError(f"joint {j.name!r}: type {j.type!r} does not move")
    return kind


def _moving(j: JointSpec) -> bool:
    # a <mimic> on a fixed joint (talos_reduced's grippers) does not make it move
    return urdf_kind(j.type) is not None


def _leader(tree: URDFTree, j: JointSpec) -> tuple[JointSpec, float, float]:
    """The independent joint driving ``j`` and the composed (multiplier, offset): q_j = m q_leader + b."""
    m, b, seen = 1.0, 0.0, {j.name}
    while j.mimic is not None:
        name, mult, off = j.mimic
        lead = tree.joint(name)
        if lead.name in seen or not _moving(lead):
            raise ModelError(f"joint {j.name!r}: mimic leader {name!r} is fixed or part of a mimic cycle")
        seen.add(lead.name)
        m, b = m * mult, m * off + b  # q = m (mult q_lead + off) + b
        j = lead
    return j, m, b


def _describe(tree: URDFTree, ends: list[str], root_link: str | None,
              floating_base: bool) -> tuple[TreeDescription, dict]:
    """The format-neutral description of the tree from ``root_link`` to the end links, and the URDF facts
    the chain keeps (element rows of its parameters, link frames)."""
    paths = [tree.path(e, root_link) for e in ends]
    used: list[JointSpec] = []  # every joint on the paths, in topological order (union of the paths)
    for path in paths:
        for j in path:
            if j not in used:
                used.append(j)
    moving = [j for j in used if _moving(j)]
    if not moving and not floating_base:
        raise ModelError(f"no moving joint between {root_link or tree.root!r} and {ends}")
    variables: list[JointSpec] = []
    couplings = []
    for j in moving:
        lead, m, b = _leader(tree, j)
        if _kind(lead).nq != 1 and (lead is not j or j.mimic is not None):
            raise ModelError(f"joint {j.name!r}: a {lead.type} joint cannot take part in a mimic")
        if lead not in variables:
            variables.append(lead)
        couplings.append((lead, m, b))
    slot, nq = {}, 7 if floating_base else 0
    for v in variables:
        slot[v.name] = nq
        nq += _kind(v).nq
    index = {j.name: i for i, j in enumerate(used)}
    axis_joints = [j for j in moving if _kind(j).has_axis]
    axis_row = {j.name: i for i, j in enumerate(axis_joints)}
    frames: list[FrameSpec] = []
    last_frame: dict[str, int] = {}  # joint name -> its last frame
    if floating_base:  # a free joint at the root: x, y, z along the root frame's axes, then a ball
        frames += kind_frames(joint_kind("free"), -1, 0, 0)
    root_frame = len(frames) - 1

    def last_moving(path: list[JointSpec]) -> int:
        return max((last_frame[j.name] for j in path if _moving(j)), default=root_frame)

    for j, (lead, m, b) in zip(moving, couplings):
        path = next(p for p in paths if j in p)
        k = path.index(j)
        start = max((i + 1 for i, s in enumerate(path[:k]) if _moving(s)), default=0)
        origins = [("O", index[s.name]) for s in path[start : k + 1]]
        parent, q0 = last_moving(path[:k]), slot[lead.name]
        kind = _kind(j)  # the joint frame: its origin, then (a kind with an axis) e_z turned onto the axis
        axis = [("A", axis_row[j.name])] if kind.has_axis else []
        axis_t = [("At", axis_row[j.name])] if kind.has_axis else []
        frames += kind_frames(kind, parent, len(frames), q0, origins + axis, axis_t, m, b)
        last_frame[j.name] = len(frames) - 1

    limits = joint_kind("free").limits(None, None) if floating_base else []
    for v in variables:
        limits += _kind(v).limits(v.lower, v.upper)
    end_factors = []
    for path in paths:
        start = max((i + 1 for i, s in enumerate(path) if _moving(s)), default=0)
        end_factors.append([("O", index[s.name]) for s in path[start:]])
    axes = torch.tensor([j.axis for j in axis_joints], dtype=torch.float64).reshape(-1, 3)
    description = TreeDescription(
        tree.name, frames, [last_moving(p) for p in paths], end_factors, nq, limits,
        ["floating_base"] * floating_base + [v.name for v in variables],
        ["free"] * floating_base + [_kind(v).name for v in variables],
        parameters={"origin_xyz": torch.tensor([j.xyz for j in used], dtype=torch.float64).reshape(-1, 3),
                    "origin_rpy": torch.tensor([j.rpy for j in used], dtype=torch.float64).reshape(-1, 3),
                    "axis": axes / torch.linalg.vector_norm(axes, dim=-1, keepdim=True)},
        # origin_delta: optional local corrections (L, 6) (translation, rotation vector), origin · Δ(δ),
        # singularity-free where rpy is at gimbal lock; None by default, set by calibration, folded in by
        # fold_origins
        buffers={"_axis_flip": axes[:, 2] < 0, "origin_delta": None})
    root = root_link or tree.root
    link_frame = {root: root_frame + 1, **{j.child: last_frame[j.name] + 1 for j in moving}}
    description.inertias, description.inertia_note = _inertias(tree, link_frame)
    facts = {"root_link": root, "link_frame": link_frame,
             "frame_joint_names": [j.name for j in axis_joints], "link_names": [j.child for j in axis_joints],
             "joint_origin_names": [j.name for j in used]}
    return description, facts


def _inertias(tree: URDFTree, link_frame: dict[str, int]) -> tuple[list[BodyInertia] | None, str]:
    """The ``<inertial>`` of every link below the root link, attached to the frame of the nearest link that
    moves with one (``link_frame``: index in ``all_frames``, 0 the base): the joint origins on the way
    (fixed joints, and joints outside the chain at zero) times the inertial origin, in float64."""
    specs = parse_inertials(tree)
    if not specs:
        return None, f"URDF {tree.name!r} has no <inertial> element"
    out = []
    for link in tree.links:
        spec = specs.get(link)
        if spec is None or spec.mass <= 0.0:
            continue
        T = origin_transform(torch.tensor(spec.xyz, dtype=torch.float64),
                             torch.tensor(spec.rpy, dtype=torch.float64))
        at, inside = link, True
        while at not in link_frame:  # up to the nearest link with a frame (the root link at the latest)
            j = tree._by_child.get(at)
            if j is None:  # above the root link: not part of the chain's model
                inside = False
                break
            T = origin_transform(torch.tensor(j.xyz, dtype=torch.float64),
                                 torch.tensor(j.rpy, dtype=torch.float64)) @ T
            at = j.parent
        if inside:
            out.append(BodyInertia(link, link_frame[at] - 1, spec.mass, tuple(map(tuple, T.tolist()))))
    if not out:
        return None, f"no link of URDF {tree.name!r} below the root link has a positive <inertial> mass"
    return out, ""


class URDFChain(TreeChain):
    """A URDF robot from a root link to one or several end links (a tree), with learnable geometry (frozen
    unless ``learnable=True`` or ``requires_grad_()``).

    Parameters: ``origin_xyz``, ``origin_rpy`` ``(L, 3)`` — the ``<origin>`` of every joint on the paths
    (``joint_origin_names`` labels the rows) — and ``axis`` ``(J, 3)``, the axis of every revolute,
    continuous, prismatic and planar joint (``frame_joint_names``; kept unit length inside the kernel), plus
    the base/tool corrections of :class:`~diffkin.chain.KinematicChain`. The tree itself is the
    :class:`~diffkin.models.description.TreeDescription` the URDF reader makes (``description``).

    Attributes: ``joint_names`` (the n independent joints, the order of q's last axis), ``frame_joint_names``
    and ``link_names`` (the J moving joints in topological order, mimic followers included, and their child
    links: frames 1..J of ``forward_kinematics(q, all_frames=True)``, except that for a single end link the
    last frame is the end-link pose, with the fixed joints after the last moving joint and the tool applied),
    ``end_links``, ``root_link``.
    """

    def __init__(self, tree: URDFTree, end_links: str | list[str], root_link: str | None = None, *,
                 dtype: torch.dtype | None = None, device=None, floating_base: bool = False,
                 learnable: bool = False):
        single, ends = check_end_links(end_links, "link")
        description, facts = _describe(tree, ends, root_link, floating_base)
        super().__init__(description, dtype=dtype, device=device, single_end=single, learnable=learnable)
        self.tree = tree
        self.end_links = ends
        self.root_link = facts["root_link"]
        self.floating_base = floating_base
        #: the index in ``forward_kinematics(q, all_frames=True)`` of each link that moves with a frame: the
        #: root link (0, or the free joint's last frame with ``floating_base``) and every moving joint's child
        self.link_frame = facts["link_frame"]
        self.frame_joint_names = facts["frame_joint_names"]
        self.link_names = facts["link_names"]
        self.joint_origin_names = facts["joint_origin_names"]

    def _origins(self):
        O = origin_transform(self.origin_xyz, self.origin_rpy)  # (L, 4, 4)
        return O if self.origin_delta is None else O @ pose_correction(self.origin_delta)

    def fold_origins(self) -> None:
        """Fold ``origin_delta`` (if set) into ``origin_xyz`` / ``origin_rpy`` and clear it (same FK)."""
        if self.origin_delta is None:
            return
        with torch.no_grad():
            O = self._origins().double()
            rpy = _matrix_to_euler(O[..., :3, :3], "RPY").flip(-1)
            self.origin_xyz.copy_(O[..., :3, 3].to(self.origin_xyz.dtype))
            self.origin_rpy.copy_(rpy.to(self.origin_rpy.dtype))
        self.origin_delta = None

    def _factors(self, eye):
        S = axis_alignment(self.axis, self._axis_flip)
        zero = torch.zeros_like(self.axis)
        return {"O": self._origins().unbind(0), "A": _make_transform(S, zero).unbind(0),
                "At": _make_transform(S.transpose(-1, -2), zero).unbind(0)}

    # ------------------------------------------------------------------------------------- helpers
    def velocity_limits(self) -> Tensor | None:
        """The joint velocity limits ``(nq,)`` of the URDF's ``<limit velocity=>`` (rad/s, m/s), in the
        chain's dtype and device, in ``joint_names`` order; None when a joint has none (or the chain has a
        joint of several coordinates, whose URDF carries no per-coordinate limit)."""
        v = [self.tree.joint(n).velocity if n in self.tree._by_name else None for n in self.joint_names]
        if len(v) != self.nq or any(x is None for x in v):
            return None
        return torch.tensor(v, dtype=self.dtype, device=self.device)

    def to_urdf(self, path=None) -> str:
        """The source URDF with this chain's current joint origins and axes written in; everything else in
        the file (visuals, collisions, inertials, transmissions, comments) is kept byte for byte. Also
        written to ``path`` if given; returns the text. ``from_urdf`` of it gives the same FK.

        A base transform is folded into the origins of the joints leaving the root link; a tool transform
        into the origin of the fixed joint that ends each path (a ModelError if a path ends with a moving
        joint: a URDF has no place for a tool there).
        """
        with torch.no_grad():
            O = self._origins().double().cpu()
        origins = dict(zip(self.joint_origin_names, O.unbind(0)))
        base, tool = self.base, self.tool
        if base is not None:
            B = base.detach().double().cpu()
            for j in self.tree.children(self.root_link):
                T = origins.get(j.name)
                if T is None:
                    T = origin_transform(torch.tensor(j.xyz, dtype=torch.float64),
                                         torch.tensor(j.rpy, dtype=torch.float64))
                origins[j.name] = B @ T
        if tool is not None:
            for end in self.end_links:
                last = self.tree.parent_joint(end)
                if last is None or _moving(last):
                    raise ModelError(f"to_urdf: the tool transform cannot be written: end link {end!r} is "
                                     "moved by a joint, not attached by a fixed one")
                origins[last.name] = origins[last.name] @ tool.detach().double().cpu()
        written = {}
        for name, T in origins.items():
            rpy = _matrix_to_euler(T[:3, :3], "RPY").flip(-1)
            written[name] = (T[:3, 3].tolist(), rpy.tolist())
        axis = self.axis.detach().double().cpu().tolist()
        axes = dict(zip(self.frame_joint_names, axis))
        return write_urdf(self.tree, written, path, axes=axes)

    def extra_repr(self) -> str:
        ends = self.end_links[0] if self._single_end else self.end_links
        return super().extra_repr() + f", end_link={ends!r}, joints={self.joint_names}"


def from_urdf(source, end_link: str | list[str], *, root_link: str | None = None,
              dtype: torch.dtype | None = None, device=None, floating_base: bool = False,
              learnable: bool = False) -> URDFChain:
    """A :class:`URDFChain` from a URDF file path, XML text (str or bytes; an XML encoding declaration is
    fine) or a parsed :class:`~diffkin.models.urdf_xml.URDFTree`, from ``root_link`` (default: the tree's
    root) to ``end_link`` — a link name, or a list of K link names for a tree whose FK is ``(..., K, 4, 4)``
    and Jacobian ``(..., K, 6, nv)`` in that order.

    Revolute, continuous (no joint limit: IK wraps them) and prismatic joints move; ``floating`` joints are
    free joints (q: position, then a unit quaternion (w, x, y, z); v: linear velocity in the joint's parent
    frame, angular velocity in the child frame, as MuJoCo's) and ``planar`` joints three coordinates (x, y
    in the plane normal to the axis, then the angle about it); fixed joints keep their origin as
    parameters; ``<mimic>`` joints follow their leader (on any branch) and are not variables.
    ``floating_base=True`` puts a free joint at the root (q starts with its seven coordinates; a humanoid's
    pelvis in the world). The geometry is frozen unless ``learnable=True`` (see
    :class:`~diffkin.chain.KinematicChain`). Raises :class:`~diffkin.errors.ModelError` naming the joint or
    link for invalid files (missing links, a link with two parents, duplicate names, loops) or an unknown
    link.
    """
    tree = source if isinstance(source, URDFTree) else parse_urdf(source)
    return URDFChain(tree, end_link, root_link, dtype=dtype or torch.get_default_dtype(), device=device,
                     floating_base=floating_base, learnable=learnable)
