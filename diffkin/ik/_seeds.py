"""The seeds of :func:`diffkin.ik.solve` (private): one pool, one rule, for both backends.

Seed ``s`` of target ``t`` is

* ``s < S``: the user's seed ``(t, s)`` (``q0``, at most ``num_seeds`` per target), mapped to u;
* ``s < S + R``: the configuration of a **fixed pose library** (``library_size`` configurations drawn once
  per chain state from a generator seeded with :data:`LIBRARY_SEED`, so that a single-target call does not
  pay for sampling and evaluating a library) whose end-link pose is the ``(s - S)``-th nearest to the
  target's (squared distance of the positions plus ``orientation_weight`` times that of the rotation
  columns; ties: the lower library index first), R = min(``library_ranks``, L) (``library_ranks`` at most
  :data:`MAX_RANKS`: :class:`~diffkin.ik._lm.LMConfig` refuses more);
* else column ``(t · num_seeds + s) mod P`` of a pool of P = min(N · num_seeds, max(num_seeds, 4096))
  columns of ``n_uniform`` numbers drawn in advance from the **caller's generator** (one draw per call, in
  :func:`draw_pool`), mapped by the one sampler
  (:meth:`~diffkin.kernels.configuration.ConfigurationSpace.from_uniform`: scalars uniform in their ranges,
  quaternions by Shoemake's map) and :meth:`~diffkin.ik._kernel.JointMap.u_of_q`.

The C solve (``dk_solve``, :mod:`._native_solve`) reads the same arrays (it finds the nearest library poses
itself, by the same distance); :class:`SeedPool` is the torch backend's reading of the rule.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..kernels import native

LIBRARY_SEED = 0
POOL = 4096
MAX_RANKS = native.CONSTANTS["MAX_RANKS"]  # the most library_ranks (LMConfig refuses more: no clamp)
MAX_ENDS = native.CONSTANTS["MAX_ENDS"]  # more end links: no library seeds


def library_u(jmap, L: int) -> Tensor:
    """The fixed library ``u (n, L)`` of the joint map ``jmap`` (its dtype and device), drawn from a CPU
    generator seeded with :data:`LIBRARY_SEED`: the same configurations for every device."""
    return jmap.sample_u(L, torch.Generator().manual_seed(LIBRARY_SEED))


def ranks(L: int, K: int, library_ranks: int) -> int:
    """R: how many nearest library poses a target tries (as ``dk_solve`` reads it)."""
    if L <= 0 or K > MAX_ENDS:
        return 0
    return max(min(library_ranks, L), 0)  # library_ranks <= MAX_RANKS: LMConfig checked it


def pool_size(N: int, num_seeds: int, S: int, R: int) -> int:
    """P: columns of the random pool (0 when the user's and library seeds cover ``num_seeds``)."""
    return min(N * num_seeds, max(num_seeds, POOL)) if num_seeds > S + R else 0


def draw_pool(generator, P: int, nu: int, dtype) -> Tensor | None:
    """The pool ``(P * nu,)`` of uniforms in [0, 1) from the caller's generator (on its device): the one
    draw of a solve."""
    if not P:
        return None
    dev = None if generator is None else generator.device
    return torch.rand(P * nu, generator=generator, dtype=dtype, device=dev)


def library_features(x: Tensor, y: Tensor, z: Tensor, p: Tensor, position_only: bool) -> Tensor:
    """Pose features ``(F, M)`` (F = 3K or 12K) of end-link columns ``(3K, M)`` each: p, then x, y, z."""
    return p if position_only else torch.cat((p, x, y, z), 0)


def nearest(tg, lib_f: Tensor, R: int, weight: float) -> Tensor:
    """The R library indices nearest each target ``(N, R)``: squared distance of the positions plus
    ``weight`` times that of the rotation columns (``dk_solve``'s distance); ties: the lower index."""
    f = library_features(tg.xd, tg.yd, tg.zd, tg.pd, tg.position_only)  # (F, N)
    K3 = tg.pd.shape[0]
    d = None  # (N, L), accumulated feature by feature in order (no (F, N, L) temporary)
    for i in range(f.shape[0]):
        term = (f[i, :, None] - lib_f[i, None, :]).square()
        if i >= K3:
            term = term * weight
        d = term if d is None else d.add_(term)
    return torch.sort(d, dim=1, stable=True).indices[:, :R]


class SeedPool:
    """Seed number ``s`` of targets ``t`` -> u ``(n, m)`` by the rule of this module (torch backend).

    ``user_u (N, S, n)`` the user's seeds in u (or None), ``lib_u (n, L)`` and ``nn (N, R)`` the library and
    each target's nearest ranks (or None), ``pool (P * nu,)`` the random draws (or None), ``num_seeds`` the
    stride of the pool's column rule."""

    def __init__(self, jmap, user_u: Tensor | None, lib_u: Tensor | None, nn: Tensor | None,
                 pool: Tensor | None, num_seeds: int):
        self.jmap, self.user_u, self.lib_u, self.nn, self.num_seeds = jmap, user_u, lib_u, nn, num_seeds
        self.S = 0 if user_u is None else user_u.shape[1]
        self.R = 0 if nn is None else nn.shape[1]
        space = jmap.space
        self.nu = space.n_uniform
        self.pool = None if pool is None else pool.view(-1, self.nu).to(jmap.c.device)
        s = list(space.scalar_index())
        self._lo, self._hi = jmap.lo[s, 0], jmap.hi[s, 0]

    def __call__(self, t: Tensor, s: Tensor) -> Tensor:
        jm, S, R = self.jmap, self.S, self.R
        n, m = jm.c.shape[0], t.numel()
        u = torch.zeros(n, m, dtype=jm.c.dtype, device=jm.c.device)
        if self.pool is not None:
            col = (t * self.num_seeds + s) % self.pool.shape[0]
            q = jm.space.from_uniform(self._lo, self._hi, self.pool[col])  # (m, n)
            u = jm.u_of_q(q.T)
        if R:
            rank = s - S
            use = (rank >= 0) & (rank < R)
            lib = self.lib_u[:, self.nn[t, rank.clamp(0, R - 1)]]
            u = torch.where(use, lib, u)
        if S:
            use = s < S
            usr = self.user_u[t, s.clamp(max=S - 1)].T
            u = torch.where(use, usr, u)
        return u
