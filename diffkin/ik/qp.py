"""Small batched convex QPs in torch with KKT gradients: the solvers behind :func:`~diffkin.ik.velocity_step`.

Both solve, for every batch row independently, a strictly convex QP in n variables (n is small: the joint
velocities of one robot)

    min_x  ½ xᵀ H x − gᵀ x                                                                            (Q.1)
    s.t.   lower ≤ x ≤ upper          (box_qp)
           G x ≤ h, lower ≤ x ≤ upper (solve_qp)

with H ``(..., n, n)`` symmetric positive definite, g ``(..., n)``, bounds ``(..., n)`` (±inf: no bound),
G ``(..., p, n)``, h ``(..., p)`` (inf: no constraint); leading batch dims broadcast.

* :func:`box_qp` — a primal active-set method (Nocedal & Wright, Alg. 16.3, specialised to bounds): rows
  whose unconstrained minimiser lies in the box are done at once; the others start from two rounds of the
  primal-dual active-set method (Hintermüller, Ito & Kunisch: every bound moved at once), then per
  iteration solve the equality QP on the free variables (one batched n × n Cholesky solve, the fixed
  variables as identity rows) and either step to the first bound in the way (adding it) or release the
  bound whose multiplier has the wrong sign. Finite and exact: each row stops at its own KKT point, most
  within 1–3 iterations. The iterations are batched tensor ops; on CPU they run on the unfinished rows
  only and the loop ends when every row has finished; on CUDA all rows run, finished ones frozen by a
  mask, and the "all done" flag is read once every 4 iterations (the only host syncs), up to ``max_iter``.
* :func:`solve_qp` — a primal-dual interior-point method (Mehrotra's predictor-corrector, as in OptNet /
  qpth) for general inequalities: at most 30 Newton steps (finished rows frozen), each one batched LU
  factorisation of the n × n reduced system H + GᵀΛS⁻¹G, in float64 whatever the inputs' dtype, then a
  polish on the identified active set. Chosen over ADMM,
  which needs hundreds of iterations and a tuned penalty for 1e-8 accuracy, and over a general active set,
  whose working sets of differing sizes and degenerate cases do not batch: an interior point takes the same
  ~20 iterations for every row, with no host sync at all.

Gradients (custom autograd functions) come from implicit differentiation of the KKT conditions at the
solution on its active set 𝒜 (Amos & Kolter 2017, OptNet): with [H G_𝒜ᵀ; G_𝒜 0][a; β] = [x̄; 0],

    ḡ = a,  H̄ = −a xᵀ,  h̄_𝒜 = β,  Ḡ_𝒜 = −λ_𝒜 aᵀ − β xᵀ                                                (Q.2)

(a bound is a row ±e_i of G: the free variables get a, the fixed ones their bound's β). They are exact
where the active set is locally constant (strict complementarity) and one-sided limits elsewhere.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from .._numerics import broadcast_shapes, eps_for
from ..errors import DiffkinError, ShapeError
from ..kernels.dls import _spd_solve_batch_last
from ..validation import broadcast_batch, check_count, shape_str, tensors
from ._qp_ip import ip_solve

__all__ = ["BoxQPResult", "QPResult", "box_qp", "solve_qp"]

_WARM_START = 2  # primal-dual active-set rounds before the primal active set (all rows, no sync)
# interior-point steps (at most): 1e-12 residuals take 12-25, ill-conditioned H (eigenvalues ~1e-3 beside ~1)
# up to ~60; the loop stops once every row has converged (checked every 8 steps)
_IP_ITERATIONS = 80


class BoxQPResult(NamedTuple):
    """x ``(..., n)``; at_lower / at_upper ``(..., n)`` bool: the variables fixed at a bound (the active
    set); converged ``(...)`` bool: the row reached its KKT point within ``max_iter``."""

    x: Tensor
    at_lower: Tensor
    at_upper: Tensor
    converged: Tensor


class QPResult(NamedTuple):
    """x ``(..., n)``; multipliers ``(..., p + 2n)`` of the rows [G; I; −I] (0 where inactive);
    active ``(..., p + 2n)`` bool; converged ``(...)`` bool (residuals below tolerance)."""

    x: Tensor
    multipliers: Tensor
    active: Tensor
    converged: Tensor


# ------------------------------------------------------------------------------------------ inputs
def _inputs(H, g, lower, upper, name: str):
    H, g, lower, upper = tensors(("H", H, (None, None)), ("g", g, (None,)), ("lower", lower, None),
                                 ("upper", upper, None), finite=(True, True, False, False))
    n = g.shape[-1]
    if H.shape[-2:] != (n, n):
        raise ShapeError(f"{name}: expected H of shape (..., {n}, {n}) for g (..., {n}), got "
                         f"{shape_str(H.shape)}")
    inf = torch.tensor(float("inf"), dtype=g.dtype, device=g.device)
    lower = -inf.expand(n) if lower is None else lower
    upper = inf.expand(n) if upper is None else upper
    for nm, b in (("lower", lower), ("upper", upper)):
        if b.ndim == 0 or b.shape[-1] != n:
            raise ShapeError(f"{name}: expected {nm} of shape (..., {n}), got {shape_str(b.shape)}")
        if bool(torch.isnan(b).any()):
            raise DiffkinError(f"{name}: {nm} holds NaN")
    if bool((lower > upper).any()):
        raise DiffkinError(f"{name}: expected lower <= upper everywhere (a non-empty box)")
    if bool((lower == math.inf).any()) or bool((upper == -math.inf).any()):
        raise DiffkinError(f"{name}: expected lower < +inf and upper > -inf (no real x satisfies x >= +inf "
                           "or x <= -inf; -inf / +inf: no bound)")
    _check_spd(H, name)
    return H, g, lower, upper


def _check_spd(H: Tensor, name: str) -> None:
    """Refuse an H that is not symmetric (beyond √ε of its largest entry) or not positive definite (its
    Cholesky factorisation fails): the QP (Q.1) is then unbounded or not the problem the solvers solve, and
    no x they could return would be its minimiser. :class:`DiffkinError` naming the first offending row."""
    if H.numel() == 0:
        return
    Hd = H.detach()
    scale = Hd.abs().amax((-2, -1))
    asym = (Hd - Hd.mT).abs().amax((-2, -1))
    bad = asym > eps_for(Hd) ** 0.5 * scale
    what = "symmetric"
    if not bool(bad.any()):
        bad, what = torch.linalg.cholesky_ex(Hd)[1] != 0, "positive definite"
        if not bool(bad.any()):
            return
    index = tuple(int(i) for i in bad.nonzero()[0].tolist()) if bad.ndim else ()
    row = f"H[{', '.join(map(str, index))}]" if index else "H"
    detail = (f"max |H - Hᵀ| = {float(asym[index]):.3g}" if what == "symmetric"
              else "its Cholesky factorisation fails: a zero, negative or indefinite curvature")
    raise DiffkinError(f"{name}: expected H symmetric positive definite, but {row} is not {what} ({detail}); "
                       "the QP has no unique minimiser (add a damping λI to H)")


def _flat(batch, *xs_trailing):
    """Broadcast each (tensor, k trailing dims) to ``batch`` and flatten the batch to one axis."""
    return [x.expand(*batch, *x.shape[x.ndim - k:]).reshape(batch.numel(), *x.shape[x.ndim - k:])
            for x, k in xs_trailing]


def _mv(A: Tensor, v: Tensor) -> Tensor:
    return (A @ v.unsqueeze(-1)).squeeze(-1)


# ------------------------------------------------------------------------------------ active set
def _masked_system(H: Tensor, free: Tensor) -> Tensor:
    """H with the rows and columns of fixed variables replaced by those of the identity."""
    f = free.to(H.dtype)
    return H * (f.unsqueeze(-1) * f.unsqueeze(-2)) + torch.diag_embed(1.0 - f)


def _free_solve(H, g, x, free):
    """The equality QP with the fixed variables held at x: y_F = H_FF⁻¹(g_F − H_FA x_A), y_A = x_A."""
    x_fix = torch.where(free, torch.zeros_like(x), x)
    rhs = torch.where(free, g - _mv(H, x_fix), x)
    return _spd_solve(_masked_system(H, free), rhs)


def _spd_solve(M: Tensor, b: Tensor) -> Tensor:
    """M⁻¹b for symmetric positive definite M ``(B, n, n)`` (the masked H: H_FF and an identity block) by
    the kernels' Cholesky (unrolled over the entries for many rows: LAPACK pays a per-matrix overhead)."""
    if M.shape[0] < 1024 and not M.is_cuda:  # few systems: LAPACK directly, no layout round trip
        return torch.linalg.solve_ex(M, b.unsqueeze(-1))[0].squeeze(-1)
    return _spd_solve_batch_last(M.permute(1, 2, 0).contiguous(), b.T.contiguous()).T


