"""How many of the 700 MotionBenchMaker Panda problems start or end in collision, per scene family and robot
model: the baseline a planner's collision model is judged by (VAMP counts 699 valid problems).

    python -m benchmarks.bench_motion_problems [--models capsules spherized] [--families cage box]
    python -m benchmarks.bench_motion_problems --compare --out docs/bench/motion_problems.txt  # + VAMP, OMPL

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

``--compare``: diffkin, VAMP and OMPL on the same problems in one run, one text table (``--out``; the
figures in ``docs/bench/motion_problems.txt``), a row per method and family:

* ``diffkin plan, one call``: ``motion.plan`` on every problem in **one** batched call (``World.stack`` of
  all the scenes; ``--iterations``, ``--step``; the spherized model, Franka limits): valid problems,
  successes, the call's time per problem, and per success the duration, the joint-space length of the
  10 ms samples and the largest jerk (|Δq̈|/Δt every 1 ms); ``--recheck`` successes per family re-checked
  as in ``--plan``;
* ``VAMP rrtc + simplify`` (:mod:`benchmarks.peers_vamp`, VAMP 0.6.4 built from its sdist by
  ``benchmarks/install_vamp.sh``, in its own venv; skipped when absent): VAMP's own problem conversion,
  spherized Panda, default RRT-Connect and simplification on every problem; its clock's median planning
  (``search_ms``) and planning + simplification (``ms``) times; its simplified path timed by toppra under
  the same Franka velocity and acceleration limits (at rest at every waypoint: the path it checked;
  ``spline_s``: the unchecked cubic spline through its waypoints), length and jerk as above; ``crossing``:
  how many of its solved paths cross its own sphere model of the robot against the exact scene (a distance
  < 0) somewhere along them, between its discrete checks (:func:`vamp_crossings`: samples at most 1 mm of
  travel apart);
* ``diffkin plan, one at a time``: the first ``--subset`` problems of each family, each in its own call on one
  thread (after one untimed warm-up call), and the search stage alone on each (the edge checker and
  RRT-Connect as ``plan`` runs them, :func:`_search_stage`): median wall times, and the search's median over
  VAMP's median planning time on the same problems (``search_vs_vamp``); and the search again with its scene
  prepared before the clock starts (:func:`prepared_scene`: the edge checker and its C constants, as VAMP's
  clock starts after ``problem_dict_to_vamp`` has built its environment): ``search_prepared_ms`` and
  ``prepared_vs_vamp``; and that call's own time in C (a monotonic clock read in its thread around each
  problem), as VAMP's clock times its planner (its start and goal decisions included; no Python):
  ``search_c_ms`` and ``c_vs_vamp``; and the decisions proving the path found alone (:func:`_path_proof`:
  its edges decided whole in C at the problem's resolution, as the search decides them, the least of 3
  calls where the others are single calls; what a search returning that path pays at least):
  ``proof_ms`` and ``proof_vs_vamp``;
* ``OMPL RRTConnect``: on the same subset, as ``--ompl`` (``--ompl-time`` seconds each). When ``ompl`` is
  not importable here, ``OMPL_SITE`` names a site-packages holding PyPI ``ompl`` (appended to ``sys.path``).

Duration ratios (``dur_vs_vamp_*``) are medians of per-problem ratios over the problems both solved.
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
#: RRT-Connect iterations per problem: VAMP's budget (``vamp.configure_robot_and_planner_with_kwargs``); the C
#: trees grow as they fill, so a problem pays only for the iterations it takes (bookshelf_thin/0089, a start
#: in a narrow pocket, took 8 625 to 160 371 over seeds 0-3 with balanced trees and step 1.0: the pocket's
#: tree, the smaller, takes the iterations, most of them failing at once)
ITERATIONS = 1_000_000


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


def _plan_records(problems, chunk: int = 700, iterations: int = ITERATIONS, step: float = 1.0,
                  recheck: int = 5, seed: int = 0, optimize: bool = False) -> tuple[list[dict], float]:
    """``motion.plan`` on ``problems`` in batched calls of ``chunk`` (module docstring, ``--plan``): one
    record per problem (``family``, ``valid``, ``success``, ``duration`` [s], ``length`` (joint-space length
    of the 10 ms samples, rad), ``jerk_max`` (largest |Δq̈|/Δt of the trajectory sampled every 1 ms, rad/s³),
    ``recheck_mm`` (the coal re-check's least distance, or None), ``optimized`` (timed along the optimisation
    stage's knots, with ``optimize``), ``seconds`` (its call's time / its size)) and the total seconds of the
    calls."""
    import time

    from benchmarks.motion_problems import FRANKA_A, FRANKA_J, FRANKA_V
    from diffkin import motion
    from diffkin.collision import World
    from diffkin.kernels import native

    native.status()  # the C library built (a fresh checkout compiles it: tens of seconds) before any clock
    rc = robot_model("spherized").requires_grad_(False)
    chain = rc.chain
    total = 0.0
    checker = _CoalPanda() if recheck else None
    rechecked: dict[str, int] = defaultdict(int)
    records = []
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
        length = res.q.diff(dim=1).norm(dim=-1).sum(1)
        jerk = _max_jerk(res)
        for b, p in enumerate(part):
            ok = bool(res.success[b])
            r = {"family": p.family, "name": p.name, "valid": "in collision" not in res.reason[b],
                 "success": ok, "duration": float(res.duration[b]) if ok else None,
                 "length": float(length[b]) if ok else None, "jerk_max": float(jerk[b]) if ok else None,
                 "recheck_mm": None, "optimized": bool(res.optimized[b]), "seconds": dt / len(part)}
            if ok and checker is not None and rechecked[p.family] < recheck:
                n = int(float(res.duration[b]) / 0.01) + 1
                r["recheck_mm"] = 1e3 * checker.min_distance(res.q[b, :n].numpy(), worlds[b])
                rechecked[p.family] += 1
            records.append(r)
    return records, total


def _max_jerk(res, dt: float = 1e-3, window: int = 1000) -> torch.Tensor:
    """(B,) the largest |Δq̈|/Δt of each row of a ``MotionResult`` sampled every ``dt`` (rows rest at both
    ends, so rows past their duration add nothing), in windows of ``window`` samples."""
    n = int(float(res.duration.max()) / dt) + 2
    best = torch.zeros(res.duration.shape[0], dtype=F64)
    for k0 in range(0, n, window):
        t = torch.arange(k0, min(n, k0 + window + 1), dtype=F64) * dt  # one sample of overlap
        if t.numel() < 2:
            break
        qdd = res.state(t).acceleration
        best = torch.maximum(best, qdd.diff(dim=1).abs().flatten(1).amax(1) / dt)
    return best


def plan_rows(problems, chunk: int = 700, iterations: int = ITERATIONS, step: float = 1.0, recheck: int = 5,
              seed: int = 0, optimize: bool = False) -> list[dict]:
    """The ``--plan`` rows (module docstring): one per family and a total."""
    import numpy as np

    records, total = _plan_records(problems, chunk, iterations, step, recheck, seed, optimize)
    rows = []
    by_family = _by_family(records)
    for family, rs in by_family.items():
        dur = [r["duration"] for r in rs if r["success"]]
        length = [r["length"] for r in rs if r["success"]]
        mm = [r["recheck_mm"] for r in rs if r["recheck_mm"] is not None]
        rows.append({"benchmark": "motion_plan", "family": family, "problems": len(rs),
                     "valid": sum(r["valid"] for r in rs), "success": sum(r["success"] for r in rs),
                     "optimized": sum(r["optimized"] for r in rs),
                     "rechecked": len(mm), "recheck_min_mm": round(min(mm), 2) if mm else None,
                     "ms_per_problem": 1e3 * sum(r["seconds"] for r in rs) / len(rs),
                     "duration_s_median": float(np.median(dur)) if dur else float("nan"),
                     "length_rad_median": float(np.median(length)) if length else float("nan")})
    mm = [r["recheck_mm"] for r in records if r["recheck_mm"] is not None]
    rows.append({"benchmark": "motion_plan", "family": "all", "problems": len(records),
                 "valid": sum(r["valid"] for r in records), "success": sum(r["success"] for r in records),
                 "rechecked": len(mm), "recheck_min_mm": round(min(mm), 2) if mm else None,
                 "ms_per_problem": 1e3 * total / max(len(records), 1), "total_s": total, "chunk": chunk,
                 "iterations": iterations, "step": step})
    return rows


def _by_family(records) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for r in records:
        out.setdefault(r["family"], []).append(r)
    return dict(sorted(out.items()))


def prepared_scene(model, world, qs):
    """The scene made ready for the search: the edge checker and its C planner's constants (world arrays,
    skip masks, the decisions' struct: ``NativePlanner.make``), as VAMP's ``problem_dict_to_vamp`` makes its
    environment before its clock starts."""
    from diffkin.motion._edges import EdgeChecker

    checker = EdgeChecker(model, world, 0.0, 0.005)
    checker.native(qs)
    return checker


def _search_stage(chain, model, world, qs, qg, iterations: int, step: float,
                  seed: int, checker=None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``motion.plan``'s search stage alone, as ``plan`` runs it: one C call
    (:mod:`diffkin.motion._native_search`) deciding each start and goal at ``plan``'s resolution ladder (the
    continuous edge checker at ``plan``'s default resolution, margin 0), then RRT-Connect -> ``found``,
    ``valid`` (B,) bool, ``checked`` (B,) configurations decided and ``nanoseconds`` (B,): each problem's wall
    time in C, from a monotonic clock in its thread (as VAMP's planners time themselves). No goal IK,
    shortcutting (``plan``'s random shortcuts run in the same C call: left out here, as VAMP's planning time
    leaves out its simplification), smoothing or timing. ``checker``: the scene already prepared
    (:func:`prepared_scene`), else prepared here."""
    from diffkin.motion._native_search import search_native
    from diffkin.motion.plan import ETA_LEVELS

    lim = chain.q_limits
    checker = prepared_scene(model, world, qs) if checker is None else checker
    out = search_native(checker, qs, qg, lim[:, 0], lim[:, 1], torch.arange(qs.shape[0]), None,
                        max_iterations=iterations, step=step, shortcut_tries=0, seed=seed,
                        rungs=ETA_LEVELS + 1)
    stats = out[3]
    return out[2], stats["start_ok"] & stats["goal_ok"], stats["checked"], stats["nanoseconds"]


