"""The ``diffkin`` command: models, batch FK / IK, calibration, trajectories, training, benchmarks, demo.

Every subcommand prints a short summary; errors in the input (unknown robot, bad file, wrong column
count) are reported as one line ``error: ...`` with exit status 2.

``train``, ``evaluate`` and ``demo`` call the functions of the repository's ``training`` package in this
process (the ``rl`` extra); ``bench`` calls ``benchmarks.run`` (a checkout's ``benchmarks/``, not installed
with the package). Only :func:`main` sets torch's thread count: ``--threads N``, else 1 for ``demo`` and
``evaluate``, the config's ``torch_threads`` for ``train``, and torch's own setting for the rest.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from .errors import DiffkinError

__all__ = ["main", "build_parser"]


def _console():
    from rich.console import Console

    return Console(highlight=False)


def _table(title: str, columns: list[str], rows: list[list]):
    from rich.markup import escape
    from rich.table import Table

    table = Table(title=escape(title))
    for c in columns:
        table.add_column(escape(c))  # "[mm]" etc. are units, not rich markup
    for r in rows:
        table.add_row(*[escape(str(v)) for v in r])
    return table


def _dtype(name: str) -> torch.dtype:
    return {"float32": torch.float32, "float64": torch.float64}[name]


def _load_chain(args):
    from . import models

    dtype, device = _dtype(args.dtype), args.device
    if device == "cuda" and not torch.cuda.is_available():
        raise DiffkinError("--device cuda was requested but no CUDA device is available")
    if getattr(args, "urdf", None):
        if not args.end_link:
            raise DiffkinError("--urdf needs --end-link NAME (the end-effector link)")
        return models.from_urdf(args.urdf, args.end_link, dtype=dtype, device=device)
    if not args.robot:
        raise DiffkinError("give --robot NAME (see `diffkin models`) or --urdf FILE --end-link LINK")
    return models.load(args.robot, dtype=dtype, device=device)


# ------------------------------------------------------------------------------------------ models
def cmd_models(args) -> int:
    from . import models

    con = _console()
    if args.action == "show":
        if not args.name:
            raise DiffkinError("usage: diffkin models show NAME")
        chain = models.load(args.name, dtype=torch.float64)
        rows = []
        for i, (a, al, d, th) in enumerate(chain.dh_table().tolist()):
            lo_hi = "-" if chain.q_limits is None else "[{:.4f}, {:.4f}]".format(*chain.q_limits[i].tolist())
            rows.append(
                [i + 1, chain.joint_types[i], f"{a:.6g}", f"{al:.6g}", f"{d:.6g}", f"{th:.6g}", lo_hi]
            )
        con.print(
            _table(
                f"{chain.name} ({chain.convention} DH)",
                ["joint", "type", "a [m]", "alpha [rad]", "d [m]", "theta [rad]", "limits"],
                rows,
            )
        )
        return 0
    rows = []
    for name in models.available():
        chain = models.load(name, dtype=torch.float64)
        rows.append([name, chain.n_joints, chain.joint_types, chain.convention, models.source(name)])
    con.print(_table("built-in robots", ["name", "DOF", "joints", "DH", "source"], rows))
    return 0


# ---------------------------------------------------------------------------------------------- fk
def cmd_fk(args) -> int:
    from .data_io import read_joints, write_arrays
    from .rotations import matrix_to_quaternion

    chain = _load_chain(args)
    if args.random:
        g = torch.Generator(device="cpu").manual_seed(args.seed)
        q = chain.random_configuration(args.random, generator=g)
    elif args.input:
        q = read_joints(args.input, chain.n_joints, dtype=chain.dtype, device=chain.device)
    else:
        raise DiffkinError("give --input FILE or --random N")
    t0 = time.perf_counter()
    T = chain.forward_kinematics(q)
    if T.is_cuda:
        torch.cuda.synchronize()
    dt = time.perf_counter() - t0
    T = T.detach()
    out = {
        "q": q.cpu().numpy(),
        "T": T.cpu().numpy(),
        "position": T[:, :3, 3].cpu().numpy(),
        "quaternion": matrix_to_quaternion(T[:, :3, :3]).cpu().numpy(),
    }
    if args.output:
        if Path(args.output).suffix == ".csv":
            out = {k: out[k] for k in ("q", "position", "quaternion")}
        write_arrays(args.output, out)
    _console().print(
        f"FK of {q.shape[0]} configurations of '{chain.name}' on {chain.device} in {dt * 1e3:.2f} ms "
        f"({q.shape[0] / max(dt, 1e-9):,.0f} configs/s)" + (f" -> {args.output}" if args.output else "")
    )
    return 0


# ---------------------------------------------------------------------------------------------- ik
def cmd_ik(args) -> int:
    from .data_io import read_poses, write_arrays
    from .ik import solve

    chain = _load_chain(args)
    position_only = args.position_only
    if args.random:
        g = torch.Generator(device="cpu").manual_seed(args.seed)
        T = chain.forward_kinematics(chain.random_configuration(args.random, generator=g)).detach()
    elif args.input:
        T, pos_only_file = read_poses(args.input, dtype=chain.dtype, device=chain.device)
        position_only = position_only or pos_only_file
    else:
        raise DiffkinError("give --input FILE or --random N")
    t0 = time.perf_counter()
    options = {} if args.seeds is None else {"num_seeds": args.seeds}
    res = solve(
        chain,
        T[..., :3, 3] if position_only else T,
        position_only=position_only,
        position_tolerance=args.position_tolerance,
        orientation_tolerance=args.orientation_tolerance,
        progress=args.progress,
        **options,
    )
    dt = time.perf_counter() - t0
    if args.output:
        write_arrays(
            args.output,
            {
                "q": res.q.detach().cpu().numpy(),
                "success": res.success.cpu().numpy(),
                "position_error": res.position_error.detach().cpu().numpy(),
                "orientation_error": res.orientation_error.detach().cpu().numpy(),
                "iterations": res.iterations.cpu().numpy(),
            },
        )
    n = T.shape[0]
    rate = res.success.double().mean().item() * 100
    _console().print(
        _table(
            f"IK on '{chain.name}' ({'position only' if position_only else 'full pose'})",
            ["targets", "success", "median pos. err [mm]", "median ori. err [mrad]", "time [s]", "solves/s"],
            [
                [
                    n,
                    f"{rate:.2f} %",
                    f"{res.position_error.median().item() * 1e3:.4f}",
                    f"{res.orientation_error.median().item() * 1e3:.4f}",
                    f"{dt:.3f}",
                    f"{n / dt:,.0f}",
                ]
            ],
        )
    )
    if args.output:
        _console().print(f"wrote {args.output}")
    return 0


# ------------------------------------------------------------------------------------- calibrate
def cmd_calibrate(args) -> int:
    import math
    import warnings

    from .calibration import calibrate_from_files
    from .errors import ModelError

    out = Path(args.output)
    if out.suffix not in (".yaml", ".yml", ".urdf"):
        raise ModelError(f"--output {out}: the calibrated robot is written as .yaml (DH) or .urdf (URDF)")
    if bool(args.robot) == bool(args.urdf):
        raise ModelError("give the nominal robot as --robot NAME|FILE.yaml or --urdf FILE --end-link LINK")
    noise = None if args.noise is None else (args.noise[0] * 1e-3, math.radians(args.noise[1]))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = calibrate_from_files(
            args.urdf or args.robot, args.data, end_link=args.end_link, method=args.method,
            progress=args.progress, out_dir=args.report_dir, error_model=args.error_model,
            base=args.base, tool=args.tool, measurement_noise=noise, cross_validation=args.cv,
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix == ".urdf":
        if not hasattr(res.chain, "to_urdf"):
            raise ModelError(f"--output {out}: a DH robot is written as .yaml (nominal from --robot)")
        res.chain.to_urdf(out)
    else:
        if not hasattr(res.chain, "to_yaml"):
            raise ModelError(f"--output {out}: a URDF robot is written as .urdf (nominal from --urdf)")
        out.write_text(res.chain.to_yaml())
    rows = [
        [r["name"], f"{r['nominal']:.6f}", f"{r['identified']:.6f}", f"{r['delta']:+.6f}"]
        for r in res.parameter_table()
    ]
    con = _console()
    con.print(
        _table(
            f"calibration of '{res.nominal_chain.name}' ({args.method})",
            ["parameter", "nominal", "identified", "delta"],
            rows,
        )
    )
    rows = [["position RMS [mm]", f"{res.residuals[0] * 1e3:.4f}", f"{res.residuals[-1] * 1e3:.4f}"]]
    if res.orientation_residuals is not None:
        rows.append(["orientation RMS [deg]", f"{math.degrees(res.orientation_residuals[0]):.5f}",
                     f"{math.degrees(res.orientation_residuals[-1]):.5f}"])
    cv = res.cross_validation
    if cv is not None:
        rows.append([f"held-out position RMS [mm] ({cv['folds']}-fold CV)", "",
                     f"{cv['position_rms'] * 1e3:.4f}"])
    con.print(_table(f"before / after ({res.error_model} model, "
                     f"{'converged' if res.converged else 'NOT converged'})",
                     ["", "before", "after"], rows))
    if res.noise_ratio is not None:
        con.print(f"noise check: fit residual / measurement noise = {res.noise_ratio:.2f} (about 1 expected)")
    for w in caught:
        con.print(f"[bold yellow]warning:[/] {w.message}")
    for note in res.notes:
        con.print(f"note: {note}")
    con.print(f"wrote {args.output}")
    if res.report.unidentifiable:
        con.print(
            "not identifiable from these poses (kept at nominal): " + ", ".join(res.report.unidentifiable)
        )
    return 0


# ------------------------------------------------------------------------------------ trajectory
def cmd_trajectory(args) -> int:
    from . import trajectories as tr
    from .data_io import read_array, write_arrays

    t = torch.linspace(0.0, args.duration, args.samples, dtype=torch.float64)
    if args.space == "joint":
        if args.points:
            pts = torch.as_tensor(read_array(args.points, key="points"), dtype=torch.float64)
            if pts.ndim != 2 or pts.shape[0] < 2:
                raise DiffkinError(
                    f"{args.points}: expected via points of shape (N >= 2, n), got {tuple(pts.shape)}"
                )
            times = torch.linspace(0.0, args.duration, pts.shape[0], dtype=torch.float64)
            traj = tr.cubic_spline(pts, times, t)
        else:
            if args.start is None or args.end is None:
                raise DiffkinError("give --points FILE, or --start and --end joint vectors")
            qi = torch.tensor(args.start, dtype=torch.float64)
            qf = torch.tensor(args.end, dtype=torch.float64)
            if qi.shape != qf.shape:
                raise DiffkinError(f"--start has {qi.numel()} values but --end has {qf.numel()}")
            fn = {"cubic": tr.cubic, "quintic": tr.quintic, "trapezoidal": tr.trapezoidal}[args.profile]
            traj = fn(qi, qf, torch.tensor(args.duration, dtype=torch.float64), t)
    else:
        if args.start is None or args.end is None or len(args.start) != 3 or len(args.end) != 3:
            raise DiffkinError("a cartesian trajectory needs --start X Y Z and --end X Y Z")
        traj = tr.cartesian_segment_trajectory(
            torch.tensor(args.start, dtype=torch.float64),
            torch.tensor(args.end, dtype=torch.float64),
            args.duration,
            t,
            profile=args.profile,
        )
    out = {
        "t": t.numpy(),
        "position": traj.position.detach().numpy(),
        "velocity": traj.velocity.detach().numpy(),
        "acceleration": traj.acceleration.detach().numpy(),
    }
    write_arrays(args.output, out)
    if args.plot:
        _plot_trajectory(out, args.plot)
    _console().print(
        f"{args.space} trajectory, {args.samples} samples over {args.duration} s -> {args.output}"
        + (f" (plot: {args.plot})" if args.plot else "")
    )
    return 0


def _plot_trajectory(out: dict, path: str) -> None:
    from matplotlib.figure import Figure  # file output: no pyplot, no backend switch

    fig = Figure(figsize=(7, 7))
    axs = fig.subplots(3, 1, sharex=True)
    for ax, key in zip(axs, ("position", "velocity", "acceleration")):
        ax.plot(out["t"], out[key])
        ax.set_ylabel(key)
        ax.grid(alpha=0.3)
    axs[-1].set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


# --------------------------------------------------------------------------- train / evaluate / bench
def _missing(command: str, exc: ImportError) -> DiffkinError:
    """The error for a subcommand whose application code (training/, benchmarks/) cannot be imported."""
    if command == "bench":
        if getattr(exc, "name", None) in ("benchmarks", "benchmarks.run"):
            return DiffkinError(
                "`diffkin bench` runs the benchmark suite of a diffkin checkout (benchmarks/ is not "
                "installed with the package): run `make bench` (or `python -m diffkin.cli bench ...`) from "
                "the root of a clone of the repository"
            )
        return DiffkinError(f"the benchmarks need {exc.name or exc}: `make bench` installs the bench extra")
    return DiffkinError(
        f"`diffkin {command}` needs the training code and its dependencies ({exc}): install the `rl` extra "
        "(`pip install -e '.[rl]'` in a clone of the diffkin repository) or run from the repository"
    )


def _config_threads(args) -> int:
    """The run config's ``torch_threads`` (what ``diffkin train`` runs on without ``--threads``)."""
    try:
        from training.config import load_config
    except ImportError as exc:
        raise _missing("train", exc) from exc
    try:
        return load_config(args.config).torch_threads
    except (TypeError, ValueError) as exc:
        raise DiffkinError(str(exc)) from exc


