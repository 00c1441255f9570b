"""``diffkin plan``: collision-free, limit-respecting timed motions from start to goal joints through a scene
(a world file or a MoveIt PlanningScene YAML), batched, by :func:`diffkin.motion.plan`. Writes ``t``, ``q``,
``qd``, ``qdd`` as ``.npz`` (all problems on one time grid) or ``.csv`` (one row per problem and sample, up to
the problem's end), and optionally a plot of q, q̇, q̈ against their limits."""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from ..errors import DiffkinError
from ..validation import check_count, check_number

__all__ = ["PlanSummary", "plan_rows"]

DESCRIPTION = (
    "Plan collision-free motions from --start to --goal joint vectors (or --goal-pose poses) through a\n"
    "scene, batched: goal and start checks, RRT-Connect over all problems at once, shortcutting, a cubic\n"
    "spline checked continuously, then time-optimal timing under the velocity, acceleration and jerk\n"
    "limits (diffkin.motion.plan; docs/motion.md). The robot is a URDF or MJCF arm (its collision geometry\n"
    "is the file's own; --srdf names the pairs not checked); the scene a world file (spheres, capsules,\n"
    "boxes, cylinders, ...; see docs/collision.md) or a MoveIt PlanningScene YAML (its allowed-collision\n"
    "matrix: robot link pairs not checked). One --start / --goal vector, or files of B rows (.npy,\n"
    ".csv, .txt, .npz key q) for B problems (a single row of either is used for every problem); pose\n"
    "goals: --goal-pose x y z qw qx qy qz or --goal-pose-file (the layouts `diffkin ik --input` reads),\n"
    "solved by collision-free IK first. Problems are planned --chunk-size at a time, chunk [a, b) seeded\n"
    "from (--seed, a): results do not depend on how the chunks are split over processes.\n"
    "Prints per problem whether it succeeded, its duration or why not.\n"
    "Output by suffix: .npz holds t (B, S), q, qd, qdd (B, S, nq) sampled every --dt (rows past their\n"
    "duration hold the goal at rest; failed rows hold the start), success, duration, reason, q_goal and\n"
    "joint_names; .csv one row per problem and sample up to its end: problem, success, t, q_*, qd_*,\n"
    "qdd_*. `diffkin view --trajectory plan.npz --problem I --play` plays problem I at its rate.\n"
    "Under torchrun (as fk / ik) each process plans its contiguous shard of the chunks and writes its\n"
    "part; rank 0 writes the manifest <stem>.shards.json or, with --merge, the one file; every part\n"
    "shares one time grid, so the result equals one process's row for row.")
EXAMPLES = ("diffkin plan --robot fr3 --srdf fr3.srdf --scene table.yaml --start 0.8 0.3 0 -1.8 0 2.1 0.785 "
            "--goal -0.8 0.3 0 -1.8 0 2.1 0.785 --acceleration-limit 5 --output plan.npz --plot plan.png\n"
            "  diffkin plan --urdf arm.urdf --end-link tool0 --scene scene.yaml --start-file q0.npy "
            "--goal-file q1.npy --acceleration-limit 10 --jerk-limit 500 --output plans.csv\n"
            "  diffkin plan --robot fr3 --scene table.yaml --start-file q0.npy "
            "--goal-pose 0.5 0.2 0.4 0 1 0 0 --acceleration-limit 5 --output poses.npz\n"
            "  torchrun --nproc-per-node 4 -m diffkin.cli plan --robot fr3 --scene table.yaml --start-file "
            "q0.npy --goal-file q1.npy --acceleration-limit 5 --chunk-size 16 --output plans.npz --merge")

#: width of the ``reason`` strings written (one width in every part, so that parts merge unchanged)
REASON_WIDTH = 128


def _number(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not np.isfinite(x):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text}")
    return x


def _positive(text: str) -> float:
    x = _number(text)
    if x <= 0:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text}")
    return x


