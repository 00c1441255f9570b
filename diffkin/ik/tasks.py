"""IK tasks: what the robot should do, as small frozen objects in mink's vocabulary, batched.

A task declares an error e(q) ``(..., m)`` and its Jacobian J(q) = ∂e/∂q ``(..., m, nv)`` (columns in the
chain's velocity coordinates), a cost ``(..., m)`` (the diagonal weight W), a gain α and a
Levenberg–Marquardt damping μ. The velocity IK (:func:`~diffkin.ik.solve_velocity`) asks for the
displacement Δq = q̇ Δt with the first-order task dynamics J Δq = −α e, in the least-squares sense:

    ½ ‖W (J Δq + α e)‖² + ½ μ ‖W α e‖² ‖Δq‖²                                                     (T.1)

summed over the tasks (mink's ``Task.compute_qp_objective``). That is all a task is: a new task is one class
with :meth:`Task.error` and :meth:`Task.jacobian`.

=====================  ======================================================  =============================
task                   error e ``(..., m)``                                    Jacobian ``(..., m, nv)``
=====================  ======================================================  =============================
FrameTask (target)     log(T_f⁻¹ T_t) (body twist of the target, [v; ω])       −J_log(T_t⁻¹ T_f) J_body
FrameTask (twist)      −ξ Δt (ξ = [v; ω] in the base frame)                    J (3.30), base frame
RelativeFrameTask      log(T_t⁻¹ T_rf), T_rf = T_r⁻¹ T_f                       J_log(T_t⁻¹T_rf)(J_f − Ad J_r)
PostureTask            q ⊖ q_ref (free joints: 0)                              I (free joints' columns: 0)
DampingTask            0                                                       I (free joints' columns: 0)
ComTask                c(q) − c_target                                         ∂c/∂q
=====================  ======================================================  =============================

(J_body = diag(Rᵀ, Rᵀ) J: the geometric Jacobian (3.30) in the frame's own axes; log and J_log are the
SE(3) logarithm and its right Jacobian of :mod:`diffkin.kernels.se3`.) With the twist form and α = 1, (T.1)
is ‖W (J q̇ − ξ)‖² Δt²: the weighted least squares of :func:`~diffkin.ik.velocity_step` (V.1).

Every tensor argument may carry leading batch dims that broadcast with q's.
"""

from __future__ import annotations

from numbers import Number
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .._numerics import broadcast_shapes
from ..errors import ConventionError, DiffkinError, ShapeError
from ..kernels.se3 import se3_jlog, se3_log
from ..transforms import _transform_inverse
from ..validation import check_nonnegative, shape_str, tensors

__all__ = ["ComTask", "DampingTask", "FrameTask", "PostureTask", "RelativeFrameTask", "Task"]


class _Frozen:
    """Attributes set once in ``__init__`` (frozen like a dataclass; compared by identity)."""

    __slots__ = ()

    def _set(self, **kw) -> None:
        for k, v in kw.items():
            object.__setattr__(self, k, v)

    def __setattr__(self, name, value):
        raise AttributeError(f"{type(self).__name__} is frozen: build a new one (attribute {name!r})")

    def __repr__(self) -> str:
        slots = [k for c in type(self).__mro__ for k in getattr(c, "__slots__", ())]
        fields = ", ".join(f"{k}={_short(getattr(self, k))}" for k in slots)
        return f"{type(self).__name__}({fields})"


def _short(v) -> str:
    return f"tensor{shape_str(v.shape)}" if isinstance(v, Tensor) and v.ndim else repr(v)


class Problem:
    """One step's context: the chain, q ``(..., nq)``, Δt, and the end-link poses and Jacobians computed once
    for every task that needs them."""

    def __init__(self, chain, q: Tensor, dt: float):
        self.chain, self.q, self.dt = chain, q, dt
        self._fk: tuple[Tensor, Tensor] | None = None

    @property
    def nv(self) -> int:
        return self.chain.nv

    def frames(self) -> tuple[Tensor, Tensor]:
        """T ``(..., K, 4, 4)`` and the geometric Jacobians (3.30) ``(..., K, 6, nv)`` of every end link."""
        if self._fk is None:
            T, J = self.chain.forward_kinematics_and_jacobian(self.q, check=False)
            if self.chain.single_end:
                T, J = T.unsqueeze(-3), J.unsqueeze(-3)
            self._fk = (T, J)
        return self._fk

    def end_index(self, frame, what: str) -> int:
        """The index into the chain's end links of ``frame`` (a name or an index)."""
        K = self.chain.n_ends
        if isinstance(frame, str):
            names = list(getattr(self.chain, "end_links", None) or [])
            if frame not in names:
                raise ConventionError(f"{what}: {frame!r} is not an end link of the chain (its end links: "
                                      f"{names}); a frame must be one of them, by name or index")
            return names.index(frame)
        if isinstance(frame, bool) or not isinstance(frame, int) or not 0 <= frame < K:
            raise ShapeError(f"{what}: expected an end-link name or index in [0, {K}), got {frame!r}")
        return frame

    def like(self, name: str, value, trailing) -> Tensor:
        (t,) = tensors((name, value, trailing), like=self.q)
        return t

    def free_dofs(self) -> list[int]:
        """The velocity columns of free (floating-base) joints (``chain.joint_kinds``; none for DH chains)."""
        return free_dofs(self.chain)


