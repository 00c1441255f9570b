"""Kinematic chains and direct kinematics (§2.8).

:class:`KinematicChain` is the interface every chain offers (FK, joint axes for the Jacobian (3.30), joint
limits); :class:`DHChain` implements it from a Denavit–Hartenberg table in the standard convention of the
book (2.52) or the modified (Craig) one; :class:`diffkin.models.URDFChain` from a URDF.

Two kernels compute the same frames (the choice is by batch size only, both differentiable):

* the *column kernel* (batches above :attr:`KinematicChain.small_batch`): the frame is kept as four
  columns ``x, y, z, p`` of shape ``(3, B)`` (batch last, so each op is one contiguous vectorised pass) and
  every DH step is a few fused multiply-adds on them: no 4×4 matmul, which wastes 7/16 of its flops on the
  constant last row and is slow for tiny batched matrices;
* the *matrix kernel* (small batches): A_i in closed form (2.52) for all joints at once, then n − 1
  matmuls — fewer PyTorch ops, so less per-call overhead when there is little arithmetic to do.

When no gradient w.r.t. the DH table is needed (``torch.no_grad()`` or ``chain.requires_grad_(False)``) the
column kernel reads the table as Python constants and skips zero terms (:meth:`DHChain._constant_plan`).
``chain.compile()`` is an opt-in ``torch.compile`` path for large batches. Kernels live in
:mod:`diffkin._fk_kernels`.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence

import torch
from torch import Tensor, nn

from ._fk_kernels import Columns, columns_to_matrices, dh_ee_components, dh_frames
from ._numerics import batch_shape_str, check_finite
from .errors import ConventionError, DTypeError, ModelError, ShapeError

__all__ = ["KinematicChain", "DHChain"]

_CONVENTIONS = ("standard", "modified")


def _first_float_dtype(*xs) -> torch.dtype | None:
    for x in xs:
        if isinstance(x, Tensor) and x.is_floating_point():
            return x.dtype
    return None


def _as_param(x, n: int, name: str, dtype: torch.dtype, device) -> Tensor:
    if isinstance(x, Tensor):
        t = x.detach().to(dtype=dtype, device=device).clone()
    else:
        t = torch.as_tensor(x, dtype=dtype, device=device)
    if t.ndim == 0:
        t = t.expand(n).clone()
    if t.shape != (n,):
        raise ModelError(f"DH parameter {name} must have shape ({n},), got {batch_shape_str(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise ModelError(f"DH parameter {name} contains NaN or inf")
    return t


def as_rigid_transform(T, name: str, dtype: torch.dtype, device=None) -> Tensor:
    """Validate a fixed ``(4, 4)`` rigid transform (base, tool, URDF origin) and return a tensor copy."""
    T = torch.as_tensor(T, dtype=dtype, device=device).clone()
    if T.shape != (4, 4):
        raise ModelError(f"{name} must be a (4, 4) homogeneous transform, got {batch_shape_str(T.shape)}")
    R = T[:3, :3]
    eye = torch.eye(3, dtype=T.dtype, device=T.device)
    tol = 1e-5 if T.dtype != torch.float64 else 1e-9
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype, device=T.device)
    if (
        not bool(torch.isfinite(T).all())
        or not torch.allclose(R.T @ R, eye, atol=tol)
        or not torch.equal(T[3], bottom)
        or float(torch.linalg.det(R)) < 0
    ):
        raise ModelError(
            f"{name} must be a rigid transform (orthonormal R with det +1, last row [0, 0, 0, 1])"
        )
    return T


class KinematicChain(nn.Module):
    """A serial chain of ``n`` one-DOF joints with fixed base and tool transforms.

    Subclasses provide the kernels (see :meth:`_column_frames` and :meth:`_link_matrices`); FK, joint axes,
    limits and sampling are shared. Shapes: ``q`` is ``(..., n)``; poses are ``(..., 4, 4)``.

    Kernel frames K_0..K_n satisfy K_0 = base, K_i = K_{i-1} · A_i(q_i); the end effector is K_n · tool.
    Joint i moves about the z axis of kernel frame ``i - 1 + _axis_offset`` through its origin.
    """

    n_joints: int
    joint_types: str
    #: batches with at most this many configurations use the matrix kernel (less per-call overhead)
    small_batch: int = 16
    _axis_offset: int = 0

    def __init__(self, n_joints: int, joint_types: str, q_limits=None, name: str | None = None, *,
                 dtype: torch.dtype | None = None, device=None):
        super().__init__()
        dtype = dtype or torch.get_default_dtype()
        joint_types = joint_types.upper()
        if len(joint_types) != n_joints or set(joint_types) - {"R", "P"}:
            raise ModelError(
                f"joint_types must be a string of {n_joints} letters 'R' (revolute) or 'P' (prismatic), "
                f"got {joint_types!r}"
            )
        self.n_joints = n_joints
        self.joint_types = joint_types
        self.name = name or f"chain{n_joints}"
        revolute = torch.tensor([c == "R" for c in joint_types], dtype=dtype, device=device)
        self.register_buffer("revolute_mask", revolute)
        self.register_buffer("q_limits", None)
        self.register_buffer("base", None)
        self.register_buffer("tool", None)
        if q_limits is not None:
            lim = q_limits.detach() if isinstance(q_limits, Tensor) else q_limits
            lim = torch.as_tensor(lim, dtype=dtype, device=device).clone()
            if lim.shape != (n_joints, 2):
                raise ModelError(
                    f"q_limits must have shape ({n_joints}, 2), got {batch_shape_str(lim.shape)}"
                )
            if not bool(torch.isfinite(lim).all()) or not bool((lim[:, 0] < lim[:, 1]).all()):
                bad = [i for i, (lo, hi) in enumerate(lim.tolist()) if not lo < hi]
                raise ModelError(f"q_limits must be finite with lower < upper; joints {bad} are not")
            self.q_limits = lim
        self._compiled_fk = None
        #: free-text model information (description, source, notes) from YAML, kept by to_dict()
        self.metadata: dict[str, str] = {}

    def _set_base_tool(self, base, tool) -> None:
        dtype, device = self.dtype, self.device
        self.base = None if base is None else as_rigid_transform(base, "base", dtype, device)
        self.tool = None if tool is None else as_rigid_transform(tool, "tool", dtype, device)

    # ----------------------------------------------------------------------------------------- checks
    @property
    def dtype(self) -> torch.dtype:
        return self.revolute_mask.dtype

    @property
    def device(self) -> torch.device:
        return self.revolute_mask.device

    def check_q(self, q, name: str = "q", finite: bool = True) -> Tensor:
        """Validate a joint tensor ``(..., n)`` for this chain (type, shape, dtype, device, finiteness)."""
        if not isinstance(q, Tensor):
            raise DTypeError(
                f"{name} must be a torch.Tensor of shape (..., {self.n_joints}), got {type(q).__name__}"
            )
        if not q.is_floating_point():
            raise DTypeError(f"{name} must be a floating-point tensor, got {q.dtype}")
        if q.ndim == 0 or q.shape[-1] != self.n_joints:
            raise ShapeError(
                f"expected {name} of shape (..., {self.n_joints}) for chain '{self.name}', "
                f"got {batch_shape_str(q.shape)}"
            )
        if q.dtype != self.dtype:
            raise DTypeError(
                f"{name} has dtype {q.dtype} but chain '{self.name}' is {self.dtype}; "
                f"convert one of them (chain.to({q.dtype}) or q.to({self.dtype}))"
            )
        if q.device != self.device:
            raise DTypeError(f"{name} is on {q.device} but chain '{self.name}' is on {self.device}")
        if finite and not bool(torch.isfinite(q.detach().sum())):  # one cheap reduction: a finite sum means
            check_finite(q, name)  # all finite; otherwise the exact (5-pass) check decides (sum overflow)
        return q

    # ------------------------------------------------------------------------------ kernel protocol
    def _column_frames(self, qs: Sequence[Tensor], constants: bool = True) -> Iterator[Columns]:
        """Yield kernel frames K_0..K_n as columns ``(x, y, z, p)``, each ``(3, B)`` or ``(3, 1)``.

        ``constants=False`` forbids data-dependent specialisation (for ``torch.compile`` tracing).
        ``qs`` holds the n joint values, each ``(B,)`` (strided views of the flattened ``q``). K_0 is the
        base frame. Only the current frame is alive at a time, so memory stays a few times the output.
        """
        raise NotImplementedError

    def _link_matrices(self, q: Tensor) -> Tensor:
        """A_1..A_n of the kernel frames, ``(..., n, 4, 4)``."""
        raise NotImplementedError

    def _frame_fixup(self, i: int) -> Tensor | None:
        """Fixed transform from kernel frame i to link frame i (None: they coincide)."""
        return None

    def _ee_transform(self) -> Tensor | None:
        """Fixed transform from kernel frame n to the end effector (the tool)."""
        return self.tool

    # ------------------------------------------------------------------------------------------ FK
    def forward_kinematics(self, q: Tensor, all_frames: bool = False, check: bool = True) -> Tensor:
        """Direct kinematics T = base · A1(q1) ··· An(qn) · tool  (2.50)–(2.51).

        Args:
            q: joint variables ``(..., n)`` (rad for revolute, m for prismatic joints).
            all_frames: if True return ``(..., n + 1, 4, 4)``: frame 0 (base) and every link frame, the last
                one being the end-effector pose (tool applied). Otherwise the end-effector pose
                ``(..., 4, 4)``.
            check: validate ``q`` (shape, dtype, finiteness). Disable only in inner loops on trusted input.
        """
        if check:
            self.check_q(q)
        batch = q.shape[:-1]
        if batch.numel() <= self.small_batch:
            return self._matrix_fk(q, all_frames)
        if not all_frames and self._compiled_fk is not None:
            return self._compiled_fk(q)
        return self._column_fk(q, all_frames)

    def _matrix_fk(self, q: Tensor, all_frames: bool) -> Tensor:
        A = self._link_matrices(q)
        T = A[..., 0, :, :] if self.base is None else self.base @ A[..., 0, :, :]
        frames = [T]
        for i in range(1, self.n_joints):
            T = T @ A[..., i, :, :]
            frames.append(T)
        ee = self._ee_transform()
        T_ee = T if ee is None else T @ ee
        if not all_frames:
            return T_ee
        base = self.base if self.base is not None else torch.eye(4, dtype=q.dtype, device=q.device)
        out = [base]
        for i, F in enumerate(frames[:-1], start=1):
            fix = self._frame_fixup(i)
            out.append(F if fix is None else F @ fix)
        out.append(T_ee)
        return torch.stack(torch.broadcast_tensors(*out), dim=-3)

    def _joint_columns(self, q: Tensor) -> tuple[Tensor, ...]:
        return q.reshape(-1, self.n_joints).unbind(-1)

    def _base_columns(self, like: Tensor) -> Columns:
        if self.base is None:
            eye = torch.eye(3, dtype=like.dtype, device=like.device)
            return eye[:, 0:1], eye[:, 1:2], eye[:, 2:3], torch.zeros_like(eye[:, 0:1])
        x, y, z, p = self.base[:3].unsqueeze(-1).unbind(1)
        return x, y, z, p

    def _new_poses(self, q: Tensor, *shape: int) -> Tensor:
        out = q.new_empty(*shape, 4, 4)
        out[..., 3, :3] = 0.0
        out[..., 3, 3] = 1.0
        return out

    def _column_fk(self, q: Tensor, all_frames: bool = False) -> Tensor:
        batch, n = q.shape[:-1], self.n_joints
        qs = self._joint_columns(q)
        B = qs[0].shape[0]
        if not all_frames:
            for frame in self._column_frames(qs):  # noqa: B007 - only the last frame is needed
                pass
            out = self._new_poses(q, B)
            columns_to_matrices(frame, self._ee_transform(), out)
            return out.reshape(*batch, 4, 4)
        out = self._new_poses(q, B, n + 1)
        for i, frame in enumerate(self._column_frames(qs)):
            fix = self._ee_transform() if i == n else self._frame_fixup(i) if i > 0 else None
            columns_to_matrices(frame, fix, out[:, i])
        return out.reshape(*batch, n + 1, 4, 4)

    def forward(self, q: Tensor) -> Tensor:
        """Alias of :meth:`forward_kinematics` (end-effector pose ``(..., 4, 4)``)."""
        return self.forward_kinematics(q)

    def joint_axes_origins(self, q: Tensor, check: bool = True) -> tuple[Tensor, Tensor, Tensor]:
        """Joint motion axes and origins in the base frame, and the end-effector pose, from one FK pass.

        Returns ``(axes (..., n, 3), origins (..., n, 3), T_ee (..., 4, 4))``: for joint i the unit vector
        z_{i-1} and point p_{i-1} of (3.30) (standard DH); for modified DH the joint sits on z_i, p_i.
        Above :attr:`small_batch` ``axes`` and ``origins`` are non-contiguous views of batch-last memory
        (``reshape``, not ``view``, to flatten them).
        """
        if check:
            self.check_q(q)
        batch, n, off = q.shape[:-1], self.n_joints, self._axis_offset
        if batch.numel() <= self.small_batch:
            frames = self._matrix_kernel_frames(q)
            axes = frames[..., off : off + n, :3, 2]
            origins = frames[..., off : off + n, :3, 3]
            ee = self._ee_transform()
            T_ee = frames[..., n, :, :] if ee is None else frames[..., n, :, :] @ ee
            return axes, origins, T_ee
        qs = self._joint_columns(q)
        B = qs[0].shape[0]
        # batch-last (3, n, B) memory, handed out as (B, n, 3) views: every write is a contiguous row copy
        # (no transposing scatter), and the Jacobian kernel computes in this layout
        axes_bl, origins_bl, T_ee = q.new_empty(3, n, B), q.new_empty(3, n, B), self._new_poses(q, B)
        self._axes_origins_into(qs, axes_bl, origins_bl, T_ee)
        axes, origins = axes_bl.permute(2, 1, 0), origins_bl.permute(2, 1, 0)
        return axes.reshape(*batch, n, 3), origins.reshape(*batch, n, 3), T_ee.reshape(*batch, 4, 4)

    def _axes_origins_into(self, qs: Sequence[Tensor], axes: Tensor, origins: Tensor, T_ee: Tensor) -> Tensor:
        """Column kernel of :meth:`joint_axes_origins` for joint columns ``qs`` (each ``(B,)``): fills
        ``axes`` and ``origins`` ``(3, n, B)`` and ``T_ee (B, 4, 4)`` (last row already [0, 0, 0, 1]);
        returns the end-effector origin batch last, ``(3, B)`` or ``(3, 1)``, equal to ``T_ee[:, :3, 3].T``.
        """
        off, n = self._axis_offset, self.n_joints
        for i, frame in enumerate(self._column_frames(qs)):
            if off <= i < off + n:  # q-independent columns are (3, 1) and broadcast
                axes[:, i - off] = frame[2]
                origins[:, i - off] = frame[3]
        return columns_to_matrices(frame, self._ee_transform(), T_ee)

    def _matrix_kernel_frames(self, q: Tensor) -> Tensor:
        """Kernel frames K_0..K_n as ``(..., n + 1, 4, 4)`` (no fixups, no tool)."""
        A = self._link_matrices(q)
        T = self.base if self.base is not None else torch.eye(4, dtype=q.dtype, device=q.device)
        frames = [T]
        for i in range(self.n_joints):
            T = T @ A[..., i, :, :]
            frames.append(T)
        return torch.stack(torch.broadcast_tensors(*frames), dim=-3)

    def _ee_functional(self, qT: Tensor) -> Tensor:
        """End-effector poses ``(B, 4, 4)`` from ``qT (n, B)`` by the column kernel, without in-place
        writes or data-dependent branches: the function :meth:`compile` traces."""
        for frame in self._column_frames(qT.unbind(0), constants=False):  # noqa: B007
            pass
        F = torch.stack(torch.broadcast_tensors(*frame))  # (4, 3, B)
        ee = self._ee_transform()
        if ee is not None:
            F = (ee.transpose(0, 1) @ F.reshape(4, -1)).reshape(F.shape)
        top = F.permute(2, 1, 0)
        bottom = torch.cat((torch.zeros_like(top[:, :1, :3]), torch.ones_like(top[:, :1, :1])), dim=-1)
        return torch.cat((top, bottom), dim=1)

    def compile(self, **kwargs) -> KinematicChain:
        """Opt-in fast path: FK of the end effector through ``torch.compile`` (kwargs passed on).

        Used for batches above :attr:`small_batch` when ``all_frames=False``. The first call compiles
        (tens of seconds on a small CPU); ``dynamic=True`` by default so later batch sizes reuse it.
        :meth:`uncompile` drops it.
        """
        kwargs.setdefault("dynamic", True)
        fn = torch.compile(self._ee_functional, **kwargs)
        n = self.n_joints

        def fast(q: Tensor) -> Tensor:  # batch-last, contiguous joint rows: unit-stride loads in the kernel
            return fn(q.reshape(-1, n).transpose(0, 1).contiguous()).reshape(*q.shape[:-1], 4, 4)

        self._compiled_fk = fast
        return self

    def uncompile(self) -> KinematicChain:
        """Drop the compiled fast path of :meth:`compile`."""
        self._compiled_fk = None
        return self

    # ------------------------------------------------------------------------------- Jacobians (§3)
    def geometric_jacobian(self, q: Tensor, **kwargs) -> Tensor:
        """Geometric Jacobian ``(..., 6, n)`` (3.30); see :func:`diffkin.jacobian.geometric_jacobian`."""
        from .jacobian import geometric_jacobian

        return geometric_jacobian(self, q, **kwargs)

    def analytical_jacobian(self, q: Tensor, representation: str = "ZYZ", **kwargs) -> Tensor:
        """Analytical Jacobian ``(..., 6, n)`` (3.66); see :func:`diffkin.jacobian.analytical_jacobian`."""
        from .jacobian import analytical_jacobian

        return analytical_jacobian(self, q, representation=representation, **kwargs)

    def forward_kinematics_and_jacobian(self, q: Tensor, **kwargs) -> tuple[Tensor, Tensor]:
        """``(T_ee (..., 4, 4), J (..., 6, n))`` from one FK pass."""
        from .jacobian import forward_kinematics_and_jacobian

        return forward_kinematics_and_jacobian(self, q, **kwargs)

    # ------------------------------------------------------------------------------------ limits
    def lower_upper(self) -> tuple[Tensor, Tensor]:
        """Limits ``(lower (n,), upper (n,))``; ±π for unlimited revolute, ±1 m for unlimited prismatic."""
        if self.q_limits is not None:
            return self.q_limits[:, 0], self.q_limits[:, 1]
        span = torch.where(self.revolute_mask > 0, math.pi, torch.ones_like(self.revolute_mask))
        return -span, span

    def within_limits(self, q: Tensor, tol: float = 0.0) -> Tensor:
        """Boolean ``(...)``: every joint of ``q`` within its limits (± tol)."""
        lo, hi = self.lower_upper()
        return ((q >= lo - tol) & (q <= hi + tol)).all(dim=-1)

    def clamp_to_limits(self, q: Tensor) -> Tensor:
        """Project ``q (..., n)`` onto the joint limits (identity where the chain has none)."""
        if self.q_limits is None:
            return q
        lo, hi = self.lower_upper()
        return torch.maximum(torch.minimum(q, hi), lo)

    def random_configuration(
        self, shape: Sequence[int] | int = (), generator: torch.Generator | None = None
    ) -> Tensor:
        """Uniform joint samples within the limits, shape ``(*shape, n)``, chain dtype/device."""
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        lo, hi = self.lower_upper()
        gen_device = self.device if generator is None else generator.device
        u = torch.rand(*shape, self.n_joints, generator=generator, dtype=self.dtype, device=gen_device)
        u = u.to(self.device)
        return lo + (hi - lo) * u

    def extra_repr(self) -> str:
        return f"name={self.name!r}, n_joints={self.n_joints}, joint_types={self.joint_types!r}"


class DHChain(KinematicChain):
    """Serial chain from a Denavit–Hartenberg table (§2.8.2).

    ``a``, ``alpha``, ``d``, ``theta`` (each ``(n,)``) are ``nn.Parameter`` s, so FK is differentiable with
    respect to the DH table by default (calibration builds on this). For a revolute joint ``theta`` is the
    joint offset (ϑ_i = theta_i + q_i); for a prismatic joint ``theta`` is its constant angle and
    d_i = d_i + q_i (2.52).

    convention="standard" (the book's): A_i = Rz(ϑ_i) Tz(d_i) Tx(a_i) Rx(α_i)  (2.52).
    convention="modified" (Craig): row i holds (a_{i-1}, α_{i-1}, d_i, ϑ_i) and
    A_i = Rx(α_{i-1}) Tx(a_{i-1}) Rz(ϑ_i) Tz(d_i).

    ``base`` and ``tool`` are fixed ``(4, 4)`` transforms T^b_0 and T^n_e (2.51); ``q_limits`` is ``(n, 2)``.
    The chain's dtype is that of the first tensor among a, alpha, d, theta (else ``dtype`` or the default);
    Python numbers are converted straight to it, so float64 tables are exact.
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
        dtype: torch.dtype | None = None,
        device=None,
    ):
        n = int(a.numel()) if isinstance(a, Tensor) else len(a)
        if n == 0:
            raise ModelError("a DH chain needs at least one joint")
        if convention not in _CONVENTIONS:
            raise ConventionError(f"convention must be one of {_CONVENTIONS}, got {convention!r}")
        dtype = dtype or _first_float_dtype(a, alpha, d, theta) or torch.get_default_dtype()
        if device is None:
            device = next((x.device for x in (a, alpha, d, theta) if isinstance(x, Tensor)), None)
        super().__init__(n, joint_types or "R" * n, q_limits=q_limits, name=name, dtype=dtype, device=device)
        self.convention = convention
        self._axis_offset = 0 if convention == "standard" else 1
        self.a = nn.Parameter(_as_param(a, n, "a", dtype, device))
        self.alpha = nn.Parameter(_as_param(alpha, n, "alpha", dtype, device))
        self.d = nn.Parameter(_as_param(d, n, "d", dtype, device))
        self.theta = nn.Parameter(_as_param(theta, n, "theta", dtype, device))
        self._set_base_tool(base, tool)
        self._plan_key, self._plan = None, None

    # -------------------------------------------------------------------------------------- kernels
    def _joint_values(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Effective ϑ and d of every joint, ``(..., n)`` each (2.52)."""
        rev = self.revolute_mask
        return self.theta + q * rev, self.d + q * (1.0 - rev)

    def _ee_functional(self, qT: Tensor) -> Tensor:
        return dh_ee_components(qT, self.a, self.alpha, self.d, self.theta, self.base, self.tool,
                                 self.joint_types, self.convention == "standard")

    def _constant_plan(self) -> list[tuple[float, float, float, float, float]] | None:
        """The DH table as Python floats ``(a, cos α, sin α, d, theta)`` per joint, or None when autograd
        needs the table (grad mode on and a parameter requires grad).

        Without gradients w.r.t. the table its values are constants: the column kernel then skips zero
        terms and turns α = 0, ±π/2, π into swaps (a third fewer ops on the Panda). Cached per parameter
        version, so in-place updates (optimizer steps, ``load_state_dict``) are seen; cos/sin within one
        ulp of 0 or ±1 are snapped to it (α = π/2 rounded to the dtype gives cos α ≈ 6e-17 or -4e-8).
        """
        params = (self.a, self.alpha, self.d, self.theta)
        if torch.is_grad_enabled() and any(p.requires_grad for p in params):
            return None
        key = tuple((p._version, p.data_ptr(), p.dtype, p.device) for p in params)
        if key != self._plan_key:
            eps = torch.finfo(self.dtype).eps
            plan = []
            for a, alpha, d, theta in torch.stack([p.detach() for p in params], 1).double().cpu().tolist():
                c, s = math.cos(alpha), math.sin(alpha)
                if abs(c) <= eps:
                    c, s = 0.0, math.copysign(1.0, s)
                elif abs(s) <= eps:
                    c, s = math.copysign(1.0, c), 0.0
                plan.append((a, c, s, d, theta))
            self._plan_key, self._plan = key, plan
        return self._plan

    def _column_frames(self, qs: Sequence[Tensor], constants: bool = True) -> Iterator[Columns]:
        plan = self._constant_plan() if constants else None
        if plan is None:  # tensors: differentiable w.r.t. the DH table
            ca, sa = torch.cos(self.alpha).unbind(), torch.sin(self.alpha).unbind()
            plan = list(zip(self.a.unbind(), ca, sa, self.d.unbind(), self.theta.unbind()))
        yield from dh_frames(qs, plan, self.joint_types, self.convention == "standard",
                              self._base_columns(qs[0]))

    def _link_matrices(self, q: Tensor) -> Tensor:
        """Closed-form A_i (2.52) (standard) or Craig's matrix (modified), ``(..., n, 4, 4)``."""
        theta, d = self._joint_values(q)
        ct, st = torch.cos(theta), torch.sin(theta)
        ca, sa, a = (t.expand_as(ct) for t in (torch.cos(self.alpha), torch.sin(self.alpha), self.a))
        zero, one = torch.zeros_like(ct), torch.ones_like(ct)
        if self.convention == "standard":
            rows = (ct, -st * ca, st * sa, a * ct, st, ct * ca, -ct * sa, a * st, zero, sa, ca, d)
        else:
            rows = (ct, -st, zero, a, st * ca, ct * ca, -sa, -sa * d, st * sa, ct * sa, ca, ca * d)
        return torch.stack((*rows, zero, zero, zero, one), dim=-1).unflatten(-1, (4, 4))

    # ------------------------------------------------------------------------------------ helpers
    def dh_table(self) -> Tensor:
        """The DH table as ``(n, 4)`` columns (a, alpha, d, theta), detached."""
        return torch.stack([self.a, self.alpha, self.d, self.theta], dim=-1).detach()

    def copy(self) -> DHChain:
        """An independent copy (parameters cloned, gradients not shared)."""
        c = DHChain(
            self.a.detach().clone(),
            self.alpha.detach().clone(),
            self.d.detach().clone(),
            self.theta.detach().clone(),
            joint_types=self.joint_types,
            convention=self.convention,
            base=None if self.base is None else self.base.clone(),
            tool=None if self.tool is None else self.tool.clone(),
            q_limits=None if self.q_limits is None else self.q_limits.clone(),
            name=self.name,
        )
        c.metadata = dict(self.metadata)
        return c

    # ----------------------------------------------------------------------------------- YAML / dict
    @classmethod
    def from_dict(cls, data: dict, dtype: torch.dtype | None = None, device=None, where: str = "") -> DHChain:
        """Chain from a model mapping (YAML schema of :mod:`diffkin.models.io`); values may be expressions."""
        from .models.io import chain_from_dict

        return chain_from_dict(data, dtype=dtype, device=device, where=where)

    def to_dict(self) -> dict:
        """Model mapping (name, convention, joint_types, dh rows, q_limits, base, tool) with plain floats."""
        from .models.io import chain_to_dict

        return chain_to_dict(self)

    @classmethod
    def from_yaml(cls, path_or_str, dtype: torch.dtype | None = None, device=None) -> DHChain:
        """Chain from a YAML file path or a YAML string (see :mod:`diffkin.models` for the schema)."""
        from .models.io import chain_from_yaml

        return chain_from_yaml(path_or_str, dtype=dtype, device=device)

    def to_yaml(self, path=None) -> str:
        """YAML text of :meth:`to_dict` (angles that are exact multiples of π/12 written as e.g. ``pi/2``);
        also written to ``path`` if given."""
        from .models.io import chain_to_yaml

        return chain_to_yaml(self, path)

    def extra_repr(self) -> str:
        return super().extra_repr() + f", convention={self.convention!r}"
