"""Measurement model of kinematic calibration (§2.11): parameter vector ζ, batched FK, Φ̄ (2.85)–(2.87).

The full parameter vector of a chain with ``n`` joints has ``P = 4n + 12`` entries, always in this order::

    ζ = [a_1..a_n, alpha_1..alpha_n, d_1..d_n, theta_1..theta_n,        the book's [a; α; d; ϑ]  (2.86)
         base_x, base_y, base_z, base_rx, base_ry, base_rz,             T_b = T_b,nom · Δ(base)
         tool_x, tool_y, tool_z, tool_rx, tool_ry, tool_rz]             T_t = T_t,nom · Δ(tool)

with Δ(v) = [[R(v_r), v_t], [0, 1]] (translation in metres, rotation vector in radians, both expressed in the
nominal base / tool frame). Row ``i`` of a modified-DH chain holds (a_{i-1}, α_{i-1}, d_i, ϑ_i) as in
:class:`~diffkin.chain.DHChain`. A subset of ζ, the *candidate* mask, is estimated; the rest stays nominal.

The pose residual of one measurement is ``Δx = [p_m - p(ζ); w · rotvec(R_m R(ζ)^T)]`` in the base frame,
where ``w`` (``orientation_weight``, metres per radian) weighs radians against metres: with w = 0.1 m/rad an
orientation error of 1 mrad counts like 0.1 mm of position error. Position-only measurements drop the
last three rows.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from .._numerics import broadcast_shapes
from ..chain import DHChain
from ..errors import ModelError, ShapeError
from ..kernels.jacobian import twist_of_derivative
from ..kernels.joints import dh_joints, pose_correction
from ..kernels.pose_error import pose_error as _pose_error
from ..kernels.tree import Segments, Topology, matrix_frames
from ..transforms import as_measured_transform
from ..validation import shape_str, tensors

__all__ = ["CalibrationModel", "ForwardModeMatrix", "parameter_jacobian", "parameter_names", "DH_KINDS",
           "POSE_AXES"]

DH_KINDS = ("a", "alpha", "d", "theta")
POSE_AXES = ("x", "y", "z", "rx", "ry", "rz")


def learnable_like(chain, source) -> None:
    """Give a calibrated ``chain`` the learnability of its nominal ``source``, parameter by parameter (a
    parameter the source lacks, e.g. an added β, follows the source's :attr:`learnable`). Calibration works
    on ζ, never on the chain's ``requires_grad``: a frozen chain (the default) calibrates, and so does a
    learnable one; what comes back is as learnable as what went in."""
    own = dict(source.named_parameters())
    for key, p in chain.named_parameters():
        p.requires_grad_(own[key].requires_grad if key in own else source.learnable)


def parameter_names(n: int) -> tuple[str, ...]:
    """Names of the full ζ of an ``n``-joint chain: ``a1.., alpha1.., d1.., theta1.., base_x.., tool_x..``."""
    dh = [f"{k}{i + 1}" for k in DH_KINDS for i in range(n)]
    return tuple(dh + [f"base_{s}" for s in POSE_AXES] + [f"tool_{s}" for s in POSE_AXES])


def _frames_to_matrix(x: Tensor, y: Tensor, z: Tensor, p: Tensor) -> Tensor:
    """Columns (..., 3) each -> homogeneous (..., 4, 4)."""
    top = torch.stack(torch.broadcast_tensors(x, y, z, p), dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat((top, bottom), dim=-2)


def _dh_frames(a, alpha, d, theta, q, revolute, convention, base):
    """Frames 0..n as columns ``(x, y, z, p)`` with batched DH parameters, by the kernel layer's DH joints
    and chain product (one encoding of (2.52) / Craig's matrix with the chains).

    ``a, alpha, d, theta`` are ``(..., n)`` and broadcast against ``q (..., n)``; ``base`` is ``(..., 4, 4)``
    broadcastable to ``q.shape[:-1]``. Returns a list of ``n + 1`` tuples of ``(..., 3)`` tensors.
    """
    pre, offset, post = dh_joints(a, alpha, d, theta, revolute, convention == "modified")
    topo = Topology.serial(["R" if r > 0 else "P" for r in revolute.tolist()])
    _, F, _, _ = matrix_frames(q, topo, Segments(pre, offset, post, base, [None]))
    mats = [base.expand(*F.shape[:-3], 4, 4), *F.unbind(-3)]
    return [(T[..., :3, 0], T[..., :3, 1], T[..., :3, 2], T[..., :3, 3]) for T in mats]


def _as_selection(parameters, n: int, joint_types: str, base: bool, tool: bool, joint_offsets: bool):
    names = parameter_names(n)
    index = {nm: j for j, nm in enumerate(names)}
    mask = [False] * len(names)
    if isinstance(parameters, str):
        parameters = DH_KINDS if parameters == "all" else (parameters,)
    for item in parameters:
        if item in DH_KINDS:
            k = DH_KINDS.index(item)
            for i in range(n):
                mask[k * n + i] = True
        elif item in index:
            mask[index[item]] = True
        else:
            raise ModelError(
                f"unknown calibration parameter {item!r}; use 'all', a kind {DH_KINDS} or a name "
                f"such as 'a2', 'theta3', 'base_z', 'tool_rx'"
            )
    for i, jt in enumerate(joint_types):  # encoder zero: theta of revolute, d of prismatic joints
        mask[(3 if jt == "R" else 2) * n + i] = bool(joint_offsets)
    for j in range(6):
        mask[4 * n + j] = mask[4 * n + j] or base
        mask[4 * n + 6 + j] = mask[4 * n + 6 + j] or tool
    return torch.tensor(mask, device="cpu")


@contextlib.contextmanager
def quiet_forward_mode():
    """Silence, here only, torch's ``torch.jit.script is deprecated`` DeprecationWarning, which its own
    forward-mode decompositions raise inside ``torch.func.jacfwd``: the user did not call jit and can do
    nothing about it (every other warning passes)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r".*torch\.jit\.script.*deprecated",
                                category=DeprecationWarning)
        yield


def parameter_jacobian(f, theta: Tensor, x: Tensor, n_params: int, columns: Tensor | None) -> Tensor:
    """Forward-mode derivative of a measurement function ``f(theta (P,), x (N, ...)) -> (N, ...)`` with
    respect to the selected entries of θ (``columns``: bool ``(P,)``, default all), vectorised over K
    robots: ``theta (K, P)``, ``x (K, N, ...)`` -> ``(K, N, ..., C)`` (the models of measurements other than
    poses: pixels, contact distances)."""
    cols = torch.ones(n_params, dtype=torch.bool, device="cpu") if columns is None else columns.cpu()
    idx = cols.nonzero().flatten().to(theta.device)

    def shifted(delta, z, xk):
        return f(z.index_add(0, idx, delta), xk)

    def one(z, xk):
        return torch.func.jacfwd(shifted)(z.new_zeros(idx.numel()), z, xk)

    with quiet_forward_mode():
        if theta.shape[0] == 1:  # one robot: vmap's overhead on a chain's many small operations is the cost
            return one(theta[0], x[0])[None]
        return torch.func.vmap(one)(theta, x)


class ParameterLayout:
    """The solvers' view of a model's parameter vector θ: ``n_params`` (one per entry of ``names``),
    ``dtype`` (``nominal``'s) and ``is_length()`` (``(P,)`` bool: the entries in metres, from the ``_length``
    mask the model builds), shared by the error models the solvers of :mod:`.solvers` take."""

    @property
    def n_params(self) -> int:
        return len(self.names)

    @property
    def dtype(self) -> torch.dtype:
        return self.nominal.dtype

    def is_length(self) -> Tensor:
        return self._length.to(self.nominal.device)


class ForwardModeMatrix:
    """The calibration matrix Φ (2.86) of every error model, by forward-mode differentiation of the one FK
    kernel (what :meth:`~diffkin.chain.KinematicChain.parameter_jacobian` does), vectorised over K robots
    with ``torch.func``. A model provides ``n_params``, ``forward_kinematics(zeta (K, P), q (K, N, n))`` and
    ``_fk_one(zeta (P,), q (N, n))``."""

    def calibration_matrix(self, zeta: Tensor, q: Tensor, position_only: bool, orientation_weight: float,
                           columns: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Φ ``(K, N, m, C)``, m = 6 or 3: column j is the base-frame twist [δp; w δω] of the end effector
        per unit change of the j-th selected entry of ζ (``columns``: bool ``(P,)``, default all), so that
        ζ' = ζ + Δζ (2.89) is exact to first order; and the poses ``(K, N, 4, 4)``. ``zeta (P,)`` with
        ``q (N, n)`` gives ``(N, m, C)`` and ``(N, 4, 4)``."""
        cols = torch.ones(self.n_params, dtype=torch.bool, device="cpu") if columns is None else columns.cpu()
        idx = cols.nonzero().flatten().to(zeta.device)
        squeeze = zeta.ndim == 1
        Z, Q = (zeta[None], q[None]) if squeeze else (zeta, q)

        def fk_delta(delta: Tensor, z: Tensor, qk: Tensor) -> Tensor:
            return self._fk_one(z.index_add(0, idx, delta), qk)

        def one(z: Tensor, qk: Tensor):
            delta = z.new_zeros(idx.numel())
            return torch.func.jacfwd(fk_delta)(delta, z, qk)

        with torch.no_grad():
            T = self.forward_kinematics(Z, Q)
        with quiet_forward_mode():
            dT = torch.func.vmap(one)(Z, Q)  # (K, N, 4, 4, C)
        Phi = twist_of_derivative(dT, T)
        if position_only:
            Phi = Phi[..., :3, :]
        else:
            Phi = torch.cat((Phi[..., :3, :], orientation_weight * Phi[..., 3:, :]), dim=-2)
        if squeeze:
            Phi, T = Phi[0], T[0]
        return Phi, T

    def residual_of(self, prediction: Tensor, measured: Tensor, orientation_weight: float) -> Tensor:
        """Δx of the prediction :meth:`calibration_matrix` returns beside Φ (the poses) against the
        measurements: :func:`pose_residual` (a model of other measurements, e.g. pixels, overrides it)."""
        return pose_residual(prediction, measured, orientation_weight)


@dataclass(frozen=True, eq=False)
class CalibrationModel(ForwardModeMatrix):
    """Parameterised DH kinematics of one chain structure for ``K`` robots (or one shared nominal).

    Attributes: ``nominal`` ζ_n ``(..., P)`` with ``...`` = ``()`` or ``(K,)``; ``base_nominal`` and
    ``tool_nominal`` ``(..., 4, 4)``; ``candidate`` ``(P,)`` bool, the parameters to estimate; ``names``.
    Build it with :meth:`from_chains`.
    """

    n: int
    joint_types: str
    convention: str
    revolute: Tensor
    nominal: Tensor
    base_nominal: Tensor
    tool_nominal: Tensor
    candidate: Tensor
    names: tuple[str, ...]
    chains: tuple[DHChain, ...]

    @classmethod
    def from_chains(
        cls,
        chains: DHChain | Sequence[DHChain],
        parameters: str | Iterable[str] = "all",
        base: bool = False,
        tool: bool = False,
        joint_offsets: bool = True,
    ) -> CalibrationModel:
        """Model of one nominal chain (batch ``()``) or of ``K`` nominal chains of equal structure (``(K,)``).

        ``parameters``: ``"all"`` (every a, α, d, ϑ), or an iterable of kinds (``"a"``, ``"alpha"``, ``"d"``,
        ``"theta"``) and/or names (``"a2"``, ``"base_z"``). ``joint_offsets`` adds (True) or removes (False)
        the encoder zero offsets ϑ_i (revolute) / d_i (prismatic); ``base`` / ``tool`` add the six pose
        corrections of the base / tool frame.
        """
        single = isinstance(chains, DHChain)
        chains = (chains,) if single else tuple(chains)
        if not chains or not all(isinstance(c, DHChain) for c in chains):
            raise ModelError("calibration needs a DHChain (or a non-empty sequence of DHChains)")
        ref = chains[0]
        for c in chains[1:]:
            if (c.n_joints, c.joint_types, c.convention, c.dtype) != (
                ref.n_joints,
                ref.joint_types,
                ref.convention,
                ref.dtype,
            ):
                raise ModelError(
                    "all nominal chains of a batch must share n_joints, joint_types, convention "
                    f"and dtype; '{c.name}' differs from '{ref.name}'"
                )
        dtype, device = ref.dtype, ref.device
        eye = torch.eye(4, dtype=dtype, device=device)
        zeros = torch.zeros(12, dtype=dtype, device=device)
        nominal = torch.stack([torch.cat((c.dh_table().T.reshape(-1), zeros)) for c in chains])
        base_nom = torch.stack([eye if c.base is None else c.base.detach() for c in chains])
        tool_nom = torch.stack([eye if c.tool is None else c.tool.detach() for c in chains])
        if single:
            nominal, base_nom, tool_nom = nominal[0], base_nom[0], tool_nom[0]
        cand = _as_selection(parameters, ref.n_joints, ref.joint_types, base, tool, joint_offsets).to(device)
        return cls(
            ref.n_joints,
            ref.joint_types,
            ref.convention,
            ref.revolute_mask.detach(),
            nominal,
            base_nom,
            tool_nom,
            cand,
            parameter_names(ref.n_joints),
            chains,
        )

    # ------------------------------------------------------------------------------------ layout
    @property
    def n_params(self) -> int:
        return 4 * self.n + 12

    @property
    def dtype(self) -> torch.dtype:
        return self.nominal.dtype

    def is_length(self) -> Tensor:
        """``(P,)`` bool: parameters in metres (a, d, base/tool translations); the others are radians."""
        n = self.n
        m = torch.zeros(self.n_params, dtype=torch.bool, device=self.nominal.device)
        m[:n] = m[2 * n : 3 * n] = True
        m[4 * n : 4 * n + 3] = m[4 * n + 6 : 4 * n + 9] = True
        return m

    def base_tool(self, zeta: Tensor) -> tuple[Tensor, Tensor]:
        """Base and tool transforms ``(..., 4, 4)`` of parameters ``zeta (..., P)``."""
        n4 = 4 * self.n
        base = self.base_nominal @ pose_correction(zeta[..., n4 : n4 + 6])
        tool = self.tool_nominal @ pose_correction(zeta[..., n4 + 6 :])
        return base, tool

    def _frames(self, zeta: Tensor, q: Tensor):
        n = self.n
        base, tool = self.base_tool(zeta)
        z = zeta[..., None, :]  # broadcast over the N poses
        a, alpha, d, theta = (z[..., k * n : (k + 1) * n] for k in range(4))
        frames = _dh_frames(a, alpha, d, theta, q, self.revolute, self.convention, base[..., None, :, :])
        T_flange = _frames_to_matrix(*frames[-1])
        return frames, T_flange @ tool[..., None, :, :], base

    # ----------------------------------------------------------------------------- kinematics
    def forward_kinematics(self, zeta: Tensor, q: Tensor) -> Tensor:
        """End-effector poses ``(..., N, 4, 4)`` of ``zeta (..., P)`` at joints ``q (..., N, n)``."""
        return self._frames(zeta, q)[1]

    def residual(self, zeta: Tensor, q: Tensor, measured: Tensor, orientation_weight: float) -> Tensor:
        """Δx = x_m - k(ζ) per pose ``(..., N, 6)`` (``(..., N, 3)`` for positions ``(..., N, 3)``)."""
        T = self.forward_kinematics(zeta, q)
        return pose_residual(T, measured, orientation_weight)

    def _fk_one(self, zeta: Tensor, q: Tensor) -> Tensor:
        """Poses ``(N, 4, 4)`` of one robot's ``zeta (P,)`` at ``q (N, n)`` (:class:`ForwardModeMatrix`)."""
        return self.forward_kinematics(zeta, q)

    # ---------------------------------------------------------------------------------- chains
    def to_chain(self, zeta: Tensor, index: int = 0) -> DHChain:
        """A new :class:`DHChain` with the DH table, base and tool of ``zeta (P,)``; limits, name: nominal."""
        return self.to_chains(zeta[None], first=index)[0]

    def to_chains(self, zeta: Tensor, first: int = 0) -> list[DHChain]:
        """One new :class:`DHChain` per row of ``zeta (K, P)`` (row k uses nominal chain ``first + k``)."""
        z = zeta.detach()
        n, n4 = self.n, 4 * self.n
        base_used = bool(self.candidate[n4 : n4 + 6].any())
        tool_used = bool(self.candidate[n4 + 6 :].any())
        base, tool = self.base_tool(z) if base_used or tool_used else (None, None)
        out = []
        for k in range(z.shape[0]):
            ref = self.chains[min(first + k, len(self.chains) - 1)]
            out.append(
                DHChain(
                    z[k, :n].clone(),
                    z[k, n : 2 * n].clone(),
                    z[k, 2 * n : 3 * n].clone(),
                    z[k, 3 * n : n4].clone(),
                    joint_types=self.joint_types,
                    convention=self.convention,
                    base=base[k] if base_used else ref.base,
                    tool=tool[k] if tool_used else ref.tool,
                    q_limits=ref.q_limits,
                    name=ref.name,
                )
            )
            learnable_like(out[-1], ref)
        return out


def pose_residual(T: Tensor, measured: Tensor, orientation_weight: float) -> Tensor:
    """[p_m - p; w rotvec(R_m R^T)] ``(..., 6)``, or ``p_m - p`` ``(..., 3)`` for ``measured (..., 3)``."""
    if measured.shape[-1] == 3 and measured.ndim == T.ndim - 1:
        return measured - T[..., :3, 3]
    R_m, R = measured[..., :3, :3], T[..., :3, :3]
    e_p, e_o, _ = _pose_error(measured[..., :3, 3], R_m, T[..., :3, 3], R, "rotvec")
    e_p, e_o = torch.broadcast_tensors(e_p, e_o)
    return torch.cat((e_p, orientation_weight * e_o), dim=-1)


def check_measurements(q, measured, n: int, like, batch: tuple[int, ...] = ()) -> tuple[Tensor, Tensor, bool]:
    """Validate joints ``q (*batch, N, n)`` and poses ``(*batch, N, 4, 4)`` / positions ``(*batch, N, 3)`` by
    the rule of :mod:`diffkin.validation` (tensors of ``like``'s dtype and device; numbers, sequences and
    numpy arrays converted to it; finite), with N >= 1 poses.

    Returns ``(q, T, position_only)``, detached, with the rotation blocks of T re-orthonormalised
    (deviations up to 1e-3 accepted, :data:`~diffkin.transforms.RIGIDITY_TOLERANCE`). Raises ShapeError /
    DTypeError / NonFiniteError / DiffkinError.
    """
    q, measured = tensors(("q", q, None), ("T", measured, None), like=like)
    # data, not variables: joint readings from a network carry its graph, which the fit must not backward
    # through (the gradient method's closure calls backward once per step); calibration_loss stays
    # differentiable in q for pipelines that want that
    q, measured = q.detach(), measured.detach()
    position_only = measurement_shapes(q, measured, n, batch)
    if not position_only:
        measured = as_measured_transform(measured, "T")  # the one rigidity rule, re-orthonormalised
    return q, measured, position_only


def measurement_shapes(q: Tensor, T: Tensor, n: int, batch: tuple[int, ...] | None = ()) -> bool:
    """Check the shapes of ``q (*batch, N, n)`` and ``T (*batch, N, 4, 4)`` or ``(*batch, N, 3)``, N >= 1
    (``batch=None``: any leading dims, as many in T as in q, broadcasting). Returns True for positions."""
    lead = "..., " if batch is None else "".join(f"{b}, " for b in batch)
    k = q.ndim - 2 if batch is None else len(batch)
    if q.ndim < 2 or q.ndim != k + 2 or q.shape[-1] != n or (
        batch is not None and tuple(q.shape[:k]) != tuple(batch)
    ):
        raise ShapeError(f"expected q of shape ({lead}N, {n}), got {shape_str(q.shape)}")
    N = q.shape[-2]
    position_only = T.ndim == q.ndim and T.shape[-1] == 3
    if not position_only and (T.ndim != q.ndim + 1 or T.shape[-2:] != (4, 4)):
        raise ShapeError(
            f"expected measured poses T of shape ({lead}N, 4, 4) or positions ({lead}N, 3) with N = {N} as "
            f"in q {shape_str(q.shape)}, got {shape_str(T.shape)}"
        )
    if T.shape[k] != N:
        raise ShapeError(
            f"q holds {N} joint vectors but T holds {T.shape[k]} measurements "
            f"(q {shape_str(q.shape)}, T {shape_str(T.shape)})"
        )
    if batch is None:
        try:
            broadcast_shapes(q.shape[:k], T.shape[:k])
        except RuntimeError:
            raise ShapeError(
                f"the batch dims of q {shape_str(q.shape)} and T {shape_str(T.shape)} do not broadcast"
            ) from None
    elif tuple(T.shape[:k]) != tuple(batch):
        raise ShapeError(f"expected T of shape ({lead}{N}, ...), got {shape_str(T.shape)}")
    if N < 1:
        raise ShapeError(
            f"calibration needs at least 1 measured pose (N >= 1), got q of shape {shape_str(q.shape)}"
        )
    return position_only
