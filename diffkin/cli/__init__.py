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

This module holds the parser and :func:`main`; each subcommand is a module of this package (``models``,
``kinematics`` for ``fk`` / ``ik``, ``calibrate``, ``trajectory``, ``plan``, ``retarget``, ``training`` for
``train`` / ``tune`` / ``evaluate`` / ``bench``, ``doctor`` for ``doctor`` / ``demo``), the shared options and
printing in ``_common``.
"""

from __future__ import annotations

import argparse
import inspect
import math
import os
import sys
import traceback

import torch

from ..errors import DiffkinError
from .calibrate import cmd_calibrate
from .doctor import _Version, cmd_demo, cmd_doctor
from .kinematics import cmd_fk, cmd_ik
from .models import cmd_models
from .training import _config_threads, cmd_bench, cmd_evaluate, cmd_train, cmd_tune
from .trajectory import cmd_trajectory

__all__ = ["main", "build_parser"]

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

