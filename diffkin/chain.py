"""The learnable kinematic model (§2.8): one class for serial chains and trees, DH and URDF alike.

:class:`KinematicChain` is the one model. Its geometry is ``nn.Parameter`` s, turned into fixed transforms
around a motion about z per joint by :mod:`diffkin.kernels.joints`, and multiplied along a tree of joints by
:mod:`diffkin.kernels.tree`; the Jacobian (3.30) comes from :mod:`diffkin.kernels.jacobian`. Subclasses only
say what their parameters are and how they map to those transforms (:meth:`KinematicChain._geometry`):
:class:`DHChain` (a DH table, standard (2.52) or modified, optionally with Hayati's β) and
:class:`diffkin.models.URDFChain` (URDF joint origins and axes, trees with several end links, mimic joints).

Base and tool are learnable too: T_base = T_base,nominal · Δ(``base_delta``), T_tool = T_tool,nominal ·
Δ(``tool_delta``), with Δ a pose correction that stays rigid for any value (both deltas start at zero).

Learnable means able to learn, on request: the geometry is frozen (``requires_grad=False``) by default, so
that a solve or an FK call returns plain tensors and takes the constant fast path; ``learnable=True`` on
the constructor or loader, or ``chain.requires_grad_()``, makes it trainable.

The evaluations of the product, chosen in one place (:meth:`KinematicChain._route`):

* CPU calls that need no gradient (``torch.no_grad()``, or neither ``q`` nor a parameter requires grad): the
  fused C pass of :mod:`diffkin.kernels.native` (FK and Jacobian together, any batch size);
* otherwise, batches above :attr:`KinematicChain.small_batch`: batch last, joint after joint on the four
  columns of the current frame (few fused multiply-adds per joint, no 4×4 matmul);
* small batches: batch first, all link matrices at once, then one matmul per joint (fewer operations).

The last two are differentiable and traceable (``torch.compile``, ``torch.func``); all three compute the same
numbers to rounding. Under ``torch.autocast`` the kinematics run in the chain's dtype.

When no gradient w.r.t. geometry is needed (``torch.no_grad()`` or ``chain.requires_grad_(False)``) the
fixed transforms are evaluated once in float64 and used as Python constants whose zero terms are skipped
(kept on the chain's :class:`~diffkin.kernels.cache.Data` with every other fast path's derived state, and
remade by its one rule: optimizer steps, in-place updates, writes through ``.data``, replaced or moved
tensors and ``load_state_dict`` are all seen).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from .errors import ConventionError, DTypeError, ModelError, NonFiniteError, OptionError, ShapeError
from .kernels import cache, native, single
from .kernels.columns import columns_to_matrices, plan_of, stack_columns
from .kernels.configuration import MOTION_NQ, ConfigurationSpace
from .kernels.jacobian import tree_jacobian, tree_jacobian_rows
from .kernels.joints import dh_joints, pose_correction
from .kernels.tree import Segments, Topology, column_frames, matrix_frames
from .transforms import as_rigid_transform, check_transform
from .validation import (
    SUPPORTED_DTYPES,
    as_tensor,
    broadcast_batch,
    check_dtype,
    check_finite,
    check_given,
    shape_str,
    tensors,
)

__all__ = ["KinematicChain", "DHChain", "as_rigid_transform"]

_CONVENTIONS = ("standard", "modified")
_CHUNK = 8192  # configurations per thread and slice of a large CPU batch (_fk_jacobian)


def _dh_columns(columns: dict, dtype: torch.dtype | None, device) -> dict[str, Tensor | None]:
    """The DH columns by the rule of :mod:`diffkin.validation` (one float dtype; numbers and numpy arrays
    converted; finite), each ``(n,)`` or a 0-d value for every joint. An explicit ``dtype`` converts float
    tensors of the other float dtype (the caller asked for it)."""
    if dtype is not None:
        columns = {k: check_dtype(v, k).detach().to(dtype) if isinstance(v, Tensor) else v
                   for k, v in columns.items()}
        like = torch.empty(0, dtype=dtype, device=device)
        if device is None:
            like = next((v for v in columns.values() if isinstance(v, Tensor)), like)
            like = torch.empty(0, dtype=dtype, device=like.device)
    else:
        like = None
    out = tensors(*((k, v, None) for k, v in columns.items()), like=like)
    if device is not None:
        out = tuple(None if t is None else t.to(device) for t in out)
    a = out[0]
    if a.ndim != 1:
        raise ShapeError(f"expected the DH column a of shape (n,), got {shape_str(a.shape)}")
    n = a.shape[0]
    if n == 0:
        raise ModelError("a DH chain needs at least one joint")
    cols = {}
    for name, t in zip(columns, out):
        if t is not None:
            t = t.detach().expand(n) if t.ndim == 0 else t.detach()
            if t.shape != (n,):
                raise ShapeError(f"expected {name} of shape ({n},) like a (one value per joint), got "
                                 f"{shape_str(t.shape)}")
            t = t.clone()
        cols[name] = t
    return cols


def _autocast(q: Tensor) -> bool:
    """True under ``torch.autocast`` for q's device: the kinematics then run with autocast turned off, in the
    chain's dtype (float16 / bfloat16 products would be off by millimetres; the pose is cheap either way)."""
    return torch.is_autocast_enabled(q.device.type)


