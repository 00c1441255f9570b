"""The one configuration sampler: uniform within the joint ranges, optionally collision-free.

Every random configuration in diffkin comes from here (the chain's ``random_configuration``, IK's random
seeds and restarts, calibration's structural analysis, ``io.data.RandomJoints``, the envs' goals), through
:meth:`~diffkin.kernels.configuration.ConfigurationSpace.from_uniform`: each scalar joint uniform in
``chain.lower_upper()`` (its limits, else ±π for a revolute, ±1 m for a prismatic joint), each quaternion of
a ball or free joint uniform on S³ (Shoemake's map).

Collision-free sampling is rejection in vectorised batches: each round draws a batch of candidates sized
by the acceptance rate seen so far, evaluates the distances once for the batch and keeps the rows with
every distance ≥ ``margin``. A :class:`diffkin.collision.RobotCollision` is evaluated through its broad
phase (``_distances_at_least(q, world, threshold=margin)``: exact wherever a distance is below the margin,
so the decisions are those of the exact distances, and the box searches are skipped where a bounding
sphere proves the pair clear); it leaves out what no q can change, as IK does (its ``skip_fixed``). Any
other object with ``min_distance(q, world=None) -> (...)`` is asked for that: the model does not import
the geometry layer. When no draw at all was accepted after ``GIVE_UP`` draws (and two rounds) the search
stops early, and the error names the pairs in collision in (nearly) every draw.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from .errors import ModelError, SamplingError
from .validation import check_count, check_number, tensors

__all__ = ["random_configuration", "configuration_from_uniform", "MAX_CANDIDATES"]

#: at most this many candidates per rejection round (or the number still missing, if larger)
MAX_CANDIDATES = 1 << 16
#: stop after this many draws (and two rounds) when not one was accepted (acceptance below 1/GIVE_UP)
GIVE_UP = 4096


def _scalar_ranges(chain) -> tuple[Tensor, Tensor]:
    lo, hi = chain.lower_upper()
    space = chain.configuration_space
    if space.euclidean:
        return lo, hi
    idx = list(space.scalar_index())
    return lo[idx], hi[idx]


def configuration_from_uniform(chain, u: Tensor) -> Tensor:
    """Configurations ``(..., nq)`` of ``chain`` from uniforms ``u (..., n_uniform)`` in [0, 1)
    (``n_uniform = chain.configuration_space.n_uniform``: nq on 1-DOF chains, 3 per quaternion; the
    scalars' columns first), in the chain's dtype and device (``u`` must match them; numpy is converted):
    for counter-based or file-seeded sources of uniform numbers (the envs)."""
    space = chain.configuration_space
    (u,) = tensors(("u", u, (space.n_uniform,)), like=chain)
    lo, hi = _scalar_ranges(chain)
    return space.from_uniform(lo.detach(), hi.detach(), u)


def _shape(shape) -> tuple[int, ...]:
    shape = (shape,) if isinstance(shape, int | np.integer) else tuple(shape)
    return tuple(check_count(s, "random_configuration shape entries", minimum=0) for s in shape)


def random_configuration(
    chain,
    shape: Sequence[int] | int = (),
    generator: torch.Generator | None = None,
    *,
    collision=None,
    world=None,
    margin: float = 0.0,
    max_rounds: int = 32,
    return_mask: bool = False,
) -> Tensor | tuple[Tensor, Tensor]:
    """Random configurations ``(*shape, nq)`` of ``chain`` (its dtype and device), drawn from
    ``generator`` (reproducible for a given seed; the generator's device may differ from the chain's).

    With ``collision`` (e.g. a :class:`~diffkin.collision.RobotCollision`): only configurations whose
    ``collision.min_distance(q, world)`` is ≥ ``margin`` (self pairs, and the ``world``'s objects if given),
    found by rejection in at most ``max_rounds`` vectorised rounds (one host sync per round for the count).
    If fewer are found: :class:`~diffkin.errors.SamplingError` naming the acceptance rate, or, with
    ``return_mask=True``, ``(q, ok)`` where ``ok (*shape,)`` marks the collision-free rows (the others hold
    rejected, colliding draws). With ``return_mask=True`` the result is always such a pair.
    """
    shape = _shape(shape)
    lo, hi = _scalar_ranges(chain)
    space = chain.configuration_space
    if collision is None:
        if world is not None:
            raise ModelError("random_configuration: world= needs collision= (the robot's collision geometry, "
                             "e.g. diffkin.collision.RobotCollision.from_urdf / from_mjcf)")
        q = space.sample(lo, hi, shape, generator)
        return (q, torch.ones(shape, dtype=torch.bool, device=q.device)) if return_mask else q
    if not callable(getattr(collision, "min_distance", None)):
        raise ModelError(f"random_configuration: collision= needs an object with min_distance(q, world) "
                         f"(a RobotCollision), got {type(collision).__name__}")
    check = getattr(collision, "_check_chain", None)
    if check is not None:  # a RobotCollision places its geoms with its own chain: it must be this one
        check(chain, "random_configuration")
    margin = check_number(margin, "margin", positive=False, unit=" (m)")
    max_rounds = check_count(max_rounds, "max_rounds")
    n = math.prod(shape)
    q, ok, rate, rounds, why = _rejection(chain, space, lo, hi, n, generator, collision, world, margin,
                                          max_rounds)
    found = int(ok.sum())
    if found < n and not return_mask:
        stopped = " (stopped early: no draw accepted)" if rounds < max_rounds and found == 0 else ""
        raise SamplingError(
            f"random_configuration: found {found} of {n} configurations with min_distance >= {margin} m in "
            f"{rounds} rounds{stopped} (acceptance rate {rate:.3g}){why}; raise max_rounds, lower margin, "
            "or pass return_mask=True to take the rows found")
    q = q.reshape(*shape, space.nq)
    return (q, ok.reshape(shape)) if return_mask else q


def _free(collision, world, margin: float, q: Tensor) -> Tensor:
    """``(m,)``: every checked distance of ``q (m, nq)`` >= margin. A :class:`RobotCollision` leaves out
    the entries no q can change while its ``skip_fixed`` is set (geoms fixed to the base, as IK does);
    other collision objects are asked for ``min_distance``."""
    at_least = getattr(collision, "_distances_at_least", None)
    if at_least is None:
        return collision.min_distance(q, world) >= margin, None
    d = at_least(q, world, margin, moving_only=bool(getattr(collision, "skip_fixed", False)))
    bad = d < margin  # exact decisions: the broad phase is exact below the threshold
    return ~bad.any(-1), bad.sum(0)


def _always(collision, world, counts: Tensor | None, drawn: int) -> str:
    """``"; in collision in ≥ 95 % of the N draws: a × b (100 %), ..."`` naming the worst columns."""
    names = getattr(collision, "_distance_names", None)
    if counts is None or names is None or drawn == 0:
        return ""
    frac = counts.double().cpu() / drawn
    worst = [int(i) for i in frac.argsort(descending=True)[:5] if frac[i] >= 0.95]
    if not worst:
        return ""
    label = names(world, bool(getattr(collision, "skip_fixed", False)))
    listed = ", ".join(f"{label[i]} ({100 * float(frac[i]):.0f} %)" for i in worst)
    return (f"; in collision in >= 95 % of the {drawn} draws: {listed} (exclude pairs that never "
            "matter, e.g. an SRDF's <disable_collisions>, or move the world)")


def _rejection(chain, space, lo, hi, n, generator, collision, world, margin, max_rounds):
    """``(q (n, nq), ok (n,), acceptance rate, rounds run, the colliding pairs' message)``: accepted rows
    first, in draw order."""
    q = lo.new_empty(n, space.nq)
    ok = torch.zeros(n, dtype=torch.bool, device=lo.device)
    filled, drawn, accepted, rounds, counts = 0, 0, 0, 0, None
    for _ in range(max_rounds):
        need = n - filled
        if need == 0 or (accepted == 0 and drawn >= GIVE_UP and rounds >= 2):
            break
        rounds += 1
        rate = max(accepted / drawn, 1.0 / 64) if drawn else 1.0
        m = min(math.ceil(1.25 * need / rate) + 8, max(MAX_CANDIDATES, need))
        cand = space.sample(lo, hi, (m,), generator)
        with torch.no_grad():
            good, bad = _free(collision, world, margin, cand)
        if bad is not None:
            counts = bad if counts is None else counts + bad
        idx = good.nonzero().flatten()
        k = min(int(idx.numel()), need)
        drawn, accepted = drawn + m, accepted + int(idx.numel())
        q[filled:filled + k] = cand[idx[:k]]
        ok[filled:filled + k] = True
        if k < need and filled + k < n:  # keep rejected draws in the rows not filled yet (return_mask)
            rest = (~good).nonzero().flatten()[: n - filled - k]
            q[filled + k:filled + k + rest.numel()] = cand[rest]
        filled += k
    why = _always(collision, world, counts, drawn) if filled < n else ""
    return q, ok, (accepted / drawn if drawn else 1.0), rounds, why
