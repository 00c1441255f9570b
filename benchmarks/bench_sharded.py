"""Sharded batch FK / IK throughput: ``diffkin fk|ik`` in 1 process and under torchrun in 2 (gloo, one
thread each), on the same random Panda inputs, end to end (process start, streaming, output written), plus
the merge of the parts (``--merge``, ``merge_s``) against the manifest alone.

Each command is run ``repeats`` times; the table gives the median wall time, the rows per second and the
ratio to one process. ``compute_s`` is the slowest rank's compute time as the command reports it, so the
launch overhead (torchrun's rendezvous, one interpreter per rank) shows as wall - compute.

    python -m benchmarks.bench_sharded [--quick | --large]
"""

from __future__ import annotations

import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(cmd: list[str], cwd: str) -> tuple[float, float, float]:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    out = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{out.stderr[-2000:]}")
    m = (re.search(r"in ([0-9.]+) s \(", out.stdout)
         or re.search(r"solve time \[s\]\s*│\s*([0-9.]+)", out.stdout))
    merge = re.search(r"(?:merged|manifest written) in ([0-9.]+) s", out.stderr)
    return wall, float(m.group(1)) if m else float("nan"), float(merge.group(1)) if merge else 0.0


def run(args) -> list[dict]:
    quick, large = getattr(args, "quick", False), getattr(args, "large", False)
    repeats = 1 if quick or large else 3
    n_fk, n_ik = (200_000, 4_000) if quick else (16_000_000, 400_000) if large else (4_000_000, 40_000)
    rows = []
    cli = [sys.executable, "-m", "diffkin.cli"]
    launch = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2", "-m",
              "diffkin.cli"]
    with tempfile.TemporaryDirectory() as tmp:
        for kind, n, extra in (("fk", n_fk, ["--chunk-size", "262144"]),
                               ("ik", n_ik, ["--chunk-size", "4096", "--num-seeds", "4"])):
            base = [kind, "--robot", "panda", "--random", str(n), "--seed", "0", "--no-progress", *extra]
            cases = [("1 process", cli + base + ["--output", f"{kind}1.npy"]),
                     ("2 processes, manifest", launch + base + ["--output", f"{kind}2.npy"]),
                     ("2 processes, --merge", launch + base + ["--output", f"{kind}3.npy", "--merge"])]
            ref = None
            for label, cmd in cases:
                times = [_run(cmd, tmp) for _ in range(repeats)]
                wall = statistics.median(t[0] for t in times)
                compute = statistics.median(t[1] for t in times)
                merge = statistics.median(t[2] for t in times)
                ref = ref or wall
                rows.append({"benchmark": f"sharded {kind} (panda, float64, 1 thread per process)",
                             "impl": label, "rows": n, "wall_s": round(wall, 2),
                             "compute_s": round(compute, 2), "merge_s": round(merge, 3),
                             "rows_per_s": round(n / wall), "speedup_vs_1_process": round(ref / wall, 2)})
    return rows


def main(argv=None) -> int:
    import argparse

    from benchmarks.common import print_table

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--large", action="store_true",
                   help="16M poses, 400k targets, once (the launch cost amortised)")
    rows = run(p.parse_args(argv))
    for name in dict.fromkeys(r["benchmark"] for r in rows):
        print_table([r for r in rows if r["benchmark"] == name], title=name)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
