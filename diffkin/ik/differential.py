"""Differential IK from task and limit objects: mink's ``solve_ik``, batched and differentiable.

:func:`solve_velocity` returns, per batch row, q̇ = Δq/Δt with Δq the solution of the QP

    min_Δq  Σ_tasks ½ ‖W (J Δq + α e)‖² + ½ (λ + Σ_tasks μ ‖W α e‖²) ‖Δq‖²                          (D.1)
    s.t.    lo ≤ Δq ≤ hi,  G Δq ≤ h   (the limits)                                                    (D.2)

(:mod:`diffkin.ik.tasks` (T.1) summed, :mod:`diffkin.ik.limits` (L.1)–(L.3)); λ = ``damping`` is the
coefficient of the squared step, the textbook's k² of the damped least-squares inverse (3.59) — the one
meaning of ``damping`` in every velocity-level solver (:func:`~diffkin.ik.velocity_step`,
:func:`~diffkin.ik.clik`). The next configuration is ``chain.integrate(q, q̇ Δt)`` (3.48).

With box limits only, (D.1)–(D.2) is :func:`diffkin.ik.qp.box_qp` (an exact active set) on
H = AᵀA + (λ + Σμ‖b‖²) I, g = Aᵀ b (A = [W J] stacked, b = [−α W e] stacked). Where the rows of A span
more than 1e4 in norm (extreme weights: 1e8 beside 1), forming AᵀA loses the digits that matter: the free
variables are then re-solved as the least squares [A_F; √(λ+Σμ‖b‖²) I] Δq_F = [b − A_A Δq_A; 0] by QR
factorisations, which do not square A's condition number, with primal-dual active-set rounds on them.
Rows (collision limits) make it the general QP (:func:`diffkin.ik.qp.solve_qp`'s interior point) with the
boxes as rows. Both are differentiable (KKT gradients) w.r.t. q and every task and limit tensor (targets,
twists, costs, gains).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from .._numerics import broadcast_shapes
from ..errors import ConventionError
from ..validation import check_nonnegative, check_number, tensors
from . import _native_velocity
from .limits import Limit, check_limits, combine_boxes
from .qp import _solve_box, _solve_general
from .tasks import Problem, Task, objects_of

__all__ = ["solve_velocity"]


def check_tasks(tasks) -> tuple[Task, ...]:
    kinds = "FrameTask, RelativeFrameTask, PostureTask, ComTask, DampingTask"
    tasks = objects_of(tasks, Task, "tasks", kinds)
    if not tasks:
        raise ConventionError("expected at least one task")
    return tasks


def least_squares(p: Problem, tasks: Sequence[Task], damping: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """A ``(..., M, nv)``, b ``(..., M)`` and the regulariser λ + Σμ‖b‖² ``(...)`` of (D.1)."""
    parts = [t.least_squares(p) for t in tasks]
    batch = broadcast_shapes(p.q.shape[:-1], damping.shape, *(a.shape[:-2] for a, _, _ in parts),
                                   *(b.shape[:-1] for _, b, _ in parts), *(m.shape for _, _, m in parts))
    A = torch.cat([a.expand(*batch, *a.shape[-2:]) for a, _, _ in parts], dim=-2)
    b = torch.cat([b.expand(*batch, b.shape[-1]) for _, b, _ in parts], dim=-1)
    reg = damping + sum(m for _, _, m in parts)
    return A, b, reg.expand(batch)


def _qr_solve(A: Tensor, b: Tensor, reg: Tensor, x: Tensor, fixed: Tensor) -> Tensor:
    """The least squares of (D.1) with the ``fixed`` variables held at x, by QR of [A_F; √reg I_F]."""
    free = (~fixed).to(x.dtype)
    x_fix = torch.where(fixed, x, torch.zeros_like(x))
    M = torch.cat((A * free[..., None, :], torch.diag_embed(free * reg.sqrt()[..., None] + (1.0 - free))),
                  dim=-2)
    rhs = torch.cat((b - (A @ x_fix.unsqueeze(-1)).squeeze(-1), x_fix), dim=-1)
    Q, R = torch.linalg.qr(M)
    return torch.linalg.solve_triangular(R, Q.mT @ rhs.unsqueeze(-1), upper=True).squeeze(-1)


def _objective(A: Tensor, b: Tensor, reg: Tensor, x: Tensor) -> Tensor:
    r = (A @ x.unsqueeze(-1)).squeeze(-1) - b
    return (r * r).sum(-1) + reg * (x * x).sum(-1)


def _refine(A: Tensor, b: Tensor, reg: Tensor, x: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """x re-solved without forming AᵀA (module docstring): QR solves on the box QP's active set, then
    primal-dual active-set rounds (Hintermüller, Ito & Kunisch) on QR solves; of these points the feasible
    one of least objective (D.1), evaluated unsquared, is kept per row (never worse than the box QP's). The
    gradient stays the box QP's (the same KKT point wherever its active set was right)."""
    with torch.no_grad():
        best, best_f = x, _objective(A, b, reg, x)
        tol = 1e-12 * (1.0 + torch.maximum(lo.abs(), hi.abs()).nan_to_num(posinf=0.0))
        none = torch.zeros_like(x, dtype=torch.bool)
        for at_lo, at_hi in ((x <= lo, x >= hi), (none, none)):  # from the box QP's set, and from none
            for _ in range(x.shape[-1] + 2):
                y = _qr_solve(A, b, reg, torch.where(at_lo, lo, torch.where(at_hi, hi, x)), at_lo | at_hi)
                feasible = torch.isfinite(y).all(-1) & ((y >= lo - tol) & (y <= hi + tol)).all(-1)
                y = torch.minimum(torch.maximum(y, lo), hi)
                f = _objective(A, b, reg, y)
                better = feasible & (f < best_f)
                best, best_f = torch.where(better[..., None], y, best), torch.where(better, f, best_f)
                r = (A @ y.unsqueeze(-1)).squeeze(-1) - b
                grad = (A.mT @ r.unsqueeze(-1)).squeeze(-1) + reg[..., None] * y
                inside = ~at_lo & ~at_hi
                new_lo = (at_lo & (grad >= 0)) | (inside & (y <= lo))
                new_hi = (at_hi & (grad <= 0)) | (inside & (y >= hi))
                if bool(((new_lo == at_lo) & (new_hi == at_hi)).all()):
                    break
                at_lo, at_hi = new_lo, new_hi
    return x + (best - x).detach()


_EXTREME = 1e4  # row-norm ratio of A beyond which the box QP's answer is re-solved by QR (_refine)


def _extreme(A: Tensor) -> bool:
    """Whether the weighted rows span more than ``_EXTREME`` in norm in some batch row (weights like 1e8
    beside 1): there AᵀA loses the digits _refine recovers. One host read."""
    n = torch.linalg.vector_norm(A, dim=-1)
    top = n.amax(-1)
    low = torch.where(n > 0, n, torch.full_like(n, float("inf"))).amin(-1)
    return bool((top > _EXTREME * low).any())


def solve_step(p: Problem, A: Tensor, b: Tensor, reg: Tensor, limits: Sequence[Limit]) -> Tensor:
    """Δq ``(..., nv)`` of (D.1)–(D.2) for the stacked least squares (A, b, reg)."""
    nv = p.nv
    eye = torch.eye(nv, dtype=A.dtype, device=A.device)
    H = A.mT @ A + reg[..., None, None] * eye
    g = (A.mT @ b.unsqueeze(-1)).squeeze(-1)
    box = combine_boxes(limits, p)
    inf = torch.tensor(float("inf"), dtype=A.dtype, device=A.device)
    lo, hi = box if box is not None else (-inf.expand(nv), inf.expand(nv))
    rows = [r for lim in limits if (r := lim.rows(p)) is not None]
    if not rows:
        x = _solve_box(H, g, lo, hi)
        if not _extreme(A):
            return x
        batch = x.shape[:-1]
        return _refine(A.expand(*batch, *A.shape[-2:]), b.expand(*batch, b.shape[-1]), reg.expand(batch), x,
                       lo.expand(*batch, nv), hi.expand(*batch, nv))
    batch = broadcast_shapes(H.shape[:-2], lo.shape[:-1], hi.shape[:-1],
                                   *(G.shape[:-2] for G, _ in rows), *(h.shape[:-1] for _, h in rows))
    I = eye.expand(*batch, nv, nv)
    G = torch.cat([G.expand(*batch, *G.shape[-2:]) for G, _ in rows] + [I, -I], dim=-2)
    h = torch.cat([h.expand(*batch, h.shape[-1]) for _, h in rows]
                  + [hi.expand(*batch, nv), -lo.expand(*batch, nv)], dim=-1)
    x = _solve_general(H, g, G, h)
    return torch.minimum(torch.maximum(x, lo), hi)  # the boxes exactly (rounding of the interior point)


def solve_velocity(chain, q, tasks, dt, *, limits=(), damping=1e-12) -> Tensor:
    """Joint velocities q̇ ``(..., nv)`` of the differential IK problem (D.1)–(D.2): mink's ``solve_ik``
    batched (module docstring).

    Args:
        chain: a :class:`~diffkin.chain.KinematicChain`.
        q: configurations ``(..., nq)``.
        tasks: :class:`~diffkin.ik.FrameTask`, :class:`~diffkin.ik.RelativeFrameTask`,
            :class:`~diffkin.ik.PostureTask`, :class:`~diffkin.ik.ComTask`, :class:`~diffkin.ik.DampingTask`
            (one or a sequence); their tensors broadcast with q's batch dims.
        dt: the step Δt (s), > 0.
        limits: :class:`~diffkin.ik.ConfigurationLimit`, :class:`~diffkin.ik.VelocityLimit`,
            :class:`~diffkin.ik.CollisionLimit` (hard constraints; none by default, unlike mink, whose
            ``limits=None`` means a ConfigurationLimit).
        damping: λ of (D.1) (= k² of (3.59)), >= 0: a number or ``(...)`` per row.

    Returns:
        q̇ ``(..., nv)``, differentiable (KKT gradients) w.r.t. q and the tasks' and limits' tensors.

    Every limit holds after ``chain.integrate(q, q̇ * dt)`` to rounding (boxes exactly).

    On the CPU without autograd, one C call serves these combinations
    (:func:`diffkin.ik._native_velocity.route` gives the details):

    - tasks: any number of :class:`~diffkin.ik.FrameTask` with a ``target`` pose, at most one
      :class:`~diffkin.ik.PostureTask` and at most one :class:`~diffkin.ik.ComTask` (a chain with link
      masses), costs numbers or per axis, gains and damping numbers;
    - limits: at most one each of :class:`~diffkin.ik.ConfigurationLimit`,
      :class:`~diffkin.ik.VelocityLimit` and :class:`~diffkin.ik.CollisionLimit` (a collision model of
      capsules and spheres on this chain; a world of spheres, capsules, half-spaces and points without batch
      dims, or none); with collision rows the QP (D.1)–(D.2) is solved exactly by a dual active set.

    Everything else (``FrameTask(twist=...)``, :class:`~diffkin.ik.RelativeFrameTask`,
    :class:`~diffkin.ik.DampingTask`, box geoms or world boxes, a batched world, batched costs, a gradient
    wanted, CUDA) runs the torch path. The two agree to rounding (1e-9 in float64:
    ``tests/test_native_velocity.py``, ``tests/test_native_velocity_rows.py``), except where collision
    rows bind nearly dependently: there the C step's exact active set equals daqp's answer at tolerance
    1e-12, and the torch path's polished interior point may be off by up to ~1e-6.
    """
    fast = _native_velocity.route(chain, q, tasks, dt, limits, damping)  # the C step, where it serves
    if fast is not None:
        return fast
    q = chain.check_q(q)
    dt = check_number(dt, "dt", unit=" (s)")
    (lam,) = tensors(("damping", damping, None), like=chain)
    check_nonnegative(lam, "damping (λ of (D.1))")
    tasks, limits = check_tasks(tasks), check_limits(limits)
    p = Problem(chain, q, dt)
    A, b, reg = least_squares(p, tasks, lam)
    return solve_step(p, A, b, reg, limits) / dt