def cmd_train(args) -> int:
    try:
        from training.train import resolve_run, summary_json, train
    except ImportError as exc:
        raise _missing("train", exc) from exc
    try:
        cfg, out = resolve_run(
            args.config, seed=args.seed, total_timesteps=args.total_timesteps, out=args.out
        )
    except (TypeError, ValueError) as exc:
        raise DiffkinError(str(exc)) from exc
    res = train(cfg, out, progress_bar=not args.no_progress)
    print(summary_json(res))
    _console().print(f"wrote {out}")
    return 0


def cmd_evaluate(args) -> int:
    try:
        from training.evaluate import evaluate_and_save
    except ImportError as exc:
        raise _missing("evaluate", exc) from exc
    import json

    res = evaluate_and_save(args.run_dir, episodes=args.episodes)
    print(json.dumps(res, indent=2))
    return 0


def cmd_bench(args) -> int:
    try:
        from benchmarks.run import main as run_benchmarks
    except ImportError as exc:
        raise _missing("bench", exc) from exc
    argv = [args.which] + (["--quick"] if args.quick else []) + ["--device", args.device]
    if args.threads is not None:
        argv += ["--threads", str(args.threads)]
    return run_benchmarks(argv)


def cmd_demo(args) -> int:
    from .demo import run_demo

    return run_demo(quick=args.quick, out=args.out, skip_rl=args.skip_rl)


