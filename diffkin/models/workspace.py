"""Manipulator workspace (§2.10.1): reachable end-effector positions by sampling the joint space."""

from __future__ import annotations

import torch
from torch import Tensor

from .._unchecked import fk
from ..chain import KinematicChain

__all__ = ["sample_workspace"]


def sample_workspace(
    chain: KinematicChain,
    n: int,
    generator: torch.Generator | None = None,
    return_q: bool = False,
) -> Tensor | tuple[Tensor, Tensor]:
    """``n`` reachable end-effector positions ``(n, 3)`` (base frame) from joint samples drawn uniformly
    within the joint limits q_im <= q_i <= q_iM (§2.10.1): the reachable workspace is the image of the
    joint-limit box under p_e(q).

    One batched FK pass, no gradients. With ``return_q`` also the joint samples ``(n, n_joints)``.
    """
    q = chain.random_configuration((int(n),), generator=generator)
    with torch.no_grad():
        p = fk(chain, q)[..., :3, 3]
    return (p, q) if return_q else p
