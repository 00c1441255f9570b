"""benchmarks/cuda_smoke.py, the script run on a GPU beside ``pytest -m cuda``, runs on the CPU (a few cases:
every case runs under the stand-in in tests/test_device_standin_motion.py) and reports a failing case as a
FAIL line and exit code 1, a missing optional package as a skip."""

from __future__ import annotations

import torch

from benchmarks import cuda_smoke as smoke

F64 = torch.float64


def test_runs_on_the_cpu(capsys):
    assert smoke.main(["--device", "cpu", "--only", "time_optimal spline jerk", "retarget.metrics"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 5 and lines[-1] == "ok: 0 case(s) failed on cpu", lines
    for line, name in zip(lines, ["time_optimal spline jerk [float64]", "time_optimal spline jerk [float32]",
                                  "retarget.metrics [float64]", "retarget.metrics [float32]"]):
        assert line.startswith("ok    ") and name in line and "max|diff| 0.00e+00" in line, line


def test_failures_are_lines_and_the_exit_code(monkeypatch, capsys):
    made = []  # run_case makes the CPU reference first, then the device's call

    def differs(device, dtype):  # the device's call 1e-6 off the reference
        made.append(device)
        x = torch.ones(3, dtype=dtype) + (1e-6 if len(made) % 2 == 0 else 0.0)
        return lambda: (x,)

    def raises(device, dtype):
        return lambda: torch.ones(2, dtype=dtype) @ torch.ones(3, dtype=dtype)

    def wrong_dtype(device, dtype):
        made.append(device)
        return lambda: torch.ones(2, dtype=dtype if len(made) % 2 else torch.float32)

    monkeypatch.setattr(smoke, "CASES", [
        smoke.Case("within", differs, {F64: 1e-5}), smoke.Case("beyond", differs, {F64: 1e-7}),
        smoke.Case("raises", raises, {F64: 1e-9}), smoke.Case("dtype", wrong_dtype, {F64: 1e-9}),
        smoke.Case("absent", differs, {F64: 1e-9}, needs=("no_such_package_here",))])
    assert smoke.main(["--device", "cpu"]) == 1
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines] == ["ok", "FAIL", "FAIL", "FAIL", "skip", "FAIL:"], lines
    assert "1e-06 above the tolerance 1e-07" in lines[1] and "RuntimeError" in lines[2]
    assert "AssertionError" in lines[3] and "no no_such_package_here" in lines[4]
    assert lines[-1] == "FAIL: 3 case(s) failed on cpu"
