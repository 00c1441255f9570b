"""``diffkin retarget`` (issue 37): a shipped clip onto the 29-DoF G1, written as NPZ and CSV."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from diffkin.cli import main

G1_URDF = Path(__file__).parent / "data" / "urdf" / "g1_29dof_rev_1_0.urdf"


def test_retarget_cli_npz_and_csv(tmp_path, capsys):
    out = tmp_path / "hop.npz"
    fast = ["--frames", "0:6", "--warm-start", "batched"]
    assert main(["retarget", "hop", "--mapping", "g1", "--urdf", str(G1_URDF), *fast, "--iterations", "2",
                 "--output", str(out)]) == 0
    text = capsys.readouterr().out
    assert "stage one" in text and "whole clip" in text and "6 frames" in text
    z = np.load(out)
    assert z["q"].shape == (1, 6, 36) and z["contacts"].shape == (1, 6, 2) and float(z["fps"]) == 60.0
    assert len(z["joint_names"]) == 29 and np.isfinite(z["q"]).all()
    csv = tmp_path / "hop.csv"
    assert main(["retarget", "hop", "--urdf", str(G1_URDF), *fast, "--iterations", "0",
                 "--output", str(csv)]) == 0
    header = csv.read_text().splitlines()[0].split(",")
    rows = np.loadtxt(csv, delimiter=",", skiprows=1)
    assert header[:3] == ["clip", "frame", "t"] and header[-2:] == ["contact_0", "contact_1"]
    assert rows.shape == (6, 3 + 36 + 2)
    np.testing.assert_allclose(rows[:, 2], np.arange(6) / 60.0)


def test_retarget_cli_robot_by_name_writes_the_librarys_clip(tmp_path, capsys):
    """``--robot g1`` (Menagerie's current G1, shipped) writes exactly what retarget.clip returns."""
    import torch

    from diffkin import models, retarget

    out = tmp_path / "hop.npz"
    assert main(["retarget", "hop", "--mapping", "g1", "--robot", "g1", "--frames", "0:5",
                 "--iterations", "0", "--output", str(out)]) == 0
    mp = retarget.Mapping.builtin("g1")
    chain = models.load("g1", dtype=torch.float64, end_link=mp.frames)
    hop = retarget.load_bvh(retarget.example_clips()["hop"]).frames_slice(0, 5)
    ref = retarget.clip(chain, hop, mp, whole_clip=False)
    np.testing.assert_array_equal(np.load(out)["q"], ref.q.numpy())


@pytest.mark.parametrize("argv, message", [
    (["nothing.txt"], "shipped clip"),
    (["hop", "--frames", "5:5"], "no frame"),
    (["hop", "--frames", "a:b"], "START:STOP"),
])
def test_retarget_cli_errors(tmp_path, capsys, argv, message):
    code = main(["retarget", *argv, "--urdf", str(G1_URDF), "--output", str(tmp_path / "x.npz")])
    assert code != 0
    assert message in capsys.readouterr().err


def test_retarget_help_has_a_description_defaults_and_an_example(capsys):
    assert main(["retarget", "--help"]) == 0
    out = capsys.readouterr().out
    assert "Retarget a human clip" in out and "diffkin retarget walk" in out[out.index("examples:"):]
    assert "--threads" in out and "(default: " in out


@pytest.mark.extended
def test_demo_retarget_section(tmp_path):
    """The demo's retargeting section (about 10 s): the table, the frame picture and the sole-height
    figure, no failure."""
    from diffkin.demo import Report, section_retarget

    report = Report(tmp_path)
    section_retarget(report, quick=True)
    assert not report.failures
    text = report.sections[-1]
    assert "frame by frame (ik.solve)" in text and "| whole clip | 0 |" in text
    assert (tmp_path / "retarget_soles.png").stat().st_size > 10_000
    assert (tmp_path / "retarget_frame.png").stat().st_size > 10_000 and "retarget_frame.png" in text
