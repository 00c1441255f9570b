"""Issue 30 item 16: the first FK call that compiles the fused C kernel says so once (a warning naming the
cache directory), a machine without a compiler is told why the torch kernels serve it, and ``diffkin
doctor`` / ``diffkin --version`` report whether the fused kernel is in use and why not. Run in subprocesses
with a fresh cache directory (``DIFFKIN_CACHE_DIR``): the session's cached library must not hide the first
build. Each subprocess imports torch (with a compile, the slow part), so one process runs doctor and
--version together, the first FK build is shared by the tests that read it, and the subprocesses' builds
get their library from a stand-in compiler that copies the one this session compiled (every other step of
the build is the library's own): 6 processes, no compile of their own."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tests.helpers import stand_in_compiler

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


#: ``diffkin doctor`` then ``diffkin --version`` in one process (through the CLI's ``main``, as
#: ``python -m diffkin.cli`` calls it), each followed by a line ``rc=N``; doctor meets the cache as it is
CLI = ("import sys; from diffkin.cli import main\n"
       "for argv in (['doctor'], ['--version']):\n"
       "    rc = main(argv); sys.stdout.flush(); print(f'rc={rc}', flush=True)")


def _cli_reports(stdout: str) -> list[tuple[int, list[str]]]:
    """(exit status, the ``fused C kernel:`` lines) of doctor and of --version, from ``CLI``'s output."""
    out, lines = [], []
    for ln in stdout.splitlines():
        if ln.startswith("rc="):
            out.append((int(ln.removeprefix("rc=")), lines))
            lines = []
        elif ln.startswith("fused C kernel:"):
            lines.append(ln.removeprefix("fused C kernel: "))
    return out


@pytest.fixture(scope="module")
def stand_in_cc(tmp_path_factory) -> str:
    """:func:`tests.helpers.stand_in_compiler` (the session's library copied where the build asks)."""
    if not HAS_CC:
        pytest.skip("no C compiler: nothing is compiled")
    return stand_in_compiler(tmp_path_factory.mktemp("stand_in_cc"))


@pytest.fixture(scope="module")
def first_build(tmp_path_factory, stand_in_cc):
    """One fresh cache directory and the first FK process that built the kernel into it (shared by the
    two tests that read it)."""
    tmp = tmp_path_factory.mktemp("first_build")
    return tmp, _run(["-c", FK], {"CC": stand_in_cc}, tmp)


def test_first_fk_call_announces_the_build_once(first_build):
    tmp_path, r = first_build
    assert r.returncode == 0, r.stderr
    said = [ln for ln in r.stderr.splitlines() if "NativeBuildWarning" in ln]
    assert len(said) == 1, r.stderr
    assert str(tmp_path / "cache") in said[0] and "python -m diffkin.kernels" in said[0]
    assert list((tmp_path / "cache").glob("diffkin_native-*.so"))  # built where it said


def test_a_cached_build_is_silent_and_reported_in_use(first_build):
    """A second process on the built cache: FK says nothing, and doctor / --version report the kernel in
    use from that cache."""
    tmp_path, _ = first_build
    again = _run(["-c", FK + "\n" + CLI], {}, tmp_path)
    assert again.returncode == 0, again.stderr
    assert "NativeBuildWarning" not in again.stderr, again.stderr
    reports = _cli_reports(again.stdout)
    assert len(reports) == 2, again.stdout
    for rc, line in reports:
        assert rc == 0 and len(line) == 1 and line[0].startswith("in use"), again.stdout
        assert str(tmp_path / "cache") in line[0]


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
] + ([({"CC": "STAND-IN"}, None, "in use")] if HAS_CC else []))
def test_doctor_and_version_report_the_fused_kernel(request, tmp_path, env, path, expect):
    """On a fresh cache: doctor (which tries the build itself, silently), then --version in that process."""
    if path == "EMPTY":
        path = str(tmp_path / "bin")
        os.mkdir(path)
    if env.get("CC") == "STAND-IN":
        env = {"CC": request.getfixturevalue("stand_in_cc")}
    r = _run(["-c", CLI], env, tmp_path, path=path)
    assert r.returncode == 0, r.stderr
    reports = _cli_reports(r.stdout)
    assert len(reports) == 2, r.stdout  # doctor, --version
    for rc, line in reports:
        assert rc == 0 and len(line) == 1, r.stdout
        assert line[0].startswith(expect), r.stdout
    assert "NativeBuildWarning" not in r.stderr  # the report says it; no warning on top
    if expect == "in use":
        assert str(tmp_path / "cache") in reports[0][1][0]


def test_native_outputs_land_on_the_cpu_whatever_the_default_device():
    """The fused kernels write into buffers they make themselves: those are the CPU's even when the caller
    sets another default device (meta here; CUDA for a user of torch.set_default_device), so the C code never
    receives a pointer it cannot write (FK and the TOPP-RA passes of time_optimal)."""
    from diffkin import models
    from diffkin.kernels import native
    from diffkin.trajectories import time_optimal

    if not native.available():
        pytest.skip("the native kernel is not built")
    chain = models.load("panda", dtype=torch.float64)
    q = chain.random_configuration((3,), generator=torch.Generator().manual_seed(0))
    path = torch.stack([chain.random_configuration((4,), generator=torch.Generator().manual_seed(s))
                        for s in range(2)])  # (2, 4, 7)
    want_T = chain.forward_kinematics(q)
    want_d = time_optimal(path, 2.0, 10.0).duration
    with torch.device("meta"):
        T = chain.forward_kinematics(q)
        d = time_optimal(path, 2.0, 10.0).duration
    assert T.device.type == "cpu" and d.device.type == "cpu"
    assert torch.equal(T, want_T) and torch.equal(d, want_d)
