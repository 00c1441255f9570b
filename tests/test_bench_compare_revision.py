"""benchmarks/compare_revision.py at a tiny size, against this checkout's own HEAD (so that it runs in any
clone with git): both rows, honest successes, the ratio's definition (its value is timing: not asserted)."""

from __future__ import annotations

import argparse
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(),
                    reason="needs a git checkout")
def test_compare_revision_runs_small():
    if subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True).returncode:
        pytest.skip("no commit to compare against")
    from benchmarks import compare_revision

    args = argparse.Namespace(rev="HEAD", targets=24, threads=1, rounds=1, repeats=1, all=True, singles=3)
    rows = compare_revision.run(args)
    solve, extra = rows[:2], rows[2:]
    assert [r["impl"] for r in solve] == ["this checkout", "HEAD"]
    assert all(r["success"] == 1.0 and r["within_limits"] == 1.0 for r in solve)
    # --all: FK, Jacobian and the one-target solve, each for both trees, ratio against the old tree's time
    assert [(r["benchmark"], r["impl"]) for r in extra] == [
        (label, impl) for label, _, _ in compare_revision.EXTRA.values()
        for impl in ("this checkout", "HEAD")]
    for mine, old in zip(extra[::2], extra[1::2]):
        unit = "us" if "us" in mine else "ms"
        assert mine[unit] > 0 and old["speedup_vs_old"] == 1.0
        assert mine["speedup_vs_old"] == pytest.approx(old[unit] / mine[unit])
    for r in solve:
        assert r["speedup_vs_old"] == pytest.approx(rows[1]["seconds"] / r["seconds"])
        assert r["solves_per_s"] == pytest.approx(24 / r["seconds"])
    listed = subprocess.run(["git", "-C", str(ROOT), "worktree", "list"], capture_output=True,
                            text=True).stdout
    assert "/old " not in listed  # the temporary worktree is gone