def _tolerances(H, g, lo, hi):
    eps = eps_for(g)
    fin = lambda b: torch.where(torch.isfinite(b), b.abs(), torch.zeros_like(b))  # noqa: E731
    size = 1.0 + torch.maximum(fin(lo), fin(hi)).amax(-1, keepdim=True)
    tol_x = 64 * eps * size
    tol_mu = 64 * eps * (1.0 + g.abs().amax(-1, keepdim=True) + H.abs().amax((-2, -1))[..., None] * size)
    return tol_x, tol_mu


def _active_set_iteration(H, g, lo, hi, x, at_lo, at_hi, done, tols):
    """One iteration for every unfinished row (module docstring); returns the new state."""
    tol_x, tol_mu = tols
    free = ~(at_lo | at_hi)
    y = _free_solve(H, g, x, free)
    p = y - x
    below, above = free & (y < lo - tol_x), free & (y > hi + tol_x)
    blocked = (below | above).any(-1, keepdim=True)
    # infeasible: step to the first bound in the way and fix it
    inf = torch.full_like(x, float("inf"))
    ratio = torch.where(below, (lo - x) / torch.where(below, p, -1.0), inf)
    ratio = torch.where(above, (hi - x) / torch.where(above, p, 1.0), ratio)
    alpha, j = ratio.min(-1, keepdim=True)
    alpha = alpha.clamp(0.0, 1.0)
    hit = torch.zeros_like(free).scatter(-1, j, True) & blocked
    x_step = torch.where(hit & below, lo, torch.where(hit & above, hi, x + alpha * p))
    # feasible: the multipliers of the fixed variables (μ_lo = r_i ≥ 0 at a lower bound, −r_i ≥ 0 at an upper)
    y = torch.maximum(torch.minimum(y, hi), lo)
    r = _mv(H, y) - g
    wrong = torch.where(at_lo, -r, torch.where(at_hi, r, torch.zeros_like(r)))
    wrong = torch.where(lo == hi, torch.zeros_like(wrong), wrong)  # a zero-width box stays fixed
    worst, k = wrong.max(-1, keepdim=True)
    release = (worst > tol_mu) & ~blocked
    drop = torch.zeros_like(free).scatter(-1, k, True) & release
    finished = ~blocked & ~release
    keep = done.unsqueeze(-1)
    x_new = torch.where(keep, x, torch.where(blocked, x_step, y))
    at_lo = torch.where(keep, at_lo, (at_lo & ~drop) | (hit & below))
    at_hi = torch.where(keep, at_hi, (at_hi & ~drop) | (hit & above))
    return x_new, at_lo, at_hi, done | finished.squeeze(-1)


