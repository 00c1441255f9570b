"""Shared pieces of the ``diffkin`` subcommands: the console and its tables, naming and loading the robot
(``--robot`` / ``--urdf`` / ``--mjcf``), dtype and device options, progress bars."""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path

import torch

from ..errors import DiffkinError


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


def _check_output_dir(path: Path) -> None:
    if path.exists() and not path.is_dir():
        raise DiffkinError(f"{path}: is a file; the report needs a directory")
    for parent in path.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise DiffkinError(f"{path}: cannot create it: {parent} is a file, not a directory")
            break
