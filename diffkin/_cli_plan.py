"""``diffkin plan``: collision-free, limit-respecting timed motions from start to goal joints through a scene
(a world file or a MoveIt PlanningScene YAML), batched, by :func:`diffkin.motion.plan`. Writes ``t``, ``q``,
``qd``, ``qdd`` as ``.npz`` (all problems on one time grid) or ``.csv`` (one row per problem and sample, up to
the problem's end), and optionally a plot of q, q̇, q̈ against their limits."""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from .errors import DiffkinError

__all__: list[str] = []

DESCRIPTION = (
    "Plan collision-free motions from --start to --goal joint vectors through a scene, batched: goal\n"
    "and start checks, RRT-Connect over all problems at once, shortcutting, a cubic spline checked\n"
    "continuously, then time-optimal timing under the velocity, acceleration and jerk limits\n"
    "(diffkin.motion.plan; docs/motion.md). The robot is a URDF or MJCF arm (its collision geometry is\n"
    "the file's own; --srdf names the pairs not checked); the scene a world file (spheres, capsules,\n"
    "boxes, cylinders, ...; see docs/collision.md) or a MoveIt PlanningScene YAML (its allowed-collision\n"
    "matrix: robot link pairs not checked). One --start / --goal vector, or files of B rows (.npy,\n"
    ".csv, .txt, .npz key q) for B problems (a single row of either is used for every problem).\n"
    "Prints per problem whether it succeeded, its duration or why not.\n"
    "Output by suffix: .npz holds t (B, S), q, qd, qdd (B, S, nq) sampled every --dt (rows past their\n"
    "duration hold the goal at rest; failed rows hold the start), success, duration, reason, q_goal and\n"
    "joint_names; .csv one row per problem and sample up to its end: problem, success, t, q_*, qd_*,\n"
    "qdd_*. Not sharded over torchrun (one process plans the whole batch).")
EXAMPLES = ("diffkin plan --robot fr3 --srdf fr3.srdf --scene table.yaml --start 0.8 0.3 0 -1.8 0 2.1 0.785 "
            "--goal -0.8 0.3 0 -1.8 0 2.1 0.785 --acceleration-limit 5 --output plan.npz --plot plan.png\n"
            "  diffkin plan --urdf arm.urdf --end-link tool0 --scene scene.yaml --start-file q0.npy "
            "--goal-file q1.npy --acceleration-limit 10 --jerk-limit 500 --output plans.csv")


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
                   help="most travel of any geom point between two collision checks [m]")
    o.add_argument("--max-iterations", dest="max_iterations", type=int, default=2000, metavar="N",
                   help="RRT-Connect iterations")
    o.add_argument("--seed", type=int, default=0, help="randomness of the search and the shortcuts")
    p.add_argument("--output", required=True, help="the motions: .npz or .csv (see above)")
    p.add_argument("--plot", help="PNG/PDF/SVG of q, q̇, q̈ of the first successful problem with the limits")


def _robot(args):
    """``(chain, collision source path, 'urdf' | 'mjcf')`` of the robot options."""
    from . import models

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
    from .collision import RobotCollision

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
    from .collision import read_scene, read_world
    from .collision.moveit import is_moveit_scene

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
    from .data_io import read_array

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
    from .errors import require

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


def cmd_plan(args) -> int:
    from . import motion
    from .data_io import check_output_path, write_arrays

    out = check_output_path(args.output, (".npz", ".csv"))
    if args.plot:
        check_output_path(args.plot, (".png", ".pdf", ".svg"))
    if args.max_iterations < 0:
        raise DiffkinError(f"--max-iterations: expected an integer >= 0, got {args.max_iterations}")
    if args.margin < 0:
        raise DiffkinError(f"--margin: expected a distance >= 0 [m], got {args.margin}")
    chain, path, kind = _robot(args)
    q0 = _joints(args.start, args.start_file, "start", chain)
    q1 = _joints(args.goal, args.goal_file, "goal", chain)
    if q0.shape[0] != q1.shape[0] and 1 not in (q0.shape[0], q1.shape[0]):
        raise DiffkinError(f"--start gives {q0.shape[0]} rows and --goal {q1.shape[0]}: expected as many, or "
                           "one of them a single row")
    B = max(q0.shape[0], q1.shape[0])
    q0, q1 = q0.expand(B, -1).contiguous(), q1.expand(B, -1).contiguous()
    limits = {f: _limit(getattr(args, f), f.replace("_", "-"), chain.nq)
              for f in ("velocity_limit", "acceleration_limit", "jerk_limit")}
    rc, world = _scene(args.scene, _collision(chain, path, kind, args.srdf), chain)
    t0 = time.perf_counter()
    res = motion.plan(chain, q0, q1, collision=rc, world=world, margin=args.margin, dt=args.dt,
                      resolution=args.resolution, max_iterations=args.max_iterations, seed=args.seed,
                      **limits)
    seconds = time.perf_counter() - t0
    ok = res.success.cpu()
    for b in range(B):
        if ok[b]:
            print(f"problem {b}: success, duration {float(res.duration[b]):.3f} s, "
                  f"{int(res.n_waypoints[b])} waypoints ({res.interpolation[b]})")
        else:
            print(f"problem {b}: FAILED: {res.reason[b]}")
    print(f"planned {int(ok.sum())} of {B} problem(s) on '{chain.name}' in {seconds:.2f} s")
    host = lambda x: x.detach().cpu().double().numpy()  # noqa: E731
    if out.suffix == ".npz":
        out.parent.mkdir(parents=True, exist_ok=True)
        np.savez(out, t=host(res.t), q=host(res.q), qd=host(res.qd), qdd=host(res.qdd), success=ok.numpy(),
                 duration=host(res.duration), reason=np.array(res.reason, dtype=str), q_goal=host(res.q_goal),
                 joint_names=np.array(chain.joint_names, dtype=str))
    else:  # one row per problem and sample up to the first sample at or after its end (at rest at the goal)
        S = res.t.shape[1]
        n = torch.clamp(torch.ceil(res.duration / args.dt - 1e-9).long() + 1, 1, S).cpu()
        keep = (torch.arange(S)[None] < n[:, None]).numpy()
        write_arrays(out, {"problem": np.repeat(np.arange(B), S).reshape(B, S)[keep],
                           "success": np.repeat(ok.numpy(), S).reshape(B, S)[keep].astype(np.float64),
                           "t": host(res.t)[keep], "q": host(res.q)[keep], "qd": host(res.qd)[keep],
                           "qdd": host(res.qdd)[keep]})
    print(f"wrote {out}")
    if args.plot:
        row = int(ok.nonzero()[0, 0]) if ok.any() else 0
        v = limits["velocity_limit"]
        if v is None:  # the URDF's, as plan read them
            v = chain.velocity_limits()
        fig = plan_figure(res, chain, v, limits["acceleration_limit"], row)
        Path(args.plot).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(args.plot, dpi=110)
        print(f"wrote {args.plot}")
    return 0
