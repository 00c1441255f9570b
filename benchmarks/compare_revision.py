"""Batched ``ik.solve`` of this checkout against an older revision of diffkin, in one run.

    python -m benchmarks.compare_revision [--rev 048e70a] [--targets 10000] [--threads 2] [--rounds 3]

The revision is checked out into a temporary ``git worktree`` (removed afterwards) and both trees run the
same timing script in fresh processes, alternately, ``--rounds`` times (this machine's speed drifts; the
alternation puts both under the same drift): random Panda targets within the limits (float64, seed 0), the
solver's defaults (0.1 mm / 1 mrad), ``generator`` seeded 1, one warm-up call, then the median of
``--repeats`` timed calls per process; success is re-checked by :func:`benchmarks.bench_ik.verify` (an
independent float64 FK and the limits). The default revision, ``048e70a``, is the code as it stood when
issue 28 was filed ("today" of its targets).

With ``--all`` the script also times, in the same processes: batched forward kinematics and the geometric
Jacobian of ``--targets`` configurations (float64), and one-target ``ik.solve`` (the median of ``--singles``
calls on one pose each, ``seed=`` given). Issue 40 asks that its redesign keep these figures within noise of
revision ``2dc4796``: ``python -m benchmarks.compare_revision --rev 2dc4796 --all``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.common import print_table

__all__ = ["run", "main", "SCRIPT"]

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = r"""
import json, statistics, sys, time, torch
sys.path.insert(0, sys.argv[1])
from diffkin import models, ik
torch.set_num_threads(int(sys.argv[3]))
n, repeats = int(sys.argv[2]), int(sys.argv[4])
chain = models.load("panda", dtype=torch.float64)
q = chain.random_configuration((n,), generator=torch.Generator().manual_seed(0))
with torch.no_grad():
    T = chain.forward_kinematics(q)
def once():
    t0 = time.perf_counter()
    r = ik.solve(chain, T, generator=torch.Generator().manual_seed(1))
    return time.perf_counter() - t0, r
once()
times = []
for _ in range(repeats):
    t, r = once()
    times.append(t)
torch.save({"q": r.q.detach(), "T": T}, sys.argv[5])
row = {"seconds": statistics.median(times)}
if int(sys.argv[6]):
    def med(f, k):
        f()
        ts = []
        for _ in range(k):
            t0 = time.perf_counter()
            f()
            ts.append(time.perf_counter() - t0)
        return statistics.median(ts)
    with torch.no_grad():
        row["fk_s"] = med(lambda: chain.forward_kinematics(q), repeats * 5)
        row["jacobian_s"] = med(lambda: chain.geometric_jacobian(q), repeats * 5)
    singles = int(sys.argv[7])
    one = []
    for i in range(singles + 10):
        Ti = T[i % n].clone()
        t0 = time.perf_counter()
        ik.solve(chain, Ti, seed=i)
        one.append(time.perf_counter() - t0)
    row["one_target_s"] = statistics.median(one[10:])
print(json.dumps(row))
"""


def _one(tree: Path, args, out: Path) -> dict:
    proc = subprocess.run([sys.executable, "-c", SCRIPT, str(tree), str(args.targets), str(args.threads),
                           str(args.repeats), str(out), str(int(args.all)), str(args.singles)],
                          capture_output=True, text=True, cwd=tree,
                          timeout=1800, check=True)
    row = json.loads(proc.stdout.strip().splitlines()[-1])
    import torch

    from benchmarks.bench_ik import verify

    saved = torch.load(out)
    row.update(verify(saved["q"], saved["T"]))
    return row


def run(args) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        old = Path(tmp) / "old"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(old), args.rev],
                       check=True)
        try:
            times = {"this checkout": [], args.rev: []}
            extra = {"this checkout": {k: [] for k in EXTRA}, args.rev: {k: [] for k in EXTRA}}
            last = {}
            for _ in range(args.rounds):
                for name, tree in ((args.rev, old), ("this checkout", ROOT)):
                    r = _one(tree, args, Path(tmp) / "out.pt")
                    times[name].append(r["seconds"])
                    for k in EXTRA:
                        if k in r:
                            extra[name][k].append(r[k])
                    last[name] = r
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old)], check=False)
    base = statistics.median(times[args.rev])
    for name, ts in times.items():
        t = statistics.median(ts)
        rows.append({"benchmark": "ik.solve vs an older revision", "impl": name, "targets": args.targets,
                     "threads": args.threads, "seconds": t, "solves_per_s": args.targets / t,
                     "success": last[name]["success"], "within_limits": last[name]["success_within_limits"],
                     "speedup_vs_old": base / t})
    for key, (label, unit, scale) in EXTRA.items():
        if not extra[args.rev][key]:
            continue
        old_t = statistics.median(extra[args.rev][key])
        for name in times:
            t = statistics.median(extra[name][key])
            n = 1 if key == "one_target_s" else args.targets
            rows.append({"benchmark": label, "impl": name, "targets": n,
                         "threads": args.threads, unit: t * scale, "speedup_vs_old": old_t / t})
    return rows


#: the figures of ``--all``: key in the script's output -> (table label, column, scale from seconds)
EXTRA = {"fk_s": ("forward_kinematics", "ms", 1e3), "jacobian_s": ("jacobian", "ms", 1e3),
         "one_target_s": ("one-target ik.solve", "us", 1e6)}


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rev", default="048e70a")
    p.add_argument("--targets", type=int, default=10_000)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--all", action="store_true", help="also FK, Jacobian and one-target solve (issue 40)")
    p.add_argument("--singles", type=int, default=300, help="one-target solves timed per process with --all")
    return p.parse_args(argv)


def main(argv=None) -> int:
    print_table(run(parse_args(argv)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