def _path_proof(chain, checker, qs, qg, iterations: int, step: float, seed: int,
                repeats: int = 3) -> tuple[float, int] | None:
    """The decisions proving the found path alone (what a search returning this path pays at least with this
    edge checker, its start and goal decisions aside): the path of :func:`_search_stage` (one problem,
    ``checker`` prepared, :func:`prepared_scene`) found again, then its edges decided whole in C at the
    problem's resolution (``EdgeChecker.edges``: covers, as the search's; each edge from its first sample,
    where the search takes that one as known clear), timed alone -> (seconds: the least of ``repeats`` calls'
    wall time less the least of as many calls with no edge; configurations decided), None where no path was
    found (or, never seen, the C call is refused or refuses an edge of the path: rounding at a threshold)."""
    import time

    from diffkin.motion._native_search import search_native
    from diffkin.motion.plan import ETA_LEVELS

    lim = chain.q_limits
    out = search_native(checker, qs, qg, lim[:, 0], lim[:, 1], torch.arange(1), None,
                        max_iterations=iterations, step=step, shortcut_tries=0, seed=seed,
                        rungs=ETA_LEVELS + 1)
    if not bool(out[2][0]):
        return None
    n = int(out[1][0])
    qa, qb = out[0][0, :n - 1].contiguous(), out[0][0, 1:n].contiguous()
    checker.set_row_resolution(out[3]["eta"])
    rows = torch.zeros(n - 1, dtype=torch.long)
    steps, eta = checker.steps(qb - qa, rows), checker.eta_of(rows)
    planner = checker.native(qs)
    best, empty = float("inf"), float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        got = planner.edges(qa, qb, steps, eta, None, False)
        t1 = time.perf_counter()
        planner.edges(qa[:0], qb[:0], steps[:0], eta[:0], None, False)
        t2 = time.perf_counter()
        best, empty = min(best, t1 - t0), min(empty, t2 - t1)
    if got is None or not bool((got[0] > steps).all()):  # (first_bad > steps: every sample clear)
        return None
    return max(best - empty, 0.0), int(got[1].sum())


