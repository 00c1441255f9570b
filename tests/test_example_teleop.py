"""examples/teleop.py runs (short) and its limits hold: joint positions within their limits and |q̇| within
the velocity limits at every tick, the hand on its target (Panda and the floating-base G1)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

pytest.importorskip("mujoco")

_PATH = Path(__file__).resolve().parents[1] / "examples" / "teleop.py"


def _example():
    spec = importlib.util.spec_from_file_location("teleop_example", _PATH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("robot", ["panda", "g1"])
def test_teleop_example_runs_and_limits_hold(robot):
    r = _example().run(robot, seconds=0.3)
    assert r["steps"] == 150
    assert r["worst_limit_margin"] >= -1e-9  # never beyond a position limit
    assert r["max_speed_ratio"] <= 1 + 1e-9  # never above a velocity limit
    assert r["final_tracking_error_m"] < 5e-3
    assert r["feet_drift_m"] < 5e-3


def test_teleop_example_main_prints(capsys):
    assert _example().main(["--robot", "panda", "--seconds", "0.1"]) == 0
    out = capsys.readouterr().out
    assert "ticks at 500 Hz" in out and "worst joint-limit margin" in out


def test_demo_teleop_section(tmp_path):
    from diffkin.demo import Report, section_teleop

    report = Report(tmp_path)
    section_teleop(report, quick=True)
    assert not report.failures
    text = report.sections[-1]
    assert "Teleoperation rate" in text and "diffkin ik.solve_velocity (C step)" in text
    assert "(never negative)" in text
