"""The ``diffkin`` command: models, batch FK / IK, calibration, trajectories, training, benchmarks, demo.

Every failure — a bad option value, an unreadable or ill-shaped file, an error raised by the library
(:class:`~diffkin.errors.DiffkinError`), a file-system error — prints one line ``error: ...`` on stderr and
exits with status 2; an unexpected internal error prints one ``error: internal error ...`` line and exits 1.
``--debug`` (or ``DIFFKIN_DEBUG=1``) shows the traceback instead. A calibration whose result fails its
plausibility checks (``CalibrationResult.success`` False) is such a failure too, unless ``--force``.

Threads: :func:`main` sets torch's intra-op thread count to ``--threads N``, else to 1 (``train``: the run
config's ``torch_threads``; ``bench``: the benchmarks' own default, 1). Batched kinematics gains little from
intra-op threads and collapses when another process holds a core (``diffkin ik --random 10000`` measured
about 1 000 solves/s with torch's default threads on a busy 2-core machine against 35 000 with one thread).

``train``, ``evaluate`` and ``demo`` call the functions of the repository's ``training`` package in this
process (the ``rl`` extra); ``bench`` calls ``benchmarks.run`` (a checkout's ``benchmarks/``, not installed
with the package). ``fk`` and ``ik`` stream their input in chunks (:mod:`diffkin.io.streaming`).
"""

from __future__ import annotations

import argparse
import contextlib
import inspect
import math
import os
import sys
import traceback
from pathlib import Path

import torch

from ..errors import DiffkinError

__all__ = ["main", "build_parser"]


def _console():
    """rich's console, or plain ``print`` without the ``cli`` extra (tables then print as aligned text)."""
    from .._console import console

    return console()


def _table(title: str, columns: list[str], rows: list[list], whole: tuple[int, ...] = ()):
    """A rich table (aligned text without the ``cli`` extra); the cells of the columns in ``whole`` are never
    cut or wrapped, whatever the terminal's width (the other columns wrap to make room)."""
    try:
        from rich.markup import escape
        from rich.table import Table
    except ImportError:  # no `cli` extra: the same table as aligned text
        cells = [[str(c) for c in columns]] + [[str(v) for v in r] for r in rows]
        widths = [max(len(r[i]) for r in cells) for i in range(len(columns))]
        lines = [title] + ["  ".join(v.ljust(w) for v, w in zip(r, widths)).rstrip() for r in cells]
        return "\n".join(lines)

    table = Table(title=escape(title))
    for i, c in enumerate(columns):
        if i in whole:
            longest = max([len(str(r[i])) for r in rows] + [len(str(c))])
            table.add_column(escape(c), no_wrap=True, min_width=longest)
        elif whole:  # the others wrap, folding a word longer than the column rather than cutting it
            table.add_column(escape(c), overflow="fold")
        else:
            table.add_column(escape(c))  # "[mm]" etc. are units, not rich markup
    for r in rows:
        table.add_row(*[escape(str(v)) for v in r])
    return table


def _print_whole(con, table) -> None:
    """Print a table of :func:`_table` with ``whole`` columns: wider than the terminal where these need
    more room than it has (the terminal then wraps the lines; nothing is cut)."""
    try:
        from rich.measure import Measurement
    except ImportError:  # plain text: never cut
        con.print(table)
        return
    width = con.width
    need = Measurement.get(con, con.options.update(max_width=10_000), table).minimum
    con.width = max(width, need)
    try:
        con.print(table)
    finally:
        con.width = width


def _dtype(name: str) -> torch.dtype:
    return {"float32": torch.float32, "float64": torch.float64}[name]


def _check_device(device: str) -> None:
    if device == "cuda" and not torch.cuda.is_available():
        raise DiffkinError("--device cuda was requested but no CUDA device is available (use --device cpu)")


def _robot_format(args) -> str | None:
    """The reader the robot option names: ``"urdf"`` (``--urdf``), ``"mjcf"`` (``--mjcf``) or None
    (``--robot``: a built-in name or a robot YAML). The flag decides, never the file's suffix."""
    return next((flag for flag in ("urdf", "mjcf") if getattr(args, flag, None)), None)


def _robot_source(args) -> tuple[str, str | None]:
    """``(source, end_link)`` of the robot options: ``--urdf`` / ``--mjcf FILE --end-link`` or ``--robot``;
    exactly one of them (two are an error, never one silently ignored)."""
    from .._console import check_one_robot

    check_one_robot(args)
    for flag in ("urdf", "mjcf"):
        path = getattr(args, flag, None)
        if path:
            if not args.end_link:
                raise DiffkinError(f"--{flag} needs --end-link NAME (the end-effector link)")
            return path, args.end_link
    if not args.robot:
        raise DiffkinError("give --robot NAME (see `diffkin models`), --urdf FILE or --mjcf FILE with "
                           "--end-link LINK")
    _check_robot_option(args.robot)
    # a built-in URDF / MuJoCo robot takes --end-link instead of its default end links (a DH model refuses it)
    return args.robot, getattr(args, "end_link", None)


def _load_chain(args):
    from ..models import load_chain

    _check_device(args.device)
    source, end_link = _robot_source(args)
    return load_chain(source, end_link, dtype=_dtype(args.dtype), device=args.device,
                      file_format=_robot_format(args))


def _check_robot_option(robot: str) -> None:
    """``--robot`` takes a built-in name or a robot YAML: a URDF or MJCF file there is told its option."""
    suffix = Path(robot).suffix.lower()
    if suffix == ".urdf":
        raise DiffkinError(f"--robot {robot}: a URDF file is given as --urdf {robot} --end-link LINK "
                           "(--robot takes a built-in name or a robot YAML file)")
    if suffix in (".xml", ".mjcf"):
        raise DiffkinError(f"--robot {robot}: an XML model; a MuJoCo MJCF is given as --mjcf FILE --end-link "
                           "BODY, a URDF as --urdf FILE --end-link LINK (--robot takes a built-in name or a "
                           "robot YAML file)")


@contextlib.contextmanager
def _progress(args, label: str):
    """A rich progress bar on stderr when it is a terminal (and no ``--no-progress``): yields the callback
    ``(done, total)`` for :mod:`diffkin.io.streaming`, or None."""
    try:
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
    except ImportError:  # the bar is a `cli` extra nicety
        yield None
        return
    if getattr(args, "no_progress", False) or not sys.stderr.isatty():
        yield None
        return

    with Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                  console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task(label, total=None)
        yield lambda done, total: bar.update(task, completed=done, total=total)


