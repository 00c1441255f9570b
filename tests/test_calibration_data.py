"""Issue 30's calibration seams: one measurement reader by header (data_io), the joint count checked against
the robot, one rigidity rule for measured poses, gradient calibration with joint readings that require grad,
calibrate_batch's honesty on degenerate data, the robust loss with its outlier report.

References: the chains' own forward kinematics (the simulated "true" robot), the CLI's error convention.
"""

from __future__ import annotations

import contextlib
import io

import numpy as np
import pytest
import torch

from diffkin import models
from diffkin.calibration import calibrate_from_files, load_measurements
from diffkin.cli import main
from diffkin.errors import ShapeError

F64 = torch.float64


def _cli(*args) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in args])
    return rc, out.getvalue(), err.getvalue()


def _fk_csv(tmp_path, robot: str, n: int = 12):
    """``diffkin fk``'s CSV (header q1..qn,x,y,z,qw,qx,qy,qz) of ``n`` random configurations."""
    path = tmp_path / f"{robot}_measurements.csv"
    rc, _, err = _cli("fk", "--robot", robot, "--random", n, "--seed", 3, "--output", path)
    assert rc == 0, err
    return path


# ------------------------------------------------------------------------------------------ item 1
def test_cli_calibrate_refuses_data_of_another_joint_count(tmp_path):
    data = _fk_csv(tmp_path, "panda")  # 7 joint columns, a 6-joint robot
    rc, out, err = _cli("calibrate", "--robot", "ur5", "--data", data, "--output", tmp_path / "cal.yaml")
    assert rc == 2, out + err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "7" in lines[0] and "6" in lines[0] and "joint" in lines[0], err
    assert not (tmp_path / "cal.yaml").exists()
    with pytest.raises(ShapeError, match=r"7 joint.*6 joints"):
        calibrate_from_files("ur5", data, progress=False)
    np.savez(tmp_path / "m.npz", q=np.zeros((5, 7)), T=np.tile(np.eye(4), (5, 1, 1)))
    with pytest.raises(ShapeError, match=r"7 joint.*6 joints"):
        calibrate_from_files("ur5", tmp_path / "m.npz", progress=False)


# ------------------------------------------------------------------------------------------ item 2
def test_load_measurements_reads_fk_csv_by_header(tmp_path):
    data = _fk_csv(tmp_path, "panda", 9)
    q, T = load_measurements(data)
    assert q.shape == (9, 7) and T.shape == (9, 4, 4)
    chain = models.load("panda", dtype=F64)
    torch.testing.assert_close(chain.forward_kinematics(q).detach(), T, atol=1e-7, rtol=0)
    # the same reader as the CLI's calibrate (calibrate_from_files): the same arrays
    from diffkin.data_io import read_measurements

    q2, T2, position_only = read_measurements(data, n_joints=7)
    assert not position_only
    torch.testing.assert_close(q2, q)
    torch.testing.assert_close(T2, T)
    # positions only: x,y,z without a quaternion
    (tmp_path / "p.csv").write_text("q1,q2,x,y,z\n0.1,0.2,1,2,3\n0.3,0.4,4,5,6\n")
    q, p = load_measurements(tmp_path / "p.csv")
    assert q.shape == (2, 2) and p.shape == (2, 3)
    np.testing.assert_array_equal(p.numpy(), [[1, 2, 3], [4, 5, 6]])
    # a header that names q1..q3 read as a 2-joint robot's data: refused with both counts
    (tmp_path / "q3.csv").write_text("q1,q2,q3,x,y,z\n0,0,0,1,2,3\n")
    with pytest.raises(ShapeError, match=r"3 joint.*2 joints"):
        read_measurements(tmp_path / "q3.csv", n_joints=2)
