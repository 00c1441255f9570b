"""Calibration solvers for K robots at once: iterated least squares (2.85)–(2.89) and gradient descent.

Both work on ``zeta (K, P)`` (the full parameter vector) and a ``free (K, C)`` mask over the C candidate
parameters of the model (True: identifiable, estimated); the other entries of ζ never move. Histories are
lists of ``(K,)`` tensors, one per iteration, the first at ζ_n.
"""

from __future__ import annotations

import math
import sys
import warnings
from contextlib import contextmanager
from dataclasses import dataclass

import torch
from torch import Tensor

from .._numerics import broadcast_shapes, eps_for, tol_for
from ..errors import ConventionError, DiffkinError, ShapeError
from ..kernels.dls import dls_solve
from ..validation import _traced, check_number, shape_str, tensors
from .model import CalibrationModel, measurement_shapes

__all__ = ["calibration_loss", "robust_loss", "robust_weights", "least_squares", "gradient_descent",
           "SolverOutput", "LOSSES", "kfold_split", "fold_fits"]

LOSSES = ("huber", "cauchy", "soft_l1", "l2")


def kfold_split(N: int, folds: int, device, min_train: int = 1) -> tuple[Tensor, Tensor] | None:
    """``(train (k, N − N//k), test (k, N//k))`` row indices of a k-fold split of N measurements (one fixed
    random permutation, seed 0: reproducible); None when a fold would have no test row or fewer than
    ``min_train`` training rows."""
    n_test = N // folds
    if folds < 2 or n_test < 1 or N - n_test < min_train:
        return None
    perm = torch.randperm(N, generator=torch.Generator().manual_seed(0), device="cpu").to(device)
    test = perm[: folds * n_test].reshape(folds, n_test)
    train = torch.stack([perm[torch.isin(perm, t, invert=True)] for t in test])
    return train, test