def _rate(n: int, seconds: float) -> str:
    return f"{n / seconds:,.0f}" if seconds > 0 else "-"


# ------------------------------------------------------------------------------------------ models
def cmd_models(args) -> int:
    from .. import models

    con = _console()
    if args.action == "show":
        if not args.name:
            raise DiffkinError("usage: diffkin models show NAME")
        robot = models.info(args.name)
        if robot.format != "dh":  # a URDF / MuJoCo robot: its joints, limits and where it comes from
            chain = models.load(args.name, dtype=torch.float64)
            kinds = getattr(chain, "joint_kinds", None) or ["-"] * len(chain.joint_names)
            rows = [[i + 1, name, kind] for i, (name, kind) in enumerate(zip(chain.joint_names, kinds))]
            con.print(_table(f"{robot.name} ({robot.format.upper()}, nq {chain.nq}, nv {chain.nv}; end links "
                             f"{', '.join(robot.end_links or ())})", ["joint", "name", "kind"], rows))
            con.print(f"file: {robot.path}\nsource: {robot.source}\nlicence: {robot.licence}")
            return 0
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
    rows, files = [], []
    for robot in models.available(details=True):
        if robot.format == "dh":
            chain = models.load(robot.name, dtype=torch.float64)
            rows.append([robot.name, chain.n_joints, chain.joint_types, chain.convention, robot.source])
        else:  # listed from the catalogue, not compiled: `diffkin models show NAME` loads one
            files.append([robot.name, ", ".join(robot.aliases) or "-", robot.format.upper(), robot.category,
                          ", ".join(robot.end_links or ()), robot.licence])
    con.print(_table("built-in robots (DH tables)", ["name", "DOF", "joints", "DH", "source"], rows))
    con.print(_table("built-in robots (URDF and MuJoCo files; `diffkin models show NAME` for one)",
                     ["name", "aliases", "format", "kind", "default end links", "licence"], files))
    return 0


# ---------------------------------------------------------------------------------------------- fk
def cmd_fk(args) -> int:
    from ..io.streaming import stream_fk

    chain, source = _stream_input(args, poses=False)
    res = _streamed(args, chain, "FK", stream_fk, source)
    if res is None:  # a rank other than 0 of a sharded run: rank 0 reports
        return 0
    print(
        f"FK of {res.count:,} configurations of '{chain.name}' on {chain.device} "
        f"in {res.compute_seconds:.3f} s "
        f"({_rate(res.count, res.compute_seconds)} configs/s; {res.seconds:.3f} s with I/O)"
        + (f" -> {res.output}" if res.output else "")
    )
    return 0


def _streamed(args, chain, label: str, stream, source, **options):
    """Run ``stream`` (stream_fk / stream_ik) over the input, in this process or, under torchrun, over
    this rank's shard (:func:`diffkin.io.distributed.run_sharded`); returns the summary (the combined one
    on rank 0, None on the other ranks)."""
    from ..io import distributed as dist

    info = dist.init(args.device)
    title = f"{label} (rank 0 of {info.world})" if info.sharded else label
    with _progress(args if info.rank == 0 else _Quiet(), title) as cb:
        return dist.run_sharded(stream, chain, source, args.output, chunk_size=args.chunk_size,
                                merge=args.merge, command=" ".join(sys.argv), progress=cb, device=args.device,
                                log=lambda line: print(line, file=sys.stderr), **options)


class _Quiet:
    no_progress = True


def _stream_input(args, poses: bool):
    """(chain, input) of ``fk`` / ``ik``: the output path checked first, the ranks joined (torchrun), the
    chain loaded, then :func:`_random_source`."""
    from ..io.data import RandomJoints, check_output_path

    if args.output:
        check_output_path(args.output)
    _join_ranks(args)
    chain = _load_chain(args)
    return chain, _random_source(args, chain, RandomJoints, poses)


def _random_source(args, chain, RandomJoints, poses: bool):
    """The input of ``fk`` / ``ik``: ``--input``, or ``--random N`` (collision-free with ``--self-collision``
    / ``--world``: joints, or for ``ik`` their FK poses as the targets). Sets ``args.collision``."""
    from .collision import collision_free_joints, collision_options

    collision, world = collision_options(args, chain, _robot_source(args)[0])
    args.collision = (collision, world, args.margin)
    if not args.random:
        if collision is not None and not poses:
            raise DiffkinError("fk: --self-collision / --world apply to --random samples")
        return args.input
    if collision is None:
        return RandomJoints(args.random, args.seed)
    q = collision_free_joints(chain, args.random, args.seed, args.chunk_size, collision, world, args.margin)
    if not poses:
        return q
    with torch.no_grad():
        T = chain.forward_kinematics(torch.as_tensor(q, dtype=chain.dtype, device=chain.device))
    return T.cpu().double().numpy()


def _join_ranks(args) -> None:
    """Under torchrun: join the process group first, so that ``--device cuda`` is this rank's GPU."""
    from ..io import distributed

    _check_device(args.device)
    distributed.init(args.device)


# ---------------------------------------------------------------------------------------------- ik
def _mm(x: float) -> str:
    return f"{x * 1e3:.4g}"


def _ik_table(chain, res) -> object:
    n, ok = res.count, res.successes
    rate = 100.0 * ok / n
    if ok < n:  # never round a failure away: 99.999 % shows as 99.99 %, not 100.00 %
        rate = math.floor(rate * 100) / 100
    med = "≈" if res.median_approximate else ""
    pos = f"{med}{_mm(res.position_error[0])} / {_mm(res.position_error[1])}"
    ori = "—" if res.orientation_error is None else (
        f"{med}{_mm(res.orientation_error[0])} / {_mm(res.orientation_error[1])}")
    rows = [
        ["targets", f"{n:,}"],
        ["successes", f"{ok:,}"],
        ["failures", f"{n - ok:,}"],
        ["success rate", f"{rate:.2f} %"],
        ["position error median / max [mm]", pos],
        ["orientation error median / max [mrad]", ori],
        ["solve time [s]", f"{res.compute_seconds:.3f} ({res.seconds:.3f} with I/O)"],
        ["solves/s", _rate(n, res.compute_seconds)],
    ]
    title = f"IK on '{chain.name}' ({'position only' if res.position_only else 'full pose'})"
    return _table(title, ["", "value"], rows)


