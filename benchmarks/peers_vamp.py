"""VAMP (KavrakiLab's Vector-Accelerated Motion Planner, ``vamp-planner`` 0.6.4, Apache-2.0) as a peer of
``motion.plan`` on the 700 MotionBenchMaker Panda problems.

VAMP is built from its PyPI source distribution into its own venv by ``benchmarks/install_vamp.sh``
(``VAMP_PYTHON``, default ``/work/venvs/vamp/bin/python``); :func:`solve_vamp` runs this file there as a child
process (stdlib and VAMP only: no torch, no diffkin) and reads its answers back as JSON lines
(:func:`parse_lines`). The rows are skipped when that interpreter cannot import ``vamp`` (:func:`available`).

**What the child runs** is VAMP's own benchmark path, unchanged:

* the problems: VAMP's converter ``resources/problem_tar_to_pkl_json.py`` of the sdist (``VAMP_SDIST``)
  imported as it is (``load_moveit_yaml_scene``, ``load_moveit_yaml_request``, ``test_problem``), on the same
  ``problems.tar.bz2`` diffkin reads (``benchmarks.motion_problems.ARCHIVE``, byte-identical to the sdist's);
  the environment is ``vamp.problem_dict_to_vamp`` (cylinders as capsules, the ``box`` family's cylinders as
  boxes: VAMP's own choices); a problem is valid when VAMP's ``test_problem`` says so (its 699);
* the robot: VAMP's compiled spherized Panda (``vamp.panda``);
* the planner: ``vamp.configure_robot_and_planner_with_kwargs("panda", "rrtc")`` (RRT-Connect, range 1.0,
  10⁶ iterations), VAMP's default Halton sampler reset before each problem, then ``vamp.panda.simplify``
  with its default settings, as ``scripts/evaluate_mbm.py`` does;
* the times: VAMP's own ``nanoseconds`` of the planning and simplification results (what its README's
  35 µs median is), and the wall time of the two Python calls.

Each answer: ``name`` (``family/index``), ``valid``, ``solved``, ``plan_ns``, ``simplify_ns``, ``wall_ns``,
``iterations``, ``initial_cost`` and ``cost`` (VAMP's L2 path costs) and ``path``: the simplified path's
waypoints, a list of 7-lists (radians), start to goal.

**Timing VAMP's path** (its output is a path, not a trajectory): with ``velocity_limit`` and
``acceleration_limit`` given, the child also times each solved path with toppra (TOPP-RA, PyPI, installed in
VAMP's venv; ``ParametrizeConstAccel``, the same constraints as ``benchmarks/bench_motion.py``), after VAMP's
clock has stopped:

* ``toppra_stop_s``: the path VAMP checked, exactly: each straight segment timed from rest to rest (a
  two-point ``SplineInterpolator`` is the straight line) and the durations summed; ``jerk_max``: the largest
  |Δq̈|/Δt of that trajectory sampled every 1 ms (toppra's q̈ is piecewise constant: this grows as 1/Δt);
* ``toppra_spline_s``: toppra on the cubic spline through the waypoints (chord-length knots, clamped ends,
  as diffkin's smoothing), **not** collision-checked: a lower bound for a smoothed VAMP path;
* ``length``: the polyline's joint-space length Σ‖Δq‖ (rad).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

__all__ = ["VAMP_PYTHON", "VAMP_SDIST", "available", "solve_vamp", "parse_lines"]

VAMP_PYTHON = os.environ.get("VAMP_PYTHON", "/work/venvs/vamp/bin/python")
VAMP_SDIST = os.environ.get("VAMP_SDIST", "/work/venvs/vamp_src/vamp_planner-0.6.4")
_KEYS = ("name", "valid", "solved", "plan_ns", "simplify_ns", "wall_ns", "iterations", "initial_cost",
         "cost", "path")


def available() -> bool:
    """Whether ``VAMP_PYTHON`` imports ``vamp`` with its Panda and the sdist's converter is there."""
    converter = Path(VAMP_SDIST) / "resources" / "problem_tar_to_pkl_json.py"
    if not Path(VAMP_PYTHON).exists() or not converter.exists():
        return False
    probe = subprocess.run([VAMP_PYTHON, "-c", "import vamp; vamp.panda"], capture_output=True)
    return probe.returncode == 0


def solve_vamp(problems, archive, velocity_limit=None, acceleration_limit=None) -> list[dict]:
    """VAMP's RRT-Connect and simplification (module docstring) on ``problems`` (objects with ``family`` and
    ``index``, e.g. :class:`benchmarks.motion_problems.MotionProblem`) of ``archive``: one answer per problem,
    in their order; with both limits (7 numbers each) the toppra timings of the paths as well."""
    request = {"archive": str(archive), "sdist": VAMP_SDIST,
               "problems": [[p.family, int(p.index)] for p in problems], "limits": None}
    if velocity_limit is not None and acceleration_limit is not None:
        request["limits"] = [[float(x) for x in velocity_limit], [float(x) for x in acceleration_limit]]
    done = subprocess.run([VAMP_PYTHON, str(Path(__file__).resolve()), "--child"], input=json.dumps(request),
                          capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"VAMP child failed ({done.returncode}): {done.stderr[-2000:]}")
    answers = parse_lines(done.stdout)
    names = [f"{p.family}/{int(p.index):04d}" for p in problems]
    missing = [n for n in names if n not in answers]
    if missing:
        raise RuntimeError(f"VAMP child gave no answer for {missing[:5]} ({len(missing)} in all)")
    return [answers[n] for n in names]