def _warm_start(H, g, lo, hi, rounds: int, y: Tensor | None = None):
    """A feasible start and working set from a few primal-dual active-set rounds (Hintermüller, Ito &
    Kunisch 2002): fix at a bound every free variable beyond it and keep every fixed one whose multiplier
    μ = Hx − g has the right sign, all at once (the primal phase then moves one bound at a time). Exact for
    most rows within 2–3 rounds; it may cycle on others, which the primal phase then settles. ``y``: the
    unconstrained minimiser if known (the first round's solve)."""
    fixed_lo = torch.zeros_like(g, dtype=torch.bool)
    fixed_hi = torch.zeros_like(fixed_lo)  # its own tensor: callers write into the returned sets
    x = torch.zeros_like(g)
    for k in range(rounds + 1):
        if k == 0 and y is not None:
            x = y
        else:
            held = torch.where(fixed_lo, lo, torch.where(fixed_hi, hi, 0.0))
            x = _free_solve(H, g, held, ~(fixed_lo | fixed_hi))
        if k == rounds:
            break
        mu = _mv(H, x) - g
        fixed_lo, fixed_hi = (~(fixed_lo | fixed_hi) & (x <= lo)) | (fixed_lo & (mu >= 0)), \
            (~(fixed_lo | fixed_hi) & (x >= hi) & (x > lo)) | (fixed_hi & (mu <= 0))
    x = torch.where(fixed_lo, lo, torch.where(fixed_hi, hi, torch.maximum(torch.minimum(x, hi), lo)))
    return x, fixed_lo, fixed_hi


def _box_solve(H, g, lo, hi, max_iter: int, compact: bool | None = None):
    """Flat ``(B, n)`` inputs -> (x, at_lo, at_hi, converged), no autograd. ``compact``: iterate on the
    unfinished rows only (default: on CPU, where reading a flag is no device sync)."""
    tols = _tolerances(H, g, lo, hi)
    if g.device.type == "cpu" if compact is None else compact:
        return _box_solve_compacted(H, g, lo, hi, tols, max_iter)
    x, at_lo, at_hi = _warm_start(H, g, lo, hi, _WARM_START)
    done = torch.zeros(g.shape[:-1], dtype=torch.bool, device=g.device)
    for it in range(max_iter):
        x, at_lo, at_hi, done = _active_set_iteration(H, g, lo, hi, x, at_lo, at_hi, done, tols)
        if (it + 1) % 4 == 0 and bool(done.all()):  # the only host syncs: one every 4 iterations
            break
    return x, at_lo, at_hi, done


