"""End-to-end tests of the ``diffkin`` command, each run as a subprocess on small inputs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from diffkin import models

REPO = Path(__file__).resolve().parent.parent


def run_cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "diffkin.cli", *args],
        capture_output=True,
        text=True,
        cwd=cwd or REPO,
        timeout=300,
    )


def ok(proc: subprocess.CompletedProcess) -> str:
    assert proc.returncode == 0, f"exit {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    return proc.stdout


def fails_clearly(proc: subprocess.CompletedProcess, *needles: str) -> None:
    assert proc.returncode != 0, proc.stdout
    assert "Traceback" not in proc.stderr, proc.stderr
    for needle in needles:
        assert needle in proc.stderr, proc.stderr


def test_models_list_and_show():
    out = ok(run_cli("models"))
    for name in ("panda", "ur5", "kuka_iiwa14", "three_link_planar", "stanford"):
        assert name in out
    out = ok(run_cli("models", "show", "panda"))
    assert "0.333" in out and "0.088" in out and "modified" in out


def test_unknown_robot_is_a_clear_error():
    fails_clearly(run_cli("fk", "--robot", "no_such_robot", "--random", "3"), "no_such_robot")


def test_fk_on_a_file_matches_the_library(tmp_path):
    chain = models.load("panda", dtype=torch.float64)
    q = chain.random_configuration(20, generator=torch.Generator().manual_seed(3))
    np.save(tmp_path / "q.npy", q.numpy())
    ok(
        run_cli(
            "fk", "--robot", "panda", "--input", str(tmp_path / "q.npy"), "--output", str(tmp_path / "T.npz")
        )
    )
    with np.load(tmp_path / "T.npz") as data:
        T = data["T"]
    np.testing.assert_allclose(T, chain.forward_kinematics(q).detach().numpy(), atol=1e-12)


def test_fk_csv_round_trip(tmp_path):
    chain = models.load("ur5", dtype=torch.float64)
    q = chain.random_configuration(5, generator=torch.Generator().manual_seed(0)).numpy()
    np.savetxt(tmp_path / "q.csv", q, delimiter=",", header=",".join(f"q{i}" for i in range(6)), comments="")
    ok(
        run_cli(
            "fk", "--robot", "ur5", "--input", str(tmp_path / "q.csv"), "--output", str(tmp_path / "out.csv")
        )
    )
    lines = (tmp_path / "out.csv").read_text().splitlines()
    assert lines[0].startswith("q_0") and len(lines) == 6
    pos = np.loadtxt(tmp_path / "out.csv", delimiter=",", skiprows=1)[:, 6:9]
    ref = chain.forward_kinematics(torch.as_tensor(q))[:, :3, 3].detach().numpy()
    np.testing.assert_allclose(pos, ref, atol=1e-9)


def test_fk_wrong_column_count(tmp_path):
    np.save(tmp_path / "q.npy", np.zeros((4, 5)))
    fails_clearly(run_cli("fk", "--robot", "panda", "--input", str(tmp_path / "q.npy")), "(N, 7)", "(4, 5)")


def test_fk_bad_file(tmp_path):
    (tmp_path / "bad.csv").write_text("q1,q2\n1.0,abc\n")
    fails_clearly(run_cli("fk", "--robot", "panda", "--input", str(tmp_path / "bad.csv")), "bad.csv")
    fails_clearly(run_cli("fk", "--robot", "panda", "--input", str(tmp_path / "missing.npy")), "no such file")
    (tmp_path / "q.txt").write_text("0 0 0")
    fails_clearly(run_cli("fk", "--robot", "panda", "--input", str(tmp_path / "q.txt")), "unsupported")


def test_ik_on_a_file_reaches_targets(tmp_path):
    chain = models.load("panda", dtype=torch.float64)
    q = chain.random_configuration(16, generator=torch.Generator().manual_seed(1))
    np.save(tmp_path / "T.npy", chain.forward_kinematics(q).detach().numpy())
    out = ok(
        run_cli(
            "ik", "--robot", "panda", "--input", str(tmp_path / "T.npy"), "--output", str(tmp_path / "q.npz")
        )
    )
    assert "success" in out
    with np.load(tmp_path / "q.npz") as data:
        q_sol, success = torch.as_tensor(data["q"]), data["success"]
    assert success.all()
    T_sol = chain.forward_kinematics(q_sol)
    err = (T_sol[:, :3, 3].detach() - torch.as_tensor(np.load(tmp_path / "T.npy"))[:, :3, 3]).norm(dim=-1)
    assert float(err.max()) <= 1e-4


def test_ik_wrong_pose_layout(tmp_path):
    np.save(tmp_path / "T.npy", np.zeros((3, 5)))
    fails_clearly(run_cli("ik", "--robot", "panda", "--input", str(tmp_path / "T.npy")), "(N, 4, 4)")


def test_calibrate_writes_a_yaml_that_loads_back(tmp_path):
    nominal = models.load("ur5", dtype=torch.float64)
    true = nominal.copy()
    with torch.no_grad():
        true.a.add_(torch.linspace(-1e-3, 1e-3, 6, dtype=torch.float64))
    q = nominal.random_configuration(40, generator=torch.Generator().manual_seed(2))
    T = true.forward_kinematics(q).detach()
    np.savez(tmp_path / "meas.npz", q=q.numpy(), T=T.numpy())
    out_yaml = tmp_path / "cal.yaml"
    out = ok(
        run_cli(
            "calibrate", "--robot", "ur5", "--data", str(tmp_path / "meas.npz"), "--output", str(out_yaml)
        )
    )
    assert "position RMS" in out and "before" in out
    calibrated = models.load(str(out_yaml), dtype=torch.float64)
    err = (calibrated.forward_kinematics(q)[:, :3, 3] - T[:, :3, 3]).norm(dim=-1)
    assert float(err.max()) < 1e-6
    assert yaml.safe_load(out_yaml.read_text())["name"]


def test_calibrate_urdf_in_urdf_out_with_noise_check(tmp_path):
    from pathlib import Path

    from diffkin.models import from_urdf

    urdf = Path(__file__).parent / "data" / "urdf" / "irb2400.urdf"
    nominal = from_urdf(urdf, "tool0", dtype=torch.float64)
    true = nominal.copy()
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        u = torch.rand(true.origin_xyz.shape, generator=g, dtype=torch.float64)
        true.origin_xyz.add_(1e-3 * (2 * u - 1))
    q = nominal.random_configuration(40, generator=g)
    T = true.forward_kinematics(q).detach()
    np.savez(tmp_path / "meas.npz", q=q.numpy(), T=T.numpy())
    out_urdf = tmp_path / "cal.urdf"
    out = ok(run_cli("calibrate", "--urdf", str(urdf), "--end-link", "tool0", "--data",
                     str(tmp_path / "meas.npz"), "--tool", "--noise", "0.02", "0.005",
                     "--output", str(out_urdf)))
    assert "general" in out and "noise check" in out and "held-out" in out and "fit residual is" not in out
    calibrated = from_urdf(out_urdf, "tool0", dtype=torch.float64)
    err = (calibrated.forward_kinematics(q)[:, :3, 3] - T[:, :3, 3]).norm(dim=-1)
    assert float(err.max()) < 1e-9
    # a DH model's data written as URDF, or a URDF as YAML: a clear error
    fails_clearly(run_cli("calibrate", "--urdf", str(urdf), "--end-link", "tool0", "--data",
                          str(tmp_path / "meas.npz"), "--output", str(tmp_path / "c.yaml")), ".urdf")


def test_calibrate_mismatched_data(tmp_path):
    np.savez(tmp_path / "meas.npz", q=np.zeros((5, 6)), T=np.tile(np.eye(4), (4, 1, 1)))
    fails_clearly(
        run_cli(
            "calibrate",
            "--robot",
            "ur5",
            "--data",
            str(tmp_path / "meas.npz"),
            "--output",
            str(tmp_path / "c.yaml"),
        )
    )


def test_trajectory_joint_and_cartesian(tmp_path):
    ok(
        run_cli(
            "trajectory",
            "joint",
            "--profile",
            "quintic",
            "--start",
            "0",
            "0",
            "--end",
            "1",
            "-1",
            "--duration",
            "2",
            "--samples",
            "21",
            "--output",
            str(tmp_path / "j.npz"),
            "--plot",
            str(tmp_path / "j.png"),
        )
    )
    with np.load(tmp_path / "j.npz") as data:
        np.testing.assert_allclose(data["position"][0], [0, 0], atol=1e-12)
        np.testing.assert_allclose(data["position"][-1], [1, -1], atol=1e-12)
        np.testing.assert_allclose(data["velocity"][[0, -1]], 0, atol=1e-12)
    assert (tmp_path / "j.png").stat().st_size > 1000
    ok(
        run_cli(
            "trajectory",
            "cartesian",
            "--start",
            "0.3",
            "0",
            "0.5",
            "--end",
            "0.5",
            "0.1",
            "0.4",
            "--output",
            str(tmp_path / "c.csv"),
        )
    )
    rows = np.loadtxt(tmp_path / "c.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(rows[-1, 1:4], [0.5, 0.1, 0.4], atol=1e-12)


def test_trajectory_mismatched_vectors(tmp_path):
    fails_clearly(
        run_cli("trajectory", "joint", "--start", "0", "0", "--end", "1", "--output", str(tmp_path / "x.npz"))
    )


@pytest.mark.slow
def test_demo_quick(tmp_path):
    out = ok(run_cli("demo", "--quick", "--out", str(tmp_path / "demo")))
    report = (tmp_path / "demo" / "report.md").read_text()
    assert "IK" in report and "Calibration" in report and "CLIK" in report
    assert list((tmp_path / "demo").glob("*.png"))
    assert str(tmp_path / "demo") in out


@pytest.mark.slow
def test_train_then_evaluate(tmp_path):
    run_dir = tmp_path / "run"
    out = ok(
        run_cli(
            "train",
            "--config",
            "configs/ppo_batched_reach_panda.yaml",
            "--total-timesteps",
            "256",
            "--out",
            str(run_dir),
        )
    )
    results = json.loads((run_dir / "results.json").read_text())
    assert results["env_id"] == "diffkin/Reach-v0" and results["timesteps"] >= 256
    assert (run_dir / "model.zip").exists() and (run_dir / "config.yaml").exists() and "timesteps" in out
    ok(run_cli("evaluate", str(run_dir), "--episodes", "8"))
    evaluation = json.loads((run_dir / "evaluation.json").read_text())
    assert 0.0 <= evaluation["policy"]["success_rate"] <= 1.0
    assert evaluation["scripted_ik"]["success_rate"] >= 0.9


def test_train_missing_config_fails(tmp_path):
    proc = run_cli("train", "--config", str(tmp_path / "nope.yaml"))
    assert proc.returncode != 0


@pytest.mark.slow
def test_bench_prints_ratios():
    out = ok(run_cli("bench", "calibration", "--quick"))
    assert "calibrate_batch" in out and "ratio" in out