def search_rows(problems, iterations: int = ITERATIONS, step: float = 1.0, single: int = 10,
                seed: int = 0) -> list[dict]:
    """The ``--search`` rows: the search stage alone (:func:`_search_stage`), all problems in one call (their
    threads over the cores); then ``single`` problems per family one at a time on one thread: the search
    stage and the whole ``motion.plan`` (smoothing and timing included), median milliseconds. Per family:
    valid problems, paths found, configurations decided."""
    import time

    import numpy as np

    from benchmarks.motion_problems import FRANKA_A, FRANKA_J, FRANKA_V
    from diffkin import motion
    from diffkin.collision import World

    rc = robot_model("spherized").requires_grad_(False)
    chain = rc.chain
    model = rc.allow_collisions(problems[0].scene.allowed)

    def stage(part):
        worlds = World.stack([p.scene.to_world(dtype=F64) for p in part])
        qs = torch.tensor([p.start for p in part], dtype=F64)
        qg = torch.tensor([p.goal for p in part], dtype=F64)
        t0 = time.perf_counter()
        found, valid, checked, _ = _search_stage(chain, model, worlds, qs, qg, iterations, step, seed)
        return time.perf_counter() - t0, valid, found, checked, (qs, qg, worlds)

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


def _one_at_a_time(problems, iterations: int, step: float, seed: int, ompl_time: float) -> list[dict]:
    """One record per problem: ``motion.plan`` on it alone (``plan_s``, ``success``), the search stage alone
    (``search_s``, ``found``) and OMPL's RRT-Connect (``ompl_s``, ``ompl_success``; None without ompl), on
    one thread (the issue's measure; torch's thread count restored after)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _one_at_a_time_records(problems, iterations, step, seed, ompl_time)
    finally:
        torch.set_num_threads(threads)


def _one_at_a_time_records(problems, iterations: int, step: float, seed: int, ompl_time: float) -> list[dict]:
    """:func:`_one_at_a_time`'s records, on the threads set."""
    import time

    from benchmarks.motion_problems import FRANKA_A, FRANKA_J, FRANKA_V
    from diffkin import motion

    rc = robot_model("spherized").requires_grad_(False)
    chain = rc.chain
    lim = chain.q_limits.numpy()
    mods = _ompl_modules()
    records = []
    for k, p in enumerate([*problems[:1], *problems]):  # the first one twice: a warm-up call, not recorded
        model = rc.allow_collisions(p.scene.allowed)
        world = p.scene.to_world(dtype=F64)
        qs = torch.tensor([p.start], dtype=F64)
        qg = torch.tensor([p.goal], dtype=F64)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t0 = time.perf_counter()
            res = motion.plan(chain, qs, qg, collision=model, world=world, velocity_limit=FRANKA_V,
                              acceleration_limit=FRANKA_A, jerk_limit=FRANKA_J, max_iterations=iterations,
                              step=step, seed=seed)
            t1 = time.perf_counter()
            found = _search_stage(chain, model, world, qs, qg, iterations, step, seed)[0]
            t2 = time.perf_counter()
            checker = prepared_scene(model, world, qs)  # the scene made ready first, as VAMP's environment
            t3 = time.perf_counter()
            c_ns = _search_stage(chain, model, world, qs, qg, iterations, step, seed, checker)[3]
            t4 = time.perf_counter()
            proof = _path_proof(chain, checker, qs, qg, iterations, step, seed)
        r = {"family": p.family, "name": p.name, "valid": "in collision" not in res.reason[0],
             "success": bool(res.success[0]), "plan_s": t1 - t0, "found": bool(found[0]), "search_s": t2 - t1,
             "search_prepared_s": t4 - t3, "search_c_s": 1e-9 * float(c_ns[0]),
             "proof_s": proof[0] if proof else None,
             "ompl_success": None, "ompl_s": None}
        if mods is not None:
            r["ompl_success"], r["ompl_s"] = _ompl_solve(*mods, model, world, lim, p, ompl_time)
        if k:
            records.append(r)
    return records


