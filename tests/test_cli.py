"""End-to-end tests of the ``diffkin`` command: a few as subprocesses, the rest through ``main([...])``."""

from __future__ import annotations

import contextlib
import io
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

import diffkin
from diffkin import models
from diffkin.cli import main

REPO = Path(__file__).resolve().parent.parent


def run_cli(*args: str) -> subprocess.CompletedProcess:
    """``diffkin ARGS`` in this process (seconds faster than a subprocess), as a CompletedProcess."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in args])
    return subprocess.CompletedProcess(["diffkin", *args], rc, out.getvalue(), err.getvalue())


def run_subprocess(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """``python -m diffkin.cli ARGS`` as a real subprocess (exit status, no traceback on stderr)."""
    return subprocess.run(
        [sys.executable, "-m", "diffkin.cli", *args],
        capture_output=True,
        text=True,
        cwd=cwd or REPO,
    )


def ok(proc: subprocess.CompletedProcess) -> str:
    assert proc.returncode == 0, f"exit {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    return proc.stdout


def fails_clearly(proc: subprocess.CompletedProcess, *needles: str) -> None:
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and proc.stderr.startswith("error: "), proc.stderr
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
    assert lines[0] == "q1,q2,q3,q4,q5,q6,x,y,z,qw,qx,qy,qz" and len(lines) == 6
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
    err = (calibrated.forward_kinematics(q)[:, :3, 3].detach() - T[:, :3, 3]).norm(dim=-1)
    assert float(err.max()) < 1e-6
    assert yaml.safe_load(out_yaml.read_text())["name"]
    # --output DIR: the robot and the report
    ok(run_cli("calibrate", "--robot", "ur5", "--data", str(tmp_path / "meas.npz"), "--cv", "0",
               "--output", str(tmp_path / "report")))
    assert sorted(p.name for p in (tmp_path / "report").iterdir()) == [
        "calibrated.yaml", "parameters.md", "report.json", "residuals.png"]
    again = models.load(str(tmp_path / "report" / "calibrated.yaml"), dtype=torch.float64)
    torch.testing.assert_close(again.a, calibrated.a)


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
    err = (calibrated.forward_kinematics(q)[:, :3, 3].detach() - T[:, :3, 3]).norm(dim=-1)
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
    out = ok(run_subprocess("demo", "--quick", "--output", str(tmp_path / "demo")))
    report = (tmp_path / "demo" / "report.md").read_text()
    assert "IK" in report and "Calibration" in report and "CLIK" in report
    assert list((tmp_path / "demo").glob("*.png"))
    assert str(tmp_path / "demo") in out


@pytest.mark.slow
def test_train_then_evaluate(tmp_path):
    run_dir = tmp_path / "run"
    out = ok(
        run_subprocess(
            "train",
            "--config",
            "configs/ppo.yaml",
            "--env",
            "diffkin/Reach-v0",
            "--variant",
            "cartesian",
            "--total-timesteps",
            "256",
            "--output",
            str(run_dir),
        )
    )
    results = json.loads((run_dir / "results.json").read_text())
    assert results["env_id"] == "diffkin/Reach-v0" and results["timesteps"] >= 256
    assert (run_dir / "model.zip").exists() and (run_dir / "config.yaml").exists() and "timesteps" in out
    ok(run_subprocess("evaluate", str(run_dir), "--episodes", "8"))
    evaluation = json.loads((run_dir / "evaluation.json").read_text())
    # the same evaluation computed here, independently of the command: the same episodes, the same numbers
    from diffkin.training.evaluate import evaluate_run

    torch.set_num_threads(1)
    again = evaluate_run(run_dir, 8)
    assert evaluation["policy"] == pytest.approx(again["policy"])
    assert evaluation["policy"]["episodes"] == 8
    successes = evaluation["policy"]["success_rate"] * 8
    assert successes == pytest.approx(round(successes))
    assert evaluation["scripted_ik"]["success_rate"] >= 0.9


def one_error(proc_or_rc, err: str, *needles: str) -> str:
    """Exit status 2 and exactly one line on stderr, ``error: ...``, holding every needle."""
    rc = proc_or_rc if isinstance(proc_or_rc, int) else proc_or_rc.returncode
    lines = err.strip().splitlines()
    assert rc == 2, (rc, err)
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def test_train_missing_config_fails(tmp_path):
    proc = run_subprocess("train", "--config", str(tmp_path / "nope.yaml"))
    one_error(proc, proc.stderr, "nope.yaml", "no such file")


def test_train_needs_an_entry_of_an_algorithm_file():
    proc = run_subprocess("train", "--config", "configs/sac.yaml")
    one_error(proc, proc.stderr, "configs/sac.yaml", "--env", "diffkin/Reach-v0:cartesian")
    proc = run_subprocess("train", "--config", "configs/sac.yaml", "--env", "diffkin/Reach-v0", "--variant=x")
    one_error(proc, proc.stderr, "no entry 'diffkin/Reach-v0:x'")


@pytest.mark.slow
def test_bench_prints_ratios():
    # the quickest suite with a peer in the same run (calibration's quick run took 50 s of the suite)
    out = ok(run_subprocess("bench", "jacobian", "--quick"))
    assert "geometric_jac" in out and "ratio_pk_over" in out


# ------------------------------------------------------------------------- in-process: main([...])
def run_main(capsys, *args: str) -> tuple[int, str, str]:
    capsys.readouterr()
    rc = main([str(a) for a in args])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def test_version():
    proc = run_subprocess("--version")
    lines = proc.stdout.strip().splitlines()
    assert proc.returncode == 0 and lines[0] == f"diffkin {diffkin.__version__}"
    assert len(lines) == 2 and lines[1].startswith("fused C kernel: ")  # in use (path) / not in use: why


COMMANDS = ["models", "fk", "ik", "calibrate", "trajectory", "train", "evaluate", "bench", "demo", "doctor",
            "plan"]


@pytest.mark.parametrize("command", COMMANDS)
def test_help_has_a_description_defaults_and_an_example(capsys, command):
    rc, out, _ = run_main(capsys, command, "--help")
    assert rc == 0
    usage_end = out.index("\n\n")
    description = out[usage_end:].strip().split("\n\n")[0]
    assert len(description) > 40 and not description.startswith("options")
    examples = out[out.index("examples:"):]
    assert f"diffkin {command}" in examples
    assert "--threads" in out
    if command not in ("models", "evaluate", "train", "demo", "doctor"):
        assert "(default: " in out


def test_help_states_the_defaults(capsys):
    _, out, _ = run_main(capsys, "ik", "--help")
    flat = " ".join(out.split())
    from diffkin.io.streaming import IK_CHUNK_SIZE

    chunk = "--chunk-size N rows per chunk (memory grows with it, not with the input)"
    assert f"{chunk} (default: {IK_CHUNK_SIZE})" in flat
    assert "(default: 0.0001)" in flat and "(default: 64)" in flat and "(default: 0)" in flat
    assert "default: 1" in flat  # --threads policy


def test_every_compute_command_takes_threads(capsys, monkeypatch):
    parser = diffkin.cli.build_parser()
    for command in COMMANDS:
        extra = {"fk": ["--random", "1"], "ik": ["--random", "1"],
                 "calibrate": ["--data", "x", "--output", "y"],
                 "trajectory": ["joint", "--output", "x.npz"], "train": ["--config", "x"],
                 "evaluate": ["run"],
                 "plan": ["--acceleration-limit", "5", "--output", "x.npz"]}.get(command, [])
        assert parser.parse_args([command, "--threads", "3", *extra]).threads == 3
        assert parser.parse_args(["--threads", "2", command, *extra]).threads == 2
    # the default is one thread (not torch's all-cores default); --threads N sets N
    calls = []
    monkeypatch.setattr(torch, "set_num_threads", calls.append)
    run_main(capsys, "fk", "--robot", "ur5", "--random", "2")
    run_main(capsys, "--threads", "2", "fk", "--robot", "ur5", "--random", "2")
    assert calls == [1, 2]


def _bad_files(tmp_path: Path) -> dict[str, Path]:
    f = {}
    f["empty"] = tmp_path / "empty.npy"
    np.save(f["empty"], np.zeros((0, 7)))
    f["garbage"] = tmp_path / "garbage.npz"
    f["garbage"].write_bytes(b"PK\x03\x04 this is not a zip file")
    f["mismatch"] = tmp_path / "mismatch.npz"
    np.savez(f["mismatch"], position=np.zeros((5, 3)), quaternion=np.tile([1.0, 0, 0, 0], (4, 1)))
    f["file"] = tmp_path / "a_file"
    f["file"].write_text("x")
    f["nan"] = tmp_path / "nan.npy"
    q = np.zeros((4, 7))
    q[2, 3] = np.nan
    np.save(f["nan"], q)
    return f


ERROR_CASES = {
    "random -1": (["fk", "--robot", "panda", "--random", "-1"], ["--random", "-1"]),
    "random 0": (["ik", "--robot", "panda", "--random", "0"], ["--random", "positive"]),
    "num-seeds 0": (["ik", "--robot", "panda", "--random", "2", "--num-seeds", "0"], ["--num-seeds"]),
    "chunk-size 0": (["fk", "--robot", "panda", "--random", "2", "--chunk-size", "0"], ["--chunk-size"]),
    "samples 0": (["trajectory", "joint", "--start", "0", "--end", "1", "--samples", "0", "--output",
                   "{tmp}/t.npz"], ["--samples"]),
    "tolerance nan": (["ik", "--robot", "panda", "--random", "2", "--position-tolerance", "nan"],
                      ["--position-tolerance", "nan"]),
    "tolerance inf": (["ik", "--robot", "panda", "--random", "2", "--orientation-tolerance", "inf"],
                      ["--orientation-tolerance"]),
    "start nan": (["trajectory", "joint", "--start", "nan", "--end", "1", "--output", "{tmp}/t.npz"],
                  ["--start"]),
    "duration -1": (["trajectory", "joint", "--start", "0", "--end", "1", "--duration", "-1", "--output",
                     "{tmp}/t.npz"], ["--duration"]),
    "noise nan": (["calibrate", "--robot", "ur5", "--data", "{tmp}/m.npz", "--noise", "nan", "1", "--output",
                   "{tmp}/c.yaml"], ["--noise"]),
    "no input": (["fk", "--robot", "panda"], ["--input", "--random"]),
    "empty npy": (["fk", "--robot", "panda", "--input", "{empty}"], ["empty.npy", "empty"]),
    "garbage npz": (["ik", "--robot", "panda", "--input", "{garbage}"], ["garbage.npz", "not a valid .npz"]),
    "mismatched arrays": (["ik", "--robot", "panda", "--input", "{mismatch}"], ["5 rows", "4"]),
    "nan in file": (["fk", "--robot", "panda", "--input", "{nan}"], ["nan.npy", "row 3", "NaN"]),
    "output under a file": (["fk", "--robot", "panda", "--random", "2", "--output", "{file}/T.npy"],
                            ["a_file", "not a directory"]),
    "output is a directory": (["fk", "--robot", "panda", "--random", "2", "--output", "{tmp}"],
                              ["directory"]),
    "trajectory output under a file": (["trajectory", "joint", "--start", "0", "--end", "1", "--output",
                                        "{file}/t.csv"], ["a_file"]),
    "bad output type": (["fk", "--robot", "panda", "--random", "2", "--output", "{tmp}/T.txt"], [".txt"]),
    "train missing config": (["train", "--config", "{tmp}/nope.yaml"], ["nope.yaml", "no such file"]),
    "evaluate missing run": (["evaluate", "{tmp}/no_run"], ["no_run", "no such run directory"]),
    "unknown robot": (["ik", "--robot", "nobot", "--random", "2"], ["nobot"]),
    "urdf without end link": (["fk", "--urdf", "x.urdf", "--random", "2"], ["--end-link"]),
    "calibrate missing data": (["calibrate", "--robot", "ur5", "--data", "{tmp}/none.npz", "--output",
                                "{tmp}/c.yaml"], ["none.npz", "no such file"]),
    "cv 1": (["calibrate", "--robot", "ur5", "--data", "{tmp}/m.npz", "--cv", "1", "--output",
              "{tmp}/c.yaml"], ["--cv"]),
    "unknown option": (["fk", "--robot", "panda", "--random", "2", "--frobnicate"], ["--frobnicate"]),
}


@pytest.mark.parametrize("case", list(ERROR_CASES))
def test_every_failure_is_one_error_line_and_exit_2(capsys, tmp_path, case):
    argv, needles = ERROR_CASES[case]
    paths = {k: str(v) for k, v in _bad_files(tmp_path).items()}
    argv = [a.format(tmp=tmp_path, **paths) for a in argv]
    rc, _, err = run_main(capsys, *argv)
    one_error(rc, err, *needles)


def test_bench_cuda_without_cuda_is_an_error(capsys, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    rc, _, err = run_main(capsys, "bench", "fk", "--device", "cuda")
    one_error(rc, err, "CUDA")
    rc, _, err = run_main(capsys, "fk", "--robot", "panda", "--random", "2", "--device", "cuda")
    one_error(rc, err, "CUDA")


def test_library_errors_and_os_errors_become_one_line(capsys, tmp_path, monkeypatch):
    from diffkin.errors import NonFiniteError

    def boom(*a, **k):
        raise NonFiniteError("q holds NaN\nat row 3")

    monkeypatch.setattr("diffkin.io.streaming.stream_fk", boom)
    rc, _, err = run_main(capsys, "fk", "--robot", "panda", "--random", "2")
    assert one_error(rc, err) == "error: q holds NaN at row 3"

    def denied(*a, **k):
        raise PermissionError(13, "Permission denied", "/root/x.npy")

    monkeypatch.setattr("diffkin.io.streaming.stream_fk", denied)
    rc, _, err = run_main(capsys, "fk", "--robot", "panda", "--random", "2")
    assert one_error(rc, err) == "error: /root/x.npy: Permission denied"

    def bug(*a, **k):
        raise RuntimeError("something internal")

    monkeypatch.setattr("diffkin.io.streaming.stream_fk", bug)
    rc, _, err = run_main(capsys, "fk", "--robot", "panda", "--random", "2")
    assert rc == 1 and err.count("\n") == 1 and err.startswith("error: internal error: RuntimeError")
    with pytest.raises(RuntimeError):
        main(["--debug", "fk", "--robot", "panda", "--random", "2"])


def test_errors_in_a_subprocess_have_no_traceback(tmp_path):
    files = _bad_files(tmp_path)
    proc = run_subprocess("ik", "--robot", "panda", "--input", str(files["garbage"]))
    one_error(proc, proc.stderr, "garbage.npz")


def test_fk_npy_holds_the_poses(capsys, tmp_path):
    chain = models.load("panda", dtype=torch.float64)
    q = chain.random_configuration(37, generator=torch.Generator().manual_seed(5))
    np.save(tmp_path / "q.npy", q.numpy())
    rc, out, _ = run_main(capsys, "fk", "--robot", "panda", "--input", tmp_path / "q.npy", "--output",
                          tmp_path / "T.npy", "--chunk-size", "10")
    assert rc == 0 and "37 configurations" in out
    T = np.load(tmp_path / "T.npy")
    assert T.shape == (37, 4, 4) and T.dtype == np.float64
    np.testing.assert_allclose(T, chain.forward_kinematics(q).detach().numpy(), rtol=0, atol=1e-13)
    # float32: a float32 file of the float32 chain's poses
    rc, _, _ = run_main(capsys, "fk", "--robot", "panda", "--input", tmp_path / "q.npy", "--dtype", "float32",
                        "--output", tmp_path / "T32.npy")
    T32 = np.load(tmp_path / "T32.npy")
    assert T32.dtype == np.float32
    np.testing.assert_allclose(T32, T, atol=2e-6)


def test_fk_npz_and_csv_columns(capsys, tmp_path):
    chain = models.load("ur5", dtype=torch.float64)
    assert run_main(capsys, "fk", "--robot", "ur5", "--random", "9", "--seed", "4", "--output",
                    tmp_path / "fk.npz")[0] == 0
    assert run_main(capsys, "fk", "--robot", "ur5", "--random", "9", "--seed", "4", "--output",
                    tmp_path / "fk.csv")[0] == 0
    with np.load(tmp_path / "fk.npz") as d:
        assert sorted(d.files) == ["T", "position", "q", "quaternion"]
        q, T, pos, quat = d["q"], d["T"], d["position"], d["quaternion"]
    np.testing.assert_allclose(T, chain.forward_kinematics(torch.as_tensor(q)).detach().numpy(), atol=1e-13)
    np.testing.assert_array_equal(pos, T[:, :3, 3])
    from diffkin.rotations import quaternion_to_matrix

    np.testing.assert_allclose(quaternion_to_matrix(torch.as_tensor(quat)).numpy(), T[:, :3, :3], atol=1e-12)
    lines = (tmp_path / "fk.csv").read_text().splitlines()
    assert lines[0] == "q1,q2,q3,q4,q5,q6,x,y,z,qw,qx,qy,qz" and len(lines) == 10
    rows = np.loadtxt(tmp_path / "fk.csv", delimiter=",", skiprows=1)
    np.testing.assert_array_equal(rows, np.concatenate([q, pos, quat], axis=1))  # %.17g: exact round trip


def test_ik_reads_fk_csv_and_recovers_the_poses(capsys, tmp_path):
    chain = models.load("panda", dtype=torch.float64)
    assert run_main(capsys, "fk", "--robot", "panda", "--random", "12", "--seed", "7", "--output",
                    tmp_path / "fk.csv")[0] == 0
    rc, out, err = run_main(capsys, "ik", "--robot", "panda", "--input", tmp_path / "fk.csv", "--output",
                            tmp_path / "ik.npz")
    assert rc == 0, err
    with np.load(tmp_path / "ik.npz") as d:
        q, success = torch.as_tensor(d["q"]), d["success"]
    rows = np.loadtxt(tmp_path / "fk.csv", delimiter=",", skiprows=1)
    T = chain.forward_kinematics(q).detach().numpy()
    np.testing.assert_allclose(T[:, :3, 3], rows[:, 7:10], atol=1e-4)
    from diffkin.rotations import quaternion_to_matrix

    R_target = quaternion_to_matrix(torch.as_tensor(rows[:, 10:14])).numpy()
    cos = (np.einsum("nij,nij->n", T[:, :3, :3], R_target) - 1) / 2
    assert np.arccos(np.clip(cos, -1, 1)).max() <= 1e-3
    assert success.all()
    assert "full pose" in out and "failures" in out


def test_ik_position_only_file_and_summary(capsys, tmp_path):
    (tmp_path / "xyz.csv").write_text("x,y,z\n0.4,0.1,0.5\n0.3,-0.2,0.6\n10.0,0.0,0.0\n")
    rc, out, _ = run_main(capsys, "ik", "--robot", "panda", "--input", tmp_path / "xyz.csv", "--output",
                          tmp_path / "ik.csv")
    assert rc == 0
    flat = " ".join(out.split())
    assert "position only" in flat
    assert "failures │ 1 " in flat and "successes │ 2 " in flat
    assert "success rate │ 66.66 %" in flat  # floored: a failure is never rounded away
    assert "orientation error median / max [mrad] │ — " in flat
    data = np.loadtxt(tmp_path / "ik.csv", delimiter=",", skiprows=1)
    assert (tmp_path / "ik.csv").read_text().startswith(
        "q1,q2,q3,q4,q5,q6,q7,success,position_error,orientation_error,iterations")
    np.testing.assert_array_equal(data[:, 7], [1, 1, 0])
    assert np.isnan(data[:, 9]).all()  # not measured in a position-only solve
    # the printed max is the unreachable target's error: at least 10 m minus the arm's reach (< 1.2 m)
    assert data[2, 8] > 8.5
    max_mm = float(flat.split("position error median / max [mm] │ ")[1].split(" / ")[1].split()[0])
    assert max_mm == pytest.approx(data[2, 8] * 1e3, rel=1e-3)


def test_ik_refuses_non_unit_quaternions(capsys, tmp_path):
    rng = np.random.default_rng(0)
    np.savetxt(tmp_path / "joints.csv", rng.uniform(-2, 2, (5, 7)), delimiter=",")  # joint vectors, 7 columns
    rc, _, err = run_main(capsys, "ik", "--robot", "panda", "--input", tmp_path / "joints.csv")
    one_error(rc, err, "joints.csv", "row 1", "quaternion", "norm")
    quat = rng.normal(size=(4, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    rows = np.concatenate([np.tile([0.4, 0.0, 0.5], (4, 1)), quat], axis=1)
    rows[2, 3:] *= 1 + 2e-3  # row 3: norm off by 2e-3 > 1e-3
    np.save(tmp_path / "poses7.npy", rows)
    rc, _, err = run_main(capsys, "ik", "--robot", "panda", "--input", tmp_path / "poses7.npy")
    one_error(rc, err, "row 3", "1.002")
    rows[2, 3:] *= (1 + 5e-4) / (1 + 2e-3)  # within tolerance: accepted (and normalised)
    np.save(tmp_path / "poses7.npy", rows)
    rc, out, err = run_main(capsys, "ik", "--robot", "panda", "--input", tmp_path / "poses7.npy")
    assert rc == 0, err


def test_old_spellings_are_gone(capsys):
    """The pre-release spellings --seeds, --progress and --report-dir kept no alias (``--out`` is still
    argparse's prefix of ``--output``)."""
    for argv in (["ik", "--robot", "ur5", "--seeds", "4"], ["ik", "--robot", "ur5", "--progress"],
                 ["calibrate", "--robot", "ur5", "--report-dir", "r"]):
        with pytest.raises(SystemExit):
            diffkin.cli.build_parser().parse_args(argv)
    capsys.readouterr()
    assert diffkin.cli.build_parser().parse_args(["demo", "--output", "d"]).output == "d"


@pytest.mark.parametrize("space,names,unit", [("joint", ["q1", "q2"], "[rad/s or m/s]"),
                                              ("cartesian", ["x", "y", "z"], "[m/s]")])
def test_trajectory_plot_has_a_legend_and_units(space, names, unit):
    pytest.importorskip("matplotlib")
    from diffkin.cli.trajectory import _trajectory_figure

    n, t = len(names), np.linspace(0.0, 1.0, 5)
    out = {"t": t, **{k: np.zeros((5, n)) for k in ("position", "velocity", "acceleration")}}
    axs = _trajectory_figure(out, space).axes
    assert [txt.get_text() for txt in axs[0].get_legend().get_texts()] == names
    assert all("[" in ax.get_ylabel() and "]" in ax.get_ylabel() for ax in axs)
    assert unit in axs[1].get_ylabel() and axs[-1].get_xlabel() == "time t [s]"
