"""Issue 30 item 16: the first FK call that compiles the fused C kernel says so once (a warning naming the
cache directory), a machine without a compiler is told why the torch kernels serve it, and ``diffkin
doctor`` / ``diffkin --version`` report whether the fused kernel is in use and why not. Run in subprocesses
with a fresh cache directory (``DIFFKIN_CACHE_DIR``): the session's cached library must not hide the first
build."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FK = ("import torch; from diffkin import models; c = models.load('ur5', dtype=torch.float64); "
      "c.forward_kinematics(torch.zeros(100, 6, dtype=torch.float64)); "
      "c.forward_kinematics(torch.zeros(100, 6, dtype=torch.float64))")
HAS_CC = any(shutil.which(c) for c in (os.environ.get("CC", "cc"), "gcc", "clang"))


def _run(args, env_extra, tmp_path, path=None):
    env = {k: v for k, v in os.environ.items() if k not in ("DIFFKIN_NATIVE", "CC")}
    env.update(DIFFKIN_CACHE_DIR=str(tmp_path / "cache"), OMP_NUM_THREADS="1", **env_extra)
    if path is not None:
        env["PATH"] = path
    return subprocess.run([sys.executable, "-W", "default", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True)


@pytest.mark.skipif(not HAS_CC, reason="no C compiler: nothing is compiled")
def test_first_fk_call_announces_the_build_once(tmp_path):
    r = _run(["-c", FK], {}, tmp_path)
    assert r.returncode == 0, r.stderr
    said = [ln for ln in r.stderr.splitlines() if "NativeBuildWarning" in ln]
    assert len(said) == 1, r.stderr
    assert str(tmp_path / "cache") in said[0] and "python -m diffkin.kernels" in said[0]
    assert list((tmp_path / "cache").glob("diffkin_native-*.so"))  # built where it said
    again = _run(["-c", FK], {}, tmp_path)  # cached: silent
    assert "NativeBuildWarning" not in again.stderr, again.stderr


def test_no_compiler_is_said_once_and_fk_still_works(tmp_path):
    empty = tmp_path / "bin"
    empty.mkdir()
    r = _run(["-c", FK + "; print('ok')"], {"CC": "no-such-cc"}, tmp_path, path=str(empty))
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr
    said = [ln for ln in r.stderr.splitlines() if "NativeBuildWarning" in ln]
    assert len(said) == 1 and "no C compiler" in said[0] and "torch kernels" in said[0], r.stderr


@pytest.mark.parametrize(("env", "path", "expect"), [
    ({"DIFFKIN_NATIVE": "0"}, None, "not in use: disabled by DIFFKIN_NATIVE=0"),
    ({"CC": "no-such-cc"}, "EMPTY", "not in use: no C compiler found"),
] + ([({}, None, "in use")] if HAS_CC else []))
def test_doctor_and_version_report_the_fused_kernel(tmp_path, env, path, expect):
    if path == "EMPTY":
        path = str(tmp_path / "bin")
        os.mkdir(path)
    for args in (["-m", "diffkin.cli", "doctor"], ["-m", "diffkin.cli", "--version"]):
        r = _run(args, env, tmp_path, path=path)
        assert r.returncode == 0, r.stderr
        line = [ln for ln in r.stdout.splitlines() if ln.startswith("fused C kernel:")]
        assert len(line) == 1 and line[0].removeprefix("fused C kernel: ").startswith(expect), r.stdout
        assert "NativeBuildWarning" not in r.stderr  # the report says it; no warning on top
    if expect == "in use":
        assert str(tmp_path / "cache") in line[0]