def vamp_crossings(problems, vamp: dict, max_travel: float = 1e-3) -> dict[str, bool]:
    """Whether each path VAMP solved crosses its own collision model somewhere along it: the spherized Panda
    of this benchmark against the problem's exact scene (VAMP's own environment encloses its cylinders, so a
    crossing here is one there too), margin 0, decided by diffkin's C decisions at samples of the path's
    straight segments no point of the robot moves more than ``max_travel`` m apart (the edge checker's bound
    sum_j R_j |dq_j|): ``True`` where some sample has a distance < 0 (its waypoints included: VAMP checked
    them). ``vamp``: :func:`benchmarks.peers_vamp.solve_vamp`'s answers by name; keys: the solved
    problems."""
    import math

    from diffkin.motion._edges import EdgeChecker

    rc = robot_model("spherized").requires_grad_(False)
    out = {}
    for p in problems:
        a = vamp[p.name]
        if not a["solved"]:
            continue
        checker = EdgeChecker(rc.allow_collisions(p.scene.allowed), p.scene.to_world(dtype=F64), 0.0, 0.005)
        path = torch.tensor(a["path"], dtype=F64)
        parts = [path[:1]]
        for qa, qb in zip(path[:-1], path[1:]):
            k = max(1, math.ceil(float((qb - qa).abs() @ checker.reach) / max_travel))
            parts.append(qa + torch.arange(1, k + 1, dtype=F64)[:, None] / k * (qb - qa))
        q = torch.cat(parts)
        out[p.name] = not bool(checker.clear(q, torch.zeros(q.shape[0], dtype=torch.long), slack=0.0).all())
    return out