def add_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("robot (a URDF or MJCF arm: its collision geometry is the file's own)")
    g.add_argument("--robot", help="a built-in URDF / MuJoCo robot's name (see `diffkin models`)")
    g.add_argument("--urdf", help="URDF file (with --end-link)")
    g.add_argument("--mjcf", help="MuJoCo MJCF file (with --end-link: a body or site)")
    g.add_argument("--end-link", dest="end_link", help="end-effector link (with --robot: instead of its "
                                                       "default end links)")
    g.add_argument("--srdf", metavar="FILE", help="SRDF whose <disable_collisions> pairs are not checked "
                                                  "(URDF robots)")
    g.add_argument("--dtype", default="float64", choices=["float32", "float64"], help="compute dtype")
    g.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="where to compute")
    s = p.add_argument_group("problems")
    s.add_argument("--scene", metavar="FILE", help="obstacles: a world file (.yaml/.json) or a MoveIt "
                                                   "PlanningScene YAML (default: none, self-collision only)")
    s.add_argument("--start", type=_number, nargs="+", metavar="Q", help="start joint vector")
    s.add_argument("--goal", type=_number, nargs="+", metavar="Q", help="goal joint vector")
    s.add_argument("--start-file", dest="start_file", metavar="FILE", help="start joint vectors (B, nq)")
    s.add_argument("--goal-file", dest="goal_file", metavar="FILE", help="goal joint vectors (B, nq)")
    s.add_argument("--goal-pose", dest="goal_pose", type=_number, nargs="+", metavar="X",
                   help="goal pose of the end link: x y z qw qx qy qz (7 numbers per end link)")
    s.add_argument("--goal-pose-file", dest="goal_pose_file", metavar="FILE",
                   help="goal poses (B): .npy (B, 4, 4) or (B, 7) x y z qw qx qy qz, .npz key T or "
                        "position + quaternion, .csv with x,y,z,qw,qx,qy,qz columns (diffkin fk's output)")
    o = p.add_argument_group("planning")
    o.add_argument("--velocity-limit", dest="velocity_limit", type=_positive, nargs="+", metavar="V",
                   help="rad/s: one for all joints or one per joint (default: the URDF's <limit velocity=>)")
    o.add_argument("--acceleration-limit", dest="acceleration_limit", type=_positive, nargs="+", metavar="A",
                   required=True, help="rad/s²: one for all joints or one per joint")
    o.add_argument("--jerk-limit", dest="jerk_limit", type=_positive, nargs="+", metavar="J",
                   help="rad/s³: one or one per joint (default: 100 × the acceleration limit per second)")
    o.add_argument("--dt", type=_positive, default=0.01, help="sampling period of the output [s]")
    o.add_argument("--margin", type=_number, default=0.0, metavar="M",
                   help="least clearance of the continuous motion [m]")
    o.add_argument("--resolution", type=_positive, default=0.005, metavar="M",
                   help="slack of each collision check [m]: samples clear of margin + it, 2x it apart")
    o.add_argument("--max-iterations", dest="max_iterations", type=int, default=2000, metavar="N",
                   help="RRT-Connect iterations")
    o.add_argument("--seed", type=int, default=0, help="randomness of the search and the shortcuts (chunk "
                                                          "[a, b) seeded from (seed, a))")
    o.add_argument("--chunk-size", dest="chunk_size", type=int, default=64, metavar="N",
                   help="problems per motion.plan call (the unit of seeding and of sharding)")
    p.add_argument("--output", required=True, help="the motions: .npz or .csv (see above)")
    p.add_argument("--merge", action="store_true",
                   help="under torchrun: concatenate the ranks' parts into --output (default: the parts and "
                        "a manifest <stem>.shards.json)")
    p.add_argument("--plot", help="PNG/PDF/SVG of q, q̇, q̈ of the first successful problem with the limits")


