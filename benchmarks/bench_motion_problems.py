"""How many of the 700 MotionBenchMaker Panda problems start or end in collision, per scene family and robot
model: the baseline a planner's collision model is judged by (VAMP counts 699 valid problems).

    python -m benchmarks.bench_motion_problems [--models capsules spherized] [--families cage box]

Models, both built from VAMP's files unchanged (``tests/data/vamp_panda``, the SRDF's pair rules and each
scene's allowed-collision matrix through :meth:`~diffkin.collision.RobotCollision.allow_collisions`):

* ``capsules``: today's default ``RobotCollision.from_urdf(panda.urdf)`` (each collision mesh fitted by at
  most 4 enclosing capsules; never optimistic, oversized);
* ``spherized``: ``panda_spherized.urdf``'s 59 spheres (VAMP's conservative spherical decomposition);
* ``convex``: ``RobotCollision.from_urdf(panda.urdf, geometry="convex")``, each collision mesh as its exact
  convex hull (link6's mesh is not convex: its hull, larger by at most a few mm).

A state (a start or a goal) is in collision when a checked self pair or a geom–obstacle pair has a signed
distance < 0 (no margin). The world is :meth:`Scene.to_world <diffkin.collision.moveit.Scene.to_world>`;
while it holds a cylinder as its enclosing capsule, every geom–cylinder pair that capsule flags is re-checked
by coal against the true cylinder (``cylinders: exact (coal)``; without coal or with ``--cylinders
capsules``: ``capsules``, the counts of the enclosing capsules). Columns: ``start`` / ``goal`` /
``start_or_goal`` (problems), ``self`` and ``world`` (states in self-collision / touching an obstacle),
``base_world`` (states where a geom of ``panda_link0``, which no joint moves, touches an obstacle). Counting
only: no timing.
"""

from __future__ import annotations

import argparse
import warnings
from collections import defaultdict

import torch

from benchmarks.common import cli
from benchmarks.motion_problems import PANDA_SPHERIZED_URDF, PANDA_SRDF, PANDA_URDF, load_problems
from diffkin import models as dk_models
from diffkin.collision import RobotCollision

__all__ = ["run", "robot_model", "main"]

MODELS = ("capsules", "spherized", "convex")
F64 = torch.float64


def robot_model(name: str) -> RobotCollision:
    """The robot model ``name`` (module docstring) on a float64 chain to ``panda_hand`` (fingers included:
    they are fixed joints in VAMP's URDF)."""
    urdf = {"capsules": PANDA_URDF, "spherized": PANDA_SPHERIZED_URDF, "convex": PANDA_URDF}[name]
    chain = dk_models.from_urdf(urdf, "panda_hand", dtype=F64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # panda.urdf's visual meshes are not vendored (collision ones are)
        return RobotCollision.from_urdf(urdf, chain, PANDA_SRDF,
                                        geometry="convex" if name == "convex" else "capsules")


def run(args=None, *, models=MODELS, families=None, problems=None, cylinders: str = "exact") -> list[dict]:
    """One row per (model, family) and a total row per model (module docstring); ``cylinders="capsules"``
    counts the world's capsules as they are (no coal re-check)."""
    if args is not None:  # benchmarks.run's namespace has none of these: the defaults then
        models = getattr(args, "models", models)
        families = getattr(args, "families", families)
        cylinders = getattr(args, "cylinders", cylinders)
    problems = load_problems(families=families) if problems is None else problems
    rows = []
    for name in models:
        rc = robot_model(name)
        counts = _count(rc, problems, exact=cylinders == "exact")
        total: dict = defaultdict(int)
        for family in sorted(counts):
            c = counts[family]
            rows.append({"benchmark": "motion_problems", "model": name, "family": family, **c})
            for k, v in c.items():
                total[k] = v if isinstance(v, str) else total[k] + v
        rows.append({"benchmark": "motion_problems", "model": name, "family": "all", **total})
    return rows


def _count(rc: RobotCollision, problems, exact: bool = True) -> dict[str, dict]:
    rules: dict = {}  # one model per distinct allowed-collision matrix (all 700 share one)
    q = torch.tensor([[p.start, p.goal] for p in problems], dtype=F64)  # (N, 2, 7)
    base = torch.tensor([g.link == "panda_link0" for g in rc.geoms])
    label = "exact" if exact else "capsules"
    out: dict[str, dict] = {}
    with torch.no_grad():
        for k, p in enumerate(problems):
            model = rules.get(p.scene.allowed)
            if model is None:
                model = rules[p.scene.allowed] = rc.allow_collisions(p.scene.allowed)
            world = p.scene.to_world(dtype=F64, cylinders=None if exact else "capsules")
            self_hit = (model.self_distances(q[k]) < 0).any(-1)  # (2,)
            d = model.world_distances(q[k], world)  # (2, G, W)
            hit = d < 0
            world_hit = hit.flatten(1).any(-1)
            base_hit = hit[:, base].flatten(1).any(-1)
            state = self_hit | world_hit
            c = out.setdefault(p.family, {"problems": 0, "start": 0, "goal": 0, "start_or_goal": 0, "self": 0,
                                          "world": 0, "base_world": 0,
                                          "cylinders": label})
            c["problems"] += 1
            c["start"] += int(state[0])
            c["goal"] += int(state[1])
            c["start_or_goal"] += int(state.any())
            c["self"] += int(self_hit.sum())
            c["world"] += int(world_hit.sum())
            c["base_world"] += int(base_hit.sum())
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", nargs="*", default=list(MODELS), choices=MODELS)
    p.add_argument("--families", nargs="*", default=None)
    p.add_argument("--cylinders", default="exact", choices=("exact", "capsules"),
                   help="exact: the scenes' cylinders as exact cylinders; capsules: as their enclosing "
                   "capsules")
    return cli(p, run, "MotionBenchMaker Panda: problems whose start or goal is in collision", argv)


if __name__ == "__main__":
    raise SystemExit(main())