def compare_rows(problems, subset: int = 5, iterations: int = ITERATIONS, step: float = 1.0, recheck: int = 2,
                 ompl_time: float = 1.0, seed: int = 0) -> list[dict]:
    """The ``--compare`` table (module docstring): diffkin (all problems in one call; one at a time on the
    first ``subset`` of each family), VAMP and OMPL in one run, a row per method and family."""
    import numpy as np

    from benchmarks import peers_vamp
    from benchmarks.motion_problems import ARCHIVE, FRANKA_A, FRANKA_V

    def med(x):
        return float(np.median(x)) if len(x) else None

    def pick(rs, f):
        return [r for r in rs if f in ("all", r["family"])]

    vamp = None
    if peers_vamp.available():
        vamp = {a["name"]: a for a in peers_vamp.solve_vamp(problems, ARCHIVE, FRANKA_V, FRANKA_A)}
        crossing = vamp_crossings(problems, vamp)
    batch, total = _plan_records(problems, len(problems), iterations, step, recheck, seed)
    first = [p for p in problems if p.index <= subset]
    single = _one_at_a_time(first, iterations, step, seed, ompl_time)
    rows = []
    families = sorted({p.family for p in problems}) + ["all"]
    for f in families:
        rs = pick(batch, f)
        ratio_stop, ratio_spline = [], []
        if vamp is not None:
            for r in rs:
                v = vamp[r["name"]]
                if r["success"] and v["solved"]:
                    ratio_stop.append(r["duration"] / v["toppra_stop_s"])
                    ratio_spline.append(r["duration"] / v["toppra_spline_s"])
        mm = [r["recheck_mm"] for r in rs if r["recheck_mm"] is not None]
        ok = [r for r in rs if r["success"]]
        rows.append({"method": "diffkin plan, one call", "family": f, "problems": len(rs),
                     "valid": sum(r["valid"] for r in rs), "success": len(ok),
                     "ms": 1e3 * total / len(batch) if f == "all" else None,
                     "duration_s": med([r["duration"] for r in ok]),
                     "dur_vs_vamp_stop": med(ratio_stop), "dur_vs_vamp_spline": med(ratio_spline),
                     "length_rad": med([r["length"] for r in ok]),
                     "jerk_max": max((r["jerk_max"] for r in ok), default=None),
                     "recheck_min_mm": min(mm) if mm else None})
        if vamp is not None:
            vs = [vamp[r["name"]] for r in rs]
            sv = [v for v in vs if v["solved"]]
            rows.append({"method": "VAMP rrtc + simplify", "family": f, "problems": len(vs),
                         "valid": sum(v["valid"] for v in vs), "success": len(sv),
                         "ms": med([1e-6 * (v["plan_ns"] + v["simplify_ns"]) for v in sv]),
                         "crossing": sum(crossing[v["name"]] for v in sv),
                         "search_ms": med([1e-6 * v["plan_ns"] for v in sv]),
                         "duration_s": med([v["toppra_stop_s"] for v in sv]),
                         "spline_s": med([v["toppra_spline_s"] for v in sv]),
                         "length_rad": med([v["length"] for v in sv]),
                         "jerk_max": max((v["jerk_max"] for v in sv), default=None)})
        ss = pick(single, f)
        if not ss:
            continue
        search_ms = [1e3 * r["search_s"] for r in ss if r["found"]]
        prepared_ms = [1e3 * r["search_prepared_s"] for r in ss if r["found"]]
        c_ms = [1e3 * r["search_c_s"] for r in ss if r["found"]]
        proof_ms = [1e3 * r["proof_s"] for r in ss if r["proof_s"] is not None]
        vamp_ms = [1e-6 * vamp[r["name"]]["plan_ns"] for r in ss if vamp[r["name"]]["solved"]] if vamp else []
        rows.append({"method": f"diffkin plan, one at a time (first {subset})", "family": f,
                     "problems": len(ss), "valid": sum(r["valid"] for r in ss),
                     "success": sum(r["success"] for r in ss), "ms": med([1e3 * r["plan_s"] for r in ss]),
                     "search_ms": med(search_ms), "search_found": sum(r["found"] for r in ss),
                     "search_vs_vamp": (med(search_ms) / med(vamp_ms)) if search_ms and vamp_ms else None,
                     "search_prepared_ms": med(prepared_ms),
                     "prepared_vs_vamp": (med(prepared_ms) / med(vamp_ms)) if prepared_ms and vamp_ms
                     else None, "search_c_ms": med(c_ms),
                     "c_vs_vamp": (med(c_ms) / med(vamp_ms)) if c_ms and vamp_ms else None,
                     "proof_ms": med(proof_ms),
                     "proof_vs_vamp": (med(proof_ms) / med(vamp_ms)) if proof_ms and vamp_ms else None})
        if ss[0]["ompl_success"] is not None:
            rows.append({"method": f"OMPL RRTConnect, diffkin checker (first {subset}, {ompl_time:g} s)",
                         "family": f, "problems": len(ss), "success": sum(r["ompl_success"] for r in ss),
                         "ms": med([1e3 * r["ompl_s"] for r in ss])})
    return rows


