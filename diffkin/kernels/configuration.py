"""The configuration space: joint kinds (a table) and the manifold operations on q (the only encodings).

A joint of every kind is a short sequence of *elementary motions*, each of which the tree product
(:mod:`diffkin.kernels.tree`) knows how to apply to a frame, in the way Pinocchio and MuJoCo model joints:

* ``"R"``: a rotation about the z axis of the current frame by one angle (1 coordinate, 1 velocity);
* ``"P"``: a translation along that z axis (1 coordinate, 1 velocity);
* ``"S"``: a rotation by a unit quaternion (η, ε) (2.30) (4 coordinates, 3 velocities: the angular
  velocity in the rotated, child frame, as MuJoCo's ball joints).

=============  ====  ====  ==============  ==============================================================
kind           nq    nv    motions         coordinates (MuJoCo's qpos order)
=============  ====  ====  ==============  ==============================================================
revolute       1     1     R               angle (rad), limited
continuous     1     1     R               angle (rad), no limit
prismatic      1     1     P               length (m), limited
planar         3     3     Px Py R         x, y (m) in the plane normal to the axis, then the angle about it
ball           4     3     S               unit quaternion (w, x, y, z)
free           7     6     Px Py Pz S      position (m) in the parent frame, then a unit quaternion
=============  ====  ====  ==============  ==============================================================

The velocity of a free joint is MuJoCo's: the linear velocity in the parent (world) frame, then the angular
velocity in the body frame; a planar joint's is the rate of its coordinates. A kind built from these motions
is one row of :data:`JOINT_KINDS` (:class:`JointKind`: its motions, whether it is limited, its URDF / MuJoCo
type names): the readers lay out its frames from the row (:func:`diffkin.models.description.kind_frames`),
the topology, the native packer and the configuration space see only the motions, the viewer labels its
sliders from it. A new *motion* is a row of :data:`MOTIONS` plus its kernel code (Python and C).

:class:`ConfigurationSpace` is the product of the chain's coordinates: scalars (R and P motions, additive)
and unit quaternions (S motions). ``integrate(q, v)`` = q ⊕ v (MuJoCo's ``mj_integratePos`` with dt = 1:
q_S ← q_S ⊗ exp(ω/2)), ``difference(q0, q1)`` its inverse (``mj_differentiatePos``: the shortest rotation),
``interpolate`` the geodesic (slerp on the quaternions), ``neutral``, ``sample`` (uniform on the sphere),
``normalize``. Every operation is over leading batch dims, differentiable, finite at zero rotation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from .._numerics import broadcast_shapes, safe_norm, sinc, stable_normalize
from .rigid import _canonical, _quaternion_multiply, _quaternion_to_rotvec

__all__ = ["Motion", "MOTIONS", "JointKind", "JOINT_KINDS", "joint_kind", "urdf_kind", "mjcf_kind",
           "MOTION_NQ", "MOTION_NV", "ConfigurationSpace"]

@dataclass(frozen=True)
class Motion:
    """One elementary motion the kernels apply to a frame (module doc): its letter, the coordinates it
    reads from q, the velocities (Jacobian columns) it moves, and whether it rotates the frame."""

    letter: str
    nq: int
    nv: int
    rotation: bool


#: the elementary motions (the native library's ``DK_MOTIONS`` is checked against this table at load)
MOTIONS: dict[str, Motion] = {m.letter: m for m in (
    Motion("R", 1, 1, True),
    Motion("P", 1, 1, False),
    Motion("S", 4, 3, True),
)}
MOTION_NQ = {m.letter: m.nq for m in MOTIONS.values()}
MOTION_NV = {m.letter: m.nv for m in MOTIONS.values()}


@dataclass(frozen=True)
class JointKind:
    """One row of the table, everything the library knows about a kind (readers, topology, native packer,
    viewer and configuration space all read it from here).

    ``motions``: the frames of the joint in order, each an elementary motion letter optionally followed by
    an axis of the joint frame (``"Px"``: a translation along x, in the frame (x, y, z) whose z is the joint
    axis; a bare ``"R"`` / ``"P"`` acts along the file's axis, ``"S"`` is a ball); ``limited``: whether its
    scalar coordinates take the file's position limits; ``urdf`` / ``mjcf``: the joint type names that
    read as this kind in a URDF file / a MuJoCo model (None: not in that format)."""

    name: str
    motions: tuple[str, ...]
    limited: bool
    urdf: str | None = None
    mjcf: str | None = None

    def __post_init__(self):
        for m in self.motions:
            if m[:1] not in MOTIONS or m[1:] not in ("", "x", "y", "z") or (m[0] == "S" and m[1:]):
                raise ValueError(f"joint kind {self.name!r}: a motion is one of {sorted(MOTIONS)} with an "
                                 f"optional axis x, y or z (S: none), got {m!r}")

    @property
    def letters(self) -> tuple[str, ...]:
        """The elementary motion of each frame (``"R"``, ``"P"``, ``"S"``)."""
        return tuple(m[0] for m in self.motions)

    @property
    def axes(self) -> tuple[str | None, ...]:
        """The joint-frame axis of each frame's motion (None: the file's axis, or a ball)."""
        return tuple(m[1:] or None for m in self.motions)

    @property
    def has_axis(self) -> bool:
        """Whether the kind reads a joint axis from the file (some R or P motion acts along it)."""
        return any(m in ("R", "P") for m in self.motions)

    @property
    def nq(self) -> int:
        return sum(MOTION_NQ[m] for m in self.letters)

    @property
    def nv(self) -> int:
        return sum(MOTION_NV[m] for m in self.letters)

    @property
    def q_offsets(self) -> tuple[int, ...]:
        """Where each frame's coordinates start within the joint's ``nq`` entries of q."""
        out, i = [], 0
        for m in self.letters:
            out.append(i)
            i += MOTION_NQ[m]
        return tuple(out)

    def limits(self, lower: float | None, upper: float | None) -> list[list[float]]:
        """The ``(nq, 2)`` rows of q limits from a file's ``lower`` / ``upper`` (None: none): a limited kind
        gives them to its scalar coordinates, everything else is ±inf."""
        free = [-math.inf, math.inf]
        lo = -math.inf if lower is None else lower
        hi = math.inf if upper is None else upper
        rows: list[list[float]] = []
        for m in self.letters:
            scalar = MOTION_NQ[m] == 1
            rows += [[lo, hi] if self.limited and scalar else list(free)] * MOTION_NQ[m]
        return rows

    @property
    def velocity_labels(self) -> tuple[str, ...]:
        """A short label per velocity coordinate (``()`` for a one-coordinate kind: the joint's name is its
        label): a translation its axis, a rotation about the file's axis ``theta``, about a joint-frame axis
        ``r`` + axis, a ball ``rx, ry, rz``."""
        if self.nv == 1:
            return ()
        out: list[str] = []
        for letter, ax in zip(self.letters, self.axes):
            if letter == "S":
                out += ["rx", "ry", "rz"]
            elif letter == "P":
                out.append(ax or "z")
            else:
                out.append(f"r{ax}" if ax else "theta")
        return tuple(out)


JOINT_KINDS: dict[str, JointKind] = {k.name: k for k in (
    JointKind("revolute", ("R",), True, urdf="revolute", mjcf="hinge"),
    JointKind("continuous", ("R",), False, urdf="continuous", mjcf="hinge"),
    JointKind("prismatic", ("P",), True, urdf="prismatic", mjcf="slide"),
    JointKind("planar", ("Px", "Py", "R"), False, urdf="planar"),
    JointKind("ball", ("S",), False, mjcf="ball"),
    JointKind("free", ("Px", "Py", "Pz", "S"), False, urdf="floating", mjcf="free"),
)}


def joint_kind(name: str) -> JointKind:
    """The table entry of a kind name (KeyError-free: an unknown name raises ValueError naming the kinds)."""
    try:
        return JOINT_KINDS[name]
    except KeyError:
        raise ValueError(f"unknown joint kind {name!r}; known: {sorted(JOINT_KINDS)}") from None


def urdf_kind(urdf_type: str) -> JointKind | None:
    """The kind a URDF joint ``type`` reads as (None: ``"fixed"`` or a type no kind claims)."""
    return next((k for k in JOINT_KINDS.values() if k.urdf == urdf_type), None)


def mjcf_kind(mjcf_type: str, limited: bool) -> JointKind:
    """The kind of a MuJoCo joint of type ``mjcf_type`` (``"hinge"``, ``"slide"``, ``"ball"``, ``"free"``):
    of the rows with that type, the one whose ``limited`` matches (a hinge: revolute or continuous), else
    the first."""
    rows = [k for k in JOINT_KINDS.values() if k.mjcf == mjcf_type]
    if not rows:
        raise ValueError(f"no joint kind reads MuJoCo joint type {mjcf_type!r}")
    return next((k for k in rows if k.limited == bool(limited)), rows[0])


def _quaternion_exp(w: Tensor) -> Tensor:
    """exp(ω/2) = (cos(θ/2), sin(θ/2) ω/θ), θ = |ω|: the rotation by the rotation vector ω ``(..., 3)`` ->
    ``(..., 4)``; not made η ≥ 0, so that q ⊕ v is continuous in v beyond θ = π (as MuJoCo's)."""
    theta = safe_norm(w, keepdim=True)
    return torch.cat((torch.cos(0.5 * theta), 0.5 * sinc(0.5 * theta) * w), dim=-1)


class ConfigurationSpace:
    """The chain's independent coordinates as a product of scalars and unit quaternions.

    Built from the motions of the independent coordinates in q order (``motions[i]`` ∈ {R, P, S}); holds
    the index maps from q ``(..., nq)`` and v ``(..., nv)`` to the scalar and quaternion parts.
    """

    def __init__(self, motions: Sequence[str]):
        self.motions = tuple(motions)
        sq, sv, bq, bv = [], [], [], []
        iq = iv = 0
        for m in self.motions:
            if m == "S":
                bq.append(list(range(iq, iq + 4)))
                bv.append(list(range(iv, iv + 3)))
            else:
                sq.append(iq)
                sv.append(iv)
            iq, iv = iq + MOTION_NQ[m], iv + MOTION_NV[m]
        self.nq, self.nv = iq, iv
        self._scalar_q, self._scalar_v = tuple(sq), tuple(sv)
        self._quat_q, self._quat_v = tuple(map(tuple, bq)), tuple(map(tuple, bv))
        self.n_quaternions = len(bq)
        self.euclidean = not bq  # q ⊕ v = q + v: every existing 1-DOF chain
        # the inverse permutation that puts [scalars, quaternion blocks] back into q order (and v order)
        order_q = list(sq) + [i for b in bq for i in b]
        order_v = list(sv) + [i for b in bv for i in b]
        self._unperm_q = tuple(order_q.index(i) for i in range(self.nq))
        self._unperm_v = tuple(order_v.index(i) for i in range(self.nv))
        self._cache: dict = {}

    # ------------------------------------------------------------------------------ index tensors
    def _index(self, name: str, device) -> Tensor:
        key = (name, device)
        t = self._cache.get(key)
        if t is None:
            t = torch.tensor(getattr(self, name), dtype=torch.long, device=device)
            self._cache[key] = t
        return t

    def _split_q(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """``(scalars (..., Ns), quaternions (..., Nb, 4))`` of ``q (..., nq)``."""
        s = q.index_select(-1, self._index("_scalar_q", q.device))
        b = q.index_select(-1, self._index("_quat_q", q.device).reshape(-1)).unflatten(-1, (-1, 4))
        return s, b

    def _split_v(self, v: Tensor) -> tuple[Tensor, Tensor]:
        s = v.index_select(-1, self._index("_scalar_v", v.device))
        b = v.index_select(-1, self._index("_quat_v", v.device).reshape(-1)).unflatten(-1, (-1, 3))
        return s, b

    def _join(self, s: Tensor, b: Tensor, which: str) -> Tensor:
        flat = torch.cat((s, b.flatten(-2)), dim=-1)
        return flat.index_select(-1, self._index(f"_unperm_{which}", flat.device))

    # --------------------------------------------------------------------------------- operations
    def integrate(self, q: Tensor, v: Tensor) -> Tensor:
        """q ⊕ v: scalars q + v, quaternions q ⊗ exp(ω/2) (the angular velocity ω in the child frame, as
        ``mj_integratePos`` with dt = 1). ``(..., nq)``, ``(..., nv)`` -> ``(..., nq)`` (batch dims
        broadcast); the quaternions stay unit (they are normalised first)."""
        if self.euclidean:
            return q + v
        q, v = _broadcast_batch(q, v)
        s, b = self._split_q(q)
        ds, w = self._split_v(v)
        b = _quaternion_multiply(stable_normalize(b), _quaternion_exp(w))
        return self._join(s + ds, b, "q")

    def difference(self, q0: Tensor, q1: Tensor) -> Tensor:
        """v with q0 ⊕ v = q1: scalars q1 − q0, quaternions the rotation vector of q0⁻¹ ⊗ q1 along the
        shortest arc (angle ≤ π, ``mj_differentiatePos``). ``(..., nq)`` twice -> ``(..., nv)``."""
        if self.euclidean:
            return q1 - q0
        q0, q1 = _broadcast_batch(q0, q1)
        s0, b0 = self._split_q(q0)
        s1, b1 = self._split_q(q1)
        b0, b1 = stable_normalize(b0), stable_normalize(b1)
        conj = torch.cat((b0[..., :1], -b0[..., 1:]), dim=-1)
        d = _canonical(_quaternion_multiply(conj, b1))
        return self._join(s1 - s0, _quaternion_to_rotvec(d), "v")

    def interpolate(self, q0: Tensor, q1: Tensor, s: Tensor) -> Tensor:
        """The geodesic q0 ⊕ s·(q1 ⊖ q0): linear on scalars, slerp on quaternions; ``s (...)``."""
        s = torch.as_tensor(s, dtype=q0.dtype, device=q0.device)
        return self.integrate(q0, s.unsqueeze(-1) * self.difference(q0, q1))

    def normalize(self, q: Tensor) -> Tensor:
        """q with its quaternions scaled to unit length (a zero quaternion becomes the identity)."""
        if self.euclidean:
            return q
        s, b = self._split_q(q)
        return self._join(s, stable_normalize(b), "q")

    def neutral(self, dtype=None, device=None) -> Tensor:
        """The neutral configuration ``(nq,)``: zero scalars, identity quaternions (1, 0, 0, 0)."""
        s = torch.zeros(len(self._scalar_q), dtype=dtype, device=device)
        b = torch.zeros(self.n_quaternions, 4, dtype=dtype, device=device)
        b[:, 0] = 1.0
        return self._join(s, b, "q")

    @property
    def n_uniform(self) -> int:
        """Uniform numbers per configuration that :meth:`from_uniform` maps: one per scalar, three per
        quaternion."""
        return len(self._scalar_q) + 3 * self.n_quaternions

    def from_uniform(self, lower: Tensor, upper: Tensor, u: Tensor) -> Tensor:
        """Configurations ``(..., nq)`` from uniforms ``u (..., n_uniform)`` in [0, 1) (the first Ns columns
        for the scalars, then three per quaternion): scalars
        ``lower + (upper - lower) u`` (``(Ns,)``, finite, in scalar order), each quaternion from three
        uniforms by Shoemake's map (uniform on S³, the Haar measure on rotations; η ≥ 0)::

            q = (√(1-u₁) sin 2πu₂, √(1-u₁) cos 2πu₂, √u₁ sin 2πu₃, √u₁ cos 2πu₃)

        The only map from uniform numbers to configurations: seeded, counter-based and file sources of
        uniforms all sample through it."""
        ns = len(self._scalar_q)
        s = lower + (upper - lower) * u[..., :ns]
        if self.euclidean:
            return s
        w = u[..., ns:].reshape(*u.shape[:-1], self.n_quaternions, 3)
        u1, a, b = w.unbind(-1)
        r1, r2 = torch.sqrt((1.0 - u1).clamp_min(0.0)), torch.sqrt(u1.clamp_min(0.0))
        a, b = 2.0 * torch.pi * a, 2.0 * torch.pi * b
        quat = torch.stack((r1 * torch.sin(a), r1 * torch.cos(a), r2 * torch.sin(b), r2 * torch.cos(b)), -1)
        return self._join(s, _canonical(quat), "q")

    def sample(self, lower: Tensor, upper: Tensor, shape: Sequence[int], generator=None) -> Tensor:
        """Random configurations ``(*shape, nq)``: :meth:`from_uniform` of ``torch.rand(*shape, n_uniform)``
        drawn from ``generator`` (on its device; the result on ``lower``'s)."""
        gdev = lower.device if generator is None else generator.device
        u = torch.rand(*shape, self.n_uniform, generator=generator, dtype=lower.dtype, device=gdev)
        return self.from_uniform(lower, upper, u.to(lower.device))

    def tangent_map(self, q: Tensor) -> Tensor:
        """∂(q ⊕ v)/∂v at v = 0, ``(..., nq, nv)``: the identity on scalars, ½ Q ⊗ (0, e_k) on each
        quaternion Q (how a velocity moves q; its transpose pulls a gradient w.r.t. q back to v)."""
        eye = torch.eye(self.nv, dtype=q.dtype, device=q.device)
        if self.euclidean:
            return eye.expand(*q.shape[:-1], self.nv, self.nv)
        M = q.new_zeros(*q.shape[:-1], self.nq, self.nv)
        M[..., list(self._scalar_q), list(self._scalar_v)] = 1.0
        pure = torch.cat((torch.zeros_like(eye[:3, :1]), eye[:3, :3]), dim=-1)  # (0, e_k) as rows (3, 4)
        for iq, iv in zip(self._quat_q, self._quat_v):
            Q = stable_normalize(q[..., list(iq)]).unsqueeze(-2)  # (..., 1, 4)
            cols = 0.5 * _quaternion_multiply(Q, pure)  # (..., 3, 4): ½ Q ⊗ (0, e_k)
            M[..., iq[0]:iq[0] + 4, iv[0]:iv[0] + 3] = cols.transpose(-1, -2)
        return M

    def pullback(self, q: Tensor, g: Tensor) -> Tensor:
        """A gradient w.r.t. q ``(..., nq)`` as one w.r.t. v ``(..., nv)`` (the transposed tangent map)."""
        if self.euclidean:
            return g
        return (g.unsqueeze(-2) @ self.tangent_map(q)).squeeze(-2)

    def scalar_index(self, which: str = "q") -> tuple[int, ...]:
        """Positions of the scalar coordinates in q (``"q"``) or v (``"v"``)."""
        return self._scalar_q if which == "q" else self._scalar_v

    def quaternion_index(self, which: str = "q") -> tuple[tuple[int, ...], ...]:
        """The four q positions (``"q"``) or three v positions (``"v"``) of each quaternion."""
        return self._quat_q if which == "q" else self._quat_v


def _broadcast_batch(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    batch = broadcast_shapes(a.shape[:-1], b.shape[:-1])
    return a.expand(*batch, a.shape[-1]), b.expand(*batch, b.shape[-1])