def cmd_ik(args) -> int:
    from ..io.streaming import stream_ik
    from .collision import solve_keywords

    chain, source = _stream_input(args, poses=True)
    res = _streamed(
        args, chain, "IK", stream_ik, source, **solve_keywords(*args.collision),
        position_only=True if args.position_only else None,
        seed=args.seed,
        num_seeds=args.num_seeds,
        position_tolerance=args.position_tolerance,
        orientation_tolerance=args.orientation_tolerance,
    )
    if res is None:  # a rank other than 0 of a sharded run: rank 0 reports
        return 0
    _console().print(_ik_table(chain, res))
    if res.output:
        _console().print(f"wrote {res.output}")
    return 0


# ------------------------------------------------------------------------------------- calibrate
def cmd_calibrate(args) -> int:
    import warnings

    from ..calibration import calibrate_from_files
    from ..errors import ModelError
    from ..io.data import check_output_path

    if args.images is not None or args.joints is not None:
        return _cmd_calibrate_images(args)
    if args.data is None:
        raise DiffkinError("calibrate needs --data FILE (measured poses) or --images DIR with --joints FILE")
    out = Path(args.output)
    suffixes = (".yaml", ".yml", ".urdf", ".xml")
    as_dir = out.suffix not in suffixes
    if as_dir:
        if out.suffix:
            raise ModelError(f"--output {out}: give a .yaml (DH robot), a .urdf (URDF robot), an .xml (MJCF "
                             "robot) or a directory")
        _check_output_dir(out)
    else:
        check_output_path(out, suffixes)
    args.device, args.dtype = "cpu", "float64"  # calibration corrects by micrometres: float64 on the CPU
    chain = _load_chain(args)  # --robot NAME|FILE, --urdf / --mjcf FILE --end-link: as fk, ik and view
    kind = _written_kind(chain)
    if not as_dir and (".yaml" if out.suffix == ".yml" else out.suffix) != kind:
        raise ModelError(f"--output {out}: a DH robot (--robot NAME or YAML) is written as .yaml, a URDF "
                         f"robot as .urdf, an MJCF robot as .xml; this one as {kind} (or give a directory)")
    noise = None if args.noise is None else (args.noise[0] * 1e-3, math.radians(args.noise[1]))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = calibrate_from_files(
            chain, args.data, method=args.method, progress=not args.no_progress,
            out_dir=out if as_dir else None, force=args.force, error_model=args.error_model,
            base=args.base, tool=args.tool, measurement_noise=noise, cross_validation=args.cv, loss=args.loss,
        )
    written = None
    if res.success or args.force:
        if as_dir:
            written = out / f"calibrated{kind}"  # calibrate_from_files wrote it
        else:
            out.parent.mkdir(parents=True, exist_ok=True)
            if kind == ".urdf":
                res.chain.to_urdf(out)
            elif kind == ".xml":
                res.chain.to_mjcf(out)
            else:
                out.write_text(res.chain.to_yaml())
            written = out
    con = _console()
    title = f"calibration of '{res.nominal_chain.name}' ({args.method}; lengths mm, angles deg)"
    rows = res.display_rows()
    # the whole parameter names, whatever the terminal's width (URDF joints: "shoulder_pan_joint.dx")
    _print_whole(con, _table(title, ["parameter", "nominal", "identified", "delta", "unit", ""], rows,
                             whole=(0, 1, 2, 3, 4)))
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
    if res.outliers or res.loss != "l2":
        con.print(res.outlier_summary())
    for w in caught:
        con.print(f"[bold yellow]warning:[/] {w.message}")
    for note in res.notes:
        if not any(note in str(w.message) for w in caught):  # said once, as the warning
            con.print(f"note: {note}")
    if written is not None:
        con.print(f"wrote {written}" + (f" and the report in {out}" if as_dir else ""))
    elif as_dir:
        con.print(f"wrote the report in {out} (not the calibrated robot)")
    if res.report.unidentifiable:
        con.print(
            "not identifiable from these poses (kept at nominal): " + ", ".join(res.report.unidentifiable)
        )
    if not res.success:
        if not args.force:
            raise DiffkinError(f"calibration of '{res.nominal_chain.name}' failed: {res.failure}; the "
                               "calibrated robot was not written (--force writes it and exits 0)")
        con.print("[bold yellow]warning:[/] the calibration failed its plausibility checks; written anyway "
                  "(--force)")
    return 0


def _cmd_calibrate_images(args) -> int:
    """``calibrate --images DIR --joints FILE``: board pictures -> detect_board -> calibrate_camera."""
    import warnings

    from ..calibration.camera_io import calibrate_camera_from_files, write_camera_report

    need = {"--images": args.images, "--joints": args.joints, "--board": args.board, "--square": args.square,
            "--camera": args.camera}
    missing = [k for k, v in need.items() if v is None]
    if missing:
        raise DiffkinError(f"calibrate --images needs {', '.join(missing)} as well (see --help)")
    if args.data is not None:
        raise DiffkinError("give --data (measured poses) or --images with --joints (board pictures), "
                           "not both")
    if args.base or args.tool or args.noise is not None:
        raise DiffkinError("--base, --tool and --noise are for --data; with --images the camera's and the "
                           "board's poses are always estimated (--pixel-noise PX for the noise check)")
    out = Path(args.output)
    if out.suffix:
        raise DiffkinError(f"--output {out}: with --images give a directory (the calibrated robot, "
                           "camera.yaml, camera_joint.urdf, report.md, residuals.png, residuals/)")
    _check_output_dir(out)
    args.device, args.dtype = "cpu", "float64"  # calibration corrects by micrometres: float64 on the CPU
    chain = _load_chain(args)
    fx, fy, cx, cy = args.camera
    K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
    if args.dist is not None and len(args.dist) not in (4, 5):
        raise DiffkinError(f"--dist: expected 4 or 5 numbers (k1 k2 p1 p2 [k3]), got {len(args.dist)}")
    dist = None if args.dist is None else torch.tensor(args.dist, dtype=torch.float64)
    estimate = ("robot", "camera", "board") + (("intrinsics",) if args.intrinsics else ())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res, det = calibrate_camera_from_files(
            chain, args.images, args.joints, board=tuple(args.board), square=args.square, camera_matrix=K,
            detector=args.detector, marker=args.charuco_marker, dictionary=args.charuco_dictionary,
            dist_coeffs=dist, setup=args.setup, estimate=estimate, method=args.method,
            error_model=args.error_model, measurement_noise=args.pixel_noise, loss=args.loss,
            cross_validation=args.cv, progress=not args.no_progress,
        )
    written = write_camera_report(res, det, out, images=args.images)
    con = _console()
    con.print(f"board found in {int(det.found.sum())} of {len(det.names)} pictures"
              + ("" if bool(det.found.all()) else " (not in: "
                 + ", ".join(n for n, f in zip(det.names, det.found.tolist()) if not f) + ")"))
    title = f"camera calibration of '{res.nominal_chain.name}' ({args.method}; lengths mm, angles deg)"
    unit = {"m": (1e3, "mm"), "rad": (180.0 / math.pi, "deg"), "px": (1.0, "px")}
    rows = []
    for r in res.parameter_table():
        f, u = unit.get(r["unit"], (1.0, r["unit"]))
        rows.append([r["name"], f"{r['nominal'] * f:.4f}", f"{r['identified'] * f:.4f}",
                     f"{r['delta'] * f:+.4f}", u if r["identifiable"] else f"{u} (fixed: unidentifiable)"])
    if rows:
        _print_whole(con, _table(title, ["parameter", "nominal", "identified", "delta", "unit"], rows,
                                 whole=(0, 1, 2, 3, 4)))
    con.print(res.summary())
    for w in caught:
        con.print(f"[bold yellow]warning:[/] {w.message}")
    con.print("wrote " + ", ".join(str(p) for p in written))
    return 0


