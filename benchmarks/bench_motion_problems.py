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

``--plan``: instead, ``motion.plan`` on every problem with the spherized model, the problems in batched
calls of ``--chunk`` problems each (one scene per problem, ``World.stack``; Franka's velocity, acceleration
and jerk limits), ``--iterations`` RRT-Connect iterations and ``--step``: per family the valid problems
(start and goal clear of the resolution), the successes, and planning seconds; the total wall time of all
calls and its mean per problem. ``--recheck`` successes per family are re-checked by an independent checker:
Pinocchio places the spherized URDF's spheres, coal measures their distances to the scene's boxes and
cylinders at every 10 ms sample of the trajectory (geoms that move only; self pairs are not re-checked).
``--optimize``: the plans twice in the same run, without and with
``motion.plan``'s optimisation stage (``optimized``: the problems timed along their optimised knots,
``length_rad_median``: the joint-space path length). ``--indices``: those problem numbers per family.
``--ompl N``: beside it, OMPL's RRT-Connect (PyPI ``ompl``; skipped when it is not importable) on the first N
problems of each family, one problem at a time, its state validity checker diffkin's C decision for one
configuration (the same model and scene, margin 0), OMPL's own discrete motion checks (its default
resolution, not diffkin's proven step bound), ``--ompl-time`` seconds per problem, no smoothing or timing:
per family the successes and the median planning milliseconds.
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


def plan_rows(problems, chunk: int = 700, iterations: int = 30000, step: float = 0.5, recheck: int = 5,
              seed: int = 0, optimize: bool = False) -> list[dict]:
    """The ``--plan`` rows (module docstring): one per family and a total."""
    import time

    import numpy as np

    from benchmarks.motion_problems import FRANKA_A, FRANKA_J, FRANKA_V
    from diffkin import motion
    from diffkin.collision import World

    rc = robot_model("spherized").requires_grad_(False)
    chain = rc.chain
    out: dict[str, dict] = {}
    total = 0.0
    checker = _CoalPanda() if recheck else None
    for k0 in range(0, len(problems), chunk):
        part = problems[k0:k0 + chunk]
        allowed = {p.scene.allowed for p in part}
        if len(allowed) != 1:  # one model per call (all 700 share one allowed-collision matrix)
            raise ValueError("a chunk of problems with different allowed-collision matrices")
        model = rc.allow_collisions(allowed.pop())
        worlds = [p.scene.to_world(dtype=F64) for p in part]
        qs = torch.tensor([p.start for p in part], dtype=F64)
        qg = torch.tensor([p.goal for p in part], dtype=F64)
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = motion.plan(chain, qs, qg, collision=model, world=World.stack(worlds),
                              velocity_limit=FRANKA_V, acceleration_limit=FRANKA_A, jerk_limit=FRANKA_J,
                              max_iterations=iterations, step=step, seed=seed, optimize=optimize)
        dt = time.perf_counter() - t0
        total += dt
        for b, p in enumerate(part):
            c = out.setdefault(p.family, {"problems": 0, "valid": 0, "success": 0, "rechecked": 0,
                                          "recheck_min_mm": float("inf"), "seconds": 0.0, "durations": [],
                                          "lengths": [], "optimized": 0})
            c["problems"] += 1
            c["seconds"] += dt / len(part)
            c["valid"] += int("in collision" not in res.reason[b])
            c["success"] += int(res.success[b])
            c["optimized"] += int(res.optimized[b])
            if bool(res.success[b]):
                c["durations"].append(float(res.duration[b]))
                q = res.q[b].detach()
                c["lengths"].append(float((q[1:] - q[:-1]).norm(dim=-1).sum()))  # joint-space path length
                if checker is not None and c["rechecked"] < recheck:
                    n = int(float(res.duration[b]) / 0.01) + 1
                    d = checker.min_distance(res.q[b, :n].numpy(), worlds[b])
                    c["rechecked"] += 1
                    c["recheck_min_mm"] = min(c["recheck_min_mm"], 1e3 * d)
    rows = []
    for family in sorted(out):
        c = out[family]
        dur = float(np.median(c["durations"])) if c["durations"] else float("nan")
        length = float(np.median(c["lengths"])) if c["lengths"] else float("nan")
        rows.append({"benchmark": "motion_plan", "family": family, "problems": c["problems"],
                     "valid": c["valid"], "success": c["success"], "optimized": c["optimized"],
                     "rechecked": c["rechecked"], "recheck_min_mm": round(c["recheck_min_mm"], 2),
                     "ms_per_problem": 1e3 * c["seconds"] / c["problems"], "duration_s_median": dur,
                     "length_rad_median": length})
    n = sum(c["problems"] for c in out.values())
    rows.append({"benchmark": "motion_plan", "family": "all", "problems": n,
                 "valid": sum(c["valid"] for c in out.values()),
                 "success": sum(c["success"] for c in out.values()),
                 "rechecked": sum(c["rechecked"] for c in out.values()),
                 "recheck_min_mm": round(min(c["recheck_min_mm"] for c in out.values()), 2),
                 "ms_per_problem": 1e3 * total / max(n, 1), "total_s": total, "chunk": chunk,
                 "iterations": iterations, "step": step})
    return rows