def _robot(args):
    """``(chain, collision source path, 'urdf' | 'mjcf')`` of the robot options."""
    from .. import models

    given = [f for f in ("robot", "urdf", "mjcf") if getattr(args, f)]
    if len(given) != 1:
        raise DiffkinError("give exactly one of --robot NAME, --urdf FILE or --mjcf FILE (with --end-link)"
                           + (f"; got --{' and --'.join(given)}" if given else ""))
    if args.device == "cuda" and not torch.cuda.is_available():
        raise DiffkinError("--device cuda: CUDA is not available in this torch build / machine")
    dtype = getattr(torch, args.dtype)
    if args.robot:
        info = models.info(args.robot)
        if info.format not in ("urdf", "mjcf"):
            raise DiffkinError(f"--robot {args.robot}: a {info.format.upper()} model has no collision "
                               "geometry; plan needs a URDF or MuJoCo robot")
        path, kind = info.path, info.format
        chain = models.load(args.robot, dtype=dtype, device=args.device, end_link=args.end_link)
    else:
        kind = "urdf" if args.urdf else "mjcf"
        path = args.urdf or args.mjcf
        if not args.end_link:
            raise DiffkinError(f"--{kind} needs --end-link NAME (the end-effector link)")
        reader = models.from_urdf if kind == "urdf" else models.from_mjcf
        chain = reader(path, args.end_link, dtype=dtype, device=args.device)
    return chain.requires_grad_(False), path, kind


def _collision(chain, path, kind: str, srdf):
    from ..collision import RobotCollision

    if srdf and kind != "urdf":
        raise DiffkinError("--srdf applies to URDF robots (an MJCF file has its own <contact> rules)")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = (RobotCollision.from_urdf(path, chain, srdf=srdf) if kind == "urdf"
              else RobotCollision.from_mjcf(path, chain))
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    if not rc.geoms:
        raise DiffkinError(f"{path}: no collision geometry found for the chain's links")
    return rc.requires_grad_(False)


def _scene(path, rc, chain):
    """``(robot collision, world)`` of ``--scene``: a world file, or a MoveIt PlanningScene YAML whose
    allowed-collision matrix also becomes the robot's pair rules (:meth:`RobotCollision.allow_collisions`)."""
    from ..collision import read_scene, read_world
    from ..collision.moveit import is_moveit_scene

    if path is None:
        return rc, None
    world = read_world(path, dtype=chain.dtype, device=chain.device)  # names the file in its errors
    if Path(path).suffix.lower() in (".yaml", ".yml"):
        import yaml

        if is_moveit_scene(yaml.safe_load(Path(path).read_text(encoding="utf-8-sig"))):
            allowed = read_scene(path).allowed
            if allowed:
                rc = rc.allow_collisions(allowed)
    return rc, world


def _joints(values, path, flag: str, chain) -> torch.Tensor:
    """``(B, nq)`` from ``--start`` / ``--goal`` or their ``-file`` option (exactly one of them)."""
    from ..io.data import read_array

    if (values is None) == (path is None):
        raise DiffkinError(f"give --{flag} Q1 ... Q{chain.nq} or --{flag}-file FILE (exactly one)")
    arr = np.asarray(values, np.float64) if path is None else read_array(path, key="q")
    where = f"--{flag}" if path is None else f"--{flag}-file {path}"
    if arr.ndim == 1:
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] != chain.nq:
        raise DiffkinError(f"{where}: expected {chain.nq} joint values per row ('{chain.name}': "
                           f"{', '.join(chain.joint_names)}), got shape {tuple(arr.shape)}")
    if not np.isfinite(arr).all():
        raise DiffkinError(f"{where}: a value is not finite")
    return torch.as_tensor(arr, dtype=chain.dtype, device=chain.device)


def _limit(values, flag: str, nq: int):
    if values is None or len(values) == 1:
        return None if values is None else values[0]
    if len(values) != nq:
        raise DiffkinError(f"--{flag}: expected one value or {nq} (one per joint), got {len(values)}")
    return torch.tensor(values, dtype=torch.float64)


