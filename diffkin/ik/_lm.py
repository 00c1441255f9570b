"""The scheduling loop of :func:`diffkin.ik.solve` (private): LM iterations over a compacting row set.

A row is one (target, seed) pair; state is batch last (``u (n, m)``). Every ``check_every`` iterations the
loop harvests converged rows, re-seeds rows that stopped improving, drops targets that ran out of seeds and,
when few rows remain, gives the remaining targets several seeds in parallel (a small batch costs about the
same per iteration as a large one). Seeds come from the user, then from the nearest poses of a sampled
configuration library, then uniformly at random within the limits.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import torch
from torch import Tensor

from ..kernels import native
from ..kernels.dls import dls_solve
from ._kernel import BatchLastKernel, JointMap
from .residuals import PoseResidual


@dataclass(frozen=True)
class LMConfig:
    """Knobs of :func:`diffkin.ik.solve` (defaults tuned on Panda, UR5 and iiwa; see the benchmark).

    damping: k̄, constant damping (λ = k̄² + μ‖e‖², Sugihara's error-dependent LM damping).
    error_damping: μ, weight of the error-dependent part.
    orientation_weight: weight of the orientation rows relative to metres (rad → m scale).
    library_size: configurations sampled per call whose poses seed each target (nearest first); 0: off.
    library_ranks: how many nearest library poses a target tries before random seeds.
    check_every: LM iterations between two scheduling rounds (one host sync each).
    min_seed_iterations / stall_ratio: a seed older than this whose merit did not shrink by this factor
        over a round is re-seeded.
    min_rows: below this many rows, remaining targets get extra parallel seeds.
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

    damping: float = 3e-3
    error_damping: float = 0.1
    orientation_weight: float = 0.3
    library_size: int = 256
    library_ranks: int = 4
    check_every: int = 2
    min_seed_iterations: int = 8
    stall_ratio: float = 0.5
    min_rows: int = 1024
    margin: float = 0.5
    compute_dtype: torch.dtype | None = None
    collision_refine_calls: int = 0


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


def library_seeds(kernel: BatchLastKernel, jmap: JointMap, tg: Targets, cfg: LMConfig, generator,
                  select=None):
    """Sample ``library_size`` configurations; return their ``u (n, K)`` and each target's nearest ranks.
    ``select(q (n, M)) -> column indices``: keep those of 4 K samples (collision-free seeds)."""
    K, R = cfg.library_size, cfg.library_ranks
    if K <= 0 or R <= 0:
        return None, None
    lib_u = jmap.sample_u(K if select is None else 4 * K, generator)
    if select is not None:
        lib_u = lib_u[:, select(jmap.q_of_u(lib_u))]
        K = lib_u.shape[1]
    x, y, z, p = kernel.fk(jmap.q_of_u(lib_u))
    lib = Targets(p, *(None, None, None) if tg.position_only else (x, y, z))
    w = cfg.orientation_weight**0.5
    f, fl = tg.features(w).float(), lib.features(w).float()
    d = (fl * fl).sum(1) - 2.0 * (f @ fl.T)  # squared distance up to the per-row constant |f|^2, (N, K)
    if R == 1:
        return lib_u, d.argmin(1, keepdim=True)
    return lib_u, d.topk(min(R, K), dim=1, largest=False).indices  # (N, R)


class _Seeder:
    """Seed number s of a target -> u: user seeds first, then library ranks, then random."""

    def __init__(self, jmap, n_user: int, lib_u, nn_idx, generator):
        self.jmap, self.S, self.lib_u, self.nn_idx, self.gen = jmap, n_user, lib_u, nn_idx, generator
        self.R = 0 if nn_idx is None else nn_idx.shape[1]

    def __call__(self, tidx: Tensor, snum: Tensor) -> Tensor:
        u = self.jmap.sample_u(int(tidx.numel()), self.gen)
        if self.R:
            rank = snum - self.S
            use = (rank >= 0) & (rank < self.R)
            lib = self.lib_u[:, self.nn_idx[tidx, rank.clamp(0, self.R - 1)]]
            u = torch.where(use, lib, u)
        return u


@dataclass
class _Rows:
    """The active (target, seed) rows: target index, LM variable u ``(n, m)``, age of the seed, last merit."""

    idx: Tensor
    u: Tensor
    seed_it: Tensor
    last: Tensor

    @classmethod
    def fresh(cls, idx: Tensor, u: Tensor) -> _Rows:
        inf = torch.full(idx.shape, math.inf, dtype=u.dtype, device=u.device)
        return cls(idx, u, torch.zeros_like(idx), inf)

    def select(self, keep: Tensor) -> _Rows:
        return _Rows(self.idx[keep], self.u[:, keep], self.seed_it[keep], self.last[keep])

    def extend(self, other: _Rows) -> _Rows:
        cat = torch.cat
        return _Rows(cat((self.idx, other.idx)), cat((self.u, other.u), 1),
                     cat((self.seed_it, other.seed_it)), cat((self.last, other.last)))  # fmt: skip


class _Run:
    """One :func:`run_lm` call: per-target bookkeeping and the two halves of a round."""

    def __init__(self, kernel, jmap, tg: Targets, cfg: LMConfig, seeder: _Seeder, N: int, tol, num_seeds,
                 max_iterations, residual: PoseResidual, accept=None):  # fmt: skip
        dtype, device = tg.pd.dtype, tg.pd.device
        self.kernel, self.jmap, self.tg, self.cfg, self.seeder = kernel, jmap, tg, cfg, seeder
        self.tol, self.num_seeds, self.max_iterations = tol, num_seeds, max_iterations
        self.residual, self.accept = residual, accept
        self.sqrt_w = residual.sqrt_weights(kernel.K, dtype, device)  # the same in every end link's block
        self.best_u = torch.zeros(kernel.n, N, dtype=dtype, device=device)
        self.best_merit = torch.full((N,), math.inf, dtype=dtype, device=device)
        self.done = torch.zeros(N, dtype=torch.bool, device=device)
        self.iters = torch.zeros(N, dtype=torch.long, device=device)
        self.seeds = torch.zeros(N, dtype=torch.long, device=device)
        self._problem: native.LMProblem | None = None

    def _native_problem(self, u: Tensor) -> native.LMProblem | None:
        """The fused iteration's fixed inputs, made on the first round it may serve (None: torch only)."""
        if self._problem is None:
            packed = self.kernel.chain._native_model(u)
            if packed is None or not packed.euclidean:  # ball and free joints: steps on the manifold
                return None
            tg, jm = self.tg, self.jmap
            cols = None if self.residual.position_only else (tg.xd, tg.yd, tg.zd)  # the C pass's residual
            self._problem = native.LMProblem(packed, tg.pd, cols, self.sqrt_w, jm.c, jm.h, jm.bounded)
        return self._problem

    def _idle_rounds(self, rows: _Rows) -> int:
        """How many rounds from now the schedule would only count iterations: no row old enough for the
        stall check or the iteration limit, and nothing for :meth:`top_up` to add (a row converging ends
        the stretch early, see :func:`diffkin.kernels.native.lm_steps`)."""
        cfg, m = self.cfg, rows.idx.numel()
        if m < cfg.min_rows:
            tgt = torch.unique(rows.idx)
            if (cfg.min_rows - m) // tgt.numel() > 0 and bool((self.seeds[tgt] < self.num_seeds).any()):
                return 0
        limit = min(cfg.min_seed_iterations, self.max_iterations)
        return max(int(((limit - 1 - rows.seed_it) // cfg.check_every).min()), 0)

    def steps(self, rows: _Rows):
        """``check_every`` LM steps (3.59) on all rows; converged rows are frozen. Returns the new u, the u
        the last error was evaluated at, the convergence mask, the merit max(e_p / tol_p, e_o / tol_o), the
        number of rounds run ahead without a schedule (the fused path runs the rounds after which the
        schedule would do nothing in one call) and the merit of the round before the last (None if none)."""
        cfg, (tp, to) = self.cfg, self.tol
        u = rows.u
        problem = self._native_problem(u)
        if problem is not None:  # the same steps fused into one C pass per row (kernels/native.py)
            u, u_eval, conv, merit, rounds, prev = native.lm_steps(
                problem, u, rows.idx, damping2=cfg.damping**2, error_damping=cfg.error_damping,
                tolerances=(float(tp), float(to)), margin=cfg.margin, iterations=cfg.check_every,
                max_rounds=1 + self._idle_rounds(rows))
            return u, u_eval, conv, merit, rounds - 1, prev if rounds > 1 else None
        t = self.tg.take(rows.idx)
        for _ in range(cfg.check_every):
            J, e, pn, ang = self.residual.batch_last(self.kernel, u, self.jmap, t)
            conv = (pn <= tp * cfg.margin) & (ang <= to * cfg.margin)
            e = e * self.sqrt_w
            lam = cfg.damping**2 + cfg.error_damping * (e * e).sum(0)  # Sugihara's damping
            Jw = J * self.sqrt_w
            dqdu = self.jmap.dq_du(u)
            if dqdu is not None:  # chain rule through q = c + h sin(u)
                Jw = Jw * dqdu.unsqueeze(1)
            u_eval, u = u, self.jmap.step(u, dls_solve(Jw, e, lam, layout="batch_last") * (~conv))
        merit = pn / tp if self.tg.position_only else torch.maximum(pn / tp, ang / to)
        return u, u_eval, conv, merit, 0, None

    def schedule(self, rows: _Rows, u_eval: Tensor, conv: Tensor, merit: Tensor) -> _Rows:
        """Harvest converged rows, re-seed or drop stalled ones, and top up the tail."""
        cfg, idx, done = self.cfg, rows.idx, self.done
        self.iters.index_add_(0, idx, torch.full_like(idx, cfg.check_every))
        seed_it = rows.seed_it + cfg.check_every
        rejected = torch.zeros_like(conv)
        if self.accept is not None and bool(conv.any()):  # collision: refine or reject (ik/_collision.py)
            ci = conv.nonzero().squeeze(-1)
            ok, u_ok = self.accept(idx[ci], u_eval[:, ci])
            u_eval = u_eval.index_copy(1, ci, u_ok)
            rejected = rejected.index_put((ci,), ~ok)
            conv = conv & ~rejected
        done[idx[conv]] = True
        self.best_u[:, idx[conv]] = u_eval[:, conv]
        slow = (seed_it >= cfg.min_seed_iterations) & (merit > cfg.stall_ratio * rows.last)
        finished = ((seed_it >= self.max_iterations) | slow | rejected) & ~done[idx]
        if bool(finished.any()):  # keep the best failed seed of each target
            fi, fm = idx[finished], merit[finished]
            self.best_merit.scatter_reduce_(0, fi, fm, reduce="amin")
            better = fm <= self.best_merit[fi]
            self.best_u[:, fi[better]] = u_eval[:, finished][:, better]
        alive = ~done[idx]
        restart = finished & alive & (self.seeds[idx] < self.num_seeds)
        rows = _Rows(idx, rows.u, seed_it, merit)
        if bool(restart.any()):
            ri = idx[restart]
            rows.u = rows.u.clone()
            rows.u[:, restart] = self.seeder(ri, self.seeds[ri])
            self.seeds.index_add_(0, ri, torch.ones_like(ri))
            rows.seed_it = torch.where(restart, torch.zeros_like(seed_it), seed_it)
            rows.last = torch.where(restart, torch.full_like(merit, math.inf), merit)
        return self.top_up(rows.select(alive & (~finished | restart)))

    def top_up(self, rows: _Rows) -> _Rows:
        """Give the remaining targets extra parallel seeds while there are fewer than ``min_rows`` rows."""
        m, min_rows = rows.idx.numel(), self.cfg.min_rows
        if m == 0 or m >= min_rows:
            return rows
        tgt = torch.unique(rows.idx)
        room = (self.num_seeds - self.seeds[tgt]).clamp_min(0)
        per = torch.minimum(room, torch.full_like(room, (min_rows - m) // tgt.numel()))
        new = torch.repeat_interleave(tgt, per)
        if new.numel() == 0:
            return rows
        start = torch.repeat_interleave(torch.cumsum(per, 0) - per, per)
        snum = self.seeds[new] + torch.arange(new.numel(), device=new.device) - start
        self.seeds.index_add_(0, new, torch.ones_like(new))
        return rows.extend(_Rows.fresh(new, self.seeder(new, snum)))


def run_lm(kernel, jmap, tg, seeds_user, lib_u, nn_idx, N, cfg: LMConfig, generator, *, tol, num_seeds,
           max_iterations, residual: PoseResidual, accept=None, progress=False):  # fmt: skip
    """Run the scheduled LM; returns ``(u_best (n, N), iterations (N,), seeds_tried (N,))``. ``accept(idx,
    u) -> (ok, u)``: a test (and refinement) of pose-converged rows; rejected rows are re-seeded."""
    S_user = 0 if seeds_user is None else min(seeds_user.shape[1], max(num_seeds, 1))
    seeder = _Seeder(jmap, S_user, lib_u, nn_idx, generator)
    run = _Run(kernel, jmap, tg, cfg, seeder, N, tol, num_seeds, max_iterations, residual, accept)
    device = tg.pd.device
    if S_user:  # initial rows: every user seed, else one library (or random) seed per target
        idx = torch.arange(N, device=device).repeat_interleave(S_user)
        u = jmap.u_of_q(seeds_user[:, :S_user].to(tg.pd.dtype).reshape(-1, kernel.n).T)
    else:
        idx = torch.arange(N, device=device)
        u = seeder(idx, torch.zeros_like(idx))
    run.seeds += max(S_user, 1)
    rows, rnd = _Rows.fresh(idx, u), 0
    while rows.idx.numel():
        u, u_eval, conv, merit, ahead, prev = run.steps(rows)
        if ahead:  # rounds whose schedule would only have counted: count them
            run.iters.index_add_(0, rows.idx, torch.full_like(rows.idx, cfg.check_every * ahead))
            rows = _Rows(rows.idx, rows.u, rows.seed_it + cfg.check_every * ahead, prev)
        rows = run.schedule(_Rows(rows.idx, u, rows.seed_it, rows.last), u_eval, conv, merit)
        rnd += 1 + ahead
        if progress:
            solved, m = int(run.done.sum()), rows.idx.numel()
            print(f"[diffkin.ik.solve] round {rnd}: {solved}/{N} solved, {m} rows", file=sys.stderr)
    return run.best_u, run.iters, run.seeds