def search_rows(problems, iterations: int = 30000, step: float = 0.5, single: int = 10,
                seed: int = 0) -> list[dict]:
    """The ``--search`` rows: the search stage alone (``motion.plan``'s per-row validity with its resolution
    ladder, then the C RRT-Connect and shortcutting, ``diffkin.motion._native_search``), all problems in one
    call (their threads over the cores); then ``single`` problems per family one at a time on one thread:
    the search stage and the whole ``motion.plan`` (smoothing and timing included), median milliseconds.
    Per family: valid problems, paths found, configurations decided."""
    import time

    import numpy as np

    from benchmarks.motion_problems import FRANKA_A, FRANKA_J, FRANKA_V
    from diffkin import motion
    from diffkin.collision import World
    from diffkin.motion._edges import EdgeChecker
    from diffkin.motion._native_search import search_native
    from diffkin.motion.plan import _row_resolution

    rc = robot_model("spherized").requires_grad_(False)
    chain = rc.chain
    model = rc.allow_collisions(problems[0].scene.allowed)
    lim = chain.q_limits

    def stage(part, threads=None):
        worlds = World.stack([p.scene.to_world(dtype=F64) for p in part])
        qs = torch.tensor([p.start for p in part], dtype=F64)
        qg = torch.tensor([p.goal for p in part], dtype=F64)
        t0 = time.perf_counter()
        checker = EdgeChecker(model, worlds, 0.0, 0.005)
        rows = torch.arange(len(part))
        eta, a, b = _row_resolution(checker, qs, qg, rows)
        valid = a & b
        v = rows[valid]
        out = search_native(checker, qs[v], qg[v], lim[:, 0], lim[:, 1], v, eta[v], max_iterations=iterations,
                            step=step, shortcut_tries=64, seed=seed)
        dt = time.perf_counter() - t0
        found = torch.zeros(len(part), dtype=torch.bool)
        found[v] = out[2]
        checked = torch.zeros(len(part), dtype=torch.int64)
        checked[v] = out[3]["checked"]
        return dt, valid, found, checked, (qs, qg, worlds)

    total, valid, found, checked, _ = stage(problems)
    out: dict[str, dict] = {}
    for k, p in enumerate(problems):
        c = out.setdefault(p.family, {"problems": 0, "valid": 0, "found": 0, "checked": []})
        c["problems"] += 1
        c["valid"] += int(valid[k])
        c["found"] += int(found[k])
        c["checked"].append(int(checked[k]))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    one_search, one_plan = defaultdict(list), defaultdict(list)
    try:
        seen: dict = defaultdict(int)
        for p in problems:
            seen[p.family] += 1
            if seen[p.family] > single:
                continue
            dt, _, _, _, (qs, qg, world) = stage([p])
            one_search[p.family].append(1e3 * dt)
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                motion.plan(chain, qs, qg, collision=model, world=world, velocity_limit=FRANKA_V,
                            acceleration_limit=FRANKA_A, jerk_limit=FRANKA_J, max_iterations=iterations,
                            step=step, seed=seed)
            one_plan[p.family].append(1e3 * (time.perf_counter() - t0))
    finally:
        torch.set_num_threads(threads)
    rows = [{"benchmark": "motion_search", "family": f, "problems": c["problems"], "valid": c["valid"],
             "found": c["found"], "checked_median": float(np.median(c["checked"])),
             "one_search_ms_median": float(np.median(one_search[f])) if one_search[f] else float("nan"),
             "one_plan_ms_median": float(np.median(one_plan[f])) if one_plan[f] else float("nan")}
            for f, c in sorted(out.items())]
    every_s = [m for v in one_search.values() for m in v]
    every_p = [m for v in one_plan.values() for m in v]
    rows.append({"benchmark": "motion_search", "family": "all", "problems": len(problems),
                 "valid": int(valid.sum()), "found": int(found.sum()), "search_all_s": total,
                 "checked_median": float(np.median(checked.numpy())),
                 "one_search_ms_median": float(np.median(every_s)) if every_s else float("nan"),
                 "one_plan_ms_median": float(np.median(every_p)) if every_p else float("nan"),
                 "iterations": iterations, "step": step, "single_per_family": single})
    return rows