def _written_kind(chain) -> str:
    """The file a calibrated ``chain`` is written as: ``.xml`` (MJCF), ``.yaml`` (DH) or ``.urdf``."""
    if hasattr(chain, "to_mjcf"):
        return ".xml"
    return ".yaml" if hasattr(chain, "to_yaml") else ".urdf"



def _check_output_dir(path: Path) -> None:
    if path.exists() and not path.is_dir():
        raise DiffkinError(f"{path}: is a file; the report needs a directory")
    for parent in path.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise DiffkinError(f"{path}: cannot create it: {parent} is a file, not a directory")
            break


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


def _check_config(args) -> None:
    path = Path(args.config)
    if not path.is_file():
        raise DiffkinError(f"--config {path}: no such file" if not path.exists() else
                           f"--config {path}: not a file")


def _config_error(args, exc: Exception) -> DiffkinError:
    """``--config FILE: what is wrong`` (once: the config reader's messages may start with the file)."""
    text = str(exc).removeprefix(f"{args.config}: ")
    return DiffkinError(f"--config {args.config}: {text}")


def _config_threads(args) -> int:
    """The run config's ``torch_threads`` (what ``diffkin train`` runs on without ``--threads``)."""
    _check_config(args)
    try:
        from diffkin.training.config import load_config
    except ImportError as exc:
        raise _missing("train", exc) from exc
    try:
        cfg = load_config(args.config, getattr(args, "env", None), getattr(args, "variant", None))
        return cfg.torch_threads
    except (TypeError, ValueError, KeyError) as exc:
        raise _config_error(args, exc) from exc


def cmd_train(args) -> int:
    _check_config(args)
    if args.output:
        _check_output_dir(Path(args.output))
    try:
        from diffkin.training.train import resolve_run, summary_json, train
    except ImportError as exc:
        raise _missing("train", exc) from exc
    try:
        cfg, out = resolve_run(
            args.config, seed=args.seed, total_timesteps=args.total_timesteps, out=args.output, env=args.env,
            variant=args.variant,
        )
    except (TypeError, ValueError, KeyError) as exc:
        raise _config_error(args, exc) from exc
    res = train(cfg, out, progress_bar=not args.no_progress and sys.stderr.isatty())
    print(summary_json(res))
    _console().print(f"wrote {out}")
    return 0


def cmd_tune(args) -> int:
    _check_config(args)
    try:
        from diffkin.training import tune
    except ImportError as exc:
        raise _missing("tune", exc) from exc
    try:
        return tune.run(args, log=print)
    except (TypeError, ValueError, KeyError) as exc:  # messages name the config path, key or storage
        text = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)  # no KeyError repr
        raise DiffkinError(text) from exc


def cmd_evaluate(args) -> int:
    run = Path(args.run_dir)
    if not run.is_dir():
        raise DiffkinError(f"{run}: no such run directory" if not run.exists() else f"{run}: not a directory")
    if not (run / "config.yaml").is_file():
        raise DiffkinError(f"{run}: not a training run directory (no config.yaml; see `diffkin train`)")
    try:
        from diffkin.training.evaluate import evaluate_and_save
    except ImportError as exc:
        raise _missing("evaluate", exc) from exc
    import json

    try:
        res = evaluate_and_save(args.run_dir, episodes=args.episodes)
    except (TypeError, ValueError, KeyError) as exc:
        raise DiffkinError(f"{run}: {exc}") from exc
    print(json.dumps(res, indent=2))
    return 0


def cmd_bench(args) -> int:
    _check_device(args.device)
    try:
        from benchmarks.run import main as run_benchmarks
    except ImportError as exc:
        raise _missing("bench", exc) from exc
    argv = [args.which] + (["--quick"] if args.quick else []) + ["--device", args.device]
    if args.threads is not None:
        argv += ["--threads", str(args.threads)]
    return run_benchmarks(argv)


def _kernel_line() -> str:
    """``fused C kernel: in use (PATH)`` or ``fused C kernel: not in use: WHY`` (builds it if not tried)."""
    from ..kernels import native

    ok, what = native.status()
    return f"fused C kernel: in use ({what})" if ok else f"fused C kernel: not in use: {what}"


class _Version(argparse.Action):
    """``--version``: the version and the fused kernel's state, computed only when asked for."""

    def __init__(self, option_strings, version: str, dest=argparse.SUPPRESS, help=None):
        self.version = version
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"{self.version}\n{_kernel_line()}")
        parser.exit()


def cmd_doctor(args) -> int:
    from .. import __version__

    cuda = (f"{torch.cuda.device_count()} device(s), CUDA {torch.version.cuda}" if torch.cuda.is_available()
            else f"not available (CUDA build: {torch.version.cuda or 'no'})")
    print(f"diffkin {__version__} ({Path(__file__).parents[1]})")
    print(f"python {sys.version.split()[0]}, torch {torch.__version__}; CUDA: {cuda}")
    print(_kernel_line())
    return 0


