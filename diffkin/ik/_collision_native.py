"""Collision-free :func:`diffkin.ik.solve` in rounds of the whole C solve (private).

Where ``dk_solve`` serves the chain (:mod:`diffkin.ik._native_solve`: a CPU solve without ``progress`` on
any chain the fused kernel takes, ball and free joints included; the iterations run without autograd and
:func:`diffkin.ik.solve` attaches the gradients at the solution afterwards) and no refinement is configured
(``LMConfig.collision_refine_calls == 0``), the collision constraints are met by rounds instead of the
scheduled loop's per-harvest acceptance (:mod:`diffkin.ik._collision`):

1. Round 0: ``dk_solve`` of every target: the user's seeds, then its nearest poses of a fixed
   **collision-free library** (the first ``library_size`` of 4 · ``library_size`` configurations sampled
   from a generator seeded with 0 whose every distance clears margin + slack,
   :func:`~diffkin.ik._collision.free_library`), then random ones.
2. One exact, batched distance check of the pose-converged results in the chain's dtype
   (:meth:`~diffkin.ik.residuals.DistanceConstraint.satisfied`, margin).
3. Round r = 1 … ``ROUNDS``: the targets whose result collides are solved again, k = min(``COPIES`` ·
   2^(r − 1), ``MAX_COPIES``) rows each (the targets left are the hard ones, and few), each copy seeded
   first by R = ``library_ranks`` free library poses of the next nearest ranks (a window that moves on
   with every copy and round, :func:`_window_seeds`), then random seeds from the caller's generator (a
   fresh pool per call); all rows are checked in one batch and a target takes its first clear copy.

Success = the pose tolerances and every checked distance >= margin at the returned q, decided by the exact
distances in the chain's dtype (never a success in collision). Every step is ``dk_solve`` (the same for
every thread count) or a torch evaluation of the batch, so the answers do not depend on the thread count.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..kernels import native
from . import _seeds
from ._collision import CollisionConfig, free_library
from ._lm import LMConfig
from ._native_solve import checked, columns, prepared, run, user_seeds
from .residuals import DistanceConstraint
from .result import IKResult

ROUNDS = 6  # re-solve rounds of the targets converged in collision
COPIES = 2  # rows per colliding target in the first re-solve round, doubled every round up to MAX_COPIES
MAX_COPIES = 16


def solve_batch(chain, tg, batch, T_orig, seeds_user, cfg: LMConfig, generator, dtype,
                constraint: DistanceConstraint, *, tol, num_seeds, max_iterations, respect_limits,
                position_only) -> IKResult | None:
    """:func:`diffkin.ik.solve` with ``collision`` through rounds of ``dk_solve`` (module docstring; no
    gradients attached); None when ``dk_solve`` cannot serve the chain."""
    prep = prepared(chain, tg.pd, dtype, respect_limits, 0)
    if prep is None:
        return None
    with torch.no_grad():
        N = math.prod(batch)
        T = T_orig.reshape(N, *T_orig.shape[len(batch):])
        lib = _library(prep, constraint, max(cfg.library_size, 0), chain.n_ends)
        K = chain.n_ends
        out = run(prep, columns(tg), N, cfg, generator, tol=tol, num_seeds=num_seeds,
                  max_iterations=max_iterations, user_u=user_seeds(prep, seeds_user, num_seeds), K=K,
                  library=lib)
        q, ok, pe, oe = checked(chain, prep, out, T, tol, position_only)
        its, tried = out[4], out[5]
        free = constraint.satisfied(q)
        redo = (ok & ~free).nonzero().squeeze(-1)
        ok = ok & free
        near = _ranks(tg, lib, cfg.orientation_weight, redo) if redo.numel() and lib[0].shape[0] else None
        quiet, start = LMConfig(**{**cfg.__dict__, "library_ranks": 0}), 1
        for r in range(ROUNDS):
            if redo.numel() == 0:
                break
            k = min(COPIES << r, MAX_COPIES)  # the targets left are the hard ones: more rows each
            rows = redo.repeat_interleave(k)
            seeds, start = _window_seeds(lib, near, start, k, cfg.library_ranks)
            o = run(prep, columns(tg.take(rows)), rows.numel(), quiet, generator, tol=tol,
                    num_seeds=num_seeds, max_iterations=max_iterations, user_u=seeds, K=K)
            q2, ok2, pe2, oe2 = checked(chain, prep, o, T[rows], tol, position_only)
            its.index_add_(0, rows, o[4])
            tried.index_add_(0, rows, o[5])
            good = (ok2 & constraint.satisfied(q2)).view(-1, k)
            first = good.to(torch.int8).argmax(1) + k * torch.arange(redo.numel(), device=q.device)
            hit = good.any(1)
            take, src = redo[hit], first[hit]
            q[take], ok[take], pe[take], oe[take] = q2[src], True, pe2[src], oe2[src]
            redo = redo[~hit]
            near = None if near is None else near[~hit]
    return IKResult(q=q.reshape(*batch, chain.n_joints), success=ok.reshape(batch),
                    position_error=pe.reshape(batch), orientation_error=oe.reshape(batch),
                    iterations=its.reshape(batch), seeds_tried=tried.reshape(batch))


def _library(prep, constraint: DistanceConstraint, L: int, K: int) -> tuple[Tensor, Tensor]:
    """The fixed collision-free library ``(u (L', n), poses (12K, L'))`` (:func:`run`'s ``library``): the
    free ones of 4 L configurations from a generator seeded with ``_seeds.LIBRARY_SEED`` (their selection is
    remembered on the collision model, :func:`free_library`; the poses on ``prep`` for that selection)."""
    jm, dtype = prep.jmap, constraint.collision.capsule_radius.dtype
    if L == 0:
        return prep.jmap.c.new_zeros(0, prep.n), prep.jmap.c.new_zeros(12 * K, 0)
    u = _seeds.library_u(jm, 4 * L)
    idx = free_library(jm.q_of_u(u).to(dtype), constraint, CollisionConfig.slack, L)
    memo = getattr(prep, "_free_library", None)
    if memo is not None and memo[0] is idx:
        return memo[1]
    u = u[:, idx]
    Tl, _, _ = native.fk_jacobian(prep.packed, jm.q_of_u(u).T.contiguous(), threads=1)
    # (12K, L'): feature-major, as _Prepared's library (dk_solve's vectorised nearest-pose search)
    pose = Tl[:, :, :3, [3, 0, 1, 2]].permute(0, 3, 1, 2).reshape(u.shape[1], -1).T.contiguous()
    lib = (u.T.contiguous(), pose)
    prep._free_library = (idx, lib)
    return lib


def _ranks(tg, lib: tuple[Tensor, Tensor], w: float, rows: Tensor) -> Tensor:
    """The library indices of the targets ``rows``, nearest pose first ``(m, L')``, by the distance of
    ``dk_solve``'s nearest-pose search (positions plus ``w`` times the rotation columns)."""
    sub = tg.take(rows)
    f = torch.cat([t for t in (sub.pd, sub.xd, sub.yd, sub.zd) if t is not None], 0).T  # (m, F)
    F, K3 = f.shape[1], sub.pd.shape[0]
    scale = torch.full((F,), math.sqrt(w), dtype=f.dtype, device=f.device)
    scale[:K3] = 1.0
    return torch.cdist(f * scale, lib[1][:F].T * scale).argsort(1)


def _window_seeds(lib, near: Tensor | None, start: int, k: int, R: int) -> tuple[Tensor | None, int]:
    """A round's first seeds ``(m · k, S, n)`` (S = max(R, 1)) and the next round's ``start``: copy c of
    target t starts from its free library poses of nearest ranks S (start + c) … + S − 1 (round 0 tried
    ranks 0 … R − 1, so the first round starts at 1; the window wraps around the library)."""
    if near is None:
        return None, start + k
    S, (m, L) = max(R, 1), near.shape
    idx = torch.arange(k * S, device=near.device) + S * start
    return lib[0][near.index_select(1, idx % L).reshape(m * k, S)].contiguous(), start + k