COLUMNS = ("method", "family", "problems", "valid", "success", "ms", "search_ms", "search_found",
           "search_vs_vamp", "search_prepared_ms", "prepared_vs_vamp", "search_c_ms", "c_vs_vamp",
           "proof_ms", "proof_vs_vamp", "crossing",
           "duration_s", "spline_s",
           "dur_vs_vamp_stop", "dur_vs_vamp_spline", "length_rad",
           "jerk_max", "recheck_min_mm")


def format_table(rows, columns=COLUMNS) -> str:
    """``rows`` as a fixed-width text table of ``columns`` (a blank where a row has no value; numbers to
    4 significant digits), rows grouped by family in their order."""
    def cell(v):
        if v is None:
            return ""
        if isinstance(v, bool):
            return str(v)
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    cols = [c for c in columns if any(r.get(c) is not None for r in rows)]
    cells = [[cell(r.get(c)) for c in cols] for r in rows]
    width = [max([len(c)] + [len(line[k]) for line in cells]) for k, c in enumerate(cols)]
    lines = [_join(cols, width)]
    lines.append("  ".join("-" * w for w in width))
    last = None
    for r, line in zip(rows, cells):
        if last is not None and r.get("family") != last:
            lines.append("")
        last = r.get("family")
        lines.append(_join(line, width))
    return "\n".join(lines) + "\n"