def plan_figure(result, chain, velocity_limit, acceleration_limit, row: int = 0, title: str | None = None):
    """q, q̇, q̈ of problem ``row`` of a :class:`~diffkin.motion.MotionResult` against time, one colour per
    joint, its limits dashed (joint limits, ``velocity_limit`` / ``acceleration_limit``: numbers or
    ``(nq,)``); a matplotlib Figure for file output (no pyplot)."""
    from ..errors import require

    Figure = require("matplotlib.figure", "plot", "--plot").Figure
    nq = chain.nq
    T = int(round(float(result.duration[row]) / float(result.t[row, 1] - result.t[row, 0]))) + 2 \
        if result.t.shape[1] > 1 else 1
    t = result.t[row, :T].cpu().double().numpy()
    lo_hi = chain.q_limits.cpu().double().numpy()
    bounds = [(lo_hi[:, 0], lo_hi[:, 1])]
    for lim in (velocity_limit, acceleration_limit):
        v = np.broadcast_to(np.asarray(torch.as_tensor(lim).cpu().double()), (nq,))
        bounds.append((-v, v))
    fig = Figure(figsize=(7, 7.5))
    axs = fig.subplots(3, 1, sharex=True)
    for ax, key, label, (lo, hi) in zip(axs, ("q", "qd", "qdd"), ("q [rad]", "q̇ [rad/s]", "q̈ [rad/s²]"),
                                        bounds):
        x = getattr(result, key)[row, :T].cpu().double().numpy()
        for j in range(nq):
            line, = ax.plot(t, x[:, j], label=chain.joint_names[j])
            ax.hlines([lo[j], hi[j]], t[0], t[-1], colors=line.get_color(), linestyles="dashed", lw=0.8)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axs[0].legend(fontsize=7, ncols=min(nq, 4), loc="upper left", bbox_to_anchor=(0.0, 1.38))
    axs[-1].set_xlabel("time t [s]")
    fig.suptitle(title or f"planned motion {row} ({float(result.duration[row]):.3f} s; dashed: limits)",
                 y=0.995)
    fig.tight_layout()
    return fig


def _goals(args, chain) -> torch.Tensor:
    """``(B, nq)`` joint goals or ``(B, 4, 4)`` / ``(B, K, 4, 4)`` pose goals: exactly one of ``--goal``,
    ``--goal-file``, ``--goal-pose``, ``--goal-pose-file``."""
    from ..io.data import open_pose_source

    given = [f for f in ("goal", "goal_file", "goal_pose", "goal_pose_file") if getattr(args, f) is not None]
    if len(given) != 1:
        raise DiffkinError("give exactly one of --goal, --goal-file, --goal-pose, --goal-pose-file"
                           + (f"; got --{' and --'.join(g.replace('_', '-') for g in given)}" if given
                              else ""))
    if args.goal_pose is None and args.goal_pose_file is None:
        return _joints(args.goal, args.goal_file, "goal", chain)
    K = chain.n_ends
    if args.goal_pose is not None:
        if len(args.goal_pose) != 7 * K:
            raise DiffkinError(f"--goal-pose: expected x y z qw qx qy qz per end link ({7 * K} numbers for "
                               f"'{chain.name}'), got {len(args.goal_pose)}")
        rows = np.asarray(args.goal_pose, np.float64).reshape((1, 7) if chain.single_end else (1, K, 7))
        src = open_pose_source(rows, K, chain.single_end)
    else:
        src = open_pose_source(args.goal_pose_file, K, chain.single_end)
    if src.position_only:
        raise DiffkinError("--goal-pose-file: positions only; plan needs whole poses (x y z qw qx qy qz)")
    T = np.concatenate(list(src.chunks(1 << 20)))
    return torch.as_tensor(T, dtype=chain.dtype, device=chain.device)


@dataclass
class PlanSummary:
    """What ``diffkin plan`` reports of its problems ``[start, stop)`` (one rank's, or all of them combined):
    per problem ``(index, success, duration, waypoints, interpolation, reason)``; ``figure``: the first
    successful problem's ``(index, t, q, qd, qdd, duration)`` for ``--plot`` (None if none); the seconds of
    the planning (the slowest rank's); the file written."""

    problems: list
    figure: tuple | None
    seconds: float
    output: Path | None


def _combine(results: list[PlanSummary], written, merge_seconds: float) -> PlanSummary:
    """Every rank's summary in rank order as one (the ``combine`` of
    :func:`diffkin.io.distributed.run_sharded`)."""
    return PlanSummary([p for r in results for p in r.problems],
                       next((r.figure for r in results if r.figure is not None), None),
                       max(r.seconds for r in results) + merge_seconds, written)


