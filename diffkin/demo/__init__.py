"""``diffkin demo``: the tour of what diffkin does, written as a report (Markdown + PNG) under ``runs/``.

Sections: batch IK on Panda targets (against pytorch-kinematics in the same run), URDF trees, a MuJoCo
Menagerie humanoid with a floating base (FK against MuJoCo, whole-body IK), calibration before/after,
calibration from camera images beside OpenCV's hand-eye methods,
the §3.7.5 CLIK comparison, human motion retargeted onto the G1, and a short PPO run on the batched Reach
environment (``training.train``, called in-process when the ``rl`` extra and the repository's ``configs/``
are there; otherwise the section says why it was skipped).

:func:`run_demo` leaves torch's thread count and matplotlib's backend alone (figures are drawn on
:class:`matplotlib.figure.Figure` objects); ``diffkin demo`` runs it on one torch thread unless given
``--threads N``.
"""

from __future__ import annotations

import time
from pathlib import Path

from ._common import Report, _figure_module
from .calibration import section_calibration, section_camera_calibration
from .kinematics import section_ik, section_ik_layer, section_kernels, section_mjcf, section_trees
from .motion import section_clik, section_collision_ik, section_motion, section_teleop
from .retargeting import section_retarget
from .rl import section_rl

__all__ = ["run_demo"]


def run_demo(quick: bool = False, out: str | None = None, skip_rl: bool = False) -> int:
    """Run the tour and write ``report.md`` and PNGs to ``out`` (default ``runs/demo-<time>``).

    Runs on torch's current thread count (the report states it); ``diffkin demo`` sets one thread first,
    since small batched kernels gain nothing from intra-op threads and lose a lot when another process
    holds a core."""
    from .._console import console

    try:
        from rich.markdown import Markdown
    except ImportError:  # without the `cli` extra the report prints as plain Markdown
        Markdown = str
    con = console()
    _figure_module()  # the report's figures need matplotlib: say so before any work
    out_dir = Path(out) if out else Path("runs") / time.strftime("demo-%Y%m%d-%H%M%S")
    out_dir.mkdir(parents=True, exist_ok=True)
    report = Report(out_dir)
    steps = [
        ("kernels", lambda: section_kernels(report, quick)),
        ("batch IK", lambda: section_ik(report, 1_000 if quick else 10_000, 200 if quick else 1_000)),
        ("IK layer", lambda: section_ik_layer(report, quick)),
        ("URDF trees", lambda: section_trees(report, quick)),
        ("MuJoCo models", lambda: section_mjcf(report, quick)),
        ("calibration", lambda: section_calibration(report, 60 if quick else 100)),
        ("camera calibration", lambda: section_camera_calibration(report, quick)),
        ("CLIK §3.7.5", lambda: section_clik(report, quick)),
        ("collision-free IK", lambda: section_collision_ik(report, quick)),
        ("teleoperation", lambda: section_teleop(report, quick)),
        ("retargeting", lambda: section_retarget(report, quick)),
        ("motion planning", lambda: section_motion(report, quick)),
    ]
    if not skip_rl:
        steps.append(("RL", lambda: section_rl(report, 15 if quick else 150)))
    t_all = time.perf_counter()
    for name, fn in steps:
        with con.status(f"[bold]{name}[/bold] ..."):
            t0 = time.perf_counter()
            fn()
        con.print(f"[green]✓[/green] {name} ({time.perf_counter() - t0:.1f} s)")
        con.print(Markdown(report.sections[-1]))
    path = report.write()
    con.print(f"\nreport written to [bold]{path}[/bold] ({time.perf_counter() - t_all:.0f} s in all)")
    for f in report.failures:
        con.print(f"[red]problem:[/red] {f}")
    return 1 if report.failures else 0