def _join(cells, width) -> str:  # the first two columns (method, family) left-aligned, numbers right
    return "  ".join(x.ljust(w) if k < 2 else x.rjust(w) for k, (x, w) in enumerate(zip(cells, width)))


def _ompl_modules():
    """OMPL's ``base`` and ``geometric`` modules, or None: from this interpreter, else from the site-packages
    named by ``OMPL_SITE`` (e.g. a venv holding only PyPI ``ompl``), appended after this one's."""
    import os
    import sys

    for attempt in range(2):
        try:
            from ompl import base as ob
            from ompl import geometric as og
            return ob, og
        except ImportError:
            site = os.environ.get("OMPL_SITE")
            if attempt or not site:
                return None
            sys.path.append(site)
    return None


def _ompl_solve(ob, og, model, world, lim, p, time_limit: float) -> tuple[bool, float]:
    """OMPL's RRT-Connect on problem ``p`` (module docstring) -> (exact solution found, wall seconds of
    ``solve``)."""
    import time

    space = ob.RealVectorStateSpace(7)
    bounds = ob.RealVectorBounds(7)
    for j in range(7):
        bounds.setLow(j, float(lim[j, 0]))
        bounds.setHigh(j, float(lim[j, 1]))
    space.setBounds(bounds)
    ss = og.SimpleSetup(space)
    buf = torch.zeros(1, 7, dtype=F64)

    def valid(state):
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
    return bool(ss.haveExactSolutionPath()), time.perf_counter() - t0


def ompl_rows(problems, per_family: int = 10, time_limit: float = 1.0) -> list[dict]:
    """The ``--ompl`` rows (module docstring); none when ``ompl`` is not importable."""
    import numpy as np

    mods = _ompl_modules()
    if mods is None:
        return [{"benchmark": "ompl_rrtconnect", "family": "all", "note": "ompl not importable: skipped"}]
    rc = robot_model("spherized").requires_grad_(False)
    lim = rc.chain.q_limits.numpy()
    out: dict[str, dict] = {}
    count: dict[str, int] = {}
    for p in problems:
        count[p.family] = count.get(p.family, 0) + 1
        if count[p.family] > per_family:
            continue
        ok, dt = _ompl_solve(*mods, rc.allow_collisions(p.scene.allowed), p.scene.to_world(dtype=F64), lim, p,
                             time_limit)
        c = out.setdefault(p.family, {"problems": 0, "success": 0, "ms": []})
        c["problems"] += 1
        c["success"] += int(ok)
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
    p.add_argument("--iterations", type=int, default=ITERATIONS)
    p.add_argument("--step", type=float, default=1.0)
    p.add_argument("--recheck", type=int, default=5)
    p.add_argument("--ompl", type=int, default=0, help="OMPL RRT-Connect on the first N problems per family")
    p.add_argument("--ompl-time", type=float, default=1.0)
    p.add_argument("--compare", action="store_true",
                   help="diffkin, VAMP and OMPL in one run (module docstring)")
    p.add_argument("--subset", type=int, default=5,
                   help="--compare: problems per family planned one at a time")
    p.add_argument("--indices", type=int, nargs="*", default=None, help="only these problem numbers (1-100)")
    p.add_argument("--out", default=None, help="--compare: also write the table to this text file")
    p.add_argument("--optimize", action="store_true",
                   help="--plan twice in the same run, without and with the optimisation stage")
    known = p.parse_known_args(argv)[0]
    if known.compare:  # printed as format_table's text (16 columns), not the other modes' rich table
        from benchmarks.common import write_json

        p.add_argument("--threads", type=int, default=1)
        p.add_argument("--json", default=None, help="write the rows (and the environment) to this JSON file")
        a = p.parse_args(argv)
        torch.set_num_threads(a.threads)
        problems = load_problems(families=a.families, indices=a.indices)
        rows = compare_rows(problems, a.subset, a.iterations, a.step, a.recheck, a.ompl_time)
        text = _compare_text(rows, a, len(problems))
        print(text)
        if a.out:
            with open(a.out, "w") as f:
                f.write(text)
        if a.json:
            write_json(a.json, rows)
        return 0
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


