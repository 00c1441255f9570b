"""A format-neutral kinematic tree (§2.8 on a tree): what the URDF and MJCF readers produce, what
:class:`TreeChain` turns into the one learnable model.

A tree is a list of frames, each one elementary motion of :mod:`diffkin.kernels.configuration` (R: about
z, P: along z, S: a unit quaternion) between two fixed transforms, A_j(q) = Pre_j · M(q) · Post_j, with
its parent frame, the entry of q it reads and a linear coupling (mimic joints, MuJoCo joint equalities).
Pre and Post are products of named *factors* (``("O", 3)``: row 3 of factor table O), so the
description says which geometry enters where without saying how a file parametrises it; the reader adds
the learnable parameter tables and one function from them to the factor tables
(:meth:`TreeChain._factors`). The translation axes ``"C"`` / ``"Ct"`` (e_z to e_x, e_y, e_z; free and planar
joints) are always in the table.

Data flows one way: ``file -> reader -> TreeDescription -> TreeChain`` (URDF: :mod:`diffkin.models.urdf`,
MJCF: :mod:`diffkin.models.mjcf`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from ..chain import KinematicChain
from ..errors import ModelError
from ..kernels.configuration import MOTIONS, JointKind
from ..kernels.joints import compose_factors, translation_axes
from ..kernels.tree import Topology

__all__ = ["FrameSpec", "kind_frames", "BodyInertia", "TreeDescription", "TreeChain"]

Factor = tuple[str, object]  # (factor table name, row index or axis name)


@dataclass(frozen=True)
class FrameSpec:
    """One frame of the tree product: ``motion`` ``"R"``, ``"P"`` or ``"S"`` after ``pre`` and before
    ``post`` (factor lists), child of frame ``parent`` (−1: the base), reading ``q[q_index]`` (an S motion
    reads ``q[q_index : q_index + 4]``) as ``multiplier · q + q_offset``, plus ``offset`` inside the motion
    (MuJoCo's −ref of a hinge or slide)."""

    motion: str
    parent: int
    pre: tuple[Factor, ...] = ()
    post: tuple[Factor, ...] = ()
    q_index: int = 0
    multiplier: float = 1.0
    q_offset: float = 0.0
    offset: float = 0.0

    def __post_init__(self):
        if self.motion not in MOTIONS:
            raise ModelError(f"a frame's motion is one of {sorted(MOTIONS)}, got {self.motion!r}")


def kind_frames(kind: JointKind, parent: int, start: int, q_index: int, pre: Sequence[Factor] = (),
                post: Sequence[Factor] = (), multiplier: float = 1.0, q_offset: float = 0.0,
                offset: float = 0.0) -> list[FrameSpec]:
    """The frames of one joint of ``kind`` (a row of :data:`~diffkin.kernels.configuration.JOINT_KINDS`),
    the only place a kind becomes frames: one per motion of the row, chained from ``parent``, numbered
    from ``start`` (the index the first will have), reading q from ``q_index`` on (each frame at its
    :attr:`~diffkin.kernels.configuration.JointKind.q_offsets`). ``pre`` (the factors into the joint
    frame: origin, and the axis rotation A for a kind with an axis) goes before the first motion, ``post``
    after the last; a motion along a joint-frame axis ``a`` sits between ``("C", a)`` and ``("Ct", a)``
    (e_z to e_a and back). ``multiplier`` / ``q_offset`` (mimic) and ``offset`` apply to every frame."""
    frames, n = [], len(kind.motions)
    for i, (letter, ax, dq) in enumerate(zip(kind.letters, kind.axes, kind.q_offsets)):
        f_pre = (tuple(pre) if i == 0 else ()) + ((("C", ax),) if ax else ())
        f_post = ((("Ct", ax),) if ax else ()) + (tuple(post) if i == n - 1 else ())
        frames.append(FrameSpec(letter, parent if i == 0 else start + i - 1, f_pre, f_post, q_index + dq,
                                multiplier, q_offset, offset))
    return frames


@dataclass(frozen=True)
class BodyInertia:
    """The mass of one body of the model and its inertial frame: ``mass`` (kg) on the body called ``name``,
    moving with tree frame ``frame`` (−1: the base); ``pose`` the inertial frame in that frame's coordinates
    (a ``(4, 4)`` nested tuple of floats: its translation is the body's centre of mass). Bodies fixed to a
    moving one (merged fixed joints, bodies beyond the chain's joints) carry the fixed transforms between
    them in ``pose``."""

    name: str
    frame: int
    mass: float
    pose: tuple[tuple[float, ...], ...]


@dataclass
class TreeDescription:
    """A kinematic tree from a base to K end links, independent of the file format.

    ``frames`` in topological order; ``ends[k]`` the last frame at or above end link k (−1: the base) and
    ``end_factors[k]`` the fixed factors after it; ``nq`` the size of q; ``limits`` ``(nq, 2)`` (±inf: none);
    ``joint_names`` / ``joint_kinds`` the independent joints in q's order (kinds of
    :data:`diffkin.kernels.configuration.JOINT_KINDS`); ``parameters`` the learnable geometry
    (float64 tensors, registered as ``nn.Parameter`` s of those names), ``buffers`` fixed tensors the factor
    map reads; ``name`` the model's name; ``inertias`` the mass and inertial frame of every body of the model
    below the base (:class:`BodyInertia`, massless bodies left out), or None where the file says nothing
    about masses (``inertia_note`` then says why, for the error of
    :meth:`~diffkin.chain.KinematicChain.center_of_mass`; with masses, it names the bodies whose masses are
    approximate, for a warning).
    """

    name: str
    frames: list[FrameSpec]
    ends: list[int]
    end_factors: list[list[Factor]]
    nq: int
    limits: list[list[float]]
    joint_names: list[str]
    joint_kinds: list[str]
    parameters: dict[str, Tensor] = field(default_factory=dict)
    buffers: dict[str, Tensor | None] = field(default_factory=dict)
    inertias: list[BodyInertia] | None = None
    inertia_note: str = ""

    def topology(self) -> Topology:
        """The tree structure the kernels run on (:class:`~diffkin.kernels.tree.Topology`)."""
        f = self.frames
        return Topology(tuple(x.parent for x in f), tuple(x.motion for x in f), tuple(self.ends),
                        tuple(x.q_index for x in f), tuple(x.multiplier for x in f),
                        tuple(x.q_offset for x in f), self.nq)


class TreeChain(KinematicChain):
    """The learnable model of a :class:`TreeDescription`: its parameters as ``nn.Parameter`` s (frozen
    unless ``learnable=True``), its frames
    evaluated by the kernels. Subclasses (:class:`~diffkin.models.URDFChain`,
    :class:`~diffkin.models.MJCFChain`) only implement :meth:`_factors`: how their parameters map to the
    factor tables the description names."""

    def __init__(self, description: TreeDescription, *, dtype: torch.dtype | None = None, device=None,
                 single_end: bool = True, learnable: bool = False):
        super().__init__(description.topology(), q_limits=description.limits, name=description.name,
                         dtype=dtype, device=device, single_end=single_end, learnable=learnable)
        dt, dev = self.dtype, self.device
        for key, value in description.parameters.items():
            setattr(self, key, nn.Parameter(value.to(dtype=dt, device=dev), requires_grad=learnable))
        for key, value in description.buffers.items():
            floating = value is not None and value.is_floating_point()
            self.register_buffer(key, None if value is None else value.to(dtype=dt if floating else None,
                                                                         device=dev))
        offsets = [fr.offset for fr in description.frames]
        self._has_offsets = any(o != 0.0 for o in offsets)
        # not saved: the description remakes it (a state dict holds the parameters and learned buffers)
        self.register_buffer("_offsets", torch.tensor(offsets, dtype=dt, device=dev), persistent=False)
        #: the tree this chain evaluates (its parameters' initial values included)
        self.description = description
        self.joint_names = list(description.joint_names)
        self.joint_kinds = list(description.joint_kinds)
        self._pre = [list(fr.pre) for fr in description.frames]
        self._post = [list(fr.post) for fr in description.frames]
        self._end_factors = [list(e) for e in description.end_factors]
        self._set_inertias(description)

    def _set_inertias(self, description: TreeDescription) -> None:
        """The masses as buffers of the chain (dtype and device follow it; not saved: the source has them):
        ``link_masses (B,)``, ``link_inertial_frames (B, 4, 4)`` (in the frame each body moves with),
        ``mass_names``; None / [] when the model has no masses (``_mass_note`` says why)."""
        inertias = description.inertias or []
        dt, dev = self.dtype, self.device
        self.mass_names = [b.name for b in inertias]
        self._mass_frames = [b.frame for b in inertias]
        self._mass_note = description.inertia_note
        masses = poses = None
        if inertias:
            masses = torch.tensor([b.mass for b in inertias], dtype=torch.float64)
            poses = torch.tensor([b.pose for b in inertias], dtype=torch.float64)
        for key, value in (("link_masses", masses), ("link_inertial_frames", poses)):
            self.register_buffer(key, None if value is None else value.to(dtype=dt, device=dev),
                                 persistent=False)

    def _factors(self, eye: Tensor) -> dict[str, Sequence[Tensor]]:
        """The factor tables ``name -> rows of (4, 4)`` from the parameters, differentiable (``eye``: the
        identity in the parameters' dtype and device)."""
        raise NotImplementedError

    def _geometry(self):
        eye = torch.eye(4, dtype=self.dtype, device=self.device)
        C, Ct = translation_axes(eye)
        table = {"C": C, "Ct": Ct, **self._factors(eye)}
        pre = torch.stack(compose_factors(table, self._pre, eye))
        post = torch.stack(compose_factors(table, self._post, eye))
        ends = [E if r else None for E, r in zip(compose_factors(table, self._end_factors, eye),
                                                  self._end_factors)]
        return pre, (self._offsets if self._has_offsets else None), post, ends
