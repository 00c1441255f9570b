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

    args = argparse.Namespace(rev="HEAD", targets=24, threads=1, rounds=1, repeats=1)
    rows = compare_revision.run(args)
    assert [r["impl"] for r in rows] == ["this checkout", "HEAD"]
    assert all(r["success"] == 1.0 and r["within_limits"] == 1.0 for r in rows)
    for r in rows:
        assert r["speedup_vs_old"] == pytest.approx(rows[1]["seconds"] / r["seconds"])
        assert r["solves_per_s"] == pytest.approx(24 / r["seconds"])
    listed = subprocess.run(["git", "-C", str(ROOT), "worktree", "list"], capture_output=True,
                            text=True).stdout
    assert "/old " not in listed  # the temporary worktree is gone