def cmd_demo(args) -> int:
    from ..demo import run_demo

    if args.output:
        _check_output_dir(Path(args.output))
    return run_demo(quick=args.quick, out=args.output, skip_rl=args.skip_rl)


# ------------------------------------------------------------------------------------------ parser
class _Parser(argparse.ArgumentParser):
    """One ``error: ...`` line on stderr and exit status 2 for a bad command line (no usage block)."""

    def error(self, message: str):
        self.exit(2, f"error: {self.prog}: {message} (see `{self.prog} --help`)\n")


class _Formatter(argparse.RawDescriptionHelpFormatter):
    """Examples kept as written; ``(default: X)`` appended wherever an option has a default worth stating."""

    def _get_help_string(self, action):
        text = action.help or ""
        default = action.default
        if ("default" in text or default is None or default is False or default == argparse.SUPPRESS
                or isinstance(action, argparse._VersionAction)):
            return text
        return f"{text} (default: %(default)s)"


def _int_type(minimum: int, what: str):
    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if n < minimum:
            raise argparse.ArgumentTypeError(f"expected {what}, got {n}")
        return n

    parse.__name__ = "integer"
    return parse


_positive_int = _int_type(1, "a positive integer")
_count = _int_type(0, "a non-negative integer")


def _float_type(minimum: float | None = None, strict: bool = False):
    what = "a finite number" if minimum is None else (
        f"a finite number {'>' if strict else '>='} {minimum:g}")

    def parse(text: str) -> float:
        try:
            x = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(x) or (minimum is not None and (x <= minimum if strict else x < minimum)):
            raise argparse.ArgumentTypeError(f"expected {what}, got {text}")
        return x

    parse.__name__ = "number"
    return parse


_finite = _float_type()
_positive_float = _float_type(0.0, strict=True)
_nonnegative_float = _float_type(0.0)


def _cv_folds(text: str) -> int:
    n = _count(text)
    if n == 1:
        raise argparse.ArgumentTypeError("expected 0 (off) or k >= 2 folds, got 1")
    return n


_THREADS_HELP = (
    "torch intra-op threads (default: 1 — batched kinematics gains little from more and collapses when "
    "another process holds a core; `train` uses the config's torch_threads, `bench` passes N on)"
)

_EXAMPLES = {
    "models": "diffkin models\n  diffkin models show panda",
    "fk": "diffkin fk --robot panda --random 1000000 --output T.npy\n"
          "  diffkin fk --robot ur5 --input q.csv --output poses.csv\n"
          "  diffkin fk --urdf arm.urdf --end-link tool0 --input q.npy --output fk.npz",
    "ik": "diffkin ik --robot panda --input poses.csv --output q.npz\n"
          "  diffkin ik --robot ur5 --random 100000 --num-seeds 16\n"
          "  diffkin ik --robot panda --input xyz.npy --position-only --output q.csv",
    "calibrate": "diffkin calibrate --robot ur5 --data meas.npz --output cal.yaml\n"
                 "  diffkin calibrate --urdf arm.urdf --end-link tool0 --data meas.npz --tool "
                 "--noise 0.02 0.005 --output runs/cal/\n"
                 "  diffkin calibrate --mjcf ur10e.xml --end-link attachment_site --data meas.csv "
                 "--output ur10e_cal.xml\n"
                 "  diffkin calibrate --urdf panda.urdf --end-link panda_link8 --images shots/ --joints "
                 "q.csv --board 6 9 --square 0.025 --camera 1000 1000 640 512 --output runs/camcal/",
    "trajectory": "diffkin trajectory joint --profile quintic --start 0 0 --end 1 -1 --output j.csv "
                  "--plot j.png\n"
                  "  diffkin trajectory cartesian --start 0.3 0 0.5 --end 0.5 0.1 0.4 --output c.npz\n"
                  "  diffkin trajectory cartesian --points via_xyz.txt --duration 4 --output c.csv",
    "train": "diffkin train --config configs/ppo.yaml --env diffkin/Reach-v0 --variant cartesian "
             "--total-timesteps 20000 --output runs/ppo",
    "evaluate": "diffkin evaluate runs/ppo --episodes 100",
    "tune": "diffkin tune --config configs/sac.yaml --env diffkin/Reach-v0 --variant tune --trials 20\n"
            "  diffkin tune --config configs/sac.yaml --env diffkin/Reach-v0 --variant tune --trials 20 \\\n"
            "      --storage postgresql://user:pw@db/optuna --study reach   # one per worker machine\n"
            "  diffkin tune --config configs/sac.yaml --env diffkin/Reach-v0 --variant tune --show",
    "bench": "diffkin bench fk --quick\n  diffkin --threads 2 bench ik",
    "demo": "diffkin demo --quick --output runs/demo",
    "doctor": "diffkin doctor",
}

