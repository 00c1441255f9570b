"""Issue 30's command-line boundaries: a URDF / MJCF file given where a model name goes points to the right
loader; ``diffkin ik --random N --output F`` stores its targets and sampled configurations.

References: the library's own FK (the targets of a random IK run are the FK of its sampled configurations).
"""

from __future__ import annotations

import contextlib
import io
import shutil
from pathlib import Path

import pytest

from diffkin import models
from diffkin.cli import main
from diffkin.errors import ModelError

DATA = Path(__file__).parent / "data" / "urdf"


def _cli(*args) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in args])
    return rc, out.getvalue(), err.getvalue()


def _one_error(rc: int, err: str) -> str:
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


# ------------------------------------------------------------------------------------------ item 5
@pytest.mark.parametrize("relative", [True, False])
def test_fk_robot_given_a_urdf_points_to_urdf(tmp_path, monkeypatch, relative):
    shutil.copy(DATA / "irb2400.urdf", tmp_path / "ur5.urdf")
    monkeypatch.chdir(tmp_path)
    robot = "ur5.urdf" if relative else str(tmp_path / "ur5.urdf")
    line = _one_error(*_cli("fk", "--robot", robot, "--random", "3")[::2])
    assert "--urdf" in line and "--end-link" in line, line
    assert "invalid YAML" not in line and "unknown model" not in line, line
    (tmp_path / "arm.xml").write_text("<mujoco/>")
    line = _one_error(*_cli("ik", "--robot", "arm.xml", "--random", "3")[::2])
    assert "--urdf" in line and "--mjcf FILE" in line, line


@pytest.mark.parametrize("name", ["x.xml", "robots/x.xml", "x.urdf", "robots/x.URDF", "x.mjcf"])
def test_models_load_points_to_the_file_loaders(name):
    with pytest.raises(ModelError) as info:
        models.load(name)
    text = str(info.value)
    assert "from_urdf" in text, text
    if not name.lower().endswith(".urdf"):
        assert "from_mjcf" in text, text
    assert "unknown model" not in text and "invalid YAML" not in text, text
    with pytest.raises(ModelError, match="from_urdf"):
        models.load(Path(name))


# ------------------------------------------------------------------------------------------ item 6
@pytest.mark.parametrize("suffix", [".npz", ".csv"])
def test_ik_random_output_stores_targets_and_sampled_configurations(tmp_path, suffix):
    import numpy as np
    import torch

    from diffkin.io.data import read_joints, read_poses

    out = tmp_path / f"ik{suffix}"
    rc, _, err = _cli("ik", "--robot", "ur5", "--random", 7, "--seed", 5, "--output", out)
    assert rc == 0, err
    chain = models.load("ur5", dtype=torch.float64)
    if suffix == ".npz":
        data = np.load(out)
        q_sampled, T_target = data["q_sampled"], data["T_target"]
        q = data["q"]
    else:
        import csv

        header = next(csv.reader(out.open()))
        assert header[:6] == [f"q{i}" for i in range(1, 7)], header
        cols = np.loadtxt(out, delimiter=",", skiprows=1)
        pick = [header.index(f"q_sampled{i}") for i in range(1, 7)]
        q_sampled = cols[:, pick]
        T_target = read_poses(out)[0].numpy()  # the target's x,y,z,qw,qx,qy,qz columns read as poses
        q = read_joints(out, 6).numpy()
    assert q_sampled.shape == (7, 6) and T_target.shape == (7, 4, 4)
    # the targets are the FK of the sampled configurations, drawn as `diffkin fk --random` draws them
    rc, _, err = _cli("fk", "--robot", "ur5", "--random", 7, "--seed", 5, "--output", tmp_path / "fk.npz")
    assert rc == 0, err
    fk = np.load(tmp_path / "fk.npz")
    np.testing.assert_allclose(q_sampled, fk["q"], atol=1e-12)
    np.testing.assert_allclose(T_target, fk["T"], atol=1e-9)
    reached = chain.forward_kinematics(torch.as_tensor(q)).detach().numpy()
    np.testing.assert_allclose(reached[:, :3, 3], T_target[:, :3, 3], atol=1e-3)
