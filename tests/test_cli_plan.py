"""`diffkin plan` in-process on the FR3 (Franka's capsule collision model, as tests/test_motion.py) around
a sphere of a world file: the NPZ / CSV written (start and goal exact, at rest, within the URDF's velocity
limits and the acceleration limit given, clear of the sphere by the library's exact distances), bad input."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

import diffkin
from diffkin.cli import main
from diffkin.collision import RobotCollision, read_world

FR3 = Path(__file__).parent / "data" / "urdf" / "fr3.urdf"
SRDF = ('<robot name="fr3"><disable_collisions link1="fr3_link1_sc" link2="fr3_link3_sc" reason="Default"/>'
        '</robot>')
START = [0.8, 0.3, 0.0, -1.8, 0.0, 2.1, 0.785]
GOAL = [-0.8, 0.3, 0.0, -1.8, 0.0, 2.1, 0.785]  # the straight line passes through the sphere
V = [2.0, 1.0, 1.5, 1.25, 3.0, 1.5, 3.0]  # fr3.urdf's <limit velocity=> of fr3_joint1..7


MOVEIT = """\
name: one ball
allowed_collision_matrix:
  entry_names: [fr3_link1_sc, fr3_link3_sc]
  entry_values:
    - [false, true]
    - [true, false]
world:
  collision_objects:
    - id: ball
      primitives: [{type: sphere, dimensions: [0.12]}]
      primitive_poses: [{position: [0.5, 0.0, 0.45], orientation: [0, 0, 0, 1]}]
"""  # the same sphere and pair rule as a MoveIt PlanningScene


@pytest.fixture
def files(tmp_path):
    (tmp_path / "fr3.srdf").write_text(SRDF)
    (tmp_path / "world.yaml").write_text("spheres: [[0.5, 0.0, 0.45, 0.12]]\n")
    (tmp_path / "scene.yaml").write_text(MOVEIT)
    return tmp_path


def _args(d: Path, *extra: str) -> list[str]:
    return ["plan", "--urdf", str(FR3), "--end-link", "fr3_link8", "--srdf", str(d / "fr3.srdf"),
            "--scene", str(d / "world.yaml"), "--acceleration-limit", "5", "--resolution", "0.01", *extra]


def test_plan_writes_npz_around_a_sphere(files, capsys):
    starts = np.array([START, [0.7, 0.2, 0.1, -1.9, 0.0, 2.0, 0.6], [3.0, *START[1:]]])
    np.save(files / "q0.npy", starts)
    out = files / "plan.npz"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc = main(_args(files, "--start-file", str(files / "q0.npy"), "--goal", *map(str, GOAL),
                        "--output", str(out), "--plot", str(files / "plan.png")))
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "problem 0: success" in text and "problem 1: success" in text and "planned 2 of 3" in text
    assert "problem 2: FAILED: start outside the joint limits" in text
    assert (files / "plan.png").stat().st_size > 10_000
    z = np.load(out)
    t, q, qd, qdd = z["t"], z["q"], z["qd"], z["qdd"]
    B, S, nq = q.shape
    assert (B, nq) == (3, 7) and t.shape == (3, S) and qd.shape == qdd.shape == q.shape
    assert z["success"].tolist() == [True, True, False] and list(z["reason"][:2]) == ["", ""]
    assert "start outside" in z["reason"][2] and z["duration"][2] == 0 and (q[2] == starts[2]).all()
    q, qd, qdd, t = q[:2], qd[:2], qdd[:2], t[:2]
    assert np.array_equal(q[:, 0], starts[:2]) and np.array_equal(q[:, -1], np.array([GOAL, GOAL]))
    assert np.abs(qd[:, [0, -1]]).max() == 0 and np.abs(qdd[:, [0, -1]]).max() == 0
    assert (np.abs(qd) <= np.array(V) * (1 + 1e-9)).all() and (np.abs(qdd) <= 5.0 * (1 + 1e-9)).all()
    assert np.allclose(np.diff(t, axis=1), 0.01) and (z["duration"][:2] > 0.5).all()
    assert list(z["joint_names"]) == [f"fr3_joint{i}" for i in range(1, 8)]
    # the motion detours: the straight line hits the sphere, every written sample clears it
    chain = diffkin.models.from_urdf(FR3, "fr3_link8", dtype=torch.float64).requires_grad_(False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        robot = RobotCollision.from_urdf(FR3, chain, srdf=SRDF).requires_grad_(False)
    world = read_world(files / "world.yaml", dtype=torch.float64)
    line = torch.tensor(START) + torch.linspace(0, 1, 50)[:, None].double() * torch.tensor(
        [g - s for g, s in zip(GOAL, START)])
    assert robot.min_distance(line, world).min() < 0
    assert robot.min_distance(torch.as_tensor(q), world).min() >= 0


def test_plan_csv_moveit_scene_and_bad_input(files, capsys):
    out = files / "plan.csv"
    base = ["plan", "--robot", "fr3", "--scene", str(files / "scene.yaml"), "--acceleration-limit", "5",
            "--resolution", "0.01", "--start", *map(str, START), "--goal", *map(str, GOAL)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # the ACM's pair rule is the SRDF's: without it the FR3's capsules touch at the start
        assert main([*base, "--output", str(out), "--dt", "0.02"]) == 0, capsys.readouterr()
        assert "problem 0: success" in capsys.readouterr().out
        (files / "scene.yaml").write_text(MOVEIT.replace("true", "false"))
        assert main([*base, "--output", str(files / "other.npz")]) == 0
    assert "problem 0: FAILED: start in collision" in capsys.readouterr().out
    header = out.read_text().splitlines()[0].split(",")
    assert header[:3] == ["problem", "success", "t"] and len(header) == 3 + 3 * 7
    rows = np.loadtxt(out, delimiter=",", skiprows=1)
    assert (rows[:, 0] == 0).all() and (rows[:, 1] == 1).all()
    assert np.allclose(np.diff(rows[:, 2]), 0.02)
    assert np.array_equal(rows[0, 3:10], START) and np.array_equal(rows[-1, 3:10], GOAL)
    assert np.abs(rows[-1, 10:]).max() == 0  # at rest at the end
    capsys.readouterr()
    bad = [
        (["--start", "0", "0", "--goal", *map(str, GOAL), "--output", str(out)], "expected 7 joint values"),
        (["--goal", *map(str, GOAL), "--output", str(out)], "--start"),
        (["--start", *map(str, START), "--goal", *map(str, GOAL), "--output", str(files / "x.txt")], "x.txt"),
        (["--start", *map(str, START), "--goal", *map(str, GOAL), "--output", str(out), "--velocity-limit",
          "1", "2"], "one value or 7"),
    ]
    for extra, needle in bad:
        assert main(_args(files, *extra)) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("error:") and needle in err and "\n" not in err, err
    # argparse: a missing required option, a non-positive limit
    assert main(["plan", "--robot", "fr3", "--output", str(out)]) == 2
    assert main(_args(files, "--acceleration-limit", "-1", "--output", str(out))) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 1 and "acceleration-limit" in err


@pytest.mark.extended
def test_demo_motion_section(tmp_path):
    """The demo's motion-planning section (about 5 s): the table and the q/q̇/q̈ figure, no failure."""
    from diffkin.demo import Report, section_motion

    report = Report(tmp_path)
    section_motion(report, quick=True)
    assert report.failures == [] and "| success | True |" in report.sections[-1]
    assert (tmp_path / "motion_plan.png").stat().st_size > 10_000