def plan_rows(chain, problems, output, *, chunk_size: int, start: int = 0, stop: int | None = None,
              progress=None, seed: int = 0, dt: float = 0.01, joint_names=(), **options) -> PlanSummary:
    """Plan the problems ``[start, stop)`` of ``problems = (q_start (B, nq), goal (B, nq) | (B, [K,] 4, 4))``
    ``chunk_size`` at a time (chunk ``[a, b)`` by :func:`diffkin.motion.plan` with the seed
    :func:`~diffkin.io.streaming.seed_of_chunk` ``(seed, a)``) and write them to ``output`` (.npz or .csv;
    None: nothing). The samples' time grid is the longest motion's of every rank
    (:func:`diffkin.io.distributed.agree`), so the parts of a sharded run concatenate to the single run's
    file.
    The ``stream`` of :func:`~diffkin.io.distributed.run_sharded` (``collective``: every rank calls it)."""
    from .. import motion
    from ..io import distributed
    from ..io.streaming import seed_of_chunk

    q0, goal = problems
    stop = q0.shape[0] if stop is None else stop
    done, failure = [], None
    t0 = time.perf_counter()
    try:
        for a in range(start, stop, chunk_size):
            b = min(a + chunk_size, stop)
            done.append((a, motion.plan(chain, q0[a:b], goal[a:b], seed=seed_of_chunk(seed, a), dt=dt,
                                        **options)))
            if progress is not None:
                progress(b - start, stop - start)
    except Exception as exc:  # every rank must reach agree() below, or the others wait for it forever
        failure = exc
    seconds = time.perf_counter() - t0
    S = max(distributed.agree(max((r.t.shape[1] for _, r in done), default=1), failure))
    t = torch.arange(S, dtype=torch.float64, device=q0.device) * dt
    host = lambda x: x.detach().cpu().double().numpy()  # noqa: E731
    summary, figure = [], None
    writer = None
    try:
        for a, res in done:
            tr = res.state(t)  # on the common grid (rows past their end hold the goal at rest)
            ok, duration, n_way = res.success.cpu().numpy(), host(res.duration), res.n_waypoints.tolist()
            B = ok.shape[0]
            summary += [(a + i, bool(ok[i]), float(duration[i]), n_way[i], res.interpolation[i],
                         res.reason[i]) for i in range(B)]  # the report's lines (one transfer per chunk)
            cols = {"t": np.broadcast_to(host(t.to(chain.dtype)), (B, S)), "q": host(tr.position),
                    "qd": host(tr.velocity), "qdd": host(tr.acceleration), "success": ok,
                    "duration": duration, "reason": np.array(res.reason, dtype=f"<U{REASON_WIDTH}"),
                    "q_goal": host(res.q_goal)}
            if figure is None and ok.any():
                i = int(ok.nonzero()[0][0])
                figure = (a + i, *(cols[k][i] for k in ("t", "q", "qd", "qdd")), float(duration[i]))
            if output is None:
                continue
            if writer is None:
                writer = _writer(output, stop - start, S, chain.nq, joint_names)
            if Path(output).suffix == ".csv":  # one row per problem and sample up to its end (at rest there)
                n = torch.clamp(torch.ceil(res.duration / dt - 1e-9).long() + 1, 1, S).cpu()
                keep = (torch.arange(S)[None] < n[:, None]).numpy()
                grid = np.broadcast_to(np.arange(a, a + B)[:, None], (B, S))[keep], \
                    np.broadcast_to(ok[:, None], (B, S))[keep]
                writer.write({"problem": grid[0], "success": grid[1].astype(np.float64),
                              "t": cols["t"][keep], "q": cols["q"][keep], "qd": cols["qd"][keep],
                              "qdd": cols["qdd"][keep]})
            else:
                writer.write(cols)
        written = writer.close() if writer is not None else None
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    return PlanSummary(summary, figure, seconds, written)


