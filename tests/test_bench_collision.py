"""benchmarks/bench_collision.py at tiny sizes: its rows are complete, the peers it finds are timed, and the
pair count is the FR3's (so the benchmark measures what docs/collision.md says it does)."""

from __future__ import annotations

import argparse
import math

from benchmarks import bench_collision


def test_collision_benchmark_rows_at_tiny_sizes():
    rows = bench_collision.run(argparse.Namespace(quick=True, batch=[8], peer_rows=4, device="cpu"))
    ours = [r for r in rows if r["impl"].startswith("diffkin")]
    assert [(r["impl"], r["dtype"], r["batch"]) for r in ours] == [
        ("diffkin", "float32", 8), ("diffkin +grad", "float32", 8), ("diffkin", "float64", 8)]
    for r in rows:
        assert r["benchmark"] == "collision" and r["pairs"] >= 297
        assert math.isfinite(r["seconds"]) and r["seconds"] > 0 and r["us_per_row"] > 0
    peers = {r["impl"] for r in rows} - {r["impl"] for r in ours}
    if any(r["impl"].startswith("pinocchio") for r in rows):  # the ratio is then against it
        assert all(r["speedup_vs_pin_coal"] > 0 for r in rows)
    assert peers <= {"pinocchio+coal (looped)", "mujoco mj_collision (looped, contacts only)"}
