"""The Levenberg–Marquardt schedule of :func:`diffkin.ik.solve` (private): one algorithm, two backends.

Every target runs its seeds in order (:mod:`._seeds`: the user's, then the nearest poses of a fixed
library, then random draws from the caller's generator); the first seed that converges gives the answer.
One LM step of a (target, seed) row:

1. evaluate the pose error e = [p_d − p_e; θr] (per end link) and the Jacobian at q = c + h sin u;
2. converged (max ‖e_p‖ ≤ tol_p · margin and max θ ≤ tol_o · margin): the target is done with this u;
3. else, every ``check_every`` steps of the seed: a seed at least ``min_seed_iterations`` old whose merit
   max(‖e_p‖ / tol_p, θ / tol_o) did not shrink by ``stall_ratio`` since the last check, or one at
   ``max_iterations``, is finished (the target keeps the u of its best finished seed) and the target's next
   seed starts, if it has one;
4. else u ← u ⊕ Δ, Δ = J_wᵀ(J_w J_wᵀ + λI)⁻¹ e_w (3.59), J_w = diag(√w) J diag(∂q/∂u), λ = λ̄ + μ‖e_w‖²
   (Sugihara's damping), ⊕ the configuration space's integrate (quaternions on the manifold).

:func:`run_lm` is the torch backend (every device; CUDA runs it), batch last over the open targets. The C
backend (``dk_solve``, ``kernels/_native_solve.c``, the CPU) runs the same steps on SIMD lanes, one target
per lane; on the same inputs and generator both give the same success flags, iteration counts and q to
rounding (tests/test_ik_backends.py).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import torch
from torch import Tensor

from ..kernels.dls import dls_solve
from ..validation import check_count
from ._seeds import MAX_RANKS, SeedPool
from .residuals import PoseResidual


@dataclass(frozen=True)
class LMConfig:
    """Knobs of :func:`diffkin.ik.solve` (defaults tuned on Panda, UR5 and iiwa; see the benchmark).

    damping: λ̄, the constant part of the damping λ = λ̄ + μ‖e‖² added to JJᵀ's diagonal, eq. (3.59)
        (Sugihara's error-dependent LM damping; λ̄ is the textbook's k², k = 3e-3 by default; the unreleased
        0.1.0 took k here).
    error_damping: μ, weight of the error-dependent part.
    orientation_weight: weight of the orientation rows relative to metres (rad → m scale).
    library_size: configurations sampled per call whose poses seed each target (nearest first); 0: off.
    library_ranks: how many nearest library poses a target tries before random seeds (0 to
        :data:`~diffkin.ik._seeds.MAX_RANKS` = 64, the C solve's limit: more raises
        :class:`~diffkin.errors.OptionError`, never a silent clamp).
    check_every: LM steps of a seed between two stall checks (the iteration limit is checked with them).
    min_seed_iterations / stall_ratio: a seed at least this old whose merit did not shrink by this factor
        since the last check is finished, and the target's next seed starts.
    margin: internal tolerance factor (< 1 leaves room for the final FK in the chain's dtype).
    compute_dtype: dtype of the iteration; None: the chain's, except float64 for a float32 chain asked for
        tolerances below 1e-5 (float32 FK noise is ~1e-7 m / rad, so 0.1 mm and 1e-3 rad keep a 100x margin).
    collision_refine_calls: with ``collision``, how many acceptance rounds refine rows converged in
        collision by the constrained Gauss–Newton of :mod:`diffkin.ik._collision` before re-seeding them
        (the first round sees the colliding solutions of the plain solve). Default 0, re-seeding only (on
        the CPU in rounds of the C solve, :mod:`diffkin.ik._collision_native`): on the FR3 among obstacles
        re-seeding from the collision-free library reaches the same success at a fraction of the cost
        (benchmarks/bench_collision_ik.py); 1 (the scheduled loop) helps where a target has few solutions.
    """

    damping: float = 9e-6
    error_damping: float = 0.1
    orientation_weight: float = 0.3
    library_size: int = 256
    library_ranks: int = 4
    check_every: int = 2
    min_seed_iterations: int = 8
    stall_ratio: float = 0.5
    margin: float = 0.5
    compute_dtype: torch.dtype | None = None
    collision_refine_calls: int = 0

    def __post_init__(self):
        check_count(self.library_ranks, "LMConfig.library_ranks", minimum=0, maximum=MAX_RANKS)


class Targets:
    """Target position ``pd`` and rotation columns ``xd, yd, zd`` (each ``(3K, N)`` or None: the K end links'
    columns stacked), batch last."""

    def __init__(self, pd: Tensor, xd: Tensor | None, yd: Tensor | None, zd: Tensor | None):
        self.pd, self.xd, self.yd, self.zd = pd, xd, yd, zd

    @property
    def position_only(self) -> bool:
        return self.xd is None

    def take(self, idx: Tensor) -> Targets:
        return Targets(*(None if t is None else t[:, idx] for t in (self.pd, self.xd, self.yd, self.zd)))

    def features(self, w: float) -> Tensor:
        """Pose features ``(N, 3 or 12)`` for nearest-neighbour seeding."""
        if self.position_only:
            return self.pd.T
        return torch.cat((self.pd, w * self.xd, w * self.yd, w * self.zd), 0).T


def run_lm(kernel, jmap, tg: Targets, seeds: SeedPool, N: int, cfg: LMConfig, *, tol, num_seeds: int,
           max_iterations: int, residual: PoseResidual, accept=None, progress: bool = False):
    """The schedule of this module on ``N`` targets ``tg`` (columns ``(3K, N)``) from ``seeds``; returns
    ``(u (n, N) the converged or best u of each target, iterations (N,), seeds tried (N,))``.

    Without ``accept`` the seeds run in lockstep (:func:`_run_lockstep`); with it (collision:
    ``accept(idx, u) -> (ok, u)``, a test and refinement of pose-converged rows whose rejected rows finish
    as stalled ones) one after another (:func:`_run_sequential`). Both give the schedule's result."""
    if accept is None:
        return _run_lockstep(kernel, jmap, tg, seeds, N, cfg, tol=tol, num_seeds=num_seeds,
                             max_iterations=max_iterations, residual=residual, progress=progress)
    return _run_sequential(kernel, jmap, tg, seeds, N, cfg, tol=tol, num_seeds=num_seeds,
                           max_iterations=max_iterations, residual=residual, accept=accept, progress=progress)


MAX_SLOTS = 16  # the most seeds a target runs at once in a lockstep round


def _slots(r: int, left: int) -> int:
    """W of lockstep round r: 1, 2, 4, ... up to :data:`MAX_SLOTS` and the seeds left (most targets converge
    from their first seed; on 2 000 Panda targets caps of 8, 16 and 32 measured alike, within the noise)."""
    return min(1 << min(r, 10), MAX_SLOTS, left)


def _stop_rule(pn: Tensor, ang: Tensor, age: Tensor, last: Tensor, tp, to, cfg: LMConfig, pos_only: bool,
               every: int, max_iterations: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The one stopping rule of a seed's LM run (both runners, and ``dk_solve``'s): converged when both
    errors are within ``margin`` × the tolerances; every ``every`` iterations the merit (the larger error
    over its tolerance) is compared with the last check's, and a seed past ``min_seed_iterations`` that has
    not improved by ``stall_ratio``, or has used ``max_iterations``, is finished. -> ``(converged,
    finished, merit, the merit to compare at the next check)``."""
    conv = (pn <= tp * cfg.margin) & (ang <= to * cfg.margin)
    merit = pn / tp if pos_only else torch.maximum(pn / tp, ang / to)
    check = (age % every == 0) & ~conv
    slow = (age >= cfg.min_seed_iterations) & ~(merit <= cfg.stall_ratio * last)
    fin = check & (slow | (age >= max_iterations))
    return conv, fin, merit, torch.where(check, merit, last)


def _lm_update(u: Tensor, J: Tensor, e: Tensor, go: Tensor, jmap, cfg: LMConfig, sqrt_w: Tensor) -> Tensor:
    """Step 4 of the schedule on the rows ``go``: u ⊕ J_wᵀ(J_w J_wᵀ + λI)⁻¹ e_w, λ = λ̄ + μ‖e_w‖²."""
    e = e * sqrt_w
    lam = cfg.damping + cfg.error_damping * (e * e).sum(0)
    Jw = J * sqrt_w
    dqdu = jmap.dq_du(u)
    if dqdu is not None:  # chain rule through q = c + h sin(u)
        Jw = Jw * dqdu.unsqueeze(1)
    return torch.where(go, jmap.step(u, dls_solve(Jw, e, lam, layout="batch_last")), u)


def _run_lockstep(kernel, jmap, tg: Targets, seeds: SeedPool, N: int, cfg: LMConfig, *, tol, num_seeds: int,
                  max_iterations: int, residual: PoseResidual, progress: bool = False):
    """The schedule with the seeds in lockstep: in round r every open target runs its seeds
    ``base, ..., base + W_r − 1`` at once (fixed slots; W_r of :func:`_slots`: 1, 2, 4, ... 16), one row
    per (target, slot). A seed's run depends only on its target and its start, so the result is the
    sequential schedule's: the lowest seed that converges wins (a slot behind a converged lower slot of its
    target is dropped by a mask); iterations are the sum of the runs of the seeds up to the winner, seeds
    tried the winner's number + 1; a target whose seeds all finish unconverged keeps the u of the least
    merit (ties: the later seed), as one after another. One host sync per step."""
    dtype, device = tg.pd.dtype, tg.pd.device
    (tp, to), every, pos_only = tol, max(cfg.check_every, 1), tg.position_only
    sqrt_w = residual.sqrt_weights(kernel.K, dtype, device)
    open_t = torch.arange(N, device=device)
    best_u = seeds(open_t, torch.zeros_like(open_t))
    best_merit = torch.full((N,), math.inf, dtype=dtype, device=device)
    iters = torch.zeros(N, dtype=torch.long, device=device)
    tried = torch.zeros(N, dtype=torch.long, device=device)
    base, step, r = 0, 0, 0
    while open_t.numel() and base < num_seeds:
        M = open_t.numel()
        W = _slots(r, num_seeds - base)
        grid = torch.arange(M * W, device=device)  # row = (target m, slot k), target-major
        slot_of = grid % W
        t = open_t.repeat_interleave(W)
        u = seeds(t, base + slot_of)
        length = torch.zeros(M * W, dtype=torch.long, device=device)
        state = torch.zeros(M * W, dtype=torch.int8, device=device)  # 0 running, 1 converged, 2 finished
        fmerit = torch.full((M * W,), math.nan, dtype=dtype, device=device)
        fu = torch.zeros(u.shape[0], M * W, dtype=dtype, device=device)
        rows, age = grid, torch.zeros(M * W, dtype=torch.long, device=device)
        last = torch.full((M * W,), math.inf, dtype=dtype, device=device)
        while rows.numel():
            J, e, pn, ang = residual.batch_last(kernel, u, jmap, tg.take(t[rows]))
            age = age + 1
            conv, fin, merit, last = _stop_rule(pn, ang, age, last, tp, to, cfg, pos_only, every,
                                                max_iterations)
            done = conv | fin
            di = rows[done]
            length[di] = age[done]
            state[di] = torch.where(conv[done], 1, 2).to(torch.int8)
            fmerit[rows[fin]] = merit[fin]
            fu[:, di] = u[:, done]
            go = ~done
            u = _lm_update(u, J, e, go, jmap, cfg, sqrt_w)
            # a slot behind a converged lower slot of its target can no longer win: masked out
            first = torch.where((state == 1).view(M, W), slot_of.view(M, W), W).amin(1)  # (M,)
            keep = go & (slot_of[rows] < first[rows // W])
            rows, u, age, last = rows[keep], u[:, keep], age[keep], last[keep]
            step += 1
            if progress and step % every == 0:
                print(f"[diffkin.ik.solve] step {step}: seeds {base}..{base + W - 1}, {rows.numel()} rows",
                      file=sys.stderr)
        # resolve the round's targets
        conv_g = (state == 1).view(M, W)
        has = conv_g.any(1)
        slots = torch.arange(W, device=device)
        kstar = torch.where(conv_g, slots, W).amin(1)  # the winner, or W
        upto = slots[None, :] <= kstar[:, None]
        iters[open_t] += (length.view(M, W) * upto).sum(1)
        tried[open_t] += torch.where(has, kstar + 1, W)
        fu = fu.view(-1, M, W)
        mrange = torch.arange(M, device=device)
        win = open_t[has]
        best_u[:, win] = fu[:, mrange[has], kstar[has]]
        fm = fmerit.view(M, W)
        valid = ~torch.isnan(fm)
        fm_v = torch.where(valid, fm, math.inf)
        low = fm_v.amin(1)
        at = valid & (fm_v == low[:, None])
        latest = (W - 1) - at.flip(1).to(torch.int8).argmax(1)  # the later seed on a tie
        better = ~has & valid.any(1) & (low <= best_merit[open_t])
        bt = open_t[better]
        best_merit[bt] = low[better]
        best_u[:, bt] = fu[:, mrange[better], latest[better]]
        open_t = open_t[~has]
        base, r = base + W, r + 1
    return best_u, iters, tried


def _run_sequential(kernel, jmap, tg: Targets, seeds: SeedPool, N: int, cfg: LMConfig, *, tol,
                    num_seeds: int, max_iterations: int, residual: PoseResidual, accept=None,
                    progress: bool = False):
    """The schedule with each target's seeds one after another (the rows of finished seeds restart with
    the next seed). One host sync per step (the open rows are compacted)."""
    dtype, device = tg.pd.dtype, tg.pd.device
    (tp, to), every, pos_only = tol, max(cfg.check_every, 1), tg.position_only
    sqrt_w = residual.sqrt_weights(kernel.K, dtype, device)
    idx = torch.arange(N, device=device)
    u = seeds(idx, torch.zeros_like(idx))
    best_u, best_merit = u.clone(), torch.full((N,), math.inf, dtype=dtype, device=device)
    iters = torch.zeros(N, dtype=torch.long, device=device)
    tried = torch.ones(N, dtype=torch.long, device=device)
    age = torch.zeros_like(idx)
    last = torch.full((N,), math.inf, dtype=dtype, device=device)
    step, solved = 0, 0
    while idx.numel():
        J, e, pn, ang = residual.batch_last(kernel, u, jmap, tg.take(idx))
        iters.index_add_(0, idx, torch.ones_like(idx))
        age = age + 1
        conv, fin, merit, last = _stop_rule(pn, ang, age, last, tp, to, cfg, pos_only, every, max_iterations)
        if accept is not None and bool(conv.any()):  # collision: refine or reject (ik/_collision.py)
            ci = conv.nonzero().squeeze(-1)
            ok, u_ok = accept(idx[ci], u[:, ci])
            u = u.index_copy(1, ci, u_ok)
            rejected = torch.zeros_like(conv).index_put((ci,), ~ok)
            conv, fin = conv & ~rejected, fin | rejected
        best_u[:, idx[conv]] = u[:, conv]
        fi, fm = idx[fin], merit[fin]
        better = fm <= best_merit[fi]  # one row per target: no two rows of one target finish together
        best_merit[fi[better]] = fm[better]
        best_u[:, fi[better]] = u[:, fin][:, better]
        go = ~(conv | fin)
        u = _lm_update(u, J, e, go, jmap, cfg, sqrt_w)
        restart = fin & (tried[idx] < num_seeds)
        ri = idx[restart]
        u[:, restart] = seeds(ri, tried[ri])
        tried.index_add_(0, ri, torch.ones_like(ri))
        age, last = age.masked_fill(restart, 0), last.masked_fill(restart, math.inf)
        keep = go | restart
        solved += int(conv.sum()) if progress else 0
        idx, u, age, last = idx[keep], u[:, keep], age[keep], last[keep]
        step += 1
        if progress and step % every == 0:
            print(f"[diffkin.ik.solve] step {step}: {solved}/{N} solved, {idx.numel()} rows", file=sys.stderr)
    return best_u, iters, tried