def joint_dofs(chain) -> list[tuple[str, str, list[int]]]:
    """(name, kind, velocity columns) of each independent joint of ``chain`` in q order (a DH chain's joints
    are ``"joint_i"``, one column each)."""
    from ..kernels.configuration import joint_kind

    kinds = getattr(chain, "joint_kinds", None)
    names = getattr(chain, "joint_names", None)
    if kinds is None:
        return [(f"joint_{i}", "revolute", [i]) for i in range(chain.nv)]
    out, col = [], 0
    for name, kind in zip(names, kinds):
        nv = joint_kind(kind).nv
        out.append((name, kind, list(range(col, col + nv))))
        col += nv
    return out


def free_dofs(chain) -> list[int]:
    return [c for _, kind, cols in joint_dofs(chain) if kind == "free" for c in cols]


def objects_of(x: Any, cls: type, name: str, kinds: str) -> tuple:
    """``x`` (None, one ``cls`` or an iterable of them: the tasks or limits argument) as a tuple;
    :class:`~diffkin.errors.ConventionError` naming ``kinds`` and the first entry that is not a ``cls``."""
    xs = () if x is None else (x,) if isinstance(x, cls) else tuple(x)
    bad = [t for t in xs if not isinstance(t, cls)]
    if bad:
        raise ConventionError(f"expected {name} as {cls.__name__} objects ({kinds}), got {bad[0]!r}")
    return xs


def _gain_damping(task, p: Problem) -> tuple[Tensor, Tensor]:
    gain, mu = (check_nonnegative(p.like(f"{type(task).__name__}.{k}", v, None), f"{type(task).__name__}.{k}")
                for k, v in (("gain", task.gain), ("lm_damping", task.lm_damping)))
    return gain, mu


def _per_axis(p: Problem, value, name: str, m: int) -> Tensor:
    """A cost as a number or ``(..., m)``, made ``(..., m)``."""
    w = check_nonnegative(p.like(name, value, None), name)
    if w.ndim == 0:
        return w.expand(m)
    if w.shape[-1] != m:
        raise ShapeError(f"expected {name} as a number or (..., {m}), got {shape_str(w.shape)}")
    return w


class Task(_Frozen):
    """The base of every task: subclasses define :meth:`error`, :meth:`jacobian` and :meth:`cost_vector`;
    ``gain`` α and ``lm_damping`` μ of (T.1) are attributes."""

    __slots__ = ()

    def error(self, p: Problem) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def jacobian(self, p: Problem) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def cost_vector(self, p: Problem, m: int) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def least_squares(self, p: Problem) -> tuple[Tensor, Tensor, Tensor]:
        """(A = W J ``(..., m, nv)``, b = −α W e ``(..., m)``, μ‖b‖² ``(...)``): (T.1) is
        ½‖A Δq − b‖² + ½ μ‖b‖² ‖Δq‖²."""
        e, J = self.error(p), self.jacobian(p)
        w = self.cost_vector(p, e.shape[-1])
        gain, mu = _gain_damping(self, p)
        b = -gain[..., None] * w * e
        return w[..., :, None] * J, b, mu * (b * b).sum(-1)


