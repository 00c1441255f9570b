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
    assert "--urdf" in line and "from_mjcf" in line, line


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
