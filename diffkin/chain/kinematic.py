"""The learnable kinematic model (§2.8): :class:`KinematicChain`, the model of :mod:`diffkin.chain` (its
parameters, buffers and topology: construction, configuration space, base and tool, checks, limits); its
evaluations (FK, Jacobians, the constant fast paths and their dispatch) are in
:mod:`diffkin.chain.evaluation`."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from ..errors import DTypeError, ModelError, NonFiniteError, OptionError, ShapeError
from ..kernels import cache
from ..kernels.configuration import MOTION_NQ, ConfigurationSpace
from ..kernels.joints import pose_correction
from ..kernels.tree import Topology
from ..transforms import as_rigid_transform
from ..validation import as_tensor, broadcast_batch, check_finite, check_given, shape_str, tensors
from .evaluation import ChainEvaluation, _is_plain, _zero_correction

__all__ = ["KinematicChain"]


def _check_learnable(learnable) -> None:
    if not isinstance(learnable, bool):
        raise OptionError(f"learnable must be True or False, got {learnable!r}")
def _limits_inward(lim: Tensor, dtype: torch.dtype) -> Tensor:
    """Joint limits ``(n, 2)`` in ``dtype``, rounded inwards (lower up, upper down) where ``dtype`` is
    coarser than ``lim``'s: every q of ``dtype`` within the result is within the given limits too, so
    ``within_limits`` / ``clamp_to_limits`` / IK's ``success`` in float32 hold for the float64 limits of a
    URDF or MJCF (rounding to the nearest float32 could put a limit 1e-7 rad outside). ±inf stays; a range
    narrower than one step of ``dtype`` keeps the nearest values."""
    out = lim.to(dtype)
    if torch.finfo(dtype).eps <= torch.finfo(lim.dtype).eps or out.numel() == 0:
        return out
    lo, hi = out[..., 0], out[..., 1]
    up = torch.full_like(lo, math.inf)
    lo_in = torch.where(lo.to(lim.dtype) < lim[..., 0], torch.nextafter(lo, up), lo)
    hi_in = torch.where(hi.to(lim.dtype) > lim[..., 1], torch.nextafter(hi, -up), hi)
    keep = lo_in <= hi_in
    return torch.stack((torch.where(keep, lo_in, lo), torch.where(keep, hi_in, hi)), dim=-1)


class KinematicChain(ChainEvaluation, nn.Module):
    """A tree of one-DOF joints from a base to K end links; ``n`` independent joint variables.

    Geometry is frozen by default: every ``nn.Parameter`` of a chain (DH table, URDF / MJCF origins and
    axes, base and tool corrections) has ``requires_grad=False``, so results carry no autograd graph unless
    ``q`` asks for one. ``learnable=True`` (on every constructor and loader) or ``chain.requires_grad_()``
    makes the geometry trainable (gradients w.r.t. it, optimisers over ``chain.parameters()``);
    :attr:`learnable` says whether any of it is.

    Shapes: ``q`` is ``(..., n)``; poses are ``(..., 4, 4)`` for a chain with one end link (``K = 1``, made
    from a single end-link name), ``(..., K, 4, 4)`` for one made from a list of end links; Jacobians
    ``(..., 6, n)`` / ``(..., K, 6, n)``. Joint i's motion is about the z axis of its frame
    F_parent · Pre_i (:mod:`diffkin.kernels.joints`).

    Subclasses set the topology (:meth:`_set_topology`) and implement :meth:`_geometry`.
    """

    n_joints: int
    joint_types: str
    #: batches with at most this many configurations use the batch-first matrix path (less overhead)
    small_batch: int = 16
    #: model data (YAML ``home`` / ``planar``, :mod:`diffkin.models.io`): a comfortable start configuration
    #: (``nq`` floats, or None when the model names none) and whether the arm moves in its base x-y plane
    home: list[float] | None = None
    planar: bool = False

    def __init__(self, topology: Topology, q_limits=None, name: str | None = None, *,
                 dtype: torch.dtype | None = None, device=None, single_end: bool = True,
                 learnable: bool = False):
        super().__init__()
        _check_learnable(learnable)
        dtype = dtype or torch.get_default_dtype()
        if not dtype.is_floating_point or dtype not in (torch.float32, torch.float64):
            raise DTypeError(f"a chain's dtype must be torch.float32 or torch.float64, got {dtype}")
        self._set_topology(topology, single_end)
        n = topology.n_vars
        self.name = name or f"chain{n}"
        # one letter per coordinate of q: R (angle), P (length), S (an entry of a unit quaternion)
        self.joint_types = "".join(m * MOTION_NQ[m] for m in topology.motions)
        var_rev = [c == "R" for c in self.joint_types]
        self.register_buffer("revolute_mask", torch.tensor(var_rev, dtype=dtype, device=device))
        #: per Jacobian column (before the mimic coupling): 1 for a rotation, 0 for a translation
        self.register_buffer("_joint_revolute", torch.tensor(topology.column_revolute, dtype=dtype,
                                                             device=device))
        self.register_buffer("q_limits", None)
        self.register_buffer("base_nominal", None)
        self.register_buffer("tool_nominal", None)
        self.base_delta = nn.Parameter(torch.zeros(6, dtype=dtype, device=device), requires_grad=learnable)
        self.tool_delta = nn.Parameter(torch.zeros(6, dtype=dtype, device=device), requires_grad=learnable)
        if q_limits is not None:
            from ..validation import check_fits_dtype  # (local: this block is its only user here)

            lim = check_fits_dtype(q_limits.detach() if isinstance(q_limits, Tensor) else q_limits, dtype,
                                   "q_limits")
            # read in the precision they were given in (numbers: float64), then rounded inwards to dtype
            lim = as_tensor(lim, "q_limits", dtype=None if isinstance(lim, Tensor) else torch.float64)
            if lim.shape != (n, 2):
                raise ModelError(f"q_limits must have shape ({n}, 2), got {shape_str(lim.shape)}")
            lim = _limits_inward(lim, dtype).to(device=device).clone()
            # ±inf marks a joint without limit (a URDF continuous joint); NaN is never a limit
            if bool(torch.isnan(lim).any()) or not bool((lim[:, 0] < lim[:, 1]).all()) or \
                    bool(torch.isinf(lim[:, 0]).logical_and(lim[:, 0] > 0).any()):
                bad = [i for i, (lo, hi) in enumerate(lim.tolist()) if not lo < hi]
                raise ModelError(f"q_limits must have lower < upper (±inf: no limit); joints {bad} do not")
            self.q_limits = lim
        self._compiled_fk = None
        #: free-text model information (description, source, notes) from YAML, kept by to_dict()
        self.metadata: dict[str, str] = {}

    def _apply(self, fn, recurse=True):
        """``.to()`` / ``.float()`` / ``.double()``: as nn.Module, with the joint limits rounded inwards when
        the chain leaves float64 (see :func:`_limits_inward`), never to the nearest float32."""
        before = self.q_limits
        out = super()._apply(fn, recurse)
        after = self.q_limits
        if before is not None and after is not None and after.dtype != before.dtype:
            self.q_limits = _limits_inward(before, after.dtype).to(after.device)
        return out

    def _set_topology(self, topology: Topology, single_end: bool) -> None:
        if single_end and len(topology.ends) != 1:
            raise ModelError("a single-end chain needs exactly one end link")
        self._topo = topology
        self.n_joints = topology.n_vars
        self._single_end = single_end
        self.configuration_space = ConfigurationSpace(topology.motions)

    # --------------------------------------------------------------------------- configuration space
    @property
    def nq(self) -> int:
        """Size of a configuration q (MuJoCo's qpos of the chain's joints; a quaternion counts four)."""
        return self._topo.nq

    @property
    def nv(self) -> int:
        """Size of a velocity and of the Jacobian's columns (a ball joint counts three)."""
        return self._topo.nv

    def integrate(self, q: Tensor, v: Tensor) -> Tensor:
        """q ⊕ v ``(..., nq)`` for ``q (..., nq)`` and ``v (..., nv)``: additive on angles and lengths,
        q ⊗ exp(ω/2) on the quaternions of ball and free joints (MuJoCo's ``mj_integratePos``, dt = 1);
        see :mod:`diffkin.kernels.configuration`."""
        q = self.check_q(q)
        (v,) = tensors(("v", v, (self.nv,)), like=self)
        return self.configuration_space.integrate(q, v)

    def difference(self, q0: Tensor, q1: Tensor) -> Tensor:
        """v ``(..., nv)`` with q0 ⊕ v = q1 (``mj_differentiatePos``: the shortest rotation)."""
        return self.configuration_space.difference(self.check_q(q0, "q0"), self.check_q(q1, "q1"))

    def interpolate(self, q0: Tensor, q1: Tensor, s) -> Tensor:
        """The geodesic between two configurations at ``s (...)`` ∈ [0, 1]: linear on angles and lengths,
        slerp on quaternions; ``q0, q1 (..., nq)`` -> ``(..., nq)``.

        ``s`` follows the rule of :mod:`diffkin.validation` (a number, sequence, array or float tensor of the
        chain's dtype and device; finite: :class:`~diffkin.errors.NonFiniteError`; complex, bool or text:
        :class:`~diffkin.errors.DTypeError`); its shape is a batch shape that must broadcast with those of
        q0 and q1 (:class:`~diffkin.errors.ShapeError`). Values outside [0, 1] extrapolate along the geodesic.
        """
        q0, q1 = self.check_q(q0, "q0"), self.check_q(q1, "q1")
        (s,) = tensors(("s", check_given(s, "s", "interpolation parameters (...)"), None), like=self)
        broadcast_batch(("q0", q0, 1), ("q1", q1, 1), ("s", s, 0))
        return self.configuration_space.interpolate(q0, q1, s)

    def neutral_configuration(self) -> Tensor:
        """The neutral configuration ``(nq,)``: zeros, and identity quaternions (1, 0, 0, 0)."""
        return self.configuration_space.neutral(self.dtype, self.device)

    def normalize_configuration(self, q: Tensor) -> Tensor:
        """``q`` with the quaternions of its ball and free joints scaled to unit length."""
        return self.configuration_space.normalize(self.check_q(q))

    # ------------------------------------------------------------------------------- base and tool
    def _set_base_tool(self, base, tool) -> None:
        self.base, self.tool = base, tool

    def _fixed_pose(self, which: str, skip_zero: bool = True) -> Tensor | None:
        """Base or tool for the kernels: the nominal alone while its correction is zero and needs no
        gradient (checked once per parameter update), else nominal · Δ(delta)."""
        nominal, delta = getattr(self, f"{which}_nominal"), getattr(self, f"{which}_delta")
        if skip_zero and not (torch.is_grad_enabled() and delta.requires_grad) and \
                self._delta_is_zero(which, delta):
            return nominal
        if skip_zero and self._delta_is_zero(which, delta):
            D = _zero_correction(delta)  # Δ(0) = I with Δ's exact first derivative, few operations
        else:
            D = pose_correction(delta)
        return D if nominal is None else nominal @ D

    def _delta_is_zero(self, which: str, delta: Tensor) -> bool:
        """Whether the correction is exactly zero: one host read per state of the chain (kept on its
        :class:`~diffkin.kernels.cache.Data`, so a write through ``.data`` is seen too)."""
        if not _is_plain(delta):
            return False
        data = cache.current(self, grad=False)
        if data is None:
            return False
        zero = data.zero.get(which)
        if zero is None:
            zero = data.zero[which] = not bool(delta.detach().any())
        return zero

    def _fixed_transform(self, T, name: str) -> Tensor:
        """A base or tool ``(4, 4)`` by the rule (the chain's dtype and device), checked rigid."""
        (T,) = tensors((name, T, (4, 4)), like=self)
        if T.ndim != 2:
            raise ShapeError(f"expected {name} of shape (4, 4), got {shape_str(T.shape)}")
        return as_rigid_transform(T.detach(), name, self.dtype, self.device)

    def _pose_property(self, which: str) -> Tensor | None:
        nominal, delta = getattr(self, f"{which}_nominal"), getattr(self, f"{which}_delta")
        if self._delta_is_zero(which, delta):
            return nominal
        D = pose_correction(delta)
        return D if nominal is None else nominal @ D

    @property
    def base(self) -> Tensor | None:
        """The base transform T^b_0 ``(4, 4)`` (nominal · Δ(base_delta)), or None for the identity."""
        return self._pose_property("base")

    @base.setter
    def base(self, T) -> None:
        self.base_nominal = None if T is None else self._fixed_transform(T, "base")
        with torch.no_grad():
            self.base_delta.zero_()

    @property
    def tool(self) -> Tensor | None:
        """The tool transform T^n_e ``(4, 4)`` applied at every end link, or None for the identity."""
        return self._pose_property("tool")

    @tool.setter
    def tool(self, T) -> None:
        self.tool_nominal = None if T is None else self._fixed_transform(T, "tool")
        with torch.no_grad():
            self.tool_delta.zero_()

    # ----------------------------------------------------------------------------------- geometry
    def _geometry(self) -> tuple[Tensor | None, Tensor | None, Tensor | None, list[Tensor | None]]:
        """``(Pre (J, 4, 4) | None, offset (J,) | None, Post (J, 4, 4) | None, ends [K × (4, 4) | None])``
        from the parameters, differentiable (base and tool are added by the caller)."""
        raise NotImplementedError

    # ----------------------------------------------------------------------------------------- checks
    @property
    def dtype(self) -> torch.dtype:
        return self.revolute_mask.dtype

    @property
    def device(self) -> torch.device:
        return self.revolute_mask.device

    @property
    def n_ends(self) -> int:
        """K, the number of end links."""
        return len(self._topo.ends)

    @property
    def single_end(self) -> bool:
        """True for a chain made from one end-link name: poses ``(..., 4, 4)``, not ``(..., K, 4, 4)``."""
        return self._single_end

    @property
    def topology(self) -> Topology:
        """The tree structure (parents, joint kinds, end links, mimic couplings) as Python constants."""
        return self._topo

    def check_q(self, q, name: str = "q", finite: bool = True) -> Tensor:
        """Joint values ``(..., n)`` for this chain by the rule of :mod:`diffkin.validation`: a float tensor
        of the chain's dtype and device, or numbers / sequences / numpy arrays (converted to them); exact
        trailing size n (a 0-d value for a one-joint chain); finite (unless ``finite=False``). Returns the
        tensor. A tensor already of the chain's dtype, device and size costs one reduction (the finiteness
        check of :func:`~diffkin.validation.check_finite`)."""
        n = self.n_joints
        fast = isinstance(q, Tensor) and q.dtype == self.dtype and q.device == self.device and q.ndim > 0 \
            and q.shape[-1] == n
        if not fast:
            check_given(q, name, f"joint values (..., {n})")
            (q,) = tensors((name, q, None), like=self, finite=False)
            if q.ndim == 0 and n == 1:  # one joint: a 0-d value is its q
                q = q.reshape(1)
            if q.ndim == 0 or q.shape[-1] != n:
                raise ShapeError(f"expected {name} of shape (..., {n}) for chain '{self.name}', "
                                 f"got {shape_str(q.shape)}")
        return check_finite(q, name) if finite else q

    def _out(self, T: Tensor) -> Tensor:
        """Drop the end-link axis ``(..., K, ...)`` of a single-end chain."""
        return T.squeeze(-3) if self._single_end else T

    def compile_fk(self, **kwargs) -> KinematicChain:
        """Opt-in fast path: FK through ``torch.compile`` (kwargs passed on), for batches above
        :attr:`small_batch`. The first call compiles (tens of seconds on a small CPU); ``dynamic=True`` by
        default so later batch sizes reuse it. :meth:`uncompile_fk` drops it. (``chain.compile()`` is
        ``nn.Module.compile``, torch's: it compiles the module's ``forward``.)"""
        kwargs.setdefault("dynamic", True)
        fn = torch.compile(self._functional_fk, **kwargs)
        n = self.n_joints

        def fast(q: Tensor) -> Tensor:  # batch-last, contiguous joint rows: unit-stride loads in the kernel
            T = fn(q.reshape(-1, n).transpose(0, 1).contiguous())
            return self._out(T.reshape(*q.shape[:-1], self.n_ends, 4, 4))

        self._compiled_fk = fast
        return self

    def uncompile_fk(self) -> KinematicChain:
        """Drop the compiled fast path of :meth:`compile_fk`."""
        self._compiled_fk = None
        return self

    # ------------------------------------------------------------------------------- Jacobians (§3)
    def geometric_jacobian(self, q: Tensor, **kwargs) -> Tensor:
        """Geometric Jacobian ``(..., [K,] 6, n)`` (3.30); see :func:`diffkin.jacobian.geometric_jacobian`."""
        from ..jacobian import geometric_jacobian

        return geometric_jacobian(self, q, **kwargs)

    def analytical_jacobian(self, q: Tensor, representation: str = "ZYZ", **kwargs) -> Tensor:
        """Analytical Jacobian ``(..., 6, n)`` (3.66); see :func:`diffkin.jacobian.analytical_jacobian`."""
        from ..jacobian import analytical_jacobian

        return analytical_jacobian(self, q, representation=representation, **kwargs)

    def center_of_mass(self, q: Tensor) -> Tensor:
        """Centre of mass ``(..., 3)`` of the model's bodies at ``q (..., nq)``, in the base frame (MuJoCo's
        ``subtree_com`` of the root body); see :mod:`diffkin.center_of_mass`. Needs link masses (URDF
        ``<inertial>``, MJCF): a chain without them raises :class:`~diffkin.errors.ModelError`."""
        from ..center_of_mass import center_of_mass

        return center_of_mass(self, q)

    def com_jacobian(self, q: Tensor) -> Tensor:
        """Jacobian ``(..., 3, nv)`` of :meth:`center_of_mass`: Σ_i (m_i / M) J_P(p_i), the linear rows of
        (3.30) at each body's centre of mass (``mj_jacSubtreeCom``); see :mod:`diffkin.center_of_mass`."""
        from ..center_of_mass import com_jacobian

        return com_jacobian(self, q)

    def forward_kinematics_and_jacobian(self, q: Tensor, frame=None, point: Tensor | None = None,
                                        point_frame: str = "ee", check: bool = True,
                                        base: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """End poses and geometric Jacobians (3.30) from one pass: ``(T (..., [K,] 4, 4),
        J (..., [K,] 6, nv))``, with the options of :func:`diffkin.jacobian.geometric_jacobian`. ``base``
        (per-row world poses of the base ``(..., 4, 4)``): T in the world and J's rows rotated into it,
        diag(R, R) J. The plain call (no ``frame``/``point``) goes straight to the kernel pass."""
        if frame is None and point is None:
            return self._fk_jacobian(q, check, base)
        from ..jacobian import forward_kinematics_and_jacobian

        return forward_kinematics_and_jacobian(self, q, frame, point, point_frame, check, base)

    def parameter_jacobian(self, q: Tensor, check: bool = True) -> tuple[Tensor, list[str]]:
        """Jacobian of the end poses w.r.t. the geometric parameters: ``(Φ (..., [K,] 6, P), names)``.

        Column p is the base-frame twist [δp; δω] of each end link per unit change of the p-th entry of the
        flattened parameters (order of ``named_parameters()``, names like ``"a.2"``), by forward-mode
        differentiation of the one FK kernel, so the same linearisation as the geometric Jacobian's.
        """
        from ..kernels.jacobian import twist_of_derivative

        if check:
            q = self.check_q(q)
        named = [(k, p) for k, p in self.named_parameters()]
        flat = torch.cat([p.detach().reshape(-1) for _, p in named])
        sizes = [p.numel() for _, p in named]

        def fk_of(theta: Tensor) -> Tensor:
            parts = torch.split(theta, sizes)
            params = {k: t.view_as(p) for (k, p), t in zip(named, parts)}
            return torch.func.functional_call(self, params, (q,))

        dT = torch.func.jacfwd(fk_of)(flat)  # (..., [K,] 4, 4, P)
        with torch.no_grad():
            T = self.forward_kinematics(q, check=False)
        names = [f"{k}.{i}" if p.numel() > 1 else k for k, p in named for i in range(p.numel())]
        return twist_of_derivative(dT, T), names

    # ------------------------------------------------------------------------------------ limits
    def lower_upper(self) -> tuple[Tensor, Tensor]:
        """Finite ranges ``(lower (n,), upper (n,))`` for sampling and seeding: the limits where a joint has
        them, else ±π (revolute) or ±1 m (prismatic)."""
        span = torch.where(self.revolute_mask > 0, math.pi, torch.ones_like(self.revolute_mask))
        if self.q_limits is None:
            return -span, span
        lo, hi = self.q_limits[:, 0], self.q_limits[:, 1]
        return torch.where(torch.isinf(lo), -span, lo), torch.where(torch.isinf(hi), span, hi)

    def within_limits(self, q: Tensor, tol: float = 0.0, check: bool = True) -> Tensor:
        """Boolean ``(...)``: every joint of ``q (..., n)`` within its limits (± tol); always True without
        limits. ``check``: validate ``q`` (:meth:`check_q`)."""
        if check:
            q = self.check_q(q)
            if not (isinstance(tol, int | float) and math.isfinite(tol)):
                raise NonFiniteError(f"expected tol as a finite number, got {tol!r}")
        if self.q_limits is None:
            return torch.ones(q.shape[:-1], dtype=torch.bool, device=q.device)
        lo, hi = self.q_limits[:, 0], self.q_limits[:, 1]
        return ((q >= lo - tol) & (q <= hi + tol)).all(dim=-1)

    def clamp_to_limits(self, q: Tensor, check: bool = True) -> Tensor:
        """Project ``q (..., n)`` onto the joint limits (identity where the chain has none). ``check``:
        validate ``q`` (:meth:`check_q`; NaN is refused, never clamped)."""
        if check:
            q = self.check_q(q)
        if self.q_limits is None:
            return q
        return torch.maximum(torch.minimum(q, self.q_limits[:, 1]), self.q_limits[:, 0])

    def random_configuration(
        self, shape: Sequence[int] | int = (), generator: torch.Generator | None = None, *, collision=None,
        world=None, margin: float = 0.0, max_rounds: int = 32, return_mask: bool = False,
    ) -> Tensor | tuple[Tensor, Tensor]:
        """Uniform joint samples within the limits, shape ``(*shape, nq)``, chain dtype/device; the
        quaternions of ball and free joints uniform on the unit sphere (positions of a free joint within its
        limits, else ±1 m). With ``collision`` (a :class:`~diffkin.collision.RobotCollision`), ``world``,
        ``margin``: collision-free samples by batched rejection
        (:func:`diffkin.sampling.random_configuration`,
        which documents ``max_rounds`` and ``return_mask``)."""
        from ..sampling import random_configuration

        return random_configuration(self, shape, generator, collision=collision, world=world, margin=margin,
                                    max_rounds=max_rounds, return_mask=return_mask)

    @property
    def learnable(self) -> bool:
        """Whether any geometry parameter requires grad (``learnable=True`` or ``requires_grad_()``)."""
        return any(p.requires_grad for p in self.parameters())

    def copy(self) -> KinematicChain:
        """An independent deep copy (not compiled: a compiled path is bound to its own chain)."""
        import copy

        fast, self._compiled_fk = self._compiled_fk, None
        try:
            return copy.deepcopy(self)
        finally:
            self._compiled_fk = fast

    def extra_repr(self) -> str:
        if self.configuration_space.euclidean:
            return f"name={self.name!r}, n_joints={self.n_joints}, joint_types={self.joint_types!r}"
        return f"name={self.name!r}, nq={self.nq}, nv={self.nv}, joint_types={self.joint_types!r}"