def _writer(output, count: int, S: int, nq: int, joint_names):
    """The :class:`~diffkin.io.data.Writer` of ``count`` problems on ``S`` samples (the format above)."""
    from ..io.data import open_writer

    if Path(output).suffix == ".csv":
        names = lambda k: [f"{k}_{j}" for j in range(nq)]  # noqa: E731
        spec = {"problem": ((), np.float64, ["problem"]), "success": ((), np.float64, ["success"]),
                "t": ((), np.float64, ["t"]), "q": ((nq,), np.float64, names("q")),
                "qd": ((nq,), np.float64, names("qd")), "qdd": ((nq,), np.float64, names("qdd"))}
        return open_writer(output, count, spec)
    f8 = np.float64
    spec = {"t": ((S,), f8, []), "q": ((S, nq), f8, []), "qd": ((S, nq), f8, []), "qdd": ((S, nq), f8, []),
            "success": ((), np.bool_, []), "duration": ((), f8, []), "reason": ((), f"<U{REASON_WIDTH}", []),
            "q_goal": ((nq,), f8, [])}
    return open_writer(output, count, spec, constants={"joint_names": np.array(joint_names, dtype=str)})


def cmd_plan(args) -> int:
    from ..io import distributed
    from ..io.data import check_output_path

    out = check_output_path(args.output, (".npz", ".csv"))
    if args.plot:
        check_output_path(args.plot, (".png", ".pdf", ".svg"))
    check_count(args.max_iterations, "--max-iterations", minimum=0)
    check_number(args.margin, "--margin", positive=False, unit=" [m]")
    check_count(args.chunk_size, "--chunk-size")
    check_count(args.seed, "--seed", minimum=0)
    info = distributed.init(args.device)  # first: under torchrun --device cuda is this rank's GPU
    chain, path, kind = _robot(args)
    q0 = _joints(args.start, args.start_file, "start", chain)
    q1 = _goals(args, chain)
    if q0.shape[0] != q1.shape[0] and 1 not in (q0.shape[0], q1.shape[0]):
        raise DiffkinError(f"--start gives {q0.shape[0]} rows and the goals {q1.shape[0]}: expected as many, "
                           "or one of them a single row")
    B = max(q0.shape[0], q1.shape[0])
    q0, q1 = q0.expand(B, -1).contiguous(), q1.expand(B, *q1.shape[1:]).contiguous()
    limits = {f: _limit(getattr(args, f), f.replace("_", "-"), chain.nq)
              for f in ("velocity_limit", "acceleration_limit", "jerk_limit")}
    rc, world = _scene(args.scene, _collision(chain, path, kind, args.srdf), chain)
    res = distributed.run_sharded(
        plan_rows, chain, (q0, q1), out, chunk_size=args.chunk_size, merge=args.merge,
        command=" ".join(sys.argv), device=args.device, rows=B, combine=_combine, collective=True,
        constants=("joint_names",), log=lambda line: print(line, file=sys.stderr),
        seed=args.seed, dt=args.dt, joint_names=chain.joint_names, collision=rc, world=world,
        margin=args.margin, resolution=args.resolution, max_iterations=args.max_iterations, **limits)
    if res is None:  # a rank other than 0 of a sharded run: rank 0 reports
        return 0
    for b, ok, duration, n_way, how, why in res.problems:
        print(f"problem {b}: success, duration {duration:.3f} s, {n_way} waypoints ({how})" if ok
              else f"problem {b}: FAILED: {why}")
    n_ok = sum(p[1] for p in res.problems)
    where = f" ({info.world} processes)" if info.sharded else ""
    print(f"planned {n_ok} of {B} problem(s) on '{chain.name}' in {res.seconds:.2f} s{where}")
    print(f"wrote {res.output}")
    if args.plot:
        _plot(args, chain, res.figure, limits)
    return 0


def _plot(args, chain, figure, limits) -> None:
    """``--plot``: the first successful problem (else nothing to draw: a note)."""
    if figure is None:
        print("no problem succeeded: no plot", file=sys.stderr)
        return
    b, t, q, qd, qdd, duration = figure
    one = lambda x: torch.as_tensor(np.asarray(x))[None]  # noqa: E731
    res = SimpleNamespace(t=one(t), q=one(q), qd=one(qd), qdd=one(qdd), duration=torch.tensor([duration]))
    v = limits["velocity_limit"]
    if v is None:  # the URDF's, as plan read them
        v = chain.velocity_limits()
    fig = plan_figure(res, chain, v, limits["acceleration_limit"], 0,
                      title=f"planned motion {b} ({duration:.3f} s; dashed: limits)")
    Path(args.plot).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.plot, dpi=110)
    print(f"wrote {args.plot}")
