"""Kinematic chains and direct kinematics (§2.8).

:class:`KinematicChain` is the interface every chain offers (FK, joint axes for the Jacobian (3.30), joint
limits); :class:`DHChain` implements it from a Denavit–Hartenberg table in the standard convention of the
book (2.52) or the modified (Craig) one.

The FK kernel keeps the rotation as three column vectors ``x, y, z`` of shape ``(..., 3)`` and the origin
``p``; each DH step is a handful of fused multiply-adds on those columns instead of a batched 4×4 matmul
(a 4×4 matmul wastes 7/16 of its flops on the constant last row and has a high per-call overhead).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from ._numerics import batch_shape_str, check_finite
from .errors import ConventionError, DTypeError, ModelError, ShapeError

__all__ = ["KinematicChain", "DHChain"]

_CONVENTIONS = ("standard", "modified")


def _as_param(x, n: int, name: str) -> Tensor:
    t = torch.as_tensor(x, dtype=torch.get_default_dtype()) if not isinstance(x, Tensor) else x.detach().clone()
    if not t.is_floating_point():
        t = t.to(torch.get_default_dtype())
    if t.ndim == 0:
        t = t.expand(n).clone()
    if t.shape != (n,):
        raise ModelError(f"DH parameter {name} must have shape ({n},), got {batch_shape_str(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise ModelError(f"DH parameter {name} contains NaN or inf")
    return t


def _as_transform(T, name: str, like: Tensor) -> Tensor:
    if T is None:
        return torch.eye(4, dtype=like.dtype, device=like.device)
    T = torch.as_tensor(T, dtype=like.dtype, device=like.device)
    if T.shape != (4, 4):
        raise ModelError(f"{name} must be a (4, 4) homogeneous transform, got {batch_shape_str(T.shape)}")
    R = T[:3, :3]
    eye = torch.eye(3, dtype=T.dtype, device=T.device)
    tol = 1e-5 if T.dtype == torch.float32 else 1e-9
    if (
        not bool(torch.isfinite(T).all())
        or not torch.allclose(R.T @ R, eye, atol=tol)
        or not torch.allclose(T[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype, device=T.device))
        or float(torch.linalg.det(R)) < 0
    ):
        raise ModelError(f"{name} must be a rigid transform (orthonormal R with det +1, last row [0, 0, 0, 1])")
    return T.clone()


def _frames_to_matrix(x: Tensor, y: Tensor, z: Tensor, p: Tensor) -> Tensor:
    """Columns (..., 3) each -> homogeneous (..., 4, 4)."""
    top = torch.stack((x, y, z, p), dim=-1)  # (..., 3, 4)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat((top, bottom), dim=-2)


class KinematicChain(nn.Module):
    """A serial chain of ``n`` one-DOF joints with a fixed base and tool transform.

    Subclasses implement :meth:`_link_columns`, which yields the frame of every link as rotation columns
    and origin, and :meth:`joint_axes_origins`. Everything else (FK, Jacobians, limits, sampling) is shared.

    Shapes: ``q`` is ``(..., n)``; poses are ``(..., 4, 4)``.
    """

    n_joints: int
    joint_types: str

    def __init__(self, n_joints: int, joint_types: str, q_limits=None, name: str | None = None):
        super().__init__()
        joint_types = joint_types.upper()
        if len(joint_types) != n_joints or set(joint_types) - {"R", "P"}:
            raise ModelError(
                f"joint_types must be a string of {n_joints} letters 'R' (revolute) or 'P' (prismatic), "
                f"got {joint_types!r}"
            )
        self.n_joints = n_joints
        self.joint_types = joint_types
        self.name = name or f"chain{n_joints}"
        revolute = torch.tensor([c == "R" for c in joint_types], dtype=torch.get_default_dtype())
        self.register_buffer("revolute_mask", revolute)
        if q_limits is not None:
            lim = torch.as_tensor(q_limits, dtype=torch.get_default_dtype())
            if lim.shape != (n_joints, 2):
                raise ModelError(f"q_limits must have shape ({n_joints}, 2), got {batch_shape_str(lim.shape)}")
            if not bool((lim[:, 0] < lim[:, 1]).all()):
                raise ModelError("q_limits must satisfy lower < upper for every joint")
            self.register_buffer("q_limits", lim.clone())
        else:
            self.register_buffer("q_limits", None)

    # ----------------------------------------------------------------------------------------- checks
    @property
    def dtype(self) -> torch.dtype:
        return self.revolute_mask.dtype

    @property
    def device(self) -> torch.device:
        return self.revolute_mask.device

    def check_q(self, q, name: str = "q", finite: bool = True) -> Tensor:
        """Validate a joint tensor ``(..., n)`` against this chain (type, shape, dtype, finiteness)."""
        if not isinstance(q, Tensor):
            raise DTypeError(f"{name} must be a torch.Tensor of shape (..., {self.n_joints}), got {type(q).__name__}")
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
        if finite:
            check_finite(q, name)
        return q

    # ------------------------------------------------------------------------------------------ FK
    def _link_columns(self, q: Tensor):
        """Yield ``(x, y, z, p)`` of frames 0..n (each ``(..., 3)``), tool not applied. Subclasses implement."""
        raise NotImplementedError

    def _tool_columns(self):
        raise NotImplementedError

    def forward_kinematics(self, q: Tensor, all_frames: bool = False, check: bool = True) -> Tensor:
        """Direct kinematics T = base · A1(q1) ··· An(qn) · tool  (2.50)–(2.51).

        Args:
            q: joint variables ``(..., n)`` (rad for revolute, m for prismatic joints).
            all_frames: if True return ``(..., n + 1, 4, 4)``: frame 0 (base) and every link frame, the last one
                being the end-effector pose (tool applied). Otherwise the end-effector pose ``(..., 4, 4)``.
            check: validate ``q`` (shape, dtype, finiteness). Disable only in inner loops on trusted input.
        """
        if check:
            self.check_q(q)
        frames = list(self._link_columns(q)) if all_frames else None
        if frames is None:
            *_, last = self._link_columns(q)
            return _frames_to_matrix(*self._apply_tool(*last))
        frames[-1] = self._apply_tool(*frames[-1])
        mats = [_frames_to_matrix(*f) for f in frames]
        return torch.stack(torch.broadcast_tensors(*mats), dim=-3)

    def _apply_tool(self, x, y, z, p):
        tool = self.tool
        if tool is None:
            return x, y, z, p
        Rt, pt = tool[:3, :3], tool[:3, 3]
        x2 = x * Rt[0, 0] + y * Rt[1, 0] + z * Rt[2, 0]
        y2 = x * Rt[0, 1] + y * Rt[1, 1] + z * Rt[2, 1]
        z2 = x * Rt[0, 2] + y * Rt[1, 2] + z * Rt[2, 2]
        p2 = p + x * pt[0] + y * pt[1] + z * pt[2]
        return x2, y2, z2, p2

    def forward(self, q: Tensor) -> Tensor:
        """Alias of :meth:`forward_kinematics` (end-effector pose ``(..., 4, 4)``)."""
        return self.forward_kinematics(q)

    def joint_axes_origins(self, q: Tensor, check: bool = True) -> tuple[Tensor, Tensor, Tensor]:
        """Joint motion axes and origins in the base frame, and the end-effector pose, from one FK pass.

        Returns ``(axes (..., n, 3), origins (..., n, 3), T_ee (..., 4, 4))``: for joint i the unit vector
        z_{i-1} and point p_{i-1} of (3.30) (standard DH); for modified DH the joint sits on z_i, p_i.
        """
        raise NotImplementedError

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
        """Joint limits ``(lower (n,), upper (n,))``; ±π for unlimited revolute, ±1 m for unlimited prismatic."""
        if self.q_limits is not None:
            return self.q_limits[:, 0], self.q_limits[:, 1]
        span = torch.where(self.revolute_mask > 0, math.pi, 1.0).to(self.dtype)
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
    ):
        n = len(a) if not isinstance(a, Tensor) else int(a.numel())
        if n == 0:
            raise ModelError("a DH chain needs at least one joint")
        if joint_types is None:
            joint_types = "R" * n
        super().__init__(n, joint_types, q_limits=q_limits, name=name)
        if convention not in _CONVENTIONS:
            raise ConventionError(f"convention must be one of {_CONVENTIONS}, got {convention!r}")
        self.convention = convention
        params = {k: _as_param(v, n, k) for k, v in dict(a=a, alpha=alpha, d=d, theta=theta).items()}
        dtype = params["a"].dtype
        self.a = nn.Parameter(params["a"])
        self.alpha = nn.Parameter(params["alpha"].to(dtype))
        self.d = nn.Parameter(params["d"].to(dtype))
        self.theta = nn.Parameter(params["theta"].to(dtype))
        self.revolute_mask = self.revolute_mask.to(dtype)
        if self.q_limits is not None:
            self.q_limits = self.q_limits.to(dtype)
        self.register_buffer("base", _as_transform(base, "base", self.a) if base is not None else None)
        self.register_buffer("tool", _as_transform(tool, "tool", self.a) if tool is not None else None)

    # -------------------------------------------------------------------------------------- kernel
    def _joint_values(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Effective ϑ and d of every joint, ``(..., n)`` each."""
        rev = self.revolute_mask
        theta = self.theta + q * rev
        d = self.d + q * (1.0 - rev)
        return theta, d

    def _base_columns(self, like: Tensor):
        if self.base is None:
            eye = torch.eye(3, dtype=like.dtype, device=like.device)
            zero = torch.zeros(3, dtype=like.dtype, device=like.device)
            return eye[:, 0], eye[:, 1], eye[:, 2], zero
        B = self.base
        return B[:3, 0], B[:3, 1], B[:3, 2], B[:3, 3]

    def _link_columns(self, q: Tensor):
        theta, d = self._joint_values(q)
        ct, st = torch.cos(theta).unsqueeze(-1), torch.sin(theta).unsqueeze(-1)  # (..., n, 1)
        d = d.unsqueeze(-1)
        ct, st, d = ct.unbind(-2), st.unbind(-2), d.unbind(-2)
        ca, sa = torch.cos(self.alpha).unbind(), torch.sin(self.alpha).unbind()
        a = self.a.unbind()
        x, y, z, p = self._base_columns(q)
        yield x, y, z, p
        standard = self.convention == "standard"
        for i in range(self.n_joints):
            c, s, di = ct[i], st[i], d[i]
            if standard:
                # Rz(ϑ) Tz(d) Tx(a) Rx(α)
                p = p + di * z
                x, y = c * x + s * y, c * y - s * x
                p = p + a[i] * x
                y, z = ca[i] * y + sa[i] * z, ca[i] * z - sa[i] * y
            else:
                # Rx(α_{i-1}) Tx(a_{i-1}) Rz(ϑ_i) Tz(d_i)
                p = p + a[i] * x
                y, z = ca[i] * y + sa[i] * z, ca[i] * z - sa[i] * y
                x, y = c * x + s * y, c * y - s * x
                p = p + di * z
            yield x, y, z, p

    def joint_axes_origins(self, q: Tensor, check: bool = True) -> tuple[Tensor, Tensor, Tensor]:
        if check:
            self.check_q(q)
        frames = list(self._link_columns(q))
        if self.convention == "standard":
            joint_frames = frames[:-1]  # joint i moves about z_{i-1} through p_{i-1}
        else:
            joint_frames = frames[1:]  # modified DH: joint i sits on z_i, p_i
        zs = torch.broadcast_tensors(*[f[2] for f in joint_frames])
        ps = torch.broadcast_tensors(*[f[3] for f in joint_frames])
        axes = torch.stack(zs, dim=-2)
        origins = torch.stack(ps, dim=-2)
        T_ee = _frames_to_matrix(*self._apply_tool(*frames[-1]))
        batch = q.shape[:-1]
        axes = axes.expand(*batch, self.n_joints, 3)
        origins = origins.expand(*batch, self.n_joints, 3)
        return axes, origins, T_ee

    # ------------------------------------------------------------------------------------ helpers
    def dh_table(self) -> Tensor:
        """The DH table as ``(n, 4)`` columns (a, alpha, d, theta), detached."""
        return torch.stack([self.a, self.alpha, self.d, self.theta], dim=-1).detach()

    def copy(self) -> DHChain:
        """An independent copy (parameters cloned, gradients not shared)."""
        return DHChain(
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

    def extra_repr(self) -> str:
        return super().extra_repr() + f", convention={self.convention!r}"