class FrameTask(Task):
    """Track an end link's pose ``target (..., 4, 4)`` (in the chain's base frame) or its twist
    ``twist (..., 6)`` = [v; ω] (base frame, m/s and rad/s): exactly one of the two.

    frame: the end link, by name (``chain.end_links``) or index (``chain.topology.ends`` order; 0 for a
    chain). position_cost / orientation_cost: a number or per axis ``(..., 3)`` (>= 0; 0 drops the
    component); gain α ∈ [0, 1], lm_damping μ >= 0 of (T.1).

    The old spelling ``FrameTask(end=k, weight=w)`` (``w`` a number or ``(6,)``: the costs [position;
    orientation]) builds the same task.
    """

    __slots__ = ("frame", "target", "twist", "position_cost", "orientation_cost", "gain", "lm_damping")

    def __init__(self, frame: Any = None, *, target=None, twist=None, position_cost=1.0,
                 orientation_cost=1.0, gain=1.0, lm_damping=0.0, end: Any = None, weight: Any = None):
        if end is not None:
            if frame is not None:
                raise ConventionError("FrameTask: give the end link once (frame, or the old end=)")
            frame = end
        if weight is not None:  # the old (6,) weight: [position; orientation] costs
            w = weight if isinstance(weight, Tensor | Number) else np.asarray(weight)
            shape = tuple(getattr(w, "shape", ()))
            if shape and shape[-1] != 6:
                raise ShapeError(f"FrameTask: expected weight as a number or (6,), got {shape_str(shape)}")
            position_cost, orientation_cost = (w, w) if not shape else (w[..., :3], w[..., 3:])
        if target is not None and twist is not None:
            raise ConventionError("FrameTask: give a target pose or a twist, not both")
        self._set(frame=0 if frame is None else frame, target=target, twist=twist,
                  position_cost=position_cost, orientation_cost=orientation_cost, gain=gain,
                  lm_damping=lm_damping)

    @property
    def end(self):
        """The old name of :attr:`frame`."""
        return self.frame

    def cost_vector(self, p: Problem, m: int) -> Tensor:
        pos = _per_axis(p, self.position_cost, "FrameTask.position_cost", 3)
        ori = _per_axis(p, self.orientation_cost, "FrameTask.orientation_cost", 3)
        batch = broadcast_shapes(pos.shape[:-1], ori.shape[:-1])
        return torch.cat((pos.expand(*batch, 3), ori.expand(*batch, 3)), dim=-1)

    def _pose(self, p: Problem) -> tuple[Tensor, Tensor]:
        k = p.end_index(self.frame, "FrameTask.frame")
        T, J = p.frames()
        return (None if T is None else T[..., k, :, :]), J[..., k, :, :]

    def _target(self, p: Problem) -> Tensor:
        if self.target is None:
            raise DiffkinError("FrameTask: no target pose and no twist: set one of them")
        return p.like("FrameTask.target", self.target, (4, 4))

    def error(self, p: Problem) -> Tensor:
        if self.twist is not None:
            return -p.like("FrameTask.twist", self.twist, (6,)) * p.dt
        T_f, _ = self._pose(p)
        return se3_log(_transform_inverse(T_f) @ self._target(p))

    def jacobian(self, p: Problem) -> Tensor:
        T_f, J = self._pose(p)
        if self.twist is not None:
            return J
        T_tf = _transform_inverse(self._target(p)) @ T_f
        return -se3_jlog(T_tf) @ _body(T_f, J)


def _body(T: Tensor, J: Tensor) -> Tensor:
    """diag(Rᵀ, Rᵀ) J: the frame's twist in its own axes ``(..., 6, nv)``."""
    Rt = T[..., :3, :3].mT
    return torch.cat((Rt @ J[..., :3, :], Rt @ J[..., 3:, :]), dim=-2)


def _adjoint(T: Tensor) -> Tensor:
    """Ad_T ``(..., 6, 6)`` for twists [v; ω]: [[R, S(p) R], [0, R]]."""
    from ..rotations import _skew

    R, pp = T[..., :3, :3], T[..., :3, 3]
    top = torch.cat((R, _skew(pp) @ R), dim=-1)
    return torch.cat((top, torch.cat((torch.zeros_like(R), R), dim=-1)), dim=-2)


class RelativeFrameTask(Task):
    """Track the pose of end link ``frame`` in the frame of end link ``root``: ``target (..., 4, 4)`` is
    T_root⁻¹ T_frame wanted (mink's ``RelativeFrameTask``). Costs, gain and damping as :class:`FrameTask`."""

    __slots__ = ("frame", "root", "target", "position_cost", "orientation_cost", "gain", "lm_damping")

    def __init__(self, frame, root, *, target, position_cost=1.0, orientation_cost=1.0, gain=1.0,
                 lm_damping=0.0):
        self._set(frame=frame, root=root, target=target, position_cost=position_cost,
                  orientation_cost=orientation_cost, gain=gain, lm_damping=lm_damping)

    cost_vector = FrameTask.cost_vector

    def _poses(self, p: Problem):
        f = p.end_index(self.frame, "RelativeFrameTask.frame")
        r = p.end_index(self.root, "RelativeFrameTask.root")
        T, J = p.frames()
        T_rf = _transform_inverse(T[..., r, :, :]) @ T[..., f, :, :]
        target = p.like("RelativeFrameTask.target", self.target, (4, 4))
        return T, J, f, r, T_rf, _transform_inverse(target) @ T_rf

    def error(self, p: Problem) -> Tensor:
        return se3_log(self._poses(p)[-1])

    def jacobian(self, p: Problem) -> Tensor:
        T, J, f, r, T_rf, T_tf = self._poses(p)
        J_f = _body(T[..., f, :, :], J[..., f, :, :])
        J_r = _body(T[..., r, :, :], J[..., r, :, :])
        return se3_jlog(T_tf) @ (J_f - _adjoint(_transform_inverse(T_rf)) @ J_r)


