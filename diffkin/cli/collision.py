"""``--self-collision`` / ``--world FILE`` / ``--margin M`` of ``diffkin ik`` and ``diffkin fk --random``.

The collision geometry is the robot file's own (:meth:`RobotCollision.from_urdf` / ``from_mjcf``), so these
options need ``--urdf FILE`` or ``--mjcf FILE``. ``--world`` alone checks the robot's geoms against the
world's obstacles only; with ``--self-collision`` the file's self pairs count too.

Random samples with these options are collision-free configurations drawn by
:func:`diffkin.sampling.random_configuration` (torch's generator seeded with ``--seed``, one chunk of
``--chunk-size`` rows after the other), not the row-addressable stream of plain ``--random``.
"""

from __future__ import annotations

import inspect
import math
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

from ..errors import DiffkinError

__all__: list[str] = []


def add_arguments(p) -> None:
    g = p.add_argument_group("collision (needs --urdf or --mjcf)")
    g.add_argument("--self-collision", dest="self_collision", action="store_true",
                   help="collision-free: the robot file's self-collision pairs must stay apart")
    g.add_argument("--world", metavar="FILE",
                   help="obstacles (YAML/JSON: spheres, capsules, boxes, halfspaces, points; see "
                        "docs/collision.md)")
    g.add_argument("--srdf", metavar="FILE",
                   help="SRDF whose <disable_collisions> pairs are not checked (URDF robots)")
    g.add_argument("--margin", type=float, default=0.0, metavar="M",
                   help="smallest allowed distance in metres (default 0)")


def collision_options(args, chain, source: str) -> tuple[object | None, object | None]:
    """``(collision, world)`` of the options (``(None, None)`` without them); ``source``: the robot file."""
    if not (args.self_collision or args.world):
        if args.margin != 0.0 or args.srdf:
            raise DiffkinError("--margin / --srdf apply with --self-collision or --world")
        return None, None
    if not math.isfinite(args.margin) or args.margin < 0:
        raise DiffkinError(f"--margin: expected a finite distance >= 0 (m), got {args.margin}")
    # the reader the option names (--urdf / --mjcf), not the suffix; by suffix only without those options
    flag = next((f for f in ("urdf", "mjcf") if getattr(args, f, None)), None)
    suffix = {"urdf": ".urdf", "mjcf": ".xml"}[flag] if flag else Path(source).suffix.lower()
    if suffix not in (".urdf", ".xml", ".mjcf"):
        raise DiffkinError("--self-collision / --world need the robot's collision geometry: give the robot "
                           "as --urdf FILE or --mjcf FILE (with --end-link)")
    from ..collision import RobotCollision, read_world

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if suffix == ".urdf":
            robot = RobotCollision.from_urdf(source, chain, srdf=args.srdf)
        elif args.srdf:
            raise DiffkinError("--srdf applies to URDF robots (an MJCF file has its own <contact> rules)")
        else:
            robot = RobotCollision.from_mjcf(source, chain)
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    if not robot.geoms:
        raise DiffkinError(f"{source}: no collision geometry found for the chain's links")
    world = read_world(args.world, dtype=chain.dtype, device=chain.device) if args.world else None
    return (robot if args.self_collision else robot.world_only()), world


def collision_free_joints(chain, count: int, seed: int, chunk: int, collision, world, margin: float):
    """``(count, nq)`` float64 collision-free configurations, drawn chunk by chunk from one generator."""
    g = torch.Generator().manual_seed(seed)
    parts, left = [], count
    while left:
        m = min(chunk, left)
        q = chain.random_configuration(m, generator=g, collision=collision, world=world, margin=margin)
        parts.append(q.detach().cpu().double().numpy())
        left -= m
    return np.concatenate(parts)


def solve_keywords(collision, world, margin: float) -> dict:
    """The ``ik.solve`` keywords of the options; an error if this build's solver has no ``collision=``."""
    if collision is None:
        return {}
    from ..ik import solve

    if "collision" not in inspect.signature(solve).parameters:
        raise DiffkinError("ik --self-collision / --world: this build's ik.solve has no collision= keyword")
    return {"collision": collision, "world": world, "margin": margin}