def _box_solve_compacted(H, g, lo, hi, tols, max_iter: int):
    """:func:`_box_solve` on the rows still running: rows whose unconstrained minimiser lies in the box are
    done at once (most rows of a teleoperation or env step); the warm start and the primal iterations run
    on the others, each iteration on those not yet finished (most finish in 1–3)."""
    y = _spd_solve(H, g)  # the unconstrained minimiser
    done = ((y >= lo) & (y <= hi)).all(-1)
    x, at_lo = y.clone(), torch.zeros_like(y, dtype=torch.bool)
    at_hi = at_lo.clone()
    idx = (~done).nonzero().squeeze(-1)
    if idx.numel() == g.shape[0]:
        x, at_lo, at_hi = _warm_start(H, g, lo, hi, _WARM_START, y)
    elif idx.numel():
        x[idx], at_lo[idx], at_hi[idx] = _warm_start(H[idx], g[idx], lo[idx], hi[idx], _WARM_START, y[idx])
    for _ in range(max_iter):
        if idx.numel() == 0:
            break
        if idx.numel() == g.shape[0]:  # every row still running (one row, say): no gathers
            x, at_lo, at_hi, done = _active_set_iteration(H, g, lo, hi, x, at_lo, at_hi, done, tols)
            idx = (~done).nonzero().squeeze(-1)
            continue
        sub = [t[idx] for t in (H, g, lo, hi, x, at_lo, at_hi, done)]
        xs, ls, us, ds = _active_set_iteration(*sub, tuple(t[idx] for t in tols))
        x[idx], at_lo[idx], at_hi[idx], done[idx] = xs, ls, us, ds
        idx = idx[~ds]
    return x, at_lo, at_hi, done


def _box_adjoint(H, free, xbar):
    """a = M⁻ᵀ x̄ for M = [H_FF H_FA; 0 I] (the active-set KKT matrix of (Q.2)): a_F = H_FF⁻¹ x̄_F,
    a_A = x̄_A − H_AF a_F (a_A is the bound's β)."""
    a_free = _spd_solve(_masked_system(H, free), torch.where(free, xbar, 0.0))
    return a_free, torch.where(free, torch.zeros_like(xbar), xbar - _mv(H, a_free))


class _BoxQP(torch.autograd.Function):
    @staticmethod
    def forward(ctx, H, g, lo, hi, max_iter):
        x, at_lo, at_hi, ok = _box_solve(H, g, lo, hi, max_iter)
        ok = ok & torch.isfinite(x).all(-1)  # never "converged" on a NaN / inf x (no host sync)
        ctx.save_for_backward(H, x, at_lo, at_hi)
        ctx.mark_non_differentiable(at_lo, at_hi, ok)
        return x, at_lo, at_hi, ok

    @staticmethod
    def backward(ctx, xbar, *_):
        H, x, at_lo, at_hi = ctx.saved_tensors
        a, beta = _box_adjoint(H, ~(at_lo | at_hi), xbar)
        zero = torch.zeros_like(beta)
        return (-a.unsqueeze(-1) * x.unsqueeze(-2), a, torch.where(at_lo, beta, zero),
                torch.where(at_hi, beta, zero), None)


def box_qp(H, g, lower=None, upper=None, *, max_iter: int | None = None) -> BoxQPResult:
    """Solve the box-constrained QP (Q.1), ``min ½xᵀHx − gᵀx  s.t. lower ≤ x ≤ upper``, per batch row.

    Args:
        H: ``(..., n, n)`` symmetric positive definite. g: ``(..., n)``.
        lower, upper: ``(..., n)`` bounds (±inf: none; ``None``: unbounded), lower <= upper.
        max_iter: active-set iterations (default 4n + 8; each finished row is frozen).

    Returns:
        :class:`BoxQPResult`; ``x`` is differentiable w.r.t. H, g and the bounds by (Q.2). Every iterate is
        within the bounds, so a row that has not converged (``converged`` False) is still feasible;
        ``converged`` is never True for a non-finite x.

    Raises:
        DiffkinError: H not symmetric (beyond √ε of its largest entry) or not positive definite (H = 0, a
            negative-definite or indefinite H: the QP has no unique minimiser), lower = +inf or upper = -inf
            anywhere (an empty box), lower > upper, NaN bounds. ShapeError / DTypeError / NonFiniteError by
            the rule of :mod:`diffkin.validation`.
    """
    H, g, lo, hi = _inputs(H, g, lower, upper, "box_qp")
    n = g.shape[-1]
    max_iter = 4 * n + 8 if max_iter is None else check_count(max_iter, "max_iter")
    batch = broadcast_batch(("H", H, 2), ("g", g, 1), ("lower", lo, 1), ("upper", hi, 1))
    Hf, gf, lof, hif = _flat(batch, (H, 2), (g, 1), (lo, 1), (hi, 1))
    out = _BoxQP.apply(Hf, gf, lof, hif, max_iter)
    return BoxQPResult(*(t.reshape((*batch, *t.shape[1:])) for t in out))