_DESCRIPTIONS = {
    "doctor": "Report the installation: diffkin, python and torch versions, CUDA, and whether the fused C\n"
              "kernel is in use (its cached library) or why not (DIFFKIN_NATIVE=0, no C compiler, build\n"
              "failed). `python -m diffkin.kernels` builds the kernel ahead of time.",
    "models": "List the built-in robots (DOF, joint types, DH convention, source) or print one's DH table.",
    "fk": "Batch forward kinematics of joint vectors (N, n) from a file or drawn at random.\n\n"
          "Input: .npy (N, n), .npz key q, or .csv (n columns, or a header naming q1..qn).\n"
          "Output by suffix: .npy holds the poses T (N, 4, 4) ((N, K, 4, 4) for K end links); .npz holds\n"
          "q, T, position, quaternion (w, x, y, z); .csv has a header q1..qn,x,y,z,qw,qx,qy,qz.\n"
          "The input is processed in chunks of --chunk-size rows (bounded memory for any N: .npy is read\n"
          "through a memory map, outputs are written chunk by chunk). --random N draws N configurations\n"
          "uniformly within the joint limits from --seed; the draws do not depend on the chunk size.",
    "ik": "Batch inverse kinematics (Levenberg-Marquardt with restarts) of target poses.\n\n"
          "Input: .npy (N, 4, 4) poses, (N, 7) rows x y z qw qx qy qz or (N, 3) positions; .npz key T or\n"
          "position [+ quaternion]; .csv read by its header (x,y,z and qw,qx,qy,qz: diffkin fk's CSV as it\n"
          "is; x,y,z only: position-only targets) or, headerless, 3 or 7 columns. A quaternion whose norm\n"
          "is off 1 by more than 1e-3 is refused with its row, never normalised silently.\n"
          "Output by suffix: .npy holds q (N, n); .npz and .csv hold q, success, position_error [m],\n"
          "orientation_error [rad] (NaN when solving positions only) and iterations; with --random also\n"
          "the sampled configurations q_sampled and the targets (.npz T_target; .csv x,y,z,qw,qx,qy,qz).\n"
          "Targets are solved in chunks of --chunk-size (bounded memory). --random N solves the FK of N\n"
          "random configurations (drawn as in `diffkin fk --random`). The solver's restarts in chunk [a, b)\n"
          "are seeded from (--seed, a): reproducible for one chunk size; each success flag is decided by an\n"
          "exact FK of the returned q.",
    "calibrate": "Identify a robot's geometry from measured poses and write the calibrated robot.\n\n"
                 "The nominal robot is named as in fk, ik and view: --robot NAME|FILE.yaml, --urdf FILE or\n"
                 "--mjcf FILE with --end-link. --output FILE.yaml (DH robot), FILE.urdf (URDF robot) or\n"
                 "FILE.xml (MJCF robot) writes the robot; --output DIR writes DIR/calibrated.yaml|urdf|xml\n"
                 "with parameters.md, report.json and residuals.png.\n"
                 "A result that fails its plausibility checks (held-out error or noise ratio more than 5x\n"
                 "the fit, a link corrected by more than 5 cm / 10 deg: data of another robot) is not\n"
                 "written and exits with status 2 (the report directory is written); --force writes it.\n"
                 "From board pictures: --images DIR --joints FILE --board ROWS COLS --square M\n"
                 "--camera FX FY CX CY detects the chessboard in each picture (OpenCV) and fits the\n"
                 "robot's geometry with the camera's and the board's poses to the corners' pixels;\n"
                 "--output DIR gets the calibrated robot, camera.yaml, camera_joint.urdf, report.md,\n"
                 "residuals.png and residuals/<picture>.png (each picture with its detected corners, the\n"
                 "corners projected before and after the fit and the residuals magnified).",
    "trajectory": "Plan a joint-space (cubic, quintic, trapezoidal) or a Cartesian straight-line trajectory\n"
                  "from --start to --end, or in either space a cubic spline through the via points of\n"
                  "--points (rows at equally spaced times), and export t, position, velocity, acceleration.",
    "train": "Train an SB3 agent from a run config (calls diffkin.training.train in this process; needs\n"
             "the rl extra). Runs on the config's torch_threads unless --threads N.",
    "tune": "Sweep a run config's hyperparameters with Optuna: each trial trains the config with values\n"
            "drawn from its search_space section, reports every evaluation (pruned when the pruner says\n"
            "so) and scores the final one (tune.metric). Workers share one study through --storage:\n"
            "SQLite by default (one file, several processes on one machine), any SQLAlchemy URL (e.g.\n"
            "PostgreSQL) for workers on several machines, or journal:FILE. --trials counts this worker's\n"
            "trials. --show prints the best trials and writes the best config. Needs the tune extra.",
    "evaluate": "Evaluate a training run directory (policy and the scripted-IK baseline) and write\n"
                "evaluation.json into it. One torch thread unless --threads N.",
    "bench": "The benchmark suite against the peers (pytorch-kinematics, ...), printing ratios measured in\n"
             "the same run. Needs a checkout (benchmarks/ is not installed with the package).",
    "demo": "The tour: batch IK, calibration, CLIK and a short PPO run, written as a report. Runs on one\n"
            "torch thread (the report's figures are single-threaded and say so) unless --threads N.",
}


def _robot_options(p: argparse.ArgumentParser):
    """The one way every subcommand names a robot: ``--robot NAME|FILE``, ``--urdf`` / ``--mjcf FILE`` with
    ``--end-link`` (read by :func:`_load_chain`); returns the argument group."""
    g = p.add_argument_group("robot")
    g.add_argument("--robot", help="built-in robot name (DH, URDF or MuJoCo: see `diffkin models`; a "
                   "robot_descriptions name when that package is installed) or a robot YAML file")
    g.add_argument("--urdf", help="URDF file (with --end-link)")
    g.add_argument("--mjcf", help="MuJoCo MJCF file (with --end-link: a body or site)")
    g.add_argument("--end-link", dest="end_link",
                   help="end-effector link of the URDF (a body or site of the MJCF; with --robot: a built-in "
                   "URDF / MuJoCo robot's end link instead of its default ones)")
    return g


