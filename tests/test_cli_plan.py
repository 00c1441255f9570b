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