def _compare_text(rows, a, n: int) -> str:
    """The ``--compare`` table as text, under a header naming the run (command, machine, load, versions)."""
    import os
    import platform
    import sys
    import time
    from importlib import metadata

    from benchmarks import peers_vamp

    version = metadata.version("ompl") if _ompl_modules() else "not importable"
    machine = platform.processor() or platform.machine()
    found = "found" if peers_vamp.available() else "NOT found"
    head = (f"python -m benchmarks.bench_motion_problems {' '.join(sys.argv[1:])}\n"
            f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; {machine}, {os.cpu_count()} cores, "
            f"load {os.getloadavg()[0]:.1f} at the end (a shared machine: compare the rows of this one "
            f"run); torch threads {torch.get_num_threads()}. {n} problems; diffkin motion.plan: "
            f"{a.iterations} iterations, step {a.step}, VAMP's spherized Panda, Franka limits; VAMP 0.6.4 "
            f"(benchmarks/install_vamp.sh, {found}); OMPL {version}.\n"
            "Columns: ms = per problem (diffkin one call: the call / problems; VAMP: planning + "
            "simplification, its own clock; one at a time and OMPL: wall); search_ms = RRT-Connect alone "
            "(diffkin: EdgeChecker, start and goal checks and RRT-Connect, no shortcuts; VAMP: planning, no "
            "simplification); search_vs_vamp = ratio of the medians on the "
            "same problems; search_prepared_ms, prepared_vs_vamp = the same with the scene prepared before "
            "the clock starts (diffkin: the edge checker and its C constants; VAMP's clock also starts after "
            "its environment is built); search_c_ms, c_vs_vamp = that call's own time in C (a monotonic "
            "clock read in its thread; its start and goal decisions and RRT-Connect, no Python), as VAMP's "
            "clock times its planner; proof_ms, proof_vs_vamp = the found path's edges decided alone "
            "in C (the least of 3 calls' wall time less an empty call's; what a search returning that path "
            "pays at least); crossing = VAMP's solved paths that cross its own sphere model somewhere along "
            "them (samples at most 1 mm of travel apart, diffkin's C decisions at margin 0, the exact "
            "scene); duration_s = trajectory seconds under the "
            "Franka limits (VAMP: its "
            "path timed by toppra, at rest at every waypoint; spline_s: toppra on the cubic spline through "
            "its waypoints, not collision-checked); dur_vs_vamp_* = median of diffkin's duration / VAMP's on "
            "problems both solved; length_rad = joint-space path length; jerk_max = max |dq''|/dt sampled "
            "every 1 ms, rad/s^3 (toppra's q'' is piecewise constant); recheck_min_mm = coal/Pinocchio "
            "re-check of diffkin's successes.")
    import textwrap

    head = "\n".join("# " + line for para in head.split("\n") for line in textwrap.wrap(para, 108)) + "\n\n"
    return head + format_table(rows)


if __name__ == "__main__":
    raise SystemExit(main())
