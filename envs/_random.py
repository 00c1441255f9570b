"""Counter-based random numbers for episode resets.

Every env carries a 32-bit ``key`` (drawn once from ``self.np_random`` after ``super().reset(seed=...)``)
and an episode counter. The numbers of episode ``e`` are a pure hash of ``(key, e, j)``, so a batch of N
envs resets any subset of rows in one tensor op and env ``i`` of a batch seeded ``s`` draws exactly what a
single env seeded ``s + i`` draws: no per-env generator objects, no Python loop on the step path.
"""

from __future__ import annotations

import numpy as np
import torch
from gymnasium.utils import seeding
from torch import Tensor

_M32 = 0xFFFFFFFF


def _mul32(x: Tensor, c: int) -> Tensor:
    """(x * c) mod 2**32 for x < 2**32 without int64 overflow (split c into 16-bit halves)."""
    lo = x * (c & 0xFFFF)
    hi = ((x * (c >> 16)) & 0xFFFF) << 16
    return (lo + hi) & _M32


def _mix32(x: Tensor) -> Tensor:
    """The 'lowbias32' integer hash (C. Wellons): a bijection of 32-bit integers with good avalanche."""
    x = x & _M32
    x = x ^ (x >> 16)
    x = _mul32(x, 0x7FEB352D)
    x = x ^ (x >> 15)
    x = _mul32(x, 0x846CA68B)
    return x ^ (x >> 16)


def key_from_generator(rng: np.random.Generator) -> int:
    """One 32-bit key from a numpy generator (the env's ``np_random``)."""
    return int(rng.integers(0, 2**32, dtype=np.int64))


def keys_for_seeds(seeds) -> list[int]:
    """Keys of envs seeded with ``seeds``; equal to what a single env does after ``reset(seed=s)``."""
    return [key_from_generator(seeding.np_random(int(s))[0]) for s in seeds]


def uniform(key: Tensor, episode: Tensor, count: int, dtype=torch.float32) -> Tensor:
    """Uniforms in [0, 1) of shape ``(M, count)`` for rows with ``key (M,)``, ``episode (M,)`` (int64)."""
    j = torch.arange(count, dtype=torch.int64, device=key.device)
    h = _mix32(key.unsqueeze(-1) ^ _mix32(episode.unsqueeze(-1) * 0x9E3779B1 + 0x632BE5AB))
    h = _mix32(h + _mix32(j * 0x85EBCA77 + 0x165667B1))
    return (h >> 8).to(dtype) * (1.0 / (1 << 24))