def _is_plain(t: Tensor) -> bool:
    """An ordinary tensor (not a torch.func / compile wrapper), whose values can be read as constants."""
    if torch.compiler.is_compiling():  # under dynamo every tensor is a graph value (and the check traces)
        return False
    return type(t) in (Tensor, nn.Parameter) and not torch._C._functorch.is_functorch_wrapped_tensor(t)


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


class KinematicChain(nn.Module):
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
            from .validation import check_fits_dtype  # (local: this block is the only user in chain.py)

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

    def _state_key(self) -> int | None:
        """A key of the chain's state for caches kept elsewhere (collision models, the velocity IK's
        problems): the generation of its current Data (unique over all chains; a new one after every change
        the rule sees), or None where the geometry may not be read as constants now (a gradient wanted from
        it, a torch.func / compile wrapper: :func:`diffkin.kernels.cache.current`)."""
        data = cache.current(self)
        return None if data is None else data.generation

    def _constants(self) -> tuple[Segments, Segments] | None:
        """Both constant forms of :meth:`_constant_segments` from the current Data, or None (see
        :meth:`_state_key`)."""
        data = cache.current(self)
        return None if data is None else data.segments(self)

    def _segments(self, per_joint: bool, constants: bool = True) -> Segments:
        """The fixed transforms of every joint: per joint (column path) or stacked (matrix path); Python
        constants when allowed, else tensors that carry gradients to the parameters."""
        data = cache.current(self) if constants else None
        if data is not None:
            return data.segments(self)[0 if per_joint else 1]
        return self._tensor_segments(per_joint, constants)

    def _native_model(self, q: Tensor) -> native.NativeModel | None:
        """The packed constants for the fused native kernel (:mod:`diffkin.kernels.native`) when it may
        serve this call: a plain CPU tensor, nothing needing a gradient, not traced (compile / torch.func),
        the library built. None otherwise (the torch kernels serve it)."""
        if torch.compiler.is_compiling() or q.device.type != "cpu" or not _is_plain(q) \
                or (q.requires_grad and torch.is_grad_enabled()) or not native.available():
            return None
        data = cache.current(self)
        return None if data is None else data.native_model(self)

    def _route(self, q: Tensor, op: str) -> tuple[str, native.NativeModel | None]:
        """THE dispatch point: which evaluation serves a call of ``op`` on ``q`` (joints last, or joints
        first for ``"columns"``); returns ``(path, packed native constants or None)``.

        ``op``: ``"fk"`` (end poses), ``"axes"`` (joint axes and origins), ``"fk_jacobian"``, ``"columns"``
        (the batch-last kernel a solver calls, constants allowed) or ``"columns_traced"`` (it with the
        geometry as tensors, or axes asked for). Paths, in this order of preference:

        * ``"native"``: the fused C pass (CPU, no gradient, not traced, the library built; see
          :meth:`_native_model`), for ``fk`` (unless :meth:`compile_fk` ed), ``fk_jacobian`` and ``columns``;
        * ``"batch_first"``: all link matrices at once, then one matmul per joint, for batches of at most
          :attr:`small_batch` configurations and for Jacobians / axes that need a gradient;
        * ``"compiled"``: the ``torch.compile`` d FK of :meth:`compile_fk`;
        * ``"chunked"``: large CPU Jacobian batches without autograd, batch last in slices per thread;
        * ``"batch_last"``: joint after joint on the columns of the current frame (every other call).
        """
        if op == "columns_traced":
            return "batch_last", None
        if op != "axes" and not (op == "fk" and self._compiled_fk is not None):
            packed = self._native_model(q)
            if packed is not None:
                return "native", packed
        if op == "columns":
            return "batch_last", None
        B = q.shape[:-1].numel()
        grad = op != "fk" and self._grad_needed(q)
        if B <= self.small_batch or grad:
            return "batch_first", None
        if op == "fk" and self._compiled_fk is not None:
            return "compiled", None
        if op == "fk_jacobian" and q.device.type == "cpu" and not torch.compiler.is_compiling() \
                and B > 2 * _CHUNK * torch.get_num_threads():
            return "chunked", None
        return "batch_last", None

    def _tensor_segments(self, per_joint: bool, constants: bool) -> Segments:
        pre, offset, post, ends = self._geometry()
        base, tool = self._fixed_pose("base", constants), self._fixed_pose("tool", constants)
        ends = [tool if E is None else (E if tool is None else E @ tool) for E in ends]
        stacked = Segments(pre, offset, post, base, ends)
        if not per_joint:
            return stacked
        return Segments(None if pre is None else pre.unbind(0), None if offset is None else offset.unbind(0),
                        None if post is None else post.unbind(0), base, ends)

    def _constant_segments(self) -> tuple[Segments, Segments]:
        """Both forms evaluated once without autograd: plans from float64 values (exact), and stacked
        tensors in the chain's dtype."""
        with torch.no_grad():
            hi = self if self.dtype == torch.float64 else None
            pre, offset, post, ends = (hi or _as_float64(self))._geometry()
            src = hi or _as_float64(self)
            base, tool = src.base, src.tool
            ends = [tool if E is None else (E if tool is None else E @ tool) for E in ends]

            eps = torch.finfo(self.dtype).eps  # snap what the chain's dtype cannot tell from 0 or ±1

            def plans(T):
                return None if T is None else [plan_of(t, eps) for t in T.unbind(0)]

            per_joint = Segments(plans(pre), None if offset is None else offset.cpu().tolist(), plans(post),
                                 None if base is None else plan_of(base, eps),
                                 [None if E is None else plan_of(E, eps) for E in ends])
            dt, dev = self.dtype, self.device

            def cast(T):
                return None if T is None else T.to(dtype=dt, device=dev)

            stacked = Segments(cast(pre), cast(offset), cast(post), cast(base), [cast(E) for E in ends])
        return per_joint, stacked

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

    # -------------------------------------------------------------------------------------------- FK
    def _row_base(self, base, check: bool, batch: Sequence[int] | None = None, of: str = "q") -> Tensor:
        """Per-row base poses ``(..., 4, 4)`` by the rule (the chain's dtype and device), checked rigid; with
        ``batch`` (the batch dims of ``of``: q or the targets) their batch dims must broadcast with it
        (:class:`ShapeError` naming both, instead of a matmul error)."""
        (base,) = tensors(("base", base, (4, 4)), like=self)
        if batch is not None:
            try:
                torch.broadcast_shapes(tuple(batch), base.shape[:-2])
            except RuntimeError:
                got = f"{of} {shape_str(tuple(batch))}, got base {shape_str(base.shape)}"
                raise ShapeError(f"expected base of shape (..., 4, 4) whose batch dims broadcast with those "
                                 f"of {got}") from None
        return check_transform(base, "base") if check else base

    def _in_world(self, T: Tensor, base: Tensor, per_end: bool) -> Tensor:
        return base @ T if not per_end else base.unsqueeze(-3) @ T

    def forward_kinematics(self, q: Tensor, all_frames: bool = False, check: bool = True,
                           base: Tensor | None = None) -> Tensor:
        """Direct kinematics T = base · A1(q1) ··· An(qn) · tool  (2.50)–(2.51), on a tree for every end link.

        Args:
            q: joint variables ``(..., nq)`` (rad for revolute, m for prismatic joints, unit quaternions for
                ball and free joints).
            all_frames: if True return ``(..., J + 1, 4, 4)``: the base frame and the frame of every joint
                (its child link; J = n without mimic joints). For a chain with one end link the last one is
                the end-effector pose (tool applied).
            check: validate ``q`` (shape, dtype, finiteness). Disable only in inner loops on trusted input.
            base: per-row poses of the chain's base in the world ``(..., 4, 4)`` (broadcasting with q's
                batch): T_world = base · T, so robots at different places are one call.

        Returns:
            ``(..., 4, 4)`` for a chain with one end link, ``(..., K, 4, 4)`` for K end links.
        """
        if base is None and not all_frames and self._compiled_fk is None:  # one q (n,): kernels/single.py
            if (T := single.fk(self, q)) is not None:
                return T
        if base is not None:
            T = self.forward_kinematics(q, all_frames, check)
            per_end = all_frames or not self._single_end
            B = self._row_base(base, check, T.shape[: T.ndim - (3 if per_end else 2)])
            return self._in_world(T, B, per_end)
        if check:
            q = self.check_q(q, finite=False)
        if _autocast(q):  # poses in the chain's dtype: half precision would move a Panda's flange by mm
            with torch.autocast(q.device.type, enabled=False):
                return self.forward_kinematics(q, all_frames, check)
        batch = q.shape[:-1]
        if all_frames:
            if check:
                check_finite(q, "q")
            return self._all_frames(q)
        path, packed = self._route(q, "fk")
        if path == "native":  # the fused C pass; it counts non-finite entries of q as it reads them
            T, _, bad = native.fk_jacobian(packed, q.reshape(-1, self.n_joints).contiguous())
            if bad and check:
                check_finite(q, "q")  # raises the validator's error
            return self._out(T.reshape(*batch, self.n_ends, 4, 4))
        if check:
            check_finite(q, "q")
        if path == "batch_first":
            ends = matrix_frames(q, self._topo, self._segments(per_joint=False), with_frames=False)[0]
            return self._out(ends)
        if path == "compiled":
            return self._compiled_fk(q)
        # one transposing copy gives every joint a contiguous row: each op below is a unit-stride pass
        qT = q.reshape(-1, self.n_joints).T.contiguous()
        ends = column_frames(qT.unbind(0), self._topo, self._segments(per_joint=True))[0]
        return self._out(_poses_from_columns(ends, qT).reshape(*batch, self.n_ends, 4, 4))

    def _all_frames(self, q: Tensor) -> Tensor:
        ends, frames, _, _ = matrix_frames(q, self._topo, self._segments(per_joint=False))
        seg = self._segments(per_joint=False)
        base = seg.base if seg.base is not None else torch.eye(4, dtype=q.dtype, device=q.device)
        if self._single_end and self._topo.ends[0] == self._topo.n_frames - 1:
            frames = torch.cat((frames[..., :-1, :, :], ends), dim=-3)
        return torch.cat((base.expand(*frames.shape[:-3], 1, 4, 4), frames), dim=-3)

    def forward(self, q: Tensor) -> Tensor:
        """Alias of :meth:`forward_kinematics` (end-link poses)."""
        return self.forward_kinematics(q)

    def joint_axes_origins(self, q: Tensor, check: bool = True) -> tuple[Tensor, Tensor, Tensor]:
        """Joint motion axes and origins in the base frame, and the end poses, from one FK pass.

        Returns ``(axes (..., J, 3), origins (..., J, 3), T (..., [K,] 4, 4))``: for joint i the unit vector
        z_{i-1} and a point p_{i-1} of its axis in (3.30) (one row per joint frame: J = n without mimic
        joints).
        """
        if check:
            q = self.check_q(q)
        if _autocast(q):
            with torch.autocast(q.device.type, enabled=False):
                return self.joint_axes_origins(q, check)
        batch = q.shape[:-1]
        if self._route(q, "axes")[0] == "batch_first":
            ends, _, axes, origins = matrix_frames(q, self._topo, self._segments(per_joint=False), True)
            return axes, origins, self._out(ends)
        qT = q.reshape(-1, self.n_joints).T.contiguous()
        m = qT.shape[1]
        _, ends, axes = self.batch_last(qT, with_axes=True, check=False)
        # batch-last (3, J, m) memory handed out as (..., J, 3) views (reshape, not view, to flatten them)
        z = torch.stack([a[0].expand(3, m) for a in axes], dim=1).permute(2, 1, 0)
        o = torch.stack([a[1].expand(3, m) for a in axes], dim=1).permute(2, 1, 0)
        T = _poses_from_columns(ends, qT)
        J = z.shape[1]
        return (z.reshape(*batch, J, 3), o.reshape(*batch, J, 3),
                self._out(T.reshape(*batch, self.n_ends, 4, 4)))

    def _grad_needed(self, q: Tensor) -> bool:
        params = self.parameters()
        return torch.is_grad_enabled() and (q.requires_grad or any(p.requires_grad for p in params))

    def _fk_jacobian(self, q: Tensor, check: bool = True,
                     base: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """End poses and geometric Jacobians (3.30) from one pass: ``(T (..., [K,] 4, 4),
        J (..., [K,] 6, nv))``. ``base`` (per-row world poses of the base ``(..., 4, 4)``): T in the world
        and J's rows rotated into it, diag(R, R) J.

        Large CPU batches without autograd run in slices of 8192 configurations per intra-op thread through
        the batch-last path, written straight into the outputs: every value is computed as for the whole
        batch (all operations are per configuration), but the frames and rows stay in cache.
        """
        if base is None and (TJ := single.fk(self, q, jacobian=True)) is not None:  # kernels/single.py
            return TJ
        if base is not None:
            T, J = self._fk_jacobian(q, check)
            B = self._row_base(base, check, T.shape[: T.ndim - (2 if self._single_end else 3)])
            R = B[..., :3, :3] if self._single_end else B[..., None, :3, :3]
            J = torch.cat((R @ J[..., :3, :], R @ J[..., 3:, :]), dim=-2)
            return self._in_world(T, B, not self._single_end), J
        if check:
            q = self.check_q(q, finite=False)
        if _autocast(q):
            with torch.autocast(q.device.type, enabled=False):
                return self._fk_jacobian(q, check)
        batch, n, K, nv = q.shape[:-1], self.n_joints, self.n_ends, self.nv
        path, packed = self._route(q, "fk_jacobian")
        if path == "native":  # the fused C pass (poses and Jacobians at once)
            T, Jac, bad = native.fk_jacobian(packed, q.reshape(-1, n).contiguous(), with_jacobian=True)
            if bad and check:
                check_finite(q, "q")
            return self._out(T.reshape(*batch, K, 4, 4)), self._out(Jac.reshape(*batch, K, 6, nv))
        if check:
            check_finite(q, "q")
        if path == "batch_first":
            ends, _, axes, origins = matrix_frames(q, self._topo, self._segments(per_joint=False), True)
            J = tree_jacobian(axes, origins, ends[..., :3, 3], self._joint_revolute, self._topo)
            return self._out(ends), self._out(J)
        if path == "batch_last":
            ends, J = self._batch_last_fk_jacobian(q.reshape(-1, n).T.contiguous())
            return self._out(ends.reshape(*batch, K, 4, 4)), self._out(J.reshape(*batch, K, 6, nv))
        B, chunk = batch.numel(), _CHUNK * torch.get_num_threads()
        qT = q.reshape(-1, n).T.contiguous()
        T, Jout = _new_poses(q, B, K), q.new_empty(B, K, 6, nv)
        for start in range(0, B, chunk):
            part = slice(start, min(start + chunk, B))
            rows, ends = self.batch_last(qT[:, part], with_jacobian=True, check=False)
            if K == 1:  # straight into the output (contiguous rows of T)
                columns_to_matrices(ends[0], T[part, 0])
            else:
                T[part] = _poses_from_columns(ends, qT[:, part])
            Jout[part] = rows.permute(2, 1, 0).unflatten(1, (K, 6))
        return self._out(T.reshape(*batch, K, 4, 4)), self._out(Jout.reshape(*batch, K, 6, nv))

    def _batch_last_fk_jacobian(self, qT: Tensor) -> tuple[Tensor, Tensor]:
        """``qT (n, m)`` -> ``(T (m, K, 4, 4), J (m, K, 6, n))`` through the batch-last path."""
        rows, ends = self.batch_last(qT, with_jacobian=True, check=False)
        return _poses_from_columns(ends, qT), rows.permute(2, 1, 0).unflatten(1, (self.n_ends, 6))

    def batch_last(self, qT: Tensor, with_jacobian: bool = False, constants: bool = True,
                   with_axes: bool = False, check: bool = True):
        """The batch-last kernel for solvers that keep their state batch last (:mod:`diffkin.ik`).

        ``qT (n, m)`` -> ``(J, ends)``: ``ends`` the K end frames as columns ``(x, y, z, p)``, each
        ``(3, m)`` or ``(3, 1)``; ``J`` (if ``with_jacobian``) the geometric Jacobian rows ``(n, 6K, m)``
        (row block k for end link k), else None. ``with_axes`` appends the list of J joint ``(axis, origin)``
        column pairs. ``check``: validate ``qT`` by the rule (solvers pass False on their trusted state).
        """
        if check:
            (qT,) = tensors(("qT", qT, None), like=self, finite=False)
            if qT.ndim != 2 or qT.shape[0] != self.n_joints:
                raise ShapeError(f"expected qT of shape ({self.n_joints}, m) (joints first, batch last) for "
                                 f"chain '{self.name}', got {shape_str(qT.shape)}")
            check_finite(qT, "qT")
        topo = self._topo
        path, packed = self._route(qT, "columns_traced" if with_axes or not constants else "columns")
        if path == "native":  # the fused C pass, handed out in this layout (one copy each)
            m, K = qT.shape[1], self.n_ends
            T, Jac, _ = native.fk_jacobian(packed, qT.T.contiguous(), with_jacobian)
            cols = T[..., :3, :].permute(3, 2, 1, 0).contiguous()  # (4 columns, 3, K, m)
            ends = [tuple(cols[c, :, k] for c in range(4)) for k in range(K)]
            rows = None if Jac is None else Jac.reshape(m, 6 * K, self.nv).permute(2, 1, 0).contiguous()
            return rows, ends
        qs = qT.unbind(0)
        ends, axes, _ = column_frames(qs, topo, self._segments(per_joint=True, constants=constants),
                                      with_axes=with_jacobian or with_axes)
        if not with_jacobian:
            return (None, ends, axes) if with_axes else (None, ends)
        rows = tree_jacobian_rows(axes, [f[3] for f in ends], self._joint_revolute, topo, qT.shape[1])
        return (rows, ends, axes) if with_axes else (rows, ends)

    def _functional_fk(self, qT: Tensor) -> Tensor:
        """End poses ``(m, K, 4, 4)`` from ``qT (n, m)`` without in-place writes or data-dependent branches:
        the function :meth:`compile_fk` traces."""
        _, ends = self.batch_last(qT, constants=False, check=False)
        return torch.stack([stack_columns(tuple(c.expand(3, qT.shape[1]) for c in f)) for f in ends], dim=1)

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
        from .jacobian import geometric_jacobian

        return geometric_jacobian(self, q, **kwargs)

    def analytical_jacobian(self, q: Tensor, representation: str = "ZYZ", **kwargs) -> Tensor:
        """Analytical Jacobian ``(..., 6, n)`` (3.66); see :func:`diffkin.jacobian.analytical_jacobian`."""
        from .jacobian import analytical_jacobian

        return analytical_jacobian(self, q, representation=representation, **kwargs)

    def center_of_mass(self, q: Tensor) -> Tensor:
        """Centre of mass ``(..., 3)`` of the model's bodies at ``q (..., nq)``, in the base frame (MuJoCo's
        ``subtree_com`` of the root body); see :mod:`diffkin.center_of_mass`. Needs link masses (URDF
        ``<inertial>``, MJCF): a chain without them raises :class:`~diffkin.errors.ModelError`."""
        from .center_of_mass import center_of_mass

        return center_of_mass(self, q)

    def com_jacobian(self, q: Tensor) -> Tensor:
        """Jacobian ``(..., 3, nv)`` of :meth:`center_of_mass`: Σ_i (m_i / M) J_P(p_i), the linear rows of
        (3.30) at each body's centre of mass (``mj_jacSubtreeCom``); see :mod:`diffkin.center_of_mass`."""
        from .center_of_mass import com_jacobian

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
        from .jacobian import forward_kinematics_and_jacobian

        return forward_kinematics_and_jacobian(self, q, frame, point, point_frame, check, base)

    def parameter_jacobian(self, q: Tensor, check: bool = True) -> tuple[Tensor, list[str]]:
        """Jacobian of the end poses w.r.t. the geometric parameters: ``(Φ (..., [K,] 6, P), names)``.

        Column p is the base-frame twist [δp; δω] of each end link per unit change of the p-th entry of the
        flattened parameters (order of ``named_parameters()``, names like ``"a.2"``), by forward-mode
        differentiation of the one FK kernel, so the same linearisation as the geometric Jacobian's.
        """
        from .kernels.jacobian import twist_of_derivative

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
        from .sampling import random_configuration

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


def _new_poses(like: Tensor, *shape: int) -> Tensor:
    out = like.new_empty(*shape, 4, 4)
    out[..., 3, :3] = 0.0
    out[..., 3, 3] = 1.0
    return out


_LINEAR_CORRECTION: dict = {}


def _zero_correction(delta: Tensor) -> Tensor:
    """Δ(δ) at δ = 0, the identity, as I + L δ with L the exact derivative of Δ there:
    dΔ = [[[dω]×, dt], [0, 0]] (used only while δ is exactly zero).

    The base and tool corrections sit at zero until something moves them; in grad mode this gives their
    exact gradient for one small matmul instead of the rotation-vector map. Second derivatives w.r.t. the
    correction itself are not exact here (the linear map has none; Δ's ½[ω]×² term does): a Hessian in
    ``base_delta`` / ``tool_delta`` at exactly zero needs them set off zero first (mixed q–δ terms are
    exact)."""
    key = (delta.dtype, delta.device)
    L = _LINEAR_CORRECTION.get(key)
    if L is None:
        L = torch.zeros(16, 6, dtype=delta.dtype, device=delta.device)
        entries = (((0, 3), 0, 1), ((1, 3), 1, 1), ((2, 3), 2, 1), ((2, 1), 3, 1), ((1, 2), 3, -1),
                   ((0, 2), 4, 1), ((2, 0), 4, -1), ((1, 0), 5, 1), ((0, 1), 5, -1))
        for (r, c), k, sign in entries:
            L[4 * r + c, k] = sign
        _LINEAR_CORRECTION[key] = L
    return torch.eye(4, dtype=delta.dtype, device=delta.device) + (L @ delta).view(4, 4)


def _poses_from_columns(ends, qT: Tensor) -> Tensor:
    """``(m, K, 4, 4)`` poses from the K end frames' batch-last columns (``qT (n, m)`` for dtype and size):
    each end written to its own contiguous block (strided writes across K are several times slower)."""
    m = qT.shape[1]
    if len(ends) == 1:
        return columns_to_matrices(ends[0], _new_poses(qT, m)).unsqueeze(1)
    return torch.stack([columns_to_matrices(f, _new_poses(qT, m)) for f in ends], dim=1)


def _as_float64(chain: KinematicChain) -> KinematicChain:
    """A float64 CPU view of a chain's parameters and buffers for exact constant evaluation."""
    import copy

    c = copy.copy(chain)  # shallow: swap in float64 parameters/buffers without touching the original
    c._parameters = {k: None if p is None else p.detach().double().cpu()
                     for k, p in chain._parameters.items()}
    c._buffers = {k: None if b is None else (b.double() if b.is_floating_point() else b).cpu()
                  for k, b in chain._buffers.items()}
    c.__dict__.pop(cache.KEY, None)  # the original's Data is not the copy's
    return c


class DHChain(KinematicChain):
    """Serial chain from a Denavit–Hartenberg table (§2.8.2).

    ``a``, ``alpha``, ``d``, ``theta`` (each ``(n,)``) are ``nn.Parameter`` s, frozen unless
    ``learnable=True`` (or ``chain.requires_grad_()``): then FK is differentiable with respect to the DH
    table (gradient-based identification, a learnt tool). For a revolute joint ``theta`` is the
    joint offset (ϑ_i = theta_i + q_i); for a prismatic joint ``theta`` is its constant angle and
    d_i = d_i + q_i (2.52).

    convention="standard" (the book's): A_i = Rz(ϑ_i) Tz(d_i) Tx(a_i) Rx(α_i)  (2.52).
    convention="modified" (Craig): row i holds (a_{i-1}, α_{i-1}, d_i, ϑ_i) and
    A_i = Rx(α_{i-1}) Tx(a_{i-1}) Rz(ϑ_i) Tz(d_i).
    ``beta`` (standard convention only): Hayati's parameters, A_i = (2.52) · Ry(β_i); for near-parallel
    consecutive axes, where d is ill-defined, a small tilt of the next axis in their common plane is a small
    β.

    ``base`` and ``tool`` are ``(4, 4)`` transforms T^b_0 and T^n_e (2.51), learnable through ``base_delta``
    and ``tool_delta``; ``q_limits`` is ``(n, 2)``. The DH columns follow the rule of
    :mod:`diffkin.validation`: float32/float64 tensors of one dtype (mixed dtypes, integer or half tensors
    raise :class:`~diffkin.errors.DTypeError`; NaN/inf :class:`~diffkin.errors.NonFiniteError`; columns of
    another length :class:`~diffkin.errors.ShapeError`), numbers and numpy arrays converted. The chain's
    dtype is ``dtype`` if given (float tensors are then converted to it), else the columns'; Python numbers
    are converted straight to it, so float64 tables are exact. ``base``/``tool`` follow the chain's dtype.
    """

    def __init__(
        self,
        a,
        alpha,
        d,
        theta,
        joint_types: str | None = None,
        convention: str = "standard",
        base=None,
        tool=None,
        q_limits=None,
        name: str | None = None,
        *,
        beta=None,
        dtype: torch.dtype | None = None,
        device=None,
        learnable: bool = False,
    ):
        _check_learnable(learnable)
        if convention not in _CONVENTIONS:
            raise ConventionError(f"convention must be one of {_CONVENTIONS}, got {convention!r}")
        if beta is not None and convention != "standard":
            raise ConventionError("Hayati's beta is defined here for the standard DH convention only")
        if dtype is not None and dtype not in SUPPORTED_DTYPES:
            raise DTypeError(f"a chain's dtype must be torch.float32 or torch.float64, got {dtype}")
        cols = _dh_columns({"a": a, "alpha": alpha, "d": d, "theta": theta, "beta": beta}, dtype, device)
        n = cols["a"].shape[0]
        dtype, device = cols["a"].dtype, cols["a"].device
        joint_types = "R" * n if joint_types is None else joint_types
        joint_types = joint_types.upper() if isinstance(joint_types, str) else joint_types
        if not isinstance(joint_types, str) or len(joint_types) != n or set(joint_types) - {"R", "P"}:
            raise ModelError(
                f"joint_types must be a string of {n} letters 'R' (revolute) or 'P' (prismatic), "
                f"got {joint_types!r}"
            )
        topo = Topology.serial(joint_types)
        super().__init__(topo, q_limits=q_limits, name=name, dtype=dtype, device=device, learnable=learnable)
        self.convention = convention
        self.a = nn.Parameter(cols["a"], requires_grad=learnable)
        self.alpha = nn.Parameter(cols["alpha"], requires_grad=learnable)
        self.d = nn.Parameter(cols["d"], requires_grad=learnable)
        self.theta = nn.Parameter(cols["theta"], requires_grad=learnable)
        self.beta = None if beta is None else nn.Parameter(cols["beta"], requires_grad=learnable)
        # the constructor decides the chain's dtype: float base/tool tensors are converted to it
        base, tool = (check_dtype(T, k).detach().to(dtype) if isinstance(T, Tensor) else T
                      for k, T in (("base", base), ("tool", tool)))
        self._set_base_tool(base, tool)

    def _geometry(self):
        pre, offset, post = dh_joints(self.a, self.alpha, self.d, self.theta, self.revolute_mask,
                                      self.convention == "modified", self.beta)
        return pre, offset, post, [None]

    # ------------------------------------------------------------------------------------ helpers
    def dh_table(self) -> Tensor:
        """The DH table as ``(n, 4)`` columns (a, alpha, d, theta), detached."""
        return torch.stack([self.a, self.alpha, self.d, self.theta], dim=-1).detach()

    def copy(self) -> DHChain:
        """An independent copy (parameters cloned, each as learnable as its original; gradients not shared,
        not compiled)."""
        c = DHChain(
            self.a.detach().clone(),
            self.alpha.detach().clone(),
            self.d.detach().clone(),
            self.theta.detach().clone(),
            joint_types=self.joint_types,
            convention=self.convention,
            base=None if self.base is None else self.base.detach().clone(),
            tool=None if self.tool is None else self.tool.detach().clone(),
            q_limits=None if self.q_limits is None else self.q_limits.clone(),
            name=self.name,
            beta=None if self.beta is None else self.beta.detach().clone(),
        )
        c.metadata = dict(self.metadata)
        c.home, c.planar = None if self.home is None else list(self.home), self.planar
        for key, p in self.named_parameters():
            c.get_parameter(key).requires_grad_(p.requires_grad)
        return c

    # ----------------------------------------------------------------------------------- YAML / dict
    @classmethod
    def from_dict(cls, data: dict, dtype: torch.dtype | None = None, device=None, where: str = "", *,
                  learnable: bool = False) -> DHChain:
        """Chain from a model mapping (YAML schema of :mod:`diffkin.models.io`); values may be expressions."""
        from .models.io import parse_chain_dict

        kwargs = parse_chain_dict(data, dtype=dtype, device=device, where=where)
        metadata, home, planar = kwargs.pop("metadata"), kwargs.pop("home"), kwargs.pop("planar")
        chain = cls(**kwargs, learnable=learnable)
        chain.metadata, chain.home, chain.planar = metadata, home, planar
        return chain

    def to_dict(self) -> dict:
        """Model mapping (name, convention, joint_types, dh rows, q_limits, base, tool) with plain floats."""
        from .models.io import chain_to_dict

        return chain_to_dict(self)

    @classmethod
    def from_yaml(cls, path_or_str, dtype: torch.dtype | None = None, device=None, *,
                  learnable: bool = False) -> DHChain:
        """Chain from a YAML file path or a YAML string (see :mod:`diffkin.models` for the schema)."""
        from .models.io import read_yaml

        data, where = read_yaml(path_or_str)
        return cls.from_dict(data, dtype=dtype, device=device, where=where, learnable=learnable)

    def to_yaml(self, path=None) -> str:
        """YAML text of :meth:`to_dict` (angles that are exact multiples of π/12 written as e.g. ``pi/2``);
        also written to ``path`` if given."""
        from .models.io import chain_to_yaml

        return chain_to_yaml(self, path)

    def extra_repr(self) -> str:
        return super().extra_repr() + f", convention={self.convention!r}"
