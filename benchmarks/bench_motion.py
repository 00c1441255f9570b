"""Motion generation: ``trajectories.time_optimal`` beside toppra, and ``motion.plan`` on the MotionBenchMaker
Panda problems, one problem per call.

    python -m benchmarks.bench_motion [--part timing|mbm|all] [--paths 64] [--per-family 10] [--threads 1]

* ``timing``: ``--paths`` random 7-joint paths of 6 waypoints (toppra's spline, uneven knots), timed by
  ``time_optimal`` in one batched call and by toppra (TOPP-RA, PyPI) one path at a time on the same grid,
  in the same run: wall times and the duration ratio (diffkin / toppra: median, max).
* ``mbm``: the first ``--per-family`` problems of every family of the 700 (``benchmarks.motion_problems``,
  VAMP's files unchanged), each planned by ``motion.plan`` with its own scene (``Scene.to_world``; its
  allowed-collision matrix applied), VAMP's spherized Panda (``--model``), Franka's velocity, acceleration
  and jerk limits. Per family: valid problems (start and goal clear), successes, median and 90th-percentile
  planning time per problem, median trajectory duration. One problem per call (the one-at-a-time latency);
  all 700 in batched calls, one scene per problem: ``benchmarks.bench_motion_problems --plan``.

Timings on a shared machine are contended: compare the columns of one run, not runs.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
import torch

from benchmarks.common import cli
from benchmarks.motion_problems import FRANKA_A, FRANKA_J, FRANKA_V  # the Franka limits cuRobo plans with
from diffkin import motion
from diffkin.trajectories import time_optimal

__all__ = ["run", "main"]



def timing(paths: int = 64, seed: int = 0) -> list[dict]:
    import toppra as ta
    import toppra.algorithm as talgo
    import toppra.constraint as tcon

    ta.setup_logging("WARNING")
    rng = np.random.default_rng(seed)
    y = rng.uniform(-1.5, 1.5, (paths, 6, 7))
    knots = np.cumsum(rng.uniform(0.5, 1.5, (paths, 6)), 1)
    v, a = np.array(FRANKA_V), np.array(FRANKA_A)
    t0 = time.perf_counter()
    res = time_optimal(torch.tensor(y), torch.tensor(v), torch.tensor(a), knots=torch.tensor(knots))
    t_dk = time.perf_counter() - t0
    grid = res._grid.numpy() * (knots[:, -1:] - knots[:, :1]) + knots[:, :1]
    grid[:, 0], grid[:, -1] = knots[:, 0], knots[:, -1]
    ref = []
    t0 = time.perf_counter()
    for b in range(paths):
        p = ta.SplineInterpolator(knots[b], y[b])
        cons = [tcon.JointVelocityConstraint(np.stack([-v, v], 1)),
                tcon.JointAccelerationConstraint(np.stack([-a, a], 1))]
        inst = talgo.TOPPRA(cons, p, gridpoints=grid[b], parametrizer="ParametrizeConstAccel")
        ref.append(inst.compute_trajectory(0, 0).duration)
    t_ta = time.perf_counter() - t0
    ratio = res.duration.numpy() / np.array(ref)
    return [{"part": "timing", "method": "diffkin time_optimal (one batched call)", "paths": paths,
             "seconds": t_dk, "ratio_median": float(np.median(ratio)), "ratio_max": float(ratio.max())},
            {"part": "timing", "method": "toppra (one path at a time)", "paths": paths, "seconds": t_ta}]


def mbm(per_family: int = 10, model: str = "spherized", seed: int = 0) -> list[dict]:
    from benchmarks.bench_motion_problems import robot_model
    from benchmarks.motion_problems import load_problems

    rc = robot_model(model).requires_grad_(False)
    chain = rc.chain
    problems = [p for p in load_problems() if p.index <= per_family]
    rules: dict = {}
    out: dict[str, dict] = {}
    for p in problems:
        m = rules.get(p.scene.allowed)
        if m is None:
            m = rules[p.scene.allowed] = rc.allow_collisions(p.scene.allowed)
        world = p.scene.to_world(dtype=torch.float64)
        qs = torch.tensor([p.start], dtype=torch.float64)
        qg = torch.tensor([p.goal], dtype=torch.float64)
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = motion.plan(chain, qs, qg, collision=m, world=world, velocity_limit=FRANKA_V,
                              acceleration_limit=FRANKA_A, jerk_limit=FRANKA_J, seed=seed)
        dt = time.perf_counter() - t0
        c = out.setdefault(p.family, {"problems": 0, "valid": 0, "success": 0, "times": [], "durations": []})
        c["problems"] += 1
        invalid = "start in collision" in res.reason[0] or "goal in collision" in res.reason[0]
        c["valid"] += int(not invalid)
        c["success"] += int(res.success[0])
        c["times"].append(dt)
        if bool(res.success[0]):
            c["durations"].append(float(res.duration[0]))
    rows = []
    for family, c in sorted(out.items()):
        t = 1e3 * np.array(c["times"])
        dur = float(np.median(c["durations"])) if c["durations"] else float("nan")
        rows.append({"part": "mbm", "family": family, "model": model, "problems": c["problems"],
                     "valid": c["valid"], "success": c["success"], "plan_ms_median": float(np.median(t)),
                     "plan_ms_p90": float(np.quantile(t, 0.9)), "duration_s_median": dur})
    return rows


def run(args=None, *, part: str = "all", paths: int = 64, per_family: int = 10,
        model: str = "spherized") -> list[dict]:
    """The rows of the parts asked for (module docstring); ``main`` sets the torch threads."""
    if args is not None:
        part, paths, per_family, model = args.part, args.paths, args.per_family, args.model
    rows = []
    if part in ("timing", "all"):
        rows += timing(paths)
    if part in ("mbm", "all"):
        rows += mbm(per_family, model)
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("timing", "mbm", "all"), default="all")
    parser.add_argument("--paths", type=int, default=64)
    parser.add_argument("--per-family", type=int, default=10)
    parser.add_argument("--model", choices=("capsules", "spherized"), default="spherized")
    return cli(parser, run, "motion: time_optimal beside toppra; plan on MotionBenchMaker", argv)


if __name__ == "__main__":
    raise SystemExit(main())