class PostureTask(Task):
    """Move towards ``q_ref (..., nq)`` on the configuration manifold (mink's ``PostureTask``): e = q ⊖ q_ref
    (``chain.difference(q_ref, q)``: the rotation vector between quaternions on ball joints), J = I; the
    floating base's (free joints') coordinates are not affected (their error and columns are 0). cost: a
    number or ``(..., nv)`` (>= 0); ``weight`` is the old name of ``cost``.

    :func:`~diffkin.ik.solve_velocity` adds it to the weighted sum (T.1); :func:`~diffkin.ik.velocity_step`
    keeps its own lower-priority mode (V.3) (the posture in the frame tasks' null space).
    """

    __slots__ = ("q_ref", "cost", "gain", "lm_damping")

    def __init__(self, q_ref, *, cost=1.0, gain=1.0, lm_damping=0.0, weight=None):
        self._set(q_ref=q_ref, cost=cost if weight is None else weight, gain=gain, lm_damping=lm_damping)

    @property
    def weight(self):
        """The old name of :attr:`cost`."""
        return self.cost

    def cost_vector(self, p: Problem, m: int) -> Tensor:
        return _per_axis(p, self.cost, f"{type(self).__name__}.cost", m)

    def _mask(self, p: Problem) -> Tensor | None:
        free = p.free_dofs()
        if not free:
            return None
        keep = torch.ones(p.nv, dtype=p.q.dtype, device=p.q.device)
        keep[free] = 0.0
        return keep

    def error(self, p: Problem) -> Tensor:
        q_ref = p.like("PostureTask.q_ref", self.q_ref, (p.q.shape[-1],))
        batch = broadcast_shapes(q_ref.shape, p.q.shape)
        e = p.chain.configuration_space.difference(q_ref.expand(batch), p.q.expand(batch))
        keep = self._mask(p)
        return e if keep is None else e * keep

    def jacobian(self, p: Problem) -> Tensor:
        keep = self._mask(p)
        eye = torch.eye(p.nv, dtype=p.q.dtype, device=p.q.device)
        return eye if keep is None else eye * keep


class DampingTask(PostureTask):
    """Penalise the joint displacement: ½ ‖W Δq‖² (mink's ``DampingTask``: a posture task with gain 0), the
    floating base excluded. cost: a number or ``(..., nv)``."""

    __slots__ = ()

    def __init__(self, cost=1.0):
        self._set(q_ref=None, cost=cost, gain=0.0, lm_damping=0.0)

    def error(self, p: Problem) -> Tensor:
        return torch.zeros(p.nv, dtype=p.q.dtype, device=p.q.device)


class ComTask(Task):
    """Move the centre of mass to ``target (..., 3)`` (base frame): e = c(q) − c_target, J = ∂c/∂q
    (``chain.center_of_mass`` / ``chain.com_jacobian``). cost: a number or ``(..., 3)``."""

    __slots__ = ("target", "cost", "gain", "lm_damping")

    def __init__(self, target, *, cost=1.0, gain=1.0, lm_damping=0.0):
        self._set(target=target, cost=cost, gain=gain, lm_damping=lm_damping)

    def cost_vector(self, p: Problem, m: int) -> Tensor:
        return _per_axis(p, self.cost, "ComTask.cost", 3)

    def _chain_has_com(self, p: Problem) -> None:
        if not hasattr(p.chain, "center_of_mass"):
            raise DiffkinError("ComTask: this chain has no centre of mass (chain.center_of_mass)")

    def error(self, p: Problem) -> Tensor:
        self._chain_has_com(p)
        return p.chain.center_of_mass(p.q) - p.like("ComTask.target", self.target, (3,))

    def jacobian(self, p: Problem) -> Tensor:
        self._chain_has_com(p)
        return p.chain.com_jacobian(p.q)