def _robot_args(p: argparse.ArgumentParser, chunk_default: int, what: str) -> None:
    g = _robot_options(p)
    g.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="where to compute")
    g.add_argument("--dtype", default="float64", choices=["float32", "float64"],
                   help="compute (and .npy output) dtype")
    io = p.add_argument_group("input / output")
    src = io.add_mutually_exclusive_group(required=True)
    src.add_argument("--input", metavar="FILE", help=f"{what} file (.npy, .npz, .csv)")
    src.add_argument("--random", type=_positive_int, metavar="N",
                     help="use N random samples instead of --input")
    io.add_argument("--seed", type=_count, default=0,
                    help="random seed (of --random" + (" and of the solver's restarts)" if what == "pose"
                                                       else ")"))
    io.add_argument("--output", metavar="FILE",
                    help="output file (.npy, .npz, .csv; see above); without it only the summary is printed")
    io.add_argument("--chunk-size", dest="chunk_size", type=_positive_int, default=chunk_default, metavar="N",
                    help="rows per chunk (memory grows with it, not with the input)")
    io.add_argument("--no-progress", dest="no_progress", action="store_true",
                    help="no progress bar (shown only when stderr is a terminal)")
    io.add_argument("--merge", action="store_true",
                    help="under torchrun: concatenate the ranks' parts into --output (default: the parts "
                         "and a manifest <stem>.shards.json that every input option reads as one file)")
    from .collision import add_arguments

    add_arguments(p)


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__
    from ..ik import solve
    from ..io.streaming import FK_CHUNK_SIZE, IK_CHUNK_SIZE

    parser = _Parser(prog="diffkin", formatter_class=_Formatter,
                     description="diffkin: differentiable batched robot kinematics. Robot models, batch FK "
                     "and IK of files of any length, calibration, trajectories, training, benchmarks, demo.",
                     epilog="examples:\n  " + "\n  ".join(
                         ["diffkin models", "diffkin fk --robot panda --random 1000 --output T.npy",
                          "diffkin ik --robot panda --input T.npy --output q.npz",
                          "diffkin COMMAND --help"]))
    parser.add_argument("--version", action=_Version, version=f"diffkin {__version__}",
                        help="show the version and whether the fused C kernel is in use, and exit")
    parser.add_argument("--threads", type=_positive_int, default=None, metavar="N", help=_THREADS_HELP)
    parser.add_argument("--debug", action="store_true",
                        help="show the traceback of an error (also DIFFKIN_DEBUG=1)")
    # Also accepted after the subcommand; SUPPRESS keeps the subparser from overwriting the global value.
    common = _Parser(add_help=False)
    common.add_argument("--threads", type=_positive_int, default=argparse.SUPPRESS, metavar="N",
                        help=_THREADS_HELP)
    common.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add(name: str, help: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, parents=[common], help=help, description=_DESCRIPTIONS[name],
                              epilog="examples:\n  " + _EXAMPLES[name], formatter_class=_Formatter)

    p = add("models", "list built-in robots, or show one's DH table")
    p.add_argument("action", nargs="?", choices=["list", "show"], default="list", help="what to do")
    p.add_argument("name", nargs="?", help="robot to show")
    p.set_defaults(func=cmd_models)

    p = add("fk", "batch forward kinematics of joint vectors (streamed)")
    _robot_args(p, FK_CHUNK_SIZE, "joint-vector")
    p.set_defaults(func=cmd_fk)

    p = add("ik", "batch inverse kinematics of target poses (streamed)")
    _robot_args(p, IK_CHUNK_SIZE, "pose")
    g = p.add_argument_group("solver")
    g.add_argument("--position-only", action="store_true",
                   help="solve positions only (implied by a file of positions x y z)")
    g.add_argument("--position-tolerance", type=_positive_float, default=1e-4, metavar="M",
                   help="success threshold on the position error [m]")
    g.add_argument("--orientation-tolerance", type=_positive_float, default=1e-3, metavar="RAD",
                   help="success threshold on the orientation error [rad]")
    g.add_argument("--num-seeds", dest="num_seeds", type=_positive_int, metavar="S",
                   default=inspect.signature(solve).parameters["num_seeds"].default,
                   help="most initial configurations (random restarts) per target")
    p.set_defaults(func=cmd_ik)

    p = add("calibrate", "identify a robot's geometry from measured poses or board pictures")
    _robot_options(p)  # the nominal robot, named as in fk, ik and view
    p.add_argument("--data",
                   help="measurements: .npz with q (N, n) and T (N, 4, 4) or position (N, 3) [+ quaternion], "
                        "or .csv read by its header q1..qn,x,y,z[,qw,qx,qy,qz] (diffkin fk's CSV)")
    g = p.add_argument_group("from board pictures (instead of --data; needs the camera extra)")
    g.add_argument("--images", metavar="DIR", help="folder of chessboard pictures (sorted by file name)")
    g.add_argument("--joints", metavar="FILE",
                   help="joint readings, one per picture: .csv (an 'image' column names the picture; else "
                        "rows in the pictures' order), .npy (N, n) or .npz key q")
    g.add_argument("--board", type=_positive_int, nargs=2, metavar=("ROWS", "COLS"),
                   help="inner corners of the chessboard (one count even, the other odd)")
    g.add_argument("--square", type=_positive_float, metavar="M", help="side of the board's squares [m]")
    g.add_argument("--camera", type=_positive_float, nargs=4, metavar=("FX", "FY", "CX", "CY"),
                   help="camera matrix [px] (the start with --intrinsics)")
    g.add_argument("--dist", type=_finite, nargs="+", metavar="K",
                   help="OpenCV distortion k1 k2 p1 p2 [k3] (default none)")
    g.add_argument("--setup", choices=["eye_to_hand", "eye_in_hand"], default="eye_to_hand",
                   help="a fixed camera and the board on the flange, or the camera on the flange")
    g.add_argument("--intrinsics", action="store_true", help="also estimate the camera matrix and distortion")
    g.add_argument("--detector", choices=["classic", "sb"], default="classic",
                   help="OpenCV's findChessboardCorners (classic) or findChessboardCornersSB (sb)")
    g.add_argument("--charuco-marker", type=_positive_float, metavar="M",
                   help="a ChArUco board (OpenCV's CharucoBoard of ROWS+1 x COLS+1 squares): its markers' "
                        "side [m]; partial views count")
    g.add_argument("--charuco-dictionary", default="DICT_5X5_100", metavar="NAME",
                   help="the ChArUco board's ArUco dictionary (cv2.aruco.DICT_*; default DICT_5X5_100)")
    g.add_argument("--pixel-noise", dest="pixel_noise", type=_positive_float, metavar="PX",
                   help="detection noise per coordinate [px]: the noise check and the outlier threshold")
    p.add_argument("--method", default="least_squares", choices=["least_squares", "gradient"],
                   help="solver")
    p.add_argument("--error-model", dest="error_model", default="auto",
                   choices=["auto", "dh", "hayati", "general"], help="parameters identified")
    p.add_argument("--base", action="store_true", help="also estimate the base (tracker) frame")
    p.add_argument("--tool", action="store_true", help="also estimate the tool frame")
    p.add_argument("--noise", type=_nonnegative_float, nargs=2, metavar=("MM", "DEG"),
                   help="measurement noise per coordinate (position mm, orientation deg): warn when the fit "
                        "residual is more than 2x what it explains")
    p.add_argument("--loss", choices=["l2", "huber", "cauchy", "soft_l1"], default=None,
                   help="robust loss against outliers (scale from --noise, else 1 mm); default l2 for "
                        "least_squares, huber for gradient")
    p.add_argument("--cv", type=_cv_folds, default=5,
                   help="k of the k-fold cross-validated held-out error, 0: off")
    p.add_argument("--output", required=True, metavar="FILE|DIR",
                   help="calibrated robot: .yaml (DH), .urdf (URDF input) or .xml (MJCF input); a directory "
                        "gets the robot and the report (parameters.md, report.json, residuals.png)")
    p.add_argument("--force", action="store_true",
                   help="write the calibrated robot and exit 0 even when the result fails its plausibility "
                        "checks (held-out error or noise ratio more than 5x the fit, a link corrected by "
                        "more than 5 cm / 10 deg: the data are probably of another robot)")
    p.add_argument("--no-progress", dest="no_progress", action="store_true",
                   help="no progress bar (shown only when stderr is a terminal)")
    p.set_defaults(func=cmd_calibrate)

    p = add("trajectory", "plan and export a joint or Cartesian trajectory")
    p.add_argument("space", choices=["joint", "cartesian"], help="joint space or a Cartesian segment")
    p.add_argument("--profile", choices=["cubic", "quintic", "trapezoidal"],
                   help="time law from --start to --end (default quintic; not with --points)")
    p.add_argument("--start", type=_finite, nargs="+", help="start joint vector (or X Y Z)")
    p.add_argument("--end", type=_finite, nargs="+", help="end joint vector (or X Y Z)")
    p.add_argument("--points", help="via points for a cubic spline through them at equally spaced times: "
                                    "(N, n) joint vectors or (N, 3) Cartesian positions (.csv, .txt, .npy, "
                                    ".npz key points); instead of --start/--end/--profile")
    p.add_argument("--duration", type=_positive_float, default=2.0, help="seconds")
    p.add_argument("--samples", type=_int_type(2, "at least 2 samples"), default=201,
                   help="time samples, both ends included")
    p.add_argument("--output", required=True, help="output file (.npz, .csv, .npy)")
    p.add_argument("--plot", help="PNG of position/velocity/acceleration")
    p.set_defaults(func=cmd_trajectory)

    p = add("train", "train an SB3 agent from a run config (calls diffkin.training.train)")
    p.add_argument("--config", required=True,
                   help="configs/<algo>.yaml with --env (see configs/README.md), or a single-run YAML")
    p.add_argument("--env", help="the config entry's env ID, e.g. diffkin/Reach-v0")
    p.add_argument("--variant", help="the entry's variant, e.g. cartesian (key diffkin/Reach-v0:cartesian)")
    p.add_argument("--seed", type=_count, help="override the config's seed")
    p.add_argument("--total-timesteps", type=_positive_int, dest="total_timesteps",
                   help="override the config's total_timesteps")
    p.add_argument("--output", metavar="DIR", help="run directory (default runs/<name>/seed<seed>)")
    p.add_argument("--no-progress", action="store_true", dest="no_progress",
                   help="no progress bar (shown only when stderr is a terminal)")
    p.set_defaults(func=cmd_train)

    p = add("tune", "hyperparameter sweeps with Optuna on a shared study (SQLite / PostgreSQL / journal)")
    try:
        from diffkin.training.tune import add_arguments as add_tune_arguments
    except ImportError:  # no training code here: cmd_tune names what to install
        p.add_argument("--config", required=True)
    else:
        add_tune_arguments(p)
    p.set_defaults(func=cmd_tune)

    p = add("evaluate", "evaluate a training run directory")
    p.add_argument("run_dir", help="the run directory written by `diffkin train`")
    p.add_argument("--episodes", type=_positive_int, default=100, help="evaluation episodes")
    p.set_defaults(func=cmd_evaluate)

    p = add("bench", "benchmarks against pytorch-kinematics and others (prints ratios)")
    p.add_argument(
        "which", nargs="?", default="all",
        choices=["fk", "jacobian", "ik", "env", "calibration", "model", "kernels", "all"],
        help="which suite (kernels: the performance targets, latency and busy-core runs)",
    )
    p.add_argument("--quick", action="store_true", help="small sizes")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="where to run")
    p.set_defaults(func=cmd_bench)

    p = add("demo", "the tour: fused kernels, IK, calibration, CLIK, RL; report in runs/")
    p.add_argument("--quick", action="store_true", help="small sizes (under a minute)")
    p.add_argument("--output", metavar="DIR", help="report directory (default runs/demo-<time>)")
    p.add_argument("--skip-rl", action="store_true", dest="skip_rl", help="skip the PPO run")
    p.set_defaults(func=cmd_demo)

    p = add("doctor", "report versions, CUDA and whether the fused C kernel is in use (and why not)")
    p.set_defaults(func=cmd_doctor)

    from . import retarget as _cli_retarget  # `diffkin retarget` (its description and examples live with it)
    p = sub.add_parser("retarget", parents=[common], help="a human clip (BVH, SMPL joints) onto a humanoid",
                       description=_cli_retarget.DESCRIPTION, epilog="examples:\n  " + _cli_retarget.EXAMPLES,
                       formatter_class=_Formatter)
    _cli_retarget.add_arguments(p)
    p.set_defaults(func=_cli_retarget.cmd_retarget)

    from . import plan as _cli_plan  # `diffkin plan` (its description and examples live with it)
    p = sub.add_parser("plan", parents=[common], help="collision-free timed motions from start to goal",
                       description=_cli_plan.DESCRIPTION, epilog="examples:\n  " + _cli_plan.EXAMPLES,
                       formatter_class=_Formatter)
    _cli_plan.add_arguments(p)
    p.set_defaults(func=_cli_plan.cmd_plan)

    from ..viz import add_parser as add_view_parser  # `diffkin view` (viser is imported only when it runs)
    add_view_parser(sub, [common])
    return parser