def solve_qp(H, g, G=None, h=None, lower=None, upper=None, *, iterations: int | None = None) -> QPResult:
    """Solve the QP (Q.1) with general inequalities ``G x ≤ h`` and bounds, per batch row, by the
    interior-point method of the module docstring (then a polish on the active set).

    Args:
        H: ``(..., n, n)`` symmetric positive definite. g: ``(..., n)``.
        G: ``(..., p, n)`` and h: ``(..., p)`` (inf entries of h: no constraint); ``None``: none.
        lower, upper: ``(..., n)`` bounds as in :func:`box_qp`.
        iterations: at most this many Newton steps (default 80; rows that converge earlier are frozen, and
            the loop ends once all have).

    Returns:
        :class:`QPResult`; ``x`` is differentiable w.r.t. H, g, G, h and the bounds by (Q.2). The
        constraints must be feasible; an infeasible row comes back with ``converged`` False.

    Raises:
        DiffkinError: H not symmetric positive definite, an empty box, NaN or -inf entries of h (as
            :func:`box_qp`).
    """
    H, g, lo, hi = _inputs(H, g, lower, upper, "solve_qp")
    n = g.shape[-1]
    if (G is None) != (h is None):
        raise DiffkinError("solve_qp: pass G and h together")
    if G is None:
        G, h = g.new_zeros(0, n), g.new_zeros(0)
    G, h = tensors(("G", G, (None, n)), ("h", h, (None,)), like=g, finite=(True, False))
    if h.shape[-1] != G.shape[-2]:
        raise ShapeError(f"solve_qp: expected h of shape (..., {G.shape[-2]}) for G {shape_str(G.shape)}, "
                         f"got {shape_str(h.shape)}")
    if bool(torch.isnan(h).any()) or bool((h == -float("inf")).any()):
        raise DiffkinError("solve_qp: h holds NaN or -inf (an infeasible constraint)")
    iterations = _IP_ITERATIONS if iterations is None else check_count(iterations, "iterations")
    batch = broadcast_batch(("H", H, 2), ("g", g, 1), ("G", G, 2), ("h", h, 1), ("lower", lo, 1),
                            ("upper", hi, 1))
    Hf, gf, Gf, hf, lof, hif = _flat(batch, (H, 2), (g, 1), (G, 2), (h, 1), (lo, 1), (hi, 1))
    eye = torch.eye(n, dtype=g.dtype, device=g.device).expand(Hf.shape[0], n, n)
    G_all = torch.cat((Gf, eye, -eye), dim=-2)  # bounds as rows of G: [G; I; −I] x ≤ [h; u; −l]
    h_all = torch.cat((hf, hif, -lof), dim=-1)
    out = ip_solve(Hf, gf, G_all, h_all, iterations)
    return QPResult(*(t.reshape((*batch, *t.shape[1:])) for t in out))


# ---------------------------------------------------------------------------- trusted entry points
def _solve_box(H: Tensor, g: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """:func:`box_qp`'s x for validated inputs of one broadcast batch (library callers)."""
    batch = broadcast_shapes(H.shape[:-2], g.shape[:-1], lo.shape[:-1], hi.shape[:-1])
    n = g.shape[-1]
    out = _BoxQP.apply(*_flat(batch, (H, 2), (g, 1), (lo, 1), (hi, 1)), 4 * n + 8)
    return out[0].reshape(*batch, n)


def _solve_general(H: Tensor, g: Tensor, G: Tensor, h: Tensor) -> Tensor:
    """:func:`solve_qp`'s x for validated inputs (no bounds; inf entries of h switch rows off)."""
    batch = broadcast_shapes(H.shape[:-2], g.shape[:-1], G.shape[:-2], h.shape[:-1])
    n = g.shape[-1]
    out = ip_solve(*_flat(batch, (H, 2), (g, 1), (G, 2), (h, 1)), _IP_ITERATIONS)
    return out[0].reshape(*batch, n)