def _pin_pose(q: np.ndarray) -> np.ndarray:
    """fr3_link8's pose (4, 4) at q by Pinocchio (the reference for the pose goals)."""
    pin = pytest.importorskip("pinocchio")
    model = pin.buildModelFromUrdf(str(FR3))
    data = model.createData()
    pin.framesForwardKinematics(model, data, np.asarray(q, np.float64))
    return data.oMf[model.getFrameId("fr3_link8")].homogeneous


def test_plan_pose_goals_from_the_command_line_and_a_file(files, capsys):
    """--goal-pose x y z qw qx qy qz and --goal-pose-file: plan's pose goals (collision-free IK, then the
    search around the sphere); the motions end at rest where Pinocchio puts fr3_link8 on the goal pose."""
    from scipy.spatial.transform import Rotation

    T = _pin_pose(GOAL)
    w_xyz = np.roll(Rotation.from_matrix(T[:3, :3]).as_quat(), 1)  # scipy: x y z w → w x y z
    out = files / "pose.npz"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pose = [f"{x:.15f}" for x in (*T[:3, 3], *w_xyz)]  # argparse: "-1e-16" would read as an option
        rc = main(_args(files, "--start", *map(str, START), "--goal-pose", *pose, "--output", str(out)))
    assert rc == 0 and "problem 0: success" in capsys.readouterr().out
    z = np.load(out)
    assert z["success"].all()
    q_end = z["q"][0, -1]
    assert np.array_equal(q_end, z["q_goal"][0]) and np.abs(z["qd"][0, -1]).max() == 0
    got = _pin_pose(q_end)
    assert np.abs(got[:3, 3] - T[:3, 3]).max() < 1e-4
    assert Rotation.from_matrix(got[:3, :3].T @ T[:3, :3]).magnitude() < 1e-3
    # a file of two (4, 4) goal poses for two starts
    poses = np.stack([T, _pin_pose([-0.6, 0.2, 0.0, -1.9, 0.0, 2.0, 0.6])])
    np.save(files / "T.npy", poses)
    np.save(files / "q0.npy", np.array([START, START]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(_args(files, "--start-file", str(files / "q0.npy"), "--goal-pose-file",
                          str(files / "T.npy"), "--output", str(out))) == 0
    z = np.load(out)
    assert z["success"].all() and z["q"].shape[0] == 2
    for b in range(2):
        assert np.abs(_pin_pose(z["q"][b, -1])[:3, 3] - poses[b, :3, 3]).max() < 1e-4
    capsys.readouterr()
    for extra, needle in [(["--goal-pose", "0.5", "0", "0.5", "1", "0", "0"], "7 numbers"),
                          (["--goal", *map(str, GOAL), "--goal-pose", *["0"] * 7], "exactly one of")]:
        assert main(_args(files, "--start", *map(str, START), *extra, "--output", str(out))) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("error:") and needle in err, err


PROBLEMS = np.array([START, [0.7, 0.2, 0.1, -1.9, 0.0, 2.0, 0.6], [0.0, 0.3, 0.0, -2.0, 0.0, 2.1, 0.785],
                     [-0.5, 0.0, 0.0, -1.5, 0.0, 1.8, 0.0]])  # 2 detour the sphere, 1 starts in it, 1 is free


def test_plan_chunks_are_seeded_by_their_first_row_so_shards_equal_one_run(files):
    """plan_rows (the stream run_sharded shards): rows [2, 4) planned alone equal those rows of the whole
    batch (chunk [a, b) seeded from (seed, a)); the two shards' parts merged (joint names once) are the
    single file wherever the shards' time grids agree, the tail of the shorter one resting at its goal."""
    from diffkin.cli.plan import plan_rows
    from diffkin.io import distributed as dist

    chain = diffkin.models.from_urdf(FR3, "fr3_link8", dtype=torch.float64).requires_grad_(False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        robot = RobotCollision.from_urdf(FR3, chain, srdf=SRDF).requires_grad_(False)
    world = read_world(files / "world.yaml", dtype=torch.float64)
    q0 = torch.as_tensor(PROBLEMS)
    problems = (q0, torch.tensor([GOAL] * 4, dtype=torch.float64))
    kw = dict(chunk_size=1, seed=3, collision=robot, world=world, resolution=0.01, acceleration_limit=5.0,
              joint_names=chain.joint_names)
    whole = plan_rows(chain, problems, files / "one.npz", **kw)
    out = files / "T.npz"
    parts = [plan_rows(chain, problems, dist.part_path(out, r, 2), start=a, stop=b, **kw)
             for r, (a, b) in enumerate(((0, 2), (2, 4)))]
    assert [p[:2] for p in whole.problems] == [(0, True), (1, True), (2, False), (3, True)]
    assert [p for s in parts for p in s.problems] == whole.problems  # durations, waypoints, reasons
    with np.load(dist.part_path(out, 1, 2)) as p1, np.load(files / "one.npz") as one:
        S = p1["q"].shape[1]
        assert S < one["q"].shape[1]
        assert np.array_equal(p1["q"], one["q"][2:, :S]) and np.array_equal(p1["qd"], one["qd"][2:, :S])
        assert (one["q"][3, S:] == GOAL).all() and (one["q"][2] == PROBLEMS[2]).all()
    dist.merge_parts(out, [dist.part_path(out, 0, 2)], constants=("joint_names",))
    with np.load(out) as m, np.load(files / "one.npz") as one:
        assert sorted(m.files) == sorted(one.files)
        assert list(m["joint_names"]) == list(one["joint_names"]) == chain.joint_names
        for k in ("q", "qd", "qdd", "t", "success", "duration", "reason", "q_goal"):
            assert np.array_equal(m[k], one[k][:2]), k


@pytest.mark.extended  # two torchrun processes and one in-process run (about 25 s on 2 cores)
def test_two_process_plan_equals_one_process(files, capsys):
    """torchrun, 2 gloo processes, 4 problems in chunks of 1: each rank plans its 2, every part on the
    longest motion's time grid, rank 0 merges; the file equals main()'s in one process entry for entry."""
    import os
    import subprocess
    import sys

    np.save(files / "q0.npy", PROBLEMS)
    args = _args(files, "--start-file", str(files / "q0.npy"), "--goal", *map(str, GOAL), "--chunk-size", "1",
                 "--seed", "3")
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2", "-m",
           "diffkin.cli", *args, "--output", "m.npz", "--merge"]
    run = subprocess.run(cmd, cwd=files, env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert run.stdout.count("planned 3 of 4") == 1 and "problem 2: FAILED: start in collision" in run.stdout
    assert not list(files.glob("m.part-*"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main([*args, "--output", str(files / "one.npz")]) == 0
    with np.load(files / "m.npz") as a, np.load(files / "one.npz") as b:
        assert sorted(a.files) == sorted(b.files) and a["q"].shape[:2] == (4, b["q"].shape[1])
        for k in b.files:
            assert np.array_equal(a[k], b[k]), k
