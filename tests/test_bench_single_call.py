"""benchmarks/bench_single_call.py at tiny sizes, through benchmarks.run's interface: every part gives its
rows, the solves it times succeed (checked by the benchmark's independent verify), and it is listed in
benchmarks.run.NAMES."""

from __future__ import annotations

import argparse

from benchmarks import bench_single_call, run


def test_single_call_benchmark_rows_at_tiny_sizes():
    assert "single_call" in run.NAMES
    rows = bench_single_call.run(argparse.Namespace(quick=True, targets=3, batch=16, repeats=1, calls=5))
    cases = [r["case"] for r in rows]
    assert any(c.startswith("ik.solve 1 target, lean path") for c in cases)
    assert any(c.startswith("ik.solve 1 target, learnable chain") for c in cases)
    assert "FK, 1 configuration" in cases and "FK + Jacobian, 1 configuration" in cases
    batched = [r for r in rows if "16 targets" in r["case"]]
    assert len(batched) == 4 and "ratio_vs_main" in batched[0] and "ratio_vs_main" in batched[2]
    for r in rows:
        assert r["benchmark"] == "single calls and batched IK" and r["median_us"] > 0
    for r in batched:  # 16 random Panda targets, verified in float64 by the benchmark's own check
        assert r["solves_per_s"] > 0 and r["success"] >= 0.9 and r["flags_honest"]
