"""Closed-loop inverse kinematics (CLIK, §3.7): a batched forward-Euler integrator tracking x_d(t).

Each step evaluates the end-effector pose and Jacobian in one FK pass, forms the operational-space error e,
computes q̇ (or q̈) with one of the book's laws and integrates with (3.48), q(t_{k+1}) = q(t_k) + q̇(t_k) Δt:

====================  ====================================================================================
``"inverse"``         q̇ = J⁻¹(ẋ_d + K e)  (3.70); K = 0 is the open-loop scheme (3.47) and its drift
``"pseudo_inverse"``  q̇ = J†(ẋ_d + K e) + (I − J†J) q̇₀  (3.72), q̇₀ = k₀ (∂w/∂q)ᵀ  (3.55)
``"dls"``             q̇ = J*(ẋ_d + K e) + (I − J*J) q̇₀ with the damped inverse J* (3.59)
``"transpose"``       q̇ = Jᵀ K e  (3.76)
``"second_order"``    q̈ = J†(ẍ_d + K_D ė + K_P e − J̇q̇) + (I − J†J) q̈₀  (3.102)/(3.104)
====================  ====================================================================================

J⁻¹ and J† are the Moore–Penrose inverse of :func:`diffkin.redundancy.pinv` (singular values below √eps·σ_max
count as zero, so a singular J gives finite velocities, never NaN); the second-order integrator also bounds
|q̇| (``qdot_max``), so every algorithm stays finite from any start. The orientation error and the matching
Jacobian (§3.7.3):

- ``None``: position only, e = p_d − p_e (3.78) with J_P;
- ``"euler"``: e_O = φ_d − φ_e (3.80) (wrapped to (−π, π]) with the analytical Jacobian (3.66), law (3.82);
- ``"axis_angle"``: e_O = r sin ϑ of R_d R_eᵀ (3.83)–(3.85) with the geometric Jacobian and the
  L-compensated reference L⁻¹(Lᵀω_d + K_O e_O) (3.87)–(3.89);
- ``"quaternion"``: e_O = Δε (3.91) with the geometric Jacobian, reference ω_d + K_O e_O (3.92).

``rows`` selects components of the 3- or 6-vector task (e.g. ``(0, 1, 3)`` = (x, y, φ) for the planar arm
with RPY angles, ``(0, 1)`` = planar position only), so the book's §3.7.5 runs as written. Null-space
objectives: ``"manipulability"`` w = √det(J Jᵀ) (3.56) of the task Jacobian, ``"joint_limits"`` (3.57), or
any callable w(q) (..., n) -> (...); their gradient comes from autograd over the batch.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from .._numerics import broadcast_shapes, eps_for, safe_norm, wrap_angle
from ..errors import ConventionError, ModelError, ShapeError
from ..jacobian import (
    _inverse3,
    forward_kinematics_and_jacobian,
    geometric_to_analytical,
    jacobian_dot_qdot,
)
from ..kernels.pose_error import orientation_error as _orientation_error
from ..manipulability import manipulability
from ..redundancy import _damped, _pinv
from ..rotations import (
    _convention,
    _euler_rate_matrix,
    _matrix_to_euler,
    _skew,
)
from ..validation import check_count, check_number, check_trailing, shape_str, tensors
from ._clik_tasks import clik_arguments, clik_limits
from .differential import least_squares, solve_step
from .tasks import FrameTask, Problem

__all__ = ["CLIKResult", "clik", "CLIK_ALGORITHMS", "CLIK_ORIENTATIONS", "joint_limit_objective"]

CLIK_ALGORITHMS = ("inverse", "pseudo_inverse", "dls", "transpose", "second_order")
CLIK_ORIENTATIONS = (None, "euler", "axis_angle", "quaternion")


class _CLIKFields(NamedTuple):
    t: Tensor
    q: Tensor
    qdot: Tensor
    error: Tensor
    position_error: Tensor
    orientation_error: Tensor
    poses: Tensor | None


class CLIKResult(_CLIKFields):
    """Time histories of a CLIK run (``S`` = steps + 1 samples, ``m`` task rows), a 7-tuple as before.

    t ``(S,)``; q, qdot ``(..., S, n)``; error e ``(..., S, m)`` (selected rows, as fed back);
    position_error / orientation_error ``(..., S)`` the norms of its position and orientation rows;
    poses ``(..., S, 4, 4)`` end-effector poses (``None`` unless ``return_poses=True``).

    ``success`` ``(...)`` bool (the result convention of :class:`~diffkin.ik.IKResult`): the last sample's
    errors within ``position_tolerance`` [m] / ``orientation_tolerance`` (the norm of the orientation rows),
    the tolerances :func:`clik` was given.
    """

    position_tolerance: float = 1e-4  # class defaults: what _make / _replace copies carry
    orientation_tolerance: float = 1e-3

    def __new__(cls, *fields, position_tolerance: float = 1e-4, orientation_tolerance: float = 1e-3,
                **named):
        self = super().__new__(cls, *fields, **named)
        self.position_tolerance, self.orientation_tolerance = position_tolerance, orientation_tolerance
        return self

    @property
    def success(self) -> Tensor:
        return (self.position_error[..., -1] <= self.position_tolerance) & (
            self.orientation_error[..., -1] <= self.orientation_tolerance)


class _Task(NamedTuple):
    orientation: str | None
    convention: str
    rows: tuple[int, ...]
    size: int  # 3 (position only) or 6


# ------------------------------------------------------------------------------------------ targets
def _time_axis(x: Tensor) -> int:
    return -3 if x.ndim >= 3 and tuple(x.shape[-2:]) == (4, 4) else -2


_TARGET_NAMES = ("x_d", "xdot_d", "xddot_d")


def _target_tensors(values, task: _Task, like: Tensor, time_axis: bool) -> tuple:
    """(x_d, ẋ_d, ẍ_d) by the rule of :mod:`diffkin.validation` (the chain's dtype and device, finite) with
    exact trailing shapes: x_d a pose (4, 4) or the task vector (6 = [p; φ] for ``"euler"``; 3 = p, or a
    6-vector [p; φ] whose position part is used, for position only), derivatives likewise; with
    ``time_axis`` each with the same number S of samples before it."""
    values = (tuple(values) + (None, None))[:3]
    x, v, a = tensors(*((n, t, None) for n, t in zip(_TARGET_NAMES, values)), like=like)
    sizes = (6,) if task.orientation == "euler" else (3, 6)
    pose = x.ndim >= 2 and tuple(x.shape[-2:]) == (4, 4)
    if not pose:
        if task.orientation in ("axis_angle", "quaternion"):
            raise ShapeError(f"orientation={task.orientation!r} needs x_d poses "
                             f"(..., {'S, ' * time_axis}4, 4), got {shape_str(x.shape)}")
        if x.ndim == 0 or x.shape[-1] not in sizes:
            raise ShapeError(f"expected x_d of shape (..., {' or '.join(map(str, sizes))}) (or poses "
                             f"(..., 4, 4)), got {shape_str(x.shape)}")
    lead = 1 + (2 if pose else 1)
    if time_axis and x.ndim < lead:
        raise ShapeError(f"expected x_d with a time axis, (..., S, 4, 4) or (..., S, {sizes[-1]}), got "
                         f"{shape_str(x.shape)}")
    for name, d in zip(_TARGET_NAMES[1:], (v, a)):
        if d is not None:
            size = 6 if task.size == 3 and d.ndim and d.shape[-1] == 6 else task.size  # [ṗ; ω] for p only
            check_trailing(d, (x.shape[-lead], size) if time_axis else (size,), name)
    return x, v, a


def _target_sampler(target, steps: int | None, dt: float, like: Tensor, task: _Task):
    """-> (get(k) -> (x_d, ẋ_d | None, ẍ_d | None), steps). Sequences hold their last sample at rest."""
    if callable(target):
        if steps is None:
            raise ConventionError("clik: pass steps (an integer >= 0) when the target is a function of time")
        steps = check_count(steps, "clik: steps", minimum=0)

        def get_fn(k: int):
            out = target(torch.tensor(k * dt, dtype=like.dtype, device=like.device))
            out = (out,) if isinstance(out, Tensor) else tuple(out)
            return _target_tensors(out, task, like, time_axis=False)

        return get_fn, steps
    seq = _as_tuple(target)
    if not 1 <= len(seq) <= 3 or seq[0] is None:
        raise ConventionError("clik: target must be a callable t -> (x_d, xdot_d[, xddot_d]) or such tensors")
    x, *rest = _target_tensors(seq, task, like, time_axis=True)
    ax = _time_axis(x)
    n_t = x.shape[ax]
    if n_t == 0:
        raise ShapeError(f"expected x_d with at least one sample on its time axis, got {shape_str(x.shape)}")
    steps = n_t - 1 if steps is None else steps
    steps = check_count(steps, "clik: steps", minimum=0)

    def get_seq(k: int):
        kk = min(k, n_t - 1)
        derivs = [None if (v is None or k >= n_t) else v.select(-2, kk) for v in rest]
        return (x.select(ax, kk), *derivs, None, None)[:3]

    return get_seq, steps


def _split_desired(task: _Task, x: Tensor):
    """A target sample -> (p_d, orientation part): R_d (..., 3, 3), φ_d (..., 3) or None."""
    if x.ndim >= 2 and tuple(x.shape[-2:]) == (4, 4):
        p, R = x[..., :3, 3], x[..., :3, :3]
        if task.orientation == "euler":
            return p, _matrix_to_euler(R, task.convention, "positive")
        return p, (None if task.orientation is None else R)
    return x[..., :3], (x[..., 3:6] if task.orientation == "euler" else None)


def _feed(v: Tensor | None, size: int, like: Tensor) -> Tensor:
    """A validated target derivative (..., size or 6), its first ``size`` components, or zeros."""
    if v is None:
        return torch.zeros(size, dtype=like.dtype, device=like.device)
    return v[..., :size]


# ------------------------------------------------------------------------------- error and Jacobian
def _error_and_jacobian(chain, q: Tensor, task: _Task, p_d: Tensor, o_d):
    """-> (T_e, e (..., D), task Jacobian (..., D, n), L (..., 3, 3) or None, J geometric)."""
    T, J = forward_kinematics_and_jacobian(chain, q, check=False)
    e_p = p_d - T[..., :3, 3]  # (3.78)
    if task.orientation is None:
        return T, e_p, J[..., :3, :], None, J
    R_e = T[..., :3, :3]
    L = None
    if task.orientation == "euler":
        phi_e = _matrix_to_euler(R_e, task.convention, "positive")
        e_o = wrap_angle(o_d - phi_e)  # (3.80), wrapped
        J_t = geometric_to_analytical(J, phi_e, task.convention)[0]  # (3.66)
    elif task.orientation == "axis_angle":
        e_o = _orientation_error(o_d, R_e, "axis_angle")[0]  # (3.85)
        L = _L_matrix(o_d, R_e)
        J_t = J
    else:
        e_o = _orientation_error(o_d, R_e, "quaternion")[0]  # (3.91)
        J_t = J
    e_p, e_o = torch.broadcast_tensors(e_p, e_o)
    return T, torch.cat((e_p, e_o), dim=-1), J_t, L, J


def _L_matrix(R_d: Tensor, R_e: Tensor) -> Tensor:
    """L = −½ (S(n_d)S(n_e) + S(s_d)S(s_e) + S(a_d)S(a_e))  (3.87)."""
    L = sum(_skew(R_d[..., :, i]) @ _skew(R_e[..., :, i]) for i in range(3))
    return -0.5 * L


def _solve_L(L: Tensor, b: Tensor) -> Tensor:
    """L⁻¹ b, falling back to b where L is near singular (|ϑ| ≥ π/2, outside (3.83)'s validity)."""
    L_inv, bad = _inverse3(L, 1e-3)  # cofactors: no batched LAPACK call for a 3 × 3 system
    return torch.where(bad[..., None], b, _mv(L_inv, b))


# ---------------------------------------------------------------------------------------- gains
def _gain(K, task: _Task, like: Tensor, name: str) -> Tensor:
    """Scalar, (m,) diagonal or (m, m) gain over the selected rows -> (D, D) over the full task vector."""
    m, D = len(task.rows), task.size
    (K,) = tensors((name, K, None), like=like)
    if K.ndim == 0:
        K = K * torch.eye(m, dtype=like.dtype, device=like.device)
    elif K.shape == (m,):
        K = torch.diag(K)
    elif K.shape != (m, m):
        raise ShapeError(f"expected {name} as a scalar, ({m},) or ({m}, {m}), got {tuple(K.shape)}")
    G = torch.zeros(D, D, dtype=like.dtype, device=like.device)
    idx = torch.tensor(task.rows, device=like.device)
    G[idx[:, None], idx[None, :]] = K
    return G


def _mv(A: Tensor, v: Tensor) -> Tensor:
    return torch.einsum("...ij,...j->...i", A, v)


# ----------------------------------------------------------------------------------- null space
def joint_limit_objective(q: Tensor, lower: Tensor, upper: Tensor) -> Tensor:
    """Distance from the joint limits w(q) = −1/(2n) Σ ((q_i − q̄_i)/(q_iM − q_im))² (3.57).

    q ``(..., n)``, lower/upper ``(n,)`` (finite, lower < upper) -> ``(...)``; 0 at the middle of the
    ranges, negative elsewhere.
    """
    q, lower, upper = tensors(("q", q, (None,)), ("lower", lower, None), ("upper", upper, None))
    n = q.shape[-1]
    check_trailing(lower, (n,), "lower")
    check_trailing(upper, (n,), "upper")
    return _joint_limit_objective(q, lower, upper)


def _joint_limit_objective(q: Tensor, lower: Tensor, upper: Tensor) -> Tensor:
    if not bool((upper > lower).all()):
        raise ModelError("joint_limit_objective needs lower < upper for every joint")
    mid = 0.5 * (lower + upper)
    return -(((q - mid) / (upper - lower)) ** 2).sum(-1) / (2 * q.shape[-1])


def _objective(nullspace, chain, task: _Task, q_limits) -> Callable[[Tensor], Tensor] | None:
    if nullspace is None:
        return None
    if callable(nullspace):
        return nullspace
    if nullspace == "manipulability":
        return lambda q: manipulability(_task_jacobian(chain, q, task))
    if nullspace == "joint_limits":
        lim = chain.q_limits if q_limits is None else \
            tensors(("q_limits", q_limits, (chain.n_joints, 2)), like=chain)[0]
        if lim is None:
            raise ModelError(f"nullspace='joint_limits' needs q_limits; chain '{chain.name}' has none")
        lo, hi = lim[..., 0].to(chain.device), lim[..., 1].to(chain.device)
        return lambda q: _joint_limit_objective(q, lo, hi)
    raise ConventionError(
        f"unknown nullspace objective {nullspace!r}; valid: None, 'manipulability', 'joint_limits', callable"
    )


def _task_jacobian(chain, q: Tensor, task: _Task) -> Tensor:
    T, J = forward_kinematics_and_jacobian(chain, q, check=False)
    if task.orientation == "euler":
        phi = _matrix_to_euler(T[..., :3, :3], task.convention, "positive")
        J = geometric_to_analytical(J, phi, task.convention)[0]
    return J[..., list(task.rows), :]


def _gradient(w: Callable[[Tensor], Tensor], q: Tensor) -> Tensor:
    """(∂w/∂q)ᵀ (..., n) by autograd over the batch (samples are independent, so grad of the sum)."""
    if q.requires_grad:
        return torch.autograd.grad(w(q).sum(), q, create_graph=True)[0]
    with torch.enable_grad():
        qg = q.detach().requires_grad_(True)
        return torch.autograd.grad(w(qg).sum(), qg)[0]


# ------------------------------------------------------------------------------------ J̇ q̇ (§3.7.4)
def _jdot_qdot(chain, q: Tensor, qd: Tensor, task: _Task) -> Tensor:
    """J̇_t q̇ of the task Jacobian (..., D): the geometric J̇q̇, and for J_A = T_A⁻¹J (3.66)
    J̇_A q̇ = [J̇_P q̇; T⁻¹(J̇_O q̇ − Ṫ φ̇)] with φ̇ = T⁻¹ω."""
    jdqd = jacobian_dot_qdot(chain, q, qd, check=False)
    if task.orientation != "euler":
        return jdqd[..., : task.size]
    T_e, J = forward_kinematics_and_jacobian(chain, q, check=False)
    phi = _matrix_to_euler(T_e[..., :3, :3], task.convention, "positive")
    T_inv = _inverse3(_euler_rate_matrix(phi, task.convention), eps_for(phi) ** 0.5)[0]
    phidot = _mv(T_inv, _mv(J[..., 3:, :], qd))
    rhs = jdqd[..., 3:] - _mv(_euler_rate_dot(phi, phidot, task.convention), phidot)
    return torch.cat((jdqd[..., :3], _mv(T_inv, rhs)), dim=-1)


def _euler_rate_dot(phi: Tensor, phidot: Tensor, convention: str) -> Tensor:
    """Ṫ(φ, φ̇) of (3.64): T's columns are z, [−s_φ, c_φ, 0] and one depending on (φ, ϑ)."""
    a, b = phi[..., 0], phi[..., 1]
    da, db = phidot[..., 0], phidot[..., 1]
    ca, sa, cb, sb = torch.cos(a), torch.sin(a), torch.cos(b), torch.sin(b)
    z = torch.zeros_like(a)
    col2 = torch.stack((-ca * da, -sa * da, z), -1)
    if convention == "ZYZ":  # [c_φ s_ϑ, s_φ s_ϑ, c_ϑ]
        col3 = torch.stack((-sa * sb * da + ca * cb * db, ca * sb * da + sa * cb * db, -sb * db), -1)
    else:  # RPY: [c_φ c_ϑ, s_φ c_ϑ, −s_ϑ]
        col3 = torch.stack((-sa * cb * da - ca * sb * db, ca * cb * da - sa * sb * db, -cb * db), -1)
    col2, col3 = torch.broadcast_tensors(col2, col3)
    return torch.stack((torch.zeros_like(col2), col2, col3), dim=-1)


# -------------------------------------------------------------------------------------------- laws
def _nullspace_term(J_inv: Tensor, J_s: Tensor, v0: Tensor) -> Tensor:
    """(I − J†J) v0 without forming the n × n projector."""
    return v0 - _mv(J_inv, _mv(J_s, v0))


def _reference(cfg, e, v_ff, L) -> Tensor:
    """The reference velocity ẋ_d + K e of (3.70)/(3.82)/(3.92), L-compensated for (3.89)."""
    Ge = _mv(cfg.K, e)
    v = v_ff + Ge
    if L is not None:  # (3.89): L⁻¹(Lᵀω_d + K_O e_O)
        v_o = _solve_L(L, _mv(L.mT, v_ff[..., 3:].expand_as(Ge[..., 3:])) + Ge[..., 3:])
        v = torch.cat(torch.broadcast_tensors(v[..., :3], v_o), dim=-1)
    return v


def _limited(cfg, chain, q, J, v, dt: float) -> Tensor:
    """``limits``: q̇ of :func:`~diffkin.ik.solve_velocity` (D.1)–(D.2) (= :func:`~diffkin.ik.velocity_step`
    (V.1)–(V.2)) for the reference v on the selected rows (weighted by the costs), λ = ``damping`` (k² of
    (3.59)): the DLS law with the limit objects (joint position and velocity limits) as bounds."""
    task = cfg.task
    zeros = torch.zeros(6, dtype=q.dtype, device=q.device)
    twist = torch.cat((v, zeros[task.size:].expand(*v.shape[:-1], 6 - task.size)), dim=-1)
    w = zeros.index_fill(0, torch.tensor(task.rows, device=q.device), 1.0)
    if cfg.W is not None:
        w = w * cfg.W
    p = Problem(chain, q, dt)
    p._fk = (None, J.unsqueeze(-3))  # the twist form reads only the Jacobian
    frame = FrameTask(0, twist=twist, position_cost=w[..., :3], orientation_cost=w[..., 3:])
    A, b, reg = least_squares(p, [frame], cfg.damping)
    return solve_step(p, A, b, reg, cfg.limits) / dt


def _weighted(cfg, J_s: Tensor, v_s: Tensor) -> tuple[Tensor, Tensor]:
    """W J and W v on the selected rows (the FrameTask's costs W; unchanged where every cost is 1)."""
    if cfg.W is None:
        return J_s, v_s
    w = cfg.W[..., list(cfg.task.rows)]
    return w[..., :, None] * J_s, w * v_s


def _first_order(cfg, q, J_t, e, v_ff, L) -> Tensor:
    rows = list(cfg.task.rows)
    if cfg.algorithm == "transpose":
        J_s, Ke = _weighted(cfg, J_t[..., rows, :], _mv(cfg.K, e)[..., rows])
        return _mv(J_s.mT, Ke)  # (3.76)
    v = _reference(cfg, e, v_ff, L)
    J_s, v_s = _weighted(cfg, J_t[..., rows, :], v[..., rows])
    J_inv = _damped(J_s, cfg.damping) if cfg.algorithm == "dls" else _pinv(J_s)
    qd = _mv(J_inv, v_s)
    if cfg.objective is not None:  # (3.72) with (3.55)
        qd = qd + _nullspace_term(J_inv, J_s, cfg.k0 * _gradient(cfg.objective, q))
    return qd


def _second_order(cfg, chain, q, qd, J_t, e, v_ff, a_ff) -> Tensor:
    """q̈ = J†(ẍ_d + K_D ė + K_P e − J̇q̇) + (I − J†J) q̈₀ (3.102)/(3.104), q̈₀ = k₀ ∇w − k_d0 q̇."""
    rows = list(cfg.task.rows)
    e_dot = v_ff - _mv(J_t, qd)  # ė = ẋ_d − J q̇ (3.68)
    a = a_ff + _mv(cfg.K_D, e_dot) + _mv(cfg.K_P, e) - _jdot_qdot(chain, q, qd, cfg.task)
    J_s, a_s = _weighted(cfg, J_t[..., rows, :], a[..., rows])
    J_inv = _pinv(J_s)
    qdd = _mv(J_inv, a_s)
    if cfg.objective is not None or cfg.k_d0 != 0.0:
        qdd0 = -cfg.k_d0 * qd
        if cfg.objective is not None:
            qdd0 = qdd0 + cfg.k0 * _gradient(cfg.objective, q)
        qdd = qdd + _nullspace_term(J_inv, J_s, qdd0)
    return qdd


class _Config(NamedTuple):
    task: _Task
    algorithm: str
    K: Tensor
    K_P: Tensor
    K_D: Tensor
    damping: float
    objective: Callable | None
    k0: float
    k_d0: float
    qdot_max: float | None
    limits: tuple | None  # the limit objects of the limited DLS step
    W: Tensor | None  # the FrameTask's costs (..., 6), None where all are 1


def _qdot_max(v, dt: float) -> float:
    if v is None:
        return math.pi / (4.0 * dt)
    return check_number(v, "qdot_max", unit=" (rad/s)")


def _make_task(chain, orientation, convention, rows) -> _Task:
    if orientation not in CLIK_ORIENTATIONS:
        raise ConventionError(f"unknown orientation {orientation!r}; valid: {CLIK_ORIENTATIONS}")
    size = 3 if orientation is None else 6
    rows = tuple(range(size)) if rows is None else tuple(int(r) for r in rows)
    if not rows or len(set(rows)) != len(rows) or not all(0 <= r < size for r in rows):
        raise ShapeError(f"rows must be distinct indices into the {size}-vector task, got {rows}")
    return _Task(orientation, _convention(convention), rows, size)


def _check_order(T_target, q0) -> None:
    """A typed error for ``clik(chain, q0, T_target, ...)``, the old argument order: a target has a
    time axis (or is a callable or a tuple of tensors), a ``q0`` has none."""
    if callable(q0) or (isinstance(q0, tuple | list) and any(isinstance(v, Tensor) for v in q0)):
        raise ShapeError("ik.clik: q0 is a target (a callable or a tuple of tensors); the order is "
                         "clik(chain, T_target, q0, dt, ...)")
    numbers = isinstance(T_target, tuple | list) and all(isinstance(v, int | float) for v in T_target)
    if numbers or (isinstance(T_target, Tensor) and T_target.dim() <= 1):
        shape = (len(T_target),) if numbers else tuple(T_target.shape)
        raise ShapeError(f"ik.clik: T_target of shape {shape} has no time axis (it looks like q0); the "
                         "order is clik(chain, T_target, q0, dt, ...)")


def clik(
    chain,
    T_target=None,
    q0: Tensor | None = None,
    dt: float | None = None,
    steps: int | None = None,
    *,
    algorithm: str = "pseudo_inverse",
    orientation: str | None = "axis_angle",
    convention: str = "ZYZ",
    rows: Sequence[int] | None = None,
    K=None,
    K_P=None,
    K_D=None,
    damping: float = 1e-4,
    nullspace=None,
    k0: float = 0.0,
    k_d0: float = 0.0,
    q_limits=None,
    qdot0: Tensor | None = None,
    qdot_max: float | None = None,
    clamp: bool = False,
    return_poses: bool = False,
    differentiable: bool | None = None,
    limits=False,
    position_tolerance: float = 1e-4,
    orientation_tolerance: float = 1e-3,
    tasks=None,
) -> CLIKResult:
    """Closed-loop inverse kinematics along x_d(t), integrated with forward Euler (3.48) (§3.7).

    Args:
        chain: a :class:`~diffkin.chain.KinematicChain`.
        T_target: the target, before ``q0`` (the old order, ``clik(chain, q0, target)``, raises
            :class:`~diffkin.errors.ShapeError` where a 1-D ``T_target`` or a callable or tuple of tensors
            as ``q0`` shows it): a function
            ``t -> (x_d, ẋ_d[, ẍ_d])`` of a scalar time tensor (``steps`` required), or the tensors
            ``(x_d, ẋ_d[, ẍ_d])`` with a time axis sampled every ``dt``: x_d ``(..., S, 4, 4)`` or
            ``(..., S, 3|6)``, derivatives ``(..., S, 3|6)``; ``None`` derivatives are zero. Past the last
            sample the target holds still. x_d is a pose, or ``[p; φ]`` for ``"euler"`` (φ̇ in ẋ_d), or ``p``
            for position only; ẋ_d = [ṗ_d; ω_d] for ``"axis_angle"``/``"quaternion"``.
        q0: initial joints ``(..., n)``; the batch broadcasts with the target's.
        dt: the integration step Δt (the book uses 1 ms). steps: number of Euler steps.
        algorithm: one of ``CLIK_ALGORITHMS`` (module table). orientation: one of ``CLIK_ORIENTATIONS``.
        convention: Euler angles for ``"euler"`` (``"ZYZ"`` or ``"RPY"``).
        rows: task components to control (default all): indices into [p; o].
        K: gain of the first-order laws (scalar, (m,) or (m, m); default 0.5/Δt = the book's 500 at 1 ms).
            ``K=0`` with ``"inverse"`` is the open-loop scheme (3.47).
        K_P, K_D: second-order gains (default ω² and 2ω with ω = 0.1/Δt).
        damping: λ = k² of the damped least-squares inverse (3.59), Jᵀ(JJᵀ + λI)⁻¹ (the one meaning of
            ``damping`` in the velocity-level solvers, as :func:`~diffkin.ik.solve_velocity`'s).
            nullspace: ``None``, ``"manipulability"``, ``"joint_limits"`` or a callable w(q) -> (...); k0:
            its gain (3.55); k_d0: damping of the null-space acceleration (second order). q_limits:
            ``(n, 2)`` limits for ``"joint_limits"`` (default the chain's). qdot0: initial q̇ for the second
            order (default J†ẋ_d(0)).
        qdot_max: bound on |q̇| per joint of the second-order integrator (default π/(4Δt), a quarter turn
            per step: never reached by a run that converges; it keeps a diverging one — gains too high for
            the error, a pass near a singularity — finite, with its errors reported as they are).
        clamp: project q onto the chain's joint limits after each step. return_poses: keep the poses.
        limits: hard limits (with ``algorithm="dls"``): each q̇ is :func:`~diffkin.ik.solve_velocity`'s
            exact solution of the DLS problem (3.59) with λ = ``damping`` under the bounds of the limit
            objects, :class:`~diffkin.ik.ConfigurationLimit` (q + q̇Δt within γ of the way to the chain's
            joint limits) and :class:`~diffkin.ik.VelocityLimit` (|q̇| ≤ its bound): the step near a
            limit is redistributed to the other joints instead of cut (orientation ``None``,
            ``"axis_angle"`` or ``"quaternion"``; no ``nullspace``). ``True`` is the shorthand for
            ``[ConfigurationLimit(gain=1.0)]`` and, if ``qdot_max`` is given, ``VelocityLimit(qdot_max)``.
        tasks: the tracking problem as objects (:mod:`diffkin.ik._clik_tasks`) instead of ``T_target``,
            ``rows``, ``K`` and ``nullspace``: one :class:`~diffkin.ik.FrameTask` with ``target`` x_d
            ``(..., S, 4, 4)`` (its costs select and weight the rows, its gain α gives K = α/Δt unless
            ``K`` is given), optionally a FrameTask with ``twist`` ẋ_d ``(..., S, 6)`` (the feed-forward)
            and a :class:`~diffkin.ik.PostureTask` (the null-space objective w = −½‖c (q ⊖ q_ref)‖²,
            k₀ = α/Δt). The shorthand arguments are this problem: ``clik(chain, (x_d, ẋ_d), q0, dt,
            rows=(0, 1, 2), K=k)`` is ``clik(chain, q0=q0, dt=dt, K=k, tasks=[FrameTask(0, target=x_d,
            orientation_cost=0), FrameTask(0, twist=ẋ_d)])`` (``tests/test_clik_tasks.py``).
        differentiable: record the autograd graph through all the steps (w.r.t. q0, the target and the
            chain's DH parameters). Default: only when grad mode is on and q0 or a target tensor requires
            grad, since a graph over thousands of steps is costly; pass True for gradients w.r.t. the chain
            or through a callable target.
        position_tolerance, orientation_tolerance: the final errors below which
            :attr:`CLIKResult.success` is True (m; the norm of the orientation rows).

    Returns:
        :class:`CLIKResult`.
    """
    if algorithm not in CLIK_ALGORITHMS:
        raise ConventionError(f"unknown algorithm {algorithm!r}; valid: {CLIK_ALGORITHMS}")
    if q0 is None or dt is None:
        raise ConventionError("ik.clik needs q0 and dt")
    _check_order(T_target, q0)
    q = chain.check_q(q0, name="q0")
    check_number(dt, "dt", unit=" (s)")
    weights = None
    if tasks is not None:  # the objects, translated to the arguments below (diffkin.ik._clik_tasks)
        T_target, orientation, rows, weights, K, nullspace, k0 = clik_arguments(
            chain, T_target, tasks, dt, orientation, rows, K, nullspace, k0)
    elif T_target is None:
        raise ConventionError("ik.clik needs a target: T_target, or tasks=[FrameTask(0, target=x_d)]")
    limit_objs = clik_limits(limits, qdot_max)
    task = _make_task(chain, orientation, convention, rows)
    if algorithm == "inverse" and len(task.rows) != chain.n_joints:
        raise ShapeError(
            f"algorithm='inverse' needs a square Jacobian: {len(task.rows)} task rows for {chain.n_joints} "
            "joints; use 'pseudo_inverse' or 'dls', or select rows"
        )
    if qdot0 is not None:
        qdot0 = chain.check_q(qdot0, name="qdot0")
    _check_limits_mode(limit_objs, algorithm, orientation, nullspace, damping)
    if limit_objs is not None:  # the QP's velocity bound: only the one asked for (a VelocityLimit)
        qd_max = None if qdot_max is None else check_number(qdot_max, "qdot_max", unit=" (rad/s)")
    else:
        qd_max = _qdot_max(qdot_max, dt)
    tolerances = {"position_tolerance": check_number(position_tolerance, "position_tolerance", unit=" (m)"),
                  "orientation_tolerance": check_number(orientation_tolerance, "orientation_tolerance")}
    get, steps = _target_sampler(T_target, steps, dt, q, task)
    omega = 0.1 / dt
    cfg = _Config(
        task,
        algorithm,
        _gain(0.5 / dt if K is None else K, task, q, "K"),
        _gain(omega**2 if K_P is None else K_P, task, q, "K_P"),
        _gain(2 * omega if K_D is None else K_D, task, q, "K_D"),
        tensors(("damping", damping, None), like=q)[0],
        _objective(nullspace, chain, task, q_limits),
        float(k0),
        float(k_d0),
        qd_max,
        limit_objs,
        weights,
    )
    if differentiable is None:
        values = [] if callable(T_target) else _as_tuple(T_target)
        given = [q] + [v for v in values if isinstance(v, Tensor)]
        differentiable = torch.is_grad_enabled() and any(v.requires_grad for v in given)
    with contextlib.nullcontext() if differentiable else torch.no_grad():
        res = _integrate(chain, q, qdot0, get, steps, dt, cfg, clamp, return_poses)
    return CLIKResult(*res, **tolerances)


def _check_limits_mode(limits, algorithm, orientation, nullspace, damping) -> None:
    if limits is None:
        return
    if algorithm != "dls" or orientation == "euler" or nullspace is not None:
        raise ConventionError(
            "clik(limits=True, or limit objects) solves the DLS law (3.59) under the joint limits: it needs "
            "algorithm='dls', orientation None, 'axis_angle' or 'quaternion' and no nullspace; got "
            f"algorithm={algorithm!r}, orientation={orientation!r}, nullspace={nullspace!r}")
    check_number(damping, "damping (λ of (3.59), > 0 with limits)")


def _as_tuple(target) -> tuple:
    # an array (numpy, anything with a shape) is one x_d, not a sequence of its rows
    return (target,) if isinstance(target, Tensor) or hasattr(target, "shape") else tuple(target)


def _integrate(chain, q, qd, get, steps, dt, cfg: _Config, clamp: bool, return_poses: bool) -> CLIKResult:
    task, n, nv, space = cfg.task, chain.n_joints, chain.nv, chain.configuration_space
    if cfg.algorithm == "second_order" and not space.euclidean:
        raise ConventionError("algorithm='second_order' needs chains of 1-DOF joints (J̇q̇ of ball and free "
                              "joints is not implemented); use a first-order algorithm")
    qs, qds, es, Ts = [], [], [], []
    for k in range(steps + 1):
        x_d, v_d, a_d = get(k)
        p_d, o_d = _split_desired(task, x_d)
        T, e, J_t, L, J = _error_and_jacobian(chain, q, task, p_d, o_d)
        v_ff = _feed(v_d, task.size, q)
        if k == 0:
            batch = broadcast_shapes(e.shape[:-1], v_ff.shape[:-1], q.shape[:-1])
            q = q.expand(*batch, n)
        if cfg.algorithm == "second_order":
            if qd is None:
                qd = _mv(_pinv(J_t[..., list(task.rows), :]), v_ff[..., list(task.rows)].expand(*batch, -1))
                qd = qd.clamp(-cfg.qdot_max, cfg.qdot_max)
            qd = qd.expand(*batch, n)
            qdd = _second_order(cfg, chain, q, qd, J_t, e, v_ff, _feed(a_d, task.size, q))
        elif cfg.limits is not None:
            qd = _limited(cfg, chain, q, J, _reference(cfg, e, v_ff, L), dt).expand(*batch, n)
        else:
            qd = _first_order(cfg, q, J_t, e, v_ff, L).expand(*batch, nv)
        qs.append(q)
        qds.append(qd)
        es.append(e[..., list(task.rows)].expand(*batch, -1))
        if return_poses:
            Ts.append(T.expand(*batch, 4, 4))
        if k < steps:
            q_next = space.integrate(q, qd * dt)  # (3.48); on the manifold for ball and free joints
            if cfg.algorithm == "second_order":  # q̇ bounded: a diverging run stays finite
                qd = (qd + qdd * dt).clamp(-cfg.qdot_max, cfg.qdot_max)
            q = chain.clamp_to_limits(q_next, check=False) if clamp else q_next
    err = torch.stack(es, dim=-2)
    pos = torch.tensor([r < 3 for r in task.rows], device=err.device)
    zero = torch.zeros((), dtype=err.dtype, device=err.device)
    return CLIKResult(
        t=torch.arange(steps + 1, dtype=q.dtype, device=q.device) * dt,
        q=torch.stack(qs, dim=-2),
        qdot=torch.stack(qds, dim=-2),
        error=err,
        position_error=safe_norm(torch.where(pos, err, zero)),
        orientation_error=safe_norm(torch.where(pos, zero, err)),
        poses=torch.stack(Ts, dim=-3) if return_poses else None,
    )