# ------------------------------------------------------------------------------------------ parser
def _robot_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", help="built-in robot name or a robot YAML file")
    p.add_argument("--urdf", help="URDF file (with --end-link)")
    p.add_argument("--end-link", dest="end_link", help="end-effector link of the URDF")
    p.add_argument("--input", help="input file (.npz, .csv, .npy)")
    p.add_argument(
        "--random", type=int, default=0, metavar="N", help="use N random samples instead of --input"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    p.add_argument("--output", help="output file (.npz, .csv, .npy)")


def _positive_int(text: str) -> int:
    n = int(text)
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return n


_THREADS_HELP = (
    "torch intra-op threads for this command (default: torch's own setting; `demo` and `evaluate` use 1, "
    "`train` the config's torch_threads; `bench` passes it on to the benchmarks, which default to 1)"
)

# Commands that run on a fixed thread count unless --threads is given (measured figures, small kernels).
_ONE_THREAD = ("demo", "evaluate")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="diffkin", description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=_positive_int, default=None, metavar="N", help=_THREADS_HELP)
    # Also accepted after the subcommand; SUPPRESS keeps the subparser from overwriting the global value.
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--threads", type=_positive_int, default=argparse.SUPPRESS, metavar="N",
                        help=_THREADS_HELP)
    sub = parser.add_subparsers(dest="command", required=True)

    def add(name: str, **kwargs) -> argparse.ArgumentParser:
        return sub.add_parser(name, parents=[common], **kwargs)

    p = add("models", help="list built-in robots, or show one's DH table")
    p.add_argument("action", nargs="?", choices=["list", "show"], default="list")
    p.add_argument("name", nargs="?")
    p.set_defaults(func=cmd_models)

    p = add("fk", help="batch forward kinematics on a file of joint vectors")
    _robot_args(p)
    p.set_defaults(func=cmd_fk)

    p = add("ik", help="batch inverse kinematics on a file of target poses")
    _robot_args(p)
    p.add_argument("--position-only", action="store_true")
    p.add_argument("--position-tolerance", type=float, default=1e-4, help="metres (default 0.1 mm)")
    p.add_argument("--orientation-tolerance", type=float, default=1e-3, help="radians (default 1 mrad)")
    p.add_argument("--seeds", type=int, default=None, help="random restarts per target")
    p.add_argument("--progress", action="store_true")
    p.set_defaults(func=cmd_ik)

    p = add("calibrate", help="identify a robot's geometry from measured poses (DH YAML or URDF)")
    p.add_argument("--robot", help="nominal robot: built-in name or robot YAML file (DH)")
    p.add_argument("--urdf", help="nominal robot as a URDF file (with --end-link)")
    p.add_argument("--end-link", dest="end_link", help="end-effector link of the URDF")
    p.add_argument("--data", required=True, help=".npz with q (N, n) and T (N, 4, 4) or position (N, 3)")
    p.add_argument("--method", default="least_squares", choices=["least_squares", "gradient"])
    p.add_argument("--error-model", dest="error_model", default="auto",
                   choices=["auto", "dh", "hayati", "general"])
    p.add_argument("--base", action="store_true", help="also estimate the base (tracker) frame")
    p.add_argument("--tool", action="store_true", help="also estimate the tool frame")
    p.add_argument("--noise", type=float, nargs=2, metavar=("MM", "DEG"),
                   help="measurement noise per coordinate (position mm, orientation deg): warn when the fit "
                        "residual is more than 2x what it explains")
    p.add_argument("--cv", type=int, default=5, help="k of the k-fold cross-validated held-out error, 0: off")
    p.add_argument("--output", required=True, help="calibrated robot: .yaml (DH) or .urdf (URDF input)")
    p.add_argument(
        "--report-dir", dest="report_dir", help="also write parameters.md, report.json, residuals.png"
    )
    p.add_argument("--progress", action="store_true")
    p.set_defaults(func=cmd_calibrate)

    p = add("trajectory", help="plan and export a joint or Cartesian trajectory")
    p.add_argument("space", choices=["joint", "cartesian"])
    p.add_argument("--profile", default="quintic", choices=["cubic", "quintic", "trapezoidal"])
    p.add_argument("--start", type=float, nargs="+")
    p.add_argument("--end", type=float, nargs="+")
    p.add_argument("--points", help="via points (N, n) file for a cubic spline (joint space)")
    p.add_argument("--duration", type=float, default=2.0)
    p.add_argument("--samples", type=int, default=201)
    p.add_argument("--output", required=True)
    p.add_argument("--plot", help="PNG of position/velocity/acceleration")
    p.set_defaults(func=cmd_trajectory)

    p = add("train", help="train an SB3 agent from a run config (calls training.train)")
    p.add_argument("--config", required=True)
    p.add_argument("--seed", type=int)
    p.add_argument("--total-timesteps", type=int, dest="total_timesteps")
    p.add_argument("--out", help="run directory (default runs/<name>/seed<seed>)")
    p.add_argument("--no-progress", action="store_true", dest="no_progress", help="no progress bar")
    p.set_defaults(func=cmd_train)

    p = add(
        "evaluate", help="evaluate a training run directory (one torch thread unless --threads N)"
    )
    p.add_argument("run_dir")
    p.add_argument("--episodes", type=int, default=100)
    p.set_defaults(func=cmd_evaluate)

    p = add("bench", help="benchmarks against pytorch-kinematics (prints ratios)")
    p.add_argument(
        "which", nargs="?", default="all", choices=["fk", "jacobian", "ik", "env", "calibration", "all"]
    )
    p.add_argument("--quick", action="store_true")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.set_defaults(func=cmd_bench)

    p = add(
        "demo",
        help="the tour: IK, calibration, CLIK, RL; report in runs/ (1 torch thread unless --threads N)",
        description="The tour: batch IK, calibration, CLIK and a short PPO run, written as a report. Runs on "
        "one torch thread (the report's figures are single-threaded and say so) unless given --threads N.",
    )
    p.add_argument("--quick", action="store_true", help="small sizes (under a minute)")
    p.add_argument("--out", help="report directory (default runs/demo-<time>)")
    p.add_argument("--skip-rl", action="store_true", dest="skip_rl")
    p.set_defaults(func=cmd_demo)

    from .viz import add_parser as add_view_parser  # `diffkin view` (viser is imported only when it runs)
    add_view_parser(sub, [common])
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        threads = args.threads
        if threads is None and args.command in _ONE_THREAD:
            threads = 1
        elif threads is None and args.command == "train":
            threads = _config_threads(args)
        if threads is not None:
            torch.set_num_threads(threads)
        return int(args.func(args) or 0)
    except (DiffkinError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