def fold_fits(model, theta0: Tensor, free: Tensor, x: Tensor, measured: Tensor, solve, opts: dict, folds: int,
              min_train: int = 1):
    """The k fits of a k-fold split (:func:`kfold_split`) of one robot's data ``x (N, ...)``, ``measured
    (N, ...)`` from ``theta0 (1, P)`` with the free mask ``free (1, C)``, as one batch of ``solve``
    (warnings silenced: the full fit reports): ``(SolverOutput, test indices (k, N//k))`` or None."""
    split = kfold_split(x.shape[0], folds, x.device, min_train)
    if split is None:
        return None
    train, test = split
    k = train.shape[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = solve(model, theta0.expand(k, -1).clone(), free.expand(k, -1), x[train], measured[train],
                    orientation_weight=1.0, **dict(opts, progress=False))
    return out, test


@dataclass
class SolverOutput:
    zeta: Tensor  # (K, P)
    position_rms: list[Tensor]  # per iteration, (K,) metres
    orientation_rms: list[Tensor] | None  # per iteration, (K,) radians (unweighted)
    iterations: int
    converged: Tensor  # (K,) bool


@contextmanager
def _progress(enabled: bool, description: str, total: int):
    """A rich progress bar on a terminal, a no-op otherwise. Yields ``advance()``."""
    try:
        from rich.progress import Progress
    except ImportError:  # the bar is a `cli` extra nicety
        enabled = False
    if not (enabled and sys.stderr.isatty()):
        yield lambda: None
        return

    with Progress(transient=True) as bar:
        task = bar.add_task(description, total=total)
        yield lambda: bar.advance(task)


def _rms(res: Tensor, orientation_weight: float) -> tuple[Tensor, Tensor | None]:
    """Per-robot RMS of the position and (unweighted) orientation residual norms: (K, N, m) -> (K,), (K,)."""
    pos = res[..., :3].square().sum(-1).mean(-1).sqrt()
    if res.shape[-1] == 3:
        return pos, None
    return pos, (res[..., 3:].square().sum(-1).mean(-1).sqrt() / orientation_weight)


def robust_loss(sq_norm: Tensor, loss: str, scale: float) -> Tensor:
    """ρ(s) of the squared residual norm s ≥ 0 (units m²), quadratic (= s) for √s ≤ ``scale`` (metres).

    ``"huber"``: ρ = s for √s ≤ c, 2c√s − c² beyond; ``"cauchy"``: ρ = c² log(1 + s/c²) (redescending: an
    outlier's pull falls off as 1/√s); ``"soft_l1"``: ρ = 2c²(√(1 + s/c²) − 1); ``"l2"``: ρ = s.
    ``sq_norm`` of any shape, by the rule of :mod:`diffkin.validation` (finite; numbers and numpy arrays
    converted); negative entries raise ``DiffkinError``.
    """
    if loss not in LOSSES:
        raise ConventionError(f"unknown loss {loss!r}; valid: {', '.join(LOSSES)}")
    scale = check_number(scale, "scale", unit=" (metres)")
    (s,) = tensors(("sq_norm", sq_norm, None))
    if not _traced(s) and s.numel() and bool((s < 0).any()):
        raise DiffkinError(
            f"sq_norm holds negative values (min {float(s.min()):.3g}); expected squared norms >= 0"
        )
    return _robust_loss(s, loss, scale)


def _robust_loss(sq_norm: Tensor, loss: str, scale: float) -> Tensor:
    """:func:`robust_loss` on trusted input."""
    if loss == "l2":
        return sq_norm
    c2 = scale * scale
    if loss == "cauchy":
        return c2 * torch.log1p(sq_norm / c2)
    if loss == "soft_l1":
        return 2.0 * c2 * (torch.sqrt(1.0 + sq_norm / c2) - 1.0)
    if loss == "huber":
        big = sq_norm > c2
        s_safe = torch.where(big, sq_norm, torch.full_like(sq_norm, c2))  # double where: no grad of sqrt at 0
        return torch.where(big, 2.0 * scale * torch.sqrt(s_safe) - c2, sq_norm)
    raise ConventionError(f"unknown loss {loss!r}; valid: {', '.join(LOSSES)}")


def robust_weights(sq_norm: Tensor, loss: str, scale: float) -> Tensor:
    """ρ'(s), the iteratively reweighted least-squares weight of each squared residual norm (1 for "l2" and
    inside the quadratic zone), by autograd of :func:`robust_loss` (one encoding of ρ). Trusted input."""
    if loss == "l2":
        return torch.ones_like(sq_norm)
    with torch.enable_grad():
        s = sq_norm.detach().requires_grad_(True)
        (w,) = torch.autograd.grad(_robust_loss(s, loss, scale).sum(), s)
    return w


def calibration_loss(
    params: Tensor,
    q: Tensor,
    T: Tensor,
    model: CalibrationModel,
    *,
    loss: str = "huber",
    scale: float = 1e-3,
    orientation_weight: float = 0.1,
) -> Tensor:
    """Mean robust loss over the poses, a pure differentiable function: ``params (..., P)`` -> ``(...)``.

    ``q (..., N, n)``, ``T (..., N, 4, 4)`` measured poses or ``(..., N, 3)`` positions, N >= 1; ``params`` is
    the full ζ of ``model`` (see :mod:`diffkin.calibration.model`); the batch dims broadcast (T has as many as
    q). Per pose the squared norm of the weighted residual [p_m − p; w rotvec(R_m Rᵀ)] (m²) goes through
    :func:`robust_loss` with ``scale`` in metres (default 1 mm: quadratic for the sub-millimetre residuals of
    a converged fit, linear for outliers). Inputs by the rule of :mod:`diffkin.validation` in the model's
    dtype and device (shapes, dtypes, finite values; T's rotation blocks are taken as they are, not checked
    for rigidity).
    """
    if loss not in LOSSES:
        raise ConventionError(f"unknown loss {loss!r}; valid: {', '.join(LOSSES)}")
    scale = check_number(scale, "scale", unit=" (metres)")
    orientation_weight = check_number(orientation_weight, "orientation_weight", positive=False)
    params, q, T = tensors(("params", params, (model.n_params,)), ("q", q, None), ("T", T, None),
                           like=model.chains[0])
    measurement_shapes(q, T, model.n, batch=None)
    try:
        broadcast_shapes(params.shape[:-1], q.shape[:-2])
    except RuntimeError:
        raise ShapeError(f"the batch dims of params {shape_str(params.shape)} and q {shape_str(q.shape)} do "
                         "not broadcast") from None
    return _calibration_loss(params, q, T, model, loss, scale, orientation_weight)


def _calibration_loss(params, q, T, model, loss: str, scale: float, orientation_weight: float) -> Tensor:
    """:func:`calibration_loss` on trusted input (the solvers' objective)."""
    res = model.residual(params, q, T, orientation_weight)
    return _robust_loss(res.square().sum(-1), loss, scale).mean(-1)


def _preconditioner(model, zeta, q, free, position_only, w, kind: str):
    """Map u (K, C) -> Δζ (K, C) of the C candidates with |u|² ≈ mean_i |Φ_i Δζ|²: u is RMS motion (m).

    ``"gauss_newton"``: Δζ = D⁻¹ L⁻ᵀ u with L Lᵀ the Cholesky factor of the column-normalised Φ̄ᵀΦ̄ / N at ζ_n
    (D its column scales), which makes the least-squares part of the loss isotropic in u, so the optimisers
    converge in a few iterations for every robot of a batch alike; ``"diagonal"``: Δζ_j = u_j / D_j only.
    Fixed parameters get Δζ = 0 either way.
    """
    K, C = free.shape
    f = free.to(zeta.dtype)
    Phi, _ = model.calibration_matrix(zeta, q, position_only, w, columns=model.candidate)
    A = Phi.reshape(K, -1, C) * f[:, None, :]
    H = A.transpose(-1, -2) @ A / q.shape[-2]
    d = H.diagonal(dim1=-2, dim2=-1).sqrt()
    d = torch.where(free & (d > 0), d, torch.ones_like(d))
    if kind == "diagonal":
        return lambda u: u / d * f
    if kind != "gauss_newton":
        raise ConventionError(f"unknown preconditioner {kind!r}; valid: 'gauss_newton', 'diagonal'")
    Hs = H / (d[:, :, None] * d[:, None, :]) * (f[:, :, None] * f[:, None, :])
    lam, V = torch.linalg.eigh(Hs)  # pseudo-inverse square root: directions the poses leave undetermined
    keep = lam > 1e4 * eps_for(zeta) * lam.amax(-1, keepdim=True)  # get no motion (minimum-norm estimate)
    w = torch.where(keep, lam.clamp_min(torch.finfo(zeta.dtype).tiny).rsqrt(), torch.zeros_like(lam))
    return lambda u: (V @ (w * u)[..., None])[..., 0] / d * f


def least_squares(
    model: CalibrationModel,
    zeta0: Tensor,
    free: Tensor,
    q: Tensor,
    measured: Tensor,
    *,
    orientation_weight: float,
    max_iterations: int = 50,
    tol: float | None = None,
    damping: float | None = None,
    progress: bool = False,
    loss: str = "l2",
    scale: float = 1e-3,
) -> SolverOutput:
    """Iterate (2.88)–(2.89): Δζ = Φ̄⁺ Δx̄, ζ ← ζ + Δζ, with Φ̄ and Δx̄ re-evaluated at the current ζ.

    ``loss`` other than ``"l2"`` (:func:`robust_loss`, ``scale`` metres): iteratively reweighted least
    squares — each pose's rows of Φ̄ and Δx̄ are scaled by √ρ'(|Δx_i|²) at the current ζ, and the step is
    accepted on the robust cost Σ ρ(|Δx_i|²).

    Φ̄'s columns are scaled to unit norm and the step is the kernel's damped least-squares solve
    (:func:`diffkin.kernels.dls.dls_solve`, λ = ``damping`` on the unit-norm columns: the value added to the
    normal matrix's diagonal, (3.59); default 1e-14 in float64, 1e-6 in float32; the unreleased 0.1.0 took
    its square root): min ‖Φ̄ Δζ − Δx̄‖² + λ‖Δζ‖². λ only regularises the step, not the fixed point
    Φ̄ᵀ Δx̄ = 0, and it makes the step the minimum-norm one in the directions the poses do not determine
    (fewer equations than parameters). A step that raises the residual is halved (up to 20 times;
    Levenberg–Marquardt-style safeguard). ``converged``:
    |Δζ_j| ≤ tol (1 + |ζ_j|) for every j (tol default 1e-10 in float64, 1e-5 in float32) — the stopping rule
    was met — not merely the iteration budget spent.
    """
    position_only = measured.shape[-1] == 3 and measured.ndim == q.ndim
    tol = tol_for(zeta0, 1e-10, 1e-5) if tol is None else tol
    damping = tol_for(zeta0, 1e-14, 1e-6) if damping is None else damping
    K, P = free.shape  # P: the candidate parameters here
    cand_mask = model.candidate
    cand = cand_mask.nonzero().flatten().to(zeta0.device)
    zeta, f = zeta0.detach().clone(), free.to(zeta0.dtype)
    hist_p, hist_o = [], []
    converged = torch.zeros(K, dtype=torch.bool, device=zeta.device)
    it = 0

    def cost(z):
        r = model.residual(z, q, measured, orientation_weight)
        return r, _robust_loss(r.square().sum(-1), loss, scale).sum(-1)

    with torch.no_grad(), _progress(progress, "calibrating (least squares)", max_iterations) as advance:
        for it in range(1, max_iterations + 1):  # noqa: B007 (it is reported)
            Phi, T_model = model.calibration_matrix(zeta, q, position_only, orientation_weight, cand_mask)
            res = model.residual_of(T_model, measured, orientation_weight)
            sq = res.square().sum(-1)  # (K, N)
            c0 = _robust_loss(sq, loss, scale).sum(-1)
            pos, ori = _rms(res, orientation_weight)
            hist_p.append(pos)
            hist_o.append(ori)
            if loss != "l2":  # IRLS: rows of pose i weighted by √ρ'(|Δx_i|²)
                sw = robust_weights(sq, loss, scale).sqrt()
                Phi, res = Phi * sw[..., None, None], res * sw[..., None]
            A = Phi.reshape(K, -1, P) * f[:, None, :]
            s = A.norm(dim=-2)
            s = torch.where(s > 0, s, torch.ones_like(s))
            step = dls_solve(A / s[:, None, :], res.reshape(K, -1), damping) / s * f
            step = torch.where(torch.isfinite(step), step, torch.zeros_like(step))
            shrink = torch.ones(K, 1, dtype=zeta.dtype, device=zeta.device)
            for _ in range(20):  # backtrack robots whose residual grew
                _, c1 = cost(zeta.index_add(-1, cand, step * shrink))
                worse = (c1 > c0 * (1 + 1e-12) + 1e-300) & (shrink[:, 0] > 0)
                if not bool(worse.any()):
                    break
                shrink = torch.where(worse[:, None], shrink * 0.5, shrink)
            step = step * shrink
            zeta = zeta.index_add(-1, cand, step)  # (2.89)
            advance()
            converged = (step.abs() <= tol * (1.0 + zeta[:, cand].abs())).all(dim=-1)
            if bool(converged.all()):
                break
        res = model.residual(zeta, q, measured, orientation_weight)
        pos, ori = _rms(res, orientation_weight)
        hist_p.append(pos)
        hist_o.append(ori)
    return SolverOutput(zeta, hist_p, None if position_only else hist_o, it, converged)


def _optimizer(name: str, u: Tensor, lr: float | None, max_iterations: int):
    """``(optimizer, scheduler or None)``: L-BFGS with strong-Wolfe line search, or Adam with lr decay."""
    if name == "lbfgs":
        opt = torch.optim.LBFGS([u], lr=1.0, max_iter=20, history_size=50, tolerance_grad=eps_for(u) ** 2,
                                tolerance_change=0.0, line_search_fn="strong_wolfe")
        return opt, None
    opt = torch.optim.Adam([u], lr=1e-4 if lr is None else lr)
    return opt, torch.optim.lr_scheduler.ExponentialLR(opt, gamma=1e-3 ** (1.0 / max(max_iterations, 1)))


def gradient_descent(
    model: CalibrationModel,
    zeta0: Tensor,
    free: Tensor,
    q: Tensor,
    measured: Tensor,
    *,
    orientation_weight: float,
    optimizer: str = "lbfgs",
    loss: str = "huber",
    scale: float = 1e-3,
    max_iterations: int | None = None,
    tol: float | None = None,
    lr: float | None = None,
    precondition: str = "gauss_newton",
    progress: bool = False,
    gtol: float | None = None,
) -> SolverOutput:
    """Fit ζ by a torch optimiser on :func:`calibration_loss`, all K robots in one objective (their sum).

    The optimiser works on preconditioned variables u (metres of RMS end-effector motion, see
    :func:`_preconditioner`; ``precondition="gauss_newton"`` or ``"diagonal"``). ``optimizer="lbfgs"``
    (strong-Wolfe line search, ≤ 20 evaluations per iteration; stops when the loss changes by less than
    ``tol`` relative, default 1e-13 in float64, 1e-7 in float32) or ``"adam"`` (``lr`` default 1e-4 m,
    decayed ×1e-3 over ``max_iterations``). ``converged`` only when the stopping rule was met: for L-BFGS the
    loss change rule, and for both the first-order test at the end — the gradient in the preconditioned
    variables, converted to metres of RMS end-effector motion (‖∇_u‖ scale² / 2, exact for the quadratic
    part), at most ``gtol`` (default 1e-8 m in float64, 1e-5 m in float32) for that robot.
    """
    position_only = measured.shape[-1] == 3 and measured.ndim == q.ndim
    lbfgs = optimizer == "lbfgs"
    if optimizer not in ("lbfgs", "adam"):
        raise ConventionError(f"unknown optimizer {optimizer!r}; valid: 'lbfgs', 'adam'")
    if loss not in LOSSES:
        raise ConventionError(f"unknown loss {loss!r}; valid: {', '.join(LOSSES)}")
    scale = check_number(scale, "scale", unit=" (metres)")
    max_iterations = (100 if lbfgs else 3000) if max_iterations is None else max_iterations
    tol = tol_for(zeta0, 1e-13, 1e-7) if tol is None else tol
    with torch.no_grad():
        to_delta = _preconditioner(model, zeta0, q, free, position_only, orientation_weight, precondition)
    zeta0 = zeta0.detach()
    cand = model.candidate.nonzero().flatten().to(zeta0.device)
    u = torch.zeros(free.shape, dtype=zeta0.dtype, device=zeta0.device, requires_grad=True)
    norm = 1.0 / (scale * scale)  # dimensionless objective: 1 ≙ a residual of `scale` metres on every pose

    def current():
        return zeta0.index_add(-1, cand, to_delta(u))

    opt, sched = _optimizer(optimizer, u, lr, max_iterations)

    def closure():
        opt.zero_grad()
        value = _calibration_loss(current(), q, measured, model, loss, scale, orientation_weight).sum() * norm
        value.backward()
        return value

    hist_p, hist_o = [], []

    def record():
        with torch.no_grad():
            pos, ori = _rms(model.residual(current(), q, measured, orientation_weight), orientation_weight)
        hist_p.append(pos)
        hist_o.append(ori)

    record()
    prev, it, done, last = math.inf, 0, False, 0
    record_every = 1 if lbfgs else max(1, max_iterations // 100)
    with _progress(progress, f"calibrating ({optimizer})", max_iterations) as advance:
        for it in range(1, max_iterations + 1):
            value = float(opt.step(closure).detach())
            if sched is not None:
                sched.step()
            advance()
            done = lbfgs and abs(prev - value) <= tol * max(abs(value), eps_for(u))
            prev = value
            if it % record_every == 0 or done:
                record()
                last = it
            if done:
                break
    if last != it:
        record()
    gtol = tol_for(zeta0, 1e-8, 1e-5) if gtol is None else gtol
    closure()  # gradient at the final point
    g = u.grad.detach()
    dist = g.norm(dim=-1) * (scale * scale) / 2.0  # metres of RMS motion to the (local) optimum
    converged = (dist <= gtol) & torch.isfinite(dist)
    if lbfgs:
        converged = converged & done
    return SolverOutput(current().detach(), hist_p, None if position_only else hist_o, it, converged)