def ompl_rows(problems, per_family: int = 10, time_limit: float = 1.0) -> list[dict]:
    """The ``--ompl`` rows (module docstring); none when ``ompl`` is not importable."""
    import time

    import numpy as np

    try:
        from ompl import base as ob
        from ompl import geometric as og
    except ImportError:
        return [{"benchmark": "ompl_rrtconnect", "family": "all", "note": "ompl not importable: skipped"}]
    rc = robot_model("spherized").requires_grad_(False)
    lim = rc.chain.q_limits.numpy()
    out: dict[str, dict] = {}
    count: dict[str, int] = {}
    for p in problems:
        count[p.family] = count.get(p.family, 0) + 1
        if count[p.family] > per_family:
            continue
        model = rc.allow_collisions(p.scene.allowed)
        world = p.scene.to_world(dtype=F64)
        space = ob.RealVectorStateSpace(7)
        bounds = ob.RealVectorBounds(7)
        for j in range(7):
            bounds.setLow(j, float(lim[j, 0]))
            bounds.setHigh(j, float(lim[j, 1]))
        space.setBounds(bounds)
        ss = og.SimpleSetup(space)
        buf = torch.zeros(1, 7, dtype=F64)

        def valid(state, model=model, world=world, buf=buf):
            for j in range(7):
                buf[0, j] = state[j]
            return bool(model._clear(buf, world, 0.0, 0.0, moving_only=True)[0])

        ss.setStateValidityChecker(valid)
        start, goal = space.allocState(), space.allocState()
        for j in range(7):
            start[j], goal[j] = p.start[j], p.goal[j]
        ss.setStartAndGoalStates(start, goal)
        ss.setPlanner(og.RRTConnect(ss.getSpaceInformation()))
        t0 = time.perf_counter()
        ss.solve(time_limit)
        dt = time.perf_counter() - t0
        c = out.setdefault(p.family, {"problems": 0, "success": 0, "ms": []})
        c["problems"] += 1
        c["success"] += int(ss.haveExactSolutionPath())
        c["ms"].append(1e3 * dt)
    rows = [{"benchmark": "ompl_rrtconnect", "family": f, "problems": c["problems"], "success": c["success"],
             "ms_median": float(np.median(c["ms"]))} for f, c in sorted(out.items())]
    every = [m for c in out.values() for m in c["ms"]]
    rows.append({"benchmark": "ompl_rrtconnect", "family": "all", "problems": len(every),
                 "success": sum(c["success"] for c in out.values()), "ms_median": float(np.median(every)),
                 "time_limit_s": time_limit})
    return rows