def _one_line(text: str) -> str:
    return " ".join(str(text).split()) or "(no message)"


def _os_message(exc: OSError) -> str:
    if exc.filename is not None and exc.strerror:
        return f"{exc.filename}: {exc.strerror}"
    return str(exc)


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (0, 2 for any user error, 1 for an internal error)."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a bad command line (already reported)
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    debug = getattr(args, "debug", False) or os.environ.get("DIFFKIN_DEBUG", "") not in ("", "0")
    try:
        threads = args.threads
        if threads is None and args.command in ("train", "tune"):
            threads = _config_threads(args)
        elif threads is None and args.command != "bench":
            threads = 1
        if threads is not None:
            torch.set_num_threads(threads)
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
    except DiffkinError as exc:
        if debug:
            traceback.print_exc()  # the traceback on request; the status stays that of a user error
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except OSError as exc:
        if debug:
            traceback.print_exc()
        print(f"error: {_one_line(_os_message(exc))}", file=sys.stderr)
        return 2
    except Exception as exc:  # a bug, not a user error: still one line, with the way to the traceback
        if debug:
            raise
        print(f"error: internal error: {type(exc).__name__}: {_one_line(exc)} (rerun with --debug for the "
              "traceback, and please report it)", file=sys.stderr)
        return 1

