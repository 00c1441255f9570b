"""``diffkin trajectory``: joint or Cartesian trajectories (ch. 4) exported as CSV / NPZ, with a plot."""

from __future__ import annotations

import torch

from ..errors import DiffkinError


# ------------------------------------------------------------------------------------ trajectory
def cmd_trajectory(args) -> int:
    from .. import trajectories as tr
    from ..io.data import check_output_path, read_array, write_arrays

    check_output_path(args.output)
    if args.plot:
        check_output_path(args.plot, (".png", ".pdf", ".svg"))
    t = torch.linspace(0.0, args.duration, args.samples, dtype=torch.float64)
    profile = args.profile or "quintic"
    if args.points:
        # through a sequence of points (§4.2.2; in operational space "a smooth interpolating vector function
        # between the path points", §4.3): a cubic spline, the points at equally spaced times
        given = [f for f, v in (("--profile", args.profile), ("--start", args.start), ("--end", args.end))
                 if v is not None]
        if given:
            raise DiffkinError(f"{' and '.join(given)} cannot be combined with --points (the spline passes "
                               "through the points' first and last rows); give --points FILE, or --start "
                               "and --end")
        pts = torch.as_tensor(read_array(args.points, key="points"), dtype=torch.float64)
        width = "3 (x, y, z)" if args.space == "cartesian" else "n"
        if pts.ndim != 2 or pts.shape[0] < 2 or (args.space == "cartesian" and pts.shape[1] != 3):
            raise DiffkinError(
                f"{args.points}: expected {'Cartesian ' if args.space == 'cartesian' else ''}via points of "
                f"shape (N >= 2, {width}), got {tuple(pts.shape)}"
            )
        if not bool(torch.isfinite(pts).all()):
            raise DiffkinError(f"{args.points}: the via points hold NaN or inf")
        times = torch.linspace(0.0, args.duration, pts.shape[0], dtype=torch.float64)
        traj = tr.cubic_spline(pts, times, t)
    elif args.space == "joint":
        if args.start is None or args.end is None:
            raise DiffkinError("give --points FILE, or --start and --end joint vectors")
        qi = torch.tensor(args.start, dtype=torch.float64)
        qf = torch.tensor(args.end, dtype=torch.float64)
        if qi.shape != qf.shape:
            raise DiffkinError(f"--start has {qi.numel()} values but --end has {qf.numel()}")
        fn = {"cubic": tr.cubic, "quintic": tr.quintic, "trapezoidal": tr.trapezoidal}[profile]
        traj = fn(qi, qf, torch.tensor(args.duration, dtype=torch.float64), t)
    else:
        if args.start is None or args.end is None or len(args.start) != 3 or len(args.end) != 3:
            raise DiffkinError("a cartesian trajectory needs --start X Y Z and --end X Y Z, or --points FILE")
        traj = tr.cartesian_segment_trajectory(
            torch.tensor(args.start, dtype=torch.float64),
            torch.tensor(args.end, dtype=torch.float64),
            args.duration,
            t,
            profile=profile,
        )
    out = {
        "t": t.numpy(),
        "position": traj.position.detach().numpy(),
        "velocity": traj.velocity.detach().numpy(),
        "acceleration": traj.acceleration.detach().numpy(),
    }
    write_arrays(args.output, out)
    if args.plot:
        _plot_trajectory(out, args.plot, args.space)
    print(
        f"{args.space} trajectory, {args.samples} samples over {args.duration} s -> {args.output}"
        + (f" (plot: {args.plot})" if args.plot else "")
    )
    return 0


_TRAJECTORY_UNITS = {  # (symbol, unit) per panel: joint space (rad, or m for a prismatic joint), Cartesian
    "joint": (("q", "rad or m"), ("q̇", "rad/s or m/s"), ("q̈", "rad/s² or m/s²")),
    "cartesian": (("p", "m"), ("ṗ", "m/s"), ("p̈", "m/s²")),
}


def _trajectory_figure(out: dict, space: str = "joint"):
    """Position, velocity and acceleration against time, one line per joint (q1..qn) or axis (x, y, z),
    with a legend and units."""
    from ..errors import require

    Figure = require("matplotlib.figure", "plot", "--plot").Figure  # file output: no pyplot, no backend

    fig = Figure(figsize=(7, 7))
    axs = fig.subplots(3, 1, sharex=True)
    n = out["position"].shape[-1]
    names = ["x", "y", "z"] if space == "cartesian" else [f"q{i + 1}" for i in range(n)]
    for ax, key, (sym, unit) in zip(axs, ("position", "velocity", "acceleration"), _TRAJECTORY_UNITS[space]):
        for i, name in enumerate(names):
            ax.plot(out["t"], out[key][:, i], label=name)
        ax.set_ylabel(f"{key}\n{sym} [{unit}]")
        ax.grid(alpha=0.3)
    axs[0].legend(title="joint" if space == "joint" else "axis", fontsize=8, ncols=min(n, 7),
                  loc="upper left", bbox_to_anchor=(0.0, 1.32))
    axs[-1].set_xlabel("time t [s]")
    fig.suptitle(f"{space} trajectory", y=0.99)
    fig.tight_layout()
    return fig


def _plot_trajectory(out: dict, path: str, space: str = "joint") -> None:
    _trajectory_figure(out, space).savefig(path, dpi=110)