class _CoalPanda:
    """The independent re-check of ``--plan``: Pinocchio places the spheres of ``panda_spherized.urdf``
    (its own URDF parser and FK), coal measures each moving sphere's distance to each box and cylinder of a
    scene (``tests/collision_reference.py``'s coal set-up)."""

    def __init__(self):
        import pinocchio as pin

        from tests import collision_reference as ref

        self._pin, self._ref = pin, ref
        self.model = pin.buildModelFromUrdf(str(PANDA_SPHERIZED_URDF))
        self.geom = pin.buildGeomFromUrdf(self.model, str(PANDA_SPHERIZED_URDF), pin.COLLISION)
        self.data, self.gdata = self.model.createData(), pin.GeometryData(self.geom)
        self.moving = [i for i, o in enumerate(self.geom.geometryObjects) if o.parentJoint > 0]
        names = [f"panda_joint{i}" for i in range(1, 8)]
        self.q_of = [self.model.joints[self.model.getJointId(n)].idx_q for n in names]

    def min_distance(self, qs, world) -> float:
        """The least sphere–obstacle distance [m] over the configurations ``qs (S, 7)``."""
        ref, pin, coal = self._ref, self._pin, self._ref.coal
        obstacles = [ref.box(c, R, h) for c, R, h in zip(world.boxes.center.numpy(),
                                                          world.boxes.rotation.numpy(),
                                                          world.boxes.half_extents.numpy())]
        for y in world.cylinders.numpy():
            R, m, length = ref.frame_along(y[:3], y[3:6])
            obstacles.append((coal.Cylinder(float(y[6]), length), ref.placement(R, m)))
        best = float("inf")
        for q in qs:
            qp = pin.neutral(self.model)
            qp[self.q_of] = q
            pin.updateGeometryPlacements(self.model, self.data, self.geom, self.gdata, qp)
            for i in self.moving:
                M = self.gdata.oMg[i]
                g, T = self.geom.geometryObjects[i].geometry, ref.placement(M.rotation, M.translation)
                for o, To in obstacles:
                    best = min(best, ref.distance(g, T, o, To))
        return best


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", nargs="*", default=list(MODELS), choices=MODELS)
    p.add_argument("--families", nargs="*", default=None)
    p.add_argument("--cylinders", default="exact", choices=("exact", "capsules"),
                   help="exact: the scenes' cylinders as exact cylinders; capsules: as their enclosing "
                   "capsules")
    p.add_argument("--plan", action="store_true", help="plan every problem (module docstring)")
    p.add_argument("--search", action="store_true",
                   help="the search stage alone, batched and one at a time (search_rows)")
    p.add_argument("--single", type=int, default=10,
                   help="--search: problems per family planned one at a time")
    p.add_argument("--chunk", type=int, default=700)
    p.add_argument("--iterations", type=int, default=30000)
    p.add_argument("--step", type=float, default=0.5)
    p.add_argument("--recheck", type=int, default=5)
    p.add_argument("--ompl", type=int, default=0, help="OMPL RRT-Connect on the first N problems per family")
    p.add_argument("--ompl-time", type=float, default=1.0)
    p.add_argument("--indices", nargs="*", type=int, default=None, help="these problem numbers per family")
    p.add_argument("--optimize", action="store_true",
                   help="--plan twice in the same run, without and with the optimisation stage")
    known = p.parse_known_args(argv)[0]
    if known.plan or known.ompl or known.search:
        def both(a):
            problems = load_problems(families=a.families, indices=a.indices)
            rows = search_rows(problems, a.iterations, a.step, a.single) if a.search else []
            for opt in ((False, True) if a.optimize else (False,)) if a.plan else ():
                rows += [{**r, "optimize": opt} for r in plan_rows(problems, a.chunk, a.iterations, a.step,
                                                                   a.recheck, optimize=opt)]
            return rows + (ompl_rows(problems, a.ompl, a.ompl_time) if a.ompl else [])

        return cli(p, both, "MotionBenchMaker Panda: motion.plan batched, OMPL RRT-Connect", argv)
    return cli(p, run, "MotionBenchMaker Panda: problems whose start or goal is in collision", argv)


if __name__ == "__main__":
    raise SystemExit(main())