def parse_lines(text: str) -> dict[str, dict]:
    """The child's output, one JSON object per line with the keys of the module docstring, as
    ``{name: answer}``. Lines that are not JSON objects (VAMP's settings prints) are skipped; an object
    missing a key, or a solved answer whose path is not a list of 7-lists, is a ``ValueError``."""
    out: dict[str, dict] = {}
    for line in text.splitlines():
        line = line.strip()
        if not line.startswith("{"):
            continue
        answer = json.loads(line)
        missing = [k for k in _KEYS if k not in answer]
        if missing:
            raise ValueError(f"VAMP answer {line[:80]!r} lacks {missing}")
        path = answer["path"]
        if answer["solved"] and (not isinstance(path, list) or len(path) < 2
                                 or any(not isinstance(q, list) or len(q) != 7 for q in path)):
            raise ValueError(f"VAMP answer for {answer['name']}: path is not a list of >= 2 7-lists")
        out[answer["name"]] = answer
    return out


def _child() -> None:  # runs in VAMP's venv: stdlib, PyYAML and vamp only
    import importlib.util
    import re
    import tarfile
    import time

    import vamp
    from yaml import CSafeLoader, load

    request = json.loads(sys.stdin.read())
    spec = importlib.util.spec_from_file_location(
        "vamp_problem_tar", Path(request["sdist"]) / "resources" / "problem_tar_to_pkl_json.py")
    conv = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(conv)  # VAMP's own MoveIt YAML converter, unchanged
    panda = vamp.panda
    joints = panda.joint_names()
    want = {(f, i) for f, i in request["problems"]}
    scenes, requests = {}, {}
    with tarfile.open(request["archive"], "r:bz2") as tar:
        for m in tar:
            if not m.isfile():
                continue
            _, family, filename = m.name.split("/")
            family = family.replace("_panda", "")
            index = int(re.findall(r"\d+", filename)[0])
            if (family, index) not in want:
                continue
            data = load(tar.extractfile(m).read(), Loader=CSafeLoader)
            meta = {"index": index, "problem": family}
            if "scene" in filename:
                scenes[family, index] = conv.load_moveit_yaml_scene(data) | meta
            else:
                requests[family, index] = conv.load_moveit_yaml_request(data, joints) | meta
    devnull = open(os.devnull, "w")
    real = sys.stdout
    sys.stdout = devnull  # configure_...'s prints
    _, rrtc, plan_settings, simp_settings = vamp.configure_robot_and_planner_with_kwargs("panda", "rrtc")
    sys.stdout = real
    sampler = panda.halton()
    for family, index in request["problems"]:
        problem = scenes[family, index] | requests[family, index]
        answer = {"name": f"{family}/{index:04d}", "valid": bool(conv.test_problem(panda, problem)),
                  "solved": False, "plan_ns": 0, "simplify_ns": 0, "wall_ns": 0, "iterations": 0,
                  "initial_cost": None, "cost": None, "path": []}
        if answer["valid"]:
            env = vamp.problem_dict_to_vamp(problem)
            sampler.reset()
            t0 = time.perf_counter_ns()
            result = rrtc(problem["start"], problem["goals"], env, plan_settings, sampler)
            simple = panda.simplify(result.path, env, simp_settings, sampler) if result.solved else None
            answer["wall_ns"] = time.perf_counter_ns() - t0
            answer["plan_ns"] = int(result.nanoseconds)
            answer["iterations"] = int(result.iterations)
            answer["solved"] = bool(result.solved)
            if simple is not None:
                answer["simplify_ns"] = int(simple.nanoseconds)
                answer["initial_cost"] = float(result.path.cost())
                answer["cost"] = float(simple.path.cost())
                answer["path"] = [[float(x) for x in q] for q in simple.path.numpy()]
                if request["limits"] is not None:
                    answer.update(_toppra(answer["path"], *request["limits"]))
        print(json.dumps(answer), flush=True)


def _toppra(path, v, a) -> dict:
    """The toppra timings of a waypoint path (module docstring)."""
    import numpy as np
    import toppra as ta
    import toppra.algorithm as talgo
    import toppra.constraint as tcon

    ta.setup_logging("WARNING")
    y = np.asarray(path, dtype=float)
    v, a = np.asarray(v, dtype=float), np.asarray(a, dtype=float)

    def timed(knots, points, bc):
        cons = [tcon.JointVelocityConstraint(np.stack([-v, v], 1)),
                tcon.JointAccelerationConstraint(np.stack([-a, a], 1))]
        return talgo.TOPPRA(cons, ta.SplineInterpolator(knots, points, bc_type=bc),
                            parametrizer="ParametrizeConstAccel").compute_trajectory(0, 0)

    seg = np.linalg.norm(np.diff(y, axis=0), axis=1)
    stop, qdd = 0.0, []
    for k in np.nonzero(seg > 0)[0]:
        tr = timed([0.0, 1.0], y[k:k + 2], "not-a-knot")  # two points: the straight segment
        stop += tr.duration
        qdd.append(tr(np.arange(0.0, tr.duration, 1e-3), 2))
    rest = np.zeros((1, y.shape[1]))
    qdd = np.concatenate([rest] + qdd + [rest])  # at rest (q̈ = 0) before the start and after the goal
    knots = np.concatenate([[0.0], np.cumsum(seg)])
    keep = np.concatenate([[True], seg > 0])
    spline = timed(knots[keep], y[keep], "clamped").duration if keep.sum() > 1 else 0.0
    return {"toppra_stop_s": float(stop), "toppra_spline_s": float(spline), "length": float(seg.sum()),
            "jerk_max": float(np.abs(np.diff(qdd, axis=0)).max() / 1e-3) if len(qdd) > 1 else 0.0}


if __name__ == "__main__":
    if sys.argv[1:] == ["--child"]:
        _child()
    else:
        raise SystemExit("usage: python peers_vamp.py --child  (JSON request on stdin; see solve_vamp)")
